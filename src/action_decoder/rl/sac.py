"""SAC-style fine-tuning through the SDE chain (design doc §4, "Practical tips").

The actor is the whole reparameterised chain: x_{k+1} = mean_k(x_k) + std_k·ε_k with ε fixed,
so ∂Q/∂θ flows through every step into the velocity network. The entropy term uses the
ε-form log-prob, −½|ε|² − log std_k − ½log 2π per element, whose gradient reaches the
learnable σ only: the Q-term moves the drift, the entropy term only the noise level. The
chunk is squashed once, after the last step, into the env's box (`squash_to_box`); the
tanh correction enters the entropy's value but not its gradient (it would otherwise pull
the velocity network toward the origin, and the design keeps entropy gradients on σ).
Log-probs are divided by H·D (entropy per action dimension) so that α does not depend on
the chunk size. The twin Q sees the state and the executed part of the chunk.

α is tuned as in SAC v2 (`Temperature`) to hold the entropy at a target, by default the
BC policy's own: with a fixed α the entropy term's gradient on σ has one sign, and Adam
turns any consistent sign into a full-size step, so σ's multiplier ran from 1 to 1.86 in
the first 400 updates on reach.
"""

from __future__ import annotations

import copy
from typing import Callable

import torch
from torch import Tensor

from . import ppo
from .ppo import k3_kl, trained_slice
from .sde_policy import rescore_chain, sample_chain, squash_to_box


class ReplayBuffer:
    """A ring buffer of chunk-level transitions (tensors on the CPU); its fields are those of the
    first rows added (SAC: state, progress, actions, reward, next_state, next_progress, done;
    DSRL adds the noise)."""

    def __init__(self, capacity: int):
        self.capacity, self.size, self.pos = capacity, 0, 0
        self.data: dict[str, Tensor] = {}

    def add(self, rows: dict) -> None:
        n = len(next(iter(rows.values())))
        if not self.data:
            self.data = {k: torch.zeros((self.capacity, *v.shape[1:]), dtype=v.dtype) for k, v in rows.items()}
        if set(rows) != set(self.data):
            raise ValueError(f"rows: expected the fields {sorted(self.data)}, got {sorted(rows)}")
        idx = (self.pos + torch.arange(n)) % self.capacity
        for k in self.data:
            self.data[k][idx] = rows[k]
        self.pos, self.size = int((self.pos + n) % self.capacity), min(self.size + n, self.capacity)

    def sample(self, batch_size: int, generator: torch.Generator) -> dict:
        idx = torch.randint(self.size, (batch_size,), generator=generator)
        return {k: v[idx] for k, v in self.data.items()}

    def state_dict(self) -> dict:
        return {"capacity": self.capacity, "size": self.size, "pos": self.pos,
                "data": {k: v[: self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.capacity, self.size, self.pos = state["capacity"], state["size"], state["pos"]
        self.data = {k: torch.cat([v, torch.zeros((self.capacity - len(v), *v.shape[1:]), dtype=v.dtype)])
                     for k, v in state["data"].items()}


class Temperature(torch.nn.Module):
    """α = exp(log α), tuned so that the entropy per action dimension stays at `target`
    (NaN until set from the first batch: the initial policy's entropy)."""

    def __init__(self, alpha: float, target: float | None = None):
        super().__init__()
        self.log_alpha = torch.nn.Parameter(torch.tensor(float(alpha)).log())
        self.register_buffer("target", torch.tensor(float("nan") if target is None else float(target)))

    @property
    def alpha(self) -> Tensor:
        return self.log_alpha.exp().detach()

    def loss(self, logp: Tensor) -> Tensor:
        """−log α·(target − entropy): α falls while the entropy (−logp) is above target, rises below."""
        entropy = -logp.detach().mean()
        if self.target.isnan():
            self.target.fill_(float(entropy))
        return -self.log_alpha * (self.target - entropy)


def actor_sample(policy, batch: dict, cfg, generator: torch.Generator):
    """Reparameterised chunk: (env actions [B, H, D], per-dim log-prob [B] (σ-only gradient), result)."""
    res = sample_chain(policy, batch, cfg.sde_steps, generator, reduce="sum", logprob="eps")
    actions, log_det = squash_to_box(res.chain[:, -1], policy.normalizers["actions"])
    numel = res.chain.shape[-1] * res.chain.shape[-2]
    return actions, (res.step_log_probs.sum(1) - log_det.detach()) / numel, res


def sac_update(policy, reference, q, q_target, temperature: Temperature, optimizers: dict, buffer: ReplayBuffer,
               make_batch: Callable[[Tensor], dict], cfg, generator: torch.Generator) -> dict:
    """One critic, actor and temperature step on a replay batch (`optimizers`: "q", "actor",
    "alpha"); Polyak-averages the target critic."""
    alpha = temperature.alpha
    b = buffer.sample(cfg.sac_batch_size, generator)
    n = b["actions"].shape[1]
    norm = policy.normalizers["state"].normalize
    with torch.no_grad():
        nxt, logp_next, _ = actor_sample(policy, make_batch(b["next_state"]), cfg, generator)
        tq = torch.min(*q_target(norm(b["next_state"]), b["next_progress"], nxt[:, :n]))
        target = b["reward"] + cfg.gamma * (1 - b["done"].float()) * (tq - alpha * logp_next)
    q1, q2 = q(norm(b["state"]), b["progress"], b["actions"])
    q_loss = (q1 - target).square().mean() + (q2 - target).square().mean()
    optimizers["q"].zero_grad(set_to_none=True)
    q_loss.backward()
    torch.nn.utils.clip_grad_norm_(q.parameters(), cfg.grad_clip)
    optimizers["q"].step()

    # The actor's graph spans K network calls per row: back-propagated per micro-batch (ppo.MICROBATCH_ROW_CALLS).
    opt_actor = optimizers["actor"]
    opt_actor.zero_grad(set_to_none=True)
    micro = max(1, ppo.MICROBATCH_ROW_CALLS // cfg.sde_steps)
    parts = {"actor_loss": 0.0, "kl_bc_update": 0.0}
    logps, q_pis = [], []
    for sub in torch.arange(len(b["state"])).split(micro):
        w = len(sub) / len(b["state"])                     # micro-batch share of the batch mean
        batch = make_batch(b["state"][sub])
        actions, logp, res = actor_sample(policy, batch, cfg, generator)               # [b, H, D], [b]
        q_pi = torch.min(*q(norm(b["state"][sub]), b["progress"][sub], actions[:, :n]))
        loss = (alpha * logp - q_pi).mean()
        if cfg.kl_coef > 0:
            chain = res.chain.detach()
            lp = rescore_chain(policy, batch, chain, res.grid)
            with torch.no_grad():
                lp_ref = rescore_chain(reference, batch, chain, res.grid)
            credited = trained_slice(chain.shape[1] - 1, cfg.trained_steps)
            # k2's gradient is ∇KL(π_θ ‖ π_BC) on chains π_θ sampled (k3's would be the reverse KL's); k3 is logged.
            loss = loss + cfg.kl_coef * ppo.kl_penalty(lp[:, credited], lp_ref[:, credited]).mean()
            parts["kl_bc_update"] += w * float(k3_kl(lp_ref - lp.detach())[:, credited].mean())
        (w * loss).backward()
        parts["actor_loss"] += w * float(loss.detach())
        logps.append(logp.detach())
        q_pis.append(q_pi.detach())
    logp = torch.cat(logps)                                                            # [B]
    stats = {"q_loss": float(q_loss.detach()), "q": float(torch.cat(q_pis).mean()),
             "entropy_per_dim": float(-logp.mean()), "alpha": float(alpha), "actor_loss": parts["actor_loss"]}
    if cfg.kl_coef > 0:
        stats["kl_bc_update"] = parts["kl_bc_update"]
    torch.nn.utils.clip_grad_norm_([p for g in opt_actor.param_groups for p in g["params"]], cfg.grad_clip)
    opt_actor.step()
    if cfg.alpha_lr > 0:
        optimizers["alpha"].zero_grad(set_to_none=True)
        temperature.loss(logp).backward()
        optimizers["alpha"].step()
    with torch.no_grad():
        for p, tp in zip(q.parameters(), q_target.parameters()):
            tp.lerp_(p, cfg.tau)
    return stats


def make_target(q):
    target = copy.deepcopy(q)
    target.requires_grad_(False)
    return target
