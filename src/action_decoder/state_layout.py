"""What a state vector's entries are, and what the policy and training derive from that.

A "flat" state is opaque: the policy normalises it and nothing more. Meta-World's 39-d
state is a known layout of 3-d positions (hand, up to two objects, the same three one
frame earlier, the goal), and two things follow from it that few demonstrations cannot
teach a network on their own:

- **relative positions** (object − hand, goal − hand, goal − object): the policy appends
  them to the normalised state, because the expert moves the hand by deltas and reaching
  is a function of these differences wherever the layout puts the objects;
- **shift augmentation**: moving every position by one common horizontal offset gives
  another valid scene with the same delta actions, so training sees layouts between and
  around the demonstrated ones.

A camera policy on Meta-World ("metaworld_proprio") reads the robot's proprioception only, the
hand position and the gripper opening (the first `PROPRIO_DIM` entries): where the objects and
the goal are must come from its cameras. The full 39-d state still arrives (and is normalised
as a whole), so the same environment loop serves both.

An absent object is zeros in Meta-World (a real position never is: the table is at y > 0.3),
so it is neither shifted nor given relative features.
"""

from __future__ import annotations

import torch
from torch import Tensor

STATE_LAYOUTS = ("flat", "metaworld", "metaworld_proprio")
METAWORLD_LAYOUTS = ("metaworld", "metaworld_proprio")
METAWORLD_STATE_DIM = 39
PROPRIO_DIM = 4      # hand x, y, z and the gripper opening
# Start of each 3-d position in Meta-World's observation (v3): current frame, previous frame, goal.
HAND, OBJ1, OBJ2, GOAL = 0, 4, 11, 36
PREV_HAND, PREV_OBJ1, PREV_OBJ2 = 18, 22, 29
POSITIONS = (HAND, OBJ1, OBJ2, PREV_HAND, PREV_OBJ1, PREV_OBJ2, GOAL)
# (to, from) pairs of the relative features.
RELATIVE = ((OBJ1, HAND), (OBJ2, HAND), (GOAL, HAND), (GOAL, OBJ1), (GOAL, OBJ2))
RELATIVE_SCALE = 0.1
"""Metres per unit of the relative features: the workspace spans a few decimetres."""


def feature_dim(layout: str) -> int:
    """How many entries the layout appends to the normalised state."""
    return 3 * len(RELATIVE) if layout == "metaworld" else 0


def input_dim(layout: str, state_dim: int) -> int:
    """Width of what the network reads of a `state_dim` state under `layout`."""
    return PROPRIO_DIM if layout == "metaworld_proprio" else state_dim + feature_dim(layout)


def network_state(layout: str, normalized: Tensor, raw: Tensor) -> Tensor:
    """What the network reads [..., input_dim]: the normalised state [..., S], with the relative positions
    of the raw [B, 39] state appended ("metaworld"), or only its proprioception ("metaworld_proprio")."""
    if layout == "metaworld":
        return torch.cat([normalized, relative_positions(raw)], dim=-1)
    if layout == "metaworld_proprio":
        return normalized[..., :PROPRIO_DIM]
    return normalized


def _pos(state: Tensor, start: int) -> Tensor:
    return state[..., start:start + 3]


def _present(pos: Tensor) -> Tensor:
    return (pos != 0).any(-1, keepdim=True)


def relative_positions(state: Tensor) -> Tensor:
    """[B, 39] Meta-World states → [B, 15] differences in units of RELATIVE_SCALE, zero where
    either position is absent."""
    parts = []
    for to, frm in RELATIVE:
        a, b = _pos(state, to), _pos(state, frm)
        parts.append(torch.where(_present(a) & _present(b), (a - b) / RELATIVE_SCALE, torch.zeros_like(a)))
    return torch.cat(parts, dim=-1)                                          # [B, 15]


def shift_positions(state: Tensor, offset: Tensor) -> Tensor:
    """Add `offset` [B, 2] (metres, x and y) to every present position of [B, 39] states."""
    if offset.shape != (state.shape[0], 2):
        raise ValueError(f"offset: expected shape [{state.shape[0]}, 2], got {list(offset.shape)}")
    out = state.clone()
    for start in POSITIONS:
        xy = out[:, start:start + 2]
        out[:, start:start + 2] = xy + offset * _present(_pos(state, start))
    return out
