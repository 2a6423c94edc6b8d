"""Behaviour-cloning training: demonstrations → `ActionDecoderPolicy`, resumable, data-parallel.

Runs as is, under `torchrun --nproc_per_node N` or under `accelerate launch` (both set
RANK/WORLD_SIZE; DDP underneath: gloo on CPU, NCCL on GPUs). The loss — MeanFlow's JVP
included — is computed inside the DDP wrapper's forward, so gradients are all-reduced.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Literal, Mapping, Optional

import numpy as np
import torch
from torch.utils.data import default_collate

from .config import DecoderConfig
from .model_card import weights_digest
from .policy import ActionDecoderPolicy
from .run_dir import (CKPT_DIR, FINAL, _rng_state, _set_rng_state, _writing, existing_run, resume_checkpoint,
                      run_dir_lock, save_final, write_checkpoint)
from .state_layout import shift_positions
from .tracking import RunLogger, require_wandb



@dataclass
class TrainConfig:
    """Train a decoder on Meta-World demonstrations (or any LeRobot-layout dataset), then evaluate."""

    task: str = "metaworld/push"
    """Meta-World task(s): a name, a comma-separated list, or a group (MT10, easy, medium, hard, very_hard)."""
    dataset: Optional[str] = None
    """A LeRobot dataset directory to train on instead of generated demonstrations (None: generate them)."""
    cameras: Optional[list[str]] = None
    """Cameras: a --dataset's camera keys (None: all), or Meta-World cameras to render (None: none)."""
    image_size: int = 64
    """Side of the square camera frames, in pixels."""
    decoder: Literal["DDPM", "flow_matching", "mean_flow"] = "flow_matching"
    """The decoder to train (flow_matching: 10 Euler steps; docs/guides/getting_started.md compares them)."""
    steps: int = 1500
    """Optimizer steps."""
    demos: int = 10
    """Expert demonstrations per task."""
    demo_noise: float = 0.0
    """Std of the noise added to the expert's executed actions while recording (DART; 0: none)."""
    output_dir: str = "outputs/train"
    """Directory of the run: checkpoints/, final/, logs (new, or an earlier run's with --resume)."""
    seed: int = 0
    """Seed of the network, the data order and the demonstrations (layouts s·1000 + j; 0 <= s < 500)."""
    batch_size: int = 128
    """Global batch size, split across processes."""
    lr: float = 1e-3
    """Peak AdamW learning rate, reached after the warm-up, then a cosine towards 0."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    warmup_steps: int = 100
    """Steps of linear learning-rate warm-up."""
    grad_clip: float = 1.0
    """Largest gradient norm; larger ones are clipped (grad_norm is logged before clipping)."""
    ema_decay: float = 0.999
    """Ceiling of the decay of the weight average that final/ holds (0: the raw weights)."""
    state_layout: Literal["auto", "flat", "metaworld", "metaworld_proprio"] = "auto"
    """What the state is (auto: flat with --dataset; metaworld, or metaworld_proprio with cameras)."""
    image_encoder: Literal["conv", "resnet18"] = "conv"
    """Camera backbone: conv (small, for CPUs) or resnet18 (transformers' ResNet-18; the [vlm] extra)."""
    image_encoder_pretrained: Optional[str] = None
    """resnet18: a local directory or Hub id of pretrained ResNet-18 weights (None: random)."""
    freeze_image_encoder: bool = False
    """Keep the camera backbone's weights fixed (the token projection trains)."""
    image_tokens: int = DecoderConfig.image_tokens_per_camera
    """Context tokens per camera (cells of the pooled feature map)."""
    image_shift: int = DecoderConfig.image_shift
    """Largest random shift of a training frame, in pixels (0: none)."""
    augment_shift: Optional[float] = None
    """Largest horizontal shift of the scene per sample, in metres (None: 0.05 with metaworld, else 0)."""
    n_obs_steps: int = DecoderConfig.n_obs_steps
    """Observations the policy conditions on: the current one and the n - 1 before it (stored in the checkpoint)."""
    horizon: int = 16
    """Action chunk length H, in control steps."""
    n_action_steps: int = DecoderConfig.n_action_steps
    """Actions executed from each chunk before re-planning (stored in the checkpoint)."""
    clip_actions: bool = True
    """Clamp sampled chunks to the training data's per-dimension action [min, max] (stored in the checkpoint)."""
    inference_steps: int = 0
    """Sampling steps K (0: the decoder's default: DDPM 10, flow matching 10, MeanFlow 1)."""
    hidden_size: int = 96
    """Width of the Action Expert transformer."""
    num_layers: int = 3
    """Transformer layers."""
    num_heads: int = 4
    """Attention heads."""
    num_kv_heads: int = 2
    """Key/value heads (grouped-query attention; a divisor of --num-heads)."""
    prediction_type: Literal["epsilon", "sample"] = "sample"
    """DDPM's target: epsilon (the noise) or sample (the clean chunk)."""
    meanflow_ratio_r_neq_t: float = 0.25
    """MeanFlow: fraction of (t, r) pairs with r != t."""
    meanflow_adaptive_p: float = 0.5
    """MeanFlow: power p of the adaptive loss weight 1/(error + c)^p (0: plain MSE)."""
    meanflow_time_dist: Literal["uniform", "logit_normal"] = "uniform"
    """MeanFlow: distribution of the times (t, r)."""
    meanflow_target: Optional[Literal["identity", "split"]] = None
    """MeanFlow: target of the r != t rows, the MeanFlow identity or interval consistency (None: split with --rtc-max-delay, else identity)."""
    meanflow_one_step_share: Optional[float] = None
    """MeanFlow: share of the r != t rows trained on the whole interval (t, r) = (0, 1) (None: 0.25 with --rtc-max-delay and the split target, else 0)."""
    flow_prediction: Optional[Literal["velocity", "sample"]] = None
    """Flow head output: velocity or the clean chunk (None: sample for MeanFlow, velocity for FM)."""
    rtc_max_delay: int = 0
    """Training-time real-time chunking: the largest committed prefix, in actions, the policy learns to continue (0: off)."""
    rtc_delay_dist: Literal["exp", "half_zero", "uniform"] = "exp"
    """Training-time RTC: how each chunk's delay is drawn on 0..--rtc-max-delay (exp: P(d) ∝ e^(−d); half_zero: 0 for half the chunks, else uniform; uniform)."""
    rtc_balance_rows: bool = False
    """Training-time RTC: weight row j of the loss by 1/P(d ≤ j), the share of chunks whose loss covers it."""
    rtc_prefix_noise: float = 0.0
    """Training-time RTC: std of the noise added to the committed prefix the network is fed, in normalised action units (0: clean)."""
    perturbed_prefixes: Optional[int] = None
    """Training-time RTC on generated demonstrations: copies of each frame whose committed prefix is the expert's actions shifted and noised, labelled by the expert from where it leads (None: 3 for flow_matching with --rtc-max-delay, else 0)."""
    perturbed_prefix_noise: float = 0.2
    """Std of the Gaussian noise on a perturbed prefix, in the env's action units."""
    perturbed_prefix_shift: int = 2
    """Largest time shift of a perturbed prefix from the expert's own actions, in control steps."""
    checkpoint_every: int = 500
    """Steps between resumable checkpoints."""
    log_every: int = 25
    """Steps per logged row (loss, lr, grad_norm)."""
    resume: bool = False
    """Continue from the last checkpoint in --output-dir (same optimizer and RNG state)."""
    eval_episodes: int = 20
    """Closed-loop episodes per task after training, on Meta-World tasks (0: skip)."""
    val_fraction: float = 0.1
    """Share of a --dataset's episodes held out for validation, the last ones (0: none)."""
    device: str = "auto"
    """auto (CUDA when available, else CPU), cpu, cuda, cuda:N, or another torch device."""
    compile: bool = False
    """torch.compile the network for the training steps (inductor; on a CPU it needs a C compiler)."""
    progress: bool = True
    """A progress bar on stderr when stderr is a terminal."""
    wandb: bool = False
    """Also log to Weights & Biases (the [wandb] extra); TensorBoard and JSONL logs are always written."""
    wandb_project: str = "action-decoder"
    """Weights & Biases project name."""


DEFAULT_STEPS = {"DDPM": 10, "flow_matching": 10, "mean_flow": 1}


# ---------------------------------------------------------------------- distributed
def _dist_env() -> tuple[int, int, int]:
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("LOCAL_RANK", 0))


def _device(name: str, local_rank: int) -> torch.device:
    if name == "auto":
        return torch.device(f"cuda:{local_rank}") if torch.cuda.is_available() else torch.device("cpu")
    device = torch.device(name)
    # Under torchrun a bare "cuda" means each process's own GPU, not all of them on GPU 0.
    return torch.device("cuda", local_rank) if device.type == "cuda" and device.index is None else device


# ---------------------------------------------------------------------- data
CLOSED_LOOP_ENVS = ("metaworld",)
"""Environments the library runs closed loop, as a dataset's meta/info.json names them ("env")."""


def closed_loop_env(cfg: TrainConfig) -> Optional[str]:
    """The environment that evaluates a policy trained with `cfg` in closed loop, or None: Meta-World
    for generated demonstrations and for a --dataset whose info.json says "env": "metaworld"."""
    if cfg.dataset is None:
        return "metaworld"
    from .data.lerobot_format import read_info

    env = read_info(cfg.dataset).get("env")
    return env if env in CLOSED_LOOP_ENVS else None


def held_out_count(num_episodes: int, fraction: float) -> int:
    """Episodes held out for validation: the last ``fraction`` of them, at least 1, at most all but
    one; 0 with fewer than 2 episodes or ``fraction`` 0."""
    if not 0 <= fraction < 1 or not math.isfinite(fraction):
        raise ValueError(f"--val-fraction: expected a share of episodes in [0, 1), got {fraction}")
    if num_episodes < 2 or fraction == 0:
        return 0
    return min(max(1, int(num_episodes * fraction)), num_episodes - 1)


def load_training_data(cfg: TrainConfig, quiet: bool = False):
    """(ChunkDataset, task names, held-out ChunkDataset or None) from `--dataset` or generated
    Meta-World demonstrations, with the frames of `--cameras` at `--image-size` (named in one line).
    A dataset's last episodes are held out (`held_out_count`) unless it names an environment
    (`closed_loop_env`); statistics come from the training episodes alone."""
    from .data import ChunkDataset, load_dataset, load_demos
    from .data.lerobot_format import read_info

    if cfg.dataset is None:
        prefixes = perturbed_prefixes(cfg)
        if not quiet:
            copies = (f", each with {prefixes.copies} perturbed-prefix cop{'y' if prefixes.copies == 1 else 'ies'}"
                      if prefixes else "")
            print(f"demonstrations: {cfg.demos} per task of {cfg.task}{copies} (cached after the first run)", flush=True)
        episodes = load_demos(cfg.task, cfg.demos, cfg.seed, demo_noise(cfg), cameras=cfg.cameras,
                              image_size=cfg.image_size, prefixes=prefixes)
        _say_cameras(episodes, quiet)
        return ChunkDataset(episodes, cfg.horizon, n_obs_steps=cfg.n_obs_steps), list(episodes.tasks), None
    cameras = None if cfg.cameras is None else [c for item in cfg.cameras for c in item.split(",") if c]
    if cfg.n_obs_steps > 1 and (read_info(cfg.dataset).get("source") or {}).get("relabel"):
        raise ValueError(f"--n-obs-steps: {cfg.dataset} holds relabelled plans (`action-decoder relabel`), frames "
                         f"n_action_steps apart rather than consecutive observations; expected 1, got {cfg.n_obs_steps}")
    episodes = load_dataset(cfg.dataset, cameras, cfg.image_size)
    committed = 0 if episodes.prefix_lengths is None else int(episodes.prefix_lengths.max(initial=0))
    if cfg.rtc_max_delay < committed:
        raise ValueError(f"--rtc-max-delay: {cfg.dataset}'s labels start with committed prefixes of up to {committed} "
                         f"rows (action.prefix_length, `action-decoder relabel`), which training feeds in as the clean "
                         f"prefix; expected at least {committed}, got {cfg.rtc_max_delay}")
    _say_cameras(episodes, quiet)
    n = episodes.num_episodes
    env = closed_loop_env(cfg)
    held = 0 if env else held_out_count(n, cfg.val_fraction)
    if not held and not env and not quiet:
        print(f"validation: none: {cfg.dataset} names no environment the library runs (meta/info.json "
              f"\"env\"), and holding out episodes needs >= 2 of them and --val-fraction > 0 (got {n} and "
              f"{cfg.val_fraction})", flush=True)
    if not held:
        return ChunkDataset(episodes, cfg.horizon, n_obs_steps=cfg.n_obs_steps), list(episodes.tasks), None
    train_eps, val_eps = episodes.select(n - held), episodes.select(list(range(n - held, n)))
    if not quiet:
        print(f"validation: holding out the last {held} of {n} episodes (ids {val_eps.episode_ids.tolist()}; "
              f"--val-fraction {cfg.val_fraction}); training on {n - held}", flush=True)
    return (ChunkDataset(train_eps, cfg.horizon, n_obs_steps=cfg.n_obs_steps), list(episodes.tasks),
            ChunkDataset(val_eps, cfg.horizon, n_obs_steps=cfg.n_obs_steps))


def _say_cameras(episodes, quiet: bool) -> None:
    if episodes.images and not quiet:
        size = next(iter(episodes.images.values())).shape[1:3]
        print(f"cameras: {', '.join(episodes.cameras)} ({size[0]}x{size[1]} px, decoded once: "
              f"{sum(v.nbytes for v in episodes.images.values()) / 2**20:.1f} MiB)", flush=True)


VAL_NOISE_DRAWS, VAL_SEED, VAL_BATCH = 8, 0, 256


@torch.no_grad()
def validation_metrics(policy: ActionDecoderPolicy, val, num_tasks: int, device: torch.device) -> dict:
    """The trained policy on held-out chunks (a ChunkDataset): ``val_loss``, the decoder's own
    training loss averaged over `VAL_NOISE_DRAWS` noise draws, and ``val_action_mse``, the mean
    squared error of one sampled chunk per frame (the config's sampler) against the held-out actions,
    in normalised units over the steps that are not padding. Both draw from generators seeded with
    `VAL_SEED`, so the same policy gives the same numbers."""
    was_training = policy.training
    policy.eval()
    loss_gen = torch.Generator(device=device).manual_seed(VAL_SEED)
    sample_gen = torch.Generator(device=device).manual_seed(VAL_SEED + 1)
    norm = policy.normalizers["actions"].normalize
    loss_sum, err_sum, err_count = 0.0, 0.0, 0
    for start in range(0, len(val), VAL_BATCH):
        items = default_collate([val[i] for i in range(start, min(start + VAL_BATCH, len(val)))])
        batch = {"state": items["state"].to(device), "actions": items["actions"].to(device),   # [B, S], [B, H, D]
                 **{k: v.to(device) for k, v in task_context(items["task_index"], num_tasks).items()},
                 **({"images": items["images"].to(device)} if "images" in items else {}),   # [B, N_cam, 3, S, S]
                 **({"rtc_delays": items["rtc_delay"].to(device)} if "rtc_delay" in items else {})}   # [B]
        draws = [float(policy.compute_loss(batch, loss_gen).loss) for _ in range(VAL_NOISE_DRAWS)]
        loss_sum += sum(draws) / VAL_NOISE_DRAWS * len(items["state"])
        chunk = policy.sample(batch, generator=sample_gen).actions                 # [B, H, D]
        keep = ~items["action_is_pad"].to(device)                                 # [B, H]
        err = (norm(chunk) - norm(batch["actions"])).pow(2).mean(-1)               # [B, H]
        err_sum, err_count = err_sum + float(err[keep].sum()), err_count + int(keep.sum())
    policy.train(was_training)
    return {"val_loss": loss_sum / len(val), "val_action_mse": err_sum / err_count,
            "episodes": val.dataset.episode_ids.tolist(), "frames": len(val), "noise_draws": VAL_NOISE_DRAWS,
            "seed": VAL_SEED}


def task_context(task_index: torch.Tensor, num_tasks: int) -> dict:
    """Multi-task conditioning through the context path: one one-hot token per sample."""
    if num_tasks <= 1:
        return {}
    onehot = torch.nn.functional.one_hot(task_index.long(), num_tasks).float()
    return {"context": onehot[:, None, :]}                                 # [B, 1, num_tasks]


DEFAULT_SHIFT = 0.05


def demo_noise(cfg: TrainConfig) -> float:
    """The recording noise of generated demonstrations (a `--dataset` is taken as it is)."""
    if not 0 <= cfg.demo_noise <= 1:
        raise ValueError(f"--demo-noise: expected a standard deviation in [0, 1] (actions span [-1, 1]), "
                         f"got {cfg.demo_noise}")
    if cfg.demo_noise and cfg.dataset is not None:
        raise ValueError(f"--demo-noise: recording noise applies to generated demonstrations, not to "
                         f"--dataset {cfg.dataset}; drop one of them")
    return cfg.demo_noise


PERTURBED_PREFIX_COPIES = {"flow_matching": 3, "mean_flow": 0}
"""Perturbed-prefix copies per frame that generated demonstrations get with --rtc-max-delay, per decoder: MeanFlow
trained on them lost success without a prefix (docs/benchmarks/rtc.md)."""


def perturbed_prefixes(cfg: TrainConfig):
    """The perturbed-prefix copies generated demonstrations get (`data.perturbed_prefixes.PerturbedPrefixes`,
    prefixes of 1..--rtc-max-delay actions), or None: --perturbed-prefixes, None resolving to the decoder's
    `PERTURBED_PREFIX_COPIES` with --rtc-max-delay and to none without; a --dataset is taken as it is."""
    from .data.perturbed_prefixes import PerturbedPrefixes

    copies, defaults = cfg.perturbed_prefixes, {f.name: f.default for f in fields(TrainConfig)}
    if copies is not None and (isinstance(copies, bool) or not isinstance(copies, int) or copies < 0):
        raise ValueError(f"--perturbed-prefixes: expected an integer >= 0 (copies of each frame), got {copies!r}")
    tuned = [f"--{k.replace('_', '-')} {getattr(cfg, k)}" for k in ("perturbed_prefix_noise", "perturbed_prefix_shift")
             if getattr(cfg, k) != defaults[k]]
    if cfg.dataset is not None:
        if copies or tuned:
            raise ValueError(f"{', '.join([f'--perturbed-prefixes {copies}'] if copies else tuned)}: perturbed "
                             f"prefixes are recorded with the simulator's expert, and --dataset {cfg.dataset} is taken "
                             f"as it is; record them into a dataset with `action-decoder record --perturbed-prefixes "
                             f"N --rtc-max-delay D`, or drop --dataset")
        return None
    if copies and not cfg.rtc_max_delay:
        raise ValueError(f"--perturbed-prefixes: training-time real-time chunking data, expected with --rtc-max-delay "
                         f"N > 0 (the longest prefix), got --perturbed-prefixes {copies} without it")
    if copies is None:
        copies = PERTURBED_PREFIX_COPIES.get(cfg.decoder, 0) if cfg.rtc_max_delay else 0
    if not copies:
        if tuned:
            raise ValueError(f"{', '.join(tuned)}: shapes perturbed prefixes, and this run has none "
                             f"(--perturbed-prefixes {cfg.perturbed_prefixes}, --rtc-max-delay {cfg.rtc_max_delay})")
        return None
    return PerturbedPrefixes(copies, cfg.rtc_max_delay, cfg.perturbed_prefix_noise, cfg.perturbed_prefix_shift)


def state_layout(cfg: TrainConfig) -> str:
    """The layout `--state-layout auto` resolves to: flat for a --dataset; for generated Meta-World
    demonstrations metaworld, or metaworld_proprio when they come with cameras (`--cameras`)."""
    if cfg.state_layout != "auto":
        return cfg.state_layout
    if cfg.dataset is not None:
        return "flat"
    return "metaworld_proprio" if cfg.cameras else "metaworld"


def augment_shift(cfg: TrainConfig) -> float:
    """The shift augmentation's range; only Meta-World's layout says where the positions are."""
    layout = state_layout(cfg)
    if cfg.augment_shift is None:
        return DEFAULT_SHIFT if layout == "metaworld" else 0.0
    if not math.isfinite(cfg.augment_shift) or cfg.augment_shift < 0:
        raise ValueError(f"--augment-shift: expected a distance >= 0 in metres, got {cfg.augment_shift}")
    if cfg.augment_shift > 0 and layout != "metaworld":
        raise ValueError(f"--augment-shift: shifting positions needs --state-layout metaworld, got "
                         f"--state-layout {cfg.state_layout} ({layout}) with --augment-shift {cfg.augment_shift}")
    return cfg.augment_shift


def flow_prediction(cfg: TrainConfig) -> str:
    """The head `cfg.flow_prediction` names, or the decoder's measured default."""
    return cfg.flow_prediction or ("sample" if cfg.decoder == "mean_flow" else "velocity")


IMAGE_OPTIONS = ("image_size", "image_encoder", "image_encoder_pretrained", "freeze_image_encoder", "image_tokens",
                 "image_shift")


def camera_fields(cfg: TrainConfig, images: Optional[Mapping[str, np.ndarray]]) -> dict:
    """The DecoderConfig fields of a dataset's cameras (`EpisodeDataset.images`: key → uint8
    [N, S, S, 3], in the order `ChunkDataset` stacks them); {} without images."""
    layout = state_layout(cfg)
    if not images:
        image_options = [f"--{f.name.replace('_', '-')}" for f in fields(TrainConfig) if f.name in IMAGE_OPTIONS
                         and getattr(cfg, f.name) != f.default]
        if image_options:
            raise ValueError(f"{', '.join(image_options)}: set the image encoder of a camera policy; this run has "
                             f"no cameras (pass --cameras)")
        if layout == "metaworld_proprio":
            raise ValueError("--state-layout: metaworld_proprio reads only the hand and gripper, so the policy "
                             "needs cameras to see objects and goal; pass --cameras or another --state-layout")
        return {}
    sizes = {tuple(frames.shape[1:]) for frames in images.values()}
    if len(sizes) != 1 or len(next(iter(sizes))) != 3 or next(iter(sizes))[0] != next(iter(sizes))[1]:
        raise ValueError(f"cameras: expected square frames [N, S, S, 3] of one size for every camera, got "
                         f"{ {k: list(v.shape) for k, v in images.items()} }")
    return {"cameras": tuple(images), "image_size": int(next(iter(sizes))[0]), "image_encoder": cfg.image_encoder,
            "image_encoder_pretrained": cfg.image_encoder_pretrained,
            "freeze_image_encoder": cfg.freeze_image_encoder, "image_tokens_per_camera": cfg.image_tokens,
            "image_shift": cfg.image_shift}


def decoder_config(cfg: TrainConfig, state_dim: int, action_dim: int, tasks: list[str],
                   images: Optional[Mapping[str, np.ndarray]] = None) -> DecoderConfig:
    """The policy's config: `cfg`'s decoder and network, conditioned on the tasks' one-hot token
    (several tasks) and on the cameras of `images` (the dataset's `EpisodeDataset.images`)."""
    k = cfg.inference_steps or DEFAULT_STEPS[cfg.decoder]
    return DecoderConfig(state_layout=state_layout(cfg), **camera_fields(cfg, images),
        decoder_type=cfg.decoder, prediction_type=cfg.prediction_type, num_inference_timesteps=k,
        action_chunk_size=cfg.horizon, n_obs_steps=cfg.n_obs_steps, n_action_steps=cfg.n_action_steps,
        clip_actions=cfg.clip_actions,
        state_dim=state_dim,
        action_dim=action_dim, hidden_size=cfg.hidden_size, num_hidden_layers=cfg.num_layers,
        num_attention_heads=cfg.num_heads, num_key_value_heads=cfg.num_kv_heads,
        context_dim=len(tasks) if len(tasks) > 1 else None,
        meanflow_ratio_r_neq_t=cfg.meanflow_ratio_r_neq_t, meanflow_adaptive_p=cfg.meanflow_adaptive_p,
        meanflow_time_dist=cfg.meanflow_time_dist, meanflow_target=cfg.meanflow_target,
        meanflow_one_step_share=cfg.meanflow_one_step_share,
        flow_prediction=flow_prediction(cfg), rtc_max_delay=cfg.rtc_max_delay,
        rtc_delay_dist=cfg.rtc_delay_dist, rtc_balance_rows=cfg.rtc_balance_rows, rtc_prefix_noise=cfg.rtc_prefix_noise,
        extra={"tasks": tasks, "train": {**asdict(cfg), "perturbed_prefixes": getattr(perturbed_prefixes(cfg), "copies", 0)},
               **({"observation_layout": "lerobot"} if observation_layout(cfg) == "lerobot" else {})})


def observation_layout(cfg: TrainConfig) -> Optional[str]:
    """"lerobot" for a --dataset written by `record --layout lerobot` (its info.json says so): the
    policy observes what LeRobot's Meta-World env does, and `action-decoder eval` gives it that."""
    if cfg.dataset is None:
        return None
    from .data.lerobot_format import read_info

    return read_info(cfg.dataset).get("layout")


def _batch(ds, idx: torch.Tensor, num_tasks: int, device: torch.device, shift: float = 0.0,
           generator: Optional[torch.Generator] = None) -> dict:
    items = default_collate([ds[int(i)] for i in idx])
    state = items["state"]                                                 # [B, S] or [B, n, S]
    if shift > 0:
        offset = (2 * torch.rand(len(state), 2, generator=generator) - 1) * shift   # [B, 2] metres
        if state.dim() == 3:                # one shift per sample, the same at each of its observation steps
            state = shift_positions(state.flatten(0, 1), offset.repeat_interleave(state.shape[1], 0)).view_as(state)
        else:
            state = shift_positions(state, offset)
    batch = {"state": state.to(device), "actions": items["actions"].to(device)}
    batch.update({k: v.to(device) for k, v in task_context(items["task_index"], num_tasks).items()})
    if "images" in items:
        batch["images"] = items["images"].to(device)                       # [B, (n,) N_cam, 3, S, S] uint8
    if "rtc_delay" in items:
        batch["rtc_delays"] = items["rtc_delay"].to(device)                # [B] committed rows (0: drawn)
    return batch


# ---------------------------------------------------------------------- checkpoints
def ema_decay_at(decay: float, num_averaged) -> float:
    """The weight average's decay when it has averaged `num_averaged` weights: 1 − (1 + n)^(−3/4),
    at most `decay` (0 at n = 0: the first update copies the weights)."""
    return min(decay, 1.0 - (1.0 + float(num_averaged)) ** -0.75)


def weight_average(policy, decay: float) -> Optional[torch.optim.swa_utils.AveragedModel]:
    """An exponential moving average of the policy's parameters (None when decay is 0)."""
    if decay == 0:
        return None

    def update(averaged: list, current: list, num_averaged: torch.Tensor) -> None:
        torch._foreach_lerp_(averaged, current, 1.0 - ema_decay_at(decay, num_averaged))

    return torch.optim.swa_utils.AveragedModel(policy, multi_avg_fn=update)


def lr_factor(step: int, warmup_steps: int, steps: int) -> float:
    """The learning rate of optimizer step `step` (0-based) as a fraction of `--lr`: a linear warm-up
    reaching 1 at step `warmup_steps` − 1, then a cosine from 1 at step `warmup_steps` towards 0 at
    step `steps` (diffusers' and LeRobot's cosine-with-warm-up, without their lr of 0 at step 0)."""
    warm = max(warmup_steps, 1)
    if step < warm:
        return (step + 1) / warm
    progress = min(step - warm, steps - warm) / max(steps - warm, 1)
    return 0.5 * (1 + math.cos(math.pi * progress))


def save_checkpoint(out: Path, step: int, policy, optimizer, scheduler, ranks: list, history: list,
                    ema=None) -> Path:
    """`ranks`: every process's generator states and open logging window, by rank (`rank_states`),
    so that each process of a resumed run continues its own streams and logs the same rows."""
    return write_checkpoint(out, step, policy, {
        "step": step, "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
        "ranks": ranks, "rng": _rng_state(),
        "history": history, "ema": None if ema is None else ema.state_dict()})


def rank_states(data_gen: torch.Generator, loss_gen: torch.Generator, running: list, grad_norms: list,
                world: int) -> list:
    """[{data_gen, loss_gen, window}] of every process, by rank: its generator states and the losses and
    gradient norms of its steps since the last log row (a collective: every rank calls it)."""
    mine = {"data_gen": data_gen.get_state(), "loss_gen": loss_gen.get_state().cpu(),
            "window": {"losses": [float(x) for x in running], "grad_norms": [float(x) for x in grad_norms]}}
    if world == 1:
        return [mine]
    states: list = [None] * world
    torch.distributed.all_gather_object(states, mine)
    return states


def _fmt(value) -> str:
    return ",".join(map(str, value)) if isinstance(value, list) else str(value)


RESUMABLE = ("steps", "checkpoint_every", "log_every", "eval_episodes", "progress", "device", "resume", "output_dir",
             "wandb", "wandb_project")
"""TrainConfig fields that `--resume` may change: they do not change what is trained (more `steps`
stretches the rest of the cosine over the new length, from the resumed step on)."""


def _effective(cfg: TrainConfig) -> dict:
    """Every field that decides what is trained, as it takes effect (defaults resolved)."""
    values = asdict(cfg)
    on_dataset = cfg.dataset is not None
    if not on_dataset:
        from .envs.metaworld_tasks import resolve_tasks
    values.update(
        dataset=str(Path(cfg.dataset).expanduser().resolve()) if on_dataset else None,
        task=None if on_dataset else resolve_tasks(cfg.task),   # --dataset ignores --task and --demos
        demos=None if on_dataset else cfg.demos, val_fraction=cfg.val_fraction if on_dataset else None,
        state_layout=state_layout(cfg), augment_shift=augment_shift(cfg),
        flow_prediction=flow_prediction(cfg), inference_steps=cfg.inference_steps or DEFAULT_STEPS[cfg.decoder],
        perturbed_prefixes=getattr(perturbed_prefixes(cfg), "copies", 0))
    return {k: v for k, v in values.items() if k not in RESUMABLE}


def resume_conflicts(saved: dict, cfg: TrainConfig) -> list[str]:
    """`--field: saved → given` for each setting of `cfg` that differs from the run `saved`
    (a checkpoint's `extra["train"]`). Fields the saved run did not record are not compared."""
    known = {f.name for f in fields(TrainConfig)}
    saved = {"perturbed_prefixes": 0, **saved}      # runs that predate the field trained without them
    old = TrainConfig(**{**asdict(cfg), **{k: v for k, v in saved.items() if k in known}})
    before, after = _effective(old), _effective(cfg)
    # A default that resolves differently only because another listed field changed is not listed.
    derived = ("state_layout", "augment_shift", "flow_prediction", "inference_steps", "perturbed_prefixes")
    return [f"--{k.replace('_', '-')}: {_fmt(before[k])} → {_fmt(after[k])}" for k in after
            if before[k] != after[k] and (k not in derived or getattr(old, k) != getattr(cfg, k))]


# ---------------------------------------------------------------------- plots and logs
def plot_losses(history: list, path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [h["step"] for h in history]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(steps, [h["loss"] for h in history])
    ax.set(xlabel="step", ylabel="training loss", title=title, yscale="log")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------- the loop
def _check(cfg: TrainConfig) -> None:
    for name in ("steps", "demos", "batch_size", "horizon", "n_obs_steps", "n_action_steps", "checkpoint_every",
                 "log_every", "image_size"):
        if getattr(cfg, name) < 1:
            raise ValueError(f"--{name.replace('_', '-')}: expected a positive integer, got {getattr(cfg, name)}")
    if cfg.rtc_max_delay and cfg.decoder == "DDPM":
        raise ValueError(f"--rtc-max-delay: training-time real-time chunking needs --decoder flow_matching or "
                         f"mean_flow, got --decoder DDPM with --rtc-max-delay {cfg.rtc_max_delay}")
    if not 0 <= cfg.rtc_max_delay < cfg.horizon:
        raise ValueError(f"--rtc-max-delay: expected an integer number of actions in [0, {cfg.horizon - 1}] "
                         f"(below --horizon {cfg.horizon}), got {cfg.rtc_max_delay}")
    if cfg.eval_episodes < 0 or cfg.inference_steps < 0:
        raise ValueError("--eval-episodes/--inference-steps: expected >= 0")
    if not 0 <= cfg.ema_decay < 1:
        raise ValueError(f"--ema-decay: expected a decay in [0, 1), got {cfg.ema_decay}")
    if not (math.isfinite(cfg.lr) and cfg.lr > 0):
        raise ValueError(f"--lr: expected a positive finite learning rate, got {cfg.lr}")
    if not (math.isfinite(cfg.weight_decay) and cfg.weight_decay >= 0):
        raise ValueError(f"--weight-decay: expected a finite decay >= 0, got {cfg.weight_decay}")
    if not (math.isfinite(cfg.grad_clip) and cfg.grad_clip > 0):
        raise ValueError(f"--grad-clip: expected a positive finite gradient norm, got {cfg.grad_clip}")
    if cfg.warmup_steps < 0:
        raise ValueError(f"--warmup-steps: expected a number of steps >= 0, got {cfg.warmup_steps}")
    defaults = {f.name: f.default for f in fields(TrainConfig)}
    if cfg.decoder != "DDPM" and cfg.prediction_type != defaults["prediction_type"]:
        raise ValueError(f"--prediction-type: sets DDPM's target; {cfg.decoder} takes --flow-prediction, got "
                         f"--prediction-type {cfg.prediction_type} with --decoder {cfg.decoder}")
    if cfg.dataset is not None:
        ignored = [f"--{k} {getattr(cfg, k)}" for k in ("task", "demos") if getattr(cfg, k) != defaults[k]]
        if ignored:
            raise ValueError(f"{', '.join(ignored)}: choose generated Meta-World demonstrations; with --dataset the "
                             f"tasks and episodes come from the dataset (drop {', '.join(ignored)})")
    if cfg.flow_prediction is not None and cfg.decoder == "DDPM":
        raise ValueError(f"--flow-prediction: sets the flow matching or MeanFlow head, not DDPM's target "
                         f"(that is --prediction-type epsilon|sample); got --flow-prediction "
                         f"{cfg.flow_prediction} with --decoder DDPM")
    demo_noise(cfg)
    perturbed_prefixes(cfg)
    held_out_count(2, cfg.val_fraction)
    require_wandb(cfg.wandb)


def train(cfg: TrainConfig) -> Path:
    """Train; returns the directory of the final `save_pretrained` checkpoint. The first process
    holds `run_dir_lock(output_dir)` throughout, so two runs never share a directory."""
    _check(cfg)
    rank, world, local_rank = _dist_env()
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() and cfg.device != "cpu" else "gloo"
        torch.distributed.init_process_group(backend)
    if cfg.batch_size % world:
        raise ValueError(f"--batch-size: expected a multiple of the {world} processes, got {cfg.batch_size}")
    with run_dir_lock(Path(cfg.output_dir)) if rank == 0 else contextlib.nullcontext():
        return _train(cfg, rank, world, _device(cfg.device, local_rank))


def _resume(cfg: TrainConfig, out: Path, device: torch.device, main: bool):
    """Before any data is loaded: the checkpoint to continue from, checked against `cfg`
    (None: start at step 0)."""
    if not cfg.resume:
        if main and (held := existing_run(out)) is not None:
            raise ValueError(f"--output-dir: {out} already holds a training run ({held}); pass --resume to "
                             f"continue it or choose another directory")
        return None
    found = resume_checkpoint(out, device)
    if found is None:
        if main and (held := existing_run(out)) is not None:
            raise ValueError(f"--resume: {out} holds a run ({held}) but no checkpoint to continue from; "
                             f"choose another --output-dir, or move that run away to start anew")
        if main:
            print(f"resume: no checkpoint in {out / CKPT_DIR}; starting from step 0", flush=True)
        return None
    ckpt, loaded, state, note = found
    conflicts = resume_conflicts(loaded.config.extra.get("train") or {}, cfg)
    if conflicts:
        raise ValueError(f"--resume: {ckpt} was trained with other settings ("
                         + "; ".join(conflicts)
                         + "); resume with the saved values or choose another --output-dir")
    if cfg.steps < state["step"]:
        raise ValueError(f"--steps: {ckpt} is at step {state['step']}; expected --steps >= {state['step']}, "
                         f"got {cfg.steps}")
    if main:
        print(f"resume: {note + '; ' if note else ''}continuing from {ckpt} (step {state['step']})"
              + (", the newest intact checkpoint" if note else ""), flush=True)
    return ckpt, loaded, state


def _check_same_policy(ckpt: Path, loaded: ActionDecoderPolicy, policy: ActionDecoderPolicy) -> None:
    """The resumed checkpoint's network config and normalisation statistics are the new run's."""
    new, old = policy.config.to_dict(), loaded.config.to_dict()
    changed = [f"{k}: {_fmt(old.get(k))} → {_fmt(v)}" for k, v in new.items() if k != "extra" and old.get(k) != v]
    if changed:
        raise ValueError(f"--resume: {ckpt} holds another policy ({'; '.join(changed)}); resume with the "
                         f"saved settings or choose another --output-dir")
    stats = [k for k, v in policy.state_dict().items() if k.startswith("normalizers.")
             and not torch.allclose(v.cpu(), loaded.state_dict()[k].cpu(), rtol=1e-5, atol=1e-6)]
    if stats:
        raise ValueError(f"--resume: the training data's normalisation statistics ({', '.join(stats)}) differ "
                         f"from those in {ckpt}: the data changed since the run began; resume with the same "
                         f"data or choose another --output-dir")


def _train(cfg: TrainConfig, rank: int, world: int, device: torch.device) -> Path:
    out = Path(cfg.output_dir)
    main = rank == 0
    shift = augment_shift(cfg)
    if cfg.dataset is not None:
        from .data.lerobot_format import check_dataset_dir

        check_dataset_dir(cfg.dataset, "--dataset")
    resumed = _resume(cfg, out, device, main)
    ds, tasks, val = load_training_data(cfg, quiet=not main)
    dconf = decoder_config(cfg, ds.dataset.states.shape[1], ds.dataset.actions.shape[1], tasks,
                           ds.dataset.images)
    dconf.extra["data"] = {"episodes": ds.dataset.num_episodes, "frames": ds.dataset.num_frames}   # for the model card
    torch.manual_seed(cfg.seed)
    policy = ActionDecoderPolicy(dconf, ds.stats).to(device)
    # Behaviour cloning never touches the SDE noise scale; frozen, every trainable parameter is
    # used by every loss, so DDP needs no unused-parameter search (flaky with the JVP's graph).
    policy.sigma.requires_grad_(False)
    optimizer = torch.optim.AdamW([p for p in policy.parameters() if p.requires_grad], lr=cfg.lr,
                                  weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, cfg.warmup_steps, cfg.steps))
    # Rank-specific streams: each process draws its own rows and its own noise.
    data_gen = torch.Generator().manual_seed(cfg.seed * 1000 + rank)
    loss_gen = torch.Generator(device=device).manual_seed(cfg.seed * 1000 + 500 + rank)
    start, history = 0, []
    ema = weight_average(policy, cfg.ema_decay)
    if cfg.compile:                 # after the EMA's copy: the average stays a plain module
        from .compiled import check_compile, compile_network

        check_compile()
        compile_network(policy)

    if resumed is not None:
        ckpt, loaded, state = resumed
        _check_same_policy(ckpt, loaded, policy)
        policy.load_state_dict(loaded.state_dict())
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        # A checkpoint written before "ranks" kept rank 0's generators at the top level.
        saved = state.get("ranks") or [{"data_gen": state["data_gen"], "loss_gen": state["loss_gen"]}]
        window = {"losses": [], "grad_norms": []}
        if len(saved) == world:                 # each process continues its own streams and window
            data_gen.set_state(saved[rank]["data_gen"])
            loss_gen.set_state(saved[rank]["loss_gen"].to(loss_gen.get_state().device))
            window = saved[rank].get("window") or window
        else:                                   # another number of processes: fresh streams per rank and step
            data_gen.manual_seed(cfg.seed * 1000 + rank + 7919 * state["step"])
            loss_gen.manual_seed(cfg.seed * 1000 + 500 + rank + 7919 * state["step"])
            if main:
                print(f"resume: {ckpt} was trained by {len(saved)} process(es), this run has {world}: the data "
                      f"and noise streams restart (the run is not bit-exact with an uninterrupted one)", flush=True)
        _set_rng_state(state["rng"])
        start, history = state["step"], state["history"]
        if ema is not None and state.get("ema") is not None:
            ema.load_state_dict(state["ema"])

    model = policy
    if world > 1:
        model = torch.nn.parallel.DistributedDataParallel(
            policy, device_ids=[device.index] if device.type == "cuda" else None)
    local_batch = cfg.batch_size // world
    bar = None
    if main and cfg.progress:
        from tqdm import tqdm
        # stderr, and only on a terminal: results stay on stdout, and a redirected log gets no bar.
        bar = tqdm(total=cfg.steps, initial=start, desc=f"train {cfg.decoder}", dynamic_ncols=True,
                   file=sys.stderr, disable=None)
    logger = RunLogger(out, "train_log.jsonl", start, cfg.wandb_project if cfg.wandb else None, "train",
                       asdict(cfg)) if main else None
    policy.train()
    t0, cpu0 = time.perf_counter(), time.process_time()
    # The steps since the last log row (a resumed run continues the window its checkpoint kept).
    running = [torch.tensor(x, device=device) for x in window["losses"]] if resumed is not None else []
    grad_norms = [torch.tensor(x, device=device) for x in window["grad_norms"]] if resumed is not None else []
    t_logged = t0
    for step in range(start, cfg.steps):
        idx = torch.randint(len(ds), (local_batch,), generator=data_gen)
        batch = _batch(ds, idx, len(tasks), device, shift, data_gen)
        loss = model(batch, generator=loss_gen).loss
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norms.append(torch.nn.utils.clip_grad_norm_(policy.parameters(), cfg.grad_clip).detach())  # before clipping
        lr_used = optimizer.param_groups[0]["lr"]
        optimizer.step()
        scheduler.step()
        if ema is not None:
            ema.update_parameters(policy)
        running.append(loss.detach())
        done = step + 1
        if done % cfg.log_every == 0 or done == cfg.steps:
            mean = torch.stack(running).mean()
            if world > 1:                       # the global batch's loss, not rank 0's share of it
                torch.distributed.all_reduce(mean)
                mean = mean / world
            mean_loss = float(mean)
            now = time.perf_counter()
            row = {"step": done, "loss": mean_loss, "lr": lr_used,
                   "grad_norm": float(torch.stack(grad_norms).mean())}
            if ema is not None:
                row["ema_decay"] = ema_decay_at(cfg.ema_decay, int(ema.n_averaged) - 1)
            samples_per_s = cfg.batch_size * len(running) / (now - t_logged)   # not in the history: runs repeat it exactly
            running, grad_norms, t_logged = [], [], now
            if not math.isfinite(mean_loss):
                raise FloatingPointError(f"training loss became {mean_loss} at step {done}; lower --lr "
                                         f"(now {cfg.lr}) or check the dataset")
            history.append(row)
            if logger is not None:
                logger.log(done, {**row, "samples_per_s": samples_per_s}, "train")
            if bar is not None:
                bar.set_postfix(loss=f"{mean_loss:.4f}", steps_per_s=f"{(done - start) / (time.perf_counter() - t0):.1f}")
        if bar is not None:
            bar.update(1)
        if done % cfg.checkpoint_every == 0 or done == cfg.steps:
            ranks = rank_states(data_gen, loss_gen, running, grad_norms, world)
            if main:
                save_checkpoint(out, done, policy, optimizer, scheduler, ranks, history, ema)
    if bar is not None:
        bar.close()
    final = out / FINAL
    if main:
        trained = policy if ema is None else ema.module
        log = {"config": asdict(cfg), "history": history}
        if val is not None:
            log["validation"] = validation_metrics(trained, val, len(tasks), device)
            # Kept with the weights it measured, for the model card (`model_card.validation_of`).
            trained.config.extra["validation"] = {**log["validation"],
                                                  "weights_sha256": weights_digest(trained.state_dict())}
        save_final(out, trained, cfg.steps)
        if val is not None:
            print(f"validation on held-out episodes {log['validation']['episodes']}: "
                  f"val_loss={log['validation']['val_loss']:.4f} "
                  f"val_action_mse={log['validation']['val_action_mse']:.4f}", flush=True)
            logger.log(cfg.steps, {"loss": log["validation"]["val_loss"],
                                   "action_mse": log["validation"]["val_action_mse"]}, "val", record=False)
        logger.close()
        with _writing(out / "train_log.json", out):
            (out / "train_log.json").write_text(json.dumps(log, indent=1))
            if history:
                plot_losses(history, out / "loss.png",
                            f"{cfg.decoder} on {cfg.task if cfg.dataset is None else cfg.dataset}")
        # Wall time, then this process's CPU time (every thread): the README and guides quote the CPU time.
        print(f"saved {final} ({time.perf_counter() - t0:.0f} s of training, {time.process_time() - cpu0:.0f} s CPU)",
              flush=True)
    if world > 1:
        torch.distributed.barrier()
        # Free DDP's reducer (it holds the last gloo work) while the interpreter is alive: a
        # reference cycle otherwise keeps it to shutdown. Freeing it alone does not stop gloo aborting
        # at exit: the console script's ranks also skip interpreter teardown (cli.entry).
        del model
        gc.collect()
    return final
