"""`action-decoder record`: scripted-expert demonstrations written as a LeRobot v3.0 dataset."""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal, Optional


@dataclass
class RecordConfig:
    """Record scripted-expert Meta-World demonstrations as a LeRobot v3.0 dataset (loads with
    LeRobot's ``LeRobotDataset(repo_id, root=DIR)`` and with ``action-decoder train --dataset DIR``)."""

    task: str
    """``metaworld/<task>``; several comma-separated (or a group such as ``metaworld/MT10``) make one
    multi-task dataset whose task strings are the Meta-World task names."""
    demos: int
    """Successful demonstrations per task (failed expert attempts are not kept)."""
    output_dir: str
    """A new or empty directory for the dataset."""
    seed: int = 0
    """Demonstration seed: seed s draws layouts s·1000 … s·1000+999, disjoint from evaluation layouts."""
    action_noise: float = 0.0
    """DART recording: std of the Gaussian added to each executed action (the recorded action stays the
    expert's); > 0 also stores the expert's clean next actions per frame as ``action.continuation``."""
    action_label: Literal["expert", "executed"] = "expert"
    """With --action-noise: the action the dataset keeps, the expert's clean one (DART) or the executed noisy one (no continuation)."""
    cameras: Optional[list[str]] = None
    """Meta-World cameras to render at every observation (e.g. corner2, or corner2,corner), stored as
    the video features observation.images.<camera>. None: no pixels."""
    image_size: Optional[int] = None
    """Rendered frames are image_size × image_size pixels (None: 64; --layout lerobot renders at LeRobot's 480)."""
    perturbed_prefixes: int = 0
    """Training-time RTC data: copies of each frame whose committed prefix is the expert's actions shifted and noised, labelled by the expert from where it leads (0: none)."""
    rtc_max_delay: int = 4
    """With --perturbed-prefixes: the longest prefix, in actions (train on the dataset with --rtc-max-delay at least this)."""
    perturbed_prefix_noise: float = 0.2
    """With --perturbed-prefixes: std of the Gaussian noise on a prefix, in the env's action units."""
    perturbed_prefix_shift: int = 2
    """With --perturbed-prefixes: largest time shift of a prefix from the expert's own actions, in control steps."""
    layout: Literal["library", "lerobot"] = "library"
    """library: the simulator's 39-d state, cameras as observation.images.<camera>; lerobot: what LeRobot's Meta-World env (lerobot-eval --env.type=metaworld) observes, the 4-d agent position and with --cameras corner2 its observation.image."""


def check_writable(out: Path, option: str = "--output-dir") -> None:
    """Refuse, in one line naming `option`, a place where the dataset cannot be written (a read-only
    directory, a file on the way), before any demonstration is recorded; creates nothing."""
    where = out.expanduser().absolute()
    while not where.exists():
        where = where.parent
    try:
        with tempfile.TemporaryFile(dir=where):
            pass
    except OSError as err:
        raise ValueError(f"{option}: cannot write the dataset to {out} ({where}: {err.strerror}); choose a "
                         f"writable --output-dir") from None


def perturbed_prefixes(cfg: RecordConfig):
    """`data.perturbed_prefixes.PerturbedPrefixes` of --perturbed-prefixes, or None without them (then the
    options that shape them are refused, in one line, if given)."""
    from .data.perturbed_prefixes import PerturbedPrefixes

    copies = cfg.perturbed_prefixes
    if isinstance(copies, bool) or not isinstance(copies, int) or copies < 0:
        raise ValueError(f"--perturbed-prefixes: expected an integer >= 0 (copies of each frame), got {copies!r}")
    if copies:
        return PerturbedPrefixes(copies, cfg.rtc_max_delay, cfg.perturbed_prefix_noise, cfg.perturbed_prefix_shift)
    defaults = {f.name: f.default for f in fields(RecordConfig)}
    tuned = [f"--{k.replace('_', '-')} {getattr(cfg, k)}" for k in ("rtc_max_delay", "perturbed_prefix_noise",
                                                                     "perturbed_prefix_shift")
             if getattr(cfg, k) != defaults[k]]
    if tuned:
        raise ValueError(f"{', '.join(tuned)}: shapes perturbed prefixes, which are recorded with --perturbed-prefixes "
                         f"N > 0 (got 0); add it or drop {', '.join(tuned)}")
    return None


def run_record(cfg: RecordConfig) -> Path:
    """Record ``cfg.demos`` demonstrations per task into ``cfg.output_dir``; prints one summary line."""
    from .data.demos import record_demos

    if isinstance(cfg.demos, bool) or not isinstance(cfg.demos, int) or cfg.demos < 1:
        raise ValueError(f"--demos: expected an integer >= 1 (demonstrations per task), got {cfg.demos!r}")
    if cfg.image_size is not None and (isinstance(cfg.image_size, bool) or not isinstance(cfg.image_size, int)
                                       or cfg.image_size < 8):
        raise ValueError(f"--image-size: expected an integer >= 8 (pixels), got {cfg.image_size!r}")
    if not cfg.cameras and cfg.image_size is not None:
        raise ValueError(f"--image-size: sizes the frames of --cameras, which was not given (got "
                         f"--image-size {cfg.image_size}); add --cameras corner2 (or others) or drop it")
    if cfg.layout == "lerobot" and cfg.image_size not in (None, 480):
        raise ValueError(f"--image-size: --layout lerobot records LeRobot's Meta-World camera at its 480 x 480 px; "
                         f"got --image-size {cfg.image_size} (drop it)")
    prefixes = perturbed_prefixes(cfg)
    check_writable(Path(cfg.output_dir))
    size = cfg.image_size or (480 if cfg.layout == "lerobot" else 64)
    root = record_demos(cfg.task, cfg.demos, cfg.output_dir, cfg.seed, cfg.action_noise, cameras=cfg.cameras,
                        image_size=size, layout=cfg.layout, action_label=cfg.action_label, prefixes=prefixes)
    info = json.loads((root / "meta" / "info.json").read_text())
    cameras = [k for k, v in info["features"].items() if v.get("dtype") == "video"]
    demos = info["total_episodes"] // (1 + (prefixes.copies if prefixes else 0))
    n = info["total_episodes"] - demos if prefixes else 0
    copies = f" and {n} perturbed-prefix cop{'y' if n == 1 else 'ies'}" if prefixes else ""
    print(f"recorded {demos} demonstrations{copies} ({info['total_frames']} frames, {info['total_tasks']} "
          f"task(s), fps {info['fps']}"
          + (f", cameras {', '.join(cameras)} at {size}x{size} px" if cameras else "")
          + (", LeRobot's Meta-World observation" if cfg.layout == "lerobot" else "")
          + f") as a LeRobot v3.0 dataset in {root}", flush=True)
    return root
