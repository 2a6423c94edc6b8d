"""Noise-space RL (DSRL, arXiv 2506.15799): SAC over the initial noise of a frozen decoder.

The BC decoder and its deterministic sampler stay as trained; a `NoiseActor` chooses the
noise chunk w [H, D] that the sampler turns into the action chunk, so the environment seen by
the learner takes noise as its action. Two critics are offered (`critic`):

- "noise" (DSRL-SAC): Q(s, w) learnt by TD on the stored noise; no decoder call in an update.
- "action" (DSRL-NA, noise aliasing): Q_A(s, a) learnt by TD on the executed actions, whose
  target decodes the actor's next noise, and Q_W(s, w) regressed onto Q_A(s, decode(s, w)) for
  noise drawn from the actor and from the prior: noises that decode to the same chunk get the
  same value. Each update decodes two batches.

Each critic is an ensemble (`critics`, 2 by default): TD targets take the minimum of two members
drawn at random (REDQ, arXiv 2101.05982; with two members, the twin minimum), and the actor reads
the ensemble's mean when it has more than two members, the twin minimum otherwise.

The actor maximises that Q(s, w) − α·log π(w | s) (log-probs per noise element, α tuned to hold
the entropy per element at a target), plus an optional trust region `kl_coef`·KL(π(·|s) ‖ N(0, I))
that keeps its Gaussian near the noise the decoder was trained on.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from ..noise_actor import kl_to_prior
from ..policy import ActionDecoderPolicy
from .critics import subset_min
from .sac import ReplayBuffer, Temperature


def dsrl_policy(bc: ActionDecoderPolicy, hidden: int, bound: float, steps: Optional[int],
                extra: Optional[dict] = None) -> ActionDecoderPolicy:
    """A copy of a BC policy with a fresh noise actor (the decoder's weights frozen); it samples
    with the decoder's deterministic sampler at `steps` (None: the checkpoint's own)."""
    if bc.noise_actor is not None:
        raise ValueError("--checkpoint: this policy already has a noise actor (it was fine-tuned with --algo dsrl); "
                         "pass the BC checkpoint it started from")
    cfg = replace(bc.config, noise_actor_hidden=int(hidden), noise_actor_bound=float(bound), flow_sde_use=False,
                  flow_sde_return_logprob=False,
                  num_inference_timesteps=int(steps or bc.config.num_inference_timesteps),
                  extra={**bc.config.extra, **(extra or {})})
    policy = ActionDecoderPolicy(cfg, load_pretrained=False)
    missing, unexpected = policy.load_state_dict(bc.state_dict(), strict=False)
    if unexpected or any(not k.startswith("noise_actor.") for k in missing):
        raise ValueError(f"--checkpoint: weights do not fit the fine-tuning policy (missing {missing[:5]}, "
                         f"unexpected {unexpected[:5]})")
    policy.model.requires_grad_(False)
    policy.sigma.requires_grad_(False)
    return policy.to(next(bc.parameters()).device).eval()


def decode(policy: ActionDecoderPolicy, batch: dict, noise: Tensor) -> Tensor:
    """The frozen decoder's deterministic chunk [B, H, D] (env units) for the noise [B, H, D]."""
    with torch.no_grad():
        return policy.sample(batch, noise=noise, return_logprob=False).actions


def noise_actor_fn(policy: ActionDecoderPolicy, make_batch: Callable[[Tensor], dict], generator: torch.Generator):
    """The rollout's act function: noise from the stochastic actor, chunk from the frozen decoder;
    records the noise [H, D] and the executed actions [n, D]."""
    n_exec = policy.config.n_action_steps

    @torch.no_grad()
    def act(states: np.ndarray, progress: np.ndarray):
        batch = make_batch(torch.from_numpy(states))
        noise = policy.noise_actor.sample(**policy.noise_actor_inputs(batch), generator=generator)[0]
        actions = decode(policy, batch, noise)
        return actions.numpy(), {"noise": noise, "actions": actions[:, :n_exec]}

    return act


def _critic_step(q, optimizer, pred_target: tuple[tuple[Tensor, ...], Tensor], grad_clip: float) -> float:
    preds, target = pred_target
    loss = sum((p - target).square().mean() for p in preds)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(q.parameters(), grad_clip)
    optimizer.step()
    return float(loss.detach())


def _polyak(q, q_target, tau: float) -> None:
    with torch.no_grad():
        for p, tp in zip(q.parameters(), q_target.parameters()):
            tp.lerp_(p, tau)


def dsrl_update(policy: ActionDecoderPolicy, critics: dict, temperature: Temperature, optimizers: dict,
                buffer: ReplayBuffer, make_batch: Callable[[Tensor], dict], cfg, generator: torch.Generator) -> dict:
    """One critic, actor and temperature step on a replay batch.

    `critics`: {"q": Q(s, w), "q_target"} and, with `cfg.noise_critic == "action"`, {"q_action":
    Q_A(s, a), "q_action_target"}; `optimizers`: "q", "actor", "alpha" (and "q_action").
    """
    actor, alpha = policy.noise_actor, temperature.alpha
    b = buffer.sample(cfg.sac_batch_size, generator)
    n = b["actions"].shape[1]
    now, nxt = make_batch(b["state"]), make_batch(b["next_state"])
    s, s2 = policy.noise_actor_inputs(now), policy.noise_actor_inputs(nxt)
    q, q_target = critics["q"], critics["q_target"]
    stats = {}
    with torch.no_grad():
        w2, logp2, _, _ = actor.sample(**s2, generator=generator)
        cont = cfg.gamma * (1 - b["done"].float())
    if cfg.noise_critic == "noise":
        with torch.no_grad():
            target = b["reward"] + cont * (subset_min(q_target(s2["state"], b["next_progress"], w2), 2, generator)
                                           - alpha * logp2)
        stats["q_loss"] = _critic_step(q, optimizers["q"], (q(s["state"], b["progress"], b["noise"]), target),
                                       cfg.grad_clip)
    else:
        qa, qa_target = critics["q_action"], critics["q_action_target"]
        with torch.no_grad():
            a2 = decode(policy, nxt, w2)[:, :n]
            target = b["reward"] + cont * (subset_min(qa_target(s2["state"], b["next_progress"], a2), 2, generator)
                                           - alpha * logp2)
        stats["q_action_loss"] = _critic_step(qa, optimizers["q_action"],
                                              (qa(s["state"], b["progress"], b["actions"]), target), cfg.grad_clip)
        _polyak(qa, qa_target, cfg.tau)
        with torch.no_grad():   # aliasing: half the rows' noise from the actor, half from the prior N(0, I)
            w = actor.sample(**s, generator=generator)[0]
            half = len(w) // 2
            w[half:] = actor.bounded(torch.randn(w[half:].shape, generator=generator))
            target = subset_min(qa(s["state"], b["progress"], decode(policy, now, w)[:, :n]), 2, generator)
        stats["q_loss"] = _critic_step(q, optimizers["q"], (q(s["state"], b["progress"], w), target), cfg.grad_clip)

    w, logp, mean, log_std = actor.sample(**s, generator=generator)                  # [B, H, D], [B]
    qs = q(s["state"], b["progress"], w)
    q_pi = subset_min(qs, 2, generator) if len(qs) == 2 else torch.stack(qs).mean(0)   # REDQ: the ensemble's mean
    loss = (alpha * logp - q_pi).mean()
    kl = kl_to_prior(mean, log_std)                                                   # [B]
    if cfg.kl_coef > 0:
        loss = loss + cfg.kl_coef * kl.mean()
    optimizers["actor"].zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(actor.parameters(), cfg.grad_clip)
    optimizers["actor"].step()
    if cfg.alpha_lr > 0:
        optimizers["alpha"].zero_grad(set_to_none=True)
        temperature.loss(logp).backward()
        optimizers["alpha"].step()
    if cfg.noise_critic == "noise":
        _polyak(q, q_target, cfg.tau)
    stats.update({"q": float(q_pi.detach().mean()), "entropy_per_dim": float(-logp.detach().mean()),
                  "alpha": float(alpha), "actor_loss": float(loss.detach()), "kl_prior": float(kl.detach().mean()),
                  "noise_std": float(log_std.detach().exp().mean())})
    return stats
