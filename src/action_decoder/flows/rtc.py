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

MeanFlow. One step x_r = x_t + (r − t)·u(x_t, t, r); the clean estimate is one step to the end,
Â = x + (1 − t)·u(x, t, 1). A trained 1-step MeanFlow map is locally flat in its noise: J = ∂Â/∂x
is small (push, the first evaluation layout: |Jᵀ W r| is 0.03–0.16 against |W r| of 0.6–1.3 on the
overlap's first rows), so the Jᵀ-directed term above barely moves the chunk (measured: it did not
lower the jerk at chunk switches). The guidance is therefore taken with J = I, the correction
ΠGDM makes to the clean estimate itself: the guided clean estimate is Ã = Â + W ⊙ (Y − Â) (the
posterior mean for a Gaussian prior around Â whose gain towards Y is W), and each step is the
plain step plus the velocity that moves its end point by that correction spread over the
remaining time:

    ũ(x, t, r) = u(x, t, r) + w(t)·W ⊙ (Y − Â),   w(t) = min(β, 1/(1 − t)).

A step to r = 1 with w unclipped lands on Ã exactly; earlier steps move 1/(1 − t) of the
correction per unit time, so a K-step sample keeps pulling its later clean estimates. No VJP: a
1-step sample is one network call, the same as without RTC; a K-step sample adds one call u(x, t, 1)
for each step that does not end at 1 (2K − 1 calls).

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
from .paths import AvgVelocity, Generators, Velocity, check_chunk, checked_call, compute_dtype, resolve_steps
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
    if torch.is_inference_mode_enabled():
        raise RuntimeError("prev_chunk: this real-time chunking guidance needs a vector-Jacobian product through "
                           "the network; call it under torch.no_grad(), not torch.inference_mode() "
                           "(MeanFlow's own one-step guidance, sampler 'meanflow', works in either)")
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


def meanflow_guidance(avg_velocity: AvgVelocity, x: Tensor, t: Tensor, target: Tensor, weights: Tensor,
                      max_weight: float) -> tuple[Tensor, Tensor]:
    """(w(t)·W ⊙ (Y − Â), u(x, t, 1)) with Â = x + (1 − t)·u(x, t, 1) and w(t) = min(β, 1/(1 − t)):
    MeanFlow's guidance term (module docstring) and the call it made, for reuse when r = 1."""
    u1 = checked_call(avg_velocity, x, t, torch.ones_like(t), dtype=x.dtype, name="avg_velocity")   # [B, H, D]
    a_hat = x + (1 - _bcast(t, x)) * u1
    w = (1 / (1 - t.to(x.dtype))).clamp(max=max_weight)                                        # [B]
    return _bcast(w, x) * weights.to(x.dtype)[:, None] * (target.to(x.dtype) - a_hat), u1


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
    """`sample_meanflow` with RTC guidance on the average velocity (module docstring): 1 network call
    at K = 1, 2K − 1 at K steps; the first `delay` rows frozen to prev's."""
    target, weights = rtc_target(prev, delay, noise, schedule)
    beta = _max_weight(max_guidance_weight, math.inf)
    if beta == 0 or (delay == 0 and (schedule == "zeros" or prev.shape[1] == 0)):     # no guidance
        return freeze_prefix(sample_meanflow(avg_velocity, noise, steps), prev, delay)
    dtype = compute_dtype(noise)
    st = resolve_steps(steps, None, noise, dtype)
    x = noise.to(dtype)
    for k, (t, r, dt) in enumerate(zip(st.starts, st.ends, st.dts)):
        pull, u1 = meanflow_guidance(avg_velocity, x, t, target, weights, beta)
        u = u1 if k == len(st.dts) - 1 else checked_call(avg_velocity, x, t, r, dtype=dtype, name="avg_velocity")
        x = x.add(u + pull, alpha=dt)
    return freeze_prefix(x.to(noise.dtype), prev, delay)


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
