"""`action-decoder finetune`: RL fine-tuning of a BC checkpoint, through its SDE sampler (PPO, SAC)
or in its noise space (DSRL: a noise actor steers the frozen decoder, `rl/dsrl.py`).

One iteration = one episode on each of `num_envs` lockstep envs (layouts seeded from the
iteration number, below the evaluation seeds), then PPO epochs on the stored chains, or
SAC / DSRL steps on a replay buffer. Checkpoints (`checkpoints/step_N`, `checkpoints/last`) are
written atomically at iteration boundaries with the critic, optimisers, generators and
history, so `--resume` continues exactly; a SAC or DSRL iteration also checkpoints inside itself
(`checkpoint_minutes`, and on Ctrl-C) with its progress (`pending`). See `finetune` for the
CPU budget and Ctrl-C. The result (`final/`) is a `save_pretrained`
directory that `action-decoder eval` reads; it samples with the fine-tuned SDE by default (DSRL:
through the noise actor and the decoder's deterministic sampler).
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import sys
import threading
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch

from ..evaluate import check_simulator_policy, make_policy_fn
from ..model_card import weights_digest
from ..noise_actor import kl_to_prior
from ..policy import ActionDecoderPolicy
from ..run_dir import (CKPT_DIR, FINAL, _rng_state, _set_rng_state, existing_run, last_checkpoint, load_state,
                       run_dir_lock, save_final, write_checkpoint)
from ..tracking import RunLogger, require_wandb
from ..train import task_context
from .critics import QEnsemble, TwinQ, ValueNet
from .dsrl import (KL_MULTIPLIER_LR, POOL_SIZE, PRIOR_PAIRS, KLMultiplier, alias_mode, decode_pool, dsrl_policy,
                   dsrl_update, noise_actor_fn)
from .ppo import gae, group_advantages, k3_kl, ppo_update, trained_slice
from .rollout import collect
from .sac import ReplayBuffer, Temperature, make_target, sac_update
from .sde_policy import finetune_policy, rescore_chain, sample_chain, squash_to_box, step_numel

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
                         "checkpoint_every", "checkpoint_minutes", "resume", "wandb", "wandb_project"})
"""Options that set a run's budget, location or logging: `--resume` may change them; the others define the run."""


def train_layout_seeds(seed: int, iteration: int, num_envs: int, group_size: int) -> list[int]:
    """The training layouts (env seeds) of one iteration, one per env: `num_envs / group_size` distinct
    layouts, each played by `group_size` consecutive envs; consecutive iterations take the next ones."""
    layouts = num_envs // group_size
    start = seed * LAYOUT_STRIDE + iteration * layouts
    return [TRAIN_LAYOUT_BASE + (start + i // group_size) % TRAIN_LAYOUT_SPAN for i in range(num_envs)]


@dataclass
class FinetuneConfig:
    """Fine-tune a BC checkpoint with RL on its Meta-World task."""

    checkpoint: str
    """A `save_pretrained` directory of a BC policy (e.g. outputs/train/final); PPO and SAC need flow_matching or mean_flow."""
    output_dir: str = "outputs/finetune"
    """Directory of the run: checkpoints/, final/, logs (new, or an earlier run's with --resume)."""
    algo: Literal["ppo", "sac", "dsrl"] = "ppo"
    """RL algorithm: ppo or sac train the decoder through its SDE chain; dsrl trains a noise actor that steers the frozen decoder."""
    task: Optional[str] = None
    """Task to fine-tune on (default: the checkpoint's task; required for multi-task checkpoints)."""
    env_steps: Optional[int] = None
    """Environment steps to collect, stopping at the first iteration boundary past it (default 100 000; 200 000 with dsrl)."""
    max_cpu_minutes: float = 0.0
    """Budget in CPU minutes of fine-tuning (0: none)."""
    num_envs: Optional[int] = None
    """Lockstep envs; each iteration runs one episode on each (default 32; 8 with dsrl)."""
    group_size: Optional[int] = None
    """PPO: episodes per training layout; above 1, GRPO-style group advantages (None: 4)."""
    max_episode_steps: int = 200
    """Episode cap of the training episodes, in env steps (evaluation runs 500)."""
    seed: int = 0
    """Seed of the training layouts, the SDE noise and the networks."""
    sde_steps: int = 10
    """Denoising steps K of the SDE chain (also for MeanFlow, whose 1-step ODE has no density)."""
    sigma_schedule: Literal["explore", "fixed"] = "fixed"
    """σ(t): fixed (a at every t) or explore (a·√((1 − t)/max(t, 0.1)), Flow-GRPO)."""
    sigma: float = 0.25
    """Scale a of the σ(t) schedule, in normalised action units."""
    learn_sigma: bool = True
    """Learn a multiplier of σ(t) (starts at 1)."""
    lr: float = 1e-4
    """Learning rate of the velocity network (with --lr-schedule adaptive: its start)."""
    lr_schedule: Literal["adaptive", "fixed"] = "fixed"
    """PPO: fixed, or adaptive (divided or multiplied by 1.5 to keep the KL near --target-kl)."""
    lr_warmup_updates: int = 0
    """PPO, fixed schedule: updates of linear learning-rate warm-up (0: none)."""
    sigma_lr: float = 3e-3
    """Learning rate of the σ multiplier."""
    critic_lr: Optional[float] = None
    """Learning rate of the critic (default 1e-3; 3e-4 with dsrl)."""
    gamma: float = 0.99
    """Discount per decision (one chunk)."""
    gae_lambda: float = 0.95
    """λ of GAE (PPO with the critic)."""
    reward: Optional[Literal["dense", "success"]] = None
    """dense: the env's reward per chunk / 10; success: --success-reward at success, plus shaping (default dense; success with dsrl)."""
    success_reward: float = 1.0
    """`--reward success`: reward on the decision that reaches success (the episode ends there)."""
    shaping_scale: float = 0.1
    """Weight k of the potential-based shaping k·(γ·Φ(s') − Φ(s)) of --reward success (0: none)."""
    logprob_reduce: Literal["sum", "mean"] = "sum"
    """PPO: per-step log-prob of the chunk summed over H×D (true density) or averaged (Flow-GRPO; the KLs are then per element)."""
    trained_steps: int = 10
    """The last N denoising steps enter the PPO/KL objective."""
    clip_eps: float = 0.2
    """PPO's ratio clip ε."""
    ppo_epochs: int = 4
    """PPO epochs per iteration."""
    minibatch_size: int = 512
    """PPO minibatch size, in decisions."""
    target_kl: float = 0.05
    """PPO: stop an iteration's epochs when the approximate KL to the rollout policy exceeds 1.5×this."""
    vf_coef: float = 0.5
    """PPO: weight of the value loss."""
    kl_coef: float = 0.0
    """Weight of KL(π_θ ‖ π_BC) on the chains; DSRL: of the noise actor's KL to N(0, I) per element (0: off)."""
    kl_target: Optional[float] = None
    """dsrl: trust region: a learnt multiplier holds the noise actor's KL to N(0, I) at most this, in nats per element (None: off)."""
    critic_warmup_iters: Optional[int] = None
    """Iterations that train only the critics: PPO's value head with --group-size 1 (None: 1); dsrl's Q (None: 0)."""
    ratio_tol: float = 1e-4
    """PPO: tolerated |ratio − 1| before the first update of an iteration, on top of float rounding (`ppo.rescore_rounding`)."""
    alpha: float = 0.01
    """SAC: initial entropy weight α (log-probs per action dimension)."""
    alpha_lr: float = 3e-2
    """SAC: learning rate of log α (0: α fixed)."""
    target_entropy: Optional[float] = None
    """SAC: entropy per action dimension that α holds (None: the initial policy's); dsrl: per noise element (None: 0)."""
    tau: float = 0.005
    """SAC: rate of the target critics' moving average."""
    sac_batch_size: int = 128
    """SAC batch size, in transitions."""
    sac_updates_per_decision: Optional[float] = None
    """SAC and dsrl updates per collected decision (default 0.5; 2 with dsrl)."""
    steps: Optional[int] = None
    """dsrl: sampling steps of the frozen decoder (default: the checkpoint's)."""
    noise_critic: Literal["noise", "action"] = "action"
    """dsrl: Q on the executed actions with noise aliasing (DSRL-NA) or on the noise (DSRL-SAC)."""
    alias_decodes: Literal["auto", "update", "iteration"] = "auto"
    """dsrl action critic: decode the actor's chunks at every update or once an iteration for a pool (auto: update when a chunk takes ≤ 2 network calls)."""
    critics: int = 2
    """dsrl: members of each critic ensemble (2: twin Q; more: targets from the minimum of 2 drawn at random)."""
    noise_hidden: int = 256
    """dsrl: width of the noise actor's two hidden layers."""
    noise_bound: float = 2.5
    """dsrl: bound b of the actor's noise, per element, in (−b, b)."""
    noise_lr: float = 3e-4
    """dsrl: learning rate of the noise actor."""
    buffer_size: int = 100_000
    """SAC replay buffer size, in transitions."""
    grad_clip: float = 1.0
    """Largest gradient norm; larger ones are clipped."""
    eval_episodes: int = 20
    """Closed-loop evaluation episodes (eval layouts) before, every `eval_every` iterations, and after (0: none)."""
    eval_every: int = 0
    """Iterations between evaluations (0: only before and after)."""
    checkpoint_every: int = 5
    """Iterations between resumable checkpoints."""
    checkpoint_minutes: float = 10.0
    """SAC: also checkpoint inside an iteration once this many CPU minutes passed since the last checkpoint (0: off)."""
    resume: bool = False
    """Continue from the last checkpoint in --output-dir."""
    wandb: bool = False
    """Also log to Weights & Biases (the [wandb] extra); TensorBoard and JSONL logs are always written."""
    wandb_project: str = "action-decoder"
    """Weights & Biases project name."""


BEST, BEST_EVAL = "best", "best_eval.json"
"""`out/best`: the weights of the run's best evaluation (`eval_rank`), with that evaluation in `best_eval.json`."""


def eval_rank(row: dict) -> tuple:
    """What makes an evaluation better: success with the SDE (the fine-tuned policy's default sampler),
    then with the ODE (DSRL's only sampler). Among equal ones the earliest is kept."""
    return row.get("success_sde", row["success_ode"]), row["success_ode"]


ALGO_DEFAULTS = {"env_steps": {"ppo": 100_000, "sac": 100_000, "dsrl": 200_000},
                 "num_envs": {"ppo": 32, "sac": 32, "dsrl": 8},
                 "sac_updates_per_decision": {"ppo": 0.5, "sac": 0.5, "dsrl": 2.0},
                 "critic_lr": {"ppo": 1e-3, "sac": 1e-3, "dsrl": 3e-4},
                 "reward": {"ppo": "dense", "sac": "dense", "dsrl": "success"}}
"""The values an option left at None takes, per algorithm."""
CRITIC_WARMUP_ITERS = {"ppo": 1, "dsrl": 0}
"""`--critic-warmup-iters` left at None, per algorithm with a critic-only phase."""
DSRL_TARGET_ENTROPY = 0.0
"""DSRL's default entropy per noise element (a Gaussian of std ≈ 0.24)."""


def with_defaults(cfg: FinetuneConfig) -> FinetuneConfig:
    """`cfg` with the options left at None set to their algorithm's default (`ALGO_DEFAULTS`)."""
    return replace(cfg, **{k: v[cfg.algo] for k, v in ALGO_DEFAULTS.items()
                           if getattr(cfg, k) is None and cfg.algo in v})


def _successes(row: dict) -> str:
    """An evaluation's success rates by sampler: "sde=0.450 ode=0.500" (DSRL: ode only)."""
    return " ".join(f"{k[len('success_'):]}={v:.3f}" for k, v in row.items() if k.startswith("success_"))


def episodes_per_layout(cfg: FinetuneConfig) -> int:
    """Episodes per training layout: `--group-size`, by default 4 with PPO and 1 with SAC."""
    return cfg.group_size if cfg.group_size is not None else 4 if cfg.algo == "ppo" else 1


def _check(cfg: FinetuneConfig) -> None:
    if cfg.group_size is not None and cfg.algo != "ppo":
        raise ValueError(f"--group-size: only with --algo ppo (SAC and DSRL play one layout per env), got "
                         f"{cfg.group_size} with --algo {cfg.algo}")
    for name in ("env_steps", "num_envs", "group_size", "max_episode_steps", "sde_steps", "ppo_epochs", "minibatch_size",
                 "sac_batch_size", "buffer_size", "checkpoint_every", "steps", "noise_hidden"):
        if getattr(cfg, name) is not None and getattr(cfg, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive integer, got {getattr(cfg, name)}")
    for name in ("sigma", "alpha", "lr", "sigma_lr", "critic_lr", "clip_eps", "target_kl", "ratio_tol", "grad_clip",
                 "sac_updates_per_decision", "noise_bound", "noise_lr"):
        if not getattr(cfg, name) > 0:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive number, got {getattr(cfg, name)}")
    for name in ("kl_coef", "alpha_lr", "vf_coef", "eval_episodes", "eval_every", "lr_warmup_updates",
                 "shaping_scale", "max_cpu_minutes", "checkpoint_minutes"):
        if not getattr(cfg, name) >= 0:                 # NaN fails too
            raise ValueError(f"--{name.replace('_', '-')}: expected >= 0, got {getattr(cfg, name)}")
    for name in ("sigma", "alpha", "lr", "sigma_lr", "critic_lr", "clip_eps", "target_kl", "ratio_tol", "grad_clip",
                 "sac_updates_per_decision", "success_reward", "kl_coef", "shaping_scale", "noise_bound", "noise_lr"):
        if not math.isfinite(getattr(cfg, name)):
            raise ValueError(f"--{name.replace('_', '-')}: expected a finite number, got {getattr(cfg, name)}")
    if not cfg.success_reward > 0:
        raise ValueError(f"--success-reward: expected a positive reward for reaching success, got {cfg.success_reward}")
    if cfg.critics < 2:
        raise ValueError(f"--critics: expected an ensemble of at least 2 members, got {cfg.critics}")
    if not SIGMA_RANGE[0] <= cfg.sigma <= SIGMA_RANGE[1]:
        raise ValueError(f"--sigma: expected a noise scale in [{SIGMA_RANGE[0]:g}, {SIGMA_RANGE[1]:g}] (actions are "
                         f"normalised to unit scale), got {cfg.sigma}")
    if cfg.algo != "ppo" and cfg.buffer_size < cfg.sac_batch_size:
        raise ValueError(f"--buffer-size: expected at least --sac-batch-size ({cfg.sac_batch_size}) transitions, or "
                         f"{cfg.algo.upper()} never updates; got {cfg.buffer_size}")
    if cfg.kl_target is not None:
        if cfg.algo != "dsrl":
            raise ValueError(f"--kl-target: only with --algo dsrl (the noise actor's KL to N(0, I)), got --algo {cfg.algo}")
        if not (math.isfinite(cfg.kl_target) and cfg.kl_target > 0):
            raise ValueError(f"--kl-target: expected a positive finite KL per noise element in nats, got {cfg.kl_target}")
        if cfg.kl_coef > 0:
            raise ValueError(f"--kl-target: the trust region's weight is learnt; drop --kl-coef {cfg.kl_coef} "
                             f"(a fixed weight) or --kl-target")
    if cfg.target_entropy is not None and not math.isfinite(cfg.target_entropy):
        raise ValueError(f"--target-entropy: expected a finite number, got {cfg.target_entropy}")
    if cfg.max_episode_steps > 500:
        raise ValueError(f"--max-episode-steps: Meta-World caps episodes at 500 steps, got {cfg.max_episode_steps}")
    if cfg.lr_warmup_updates and (cfg.algo != "ppo" or cfg.lr_schedule != "fixed"):
        raise ValueError(f"--lr-warmup-updates: only with --algo ppo and --lr-schedule fixed, got "
                         f"{cfg.lr_warmup_updates} with --algo {cfg.algo} --lr-schedule {cfg.lr_schedule}")
    if cfg.critic_warmup_iters is not None:
        if cfg.critic_warmup_iters < 0:
            raise ValueError(f"--critic-warmup-iters: expected >= 0, got {cfg.critic_warmup_iters}")
        if cfg.algo == "sac" or (cfg.algo == "ppo" and episodes_per_layout(cfg) > 1):
            raise ValueError(f"--critic-warmup-iters: only with PPO's critic (--group-size 1) or --algo dsrl; "
                             f"{'SAC' if cfg.algo == 'sac' else 'group advantages'} (--algo {cfg.algo}, --group-size "
                             f"{episodes_per_layout(cfg)}) have no critic-only phase, got {cfg.critic_warmup_iters}")
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


def returns_to_go(rewards: torch.Tensor, last: torch.Tensor, gamma: float) -> torch.Tensor:
    """[N] discounted return each decision earned until its episode ended, over decisions stored
    episode by episode in time order (`last` marks each episode's final decision): what a critic's
    value of the behaviour policy should match (nothing is bootstrapped past an episode's end)."""
    zeros = torch.zeros_like(rewards)
    return gae(rewards, zeros, zeros, last, last, gamma, 1.0)[0]     # λ = 1 with no values: the returns


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
        pts = [(e["env_steps"], e[f"success_{sampler}"]) for e in evals if f"success_{sampler}" in e]
        if pts:
            axes[0].plot(*zip(*pts), marker=marker, label=f"eval ({sampler})")
    axes[0].set(xlabel="env steps", ylabel="success", ylim=(-0.02, 1.02), title=title)
    axes[0].legend(fontsize=7)
    axes[1].plot(x, [h["return"] for h in history])
    axes[1].set(xlabel="env steps", ylabel="episode return (env reward)")
    if all("sigma_mult" in h for h in history):
        axes[2].plot(x, [h["sigma_mult"] for h in history], label="σ multiplier")
    axes[2].plot(x, [h["kl_bc"] for h in history], label="KL to BC (per step; DSRL: noise actor to N(0, I))")
    axes[2].set(xlabel="env steps")
    axes[2].legend(fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def shaping(ro, gamma: float) -> torch.Tensor:
    """γ·Φ(s′) − Φ(s) per decision [N], Φ = env reward / 10 (Meta-World's rewards lie in [0, 10]),
    Φ(s₀) = 0 (the env's reward at s₀ comes only with an action, which would make the first term
    depend on it) and Φ(s′) = 0 wherever the critics bootstrap nothing (`episode_ends`: success, and
    the training cap, which ends the MDP of heads that see the episode's progress). Summed over an
    episode that ends there, it telescopes to 0, so the shaped return is the unshaped one and the
    policy it favours is the one the success reward favours (an episode that hovers near the goal
    until the cap keeps no k·γⁿ·Φ(sₙ)). An episode cut before the cap without success (an env's own
    limit) keeps Φ(s′), which the critics' bootstrap there balances."""
    phi_next = torch.where(episode_ends(ro), torch.zeros_like(ro.reward_after), ro.reward_after / 10)
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


@contextlib.contextmanager
def graceful_interrupt():
    """While the block runs (in the main thread), a first Ctrl-C (SIGINT) only sets the yielded
    flag["set"], which the loop reads between updates; a second one raises KeyboardInterrupt at once."""
    flag = {"set": False}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def on_sigint(signum, frame):
        if flag["set"]:
            raise KeyboardInterrupt
        flag["set"] = True
        print("finetune: interrupted; stopping at the next update or rollout's end to write a checkpoint "
              "(Ctrl-C again stops at once)", file=sys.stderr, flush=True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


def finetune(cfg: FinetuneConfig) -> Path:
    """Run the fine-tuning; returns the `final/` checkpoint directory. The output directory is
    locked for the run (`run_dir.run_dir_lock`): a second run on it stops at once.

    Budget: the run stops before a rollout the CPU left cannot pay for (its cost measured on the
    previous rollout) and between two updates (SAC steps, PPO minibatches) once `max_cpu_minutes`
    is spent, so it ends within about one update's cost of the budget; the iteration it cut logs
    the updates it took (`updates`) and is checkpointed. Ctrl-C stops the same way, after the current
    update (or rollout), writes a checkpoint and raises KeyboardInterrupt: an interrupted SAC
    iteration is checkpointed with its progress (`pending`) so that `--resume` continues it exactly;
    a PPO iteration ends at its last update, as with the budget."""
    cfg = with_defaults(cfg)
    _check(cfg)
    with run_dir_lock(Path(cfg.output_dir)), graceful_interrupt() as interrupted:
        return _finetune(cfg, interrupted)


def _finetune(cfg: FinetuneConfig, interrupted: Optional[dict] = None) -> Path:
    from ..envs import evaluate, make_env
    from ..envs.metaworld_tasks import MAX_EPISODE_STEPS

    out = Path(cfg.output_dir)
    bc = ActionDecoderPolicy.from_pretrained(cfg.checkpoint)
    if bc.config.n_obs_steps > 1:
        raise ValueError(f"--checkpoint: RL fine-tuning rolls out and re-scores chunks from one observation each; "
                         f"{cfg.checkpoint} conditions on the last {bc.config.n_obs_steps} (n_obs_steps); fine-tune a "
                         f"policy trained with --n-obs-steps 1")
    trained = list(bc.config.extra.get("tasks") or [])
    num_tasks = max(len(trained), 1)
    torch.manual_seed(cfg.seed)
    # The decoder (DDPM refused, except for dsrl), then the simulator, then the task: each refusal is the one that applies.
    dsrl = cfg.algo == "dsrl"
    if dsrl:
        policy = dsrl_policy(bc, cfg.noise_hidden, cfg.noise_bound, cfg.steps, {"finetune": asdict(cfg)})
        reference = None
    else:
        policy = finetune_policy(bc, cfg.sigma, cfg.learn_sigma, cfg.sde_steps, cfg.sigma_schedule,
                                 {"finetune": asdict(cfg)}, squash=cfg.algo == "sac")
        reference = finetune_policy(bc, cfg.sigma, False, cfg.sde_steps, cfg.sigma_schedule).requires_grad_(False)
    check_simulator_policy(bc, cfg.checkpoint, cfg.task, "finetune")
    task, task_index = _resolve_task(cfg, trained)
    state_dim, n_exec = policy.config.state_dim, policy.config.n_action_steps
    sigma_params = list(policy.sigma.parameters())
    groups = [{"params": list(policy.model.parameters()), "lr": cfg.lr}]
    groups += [{"params": sigma_params, "lr": cfg.sigma_lr}] if sigma_params else []
    buffer, critics, multiplier = None, {}, None
    if dsrl:
        critic = QEnsemble(state_dim, policy.config.action_chunk_size * policy.config.action_dim,  # Q(s, w)
                           cfg.critics)
        critics = {"q": critic, "q_target": make_target(critic)}
        temperature = Temperature(cfg.alpha, DSRL_TARGET_ENTROPY if cfg.target_entropy is None else cfg.target_entropy)
        optimizers = {"actor": torch.optim.Adam(policy.noise_actor.parameters(), lr=cfg.noise_lr),
                      "q": torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr),
                      "alpha": torch.optim.Adam(temperature.parameters(), lr=cfg.alpha_lr)}
        if cfg.kl_target is not None:
            multiplier = KLMultiplier(cfg.kl_target)
            optimizers["kl"] = torch.optim.Adam(multiplier.parameters(), lr=KL_MULTIPLIER_LR)
        alias = alias_mode(policy, cfg.alias_decodes) if cfg.noise_critic == "action" else None
        if alias is not None:
            q_action = QEnsemble(state_dim, n_exec * policy.config.action_dim, cfg.critics)        # Q_A(s, a)
            critics.update(q_action=q_action, q_action_target=make_target(q_action))
            optimizers["q_action"] = torch.optim.Adam(q_action.parameters(), lr=cfg.critic_lr)
        buffer = ReplayBuffer(cfg.buffer_size)
    elif cfg.algo == "ppo":
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
    iteration, env_steps, history, evals, pending = 0, 0, [], [], None
    interrupted = {"set": False} if interrupted is None else interrupted

    bc_digest = weights_digest(bc.state_dict())
    if cfg.resume and (ckpt := last_checkpoint(out)) is not None:
        st = load_state(ckpt)
        started = st.get("bc_weights_sha256")
        if started is not None and started != bc_digest:
            raise ValueError(f"--checkpoint: {cfg.checkpoint} holds other BC weights than the ones the run in {out} "
                             f"started from (its KL reference and initial policy); resume with that BC checkpoint")
        _check_resumed_config(st.get("config"), cfg, ckpt)
        if multiplier is not None and "kl_multiplier" not in st:
            raise ValueError(f"--kl-target: the run in {out} was started without a trust region; resume it without "
                             f"--kl-target, or start a new run in another --output-dir")
        policy.load_state_dict(ActionDecoderPolicy.from_pretrained(ckpt).state_dict())
        critic.load_state_dict(st["critic"])
        for k, opt in optimizers.items():
            opt.load_state_dict(st["optimizers"][k])
        for k, net in critics.items():
            net.load_state_dict(st["critics"][k])
        if buffer is not None:
            if not dsrl:
                q_target.load_state_dict(st["q_target"])
            temperature.load_state_dict(st["temperature"])
            if multiplier is not None:
                multiplier.load_state_dict(st["kl_multiplier"])
            buffer.load_state_dict(st["buffer"])
        gen.set_state(st["gen"])
        _set_rng_state(st["rng"])
        iteration, env_steps, history, evals = st["iteration"], st["env_steps"], st["history"], st["evals"]
        pending = st.get("pending")                 # an iteration interrupted between its SAC updates
        inside = (f"; inside iteration {iteration + 1}, after {len(pending['runs'])} of its "
                  f"{pending['n_updates']} updates" if pending else "")
        print(f"resume: continuing from {ckpt} (iteration {iteration}, {env_steps} env steps{inside})", flush=True)
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
        for sampler in ("ode",) if dsrl else ("sde", "ode"):
            fn = make_policy_fn(policy, num_tasks, sampler, policy.config.num_inference_timesteps if dsrl else cfg.sde_steps,
                                torch.Generator().manual_seed(cfg.seed))
            res = evaluate(fn, task, episodes=cfg.eval_episodes, seed=cfg.seed, n_action_steps=n_exec,
                           max_steps=MAX_EPISODE_STEPS, num_envs=min(cfg.num_envs, cfg.eval_episodes),
                           task_index=task_index)
            row[f"success_{sampler}"] = res["success_rate"]
        evals.append(row)
        logger.log(env_steps, {k: v for k, v in row.items() if k.startswith("success_")}, "eval", record=False)
        print(f"eval @ {env_steps} env steps: success {_successes(row)}", flush=True)
        if eval_rank(row) > max(map(eval_rank, evals[:-1]), default=(-1.0, -1.0)):
            note = (f"These are the best weights by closed-loop evaluation of an RL fine-tuning run ({cfg.algo} on "
                    f"{task}): iteration {iteration}, {env_steps} env steps, success {_successes(row)} on "
                    f"{cfg.eval_episodes} evaluation episodes (seed {cfg.seed}); `final/` beside this directory holds "
                    f"the run's last weights.")
            path = save_weights(BEST, note)
            (path / BEST_EVAL).write_text(json.dumps({**row, "episodes": cfg.eval_episodes, "seed": cfg.seed,
                                                      "task": task}, indent=1) + "\n")
            print(f"eval: best so far, saved {path}", flush=True)

    def save_weights(name: str, note: str) -> Path:
        """`save_final` to `out/<name>`, its model card saying which weights these are (`note`)."""
        policy.config.extra["finetune_weights"] = note
        try:
            return save_final(out, policy, env_steps, name=name)
        finally:
            policy.config.extra.pop("finetune_weights", None)

    if not evals:
        run_eval()
    envs = [make_env(task, seed=cfg.seed * 1000 + i) for i in range(cfg.num_envs)]
    credited = trained_slice(cfg.sde_steps, cfg.trained_steps)
    t0 = time.perf_counter()
    spent = pending["cpu_s"] if pending else history[-1].get("cpu_s", 0.0) if history else 0.0
    cpu0 = time.process_time() - spent                                                   # carried over a resume
    rollout_cpu = history[-1].get("rollout_cpu_s", 0.0) if history else 0.0
    last_save = {"cpu": time.process_time()}                                  # CPU time of the latest checkpoint

    def cpu_left() -> float:
        return 60 * cfg.max_cpu_minutes - (time.process_time() - cpu0) if cfg.max_cpu_minutes > 0 else math.inf

    def out_of_budget() -> bool:
        return env_steps >= cfg.env_steps or cpu_left() <= 0

    def stop_updates() -> bool:
        """Checked between two updates: Ctrl-C asked to stop, or the CPU budget is spent."""
        return interrupted["set"] or cpu_left() <= 0

    def save_checkpoint(partial: Optional[dict] = None) -> Path:
        state = {"iteration": iteration, "env_steps": env_steps, "history": history, "evals": evals,
                 "config": asdict(cfg), "bc_weights_sha256": bc_digest,
                 "critic": critic.state_dict(), "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
                 "gen": gen.get_state(), "rng": _rng_state()}
        if buffer is not None:
            state.update(buffer=buffer.state_dict(), temperature=temperature.state_dict(),
                         **({} if dsrl else {"q_target": q_target.state_dict()}))
        if critics:
            state["critics"] = {k: net.state_dict() for k, net in critics.items()}
        if multiplier is not None:
            state["kl_multiplier"] = multiplier.state_dict()
        if partial is not None:          # a SAC or DSRL iteration paused between its updates
            state["pending"] = {**partial, "cpu_s": time.process_time() - cpu0}
        last_save["cpu"] = time.process_time()
        return write_checkpoint(out, iteration, policy, state)

    def interrupt(partial: Optional[dict] = None):
        """Ctrl-C: checkpoint what was done (when anything was), then stop."""
        if iteration > 0 or partial is not None:
            print(f"finetune: interrupted; wrote {save_checkpoint(partial)}", file=sys.stderr, flush=True)
        for env in envs:
            env.close()
        logger.close()
        raise KeyboardInterrupt

    group = episodes_per_layout(cfg)
    critic_warmup = CRITIC_WARMUP_ITERS.get(cfg.algo, 0) if cfg.critic_warmup_iters is None else cfg.critic_warmup_iters

    def run_ends() -> bool:
        """At an iteration boundary: the env-step or CPU budget is spent, or cannot pay for the next rollout."""
        return out_of_budget() or cpu_left() < rollout_cpu

    while pending is not None or not run_ends():
        if pending is not None:          # resumed inside a SAC or DSRL iteration: its rollout is in the buffer
            base, runs, n_updates, pool = pending["base"], pending["runs"], pending["n_updates"], pending.get("pool")
            pending = None
            rollout_cpu = base["rollout_cpu_s"]
        else:
            if interrupted["set"]:
                interrupt()
            cpu_start = time.process_time()
            seeds = train_layout_seeds(cfg.seed, iteration, cfg.num_envs, group)
            policy.eval()
            act = noise_actor_fn(policy, make_batch, gen, PRIOR_PAIRS if alias == "iteration" else 0) if dsrl else \
                chain_actor(policy, make_batch, cfg.sde_steps, gen, cfg.logprob_reduce, squash=cfg.algo == "sac")
            ro = collect(envs, seeds, act, n_exec, cfg.max_episode_steps, stop_on_success=cfg.reward == "success")
            rec = ro.records
            rewards = decision_rewards(ro, cfg, n_exec)
            executed = ro.executed                                # [N]: < n_exec where the episode ended mid-chunk
            if dsrl:        # KL of the actor to N(0, I) per noise element: bounds its chunks' KL to the BC policy's
                with torch.no_grad():
                    mean, log_std = policy.noise_actor(**policy.noise_actor_inputs(make_batch(ro.states)))
                kl_rollout = float(kl_to_prior(mean, log_std).mean())
            else:
                with torch.no_grad():
                    cut = executed < n_exec
                    if bool(cut.any()):         # their unexecuted rows leave the log-prob, as the other rows' do
                        rec["logp"][cut] = rescore_chain(policy, make_batch(ro.states[cut]), rec["chain"][cut],
                                                         rec["grid"][0], cfg.logprob_reduce, executed[cut])
                    logp_ref = torch.cat([rescore_chain(reference, make_batch(ro.states[i:i + 512]),
                                                        rec["chain"][i:i + 512], rec["grid"][0], cfg.logprob_reduce,
                                                        executed[i:i + 512])
                                          for i in range(0, len(rewards), 512)])
                # KL(π_θ ‖ π_BC) per credited step on the chains π_θ just sampled: the one `kl_bc` (printed, logged,
                # plotted); the update's penalty term, on chains of the policy before the update, is `kl_bc_update`.
                numel = step_numel(rec["chain"].shape, executed) if cfg.logprob_reduce == "mean" else 1.0  # per element
                kl_rollout = float(k3_kl(logp_ref - rec["logp"], numel)[:, credited].mean())
            rollout_cpu = time.process_time() - cpu_start
            base = {"return": float(np.mean(ro.episode_returns)), "success": float(np.mean(ro.episode_success)),
                    "episode_length": float(np.mean(ro.episode_lengths)), "decisions": len(rewards),
                    "kl_bc": kl_rollout, "rollout_cpu_s": rollout_cpu, "env_steps": ro.env_steps}
            norm = policy.normalizers["state"].normalize
            if cfg.algo == "ppo":
                with torch.no_grad():
                    values = critic(norm(ro.states), ro.progress)
                    next_values = critic(norm(ro.next_states), ro.next_progress)
                adv, ret = gae(rewards, values, next_values, episode_ends(ro), ro.last, cfg.gamma, cfg.gae_lambda)
                if group > 1:
                    adv = group_advantages(rewards, ro.last, cfg.gamma, group)
                data = {"states": ro.states, "state_norm": norm(ro.states), "progress": ro.progress,
                        "chain": rec["chain"], "grid": rec["grid"][0], "logp_old": rec["logp"], "logp_ref": logp_ref,
                        "adv": adv, "ret": ret, "executed": executed}
                stats = ppo_update(policy, critic, optimizers["main"], make_batch, data, cfg, gen,
                                   update_policy=group > 1 or iteration >= critic_warmup, stop=stop_updates)
            else:
                base["return_to_go"] = float(returns_to_go(rewards, ro.last, cfg.gamma).mean())
                buffer.add({"state": ro.states, "progress": ro.progress, "actions": rec["actions"], "reward": rewards,
                            "next_state": ro.next_states, "next_progress": ro.next_progress,
                            "done": episode_ends(ro), **({k: rec[k] for k in ("noise", "prior_noise", "prior_actions")
                                                          if k in rec} if dsrl else {})})
                runs = []
                n_updates = (max(1, int(cfg.sac_updates_per_decision * len(rewards)))
                             if buffer.size >= cfg.sac_batch_size else 0)
                pool = decode_pool(policy, buffer, make_batch, POOL_SIZE, gen) \
                    if dsrl and alias == "iteration" and n_updates else None
        if cfg.algo != "ppo":            # checked between updates: Ctrl-C pauses the iteration, the budget cuts it
            while len(runs) < n_updates:
                if interrupted["set"]:
                    interrupt({"base": base, "runs": runs, "n_updates": n_updates, "pool": pool})
                if cpu_left() <= 0:
                    break
                if cfg.checkpoint_minutes and time.process_time() - last_save["cpu"] >= 60 * cfg.checkpoint_minutes:
                    save_checkpoint({"base": base, "runs": runs, "n_updates": n_updates, "pool": pool})  # long iteration
                runs.append(dsrl_update(policy, critics, temperature, optimizers, buffer, make_batch, cfg, gen, pool,
                                        multiplier, update_actor=iteration >= critic_warmup)
                            if dsrl
                            else sac_update(policy, reference, critic, q_target, temperature, optimizers, buffer,
                                            make_batch, cfg, gen))
            stats = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]} if runs else {}
            stats["updates"] = len(runs)
        iteration += 1
        env_steps += base["env_steps"]
        mult = float(policy.sigma.multiplier.detach()) if cfg.learn_sigma and not dsrl else 1.0
        row = {"iteration": iteration, "env_steps": env_steps, "return": base["return"], "success": base["success"],
               "episode_length": base["episode_length"], "decisions": base["decisions"],
               **({"return_to_go": base["return_to_go"]} if "return_to_go" in base else {}),
               **({} if dsrl else {"sigma_mult": mult, "sigma_scale": cfg.sigma * mult}), **stats, "kl_bc": base["kl_bc"],
               "rollout_cpu_s": base["rollout_cpu_s"], "wall_s": time.perf_counter() - t0,
               "cpu_s": time.process_time() - cpu0}
        if not all(math.isfinite(v) for v in row.values() if isinstance(v, float)):
            raise FloatingPointError(f"fine-tuning diverged at iteration {iteration} ({row}); lower --lr")
        history.append(row)
        logger.log(env_steps, row, "rl")
        ratio = f" ratio [{row['ratio_min']:.3f}, {row['ratio_max']:.3f}] clip {row['clipfrac']:.3f} " \
                f"epochs {row['epochs']} lr {row['lr']:.2e}" if "ratio_min" in row else ""
        print(f"iter {iteration} env_steps {env_steps} return {row['return']:.1f} success {row['success']:.2f} "
              + ("" if dsrl else f"σ×{mult:.3f} ") + f"kl_bc {row['kl_bc']:.4f}{ratio}", flush=True)
        if interrupted["set"]:
            interrupt()
        if cfg.eval_every and iteration % cfg.eval_every == 0:
            run_eval()
        if iteration % cfg.checkpoint_every == 0 or run_ends():
            save_checkpoint()
    if interrupted["set"]:                 # the last iteration's checkpoint is written
        interrupt()
    if not evals or evals[-1]["iteration"] != iteration:
        run_eval()
    for env in envs:
        env.close()
    best = max(evals, key=eval_rank) if evals else None              # the earliest among equals
    note = f"These are the last weights of an RL fine-tuning run ({cfg.algo} on {task}, {env_steps} env steps)"
    if best is not None:
        note += (f"; their evaluation: success {_successes(evals[-1])} on {cfg.eval_episodes} episodes. `best/` "
                 f"beside this directory holds the best by evaluation (iteration {best['iteration']}, success "
                 f"{_successes(best)})")
    final = save_weights(FINAL, note + ".")
    logger.close()
    (out / "finetune_log.json").write_text(json.dumps({"config": asdict(cfg), "task": task, "history": history,
                                                       "evals": evals, "best": best}, indent=1))
    plot_curves(history, evals, out / "finetune.png", f"{cfg.algo} on {task}")
    print(f"saved {final}: the last weights ({time.perf_counter() - t0:.0f} s of fine-tuning)", flush=True)
    if best is not None:
        same = " (the last evaluation's: the same weights as final/)" if best is evals[-1] else ""
        print(f"best by evaluation: {out / BEST}, iteration {best['iteration']}, success {_successes(best)}{same}",
              flush=True)
    return final
