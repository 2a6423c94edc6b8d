"""Noise schedules σ(t) for the SDE samplers: callables `σ(t [B]) -> [B]`.

All are `nn.Module`s so a policy can own them; only `LearnableSigma` has a parameter.
"""

from __future__ import annotations

import math

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
    divergence at the noise end (Flow-GRPO clamps at the first interior grid point; 0.1 is
    that point for the default 10 steps).
    """

    def __init__(self, scale: float = 0.7, t_min: float = 0.1):
        super().__init__()
        self.scale, self.t_min = float(scale), float(t_min)

    def forward(self, t: Tensor) -> Tensor:
        return self.scale * torch.sqrt((1 - t).clamp_min(0) / t.clamp_min(self.t_min))


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
        base = ExploringSigma(s)
    return LearnableSigma(base, config.flow_sde_sigma_init) if config.flow_sde_learn_sigma else base
