"""The policy seen as a stochastic chain: building the fine-tuning policy, sampling and
re-scoring chains with a chosen log-prob reduction, and squashing into the env's box.

`ActionDecoderPolicy.sample` sums log-probs over the chunk; PPO needs the reduction as an
option and SAC needs the chain with gradients and its ε-form density, so sampling here calls
`flows.sample_sde` on the policy's bound velocity.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Mapping, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from ..flows import SDEResult, sample_sde
from ..policy import ActionDecoderPolicy


def finetune_policy(bc: ActionDecoderPolicy, sigma: float, learn_sigma: bool, steps: int,
                    schedule: str = "explore", extra: Optional[dict] = None, squash: bool = False) -> ActionDecoderPolicy:
    """A copy of a BC policy that samples with an SDE: σ(t) = a·√((1−t)/t) ("explore") or a
    ("fixed"), a = `sigma`, times a learnable multiplier (starting at exactly 1) when
    `learn_sigma`; K = `steps`, for the SDE (`flow_sde_num_steps`) and the ODE alike
    (`num_inference_timesteps`: fine-tuning evaluates its deterministic policy at that K too).

    The saved config has flow_sde_use=True so `action-decoder eval` samples the chain that was
    optimised by default (`--sampler ode` gives the deterministic policy), and `action_squash` =
    `squash` (SAC executes tanh-squashed actions, `squash_to_box`), so it executes what was trained.
    """
    if bc.config.decoder_type == "DDPM":
        raise ValueError("--checkpoint: RL fine-tuning needs a flow_matching or mean_flow decoder (its SDE "
                         "sampler has per-step densities); this checkpoint is decoder_type='DDPM'")
    cfg = replace(bc.config, flow_sde_use=True, flow_sde_mode=schedule, flow_sde_s_churn=float(sigma),
                  flow_sde_learn_sigma=bool(learn_sigma), flow_sde_sigma_init=1.0,
                  num_inference_timesteps=int(steps), flow_sde_num_steps=int(steps), flow_sde_return_logprob=False,
                  action_squash=bool(squash),
                  extra={**bc.config.extra, **(extra or {})})
    policy = ActionDecoderPolicy(cfg)
    weights = {k: v for k, v in bc.state_dict().items() if not k.startswith("sigma.")}
    missing, unexpected = policy.load_state_dict(weights, strict=False)
    if unexpected or any(not k.startswith("sigma.") for k in missing):
        raise ValueError(f"--checkpoint: weights do not fit the fine-tuning policy (missing {missing[:5]}, "
                         f"unexpected {unexpected[:5]})")
    return policy.to(next(bc.parameters()).device)


def reduce_step_log_probs(lp: Tensor, reduce: str, executed: Optional[int | Tensor] = None) -> Tensor:
    """Per-element log-probs [B, K, H, D] -> per-step [B, K], summed or averaged over the chunk.

    With `executed` (one count, or one per row [B]), the last step keeps only the chunk's first
    `executed` rows: the others are never executed and nothing later depends on them, so their
    noise is independent of the reward and dropping their terms removes variance from the policy
    gradient without bias. Earlier steps keep every row: their noise reaches the executed rows
    through attention.
    """
    B, K, H = lp.shape[:3]
    if executed is None or (not isinstance(executed, Tensor) and executed >= H):
        return lp.sum((-2, -1)) if reduce == "sum" else lp.mean((-2, -1))
    rows = torch.as_tensor(executed, device=lp.device).reshape(-1, 1)                    # [B or 1, 1]
    keep = torch.ones(B, K, H, dtype=lp.dtype, device=lp.device)                         # [B, K, H]
    keep[:, -1] = (torch.arange(H, device=lp.device) < rows).to(lp.dtype)
    total = (lp * keep[..., None]).sum((-2, -1))
    return total if reduce == "sum" else total / (keep.sum(-1) * lp.shape[-1])


def step_numel(chain_shape, executed: Optional[int | Tensor] = None) -> Tensor:
    """Elements each step's log-prob counts [B or 1, K] for chains of shape [B, K+1, H, D]: H·D,
    and `executed`·D on the last step (`reduce_step_log_probs`). With `reduce="mean"` a per-step
    log-prob times this is the summed one, the true density's."""
    K, H, D = chain_shape[1] - 1, chain_shape[2], chain_shape[3]
    rows = torch.full((1, K), float(H)) if executed is None else torch.as_tensor(
        executed, dtype=torch.float32).reshape(-1, 1).clamp(max=H).expand(-1, K).clone()
    rows[:, :-1] = H
    return rows * D


def sample_chain(policy: ActionDecoderPolicy, batch: Mapping, steps: int, generator: Optional[torch.Generator],
                 reduce: str = "sum", logprob: str = "full", noise: Optional[Tensor] = None,
                 executed: Optional[int] = None) -> SDEResult:
    """One SDE chain per row, in normalised action units, with per-step log-probs [B, K]
    (`reduce_step_log_probs`; differentiable: wrap in no_grad for rollouts)."""
    cfg = policy.config
    if noise is None:
        b = batch["state"].shape[0]
        noise = torch.randn((b, cfg.action_chunk_size, cfg.action_dim), generator=generator,
                            device=batch["state"].device)
    res = sample_sde(policy.bind(batch).flow_velocity, noise, steps, policy.sigma, generator=generator,
                     return_logprob=True, logprob=logprob, clip_t=cfg.flow_sde_clip_t, reduce="none")
    res.step_log_probs = reduce_step_log_probs(res.step_log_probs, reduce, executed)
    res.log_prob = res.step_log_probs.sum(1)
    return res


def rescore_chain(policy: ActionDecoderPolicy, batch: Mapping, chain: Tensor, grid: Tensor,
                  reduce: str = "sum", executed: Optional[int | Tensor] = None) -> Tensor:
    """Per-step log-probs [B, K] of stored chains under the current weights and σ."""
    return reduce_step_log_probs(policy.chain_log_prob(batch, chain, grid, reduce="none"), reduce, executed)


def squash_to_box(x: Tensor, normalizer) -> tuple[Tensor, Tensor]:
    """Env-unit actions tanh(unnormalise(x)) ∈ (−1, 1) and log|det ∂a/∂x| [B] for x [B, H, D].

    The squash acts once, after the last step, on *environment* units: squashing the
    normalised chunk (`sample_sde(squash=True)`) would bound it to mean ± 1 std of the
    demonstrations, not to Meta-World's [−1, 1] box.
    """
    zero = torch.zeros(x.shape[-1], dtype=x.dtype, device=x.device)
    scale = normalizer.unnormalize(zero + 1) - normalizer.unnormalize(zero)          # [D]
    u = normalizer.unnormalize(x)
    # log(1 − tanh²u) = 2·(log 2 − u − softplus(−2u)), stable for large |u|.
    log_det = 2 * (math.log(2) - u - F.softplus(-2 * u)) + scale.abs().log()
    return torch.tanh(u), log_det.sum((-2, -1))
