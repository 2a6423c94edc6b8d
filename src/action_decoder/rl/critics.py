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


class QEnsemble(nn.Module):
    """`n` independent Q(state, progress, noise or executed actions) -> n × [B], LayerNorm after every
    hidden layer. With n = 2 it is a twin Q; larger ensembles serve REDQ-style targets (`subset_min`)."""

    def __init__(self, state_dim: int, action_numel: int, n: int = 2, hidden: int = 256):
        super().__init__()
        self.members = nn.ModuleList(_mlp(state_dim + 1 + action_numel, hidden, 1, True) for _ in range(n))

    def forward(self, state: Tensor, progress: Tensor, actions: Tensor) -> tuple[Tensor, ...]:
        x = torch.cat([state, progress[:, None], actions.flatten(1)], -1)
        return tuple(m(x).squeeze(-1) for m in self.members)


def subset_min(qs: tuple[Tensor, ...], k: int, generator: torch.Generator) -> Tensor:
    """The minimum over `k` members of an ensemble's values, drawn without replacement [B]
    (k = len(qs): the minimum over all; REDQ's pessimistic target with k = 2 of a larger ensemble)."""
    if k >= len(qs):
        return torch.stack(qs).min(0).values
    pick = torch.randperm(len(qs), generator=generator)[:k]
    return torch.stack([qs[int(i)] for i in pick]).min(0).values


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
