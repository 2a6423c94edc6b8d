"""Closed-form targets whose velocity, score, average velocity and DDPM denoiser are known.

They stand in for a trained network in tests and benchmarks: a sampler or loss that is
right reproduces them exactly (up to discretisation). Path z_t = (1 − t)·e + t·a.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import Tensor


def _b(t: Tensor, like: Tensor) -> Tensor:
    return t.reshape(-1, *([1] * (like.dim() - 1))).to(like.dtype)


@dataclass
class GaussianMixture:
    """a ~ Σ_k w_k N(μ_k, s_k² I) over chunks [H, D]; means [K, H, D], stds [K], weights [K]."""

    means: Tensor
    stds: Tensor
    weights: Tensor

    @classmethod
    def make(cls, means: Sequence, stds: Sequence[float], weights: Optional[Sequence[float]] = None,
             dtype=torch.float64) -> "GaussianMixture":
        m = torch.as_tensor(means, dtype=dtype)
        w = torch.ones(len(m), dtype=dtype) if weights is None else torch.as_tensor(weights, dtype=dtype)
        return cls(m, torch.as_tensor(stds, dtype=dtype), w / w.sum())

    def sample(self, n: int, generator: Optional[torch.Generator] = None) -> Tensor:
        k = torch.multinomial(self.weights, n, replacement=True, generator=generator)
        e = torch.randn((n, *self.means.shape[1:]), generator=generator, dtype=self.means.dtype)
        return self.means[k] + self.stds[k].reshape(-1, 1, 1) * e

    def marginal_sample(self, n: int, t: float, generator: Optional[torch.Generator] = None) -> Tensor:
        """Exact draws of z_t = (1 − t)·e + t·a."""
        a = self.sample(n, generator)
        e = torch.randn(a.shape, generator=generator, dtype=a.dtype)
        return (1 - t) * e + t * a

    def _components(self, z: Tensor, scale: Tensor, var: Tensor):
        """Responsibilities γ [B, K] for z ~ Σ w_k N(scale·μ_k, var_k I); also z − scale·μ_k."""
        d = z[:, None].double() - scale.reshape(-1, 1, 1, 1) * self.means[None]   # [B, K, H, D]
        dim = z[0].numel()
        logp = (-0.5 * d.square().sum((-2, -1)) / var - 0.5 * dim * var.log() + self.weights.log())
        return torch.softmax(logp, -1), d                                         # [B, K]

    def velocity(self, z: Tensor, t: Tensor) -> Tensor:
        tt = t.double().reshape(-1, 1)                                            # [B, 1]
        s2 = self.stds.square()[None]                                             # [1, K]
        c = (1 - tt) ** 2 + tt ** 2 * s2                                          # [B, K]
        gamma, d = self._components(z, tt, c)
        ea = self.means[None] + (tt * s2 / c)[..., None, None] * d                # E[a|z,k]
        ee = ((1 - tt) / c)[..., None, None] * d                                  # E[e|z,k]
        return (gamma[..., None, None] * (ea - ee)).sum(1).to(z.dtype)

    def score(self, z: Tensor, t: Tensor) -> Tensor:
        tt = t.double().reshape(-1, 1)
        c = (1 - tt) ** 2 + tt ** 2 * self.stds.square()[None]
        gamma, d = self._components(z, tt, c)
        return -(gamma[..., None, None] * d / c[..., None, None]).sum(1).to(z.dtype)

    def denoiser(self, x: Tensor, alpha_bar: Tensor) -> Tensor:
        """E[a | x] for x = √ᾱ·a + √(1 − ᾱ)·ε, with ᾱ [B]."""
        ab = alpha_bar.double().reshape(-1, 1)
        s2 = self.stds.square()[None]
        var = ab * s2 + 1 - ab
        gamma, d = self._components(x, ab.sqrt(), var)
        ea = self.means[None] + (ab.sqrt() * s2 / var)[..., None, None] * d
        return (gamma[..., None, None] * ea).sum(1).to(x.dtype)

    def ddpm_model(self, alphas_cumprod: Tensor, prediction_type: str):
        """The exact DDPM head `out(x, timestep [B])` for a diffusers ᾱ table."""
        def out(x: Tensor, timestep: Tensor) -> Tensor:
            ab = alphas_cumprod.to(x.device)[timestep.long()].double()
            x0 = self.denoiser(x, ab)
            if prediction_type == "sample":
                return x0
            ab = _b(ab, x).double()
            return ((x.double() - ab.sqrt() * x0.double()) / (1 - ab).sqrt()).to(x.dtype)
        return out


@dataclass
class Gaussian:
    """a ~ N(μ, s² I) with μ [H, D]: the flow map is affine, so u(z, t, r) is closed-form."""

    mean: Tensor
    std: float

    def _c(self, t: Tensor) -> Tensor:
        return (1 - t) ** 2 + t ** 2 * self.std ** 2

    def flow_map(self, z: Tensor, t: Tensor, r: Tensor) -> Tensor:
        """z_r = r·μ + √(c_r/c_t)·(z_t − t·μ): where the ODE carries z from t to r."""
        t, r = _b(t, z), _b(r, z)
        return r * self.mean + (self._c(r) / self._c(t)).sqrt() * (z - t * self.mean)

    def velocity(self, z: Tensor, t: Tensor) -> Tensor:
        tb = _b(t, z)
        dc = -2 * (1 - tb) + 2 * tb * self.std ** 2          # dc/dt
        return self.mean + 0.5 * dc / self._c(tb) * (z - tb * self.mean)

    def avg_velocity(self, z: Tensor, t: Tensor, r: Tensor) -> Tensor:
        """(z_r − z_t)/(r − t); the r → t limit is the velocity."""
        gap = _b(r - t, z)
        same = gap.abs() < 1e-12
        u = (self.flow_map(z, t, r) - z) / torch.where(same, torch.ones_like(gap), gap)
        return torch.where(same, self.velocity(z, t), u)

    def sample(self, n: int, generator: Optional[torch.Generator] = None) -> Tensor:
        e = torch.randn((n, *self.mean.shape), generator=generator, dtype=self.mean.dtype)
        return self.mean + self.std * e


def energy_distance(x: Tensor, y: Tensor) -> float:
    """Two-sample energy distance 2E|X−Y| − E|X−X'| − E|Y−Y'| between flattened samples."""
    x, y = x.detach().flatten(1).double(), y.detach().flatten(1).double()
    return float(2 * torch.cdist(x, y).mean() - torch.cdist(x, x).mean() - torch.cdist(y, y).mean())
