"""`action-decoder relabel`: a checkpoint's closed-loop plans under inference delays, labelled by the
scripted expert and added to its dataset (DAgger for real-time chunking, `data.relabel`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class RelabelConfig:
    """Roll a checkpoint out with inference delays on demonstration layouts, label each plan with the
    scripted expert's continuation after its committed prefix, and write them with --dataset's
    episodes as one LeRobot v3.0 dataset (train on it with train --dataset DIR --rtc-max-delay N)."""

    checkpoint: str
    """A save_pretrained directory (e.g. outputs/train/final) of a Meta-World state policy: the policy rolled out."""
    dataset: str
    """The Meta-World dataset of `record` (or of an earlier relabel) whose episodes the output keeps, same task."""
    output_dir: str
    """A new or empty directory for the aggregated dataset."""
    delays: list[int] = field(default_factory=lambda: [1, 2, 3, 4])
    """Inference delays to roll out with, in control steps (each new chunk's first d actions are the old chunk's)."""
    episodes: int = 15
    """Closed-loop episodes per delay, each on its own demonstration layout."""
    seed: int = 1
    """Layout seed: seed s rolls out on demonstration layouts s·1000 + k; their layouts must not be --dataset's."""
    n_action_steps: int = 0
    """Actions executed per chunk (0: the checkpoint's own)."""
    max_steps: int = 300
    """Control steps per closed-loop episode at most."""
    num_envs: int = 10
    """Environments stepped in lockstep (one policy call plans for all)."""


def _dataset_layouts(root: Path) -> list[int]:
    """The layout seed of each of the dataset's episodes (`record` keeps them as an episode column)."""
    from .data.lerobot_format import _episode_table

    rows = _episode_table(root)
    if not rows or any("seed" not in r for r in rows.values()):
        raise ValueError(f"--dataset: expected a dataset of `action-decoder record` (or relabel) with each episode's "
                         f"layout seed in meta/episodes, got {root} without them")
    return [int(rows[e]["seed"]) for e in sorted(rows)]


def run_relabel(cfg: RelabelConfig) -> Path:
    """Roll ``cfg.checkpoint`` out, label its plans and write them after ``cfg.dataset``'s episodes into
    ``cfg.output_dir``; prints one line per delay and a summary line."""
    import torch

    from .data.demos import LOOKAHEAD
    from .data.lerobot_format import load_dataset, read_info
    from .data.lerobot_write import write_episodes
    from .data.relabel import relabel_episodes
    from .envs.metaworld_tasks import SEED_STRIDE, demo_seeds
    from .evaluate import make_policy_fn
    from .policy import ActionDecoderPolicy, follow_last
    from .record import check_writable

    for option, value, low in (("--episodes", cfg.episodes, 1), ("--max-steps", cfg.max_steps, 1),
                               ("--num-envs", cfg.num_envs, 1), ("--n-action-steps", cfg.n_action_steps, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{option}: expected an integer >= {low}, got {value!r}")
    if not cfg.delays or len(set(cfg.delays)) != len(cfg.delays) or any(d < 0 for d in cfg.delays):
        raise ValueError(f"--delays: expected distinct integers >= 0 (control steps), got {cfg.delays}")
    if len(cfg.delays) * cfg.episodes > SEED_STRIDE:
        raise ValueError(f"--episodes: expected at most {SEED_STRIDE // len(cfg.delays)} per delay (a seed owns "
                         f"{SEED_STRIDE} layouts), got {cfg.episodes} for {len(cfg.delays)} delays")
    layouts = demo_seeds(cfg.seed, len(cfg.delays) * cfg.episodes)
    out, root = Path(cfg.output_dir).expanduser(), Path(cfg.dataset).expanduser()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"--output-dir: expected a new or empty directory, got {out} (not empty)")
    check_writable(out)
    info = read_info(root)
    if info.get("env") != "metaworld" or info.get("layout", "library") != "library" or \
            not isinstance(info.get("source", {}).get("task"), str):
        raise ValueError(f"--dataset: expected a single-task Meta-World dataset of `action-decoder record` in the "
                         f"library's layout (info.json \"env\": \"metaworld\", a source task), got {root}")
    task = info["source"]["task"]
    known = _dataset_layouts(root)
    shared = sorted(set(known) & set(layouts))
    if shared:
        raise ValueError(f"--seed: layouts {shared[0]}..{shared[-1]} of --seed {cfg.seed} are already episodes of "
                         f"--dataset {root}; choose a seed whose layouts it does not hold (e.g. "
                         f"{max(known) // SEED_STRIDE + 1})")
    if any(v.get("dtype") == "video" for v in info.get("features", {}).values()):
        raise ValueError(f"--dataset: expected a state dataset (relabel labels the simulator's state), got {root} "
                         f"with cameras")
    prior = load_dataset(root)

    ckpt = str(follow_last(cfg.checkpoint)) if Path(cfg.checkpoint).expanduser().is_file() else cfg.checkpoint
    policy = ActionDecoderPolicy.from_pretrained(ckpt, map_location="cpu").eval()
    pc = policy.config
    if pc.decoder_type == "DDPM" or pc.uses_cameras or pc.n_obs_steps > 1 or \
            pc.extra.get("observation_layout") == "lerobot" or len(pc.extra.get("tasks") or [task]) != 1:
        raise ValueError(f"--checkpoint: expected a single-task flow_matching or mean_flow state policy with one "
                         f"observation per plan (real-time chunking over the simulator's state), got {ckpt}")
    if (pc.extra.get("tasks") or [task])[0] != task:
        raise ValueError(f"--checkpoint: trained on {pc.extra['tasks'][0]}, but --dataset holds {task}")
    n_exec = cfg.n_action_steps or pc.n_action_steps
    if n_exec > pc.action_chunk_size:
        raise ValueError(f"--n-action-steps: expected 1..{pc.action_chunk_size} (the chunk length), got {n_exec}")
    if max(cfg.delays) > n_exec or n_exec + max(cfg.delays) > pc.action_chunk_size:
        raise ValueError(f"--delays: expected at most --n-action-steps={n_exec} and n_action_steps + delay <= the "
                         f"chunk length {pc.action_chunk_size}, got {cfg.delays}")
    if pc.action_chunk_size > LOOKAHEAD:
        raise ValueError(f"--checkpoint: chunks of {pc.action_chunk_size} actions exceed the {LOOKAHEAD} a label holds")

    episodes = []
    for e in range(len(prior.episode_lengths)):
        start, n = int(prior.episode_starts[e]), int(prior.episode_lengths[e])
        actions = prior.actions[start:start + n]                                           # [L, D]
        follow = np.minimum(np.arange(n)[:, None] + np.arange(LOOKAHEAD), n - 1)           # [L, LOOKAHEAD]
        labels = prior.continuations[start:start + n] if prior.continuations is not None else actions[follow]
        committed = prior.prefix_lengths[start:start + n] if prior.prefix_lengths is not None else np.zeros(n, np.int64)
        episodes.append({"observation.state": prior.states[start:start + n], "action": actions,
                         "action.continuation": labels[:, :LOOKAHEAD], "action.prefix_length": committed,
                         "task_index": 0, "seed": known[e]})
    generator = torch.Generator().manual_seed(cfg.seed)
    rounds = []
    for i, delay in enumerate(cfg.delays):
        mode = policy.resolve_rtc_mode(None, delay)
        fn = make_policy_fn(policy, len(pc.extra.get("tasks") or []), None, None, generator, rtc_mode=mode)
        eps, success = relabel_episodes(fn, task, layouts[i * cfg.episodes:(i + 1) * cfg.episodes], delay, n_exec,
                                        cfg.max_steps, cfg.num_envs)
        episodes += eps
        frames = sum(len(ep["action"]) for ep in eps)
        rounds.append({"delay": delay, "rtc_mode": mode, "layouts": [eps[0]["seed"], eps[-1]["seed"]],
                       "rollout_success_rate": success, "frames": frames})
        print(f"delay {delay} ({mode} RTC): {cfg.episodes} rollouts, success {success:.2f}, {frames} plans labelled",
              flush=True)
    source = {**info["source"], "relabel": [*info["source"].get("relabel", []), {
        "checkpoint": str(ckpt), "n_action_steps": n_exec, "max_steps": cfg.max_steps, "seed": cfg.seed,
        "rounds": rounds}]}
    write_episodes(out, episodes, [task], prior.fps, {"robot_type": info.get("robot_type", "sawyer"),
                                                      "env": "metaworld", "source": source})
    added = sum(r["frames"] for r in rounds)
    print(f"relabelled {added} plans of {len(rounds) * cfg.episodes} rollouts and kept {len(prior.actions)} frames of "
          f"{root}: {len(episodes)} episodes as a LeRobot v3.0 dataset in {out}", flush=True)
    return out
