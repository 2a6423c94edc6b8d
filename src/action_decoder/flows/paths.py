"""The straight path between noise and data, time grids, and the checks every sampler shares.

Convention (the whole library): t = 0 is the Gaussian prior, t = 1 is data,
    z_t = (1 − t)·e + t·a,   v = dz_t/dt = a − e,
and on this path the score is  ∇log p_t(x) = (t·v(x, t) − x) / (1 − t).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Union

import torch
from torch import Tensor

Velocity = Callable[[Tensor, Tensor], Tensor]            # v(x [B,H,D], t [B] or [B,H]) -> [B,H,D]
AvgVelocity = Callable[[Tensor, Tensor, Tensor], Tensor]  # u(x, t, r: [B] or [B,H]) -> [B,H,D]


def time_like(t: Tensor, x: Tensor) -> Tensor:
    """A time per sample [B] or per token [B, H] shaped to broadcast over x [B, H, D]."""
    return t.reshape(*t.shape, *([1] * (x.dim() - t.dim()))) if t.dim() else t.reshape(*([1] * x.dim()))


def time_grid(steps: int, device=None, dtype: torch.dtype = torch.float32) -> Tensor:
    """Uniform ascending grid `[steps + 1]` from 0 (noise) to 1 (data)."""
    check_steps(steps)
    return torch.linspace(0.0, 1.0, steps + 1, device=device, dtype=dtype)


def interpolate(noise: Tensor, actions: Tensor, t: Tensor) -> Tensor:
    """z_t = (1 − t)·e + t·a with t `[B]` (or per token, `[B, H]`) broadcast over the chunk."""
    t = time_like(t, actions)
    return (1 - t) * noise + t * actions


def score_from_velocity(x: Tensor, v: Tensor, t: Tensor, clip_t: float = 0.0) -> Tensor:
    """∇log p_t(x) = (t·v − x) / (1 − t), with 1 − t floored at `clip_t`."""
    t = time_like(t, x)
    return (t * v - x) / (1 - t).clamp_min(clip_t)


def velocity_from_sample(x: Tensor, t: Tensor, sample: Tensor, clip: float = 0.05) -> Tensor:
    """(x̂ − x) / (1 − t): the velocity that carries x at time t straight to the clean chunk x̂ at
    t = 1, with 1 − t floored at `clip`. A head that predicts x̂ instead of the velocity need not
    reproduce the noise in its output: with x̂ exact, one Euler step already lands on it."""
    dtype = compute_dtype(x)
    t = time_like(t.to(dtype), x)
    return (sample.to(dtype) - x.to(dtype)) / (1 - t).clamp_min(clip)


Generators = Union[torch.Generator, Sequence[torch.Generator], None]
"""One generator for the whole batch, or one per row (row b draws from generator[b] only, so a
row's samples do not depend on which other rows share its batch)."""


def randn_rows(batch: int, shape: tuple, generator: Generators = None, device=None,
               dtype: torch.dtype = torch.float32) -> Tensor:
    """Standard normal draws [batch, *shape] from one generator or from one generator per row."""
    if generator is None or isinstance(generator, torch.Generator):
        return torch.randn((batch, *shape), generator=generator, device=device, dtype=dtype)
    gens = list(generator)
    if len(gens) != batch or not all(isinstance(g, torch.Generator) for g in gens):
        raise ValueError(f"generator: expected a torch.Generator or a list of {batch} (one per row), got "
                         f"{len(gens)} item(s) of types {sorted({type(g).__name__ for g in gens})}")
    return torch.stack([torch.randn(shape, generator=g, device=device, dtype=dtype) for g in gens])


def compute_dtype(noise: Tensor) -> torch.dtype:
    """Integrate in float32 whatever the network returns; float64 when the noise is float64."""
    return torch.float64 if noise.dtype == torch.float64 else torch.float32


def check_steps(steps, name: str = "steps") -> None:
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"{name}: expected a positive integer number of steps, got {steps!r}")


def check_chunk(x: Tensor, name: str = "noise") -> None:
    if not isinstance(x, Tensor) or x.dim() != 3:
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"{name}: expected a tensor of shape [B, H, D], got {got}")
    if not x.is_floating_point():
        raise ValueError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


@dataclass(frozen=True)
class Steps:
    """A grid [K+1] with what the loops read each step: Δt as host floats, and the start and
    end times of each step as [B] tensors (built once, not sliced inside the loop)."""

    grid: Tensor
    dts: tuple
    starts: tuple
    ends: tuple


def _steps(grid: Tensor, batch: int) -> Steps:
    starts = grid[:-1, None].expand(-1, batch).clone()                          # [K, B], not views of grid
    ends = grid[1:, None].expand(-1, batch).clone()                             # [K, B]
    return Steps(grid, tuple(grid.diff().tolist()), tuple(starts.unbind(0)), tuple(ends.unbind(0)))


def _untouched(st: Steps) -> bool:
    """No callable changed the cached step times in place (rows share their block's version counter)."""
    return st.grid._version == 0 and st.starts[0]._version == 0 and st.ends[0]._version == 0


@functools.lru_cache(maxsize=64)
def _uniform_steps(steps: int, batch: int, device: torch.device, dtype: torch.dtype) -> Steps:
    # Shared between calls: a sampling call then costs no grid construction, no slicing and,
    # on a GPU, no host sync for the step sizes. Built outside inference mode, so that a grid
    # first made under `torch.inference_mode()` still serves later differentiable calls; the
    # samplers hand callers a clone of `grid`, never the cached tensor.
    with torch.inference_mode(False):
        return _steps(time_grid(steps, device=device, dtype=dtype), batch)


def resolve_steps(steps: int, grid: Optional[Tensor], like: Tensor, dtype: torch.dtype) -> Steps:
    """The grid a sampler integrates on: `grid` if given (validated), else uniform with `steps`."""
    if grid is None:
        check_steps(steps)
        st = _uniform_steps(steps, like.shape[0], like.device, dtype)
        if not _untouched(st):        # a callable wrote into its t: rebuild, never hand the edit on
            _uniform_steps.cache_clear()
            st = _uniform_steps(steps, like.shape[0], like.device, dtype)
        return st
    grid = torch.as_tensor(grid)
    if grid.dim() != 1 or grid.numel() < 2:
        raise ValueError(f"grid: expected an ascending 1-D time grid [K+1] from 0 to 1, "
                         f"got shape {tuple(grid.shape)}")
    grid = grid.to(device=like.device, dtype=dtype)
    # One host sync per call, only for a user-given grid.
    if not bool((grid.diff() > 0).all()) or float(grid[0]) < 0 or float(grid[-1]) > 1:
        raise ValueError(f"grid: expected strictly ascending times within [0, 1], "
                         f"got {grid.tolist()}")
    return _steps(grid, like.shape[0])


def checked_call(fn: Callable, x: Tensor, *args: Tensor, dtype: torch.dtype, name: str) -> Tensor:
    """Call a network callable and bring its output to the integration dtype."""
    out = fn(x, *args)
    if not isinstance(out, Tensor) or out.shape != x.shape:
        got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
        raise ValueError(f"{name}: expected an output of the input's shape {tuple(x.shape)}, got {got}")
    return out.to(dtype)
