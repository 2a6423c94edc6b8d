"""Training losses for flow matching and MeanFlow, over callables.

`cond` (optional) holds batch-aligned conditioning passed to the callable as keyword
arguments and sliced together with the rows when a loss splits the batch (MeanFlow calls
the r = t rows without JVP): tensors `[B, ...]`, None, or dataclasses of those.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Optional

import torch
from torch import Tensor

from ..config import MEANFLOW_DUDT
from .paths import AvgVelocity, Velocity, check_chunk, checked_call, interpolate
from .rtc_trained import (CLEAN, DELAY_DISTS, KEEP, check_delays, check_max_delay, prefix_mask, row_weights,
                          sample_delays, with_clean_prefix)


def _map_tensors(obj: Any, fn) -> Any:
    """`fn` applied to every tensor in `obj` (a tensor, None, a dataclass, tuple or list of those)."""
    if obj is None:
        return None
    if isinstance(obj, Tensor):
        return fn(obj)
    if dataclasses.is_dataclass(obj):
        return dataclasses.replace(obj, **{f.name: _map_tensors(getattr(obj, f.name), fn)
                                           for f in dataclasses.fields(obj) if f.init})
    if isinstance(obj, (tuple, list)):
        return type(obj)(_map_tensors(o, fn) for o in obj)
    return obj


def slice_cond(cond: Optional[Mapping[str, Any]], rows: slice) -> dict:
    return {k: _map_tensors(v, lambda x: x[rows]) for k, v in (cond or {}).items()}


def _bcast(t: Tensor, like: Tensor) -> Tensor:
    return t.reshape(-1, *([1] * (like.dim() - 1)))


def clean_prefix(fn, a: Tensor, max_delay: int, generator: Optional[torch.Generator],
                 cond: Optional[Mapping[str, Any]], delay_dist: str = "uniform", balance_rows: bool = False,
                 prefix_noise: float = 0.0, delays: Optional[Tensor] = None):
    """Training-time RTC (`flows.rtc_trained`): (fn, cond, live [B, H] or None). With max_delay > 0,
    row b's first d_b actions (d_b on 0..max_delay from `delay_dist`) are given clean at t = r = 1 (`with_clean_prefix`,
    its mask and clean actions travel in `cond` so that every row split slices them too) and `live`
    marks the other rows, the ones the loss covers: a bool mask, or with `balance_rows` their weights
    1/P(d ≤ j) (`row_weights`; 0 on the prefix), so that each row's expected weight is the plain loss's.
    `prefix_noise` σ > 0: the prefix fed in is a + σ·ε (ε ~ N(0, I), drawn after the delays), while the
    loss targets stay a: the network learns to continue a committed prefix that is off the data.
    `delays` [B] (integers in 0..max_delay, optional): row b's d_b where delays[b] > 0 (its label's committed
    rows, e.g. `action.prefix_length`); rows with 0 keep the drawn d_b. The draws are made either way."""
    check_max_delay(max_delay, a.shape[1])
    if isinstance(prefix_noise, bool) or not isinstance(prefix_noise, (int, float)) \
            or not 0 <= prefix_noise < float("inf"):
        raise ValueError(f"rtc_prefix_noise: expected a non-negative finite std in normalised action units, "
                         f"got {prefix_noise!r}")
    if delay_dist not in DELAY_DISTS:
        raise ValueError(f"rtc_delay_dist: expected one of {list(DELAY_DISTS)}, got {delay_dist!r}")
    if delays is not None:
        delays = check_delays(delays, a.shape[0], max_delay)
    if not max_delay:
        return fn, cond, None
    d = sample_delays(a.shape[0], max_delay, generator, a.device, delay_dist)                # [B]
    if delays is not None:
        d = torch.where(delays.to(d.device) > 0, delays.to(d.device), d)
    keep = prefix_mask(d, a.shape[1])                                                        # [B, H]
    live = ~keep
    if balance_rows:
        live = live.to(a.dtype) * row_weights(max_delay, a.shape[1], delay_dist).to(a.device, a.dtype)   # [B, H]
    clean = a + prefix_noise * torch.randn(a.shape, generator=generator, device=a.device, dtype=a.dtype) \
        if prefix_noise else a                                                                # [B, H, D]
    return with_clean_prefix(fn), {**(cond or {}), KEEP: keep, CLEAN: clean}, live


def _masked_mean(sq: Tensor, live: Optional[Tensor]) -> Tensor:
    """Per-row mean of sq [B, H, D] over H×D, or over the live rows' entries ([B, H] bool mask), or the
    weighted sum over H×D divided by H×D ([B, H] float weights)."""
    if live is None:
        return sq.mean((1, 2))
    if live.is_floating_point():
        return (sq * live[..., None].to(sq.dtype)).mean((1, 2))
    w = live[..., None].to(sq.dtype)
    return (sq * w).sum((1, 2)) / (w.sum((1, 2)) * sq.shape[2])


def flow_matching_loss(velocity: Velocity, actions: Tensor, generator: Optional[torch.Generator] = None,
                       cond: Optional[Mapping[str, Any]] = None, rtc_max_delay: int = 0,
                       rtc_delay_dist: str = "uniform", rtc_balance_rows: bool = False,
                       rtc_prefix_noise: float = 0.0, rtc_delays: Optional[Tensor] = None) -> Tensor:
    """‖v_θ(z_t, t) − (a − e)‖² with t ~ U[0, 1], z_t = (1 − t)·e + t·a; mean over all entries.

    `rtc_max_delay` > 0 (training-time real-time chunking, `flows.rtc_trained`): each row's first
    d actions (d on 0..rtc_max_delay from `rtc_delay_dist`, `flows.rtc_trained.DELAY_DISTS`) are given clean at t = 1 (the velocity then takes times per
    token [B, H]); the loss is the mean over the other rows' entries, per chunk, then over chunks
    (`rtc_balance_rows`: row j's entries weighted 1/P(d ≤ j) and summed, over H×D; `rtc_prefix_noise`: the
    prefix fed in carries Gaussian noise of that std; `rtc_delays` [B]: row b's delay where > 0, `clean_prefix`)."""
    check_chunk(actions, "actions")
    a = actions.float() if actions.dtype != torch.float64 else actions
    t = torch.rand(a.shape[0], generator=generator, device=a.device, dtype=a.dtype)
    e = torch.randn(a.shape, generator=generator, device=a.device, dtype=a.dtype)
    z = interpolate(e, a, t)
    fn, cond, live = clean_prefix(velocity, a, rtc_max_delay, generator, cond, rtc_delay_dist, rtc_balance_rows,
                                  rtc_prefix_noise, rtc_delays)
    v = checked_call(lambda x, tt: fn(x, tt, **(cond or {})), z, t, dtype=a.dtype, name="velocity")
    if live is None:
        return (v - (a - e)).square().mean()
    return _masked_mean((v - (a - e)).square(), live).mean()


# Central-difference step along (v, 1, 0) in float32. The time embedding's shortest period
# (4e-3) makes u vary fast in t: on the CLI's network (random and trained) the error of
# (t − r)·du/dt is smallest near this step, rms 3e-3–6e-3 against a target of rms 5–9
# (docs/benchmarks/meanflow_cost.md); 1e-4 truncates 4–6× worse, 3e-6 rounds 8–9× worse.
FD_STEP_FLOAT32 = 3e-5


def fd_step(dtype: torch.dtype) -> float:
    """The central-difference step for `dtype`: the float32 step scaled by the cube root of the
    machine-epsilon ratio (the optimum of truncation ε² against rounding eps/ε)."""
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"meanflow_dudt: 'finite_difference' needs float32 or float64 inputs, got {dtype} "
                         f"(use 'jvp' in lower precision)")
    ratio = torch.finfo(dtype).eps / torch.finfo(torch.float32).eps
    return FD_STEP_FLOAT32 * ratio ** (1 / 3)


def dudt_finite_difference(avg_velocity: AvgVelocity, z: Tensor, t: Tensor, r: Tensor, v: Tensor,
                           cond: Optional[Mapping[str, Any]] = None) -> Tensor:
    """du/dt along the tangent (v, 1, 0) on (z, t, r) by a central difference, without grad.

    One call over 2n rows [z + h·v, z − h·v] at times t ± h, r fixed, h = `fd_step(z.dtype)`;
    returns (u₊ − u₋)/(2h) [n, H, D] in v's dtype. The network must compute in float32 or
    float64: under autocast (mixed-precision training) this call runs with autocast off, its
    floating-point conditioning cast to z's dtype, so the difference is not rounding noise.
    """
    h = fd_step(z.dtype)
    cast = torch.is_autocast_enabled(z.device.type)
    double = lambda x: torch.cat([x, x]).to(z.dtype) if cast and x.is_floating_point() else torch.cat([x, x])
    twice = {k: _map_tensors(c, double) for k, c in (cond or {}).items()}
    step = h * v.to(z.dtype)
    with torch.no_grad(), torch.autocast(z.device.type, enabled=False):
        out = checked_call(lambda x, tt, rr: avg_velocity(x, tt, rr, **twice), torch.cat([z + step, z - step]),
                           torch.cat([t + h, t - h]), torch.cat([r, r]), dtype=v.dtype, name="avg_velocity")
    plus, minus = out.chunk(2)                                            # [n, H, D] each
    return (plus - minus) / (2 * h)


def meanflow_target(avg_velocity: AvgVelocity, z: Tensor, t: Tensor, r: Tensor, v: Tensor,
                    dudt: str = "jvp", cond: Optional[Mapping[str, Any]] = None):
    """(u, target) with u = u_θ(z, t, r) and target = sg(v − (t − r)·du/dt).

    du/dt is the total derivative along the path, with tangent (v, 1, 0) on (z, t, r):
    "jvp" computes it exactly with `torch.func.jvp` (u comes out of the same pass);
    "finite_difference" by `dudt_finite_difference`, with u from a plain call. `cond`: the
    callable's batch-aligned keyword arguments (module docstring).
    The target is detached (the MeanFlow paper's stop-gradient): the loss must not
    backpropagate through du/dt.
    """
    if dudt not in MEANFLOW_DUDT:
        raise ValueError(f"meanflow_dudt: expected one of {list(MEANFLOW_DUDT)}, got {dudt!r}")
    dtype = v.dtype
    bound = lambda x, tt, rr: avg_velocity(x, tt, rr, **(cond or {}))                 # noqa: E731
    if dudt == "jvp":
        u, d = torch.func.jvp(bound, (z, t, r), (v.to(z.dtype), torch.ones_like(t), torch.zeros_like(r)))
    else:
        u = checked_call(bound, z, t, r, dtype=dtype, name="avg_velocity")
        d = dudt_finite_difference(avg_velocity, z, t, r, v, cond)
    target = v - _bcast(t - r, v).to(dtype) * d.to(dtype)
    return u.to(dtype), target.detach()


TIME_DISTS = ("logit_normal", "uniform")
TANGENTS = ("sampled", "boundary")
TARGETS = ("identity", "split")


def sample_meanflow_times(batch: int, ratio_r_neq_t: float, mean: float, std: float,
                          generator: Optional[torch.Generator] = None, device=None,
                          dtype: torch.dtype = torch.float32, dist: str = "logit_normal",
                          one_step_share: float = 0.0):
    """(t, r, n): t ≤ r from two ordered draws; rows n: have r = t, from one draw.

    The r = t rows regress the instantaneous velocity, as flow matching does, so their t keeps
    the marginal of one draw. Ordering them too (the paper's code) would give t the density
    2(1 − t) under "uniform": the data end, where the last integration steps place the action,
    would see 5× fewer rows with t > 0.8.

    "logit_normal": the paper's recipe, with `mean` in our direction (its −0.4 with t = 1 as
    noise is +0.4 here); it rarely draws the whole interval (t ≈ 0, r ≈ 1) that 1-step
    sampling uses. "uniform": both times U[0, 1]. The first n = round(ratio·B) rows keep
    r ≠ t; rows are i.i.d., so a fixed split costs no host sync.

    `one_step_share`: the first round(share·n) of the r ≠ t rows take (t, r) = (0, 1) exactly,
    the whole interval a 1-step sampler jumps; ordered uniform pairs land within 0.05 of that
    corner with probability 0.005.
    """
    if dist not in TIME_DISTS:
        raise ValueError(f"time_dist: expected one of {list(TIME_DISTS)}, got {dist!r}")
    if not 0.0 <= one_step_share <= 1.0:
        raise ValueError(f"one_step_share: expected a fraction in [0, 1], got {one_step_share!r}")
    if not 0.0 <= ratio_r_neq_t <= 1.0:
        raise ValueError(f"ratio_r_neq_t: expected a fraction of the rows in [0, 1], got {ratio_r_neq_t!r}")
    if dist == "logit_normal" and not std > 0:
        raise ValueError(f"time_std: expected a positive std of the logit-normal times, got {std!r}")
    if dist == "uniform":
        s = torch.rand(batch, 2, generator=generator, device=device, dtype=dtype)
    else:
        s = torch.sigmoid(mean + std * torch.randn(batch, 2, generator=generator, device=device, dtype=dtype))
    n = int(round(ratio_r_neq_t * batch))
    t = torch.cat([s[:n].min(1).values, s[n:, 0]])
    r = torch.cat([s[:n].max(1).values, t[n:]])
    m = int(round(one_step_share * n))
    if m:
        t, r = t.clone(), r.clone()
        t[:m], r[:m] = 0.0, 1.0
    return t, r, n


def meanflow_loss(avg_velocity: AvgVelocity, actions: Tensor, generator: Optional[torch.Generator] = None,
                  cond: Optional[Mapping[str, Any]] = None, ratio_r_neq_t: float = 0.5,
                  time_mean: float = 0.4, time_std: float = 1.0, adaptive_p: float = 0.5,
                  adaptive_c: float = 1e-3, time_dist: str = "logit_normal",
                  one_step_share: float = 0.0, dudt: str = "jvp", tangent: str = "sampled",
                  fd_one_call: Optional[bool] = None, target: str = "identity", rtc_max_delay: int = 0,
                  rtc_delay_dist: str = "uniform", rtc_balance_rows: bool = False,
                  rtc_prefix_noise: float = 0.0, rtc_delays: Optional[Tensor] = None) -> Tensor:
    """MeanFlow loss with the recipe of NOTES §2.

    Per row: Δ = u_θ(z_t, t, r) − sg(v − (t − r)·du/dt), error = mean(Δ²) over H×D,
    weight w = sg(1 / (error + c)^p); loss = mean(w·error). Rows with r = t have target v
    and are called without JVP (free speed). p = 0.5 is MP1's choice; on Meta-World push
    (10 demos, 1500 steps, 1-step sampling) p = 0.5 reached 100 % success, p = 1 15 %, p = 0 0 %.

    `dudt` ("jvp" | "finite_difference", see `meanflow_target`): with "finite_difference" u
    comes from one plain call over all B rows and du/dt from one no-grad call over the 2n
    shifted copies of the r ≠ t rows (`dudt_finite_difference`).

    `fd_one_call`: put those 2n shifted rows into u's call instead (one call over B + 2n rows,
    their outputs detached; the same target and gradients). None chooses by device: one call on
    CUDA, where a step of these small networks costs kernel launches rather than rows (H200: 1.03×
    an FM step against 1.33× for two calls), two calls elsewhere, where rows cost time and the
    grad call's 2n extra rows would be kept for backward (CPU: 1.38–1.49× against 1.0–1.24×;
    docs/benchmarks/meanflow_cost.md). Under autocast it is always two calls: the difference must
    run in float32 while u runs in the autocast dtype.

    Why the per-element mean and not the paper's ‖Δ‖² (sum over H×D): the mean is the sum with
    c·H·D and the loss scaled by (H·D)^(p−1), i.e. c 64× larger relative to the error at H = 16,
    D = 4, and a loss 8× smaller. Measured (docs/benchmarks/meanflow_ablations.md): a wash on a
    synthetic two-route task, and on Meta-World basketball (seed 0, 1500 steps, 1 step) the mean
    reached 62 % against 42 % for the sum, so the mean stays the default.

    `tangent`: the velocity v in the r ≠ t rows' target v − (t − r)·du/dt and in the tangent
    (v, 1, 0). "sampled": the conditional a − e (the paper). "boundary": sg(u_θ(z, t, t)), the
    network's own instantaneous (marginal) velocity, from one extra no-grad call over those rows;
    its target has no sampling variance, and for the exact average velocity it is exact per row.
    The r = t rows regress a − e either way, which is what trains u_θ(z, t, t).

    `target`: how the r ≠ t rows get theirs. "identity": the MeanFlow identity above (`dudt`,
    `tangent` apply). "split": interval consistency (SplitMeanFlow) — with s = t + λ(r − t),
    λ ~ U(0, 1), u₁ = sg(u_θ(z, t, s)), z_s = z + (s − t)·u₁, u₂ = sg(u_θ(z_s, s, r)), the target is
    λ·u₁ + (1 − λ)·u₂ (the exact average velocity is additive over sub-intervals); two no-grad
    calls over the n rows, no du/dt.

    `rtc_max_delay` > 0 (training-time real-time chunking, `flows.rtc_trained`): each row's first
    d actions (d on 0..rtc_max_delay from `rtc_delay_dist`) are given clean at t = r = 1 in every call (held fixed along
    the du/dt tangent and in the split's intermediate point), and each row's error is the mean over
    its other rows' entries (`rtc_balance_rows`: weighted 1/P(d ≤ j), summed over H×D; `rtc_prefix_noise`:
    the prefix fed in carries Gaussian noise of that std; `rtc_delays` [B]: row b's delay where > 0, `clean_prefix`).
    """
    check_chunk(actions, "actions")
    if dudt not in MEANFLOW_DUDT:
        raise ValueError(f"meanflow_dudt: expected one of {list(MEANFLOW_DUDT)}, got {dudt!r}")
    if tangent not in TANGENTS:
        raise ValueError(f"tangent: expected one of {list(TANGENTS)}, got {tangent!r}")
    if target not in TARGETS:
        raise ValueError(f"target: expected one of {list(TARGETS)}, got {target!r}")
    if target == "split" and tangent != "sampled":
        raise ValueError(f"tangent: applies to target='identity'; expected 'sampled' with target='split', got {tangent!r}")
    if not adaptive_p >= 0:
        raise ValueError(f"adaptive_p: expected a power >= 0 (0: plain mean), got {adaptive_p!r}")
    if not adaptive_c > 0:
        raise ValueError(f"adaptive_c: expected a positive constant in 1 / (error + c)^p, got {adaptive_c!r}")
    a = actions.float() if actions.dtype != torch.float64 else actions
    B = a.shape[0]
    t, r, n = sample_meanflow_times(B, ratio_r_neq_t, time_mean, time_std, generator, a.device, a.dtype,
                                    time_dist, one_step_share)
    e = torch.randn(a.shape, generator=generator, device=a.device, dtype=a.dtype)
    z, v = interpolate(e, a, t), a - e                                   # [B, H, D] each
    avg_velocity, cond, live = clean_prefix(avg_velocity, a, rtc_max_delay, generator, cond, rtc_delay_dist,
                                            rtc_balance_rows, rtc_prefix_noise, rtc_delays)
    if tangent == "boundary" and n > 0:
        c = slice_cond(cond, slice(0, n))
        with torch.no_grad():
            v_hat = checked_call(lambda x, tt: avg_velocity(x, tt, tt, **c), z[:n], t[:n], dtype=a.dtype,
                                 name="avg_velocity")                    # [n, H, D] u_θ(z, t, t)
        v_tangent = torch.cat([v_hat, v[n:]])
    else:
        v_tangent = v
    if target == "split":
        u = checked_call(lambda x, tt, rr: avg_velocity(x, tt, rr, **(cond or {})), z, t, r, dtype=a.dtype,
                         name="avg_velocity")                                # [B, H, D]
        goal = v
        if n > 0:
            head, c = slice(0, n), slice_cond(cond, slice(0, n))
            lam = torch.rand(n, generator=generator, device=a.device, dtype=a.dtype)
            s = t[head] + lam * (r[head] - t[head])                          # [n] t ≤ s ≤ r
            call = lambda x, t0, t1: checked_call(lambda xx, aa, bb: avg_velocity(xx, aa, bb, **c), x, t0, t1,  # noqa: E731
                                                  dtype=a.dtype, name="avg_velocity")
            with torch.no_grad():
                u1 = call(z[head], t[head], s)                               # [n, H, D] over [t, s]
                u2 = call(z[head] + _bcast(s - t[head], v) * u1, s, r[head])  # over [s, r]
            goal = torch.cat([_bcast(lam, v) * u1 + _bcast(1 - lam, v) * u2, v[n:]])
        return _adaptive_mean(u - goal, adaptive_p, adaptive_c, live)
    deltas = []
    autocast = torch.is_autocast_enabled(a.device.type)
    if fd_one_call and autocast:
        raise ValueError("fd_one_call: expected False or None under autocast (the difference runs in float32, "
                         "u in the autocast dtype), got True")
    one_call = (a.device.type == "cuda" and not autocast) if fd_one_call is None else fd_one_call
    if dudt == "finite_difference":
        head = slice(0, n)
        if one_call and n > 0:                          # u and the 2n shifted rows in one call
            h = fd_step(z.dtype)
            step = h * v_tangent[head]
            rows = lambda x: torch.cat([x, x[head], x[head]])                # noqa: E731  B + 2n rows
            c3 = {k: _map_tensors(c, rows) for k, c in (cond or {}).items()}
            out = checked_call(lambda x, tt, rr: avg_velocity(x, tt, rr, **c3),
                               torch.cat([z, z[head] + step, z[head] - step]), torch.cat([t, t[head] + h, t[head] - h]),
                               torch.cat([r, r[head], r[head]]), dtype=a.dtype, name="avg_velocity")  # [B + 2n, H, D]
            u, (plus, minus) = out[:B], out[B:].detach().chunk(2)
            d = (plus - minus) / (2 * h)                                     # [n, H, D]
        else:                                           # u, then the difference in a no-grad call
            u = checked_call(lambda x, tt, rr: avg_velocity(x, tt, rr, **(cond or {})), z, t, r, dtype=a.dtype,
                             name="avg_velocity")                            # [B, H, D], r = t on rows n:
            d = dudt_finite_difference(avg_velocity, z[head], t[head], r[head], v_tangent[head],
                                       slice_cond(cond, head)) if n > 0 else v[:0]
        deltas.append(u - torch.cat([v_tangent[head] - _bcast(t[head] - r[head], v) * d, v[n:]]))
    elif n > 0:
        sub = slice(0, n)
        u, target = meanflow_target(avg_velocity, z[sub], t[sub], r[sub], v_tangent[sub],
                                    cond=slice_cond(cond, sub))
        deltas.append(u - target)
    if n < B and dudt == "jvp":
        sub = slice(n, B)
        c = slice_cond(cond, sub)
        u = checked_call(lambda x, tt: avg_velocity(x, tt, tt, **c), z[sub], t[sub], dtype=a.dtype,
                         name="avg_velocity")
        deltas.append(u - v[sub])
    return _adaptive_mean(torch.cat(deltas), adaptive_p, adaptive_c, live)


def _adaptive_mean(delta: Tensor, p: float, c: float, live: Optional[Tensor] = None) -> Tensor:
    """mean(w·error) with error = mean(Δ²) over H×D per row (over the `live` rows' entries, [B, H])
    and w = sg(1 / (error + c)^p)."""
    error = _masked_mean(delta.square(), live)                             # [B]
    return ((error.detach() + c).pow(-p) * error).mean()
