"""Samplers over callables: Euler ODE, MeanFlow steps, marginal-preserving Euler–Maruyama.

Time runs from 0 (noise) to 1 (data). All integrate in float32 (float64 for float64 noise)
whatever dtype the callable returns, and return actions in the dtype of the noise. The
grid is read to the host once per call (for the step sizes); the loops do no host syncs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .paths import (AvgVelocity, Generators, Velocity, check_chunk, check_steps, checked_call, compute_dtype,
                    randn_rows, resolve_steps)
from .sigma import ChurnSigma, FixedSigma

LOGPROB_FORMS = ("full", "eps")
REDUCTIONS = ("sum", "mean", "none")
_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def _setup(noise: Tensor, steps: int, grid: Optional[Tensor]):
    check_chunk(noise, "noise")
    dtype = compute_dtype(noise)
    return dtype, resolve_steps(steps, grid, noise, dtype)


def sample_ode(velocity: Velocity, noise: Tensor, steps: int = 10,
               grid: Optional[Tensor] = None) -> Tensor:
    """Euler integration of dx/dt = v(x, t) from t = 0 (noise) to 1: the FM-ODE sampler."""
    dtype, st = _setup(noise, steps, grid)
    x = noise.to(dtype)
    for t, dt in zip(st.starts, st.dts):
        x = x.add(checked_call(velocity, x, t, dtype=dtype, name="velocity"), alpha=dt)
    return x.to(noise.dtype)


def sample_meanflow(avg_velocity: AvgVelocity, noise: Tensor, steps: int = 1,
                    grid: Optional[Tensor] = None) -> Tensor:
    """MeanFlow steps `x ← x + (r − t)·u(x, t, r)` with (t, r) consecutive grid points."""
    dtype, st = _setup(noise, steps, grid)
    x = noise.to(dtype)
    for t, r, dt in zip(st.starts, st.ends, st.dts):
        x = x.add(checked_call(avg_velocity, x, t, r, dtype=dtype, name="avg_velocity"), alpha=dt)
    return x.to(noise.dtype)


def velocity_from_meanflow(avg_velocity: AvgVelocity, mode: str = "boundary",
                           delta: float = 1e-3) -> Velocity:
    """An instantaneous velocity from a MeanFlow head, to plug into `sample_ode`/`sample_sde`.

    "boundary": v̂(x, t) = u(x, t, r=t) — the r → t limit; one network call.
    "identity": v̂ = u + (t − r)·du/dt at r = min(t + delta, 1), du/dt by JVP along the
    tangent (u, 1, 0): u stands in for the unknown v in the tangent, which costs O(delta²).
    Two network calls (one of them a JVP) per velocity; `avg_velocity` must support
    `torch.func.jvp` (the policy's network does: MeanFlow training differentiates it so).
    """
    if mode == "boundary":
        return lambda x, t: avg_velocity(x, t, t)
    if mode != "identity":
        raise ValueError(f"mode: expected 'boundary' or 'identity', got {mode!r}")
    if not delta > 0:
        raise ValueError(f"delta: expected a positive time offset, got {delta!r}")

    def velocity(x: Tensor, t: Tensor) -> Tensor:
        t = t.contiguous()      # [B]; the samplers pass an expanded view, which jvp refuses
        r = (t + delta).clamp(max=1.0)
        u0 = avg_velocity(x, t, r)
        u, dudt = torch.func.jvp(lambda x_, t_: avg_velocity(x_, t_, r), (x, t),
                                 (u0, torch.ones_like(t)))
        return u + (t - r).reshape(-1, *([1] * (x.dim() - 1))).to(u.dtype) * dudt

    return velocity


@dataclass
class SDEResult:
    """What `sample_sde` did. Shapes with B batch, K steps, chunk [H, D].

    `chain`, `means`, `eps` are kept in the integration dtype (float32/64) so that the chain
    can be re-scored exactly (PPO); `actions` is in the noise dtype. `grid` is the caller's
    own copy: editing it changes no other call.
    """

    actions: Tensor                           # [B, H, D] final sample (tanh'ed if squashed)
    chain: Tensor                             # [B, K+1, H, D] states; chain[:, 0] is the noise
    means: Tensor                             # [B, K, H, D] Gaussian mean of each step
    stds: Tensor                              # [B, K] Gaussian std of each step
    eps: Tensor                               # [B, K, H, D] standard normal draws
    grid: Tensor                              # [K+1]
    step_log_probs: Optional[Tensor] = None   # [B, K] (or [B, K, H, D] with reduce="none")
    log_prob: Optional[Tensor] = None         # [B] (or [B, H, D]); includes the tanh correction
    squash_log_det: Optional[Tensor] = None   # [B] (or [B, H, D]) log|d tanh/dx|, if squashed


def _as_sigma(sigma) -> nn.Module:
    if isinstance(sigma, (int, float)):
        return FixedSigma(float(sigma))
    if not callable(sigma):
        raise ValueError(f"sigma: expected a schedule σ(t) or a number, got {type(sigma).__name__}")
    return sigma


def _step_coefficients(sigma, grid: Tensor, clip_t: float):
    """Per-step scalars of the Euler–Maruyama update `mean = a·x + b·v`, `std`.

    ṽ = v + ½σ²·(t·v − x)/(1 − t) gives mean = x + ṽ·Δt = (1 − c·Δt)·x + Δt·(1 + c·t)·v
    with c = ½σ²/max(1 − t, clip_t) computed as one expression, never σ²·score.
    """
    t, dt = grid[:-1], grid.diff()                                   # [K], [K]
    sig = sigma(t)
    if not isinstance(sig, Tensor) or sig.shape != t.shape:
        raise ValueError(f"sigma: expected σ(t) of shape {tuple(t.shape)} for t of that shape, "
                         f"got {tuple(sig.shape) if isinstance(sig, Tensor) else type(sig).__name__}")
    sig = sig.to(grid.dtype)
    c = 0.5 * sig.square() / (1 - t).clamp_min(clip_t)
    return 1 - c * dt, dt * (1 + c * t), sig * dt.sqrt()             # a, b, std: each [K]


def _check_density_std(std: Tensor, grid: Tensor, density: bool = True) -> None:
    """A step of std 0 (or NaN/inf) has no density: σ must be positive and finite on every step
    (`density=False`, sampling without log-probs: finite, as NaN or inf makes NaN actions).

    std_k = σ(t_k)·√Δt_k with Δt_k > 0, so std [K] is checked. One host sync per call, made
    after the loop's work is queued, so that on a GPU it waits only for results the caller
    reads anyway.
    """
    bad = ~(torch.isfinite(std) & (std > 0)) if density else ~torch.isfinite(std)       # [K]
    if bool(bad.any()):
        k = int(bad.nonzero()[0])
        sig = float(std[k]) / float(grid[k + 1] - grid[k]) ** 0.5
        expected = "> 0 and finite on every step to compute log-probs" if density else "finite on every step"
        raise ValueError(f"sigma: expected σ(t) {expected}, got σ({float(grid[k]):.6g}) = {sig:.6g} "
                         f"(step {k} of {len(std)})")


def _gaussian_log_prob(z: Tensor, std: Tensor, reduce: str) -> Tensor:
    """log N of standardised residuals z [B, K, H, D] with per-step std [K] or [B, K]."""
    std = std.reshape(*std.shape, 1, 1)
    lp = -0.5 * z.square() - std.log() - _HALF_LOG_2PI
    if reduce == "sum":
        return lp.sum((-2, -1))
    if reduce == "mean":
        return lp.mean((-2, -1))
    return lp


def _check_logprob_args(logprob: str, reduce: str, clip_t: float) -> None:
    if logprob not in LOGPROB_FORMS:
        raise ValueError(f"logprob: expected one of {list(LOGPROB_FORMS)}, got {logprob!r}")
    if reduce not in REDUCTIONS:
        raise ValueError(f"reduce: expected one of {list(REDUCTIONS)}, got {reduce!r}")
    if not 0 < clip_t < 1:
        raise ValueError(f"clip_t: expected a value in (0, 1), got {clip_t!r}")


def sample_sde(velocity: Velocity, noise: Tensor, steps: int = 10,
               sigma: Union[nn.Module, float, None] = None, grid: Optional[Tensor] = None,
               generator: Generators = None, return_logprob: bool = False,
               logprob: str = "full", clip_t: float = 1e-2, reduce: str = "sum",
               squash: bool = False) -> SDEResult:
    """Euler–Maruyama for dx = ṽ dt + σ(t) dW with the drift that keeps the ODE's marginals.

    mean_k = a_k·x_k + b_k·v(x_k, t_k) (see `_step_coefficients`), std_k = σ(t_k)·√Δt_k,
    x_{k+1} = mean_k + std_k·ε_k. σ is evaluated once per call on the grid's K step times.

    With `return_logprob`, `step_log_probs[:, k]` is log N(x_{k+1}; mean_k, std_k² I) of the
    returned chain, computed from the chain itself: `chain_log_prob` with the same velocity,
    σ and grid gives the same values (PPO ratio 1). σ must then be positive and finite on
    every step (ValueError, checked once per call); without log-probs σ must be finite (σ = 0 is
    the ODE). `logprob` picks only where the gradient goes:
      "full" — the chain is data (score-function / PPO form): each step's network call sees
               the detached state x_k, so gradients reach the velocity's parameters through
               the means and σ through the stds, exactly as for `chain_log_prob` of the
               returned chain. The actions then carry a gradient through the last step only.
      "eps"  — reparameterised (SAC's entropy term): the gradient is that of the ε form
               −½|ε_k|² − log std_k − ½log 2π per element, which reaches σ only; the chain
               keeps its pathwise gradient, so the actions reach the network.
    `generator` may be one generator or one per row (`paths.randn_rows`): then each row's ε
    does not depend on the rest of the batch.
    reduce="sum" sums over H×D (the density of the chunk); "mean" averages (Flow-GRPO's
    choice: a ratio of such means is the true ratio to the power 1/(H·D)); "none" keeps
    [.., H, D]. squash=True applies tanh once after the last step and subtracts
    log|d tanh/dx| from `log_prob` (not from `step_log_probs`). In the "eps" form that correction
    enters `log_prob`'s value but not its gradient, so the gradient stays on σ only (through the
    chain the log-det would pull the velocity network toward the origin; SAC's `actor_sample`
    treats its box squash the same way); `squash_log_det` itself keeps its pathwise gradient.
    """
    _check_logprob_args(logprob, reduce, clip_t)
    sigma = ChurnSigma() if sigma is None else _as_sigma(sigma)
    dtype, st = _setup(noise, steps, grid)
    grid = st.grid
    a, b, std = _step_coefficients(sigma, grid, clip_t)
    B, K = noise.shape[0], grid.numel() - 1
    eps = randn_rows(B, (K, *noise.shape[1:]), generator, noise.device, dtype)      # [B, K, H, D]
    as_data = return_logprob and logprob == "full"       # the score-function form detaches states
    x = noise.to(dtype)
    states, means = [x], []
    # Per-step views made once (unbind), not indexed inside the loop.
    for t, a_k, b_k, std_k, eps_k in zip(st.starts, a.unbind(), b.unbind(), std.unbind(), eps.unbind(1)):
        x_in = x.detach() if as_data else x
        v = checked_call(velocity, x_in, t, dtype=dtype, name="velocity")
        mean = torch.addcmul(x_in * a_k, v, b_k)
        x = torch.addcmul(mean, eps_k, std_k)
        states.append(x)
        means.append(mean)
    chain, means_t = torch.stack(states, 1), torch.stack(means, 1)   # [B, K+1, H, D], [B, K, H, D]
    stds = std.expand(B, K)
    final = x                                      # its own storage: editing actions leaves chain intact
    result = SDEResult(actions=final, chain=chain, means=means_t, stds=stds, eps=eps, grid=grid.clone())
    if squash:
        result.actions = torch.tanh(final)
        y = final.detach() if as_data else final
        # log(1 − tanh²x) = 2·(log 2 − x − softplus(−2x)), stable for large |x|.
        log_det = 2 * (math.log(2) - y - F.softplus(-2 * y))
        result.squash_log_det = log_det if reduce == "none" else (
            log_det.sum((-2, -1)) if reduce == "sum" else log_det.mean((-2, -1)))
    _check_density_std(std, grid, density=return_logprob)
    if return_logprob:
        z = (chain[:, 1:].detach() - means_t) / stds.reshape(B, K, 1, 1)     # [B, K, H, D]
        if logprob == "eps":
            z = eps + (z - eps).detach()           # the chain's value, the ε form's gradient (0)
        result.step_log_probs = _gaussian_log_prob(z, stds, reduce)
        result.log_prob = result.step_log_probs.sum(1)
        if squash:              # the ε form: the log-det's value, not its gradient (σ only)
            log_det = result.squash_log_det.detach() if logprob == "eps" else result.squash_log_det
            result.log_prob = result.log_prob - log_det
    result.actions = result.actions.to(noise.dtype)
    return result


def gaussian_target_std(sigma, steps: int, target_std: float = 0.4, clip_t: float = 1e-2,
                        device: Optional[torch.device] = None) -> float:
    """The std per element of `sample_sde`'s output on the uniform grid of `steps` steps when the
    data is N(0, target_std²) and the velocity is that data's exact one, v(x, t) = g(t)·x with
    g = (t·s² − (1 − t)) / ((1 − t)² + t²·s²), s = `target_std` (`oracles.Gaussian`).

    Each step is then affine in x, so the variance follows var_{k+1} = (a_k + b_k·g(t_k))²·var_k + std_k²
    from var_0 = 1 (closed form, float64). Enough steps return `target_std`; few leave part of the
    noise the steps inject. `device`: where σ's parameters live."""
    check_steps(steps)
    sigma = _as_sigma(sigma)
    grid = torch.linspace(0, 1, steps + 1, dtype=torch.float64, device=device)
    with torch.no_grad():
        a, b, std = _step_coefficients(sigma, grid, clip_t)
    s2 = float(target_std) ** 2
    var = 1.0
    for t, a_k, b_k, std_k in zip(grid[:-1].tolist(), a.tolist(), b.tolist(), std.tolist()):
        g = (t * s2 - (1 - t)) / ((1 - t) ** 2 + t * t * s2)
        var = (a_k + b_k * g) ** 2 * var + std_k ** 2
    return math.sqrt(var)


def chain_log_prob(velocity: Velocity, chain: Tensor, sigma, grid: Optional[Tensor] = None,
                   clip_t: float = 1e-2, reduce: str = "sum") -> Tensor:
    """Re-score a stored chain [B, K+1, H, D] under `velocity`: log N(x_{k+1}; mean_k, std_k²).

    Use the grid stored with the chain (`SDEResult.grid`): a different grid changes every
    mean and std. For the velocity that produced the chain this equals `step_log_probs`
    (PPO ratio 1); gradients reach the velocity's parameters through mean_k (and σ's), and
    the chain's own gradient if it has one (pass `chain.detach()` for the PPO form).
    """
    _check_logprob_args("full", reduce, clip_t)
    if not isinstance(chain, Tensor) or chain.dim() != 4 or chain.shape[1] < 2:
        raise ValueError(f"chain: expected a tensor [B, K+1, H, D] with K >= 1, got "
                         f"{tuple(chain.shape) if isinstance(chain, Tensor) else type(chain).__name__}")
    sigma = _as_sigma(sigma)
    B, K = chain.shape[0], chain.shape[1] - 1
    dtype, st = _setup(chain[:, 0], K, grid)
    grid = st.grid
    if grid.numel() != K + 1:
        raise ValueError(f"grid: expected {K + 1} points for a chain of {K} steps, got {grid.numel()}")
    a, b, std = _step_coefficients(sigma, grid, clip_t)
    chain = chain.to(dtype)
    means = torch.stack([torch.addcmul(x * a_k, checked_call(velocity, x, t, dtype=dtype, name="velocity"), b_k)
                         for x, t, a_k, b_k in zip(chain[:, :-1].unbind(1), st.starts, a.unbind(), b.unbind())],
                        1)                                            # [B, K, H, D]
    _check_density_std(std, grid)
    stds = std.expand(B, K)
    return _gaussian_log_prob((chain[:, 1:] - means) / stds.reshape(B, K, 1, 1), stds, reduce)
