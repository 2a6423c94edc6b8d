"""Training-time real-time chunking (Black, Ren, Equi, Levine 2025, arXiv 2512.05964), over callables.

The network learns to continue a committed prefix. In training, the first d actions of a chunk
are given clean — at flow time t = 1 (and r = 1 for MeanFlow), the data end of our convention —
while the rest of the chunk is noised at the sampled time as usual, and the loss covers only the
rest. The network therefore needs times per action token, [B, H] (`ActionExpert.forward`).
d is drawn per training row, uniformly on 0..max_delay (`sample_delays`): every delay the
controller may meet, d = 0 included, is seen equally often, so the same weights sample
without a prefix as well.

At inference the d actions the robot executes while the next chunk is computed are fed in as the
clean prefix at every step of the sampler (`sample_ode_prefix`, `sample_meanflow_prefix`): the
returned chunk keeps them exactly, costs the same network calls as a plain chunk, and works at any
number of steps, MeanFlow's one included. Nothing outside the prefix is pulled towards the previous
chunk: the rest follows the network's own conditional given the prefix.

DDPM is not offered (the policy refuses it): its sampler, DPM-Solver++, runs on one time per sample.
"""

from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor

from .paths import AvgVelocity, Velocity, check_chunk, checked_call, compute_dtype, resolve_steps

KEEP, CLEAN = "rtc_keep", "rtc_clean"      # the keyword arguments `with_clean_prefix` consumes


def check_max_delay(max_delay, horizon: int, name: str = "rtc_max_delay") -> int:
    """`max_delay` as an int in [0, horizon): some rows of every chunk must remain to learn."""
    if isinstance(max_delay, bool) or not isinstance(max_delay, int) or not 0 <= max_delay < horizon:
        raise ValueError(f"{name}: expected an integer number of control steps in [0, {horizon - 1}] "
                         f"(below the chunk length {horizon}), got {max_delay!r}")
    return max_delay


def sample_delays(batch: int, max_delay: int, generator: Optional[torch.Generator] = None,
                  device=None) -> Tensor:
    """Delays d [B] (int64), uniform on 0..max_delay."""
    return torch.randint(0, max_delay + 1, (batch,), generator=generator, device=device)


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


def _prefixed_start(noise: Tensor, prefix: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """(x0 [B, H, D], keep [B, H], clean [B, H, D]) for a normalised prefix [B, d, D]."""
    check_chunk(noise, "noise")
    B, H, D = noise.shape
    if not isinstance(prefix, Tensor) or prefix.dim() != 3 or prefix.shape[0] != B or prefix.shape[2] != D \
            or prefix.shape[1] >= H:
        got = tuple(prefix.shape) if isinstance(prefix, Tensor) else type(prefix).__name__
        raise ValueError(f"prefix: expected the committed actions [B={B}, d < {H}, D={D}], got {got}")
    d = prefix.shape[1]
    keep = prefix_mask(torch.full((B,), d, device=noise.device), H)                  # [B, H]
    clean = torch.zeros(B, H, D, device=noise.device, dtype=dtype)
    clean[:, :d] = prefix.to(dtype)
    x = torch.where(keep[..., None], clean, noise.to(dtype))
    return x, keep, clean


def sample_ode_prefix(velocity: Velocity, noise: Tensor, prefix: Tensor, steps: int = 10) -> Tensor:
    """Euler from noise (t = 0) to data (t = 1) with the committed rows `prefix` [B, d, D] held clean at
    t = 1 on every step (`velocity` takes times per token [B, H]); K network calls, the prefix exact."""
    dtype = compute_dtype(noise)
    x, keep, clean = _prefixed_start(noise, prefix, dtype)
    st = resolve_steps(steps, None, noise, dtype)
    live = (~keep)[..., None].to(dtype)                # the prefix rows of x stay clean: they never move
    for t, dt in zip(st.starts, st.dts):
        v = checked_call(velocity, x, token_times(t, keep), dtype=dtype, name="velocity")
        x = torch.addcmul(x, v, live, value=dt)
    return x.to(noise.dtype)


def sample_meanflow_prefix(avg_velocity: AvgVelocity, noise: Tensor, prefix: Tensor, steps: int = 1) -> Tensor:
    """MeanFlow's K-step sampler x_r = x_t + (r − t)·u(x_t, t, r) with the committed rows `prefix`
    [B, d, D] held clean at t = r = 1; K network calls (one at K = 1), the prefix exact."""
    dtype = compute_dtype(noise)
    x, keep, clean = _prefixed_start(noise, prefix, dtype)
    st = resolve_steps(steps, None, noise, dtype)
    live = (~keep)[..., None].to(dtype)
    for t, r, dt in zip(st.starts, st.ends, st.dts):
        u = checked_call(avg_velocity, x, token_times(t, keep), token_times(r, keep), dtype=dtype,
                         name="avg_velocity")
        x = torch.addcmul(x, u, live, value=dt)
    return x.to(noise.dtype)
