"""Closed-loop evaluation of a saved policy on its Meta-World task(s)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Literal, Optional

import numpy as np
import torch

from .flows.paths import randn_rows
from .policy import ActionDecoderPolicy, follow_last
from .tracking import log_evaluation, require_wandb
from .train import task_context


@dataclass
class EvalConfig:
    """Run closed-loop episodes of a checkpoint on layouts disjoint from its demonstrations."""

    checkpoint: Optional[str] = None
    """A save_pretrained directory (e.g. outputs/train/final) or a Hub repo id; or pass --onnx."""
    onnx: Optional[str] = None
    """Evaluate this exported policy (`action-decoder export`) with onnxruntime instead of a checkpoint: same layouts and noise."""
    compile: bool = False
    """Sample with the torch.compile'd sampler (deterministic samplers; with --rtc, trained RTC only)."""
    episodes: int = 20
    """Episodes per task."""
    sampler: Optional[Literal["ode", "sde", "euler"]] = None
    """ode, sde or euler (None: the checkpoint's own)."""
    steps: int = 0
    """Sampling steps K (0: the checkpoint's own)."""
    seed: int = 0
    """Seed of the evaluation layouts (1 000 000 + seed·1000 + j, never a demonstration's)."""
    n_action_steps: int = 0
    """Actions executed per chunk before re-planning (0: the checkpoint's own)."""
    task: Optional[str] = None
    """Task(s) to evaluate (None: those the policy was trained on)."""
    output: Optional[str] = None
    """JSON summary file, or a directory for it (None: the checkpoint directory, named by the settings)."""
    plot: bool = False
    """Also plot the hand paths next to the summary (.png)."""
    max_steps: int = 500
    """Episode cap in env steps; an episode still running there fails (Meta-World's cap: 500)."""
    video: bool = False
    """Film the first --video-episodes episodes of each task into H.264 mp4s next to the summary."""
    video_episodes: int = 4
    """Episodes filmed per task."""
    video_layout: Literal["grid", "episodes"] = "grid"
    """grid: one video per task; episodes: one video per episode."""
    video_camera: str = "corner2"
    """Meta-World camera: topview, corner, corner2, corner3, corner4, behindGripper or gripperPOV."""
    video_size: int = 224
    """Frame side in pixels, a multiple of 16."""
    video_fps: float = 0
    """Frames per second (0: real time, one frame per env step)."""
    num_envs: int = 10
    """Environments stepped together."""
    device: str = "cpu"
    """cpu, cuda, cuda:N, or auto (a GPU when there is one)."""
    wandb: bool = False
    """Also log the success rates to Weights & Biases (the [wandb] extra); TensorBoard always."""
    wandb_project: str = "action-decoder"
    """Weights & Biases project name."""
    delay: int = 0
    """Simulated inference delay in control steps (0..n_action_steps)."""
    rtc: bool = False
    """Real-time chunking: condition each new chunk on the old chunk's remaining actions (its first
    `delay` ones frozen; flow_matching and mean_flow). Off: the chunks switch naively."""
    rtc_mode: Optional[Literal["trained", "guided"]] = None
    """With --rtc: trained (feed the committed prefix; checkpoints trained with --rtc-max-delay) or guided (guidance towards the old chunk); default: trained when the checkpoint has it."""


def row_generators(base: int, episode_seeds, plan_indices, device) -> list:
    """One torch.Generator per row, seeded by (base, episode seed, plan index): row b's noise depends on
    its own episode and plan only."""
    seeds = [np.random.SeedSequence([base, int(e), int(p)]).generate_state(1, np.uint64)[0]
             for e, p in zip(episode_seeds, plan_indices)]
    return [torch.Generator(device=device).manual_seed(int(seed)) for seed in seeds]


def make_policy_fn(policy: ActionDecoderPolicy, num_tasks: int, sampler: Optional[str], steps: Optional[int],
                   generator: torch.Generator, sample_fn=None, observe=None, rtc_mode: Optional[str] = None):
    """Adapt a policy to the env harness: states [B, S] (numpy; [B, n, S] for a policy of `n_obs_steps`
    n > 1, as `envs.evaluate` stacks them) → chunks [B, H, D] (numpy).

    Given `episode_seeds` and `plan_indices` [B] (as `envs.evaluate` passes them), row b samples
    from its own generator, seeded by (generator.initial_seed(), episode_seeds[b], plan_indices[b]),
    in one batched call (`policy.sample` takes one generator per row): an episode's actions do not
    depend on the other episodes sharing its batch, so results do not depend on `num_envs` (up to
    float rounding of batched matmuls, ~1e-7). Without those keys the whole batch draws from
    `generator`. `images` [B, N_cam, 3, S, S] (as `envs.evaluate` passes them with a camera rig)
    condition a camera policy. `sample_fn(batch, noise)` (`compiled.compile_sampler`), when given,
    samples each chunk from the noise `policy.sample` would draw (with `prev_chunks`, one compiled with
    `rtc=True`: trained real-time chunking). `observe` maps the env's states [B, 39]
    to what the policy reads (default: as they are; LeRobot's agent position for a policy of
    `record --layout lerobot` data). `rtc_mode` goes to `policy.sample` with `prev_chunks` (real-time
    chunking; the rows each new chunk executes are those prev_chunks' length implies, H − L).
    """
    device = next(policy.parameters()).device
    base = generator.initial_seed()
    cfg = policy.config

    @torch.no_grad()
    def policy_fn(states: np.ndarray, task_index: np.ndarray, episode_seeds: Optional[np.ndarray] = None,
                  plan_indices: Optional[np.ndarray] = None, prev_chunks: Optional[np.ndarray] = None,
                  delay: int = 0, images: Optional[np.ndarray] = None) -> np.ndarray:
        states = observe(states) if observe is not None else states
        batch = {"state": torch.from_numpy(np.asarray(states, dtype=np.float32)).to(device)}   # [B, S]
        if images is not None:
            batch["images"] = torch.from_numpy(np.ascontiguousarray(images)).to(device)         # [B, N, 3, S, S] uint8
        ctx = task_context(torch.as_tensor(task_index), num_tasks)
        batch.update({k: v.to(device) for k, v in ctx.items()})
        gens = generator
        if episode_seeds is not None or plan_indices is not None:
            if episode_seeds is None or plan_indices is None or not len(episode_seeds) == len(plan_indices) == len(states):
                raise ValueError(f"episode_seeds, plan_indices: expected both, one per state row ({len(states)}), got "
                                 f"{None if episode_seeds is None else len(episode_seeds)} and "
                                 f"{None if plan_indices is None else len(plan_indices)}")
            gens = row_generators(base, episode_seeds, plan_indices, device)
        prev = None if prev_chunks is None else torch.from_numpy(np.asarray(prev_chunks, dtype=np.float32)).to(device)
        if sample_fn is not None:
            noise = randn_rows(len(states), (cfg.action_chunk_size, cfg.action_dim), gens, device)   # [B, H, D]
            if prev is None:
                return sample_fn(batch, noise).float().cpu().numpy()
            if not getattr(sample_fn, "rtc_max_delay", 0):
                raise ValueError("--compile: this compiled sampler has no real-time chunking (prev_chunks); compile it "
                                 "with rtc=True or drop --rtc")
            return sample_fn(batch, noise, prev_chunk=prev, delay=delay).float().cpu().numpy()
        out = policy.sample(batch, sampler=sampler, steps=steps, return_logprob=False, generator=gens,
                            prev_chunk=prev, delay=delay, rtc_mode=rtc_mode)             # prev [B, L, D]
        return out.actions.float().cpu().numpy()                                            # [B, H, D]

    return policy_fn


def check_simulator_policy(policy: ActionDecoderPolicy, checkpoint: str, task: Optional[str], command: str) -> None:
    """Refuse, in one line, a closed-loop run (`eval`, `finetune`) of a policy the library's simulator cannot
    run (`model_card.simulator_policy`): one trained on a LeRobot dataset of another robot is not told to
    pick a Meta-World task it never had; it is told what it was trained on and where its measurements are."""
    from .model_card import simulator_policy, trained_on
    from .state_layout import METAWORLD_STATE_DIM

    config = policy.config
    dims = (config.state_dim, config.action_dim) == (METAWORLD_STATE_DIM, 4)
    # With --task, a single-task policy of Meta-World's widths may be run there; a multi-task one needs
    # its own tasks' tokens, which a Meta-World task does not give.
    if simulator_policy(config) or (task is not None and dims and len(config.extra.get("tasks") or []) <= 1):
        return
    what = {"eval": "closed-loop evaluation", "finetune": "RL fine-tuning"}[command]
    instead = ("its held-out validation (val_loss, val_action_mse) is in its model card (README.md) and the run's "
               "train_log.json; to act with it, run it in its own environment from Python (the card's Use section)"
               if command == "eval" else
               "fine-tune it with an RL loop of its own environment (policy.predict_action_chunk(batch, "
               "sampler=\"sde\", return_logprob=True) gives chunks with log-probs)")
    raise ValueError(f"--checkpoint: {what} runs Meta-World tasks ({METAWORLD_STATE_DIM}-d state, 4-d actions), and "
                     f"{checkpoint} was trained on {trained_on(config)}: {instead}")


def eval_tasks(task: Optional[str], trained: list, source: str) -> list:
    """The Meta-World tasks to evaluate: `--task` (among a multi-task policy's own) or the policy's trained ones."""
    from .envs import canonical_task, resolve_tasks

    tasks = resolve_tasks(task) if task else trained
    if not tasks:
        raise ValueError(f"--task: {source} names no task; pass --task metaworld/<task>")
    unknown = [t for t in tasks if canonical_task(t) not in trained] if len(trained) > 1 else []
    if unknown:
        raise ValueError(f"--task: {unknown} not among the tasks this policy was trained on: {trained}")
    return tasks


EPISODE_CAP = 500
"""Meta-World's episode cap (`envs.MAX_EPISODE_STEPS`, here without importing the simulator)."""


def run_eval(cfg: EvalConfig) -> dict:
    if (cfg.checkpoint is None) == (cfg.onnx is None):
        raise ValueError(f"--checkpoint, --onnx: expected exactly one of them, got checkpoint={cfg.checkpoint!r} "
                         f"and onnx={cfg.onnx!r}")
    if cfg.onnx is not None:
        from .evaluate_onnx import run_eval_onnx

        return run_eval_onnx(cfg)
    if cfg.episodes < 1 or cfg.steps < 0:
        raise ValueError(f"--episodes/--steps: expected episodes >= 1 and steps >= 0, got {cfg.episodes}, {cfg.steps}")
    require_wandb(cfg.wandb)
    if not 1 <= cfg.max_steps <= EPISODE_CAP:
        raise ValueError(f"--max-steps: expected 1..{EPISODE_CAP} (Meta-World's episode cap), got {cfg.max_steps}")
    check_video_options(cfg)
    device = ("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device
    if Path(cfg.checkpoint).expanduser().is_file():      # a run's checkpoints/last: its step_N directory
        cfg = replace(cfg, checkpoint=str(follow_last(cfg.checkpoint)))
    policy = ActionDecoderPolicy.from_pretrained(cfg.checkpoint, map_location=device).eval()
    # Before the simulator is imported: a policy of another robot needs neither the sim nor a task.
    check_simulator_policy(policy, cfg.checkpoint, cfg.task, "eval")

    from .envs import canonical_task, evaluate
    from .envs.render import EpisodeCamera

    n_exec = cfg.n_action_steps or policy.config.n_action_steps
    if not 1 <= n_exec <= policy.config.action_chunk_size:
        raise ValueError(f"--n-action-steps: expected 1..{policy.config.action_chunk_size} (the chunk length), "
                         f"got {cfg.n_action_steps}")
    if not 0 <= cfg.delay <= n_exec or n_exec + cfg.delay > policy.config.action_chunk_size:
        raise ValueError(f"--delay: expected 0..{min(n_exec, policy.config.action_chunk_size - n_exec)} (at most "
                         f"--n-action-steps={n_exec}, and n_action_steps + delay <= the chunk length "
                         f"{policy.config.action_chunk_size}), got {cfg.delay}")
    if cfg.rtc and policy.config.decoder_type == "DDPM":
        raise ValueError("--rtc: real-time chunking needs a flow_matching or mean_flow checkpoint, got DDPM")
    if cfg.rtc_mode is not None and not cfg.rtc:
        raise ValueError(f"--rtc-mode: chooses how --rtc conditions each new chunk; got --rtc-mode {cfg.rtc_mode} "
                         f"without --rtc")
    rtc_mode = policy.resolve_rtc_mode(cfg.rtc_mode, cfg.delay, cfg.sampler) if cfg.rtc else None
    trained = list(policy.config.extra.get("tasks") or [])
    tasks = eval_tasks(cfg.task, trained, f"the checkpoint {cfg.checkpoint}")
    policy.resolve_sampler(cfg.sampler)   # fail early on an unsafe decoder/sampler mix
    if policy.config.uses_cameras:
        from .envs.render import check_rendering

        check_rendering()                  # before any env exists: MUJOCO_GL binds at mujoco's import
    steps = cfg.steps or None
    out = summary_path(cfg, policy, n_exec, steps, tasks, trained)
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    sample_fn = None
    if cfg.compile:
        from .compiled import check_compile, compile_sampler

        check_compile()
        if cfg.rtc and rtc_mode != "trained":
            raise ValueError("--compile: the compiled sampler runs trained real-time chunking only (a checkpoint "
                             f"trained with --rtc-max-delay >= --delay); this one resolves to {rtc_mode!r}: drop --compile")
        sample_fn = compile_sampler(policy, cfg.sampler, steps, rtc=bool(cfg.rtc))
    lerobot = policy.config.extra.get("observation_layout") == "lerobot"
    if lerobot:
        from .envs.lerobot_view import agent_pos
    fn = make_policy_fn(policy, len(trained), cfg.sampler, steps, generator, sample_fn,
                        observe=agent_pos if lerobot else None, rtc_mode=rtc_mode)
    results, videos = [], {}
    video_dir = tempfile.TemporaryDirectory(prefix="action_decoder_video_") if cfg.video else contextlib.nullcontext()
    for task in tasks:
        index = trained.index(canonical_task(task)) if len(trained) > 1 else 0
        wins = []

        def progress(done, total, episode, success, task=task):
            # Episodes finish out of order across envs: numbered by episode (its seed's index), counted apart.
            wins.append(success)
            print(f"[{task}] episode {episode + 1}/{total}: {'success' if success else 'failure'} "
                  f"({done}/{total} done, running success {np.mean(wins):.2f})", flush=True)

        camera = EpisodeCamera(cfg.video_episodes, cfg.video_size, cfg.video_camera) if cfg.video else None
        rig = policy_camera_rig(policy)
        try:
            res = evaluate(fn, task, episodes=cfg.episodes, seed=cfg.seed, n_action_steps=n_exec,
                           max_steps=cfg.max_steps, num_envs=cfg.num_envs, task_index=index, progress=progress,
                           record=cfg.plot, on_step=camera,
                           delay=cfg.delay, rtc=cfg.rtc, camera_rig=rig, n_obs_steps=policy.config.n_obs_steps)
        finally:
            for closable in (camera, rig):
                if closable is not None:
                    closable.close()
        if camera is not None:      # encoded now (frames are large), moved next to the summary at the end
            encoded = camera.write(res["successes"], cfg.video_layout, cfg.video_fps, Path(video_dir.name), f"_{task}")
            videos.update((path.name, path) for path in encoded)
        results.append(res)
        jerk = "" if res.get("boundary_jerk") is None else f" boundary_jerk={res['boundary_jerk']:.4g}"
        print(f"[{task}] success_rate={res['success_rate']:.3f}{jerk}", flush=True)
    summary = {
        "checkpoint": str(cfg.checkpoint), "decoder_type": policy.config.decoder_type,
        "sampler": policy.resolve_sampler(cfg.sampler), "steps": policy.resolve_steps(cfg.sampler, steps),
        "episodes_per_task": cfg.episodes, "seed": cfg.seed, "n_action_steps": n_exec, "max_steps": cfg.max_steps,
        "success_rate": float(np.mean([r["success_rate"] for r in results])),
        "per_task": {r["task"]: r["success_rate"] for r in results},
        "delay": cfg.delay, "rtc": cfg.rtc, "rtc_mode": rtc_mode,
        "boundary_jerk": _mean_jerk(results),
        "results": [{k: v for k, v in r.items() if k != "trajectories"} for r in results],
    }
    with video_dir:
        written = write_summary(summary, results if cfg.plot else None, out, videos)
    log_evaluation(summary, Path(cfg.checkpoint), written, cfg.wandb_project if cfg.wandb else None)
    update_card(Path(cfg.checkpoint), policy, summary, [r["task"] for r in results])
    print(f"success_rate={summary['success_rate']:.4f}", flush=True)
    return summary


def summary_path(cfg: EvalConfig, policy: ActionDecoderPolicy, n_exec: int, steps: Optional[int], tasks: list,
                 trained: list) -> Path:
    """Where the summary goes: `--output` (a file, or a directory that gets the default name), else the
    checkpoint directory under a name that holds every setting of a model-card row, so that no two
    settings share a file: `eval_<sampler>_k<K>_n<n>[_d<delay>][_rtc[-<rtc_mode>]]_seed<s>_e<episodes>[_t<cap>]
    [_on-<tasks>].json` (`_on-`: tasks other than the trained ones)."""
    from .envs import MAX_EPISODE_STEPS, canonical_task

    cap = f"_t{cfg.max_steps}" if cfg.max_steps < MAX_EPISODE_STEPS else ""
    timing = (f"_d{cfg.delay}" if cfg.delay else "") + ("_rtc" if cfg.rtc else "") + \
        (f"-{cfg.rtc_mode}" if cfg.rtc and cfg.rtc_mode else "")
    names = sorted(dict.fromkeys(canonical_task(t) for t in tasks))
    if names == sorted(trained):
        where = ""
    elif len(names) <= 3:
        where = "_on-" + "+".join(names)
    else:
        where = f"_on-{len(names)}tasks-" + hashlib.sha256(",".join(names).encode()).hexdigest()[:8]
    name = (f"eval_{policy.resolve_sampler(cfg.sampler)}_k{policy.resolve_steps(cfg.sampler, steps)}_n{n_exec}"
            f"{timing}_seed{cfg.seed}_e{cfg.episodes}{cap}{where}.json")
    if not cfg.output:
        return Path(cfg.checkpoint) / name
    out = Path(cfg.output)
    return out / name if out.is_dir() else out


def policy_camera_rig(policy: ActionDecoderPolicy):
    """A `CameraObservation` of the policy's cameras at its image size (Meta-World camera `name` for the
    key `observation.images.<name>`), or None for a policy without cameras."""
    from .config import CAMERA_PREFIX
    from .envs.render import CameraObservation

    cfg = policy.config
    if not cfg.uses_cameras:
        return None
    if cfg.extra.get("observation_layout") == "lerobot":
        return LeRobotRig(cfg.image_size)
    names = [key[len(CAMERA_PREFIX):] for key in cfg.cameras if key.startswith(CAMERA_PREFIX)]
    if len(names) != len(cfg.cameras):
        raise ValueError(f"checkpoint cameras: expected keys '{CAMERA_PREFIX}<simulator camera>' to render, got "
                         f"{list(cfg.cameras)} (a dataset's unnamed camera has no simulator view)")
    return CameraObservation(names, cfg.image_size, field="checkpoint cameras")


class LeRobotRig:
    """LeRobot's Meta-World camera (`envs.lerobot_view.LeRobotCamera`, 480² px) resized to the policy's
    `image_size` as the LeRobot plugin resizes it (bilinear, antialiased): ``{"observation.image": [S, S, 3] uint8}``."""

    def __init__(self, size: int):
        from .envs.lerobot_view import LeRobotCamera

        self.size, self.camera = size, LeRobotCamera()

    def __call__(self, env) -> dict:
        import torch.nn.functional as F

        out = {}
        for key, frame in self.camera(env).items():
            x = torch.from_numpy(frame).permute(2, 0, 1)[None].float() / 255.0                  # [1, 3, 480, 480]
            x = F.interpolate(x, size=(self.size, self.size), mode="bilinear", antialias=True, align_corners=False)
            out[key] = (x.clamp(0, 1) * 255).round().to(torch.uint8)[0].permute(1, 2, 0).numpy()  # [S, S, 3]
        return out

    def close(self) -> None:
        self.camera.close()


def _mean_jerk(results: list) -> Optional[float]:
    """Boundary jerk over all tasks' boundary stencils (None without any chunk switch)."""
    n = sum(r.get("boundaries", 0) for r in results)
    return sum(r["boundary_jerk"] * r["boundaries"] for r in results if r.get("boundaries")) / n if n else None


def update_card(checkpoint: Path, policy: ActionDecoderPolicy, summary: dict, tasks: list) -> None:
    """Add this evaluation's row to the model card of a local, writable checkpoint directory (a Hub
    snapshot or a read-only directory keeps its card; another failed write says so in one line)."""
    from huggingface_hub.constants import HF_HUB_CACHE

    from .model_card import record_result

    if not checkpoint.is_dir() or not os.access(checkpoint, os.W_OK) \
            or checkpoint.resolve().is_relative_to(Path(HF_HUB_CACHE).resolve()):
        return

    try:
        record_result(checkpoint, policy, summary, tasks)
    except PermissionError:
        return
    except OSError as err:
        print(f"action-decoder: warning: the model card in {checkpoint} was not updated ({err.strerror or err})",
              file=sys.stderr, flush=True)


def check_video_options(cfg: EvalConfig) -> None:
    """Refuse video options without --video or out of range, and unavailable rendering, before any episode."""
    changed = [f"--{f.name.replace('_', '-')}" for f in fields(cfg)
               if f.name.startswith("video_") and getattr(cfg, f.name) != f.default]
    if not cfg.video:
        if changed:
            raise ValueError(f"{', '.join(changed)}: take effect only with --video, which was not given")
        return
    if cfg.video_episodes < 1:
        raise ValueError(f"--video-episodes: expected an integer >= 1, got {cfg.video_episodes}")
    if not (16 <= cfg.video_size <= 2048 and cfg.video_size % 16 == 0):
        raise ValueError(f"--video-size: expected a multiple of 16 in [16, 2048] (H.264 macroblocks), "
                         f"got {cfg.video_size}")
    if not 0 <= cfg.video_fps <= 1000:
        raise ValueError(f"--video-fps: expected a number in [0, 1000] (0: real time), got {cfg.video_fps}")
    from .envs.render import check_rendering

    check_rendering()


def write_summary(summary: dict, plot_results: Optional[list], out: Path,
                  videos: Optional[dict[str, Path]] = None) -> Optional[Path]:
    """Write the JSON summary (and the plot, same name .png; each video of `videos`, name suffix → encoded
    file, as <stem><suffix>) to `out`'s directory; returns where the summary went.

    An evaluation can take minutes, so a place that cannot be written (a read-only checkpoint
    directory) does not end it with a traceback: the files go to the current directory under the
    same name, and one line on stderr says so; if that fails too, one line says nothing was saved.
    """
    tried = []
    for path in dict.fromkeys([out.absolute(), Path.cwd() / out.name]):     # the fallback, unless it is `out` itself
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(summary, indent=1))
            if plot_results is not None:
                plot_trajectories(plot_results, path.with_suffix(".png"), summary)
            for suffix, encoded in (videos or {}).items():
                shutil.copyfile(encoded, path.with_name(path.stem + suffix))
        except OSError as err:
            tried.append(f"{path} ({err.strerror or err})")
            continue
        if tried:
            print(f"action-decoder: warning: cannot write {tried[0]}; wrote {path} instead",
                  file=sys.stderr, flush=True)
        for suffix in videos or {}:
            print(f"video: {path.with_name(path.stem + suffix)}", flush=True)
        return path
    print(f"action-decoder: warning: the summary was not saved: cannot write {' or '.join(tried)}",
          file=sys.stderr, flush=True)
    return None


def plot_trajectories(results: list, path: Optional[Path], summary: dict):
    """Top-down (x, y) hand paths per task, green for successes and red for failures, from a circle (the
    start) to a star (the goal), with a legend; the title names the task(s), decoder, sampler, K and
    re-planning. Saved to `path` (unless None); returns the matplotlib Figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    fig, axes = plt.subplots(1, len(results), figsize=(max(4 * len(results), 5), 5), squeeze=False)
    for ax, res in zip(axes[0], results):
        for traj, ok in zip(res["trajectories"], res["successes"]):
            hand = np.asarray(traj["hand"])                                       # [T, 3]
            ax.plot(hand[:, 0], hand[:, 1], color="tab:green" if ok else "tab:red", alpha=0.6, lw=1)
            ax.scatter(hand[0, 0], hand[0, 1], marker="o", facecolors="none", edgecolors="k", s=20, lw=0.8)
            ax.scatter(*traj["goal"][:2], marker="*", color="k", s=30)
        wins = int(sum(res["successes"]))
        ax.legend(handles=[Line2D([], [], color="tab:green", label=f"success ({wins})"),
                           Line2D([], [], color="tab:red", label=f"failure ({len(res['successes']) - wins})"),
                           Line2D([], [], ls="", marker="o", mfc="none", mec="k", label="start"),
                           Line2D([], [], ls="", marker="*", color="k", label="goal")], fontsize=7, loc="best")
        ax.set(title=f"{res['task']}: {res['success_rate']:.0%}", xlabel="x", ylabel="y")
        ax.set_aspect("equal", adjustable="datalim")
    tasks = [r["task"] for r in results]
    fig.suptitle(f"{', '.join(tasks) if len(tasks) <= 3 else f'{len(tasks)} tasks'}: {summary['decoder_type']}\n"
                 f"sampler {summary['sampler']}, K = {summary['steps']}, {summary['n_action_steps']} actions per plan",
                 fontsize=10)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return fig
