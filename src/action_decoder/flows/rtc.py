"""Real-time chunking (RTC, Black et al. 2025) as guided samplers over callables.

Inference takes d control steps, so the next chunk must continue what the robot executes
meanwhile. The next chunk is sampled as an inpainting problem: its first d actions are the
previous chunk's (frozen), the rest of the overlap is pulled towards the previous chunk with
decaying weights, and beyond the overlap it is free. Time runs from 0 (noise) to 1 (data).

`prev` is the previous chunk's leftover aligned to the new chunk's time: `prev[:, j]` is what
the previous chunk planned for the new chunk's step j, [B, L, D] with d ≤ L ≤ H (L = H − s for
an execution horizon of s steps). The weights (`rtc_weights`) are 1 on j < d, decay over
d ≤ j < L, and are 0 beyond L.

Guidance (ΠGDM, the paper's eq. 2–5). With the clean estimate Â(x, t) = x + (1 − t)·v(x, t)
and the Gaussian likelihood p(Y | x_t) ∝ exp(−½|W^½(Y − Â)|² / r_t²), r_t² = (1 − t)²/(t² + (1 − t)²),
the score gains ∇log p(Y | x) = (Y − Â)ᵀ diag(W) ∂Â/∂x / r_t², and on the straight path
v = (x + (1 − t)·score)/t, so the velocity gains (1 − t)/t times that:

    v_guided = v + w(t)·g,   g = (Y − Â)ᵀ diag(W) ∂Â/∂x   (one VJP per step),
    w(t) = min(β, (1 − t)/(t·r_t²)) = min(β, (t² + (1 − t)²)/(t·(1 − t))).

A step of size Δt moves Â by Δt·w·J Jᵀ W (Y − Â) (J = ∂Â/∂x): for J = I, Δt·w > 1 overshoots
the target. The samplers here therefore clip w at min(β, 1/Δt): at 10 steps with the paper's
β = 5 nothing changes; a 1-step MeanFlow sample moves Â exactly onto Y where W = 1 (for J = I).

MeanFlow. One step x_r = x_t + (r − t)·u(x_t, t, r). The clean estimate is one step to the end,
Â = x + (1 − t)·u(x, t, 1), and the guided average velocity is u(x, t, r) + w(t)·g with g the
same VJP through Â: the average of the guided velocity over [t, r] with the guidance frozen at
its value at t (exact as r → t). When r = 1 (every 1-step sample, and the last step of K) the
step's u is the one inside Â: one network call with its VJP; otherwise one call more.
Measured on Meta-World push (docs/benchmarks/rtc.md): this cuts flow matching's jerk at chunk
switches by a third at d = 2 and 4, but not MeanFlow's: at t = 0 its clean estimate barely moves
with x (small J), so Jᵀ-directed guidance cannot carry a 1- or 2-step sample to the previous chunk.

DDPM is not offered: its sampler is diffusers' DPM-Solver++, a multistep scheme whose updates
keep their own history of model outputs inside the scheduler, so a guidance term cannot be
added per step without re-deriving the solver; the policy refuses `prev_chunk` for DDPM.

Frozen actions. The frozen rows of the returned chunk are replaced by Y[:, :d] exactly: those
actions are executed whatever the sampler returns (the robot carries them out while the new
chunk is computed), and the guidance, with W = 1 on them, has already pulled the rest of the
chunk into agreement with them. Replacing the final rows (rather than inpainting x_t's rows
at every step) keeps the network's input on the guided ODE's own path, with no rows spliced in
from another chunk.
"""

from __future__ import annotations

import math
from typing import Optional, Union

import torch
from torch import Tensor, nn

from ..config import RTC_SCHEDULES
from .paths import AvgVelocity, Generators, Velocity, check_chunk
from .samplers import SDEResult, sample_meanflow, sample_ode, sample_sde


def rtc_weights(delay: int, overlap: int, horizon: int, schedule: str = "exp",
                device=None, dtype: torch.dtype = torch.float32) -> Tensor:
    """Guidance weights W [horizon]: 1 on the d frozen steps, a decay over d ≤ j < overlap, 0 beyond.

    "exp" (the paper): c_j = (overlap − j)/(overlap − d + 1), W_j = c_j·(e^{c_j} − 1)/(e − 1);
    "linear": W_j = c_j; "ones": 1 over the whole overlap; "zeros": only the frozen steps.
    """
    if schedule not in RTC_SCHEDULES:
        raise ValueError(f"schedule: expected one of {list(RTC_SCHEDULES)}, got {schedule!r}")
    for name, value in (("delay", delay), ("overlap", overlap), ("horizon", horizon)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name}: expected a non-negative integer, got {value!r}")
    if not delay <= overlap <= horizon:
        raise ValueError(f"delay, overlap: expected 0 <= delay <= overlap <= horizon ({horizon}), "
                         f"got delay={delay}, overlap={overlap}")
    j = torch.arange(horizon, device=device, dtype=dtype)                        # [H]
    c = ((overlap - j) / (overlap - delay + 1)).clamp(0, 1)
    soft = {"exp": c * torch.expm1(c) / math.expm1(1.0), "linear": c,
            "ones": torch.ones_like(c), "zeros": torch.zeros_like(c)}[schedule]
    w = torch.where(j < delay, torch.ones_like(c), soft)
    return torch.where(j < overlap, w, torch.zeros_like(c))


def guidance_weight(t: Tensor, max_weight: float) -> Tensor:
    """w(t) = min(β, (t² + (1 − t)²)/(t·(1 − t))) [B]: the paper's (1 − t)/(t·r_t²), clipped at β."""
    raw = (t.square() + (1 - t).square()) / (t * (1 - t))                     # inf at t = 0
    return raw.clamp(max=max_weight)


def _guidance(clean, x: Tensor, target: Tensor, weights: Tensor):
    """g = (Y − Â)ᵀ diag(W) ∂Â/∂x by one vector–Jacobian product; `clean(x) -> (Â, aux)`.

    Returns g and aux, both detached: an RTC chunk is for execution and carries no gradient.
    `torch.autograd.grad` (not `torch.func.vjp`: on the policy's network at batch 1 the latter
    costs 3.8 network calls against 2.1) under `enable_grad`, so it works inside `no_grad`."""
    with torch.enable_grad():
        x_ = x.detach().requires_grad_()
        a_hat, aux = clean(x_)                                                # [B, H, D] each
        (g,) = torch.autograd.grad(a_hat, x_, weights[:, None] * (target - a_hat.detach()))
    return g, aux.detach()


def _bcast(t: Tensor, x: Tensor) -> Tensor:
    return t.reshape(-1, *([1] * (x.dim() - 1))).to(x.dtype)


def rtc_guided_velocity(velocity: Velocity, target: Tensor, weights: Tensor, max_weight: float) -> Velocity:
    """v(x, t) + w(t)·g with Â = x + (1 − t)·v(x, t): FM's guided velocity (module docstring).

    target Y [B, H, D] and weights W [H] in the sampler's units; one network call with its VJP."""
    def guided(x: Tensor, t: Tensor) -> Tensor:
        t = t.contiguous()                               # the samplers pass expanded views

        def clean(x_: Tensor):
            v = velocity(x_, t).to(x_.dtype)
            return x_ + (1 - _bcast(t, x_)) * v, v

        g, v = _guidance(clean, x, target.to(x.dtype), weights.to(x.dtype))
        return v + _bcast(guidance_weight(t.to(x.dtype), max_weight), x) * g

    return guided


def rtc_guided_avg_velocity(avg_velocity: AvgVelocity, target: Tensor, weights: Tensor,
                            max_weight: float) -> AvgVelocity:
    """u(x, t, r) + w(t)·g with Â = x + (1 − t)·u(x, t, 1): MeanFlow's guided average velocity."""
    def guided(x: Tensor, t: Tensor, r: Tensor) -> Tensor:
        t, r = t.contiguous(), r.contiguous()
        one = torch.ones_like(t)

        def clean(x_: Tensor):
            u1 = avg_velocity(x_, t, one).to(x_.dtype)
            return x_ + (1 - _bcast(t, x_)) * u1, u1

        g, u1 = _guidance(clean, x, target.to(x.dtype), weights.to(x.dtype))
        u = u1 if bool((r == 1).all()) else avg_velocity(x, t, r).to(x.dtype)
        return u + _bcast(guidance_weight(t.to(x.dtype), max_weight), x) * g

    return guided


def rtc_target(prev: Tensor, delay: int, noise: Tensor, schedule: str = "exp"):
    """The padded target Y [B, H, D] (zeros beyond the overlap) and weights W [H] for `prev` [B, L, D]."""
    check_chunk(noise, "noise")
    B, H, D = noise.shape
    if not isinstance(prev, Tensor) or prev.dim() != 3 or prev.shape[0] != B or prev.shape[2] != D \
            or prev.shape[1] > H:
        got = tuple(prev.shape) if isinstance(prev, Tensor) else type(prev).__name__
        raise ValueError(f"prev: expected the previous chunk's leftover [B={B}, L <= {H}, D={D}], got {got}")
    if isinstance(delay, bool) or not isinstance(delay, int) or not 0 <= delay <= prev.shape[1]:
        raise ValueError(f"delay: expected an integer in [0, {prev.shape[1]}] (the leftover's length), got {delay!r}")
    weights = rtc_weights(delay, prev.shape[1], H, schedule, device=noise.device, dtype=torch.float32)
    target = torch.zeros(B, H, D, device=noise.device, dtype=prev.dtype)
    target[:, : prev.shape[1]] = prev
    return target, weights


def freeze_prefix(x: Tensor, prev: Tensor, delay: int) -> Tensor:
    """x with its first `delay` rows replaced by prev's (a copy; x [B, H, D], prev [B, L, D])."""
    if delay == 0:
        return x
    x = x.clone()
    x[:, :delay] = prev[:, :delay].to(x.dtype)
    return x


def _max_weight(beta: float, steps: int) -> float:
    if isinstance(beta, bool) or not isinstance(beta, (int, float)) or not (beta >= 0 and math.isfinite(beta)):
        raise ValueError(f"max_guidance_weight: expected a non-negative finite number, got {beta!r}")
    return min(float(beta), float(steps))               # 1/Δt on the uniform grid of `steps`


def sample_ode_rtc(velocity: Velocity, noise: Tensor, prev: Tensor, delay: int, steps: int = 10,
                   max_guidance_weight: float = 5.0, schedule: str = "exp") -> Tensor:
    """`sample_ode` with RTC guidance towards `prev` [B, L, D] and its first `delay` rows frozen."""
    target, weights = rtc_target(prev, delay, noise, schedule)
    guided = rtc_guided_velocity(velocity, target, weights, _max_weight(max_guidance_weight, steps))
    return freeze_prefix(sample_ode(guided, noise, steps), prev, delay)


def sample_meanflow_rtc(avg_velocity: AvgVelocity, noise: Tensor, prev: Tensor, delay: int, steps: int = 1,
                        max_guidance_weight: float = 5.0, schedule: str = "exp") -> Tensor:
    """`sample_meanflow` with RTC guidance on the average velocity (module docstring)."""
    target, weights = rtc_target(prev, delay, noise, schedule)
    guided = rtc_guided_avg_velocity(avg_velocity, target, weights, _max_weight(max_guidance_weight, steps))
    return freeze_prefix(sample_meanflow(guided, noise, steps), prev, delay)


def sample_sde_rtc(velocity: Velocity, noise: Tensor, prev: Tensor, delay: int, steps: int = 10,
                   sigma: Union[nn.Module, float, None] = None, generator: Generators = None,
                   clip_t: float = 1e-2, max_guidance_weight: float = 5.0, schedule: str = "exp") -> SDEResult:
    """`sample_sde` with the guided velocity in its marginal-preserving drift; `actions` has its
    first `delay` rows frozen (the chain is the guided one, as sampled). No log-probs: the chain's
    density would be under the guided drift, which `chain_log_prob` does not re-create."""
    target, weights = rtc_target(prev, delay, noise, schedule)
    guided = rtc_guided_velocity(velocity, target, weights, _max_weight(max_guidance_weight, steps))
    res = sample_sde(guided, noise, steps, sigma, generator=generator, clip_t=clip_t)
    res.actions = freeze_prefix(res.actions, prev, delay)
    return res
