"""`action-decoder finetune`: RL fine-tuning of a BC flow checkpoint through its SDE sampler.

One iteration = one episode on each of `num_envs` lockstep envs (layouts seeded from the
iteration number, below the evaluation seeds), then PPO epochs on the stored chains or
SAC steps on a replay buffer. Checkpoints (`checkpoints/step_N`, `checkpoints/last`) are
written atomically at iteration boundaries with the critic, optimisers, generators and
history, so `--resume` continues exactly. The result (`final/`) is a `save_pretrained`
directory that `action-decoder eval` reads; it samples with the fine-tuned SDE by default.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch

from ..evaluate import make_policy_fn
from ..model_card import weights_digest
from ..policy import ActionDecoderPolicy
from ..run_dir import (CKPT_DIR, _rng_state, _set_rng_state, existing_run, last_checkpoint, load_state, run_dir_lock,
                       save_final, write_checkpoint)
from ..tracking import RunLogger, require_wandb
from ..train import task_context
from .critics import TwinQ, ValueNet
from .ppo import gae, group_advantages, k3_kl, ppo_update, trained_slice
from .rollout import collect
from .sac import ReplayBuffer, Temperature, make_target, sac_update
from .sde_policy import finetune_policy, rescore_chain, sample_chain, squash_to_box

TRAIN_LAYOUT_BASE, TRAIN_LAYOUT_SPAN = 500_000, 400_000
"""Training layouts: seeds in [500 000, 900 000), apart from demonstrations (low seeds) and
evaluation (≥ 1 000 000)."""
LAYOUT_STRIDE = 247_213
"""Start of seed s's layout stream: s × this, modulo the span. ≈ span / φ (golden ratio) and coprime
with it, so the first 16 seeds start ≥ 13 769 layouts apart (32 seeds: 8 527), far more than a
45-CPU-minute run plays (≈ 800)."""
SIGMA_RANGE = (1e-3, 10.0)
"""`--sigma` bounds: below, the chain's steps have no noise to explore with (densities overflow);
above, its noise swamps the unit-scale normalised actions."""
RUN_OPTIONS = frozenset({"checkpoint", "output_dir", "env_steps", "max_cpu_minutes", "eval_episodes", "eval_every",
                         "checkpoint_every", "resume", "wandb", "wandb_project"})
"""Options that set a run's budget, location or logging: `--resume` may change them; the others define the run."""


def train_layout_seeds(seed: int, iteration: int, num_envs: int, group_size: int) -> list[int]:
    """The training layouts (env seeds) of one iteration, one per env: `num_envs / group_size` distinct
    layouts, each played by `group_size` consecutive envs; consecutive iterations take the next ones."""
    layouts = num_envs // group_size
    start = seed * LAYOUT_STRIDE + iteration * layouts
    return [TRAIN_LAYOUT_BASE + (start + i // group_size) % TRAIN_LAYOUT_SPAN for i in range(num_envs)]


@dataclass
class FinetuneConfig:
    """Fine-tune a flow-matching or MeanFlow BC checkpoint with RL on its Meta-World task."""

    checkpoint: str
    """A `save_pretrained` directory of a flow_matching or mean_flow policy (e.g. outputs/train/final)."""
    output_dir: str = "outputs/finetune"
    algo: Literal["ppo", "sac"] = "ppo"
    task: Optional[str] = None
    """Task to fine-tune on (default: the checkpoint's task; required for multi-task checkpoints)."""
    env_steps: int = 100_000
    """Environment steps to collect (the run stops at the first iteration boundary past it)."""
    max_cpu_minutes: float = 0.0
    """Also stop at the first iteration boundary past this much CPU time of fine-tuning (0: no
    limit). CPU rather than wall time, so that runs sharing a machine compare fairly."""
    num_envs: int = 32
    """Lockstep envs; each iteration runs one episode on each."""
    group_size: Optional[int] = None
    """PPO: episodes per training layout (default 4). Above 1, advantages are GRPO-style (each decision's
    reward-to-go against the other episodes of its layout, see `ppo.group_advantages`) instead of
    the critic's GAE (1). On 3-demo reach the return varies 3–4× between layouts and by a few %
    between episodes of one layout: the critic's error swamped that signal (no learning), the
    group comparison isolates it. SAC plays one layout per env and refuses the option."""
    max_episode_steps: int = 200
    """Length cap of the training episodes in env steps (BC successes come within ~50–150 steps;
    longer episodes cost env steps without a new signal). Evaluation always runs 500."""
    seed: int = 0
    sde_steps: int = 10
    """Denoising steps K of the SDE chain (also for MeanFlow, whose 1-step ODE has no density)."""
    sigma_schedule: Literal["explore", "fixed"] = "fixed"
    """σ(t): "fixed" = a at every t; "explore" = a·√((1 − t)/max(t, 0.1)) (Flow-GRPO). On a 3-demo
    reach policy, fixed a = 0.5 gives executed actions 3× the variance of explore a = 1 (whose
    exploration is 0.02–0.04 in env units) and no step with a much sharper density than the others."""
    sigma: float = 0.25
    """Scale a of the σ(t) schedule. The exploring policy must still succeed where the BC policy
    does: on 3-demo door-lock (BC 44 % with the ODE) the SDE succeeds in 16 % of episodes at
    a = 0.5 and 38 % at a = 0.25, and PPO learnt nothing at 0.5 in 160k env steps (evaluation
    15 → 10 %) against 25 → 60 % (SDE) / 75 % (ODE) at 0.25 in 64k (docs/benchmarks/rl_finetune.md)."""
    learn_sigma: bool = True
    """Learn a multiplier of σ(t) (starts at 1)."""
    lr: float = 1e-4
    """Velocity network learning rate (3e-4 jumps by several nats of KL in one step; 3e-5 barely moves);
    with `--lr-schedule adaptive`, the starting value."""
    lr_schedule: Literal["adaptive", "fixed"] = "fixed"
    """PPO: "adaptive" divides the velocity network's learning rate by 1.5 after a minibatch update
    that takes the policy beyond 2 × `target_kl` from the rollout policy and multiplies it by 1.5
    below `target_kl` / 2 (within [lr / 100, lr × 10]); "fixed" keeps `lr`."""
    lr_warmup_updates: int = 0
    """PPO, fixed schedule: the velocity network's learning rate rises linearly from lr / N to lr over
    its first N updates (0: none). At lr 1e-4 the first update moves the policy 0.3–0.8 nats per
    credited step from the rollout policy (approximate KL; target 0.05) on Meta-World; N = 20 takes
    that to 0.002–0.003 but gained no more on door-lock (docs/benchmarks/rl_finetune_screen.md)."""
    sigma_lr: float = 3e-3
    critic_lr: float = 1e-3
    gamma: float = 0.99
    """Discount per decision (one chunk)."""
    gae_lambda: float = 0.95
    reward: Literal["dense", "success"] = "dense"
    """"dense": the env's reward averaged over the chunk's steps / 10 ∈ [0, 1], episodes running past
    success to `max_episode_steps` (the protocol of Meta-World's RL baselines: its rewards are largest
    in the success region). "success": `success_reward` on the decision that succeeds, where the
    episode ends, plus `shaping_scale` potential-based shaping."""
    success_reward: float = 1.0
    """`--reward success`: reward on the decision that reaches success (the episode ends there)."""
    shaping_scale: float = 0.1
    """`--reward success`: weight k of potential-based shaping k·(γ·Φ(s′) − Φ(s)), Φ = the env's dense reward / 10 ∈ [0, 1],
    Φ = 0 after success. It guides credit assignment without changing the optimal policy (0: success
    only). Keep k well below `success_reward`: a truncated episode that hovers at the goal earns
    ≈ k·γⁿ, so with k = 1 succeeding would be worth little more than nearly succeeding."""
    logprob_reduce: Literal["sum", "mean"] = "sum"
    """PPO: per-step log-prob of the chunk summed over H×D (true density) or averaged (Flow-GRPO)."""
    trained_steps: int = 10
    """The last N denoising steps enter the PPO/KL objective. Their noise is what moves the executed
    actions: on a 3-demo reach policy the last 5 of 10 steps carry 97 % of the executed-action
    variance and the last one 71 %, while the first 5 carry 5 % (the velocity field contracts early
    noise back onto the data), so crediting early steps gives PPO almost no signal."""
    clip_eps: float = 0.2
    ppo_epochs: int = 4
    minibatch_size: int = 512
    target_kl: float = 0.05
    """PPO: stop an iteration's epochs when the approximate KL to the rollout policy exceeds 1.5×this."""
    vf_coef: float = 0.5
    kl_coef: float = 0.0
    """Weight of KL(π_θ ‖ π_BC) on the chains (0: off; the KL is still logged)."""
    critic_warmup_iters: Optional[int] = None
    """PPO with the critic (`--group-size 1`): first iterations train only the value head (default 1).
    Group advantages do not use the value head, so with `--group-size` above 1 the policy updates
    from the first iteration and this option is refused."""
    ratio_tol: float = 1e-4
    """PPO: tolerated |ratio − 1| before the first update of an iteration."""
    alpha: float = 0.01
    """SAC: initial entropy weight α (log-probs per action dimension)."""
    alpha_lr: float = 3e-2
    """SAC: learning rate of log α, tuned to hold the entropy at `target_entropy` (0: α fixed). It
    must outpace σ's drift under the entropy term (Adam moves log σ by up to `sigma_lr` per update)."""
    target_entropy: Optional[float] = None
    """SAC: entropy per action dimension that α holds (default: the initial policy's, so exploration
    stays where `--sigma` puts it)."""
    tau: float = 0.005
    sac_batch_size: int = 128
    sac_updates_per_decision: float = 0.5
    buffer_size: int = 100_000
    grad_clip: float = 1.0
    eval_episodes: int = 20
    """Closed-loop evaluation episodes (eval layouts) before, every `eval_every` iterations, and after (0: none)."""
    eval_every: int = 0
    checkpoint_every: int = 5
    """Iterations between resumable checkpoints."""
    resume: bool = False
    wandb: bool = False
    """Also log to Weights & Biases (pip install "action-decoder[wandb]"). TensorBoard events and
    finetune_log.jsonl are always written to the output directory, per iteration, at its env steps."""
    wandb_project: str = "action-decoder"


def episodes_per_layout(cfg: FinetuneConfig) -> int:
    """Episodes per training layout: `--group-size`, by default 4 with PPO and 1 with SAC."""
    return cfg.group_size if cfg.group_size is not None else 4 if cfg.algo == "ppo" else 1


def _check(cfg: FinetuneConfig) -> None:
    if cfg.group_size is not None and cfg.algo != "ppo":
        raise ValueError(f"--group-size: only with --algo ppo (SAC plays one layout per env), got {cfg.group_size} "
                         f"with --algo {cfg.algo}")
    for name in ("env_steps", "num_envs", "group_size", "max_episode_steps", "sde_steps", "ppo_epochs", "minibatch_size",
                 "sac_batch_size", "buffer_size", "checkpoint_every"):
        if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive integer, got {getattr(cfg, name)}")
    for name in ("sigma", "alpha", "lr", "sigma_lr", "critic_lr", "clip_eps", "target_kl", "ratio_tol", "grad_clip",
                 "sac_updates_per_decision"):
        if not getattr(cfg, name) > 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive number, got {getattr(cfg, name)}")
    for name in ("kl_coef", "alpha_lr", "vf_coef", "eval_episodes", "eval_every", "lr_warmup_updates",
                 "shaping_scale", "max_cpu_minutes"):
        if not getattr(cfg, name) >= 0:                 # NaN fails too
            raise ValueError(f"--{name.replace('_', '-')}: expected >= 0, got {getattr(cfg, name)}")
    for name in ("sigma", "alpha", "lr", "sigma_lr", "critic_lr", "clip_eps", "target_kl", "ratio_tol", "grad_clip",
                 "sac_updates_per_decision", "success_reward", "kl_coef", "shaping_scale"):
        if not math.isfinite(getattr(cfg, name)):
            raise ValueError(f"--{name.replace('_', '-')}: expected a finite number, got {getattr(cfg, name)}")
    if not cfg.success_reward > 0:
        raise ValueError(f"--success-reward: expected a positive reward for reaching success, got {cfg.success_reward}")
    if not SIGMA_RANGE[0] <= cfg.sigma <= SIGMA_RANGE[1]:
        raise ValueError(f"--sigma: expected a noise scale in [{SIGMA_RANGE[0]:g}, {SIGMA_RANGE[1]:g}] (actions are "
                         f"normalised to unit scale), got {cfg.sigma}")
    if cfg.algo == "sac" and cfg.buffer_size < cfg.sac_batch_size:
        raise ValueError(f"--buffer-size: expected at least --sac-batch-size ({cfg.sac_batch_size}) transitions, or "
                         f"SAC never updates; got {cfg.buffer_size}")
    if cfg.max_episode_steps > 500:
        raise ValueError(f"--max-episode-steps: Meta-World caps episodes at 500 steps, got {cfg.max_episode_steps}")
    if cfg.lr_warmup_updates and (cfg.algo != "ppo" or cfg.lr_schedule != "fixed"):
        raise ValueError(f"--lr-warmup-updates: only with --algo ppo and --lr-schedule fixed, got "
                         f"{cfg.lr_warmup_updates} with --algo {cfg.algo} --lr-schedule {cfg.lr_schedule}")
    if cfg.critic_warmup_iters is not None:
        if cfg.critic_warmup_iters < 0:
            raise ValueError(f"--critic-warmup-iters: expected >= 0, got {cfg.critic_warmup_iters}")
        if cfg.algo != "ppo" or episodes_per_layout(cfg) > 1:
            raise ValueError(f"--critic-warmup-iters: only with PPO's critic (--group-size 1); SAC and group advantages "
                             f"(--group-size {episodes_per_layout(cfg)}) do not use the value head, "
                             f"got {cfg.critic_warmup_iters}")
    if cfg.num_envs % episodes_per_layout(cfg):
        raise ValueError(f"--group-size: expected a divisor of --num-envs={cfg.num_envs}, "
                         f"got {episodes_per_layout(cfg)}")
    if not 1 <= cfg.trained_steps <= cfg.sde_steps:
        raise ValueError(f"--trained-steps: expected between 1 and --sde-steps={cfg.sde_steps}, got {cfg.trained_steps}")
    for name, low_open in (("gamma", True), ("gae_lambda", False), ("tau", True)):
        v = getattr(cfg, name)
        if not ((0 < v) if low_open else (0 <= v)) or not v <= 1:
            raise ValueError(f"--{name.replace('_', '-')}: expected a number in {'(0' if low_open else '[0'}, 1], got {v}")
    require_wandb(cfg.wandb)


def episode_ends(ro) -> torch.Tensor:
    """[N] bool: decisions after which nothing follows, where critics bootstrap with 0: success with
    `--reward success`, and the training cap. The value and Q heads see the episode's progress, so the
    cap belongs to their MDP (a time-aware value is 0 there); bootstrapping at progress 1 would read a
    head never trained there."""
    return ro.terminal | (ro.next_progress >= 1)


def _check_resumed_config(saved: Optional[dict], cfg: FinetuneConfig, ckpt: Path) -> None:
    """`--resume` continues the run it finds only with that run's options (`RUN_OPTIONS` aside)."""
    if saved is None:           # checkpoints written before the config was stored
        return
    now = asdict(cfg)
    changed = sorted(k for k in now if k not in RUN_OPTIONS and k in saved and saved[k] != now[k])
    if changed:
        raise ValueError(f"--resume: {ckpt} was started with " + ", ".join(f"{k}={saved[k]!r}" for k in changed)
                         + "; this call sets " + ", ".join(f"{k}={now[k]!r}" for k in changed)
                         + ": pass the run's own options or choose another --output-dir")


def _resolve_task(cfg: FinetuneConfig, trained: list[str]) -> tuple[str, int]:
    from ..envs import canonical_task

    if cfg.task is None:
        if len(trained) != 1:
            raise ValueError(f"--task: the checkpoint was trained on {trained or 'no named task'}; "
                             f"pass --task metaworld/<task>")
        return trained[0], 0
    task = canonical_task(cfg.task)
    if len(trained) > 1 and task not in trained:
        raise ValueError(f"--task: {task} is not among the tasks this policy was trained on: {trained}")
    if trained and task not in trained:
        print(f"finetune: note: {task} is not the task this policy was trained on ({trained[0]}); fine-tuning it "
              f"there keeps its state normalisation", flush=True)
    return task, trained.index(task) if len(trained) > 1 else 0


def plot_curves(history: list, evals: list, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [h["env_steps"] for h in history]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    axes[0].plot(x, [h["success"] for h in history], alpha=0.4, label="training episodes (SDE)")
    for sampler, marker in (("sde", "o"), ("ode", "s")):
        pts = [(e["env_steps"], e[f"success_{sampler}"]) for e in evals]
        if pts:
            axes[0].plot(*zip(*pts), marker=marker, label=f"eval ({sampler})")
    axes[0].set(xlabel="env steps", ylabel="success", ylim=(-0.02, 1.02), title=title)
    axes[0].legend(fontsize=7)
    axes[1].plot(x, [h["return"] for h in history])
    axes[1].set(xlabel="env steps", ylabel="episode return (env reward)")
    axes[2].plot(x, [h["sigma_mult"] for h in history], label="σ multiplier")
    axes[2].plot(x, [h["kl_bc"] for h in history], label="KL to BC (per step)")
    axes[2].set(xlabel="env steps")
    axes[2].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def shaping(ro, gamma: float) -> torch.Tensor:
    """γ·Φ(s′) − Φ(s) per decision [N], Φ = env reward / 10 (Meta-World's rewards lie in [0, 10]),
    Φ(terminal) = 0 and Φ(s₀) = 0 (the env's reward at s₀ comes only with an action, which would make
    the first term depend on it). Summed over an episode it telescopes to the bootstrapped tail at a
    time limit, so the policy it favours is the one the success reward favours."""
    phi_next = torch.where(ro.terminal, torch.zeros_like(ro.reward_after), ro.reward_after / 10)
    return gamma * phi_next - ro.reward_before / 10


def decision_rewards(ro, cfg: FinetuneConfig, n_exec: int) -> torch.Tensor:
    """Training reward per decision [N] (see `FinetuneConfig.reward`)."""
    if cfg.reward == "dense":
        return ro.env_rewards / (10 * n_exec)
    return cfg.success_reward * ro.terminal.float() + cfg.shaping_scale * shaping(ro, cfg.gamma)


def chain_actor(policy, make_batch, steps: int, generator: torch.Generator, reduce: str, squash: bool):
    """The rollout's act function: one SDE chain per env; records the chain [K+1, H, D], its
    grid and per-step log-probs [K] (for PPO) and the executed actions (for SAC's buffer).
    PPO executes the unnormalised final state as BC does (clamped to the data's range with
    `clip_actions`); SAC squashes it into the box."""
    n_exec = policy.config.n_action_steps

    @torch.no_grad()
    def act(states: np.ndarray, progress: np.ndarray):
        res = sample_chain(policy, make_batch(torch.from_numpy(states)), steps, generator, reduce=reduce,
                           executed=n_exec)
        if squash:
            actions = squash_to_box(res.chain[:, -1], policy.normalizers["actions"])[0]
        else:
            actions = policy.normalizers["actions"].unnormalize(res.chain[:, -1])
            if policy.config.clip_actions:
                actions = policy.normalizers["actions"].clip(actions)
        return actions.numpy(), {"chain": res.chain, "logp": res.step_log_probs, "actions": actions[:, :n_exec],
                                 "grid": res.grid.expand(len(states), -1)}

    return act


def finetune(cfg: FinetuneConfig) -> Path:
    """Run the fine-tuning; returns the `final/` checkpoint directory. The output directory is
    locked for the run (`run_dir.run_dir_lock`): a second run on it stops at once."""
    _check(cfg)
    with run_dir_lock(Path(cfg.output_dir)):
        return _finetune(cfg)


def _finetune(cfg: FinetuneConfig) -> Path:
    from ..envs import evaluate, make_env
    from ..envs.metaworld_tasks import MAX_EPISODE_STEPS

    out = Path(cfg.output_dir)
    bc = ActionDecoderPolicy.from_pretrained(cfg.checkpoint)
    trained = list(bc.config.extra.get("tasks") or [])
    task, task_index = _resolve_task(cfg, trained)
    num_tasks = max(len(trained), 1)
    torch.manual_seed(cfg.seed)
    policy = finetune_policy(bc, cfg.sigma, cfg.learn_sigma, cfg.sde_steps, cfg.sigma_schedule, {"finetune": asdict(cfg)},
                             squash=cfg.algo == "sac")
    reference = finetune_policy(bc, cfg.sigma, False, cfg.sde_steps, cfg.sigma_schedule).requires_grad_(False)
    state_dim, n_exec = policy.config.state_dim, policy.config.n_action_steps
    sigma_params = list(policy.sigma.parameters())
    groups = [{"params": list(policy.model.parameters()), "lr": cfg.lr}]
    groups += [{"params": sigma_params, "lr": cfg.sigma_lr}] if sigma_params else []
    buffer = None
    if cfg.algo == "ppo":
        critic = ValueNet(state_dim)
        optimizers = {"main": torch.optim.Adam(groups + [{"params": list(critic.parameters()),
                                                          "lr": cfg.critic_lr}])}
    else:
        critic = TwinQ(state_dim, n_exec * policy.config.action_dim)
        q_target = make_target(critic)
        temperature = Temperature(cfg.alpha, cfg.target_entropy)
        optimizers = {"actor": torch.optim.Adam(groups), "q": torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr),
                      "alpha": torch.optim.Adam(temperature.parameters(), lr=cfg.alpha_lr)}
        buffer = ReplayBuffer(cfg.buffer_size)
    gen = torch.Generator().manual_seed(cfg.seed)
    iteration, env_steps, history, evals = 0, 0, [], []

    bc_digest = weights_digest(bc.state_dict())
    if cfg.resume and (ckpt := last_checkpoint(out)) is not None:
        st = load_state(ckpt)
        started = st.get("bc_weights_sha256")
        if started is not None and started != bc_digest:
            raise ValueError(f"--checkpoint: {cfg.checkpoint} holds other BC weights than the ones the run in {out} "
                             f"started from (its KL reference and initial policy); resume with that BC checkpoint")
        _check_resumed_config(st.get("config"), cfg, ckpt)
        policy.load_state_dict(ActionDecoderPolicy.from_pretrained(ckpt).state_dict())
        critic.load_state_dict(st["critic"])
        for k, opt in optimizers.items():
            opt.load_state_dict(st["optimizers"][k])
        if buffer is not None:
            q_target.load_state_dict(st["q_target"])
            temperature.load_state_dict(st["temperature"])
            buffer.load_state_dict(st["buffer"])
        gen.set_state(st["gen"])
        _set_rng_state(st["rng"])
        iteration, env_steps, history, evals = st["iteration"], st["env_steps"], st["history"], st["evals"]
        print(f"resume: continuing from {ckpt} (iteration {iteration}, {env_steps} env steps)", flush=True)
    elif (held := existing_run(out)) is not None:
        if cfg.resume:
            raise ValueError(f"--resume: {out} holds a run ({held}) but no checkpoint to continue from; "
                             f"choose another --output-dir, or move that run away to start anew")
        raise ValueError(f"--output-dir: {out} already holds a fine-tuning run ({held}); pass --resume to "
                         f"continue it or choose another directory")
    elif cfg.resume:
        print(f"resume: no checkpoint in {out / CKPT_DIR}; starting from the BC policy", flush=True)

    logger = RunLogger(out, "finetune_log.jsonl", env_steps, cfg.wandb_project if cfg.wandb else None, "finetune",
                       asdict(cfg))

    def make_batch(states: torch.Tensor) -> dict:
        ctx = task_context(torch.full((len(states),), task_index), num_tasks)
        return {"state": states.float(), **ctx}

    def run_eval() -> None:
        if not cfg.eval_episodes:
            return
        row = {"iteration": iteration, "env_steps": env_steps}
        for sampler in ("sde", "ode"):
            fn = make_policy_fn(policy, num_tasks, sampler, cfg.sde_steps, torch.Generator().manual_seed(cfg.seed))
            res = evaluate(fn, task, episodes=cfg.eval_episodes, seed=cfg.seed, n_action_steps=n_exec,
                           max_steps=MAX_EPISODE_STEPS, num_envs=min(cfg.num_envs, cfg.eval_episodes),
                           task_index=task_index)
            row[f"success_{sampler}"] = res["success_rate"]
        evals.append(row)
        logger.log(env_steps, {"success_sde": row["success_sde"], "success_ode": row["success_ode"]}, "eval",
                   record=False)
        print(f"eval @ {env_steps} env steps: success sde={row['success_sde']:.3f} ode={row['success_ode']:.3f}",
              flush=True)

    if not evals:
        run_eval()
    envs = [make_env(task, seed=cfg.seed * 1000 + i) for i in range(cfg.num_envs)]
    credited = trained_slice(cfg.sde_steps, cfg.trained_steps)
    t0 = time.perf_counter()
    cpu0 = time.process_time() - (history[-1].get("cpu_s", 0.0) if history else 0.0)   # carried over a resume

    def out_of_budget() -> bool:
        return env_steps >= cfg.env_steps or (cfg.max_cpu_minutes > 0 and
                                              time.process_time() - cpu0 >= 60 * cfg.max_cpu_minutes)

    group = episodes_per_layout(cfg)
    critic_warmup = 1 if cfg.critic_warmup_iters is None else cfg.critic_warmup_iters
    while not out_of_budget():
        seeds = train_layout_seeds(cfg.seed, iteration, cfg.num_envs, group)
        policy.eval()
        act = chain_actor(policy, make_batch, cfg.sde_steps, gen, cfg.logprob_reduce, squash=cfg.algo == "sac")
        ro = collect(envs, seeds, act, n_exec, cfg.max_episode_steps, stop_on_success=cfg.reward == "success")
        rec = ro.records
        rewards = decision_rewards(ro, cfg, n_exec)
        executed = ro.executed                                    # [N]: < n_exec where the episode ended mid-chunk
        with torch.no_grad():
            cut = executed < n_exec
            if bool(cut.any()):         # their unexecuted rows leave the log-prob, as the other rows' do
                rec["logp"][cut] = rescore_chain(policy, make_batch(ro.states[cut]), rec["chain"][cut], rec["grid"][0],
                                                 cfg.logprob_reduce, executed[cut])
            logp_ref = torch.cat([rescore_chain(reference, make_batch(ro.states[i:i + 512]), rec["chain"][i:i + 512],
                                                rec["grid"][0], cfg.logprob_reduce, executed[i:i + 512])
                                  for i in range(0, len(rewards), 512)])
        # KL(π_θ ‖ π_BC) per credited step on the chains π_θ just sampled: the one `kl_bc` (printed, logged,
        # plotted); the update's penalty term, on chains of the policy before the update, is `kl_bc_update`.
        kl_rollout = float(k3_kl(logp_ref - rec["logp"])[:, credited].mean())
        norm = policy.normalizers["state"].normalize
        if cfg.algo == "ppo":
            with torch.no_grad():
                values = critic(norm(ro.states), ro.progress)
                next_values = critic(norm(ro.next_states), ro.next_progress)
            adv, ret = gae(rewards, values, next_values, episode_ends(ro), ro.last, cfg.gamma, cfg.gae_lambda)
            if group > 1:
                adv = group_advantages(rewards, ro.last, cfg.gamma, group)
            data = {"states": ro.states, "state_norm": norm(ro.states), "progress": ro.progress, "chain": rec["chain"],
                    "grid": rec["grid"][0], "logp_old": rec["logp"], "logp_ref": logp_ref, "adv": adv, "ret": ret,
                    "executed": executed}
            stats = ppo_update(policy, critic, optimizers["main"], make_batch, data, cfg, gen,
                               update_policy=group > 1 or iteration >= critic_warmup)
        else:
            buffer.add({"state": ro.states, "progress": ro.progress, "actions": rec["actions"], "reward": rewards,
                        "next_state": ro.next_states, "next_progress": ro.next_progress, "done": episode_ends(ro)})
            stats, n_updates = {}, max(1, int(cfg.sac_updates_per_decision * len(rewards)))
            if buffer.size >= cfg.sac_batch_size:
                runs = [sac_update(policy, reference, critic, q_target, temperature, optimizers, buffer, make_batch, cfg,
                                   gen) for _ in range(n_updates)]
                stats = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        iteration += 1
        env_steps += ro.env_steps
        mult = float(policy.sigma.multiplier.detach()) if cfg.learn_sigma else 1.0
        row = {"iteration": iteration, "env_steps": env_steps, "return": float(np.mean(ro.episode_returns)),
               "success": float(np.mean(ro.episode_success)), "episode_length": float(np.mean(ro.episode_lengths)),
               "decisions": len(rewards), "sigma_mult": mult, "sigma_scale": cfg.sigma * mult, **stats,
               "kl_bc": kl_rollout,
               "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - cpu0}
        if not all(math.isfinite(v) for v in row.values() if isinstance(v, float)):
            raise FloatingPointError(f"fine-tuning diverged at iteration {iteration} ({row}); lower --lr")
        history.append(row)
        logger.log(env_steps, row, "rl")
        ratio = f" ratio [{row['ratio_min']:.3f}, {row['ratio_max']:.3f}] clip {row['clipfrac']:.3f} " \
                f"epochs {row['epochs']} lr {row['lr']:.2e}" if "ratio_min" in row else ""
        print(f"iter {iteration} env_steps {env_steps} return {row['return']:.1f} success {row['success']:.2f} "
              f"σ×{mult:.3f} kl_bc {kl_rollout:.4f}{ratio}", flush=True)
        if cfg.eval_every and iteration % cfg.eval_every == 0:
            run_eval()
        if iteration % cfg.checkpoint_every == 0 or out_of_budget():
            state = {"iteration": iteration, "env_steps": env_steps, "history": history, "evals": evals,
                     "config": asdict(cfg), "bc_weights_sha256": bc_digest,
                     "critic": critic.state_dict(), "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
                     "gen": gen.get_state(), "rng": _rng_state()}
            if buffer is not None:
                state.update(q_target=q_target.state_dict(), buffer=buffer.state_dict(),
                             temperature=temperature.state_dict())
            write_checkpoint(out, iteration, policy, state)
    if not evals or evals[-1]["iteration"] != iteration:
        run_eval()
    for env in envs:
        env.close()
    final = save_final(out, policy, env_steps)
    logger.close()
    (out / "finetune_log.json").write_text(json.dumps({"config": asdict(cfg), "task": task, "history": history,
                                                       "evals": evals}, indent=1))
    plot_curves(history, evals, out / "finetune.png", f"{cfg.algo} on {task}")
    print(f"saved {final} ({time.perf_counter() - t0:.0f} s of fine-tuning)", flush=True)
    return final
