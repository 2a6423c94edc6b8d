"""State and action normalisation from data statistics, stored with the weights as buffers."""

from __future__ import annotations

from typing import Mapping, Optional

import torch
from torch import Tensor, nn

STAT_NAMES = ("mean", "std", "min", "max")
# Constant dimensions (Meta-World has several) must not blow up when divided by their spread:
# a spread below a feature's `constant_below` is replaced by this floor.
SPREAD_FLOOR = 1e-2
# An action dimension is constant below this spread; any other keeps its own (an end-effector
# delta of std 0.003 m must reach the network at unit scale). States take the floor below SPREAD_FLOOR.
ACTION_CONSTANT_BELOW = 1e-6


class Float32Buffers(nn.Module):
    """A module whose buffers named in `float32_buffers` (data statistics, tables derived from the config)
    follow the device it is moved to but stay float32 whatever dtype it is cast to."""

    float32_buffers: tuple[str, ...] = ()

    def _apply(self, fn, recurse=True):
        kept = {name: self._buffers.pop(name) for name in self.float32_buffers}
        super()._apply(fn, recurse)
        for name, buf in kept.items():
            self._buffers[name] = buf.to(device=fn(buf).device)
        return self


class Normalizer(Float32Buffers):
    """Maps one feature to and from the network's units.

    mean_std: (x − mean)/std;  min_max: to [−1, 1] by 2·(x − min)/(max − min) − 1;
    identity: unchanged. Buffers hold every statistic so any mode can be reloaded. Without
    statistics the range [min, max] is (−inf, inf): unknown, so nothing is clipped to it
    (`DecoderConfig.clip_actions`), and min_max leaves such a dimension as it is.

    A spread (std, or half the range) below `constant_below` marks a constant dimension and is
    replaced by `SPREAD_FLOOR`. The statistics stay float32 whatever dtype the policy is moved to
    (`.half()`, `.to(torch.bfloat16)`): rounding a mean of 250.3 to bf16 would shift every input.
    """

    float32_buffers = STAT_NAMES        # follow the policy's device, never its dtype

    def __init__(self, name: str, dim: int, mode: str, constant_below: float = SPREAD_FLOOR):
        super().__init__()
        self.name, self.dim, self.mode, self.constant_below = name, dim, mode, float(constant_below)
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))
        self.register_buffer("min", torch.full((dim,), -torch.inf))
        self.register_buffer("max", torch.full((dim,), torch.inf))

    def set_stats(self, stats: Mapping[str, object]) -> None:
        values = {}
        for key in STAT_NAMES:
            if key not in stats:
                raise ValueError(f"stats[{self.name!r}]: expected keys {list(STAT_NAMES)}, "
                                 f"missing {key!r}")
            value = torch.as_tensor(stats[key], dtype=torch.float32).flatten()
            if value.shape != (self.dim,):
                raise ValueError(f"stats[{self.name!r}][{key!r}]: expected {self.dim} values, "
                                 f"got shape {tuple(value.shape)}")
            if not torch.isfinite(value).all():
                raise ValueError(f"stats[{self.name!r}][{key!r}]: contains NaN or Inf")
            values[key] = value
        if bool((values["std"] < 0).any()):
            raise ValueError(f"stats[{self.name!r}]['std']: expected non-negative values, got {values['std'].tolist()}")
        if bool((values["min"] > values["max"]).any()):
            raise ValueError(f"stats[{self.name!r}]: expected min <= max in every dimension, got min "
                             f"{values['min'].tolist()} and max {values['max'].tolist()}")
        for key, value in values.items():
            getattr(self, key).copy_(value)

    def _scale_shift(self):
        if self.mode == "mean_std":
            std = self.std
            return torch.where(std < self.constant_below, torch.full_like(std, SPREAD_FLOOR), std), self.mean
        if self.mode == "min_max":
            known = torch.isfinite(self.min) & torch.isfinite(self.max)        # [D] False: no statistics
            low, high = torch.where(known, self.min, -1.0), torch.where(known, self.max, 1.0)
            half = (high - low) / 2
            half = torch.where(half < self.constant_below / 2, torch.full_like(half, SPREAD_FLOOR / 2), half)
            return half, (high + low) / 2
        return None, None

    def clip(self, x: Tensor) -> Tensor:
        """`x` [..., D] clamped to the statistics' [min, max] per dimension (no statistics: unchanged)."""
        return torch.minimum(torch.maximum(x, self.min.to(x.dtype)), self.max.to(x.dtype))

    def normalize(self, x: Tensor) -> Tensor:
        scale, shift = self._scale_shift()
        return x if scale is None else (x - shift.to(x.dtype)) / scale.to(x.dtype)

    def unnormalize(self, x: Tensor) -> Tensor:
        scale, shift = self._scale_shift()
        return x if scale is None else x * scale.to(x.dtype) + shift.to(x.dtype)


def make_normalizers(state_dim: int, action_dim: int, mode: str,
                     stats: Optional[Mapping[str, Mapping[str, object]]] = None,
                     action_constant_below: float = SPREAD_FLOOR) -> nn.ModuleDict:
    """`{"state": ..., "actions": ...}`; `stats` uses those keys (or LeRobot's
    "observation.state" / "action"). State spreads below `SPREAD_FLOOR` take the floor; action
    spreads only below `action_constant_below` (`DecoderConfig.action_constant_below`)."""
    norms = nn.ModuleDict({"state": Normalizer("state", state_dim, mode),
                           "actions": Normalizer("actions", action_dim, mode, action_constant_below)})
    if stats is not None:
        aliases = {"state": ("state", "observation.state"), "actions": ("actions", "action")}
        for key, names in aliases.items():
            found = next((stats[n] for n in names if n in stats), None)
            if found is None:
                raise ValueError(f"stats: expected an entry {names[0]!r} (or {names[1]!r}), "
                                 f"got keys {sorted(stats)}")
            norms[key].set_stats(found)
    return norms
