"""DDPM: training with diffusers' `DDPMScheduler.add_noise`, sampling with DPM-Solver++.

diffusers counts integer timesteps 0 (data) … T−1 (noise); callables receive those integer
timesteps `[B]` — the policy maps them onto the library's t ∈ [0, 1] (t = 1 − step/T).
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Mapping, Optional

import torch
from torch import Tensor

from ..config import DecoderConfig
from .paths import check_chunk, check_steps, checked_call, compute_dtype

ModelOutput = Callable[[Tensor, Tensor], Tensor]   # out(x [B,H,D], timestep int [B]) -> [B,H,D]

# diffusers' advice for the cosine schedule: its last steps have SNR ≈ 0, where turning an
# ε-prediction into x0 divides by √ᾱ ≈ 5e-5; clipping λ = log(α/σ) at −5.1 starts there.
_LAMBDA_MIN = {"squaredcos_cap_v2": -5.1}
_local = threading.local()   # schedulers are stateful: one per thread and configuration


def _key(config: DecoderConfig):
    return (config.num_train_timesteps, config.beta_schedule, config.prediction_type)


def _cached(kind: str, config: DecoderConfig, **kwargs):
    """One scheduler per thread and configuration; diffusers is imported on first use (slow)."""
    cache = _local.__dict__.setdefault("schedulers", {})
    key = (kind, _key(config))
    if key not in cache:
        import diffusers
        cache[key] = getattr(diffusers, kind)(num_train_timesteps=config.num_train_timesteps,
                                              beta_schedule=config.beta_schedule,
                                              prediction_type=config.prediction_type, **kwargs)
    return cache[key]


def training_scheduler(config: DecoderConfig):
    """diffusers' DDPMScheduler for `add_noise`."""
    return _cached("DDPMScheduler", config, clip_sample=config.clip_sample)


def inference_scheduler(config: DecoderConfig):
    """diffusers' DPMSolverMultistepScheduler; final_sigmas_type="zero" makes 1 step return x0."""
    return _cached("DPMSolverMultistepScheduler", config, algorithm_type="dpmsolver++",
                   solver_order=2, final_sigmas_type="zero",
                   lambda_min_clipped=_LAMBDA_MIN.get(config.beta_schedule, -float("inf")))


def ddpm_loss(model_output: ModelOutput, actions: Tensor, config: DecoderConfig,
              generator: Optional[torch.Generator] = None,
              cond: Optional[Mapping[str, Any]] = None) -> Tensor:
    """‖out − target‖² with target ε or the clean sample, as `config.prediction_type` says."""
    check_chunk(actions, "actions")
    a = actions.float() if actions.dtype != torch.float64 else actions
    sched = training_scheduler(config)
    steps = torch.randint(0, config.num_train_timesteps, (a.shape[0],), generator=generator,
                          device=a.device)
    noise = torch.randn(a.shape, generator=generator, device=a.device, dtype=a.dtype)
    noisy = sched.add_noise(a, noise, steps)
    out = checked_call(lambda x, s: model_output(x, s, **(cond or {})), noisy, steps, dtype=a.dtype,
                       name="model_output")
    target = noise if config.prediction_type == "epsilon" else a
    return (out - target).square().mean()


def sample_ddpm(model_output: ModelOutput, noise: Tensor, config: DecoderConfig,
                steps: Optional[int] = None) -> Tensor:
    """DPM-Solver++ (2nd order) from pure noise; `steps` defaults to num_inference_timesteps.

    With `config.clip_sample` the x0 prediction is clamped to [−1, 1] at every step.
    """
    check_chunk(noise, "noise")
    steps = config.num_inference_timesteps if steps is None else steps
    check_steps(steps)
    if steps > config.num_train_timesteps:
        raise ValueError(f"steps: expected at most num_train_timesteps={config.num_train_timesteps}, "
                         f"got {steps}")
    dtype = compute_dtype(noise)
    sched = inference_scheduler(config)
    sched.set_timesteps(steps, device=noise.device)   # also resets the multistep history
    alphas = sched.alphas_cumprod.to(device=noise.device, dtype=dtype) if config.clip_sample else None
    B = noise.shape[0]
    x = noise.to(dtype)
    for step in sched.timesteps:
        ts = step.expand(B)
        out = checked_call(model_output, x, ts, dtype=dtype, name="model_output")
        if config.clip_sample:
            out = _clip_x0(out, x, alphas[step], config.prediction_type)
        x = sched.step(out, step, x).prev_sample
    return x.to(noise.dtype)


def _clip_x0(out: Tensor, x: Tensor, alpha_bar: Tensor, prediction_type: str) -> Tensor:
    if prediction_type == "sample":
        return out.clamp(-1, 1)
    x0 = ((x - (1 - alpha_bar).sqrt() * out) / alpha_bar.sqrt()).clamp(-1, 1)
    return (x - alpha_bar.sqrt() * x0) / (1 - alpha_bar).sqrt()
