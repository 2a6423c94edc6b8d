"""PPO on denoising chains (Flow-GRPO / πRL style).

Each denoising step k of a stored chain is a Gaussian "action" x_{k+1} ~ N(mean_k(x_k), std_k²)
taken with the chunk's advantage: the ratio is per step, exp(log π_θ(x_{k+1}|x_k) − log π_old),
clipped per step, and the objective averages over the trained steps. The chain and its
grid are stored at rollout time and re-scored under the current weights, so before the
first update of an iteration every ratio is 1 — checked at run time, up to `--ratio-tol` plus
the float rounding of re-scoring in another batch composition (`rescore_rounding`).
"""

from __future__ import annotations

from typing import Callable, Optional

import torch
from torch import Tensor

from .sde_policy import rescore_chain, step_numel


def gae(rewards: Tensor, values: Tensor, next_values: Tensor, terminal: Tensor, last: Tensor,
        gamma: float, lam: float) -> tuple[Tensor, Tensor]:
    """Advantages and returns [N] over decisions stored episode by episode in time order.

    `next_values` [N] = V(next state), used only where an episode was truncated (time limit);
    a terminal (success) decision has no future, a mid-episode one uses the next row's value.
    """
    adv = torch.zeros_like(rewards)
    running = torch.zeros(())
    for i in range(len(rewards) - 1, -1, -1):
        if last[i]:
            nxt = torch.zeros(()) if terminal[i] else next_values[i]
            running = torch.zeros(())
        else:
            nxt = values[i + 1]
        delta = rewards[i] + gamma * nxt - values[i]
        running = delta + gamma * lam * running
        adv[i] = running
    return adv, adv + values


def group_advantages(rewards: Tensor, last: Tensor, gamma: float, group_size: int) -> Tensor:
    """GRPO-style advantages [N] for episodes played in groups of `group_size` consecutive
    episodes from one layout (rows stored episode by episode, in time order).

    Decision t of an episode gets its discounted reward-to-go minus the mean reward-to-go at
    decision t of the *other* episodes of its group (an episode that has ended counts 0: after
    success nothing more is earned). Leaving the episode out keeps the baseline independent of
    its own actions (no bias). Why: with few demonstrations the return varies 3–4× between
    layouts but a few % between episodes of one layout, so a critic's error swamps the signal
    that comparing episodes of one layout isolates exactly. Scaling is left to the update's
    per-iteration normalisation.
    """
    if group_size < 2:
        raise ValueError(f"group_size: expected at least 2 episodes per layout, got {group_size}")
    ends = last.long()
    episode = torch.cumsum(ends, 0) - ends                                    # [N] episode index
    n_episodes = int(episode[-1]) + 1
    if n_episodes % group_size:
        raise ValueError(f"group_size: {n_episodes} episodes do not split into groups of {group_size}")
    starts = torch.nonzero(torch.cat([torch.ones(1, dtype=torch.bool), last[:-1]])).flatten()   # [E]
    position = torch.arange(len(rewards)) - starts[episode]                  # decision index in its episode
    horizon = int(position.max()) + 1
    padded = torch.zeros(n_episodes, horizon, dtype=rewards.dtype)
    padded[episode, position] = rewards                                       # [E, T], 0 after the end
    to_go = torch.zeros_like(padded)
    running = torch.zeros(n_episodes, dtype=rewards.dtype)
    for t in range(horizon - 1, -1, -1):
        running = padded[:, t] + gamma * running
        to_go[:, t] = running
    groups = to_go.view(-1, group_size, horizon)                             # [E/G, G, T]
    others = (groups.sum(1, keepdim=True) - groups) / (group_size - 1)
    return (groups - others).view(n_episodes, horizon)[episode, position]


def k3_kl(log_ratio_ref: Tensor, numel: float | Tensor = 1.0) -> Tensor:
    """Schulman's non-negative KL(π_θ ‖ π_ref) estimate from log(π_ref/π_θ) on samples of π_θ.

    `numel`: for log-probs averaged over the chunk (`--logprob-reduce mean`), the elements each one
    averages (`sde_policy.step_numel`); the estimate is then that of the summed (true) log-ratio
    divided by them, KL per element. k3 of the averaged log-ratio itself is not KL / (H·D)."""
    x = log_ratio_ref * numel
    return (torch.expm1(x) - x) / numel


def kl_penalty(logp: Tensor, logp_ref: Tensor, numel: float | Tensor = 1.0) -> Tensor:
    """Per-sample loss whose gradient, on samples of π_θ, is ∇ KL(π_θ ‖ π_ref): k2 = ½ (log π_θ − log π_ref)².
    (Back-propagating `k3_kl` instead gives ∇ KL(π_ref ‖ π_θ), the reverse direction; its value, not its
    gradient, is the estimate of KL(π_θ ‖ π_ref) that is logged.) `numel` as in `k3_kl`: k2 of the
    summed log-ratio divided by the elements, so the gradient is that of KL per element (k2 of the
    averaged log-ratio would shrink it by numel² instead of numel)."""
    return 0.5 * ((logp - logp_ref) * numel).square() / numel


def trained_slice(steps: int, trained_steps: int) -> slice:
    """The denoising steps an objective credits: the last `trained_steps` of `steps`."""
    return slice(steps - trained_steps, steps)


MICROBATCH_ROW_CALLS = 256
"""Rows × network calls re-scored with a live autograd graph at a time (≈ 0.7 MB per row-call
for the default network): a minibatch of 512 chains × 10 steps kept every call's activations
until its one backward, 3.5 GB; micro-batches accumulate the same gradient in ≈ 180 MB."""


RESCORE_ROUNDING = 16.0
"""Margin of `rescore_rounding` over its first-order bound."""


def rescore_rounding(policy, chain: Tensor, grid: Tensor, logp: Tensor, numel: Tensor) -> Tensor:
    """[b, K'] bound of the rounding error between a step's log-prob as sampled and as re-scored in
    another batch composition (the rollout samples on the envs still running, PPO re-scores in
    micro-batches): the network's matrix products round differently with the batch's shape, so each
    element's mean moves by about ε·max(1, |x|), its residual z by that / std_k, and the step's
    summed log-prob by ε·Σ max(1, |x_{k+1}|) / std_k, plus ε·|log-prob| for the sum's own rounding.
    Scaled by `RESCORE_ROUNDING`; per element (÷ `numel`) for averaged log-probs (`numel` = 1 for sums).

    `chain` [b, K'+1, H, D] and `grid` [K'+1] the re-scored steps, `logp` [b, K'] their log-probs.
    The bound grows as σ shrinks (the densities sharpen): a stored chain re-scored with another
    velocity, σ or grid moves the log-prob by far more at any σ."""
    eps = torch.finfo(logp.dtype).eps
    with torch.no_grad():
        std = policy.sigma(grid[:-1]) * grid.diff().sqrt()                               # [K']
        spread = chain[:, 1:].abs().clamp_min(1).sum((-2, -1))                           # [b, K']
        summed = eps * (logp.detach().abs() * numel + spread / std)
    return RESCORE_ROUNDING * summed / numel


LR_STEP = 1.5
"""Factor by which `adapt_lr` lowers or raises the learning rate."""


def adapt_lr(lr: float, approx_kl: float, target_kl: float, lo: float, hi: float) -> float:
    """The KL-adaptive learning rate of common PPO code (rsl_rl's "adaptive" schedule): lr / 1.5 when
    an update took the policy beyond 2 × `target_kl` from the rollout policy, lr × 1.5 when it stayed
    below `target_kl` / 2, unchanged in between; kept within [lo, hi]."""
    if approx_kl > 2.0 * target_kl:
        lr = lr / LR_STEP
    elif approx_kl < 0.5 * target_kl:
        lr = lr * LR_STEP
    return min(max(lr, lo), hi)


def warmup_lr(lr: float, updates_done: int, warmup_updates: int) -> float:
    """Learning rate of update number `updates_done` + 1 under a linear warm-up: lr × (n + 1) / N over
    the first N = `warmup_updates` updates, then lr (N = 0: no warm-up). Adam's first steps move
    every weight by about lr whatever the gradient's noise (m̂ / √v̂ = ±1 at the first step)."""
    return lr if warmup_updates <= 0 else lr * min(1.0, (updates_done + 1) / warmup_updates)


def ppo_update(policy, value_net, optimizer: torch.optim.Optimizer, make_batch: Callable[[Tensor], dict],
               data: dict, cfg, generator: torch.Generator, update_policy: bool = True,
               stop: Optional[Callable[[], bool]] = None) -> dict:
    """Clipped-PPO epochs over one iteration's decisions; returns statistics.

    `data`: states [N, S], state_norm [N, S], progress [N], chain [N, K+1, H, D], grid [K+1],
    logp_old / logp_ref [N, K] (rollout policy / frozen BC policy), adv, ret [N], and optionally
    executed [N] (actions of each chunk executed; default n_action_steps).
    `update_policy=False` trains only the critic (warm-up). With `cfg.lr_schedule == "adaptive"` the
    first parameter group's learning rate (the velocity network's) follows `adapt_lr` after every
    minibatch measured past an update, within [`cfg.lr` / 100, `cfg.lr` × 10]; it lives in the
    optimizer's state, so it carries over iterations and resumes. With `cfg.lr_warmup_updates` = N > 0
    (fixed schedule) that rate follows `warmup_lr` over the velocity network's first N updates, counted
    by Adam's own step count, which also resumes.

    Only the trained steps are re-scored (each step's density needs only its stored start and
    end states), in micro-batches whose losses are back-propagated at once (`MICROBATCH_ROW_CALLS`):
    the gradient is the minibatch's, the memory that of a micro-batch. `approx_kl` estimates
    KL(π_old ‖ π_θ) per trained step on the stored chains, which π_old sampled: k3 of
    log(π_θ/π_old), i.e. mean(ratio − 1 − log ratio) as in common PPO code. It grows like |log ratio|
    where a step's density collapses; the reverse form, mean(1/ratio − 1 + log ratio), grows like
    1/ratio and overflowed to inf on the clean-chunk head's sharp last step. With `kl_coef` > 0 the loss
    adds `kl_coef` × `kl_penalty` to BC, and `kl_bc_update` logs k3's KL(π_θ ‖ π_BC) averaged over the update's
    minibatches. `approx_kl_first_update` is the approximate KL on the minibatch right after the iteration's
    first update; `updates` the number of policy updates the iteration took. `stop`, when given, is
    asked before each minibatch (a CPU budget, Ctrl-C): True ends the epochs there, as the KL stop does.
    """
    n, K = data["chain"].shape[0], data["chain"].shape[1] - 1
    trained = trained_slice(K, cfg.trained_steps)
    chain, grid = data["chain"][:, trained.start:], data["grid"][trained.start:]   # [N, K'+1, H, D], [K'+1]
    micro = max(1, MICROBATCH_ROW_CALLS // cfg.trained_steps)
    adv = data["adv"]
    adv = (adv - adv.mean()) / (adv.std() + 1e-8) if n > 1 else adv
    # Clipped apart: the critic's gradient scale (returns of up to ~1/(1−γ)) must not shrink the policy's.
    critic_params = list(value_net.parameters())
    critic_ids = {id(p) for p in critic_params}
    policy_params = [p for g in optimizer.param_groups for p in g["params"] if id(p) not in critic_ids]
    stats: dict = {"ratio_dev_before_update": 0.0, "epochs": 0, "updates": 0}
    logs = {k: [] for k in ("pg_loss", "v_loss", "kl_bc_update", "approx_kl", "clipfrac", "ratio_mean", "ratio_min",
                            "ratio_max")}
    first, stop_now = True, False
    for epoch in range(cfg.ppo_epochs):
        perm = torch.randperm(n, generator=generator)
        for start in range(0, n, cfg.minibatch_size):
            if stop is not None and stop():
                stop_now = True
                break
            idx = perm[start:start + cfg.minibatch_size]
            optimizer.zero_grad(set_to_none=True)
            if update_policy:
                parts = {"pg": 0.0, "kl": 0.0}
                log_ratios = []
                numels, tols = [], []
                for sub in idx.split(micro):
                    w = len(sub) / len(idx)                   # micro-batch share of the minibatch mean
                    executed = data["executed"][sub] if "executed" in data else policy.config.n_action_steps
                    lp = rescore_chain(policy, make_batch(data["states"][sub]), chain[sub], grid,
                                       cfg.logprob_reduce, executed)                                 # [b, K']
                    # KLs per element with averaged log-probs: from the summed log-ratio (`k3_kl`)
                    numel = (step_numel(chain[sub].shape, executed).expand_as(lp)
                             if cfg.logprob_reduce == "mean" else torch.ones_like(lp))               # [b, K']
                    log_ratio = lp - data["logp_old"][sub, trained]
                    ratio = log_ratio.exp()
                    a = adv[sub, None]
                    pg = -torch.min(ratio * a, ratio.clamp(1 - cfg.clip_eps, 1 + cfg.clip_eps) * a).mean()
                    loss = pg
                    if cfg.kl_coef > 0:
                        ref = data["logp_ref"][sub, trained]
                        loss = loss + cfg.kl_coef * kl_penalty(lp, ref, numel).mean()
                        parts["kl"] += w * float(k3_kl(ref - lp.detach(), numel).mean())
                    (w * loss).backward()
                    parts["pg"] += w * float(pg.detach())
                    log_ratios.append(log_ratio.detach())
                    numels.append(numel)
                    if first:
                        tols.append(rescore_rounding(policy, chain[sub], grid, lp, numel))           # [b, K']
                log_ratio = torch.cat(log_ratios)                                                    # [b, K']
                ratio = log_ratio.exp()
                if first:
                    devs = (ratio - 1).abs()                                                          # [b, K']
                    stats["ratio_dev_before_update"] = float(devs.max())
                    excess = devs - (cfg.ratio_tol + torch.cat(tols))
                    if not bool((excess <= 0).all()):            # NaN fails too
                        i = int(torch.nan_to_num(excess, nan=float("inf")).argmax())
                        dev, tol = float(devs.flatten()[i]), float(cfg.ratio_tol + torch.cat(tols).flatten()[i])
                        raise RuntimeError(f"PPO: on-policy ratio is not 1 before the first update (|ratio − 1| "
                                           f"= {dev:.2e} > {tol:.2e}, --ratio-tol {cfg.ratio_tol:g} plus float "
                                           f"rounding): the stored chain is re-scored with a different velocity, "
                                           f"σ or grid than the one that sampled it")
                approx_kl = float(k3_kl(log_ratio, torch.cat(numels)).mean())
                logs["pg_loss"].append(parts["pg"])
                if cfg.kl_coef > 0:
                    logs["kl_bc_update"].append(parts["kl"])
                logs["approx_kl"].append(approx_kl)
                logs["clipfrac"].append(float(((ratio - 1).abs() > cfg.clip_eps).float().mean()))
                logs["ratio_mean"].append(float(ratio.mean()))
                logs["ratio_min"].append(float(ratio.min()))
                logs["ratio_max"].append(float(ratio.max()))
                too_far = approx_kl > 1.5 * cfg.target_kl
                if cfg.lr_schedule == "adaptive" and not first:    # the first minibatch precedes every update
                    group = optimizer.param_groups[0]
                    # The KL stop is a "too far" too: the rate that got there comes down, as past 2 × target.
                    group["lr"] = adapt_lr(group["lr"], max(approx_kl, 2.01 * cfg.target_kl) if too_far else approx_kl,
                                           cfg.target_kl, cfg.lr / 100, cfg.lr * 10)
                if too_far:                            # too far from the rollout policy: stop here
                    optimizer.zero_grad(set_to_none=True)
                    stop_now = True
                    break
            first = False
            value = value_net(data["state_norm"][idx], data["progress"][idx])
            v_loss = (value - data["ret"][idx]).square().mean()
            logs["v_loss"].append(float(v_loss.detach()))
            (cfg.vf_coef * v_loss).backward()
            torch.nn.utils.clip_grad_norm_(policy_params, cfg.grad_clip)
            torch.nn.utils.clip_grad_norm_(critic_params, cfg.grad_clip)
            if update_policy and cfg.lr_warmup_updates > 0:
                group = optimizer.param_groups[0]
                done = max((int(optimizer.state[p]["step"]) for p in group["params"] if "step" in optimizer.state[p]),
                           default=0)
                group["lr"] = warmup_lr(cfg.lr, done, cfg.lr_warmup_updates)
            optimizer.step()
            stats["updates"] += int(update_policy)
        stats["epochs"] = epoch + 1
        if stop_now:
            break
    stats["lr"] = float(optimizer.param_groups[0]["lr"])
    if len(logs["approx_kl"]) > 1:      # measured on the minibatch after the iteration's first update
        stats["approx_kl_first_update"] = logs["approx_kl"][1]
    for k, v in logs.items():
        if v:
            stats[k] = min(v) if k == "ratio_min" else max(v) if k == "ratio_max" else sum(v) / len(v)
    return stats
