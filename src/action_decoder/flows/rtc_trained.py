"""Training-time real-time chunking (Black, Ren, Equi, Levine 2025, arXiv 2512.05964), over callables.

The network learns to continue a committed prefix. In training, the first d actions of a chunk
are given clean — at flow time t = 1 (and r = 1 for MeanFlow), the data end of our convention —
while the rest of the chunk is noised at the sampled time as usual, and the loss covers only the
rest. The network therefore needs times per action token, [B, H] (`ActionExpert.forward`).
d is drawn per training row from a distribution on 0..max_delay (`sample_delays`, `DELAY_DISTS`).
Row j of a chunk is in the loss only when d ≤ j, so the first rows — the ones a chunk without a
prefix executes — learn from a share P(d ≤ j) of the chunks: "uniform" gives row 0 a share
1/(max_delay + 1); "exp" (weights ∝ e^(−d), the training-time RTC paper's recipe in simulation)
gives it 1/Σe^(−d) (0.64 at max_delay = 4), so the weights also sample without a prefix.

At inference the d actions the robot executes while the next chunk is computed are fed in as the
clean prefix at every step of the sampler (`sample_ode_prefix`, `sample_meanflow_prefix`): the
returned chunk keeps them exactly, costs the same network calls as a plain chunk, and works at any
number of steps, MeanFlow's one included. Nothing outside the prefix is pulled towards the previous
chunk: the rest follows the network's own conditional given the prefix.

DDPM is not offered (the policy refuses it): its sampler, DPM-Solver++, runs on one time per sample.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from ..config import RTC_DELAY_DISTS
from .paths import AvgVelocity, Velocity, check_chunk, check_steps, checked_call, compute_dtype, time_grid

KEEP, CLEAN = "rtc_keep", "rtc_clean"      # the keyword arguments `with_clean_prefix` consumes
DELAY_DISTS = RTC_DELAY_DISTS             # P(d) on 0..max_delay: ∝ 1, ∝ e^(−d), or half at 0 (`delay_probs`)


def check_max_delay(max_delay, horizon: int, name: str = "rtc_max_delay") -> int:
    """`max_delay` as an int in [0, horizon): some rows of every chunk must remain to learn."""
    if isinstance(max_delay, bool) or not isinstance(max_delay, int) or not 0 <= max_delay < horizon:
        raise ValueError(f"{name}: expected an integer number of control steps in [0, {horizon - 1}] "
                         f"(below the chunk length {horizon}), got {max_delay!r}")
    return max_delay


def delay_probs(max_delay: int, dist: str = "uniform") -> Tensor:
    """P(d) [max_delay + 1] (float64) on 0..max_delay: "uniform"; "exp" (∝ e^(−d)); "half_zero" (d = 0 for
    half the chunks, the other half uniform on 1..max_delay)."""
    if dist not in DELAY_DISTS:
        raise ValueError(f"rtc_delay_dist: expected one of {list(DELAY_DISTS)}, got {dist!r}")
    d = torch.arange(max_delay + 1, dtype=torch.float64)
    if dist == "half_zero" and max_delay:
        return torch.where(d == 0, torch.full_like(d, 0.5), torch.full_like(d, 0.5 / max_delay))
    w = torch.exp(-d) if dist == "exp" else torch.ones_like(d)
    return w / w.sum()


def row_weights(max_delay: int, horizon: int, dist: str = "uniform") -> Tensor:
    """1 / P(d ≤ j) [H] (float64): the weight that makes row j's expected share of a prefix-masked loss that
    of the plain loss (row j is in the loss only when d ≤ j; rows j ≥ max_delay always are)."""
    cdf = delay_probs(max_delay, dist).cumsum(0)                                   # [max_delay + 1]
    return 1.0 / cdf[torch.arange(horizon).clamp_max(max_delay)]


def sample_delays(batch: int, max_delay: int, generator: Optional[torch.Generator] = None,
                  device=None, dist: str = "uniform") -> Tensor:
    """Delays d [B] (int64) on 0..max_delay from `delay_probs(max_delay, dist)`."""
    if dist == "uniform":                  # the same draws as before the option existed
        return torch.randint(0, max_delay + 1, (batch,), generator=generator, device=device)
    u = torch.rand(batch, generator=generator, device=device, dtype=torch.float64)              # [B]
    cdf = delay_probs(max_delay, dist).cumsum(0).to(u.device)                                 # [max_delay + 1]
    return torch.searchsorted(cdf, u, right=True).clamp_max(max_delay)


def check_delays(delays, batch: int, max_delay: int, name: str = "rtc_delays") -> Tensor:
    """Given delays [B] (e.g. a relabelled dataset's committed rows per chunk) as int64, after one check:
    a tensor of `batch` integers in 0..max_delay, else one line naming `name`."""
    integer = isinstance(delays, Tensor) and not (delays.is_floating_point() or delays.is_complex()
                                                  or delays.dtype == torch.bool)
    span = f" in {int(delays.min())}..{int(delays.max())}" if integer and delays.numel() else ""
    if not integer or delays.shape != (batch,) or (span and not 0 <= int(delays.min()) <= int(delays.max()) <= max_delay):
        got = f"{delays.dtype} {list(delays.shape)}{span}" if isinstance(delays, Tensor) else type(delays).__name__
        off = ", so training-time RTC is off" if not max_delay else ""
        raise ValueError(f"{name}: expected integers [{batch}] in 0..{max_delay} (committed rows per chunk; "
                         f"rtc_max_delay={max_delay}{off}), got {got}")
    return delays.long()


def prefix_mask(delays: Tensor, horizon: int) -> Tensor:
    """[B, H] bool, True on the first delays[b] rows of row b: the rows given clean."""
    return torch.arange(horizon, device=delays.device)[None, :] < delays[:, None]


def token_times(t: Tensor, keep: Tensor) -> Tensor:
    """Times per token [B, H]: 1 on the kept rows, t ([B] or [B, H]) elsewhere."""
    return (t[:, None] if t.dim() == 1 else t).expand(keep.shape).masked_fill(keep, 1.0)


def with_clean_prefix(fn: Callable[..., Tensor]) -> Callable[..., Tensor]:
    """`fn(x, *times, **cond)` with its keyword arguments `rtc_keep` [B, H] (bool) and `rtc_clean`
    [B, H, D] applied: the kept rows of x replaced by the clean actions and their times set to 1.

    The inputs are replaced, not offset, so along any tangent (a JVP, a finite difference) the kept
    rows stay fixed: their derivative with respect to x and to each time is zero."""
    def call(x: Tensor, *times: Tensor, **cond) -> Tensor:
        keep, clean = cond.pop(KEEP), cond.pop(CLEAN)
        x = torch.where(keep[..., None], clean.to(x.dtype), x)
        return fn(x, *(token_times(t, keep) for t in times), **cond)
    return call


@dataclass(frozen=True)
class PrefixSteps:
    """The prefix samplers' per-step inputs for d committed rows, built once per (K, B, H, d, device, dtype):
    times per token [B, H] (1 on the committed rows, the step's start or end time elsewhere), Δt as
    host floats, and `live` [1, H, 1] (0 on the committed rows, which the updates leave clean)."""

    starts: tuple
    ends: tuple
    dts: tuple
    live: Tensor


@functools.lru_cache(maxsize=64)
def _cached_prefix_steps(steps: int, batch: int, horizon: int, delay: int, device: torch.device,
                         dtype: torch.dtype) -> PrefixSteps:
    # Shared between calls, as `paths._uniform_steps`: a prefix-fed chunk builds no time tensors per step.
    with torch.inference_mode(False):
        grid = time_grid(steps, device=device, dtype=dtype)                            # [K + 1]
        keep = torch.arange(horizon, device=device) < delay                            # [H]
        per_token = lambda g: torch.where(keep, 1.0, g[:, None, None]).expand(-1, batch, -1).contiguous()  # noqa: E731
        starts, ends = per_token(grid[:-1]), per_token(grid[1:])                      # [K, B, H] each
        live = (~keep).to(dtype)[None, :, None]                                        # [1, H, 1]
        return PrefixSteps(tuple(starts.unbind(0)), tuple(ends.unbind(0)), tuple(grid.diff().tolist()), live)


def prefix_steps(steps: int, batch: int, horizon: int, delay: int, device, dtype: torch.dtype) -> PrefixSteps:
    """`_cached_prefix_steps`, rebuilt if a callable wrote into its tensors (the cache is never handed on edited)."""
    check_steps(steps)
    st = _cached_prefix_steps(steps, batch, horizon, delay, torch.device(device), dtype)
    if st.starts[0]._version or st.ends[0]._version or st.live._version:
        _cached_prefix_steps.cache_clear()
        st = _cached_prefix_steps(steps, batch, horizon, delay, torch.device(device), dtype)
    return st


def _prefixed_start(noise: Tensor, prefix: Tensor, dtype: torch.dtype) -> Tensor:
    """x0 [B, H, D]: the normalised prefix [B, d, D] followed by the noise's other rows."""
    check_chunk(noise, "noise")
    B, H, D = noise.shape
    if not isinstance(prefix, Tensor) or prefix.dim() != 3 or prefix.shape[0] != B or prefix.shape[2] != D \
            or prefix.shape[1] >= H:
        got = tuple(prefix.shape) if isinstance(prefix, Tensor) else type(prefix).__name__
        raise ValueError(f"prefix: expected the committed actions [B={B}, d < {H}, D={D}], got {got}")
    return torch.cat([prefix.to(dtype), noise[:, prefix.shape[1]:].to(dtype)], 1)


def sample_ode_prefix(velocity: Velocity, noise: Tensor, prefix: Tensor, steps: int = 10) -> Tensor:
    """Euler from noise (t = 0) to data (t = 1) with the committed rows `prefix` [B, d, D] held clean at
    t = 1 on every step (`velocity` takes times per token [B, H]); K network calls, the prefix exact."""
    dtype = compute_dtype(noise)
    x = _prefixed_start(noise, prefix, dtype)
    st = prefix_steps(steps, *noise.shape[:2], prefix.shape[1], noise.device, dtype)
    for t, dt in zip(st.starts, st.dts):
        v = checked_call(velocity, x, t, dtype=dtype, name="velocity")
        x = torch.addcmul(x, v, st.live, value=dt)          # the committed rows stay clean: they never move
    return x.to(noise.dtype)


def sample_meanflow_prefix(avg_velocity: AvgVelocity, noise: Tensor, prefix: Tensor, steps: int = 1) -> Tensor:
    """MeanFlow's K-step sampler x_r = x_t + (r − t)·u(x_t, t, r) with the committed rows `prefix`
    [B, d, D] held clean at t = r = 1; K network calls (one at K = 1), the prefix exact."""
    dtype = compute_dtype(noise)
    x = _prefixed_start(noise, prefix, dtype)
    st = prefix_steps(steps, *noise.shape[:2], prefix.shape[1], noise.device, dtype)
    for t, r, dt in zip(st.starts, st.ends, st.dts):
        u = checked_call(avg_velocity, x, t, r, dtype=dtype, name="avg_velocity")
        x = torch.addcmul(x, u, st.live, value=dt)
    return x.to(noise.dtype)
