"""Compiled PyTorch paths: `torch.compile` of the whole deterministic sampler and of the network.

`compile_sampler` compiles `export.ChunkSampler` (the graph `export_onnx` writes: normalisation, the K
network calls unrolled, un-normalisation, squash; with `rtc=True`, trained real-time chunking with the
delay an input) for fixed input shapes; on a CUDA device its mode
defaults to "reduce-overhead" (CUDA graphs: one launch per chunk), elsewhere to inductor's default.
`compile_network` compiles the Action Expert in place for training (`train --compile`): weights,
state_dict keys and checkpoints are unchanged.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Mapping, Optional

import torch
from torch import Tensor

from .export import ChunkSampler, export_refusal, rtc_refusal

if TYPE_CHECKING:
    from .policy import ActionDecoderPolicy


def check_compile() -> None:
    """Refuse `--compile` in one line where inductor cannot build kernels on this machine."""
    import shutil

    if not hasattr(torch, "compile"):
        raise ValueError(f"--compile: torch {torch.__version__} has no torch.compile")
    if not torch.cuda.is_available() and shutil.which("gcc") is None and shutil.which("cc") is None:
        raise ValueError("--compile: torch.compile builds CPU kernels with a C compiler, and none (gcc, cc) is on PATH")


def _mode(policy: "ActionDecoderPolicy", mode: Optional[str]) -> Optional[str]:
    device = next(policy.parameters()).device
    return mode if mode is not None else ("reduce-overhead" if device.type == "cuda" else None)


def compile_sampler(policy: "ActionDecoderPolicy", sampler: Optional[str] = None, steps: Optional[int] = None,
                    mode: Optional[str] = None, backend: str = "inductor", rtc: bool = False) -> Callable[..., Tensor]:
    """fn(batch, noise [B, H, D]) → chunk [B, H, D] (env units): `predict_action_chunk(batch, noise=noise)`
    as one compiled graph. `batch` holds "state" and, where the policy uses them, "context" (+
    "context_mask") and "images". `mode`: torch.compile's (None: "reduce-overhead" on CUDA, else the
    default); `backend`: torch.compile's. A new batch size or context length compiles once more.

    `rtc=True` (checkpoints trained with `rtc_max_delay` M > 0): fn(batch, noise, prev_chunk=None, delay=0)
    is `sample(batch, noise=noise, prev_chunk=prev_chunk, delay=delay, rtc_mode="trained").actions`, the
    delay (0..M) an input of the graph, so every delay replays the same compiled graph."""
    refusal = export_refusal(policy, sampler) or (rtc_refusal(policy, sampler) if rtc else None)
    if refusal:
        raise ValueError(refusal)
    module = ChunkSampler(policy, sampler, steps, rtc=rtc).eval()
    mode = _mode(policy, mode) if backend == "inductor" else None
    compiled = torch.compile(module, mode=mode, backend=backend, fullgraph=True, dynamic=False)
    max_delay = module.max_delay
    delay_inputs: dict[tuple, Tensor] = {}                    # (batch size, delay, device) -> the delay input

    @torch.no_grad()
    def sample(batch: Mapping[str, Any], noise: Tensor, prev_chunk: Optional[Tensor] = None, delay: int = 0) -> Tensor:
        policy._check_noise(batch, noise)
        device = noise.device
        ctx, mask, images = batch.get("context"), batch.get("context_mask"), batch.get("images")
        if ctx is not None and mask is None:
            mask = torch.ones(ctx.shape[:2], dtype=torch.bool, device=device)
        args = (batch["state"].to(device), noise, ctx, None if mask is None else mask.bool(), images)
        if not rtc:
            if prev_chunk is not None or delay:
                raise ValueError("prev_chunk: this compiled sampler has no real-time chunking; compile it with rtc=True "
                                 "(a checkpoint trained with --rtc-max-delay)")
            return compiled(*args)
        b, _, dim = noise.shape
        delay = policy._check_prev_chunk(batch, prev_chunk, delay)
        if prev_chunk is None:
            prev_chunk = noise.new_zeros(b, 0, dim)
        if delay > max_delay:
            raise ValueError(f"delay: {delay} exceeds rtc_max_delay={max_delay}, the longest prefix this checkpoint "
                             f"was trained to continue")
        if prev_chunk.shape[1] >= max_delay:                  # the usual case: the committed rows, no copy
            committed = prev_chunk[:, :max_delay].to(noise).contiguous()                     # [B, M, D] env units
        else:
            committed = noise.new_zeros(b, max_delay, dim)
            committed[:, :prev_chunk.shape[1]] = prev_chunk.to(committed)
        delays = delay_inputs.get((b, delay, device))
        if delays is None:                                    # one per (batch size, delay, device), not one per chunk
            delays = delay_inputs[b, delay, device] = torch.full((b,), delay, dtype=torch.int64, device=device)
        return compiled(*args, committed, delays)

    sample.sampler, sample.steps, sample.rtc_max_delay = module.sampler, module.steps, max_delay
    return sample


def compile_network(policy: "ActionDecoderPolicy", mode: Optional[str] = None,
                    backend: str = "inductor") -> "ActionDecoderPolicy":
    """Compile the policy's network in place (`nn.Module.compile`) for training; returns the policy."""
    if policy.config.decoder_type == "mean_flow" and policy.config.meanflow_dudt == "jvp":
        raise ValueError("--compile: MeanFlow's meanflow_dudt='jvp' differentiates the network with "
                         "torch.func.jvp, which the compiled network does not support; use "
                         "meanflow_dudt='finite_difference' (the default) or drop --compile")
    policy.model.compile(mode=mode, backend=backend)
    return policy
