"""Noise-space RL (DSRL, arXiv 2506.15799): SAC over the initial noise of a frozen decoder.

The BC decoder and its deterministic sampler stay as trained; a `NoiseActor` chooses the
noise chunk w [H, D] that the sampler turns into the action chunk, so the environment seen by
the learner takes noise as its action. Two critics are offered (`critic`):

- "noise" (DSRL-SAC): Q(s, w) learnt by TD on the stored noise; no decoder call in an update.
- "action" (DSRL-NA, noise aliasing): Q_A(s, a) learnt by TD on the executed actions, whose
  target decodes the actor's next noise, and Q_W(s, w) regressed onto Q_A(s, decode(s, w)) for
  noise drawn from the actor and from the prior: noises that decode to the same chunk get the
  same value. Where the decoder runs is `alias_decodes`:
  - "update": at every update, two batches (the actor's next noise for Q_A's target, the actor's
    and the prior's noise at s for Q_W), exactly as above;
  - "iteration": once an iteration, for a pool of `POOL_SIZE` buffer transitions (`decode_pool`):
    the actor's next noise at s' and its chunk. That iteration's updates draw their batches from
    the pool, so Q_A's target reads the chunk of the actor as it was when the iteration began
    (one iteration behind, as a target network is a few hundred updates behind). Q_W regresses
    onto Q_A at the pool's pairs (s', w', a') and at pairs the rollout decoded when it acted: the
    executed noise and `PRIOR_PAIRS` prior noises per decision (the decoder is frozen, so a pair
    (s, w, decode(s, w)) never goes stale); member i of Q_W follows member i of Q_A, so that the
    actor's minimum over two members keeps Q_A's pessimism. No update calls the decoder.

Each critic is an ensemble (`critics`, 2 by default): TD targets take the minimum of two members
drawn at random (REDQ, arXiv 2101.05982; with two members, the twin minimum), and the actor reads
the ensemble's mean when it has more than two members, the twin minimum otherwise.

The actor maximises that Q(s, w) − α·log π(w | s) (log-probs per noise element, α tuned to hold
the entropy per element at a target), minus an optional trust region λ·KL(π(·|s) ‖ N(0, I)) that
keeps its Gaussian near the noise the decoder was trained on: a fixed weight λ = `kl_coef`, or a
Lagrange multiplier (`KLMultiplier`, LP-DS, arXiv 2606.01151) learnt so that the KL per element
stays at most `kl_target`.
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

PRIOR_PAIRS = 2
"""alias_decodes="iteration": prior noises N(0, I) (bounded) decoded per decision when the rollout acts."""
KL_MULTIPLIER_LR = 3e-2
"""Learning rate of the trust region's log multiplier (`KLMultiplier`), as SAC's log α."""
POOL_SIZE = 4096
"""alias_decodes="iteration": buffer transitions whose next noise is decoded once an iteration."""


class KLMultiplier(torch.nn.Module):
    """λ = exp(log λ) ≥ 0 of the trust region KL(π(·|s) ‖ N(0, I)) ≤ `target` (per noise element): gradient
    steps on its Lagrangian raise λ while the actor's KL is above the target and lower it below."""

    def __init__(self, target: float, initial: float = 1.0):
        super().__init__()
        self.log_lambda = torch.nn.Parameter(torch.tensor(float(initial)).log())
        self.register_buffer("target", torch.tensor(float(target)))

    @property
    def value(self) -> Tensor:
        return self.log_lambda.exp().detach()

    def loss(self, kl: Tensor) -> Tensor:
        """−log λ·(KL − target), KL the batch's mean per element (detached)."""
        return -self.log_lambda * (kl.detach().mean() - self.target)


def alias_mode(policy: ActionDecoderPolicy, requested: str) -> str:
    """`alias_decodes` resolved: "auto" decodes at every update when a chunk takes at most 2
    network calls (MeanFlow at 1 or 2 steps), once an iteration otherwise."""
    if requested != "auto":
        return requested
    return "update" if policy.config.num_inference_timesteps <= 2 else "iteration"


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


def noise_actor_fn(policy: ActionDecoderPolicy, make_batch: Callable[[Tensor], dict], generator: torch.Generator,
                   prior_pairs: int = 0):
    """The rollout's act function: noise from the stochastic actor, chunk from the frozen decoder;
    records the noise [H, D] and the executed actions [n, D], and with `prior_pairs` P > 0 that many
    prior noises [P, H, D] and their executed actions [P, n, D] ("prior_noise", "prior_actions"),
    decoded in the same call."""
    n_exec = policy.config.n_action_steps

    @torch.no_grad()
    def act(states: np.ndarray, progress: np.ndarray):
        batch = make_batch(torch.from_numpy(states))
        noise = policy.noise_actor.sample(**policy.noise_actor_inputs(batch), generator=generator)[0]  # [B, H, D]
        if not prior_pairs:
            actions = decode(policy, batch, noise)
            return actions.numpy(), {"noise": noise, "actions": actions[:, :n_exec]}
        b, p = len(noise), prior_pairs
        prior = policy.noise_actor.bounded(torch.randn((b, p, *noise.shape[1:]), generator=generator))  # [B, P, H, D]
        rows = torch.cat([noise[:, None], prior], 1).flatten(0, 1)                                    # [B(1+P), H, D]
        repeated = {k: v.repeat_interleave(1 + p, 0) if torch.is_tensor(v) else v for k, v in batch.items()}
        chunks = decode(policy, repeated, rows)
        chunks = chunks.unflatten(0, (b, 1 + p))                                                      # [B, 1+P, H, D]
        return chunks[:, 0].numpy(), {"noise": noise, "actions": chunks[:, 0, :n_exec],
                                      "prior_noise": prior, "prior_actions": chunks[:, 1:, :n_exec]}

    return act


def decode_pool(policy: ActionDecoderPolicy, buffer: ReplayBuffer, make_batch: Callable[[Tensor], dict],
                size: int, generator: torch.Generator, chunk: int = 512) -> dict:
    """`size` buffer transitions drawn uniformly with, at their next state s', the current actor's
    noise "next_noise" [N, H, D], its log-prob "next_logp" [N] and the executed part of its chunk
    "next_actions" [N, n, D], decoded `chunk` rows at a time."""
    pool = buffer.sample(size, generator)
    n = pool["actions"].shape[1]
    w2, logp2, a2 = [], [], []
    with torch.no_grad():
        for i in range(0, size, chunk):
            nxt = make_batch(pool["next_state"][i:i + chunk])
            w, logp = policy.noise_actor.sample(**policy.noise_actor_inputs(nxt), generator=generator)[:2]
            w2.append(w), logp2.append(logp), a2.append(decode(policy, nxt, w)[:, :n])
    return {**pool, "next_noise": torch.cat(w2), "next_logp": torch.cat(logp2), "next_actions": torch.cat(a2)}


def _critic_step(q, optimizer, pred_target: tuple[tuple[Tensor, ...], "Tensor | tuple[Tensor, ...]"],
                 grad_clip: float) -> float:
    """One step of the members' squared error to one shared target, or each to its own (a tuple)."""
    preds, target = pred_target
    targets = target if isinstance(target, tuple) else (target,) * len(preds)
    loss = sum((p - t).square().mean() for p, t in zip(preds, targets))
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
                buffer: ReplayBuffer, make_batch: Callable[[Tensor], dict], cfg, generator: torch.Generator,
                pool: Optional[dict] = None, multiplier: Optional[KLMultiplier] = None,
                update_actor: bool = True) -> dict:
    """One critic, actor and temperature step on a replay batch (and a step of the trust region's
    `multiplier`, with its optimizer "kl", when given; otherwise `cfg.kl_coef` weighs the KL).
    `update_actor=False` steps the critics only (a warm-up): the actor, α and the multiplier stay,
    and the stats are those of the actor as it is.

    `critics`: {"q": Q(s, w), "q_target"} and, with `cfg.noise_critic == "action"`, {"q_action":
    Q_A(s, a), "q_action_target"}; `optimizers`: "q", "actor", "alpha" (and "q_action"). `pool`:
    `decode_pool`'s, for the action critic with `alias_decodes="iteration"` (the batch is drawn from it,
    and the buffer holds "prior_noise" and "prior_actions"); None decodes at this update.
    """
    actor, alpha = policy.noise_actor, temperature.alpha
    if pool is None:
        b = buffer.sample(cfg.sac_batch_size, generator)
    else:
        idx = torch.randint(len(pool["reward"]), (cfg.sac_batch_size,), generator=generator)
        b = {k: v[idx] for k, v in pool.items()}
    n = b["actions"].shape[1]
    now, nxt = make_batch(b["state"]), make_batch(b["next_state"])
    s, s2 = policy.noise_actor_inputs(now), policy.noise_actor_inputs(nxt)
    q, q_target = critics["q"], critics["q_target"]
    stats = {}
    with torch.no_grad():
        if pool is None:            # a pool holds the actor's next noise already
            w2, logp2, _, _ = actor.sample(**s2, generator=generator)
        cont = cfg.gamma * (1 - b["done"].float())
    if cfg.noise_critic == "noise":
        with torch.no_grad():
            target = b["reward"] + cont * (subset_min(q_target(s2["state"], b["next_progress"], w2), 2, generator)
                                           - alpha * logp2)
        stats["q_loss"] = _critic_step(q, optimizers["q"], (q(s["state"], b["progress"], b["noise"]), target),
                                       cfg.grad_clip)
    elif pool is not None:
        qa, qa_target = critics["q_action"], critics["q_action_target"]
        with torch.no_grad():   # the pool's chunk at s' for the actor's next noise (decoded when the iteration began)
            target = b["reward"] + cont * (subset_min(qa_target(s2["state"], b["next_progress"], b["next_actions"]),
                                                      2, generator) - alpha * b["next_logp"])
        stats["q_action_loss"] = _critic_step(qa, optimizers["q_action"],
                                              (qa(s["state"], b["progress"], b["actions"]), target), cfg.grad_clip)
        _polyak(qa, qa_target, cfg.tau)
        with torch.no_grad():   # aliasing at decoded pairs: the executed one and a prior one at s, the actor's at s'
            pick = torch.randint(b["prior_noise"].shape[1], (len(target),), generator=generator)
            rows = torch.arange(len(target))
            w = torch.cat([b["noise"], b["prior_noise"][rows, pick], b["next_noise"]])        # [3B, H, D]
            a = torch.cat([b["actions"], b["prior_actions"][rows, pick], b["next_actions"]])  # [3B, n, D]
            state = torch.cat([s["state"], s["state"], s2["state"]])
            progress = torch.cat([b["progress"], b["progress"], b["next_progress"]])
            targets = qa(state, progress, a)
        stats["q_loss"] = _critic_step(q, optimizers["q"], (q(state, progress, w), targets), cfg.grad_clip)
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

    with torch.set_grad_enabled(update_actor):
        w, logp, mean, log_std = actor.sample(**s, generator=generator)              # [B, H, D], [B]
        qs = q(s["state"], b["progress"], w)
        q_pi = subset_min(qs, 2, generator) if len(qs) == 2 else torch.stack(qs).mean(0)   # REDQ: the ensemble's mean
        loss = (alpha * logp - q_pi).mean()
        kl = kl_to_prior(mean, log_std)                                               # [B]
        kl_weight = multiplier.value if multiplier is not None else cfg.kl_coef
        if kl_weight > 0:
            loss = loss + kl_weight * kl.mean()
    if update_actor:
        optimizers["actor"].zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(actor.parameters(), cfg.grad_clip)
        optimizers["actor"].step()
        if cfg.alpha_lr > 0:
            optimizers["alpha"].zero_grad(set_to_none=True)
            temperature.loss(logp).backward()
            optimizers["alpha"].step()
        if multiplier is not None:
            optimizers["kl"].zero_grad(set_to_none=True)
            multiplier.loss(kl).backward()
            optimizers["kl"].step()
    if multiplier is not None:
        stats["kl_multiplier"] = float(kl_weight)
    if cfg.noise_critic == "noise":
        _polyak(q, q_target, cfg.tau)
    stats.update({"q": float(q_pi.detach().mean()), "entropy_per_dim": float(-logp.detach().mean()),
                  "alpha": float(alpha), "actor_loss": float(loss.detach()), "kl_prior": float(kl.detach().mean()),
                  "noise_std": float(log_std.detach().exp().mean())})
    return stats
