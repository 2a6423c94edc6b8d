"""Scalar embeddings for the expert's conditioning tokens (time t, time r, control frequency).

A sinusoidal embedder is only informative over the range its periods cover. DDPM-style
embedders (periods 1…10 000) are tuned for integer steps 0…999 and give near-constant
features for t ∈ [0, 1]; times here therefore use pi0's periods 4e-3…4.0, while the
control frequency (Hz, roughly 1…1000) keeps the DDPM-style range.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor, nn

from ..normalize import Float32Buffers

TIME_PERIODS = (4e-3, 4.0)
FREQ_PERIODS = (1.0, 1e4)


def angular_frequencies(dim: int, min_period: float, max_period: float, dtype=torch.float32,
                        device=None) -> Tensor:
    """[dim/2]: 2π / period at `dim/2` geometrically spaced periods from min_period to max_period."""
    if dim % 2:
        raise ValueError(f"dim: expected an even width, got {dim}")
    fraction = torch.linspace(0.0, 1.0, dim // 2, device=device, dtype=dtype)
    period = min_period * (max_period / min_period) ** fraction                # [dim/2]
    return 2 * math.pi / period


def sinusoidal_features(x: Tensor, dim: int, min_period: float, max_period: float,
                        freqs: Optional[Tensor] = None) -> Tensor:
    """[B] -> [B, dim] (at least float32): sin/cos at `dim/2` geometrically spaced periods.
    `freqs`: `angular_frequencies` of these periods in the features' dtype, computed once by the caller."""
    dtype = torch.promote_types(x.dtype, torch.float32)
    if freqs is None or freqs.dtype != dtype:
        freqs = angular_frequencies(dim, min_period, max_period, dtype, x.device)
    angle = x.to(dtype)[:, None] * freqs[None, :]                              # [B, dim/2]
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=-1)


class ScalarEmbedding(Float32Buffers):
    """A per-sample scalar -> one hidden-size token: sinusoidal features, then an MLP."""

    float32_buffers = ("freqs",)

    def __init__(self, hidden_size: int, periods: tuple[float, float]) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.min_period, self.max_period = periods
        self.mlp = nn.Sequential(nn.Linear(hidden_size, hidden_size), nn.SiLU(),
                                 nn.Linear(hidden_size, hidden_size))
        # The features' frequencies, a function of the periods: built once instead of on every call.
        self.register_buffer("freqs", angular_frequencies(hidden_size, *periods), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        """[B] -> [B, hidden_size] in the MLP's dtype."""
        return self.project(self.features(x))

    def features(self, x: Tensor) -> Tensor:
        """[N] -> the sinusoidal features [N, hidden_size] the MLP reads (shared by embeddings of equal periods)."""
        return sinusoidal_features(x, self.hidden_size, self.min_period, self.max_period, self.freqs)

    def project(self, feats: Tensor) -> Tensor:
        """Features [N, hidden_size] -> tokens [N, hidden_size] in the MLP's dtype."""
        return self.mlp(feats.to(self.mlp[0].weight.dtype))
