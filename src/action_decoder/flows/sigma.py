"""Noise schedules σ(t) for the SDE samplers: callables `σ(t [B]) -> [B]`.

All are `nn.Module`s so a policy can own them; only `LearnableSigma` has a parameter.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor, nn

from ..config import DecoderConfig


class ChurnSigma(nn.Module):
    """GO-1's churn schedule `s·√(1 − t/(t+ε))` (= `s·√(ε/(t+ε))`).

    Beware: with s = 0.7, ε = 1e-4 it is 0.7 at t = 0, 0.022 at t = 0.1, 0.007 at t = 1: the chain
    explores in its first step only. Kept because configs name it; `ExploringSigma`
    keeps exploring over the whole interval.
    """

    def __init__(self, s_churn: float = 0.7, eps: float = 1e-4):
        super().__init__()
        self.s_churn, self.eps = float(s_churn), float(eps)

    def forward(self, t: Tensor) -> Tensor:
        return self.s_churn * torch.sqrt(self.eps / (t + self.eps))


class FixedSigma(nn.Module):
    """Constant σ(t) = scale."""

    def __init__(self, scale: float):
        super().__init__()
        self.scale = float(scale)

    def forward(self, t: Tensor) -> Tensor:
        return torch.full_like(t, self.scale)


class ExploringSigma(nn.Module):
    """Flow-GRPO's schedule in our time direction: `a·√((1 − t) / max(t, t_min))`.

    Explores over the whole interval and vanishes at t = 1 (data). `t_min` caps the
    divergence at the noise end. `t_min=None` (the default) clamps, like Flow-GRPO, at the
    first interior point of the grid: the smallest positive time σ is evaluated on, which
    for the samplers (they evaluate σ once per call on the K step times) is grid[1], e.g.
    1/K on the uniform grid; σ then follows any step count. With no positive time (a single
    step, times [0]) the clamp is 1, the grid's only other point: σ(0) = a. A number fixes
    the clamp whatever the grid.
    """

    def __init__(self, scale: float = 0.7, t_min: Optional[float] = None):
        super().__init__()
        if t_min is not None and not (isinstance(t_min, (int, float)) and 0 < t_min <= 1):
            raise ValueError(f"t_min: expected None (the first interior grid point) or a time in (0, 1], "
                             f"got {t_min!r}")
        self.scale, self.t_min = float(scale), None if t_min is None else float(t_min)

    def forward(self, t: Tensor) -> Tensor:
        if self.t_min is None:
            floor = torch.where(t > 0, t, torch.ones_like(t)).amin()       # [] no host sync
        else:
            floor = self.t_min
        return self.scale * torch.sqrt((1 - t).clamp_min(0) / t.clamp_min(floor))


class LearnableSigma(nn.Module):
    """`base(t)·m` with a learnable multiplier `m = init·exp(θ) > 0`, θ = 0 at start.

    The initial multiplier is exactly `init` (GO-1's `softplus(init)` started 0.1 at 0.744).
    """

    def __init__(self, base: nn.Module, init: float = 1.0):
        super().__init__()
        if not (init > 0 and math.isfinite(init)):
            raise ValueError(f"init: expected a positive finite multiplier, got {init!r}")
        self.base, self.init = base, float(init)
        self.log_scale = nn.Parameter(torch.zeros(()))

    @property
    def multiplier(self) -> Tensor:
        return self.init * torch.exp(self.log_scale)

    def forward(self, t: Tensor) -> Tensor:
        # init stays a Python float so that the start is exact in any dtype.
        return self.base(t) * (self.init * torch.exp(self.log_scale.to(t.dtype)))


def make_sigma(config: DecoderConfig) -> nn.Module:
    """The schedule `config.flow_sde_mode` names, learnable when `flow_sde_learn_sigma`."""
    s = config.flow_sde_s_churn
    if config.flow_sde_mode == "churn":
        base = ChurnSigma(s, config.flow_sde_eps)
    elif config.flow_sde_mode == "fixed":
        base = FixedSigma(s)
    else:
        base = ExploringSigma(s, config.flow_sde_t_min)
    return LearnableSigma(base, config.flow_sde_sigma_init) if config.flow_sde_learn_sigma else base
