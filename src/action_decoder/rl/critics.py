"""Critics on the environment state: a value head for PPO, a twin Q for SAC.

They see the normalised state plus the episode's progress (time-limit truncation makes the
value depend on the time left); the policy network is left untouched.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


def _mlp(inp: int, hidden: int, out: int, norm_every_layer: bool = False) -> nn.Sequential:
    second = [nn.LayerNorm(hidden)] if norm_every_layer else []
    return nn.Sequential(nn.Linear(inp, hidden), nn.LayerNorm(hidden), nn.SiLU(),
                         nn.Linear(hidden, hidden), *second, nn.SiLU(), nn.Linear(hidden, out))


class ValueNet(nn.Module):
    """V(state, progress) -> [B]."""

    def __init__(self, state_dim: int, hidden: int = 256):
        super().__init__()
        self.net = _mlp(state_dim + 1, hidden, 1)

    def forward(self, state: Tensor, progress: Tensor) -> Tensor:      # [B, S], [B] -> [B]
        return self.net(torch.cat([state, progress[:, None]], -1)).squeeze(-1)


class TwinQ(nn.Module):
    """Two independent Q(state, progress, executed actions [B, n, D] or noise [B, H, D]) -> ([B], [B]).
    `norm_every_layer`: LayerNorm after each hidden layer (not only the first), which keeps Q from
    drifting past the returns under many updates per sample (DSRL)."""

    def __init__(self, state_dim: int, action_numel: int, hidden: int = 256, norm_every_layer: bool = False):
        super().__init__()
        self.q1 = _mlp(state_dim + 1 + action_numel, hidden, 1, norm_every_layer)
        self.q2 = _mlp(state_dim + 1 + action_numel, hidden, 1, norm_every_layer)

    def forward(self, state: Tensor, progress: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        x = torch.cat([state, progress[:, None], actions.flatten(1)], -1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)
