"""`action-decoder record`: scripted-expert demonstrations written as a LeRobot v3.0 dataset."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path


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


def run_record(cfg: RecordConfig) -> Path:
    """Record ``cfg.demos`` demonstrations per task into ``cfg.output_dir``; prints one summary line."""
    from .data.demos import record_demos

    if isinstance(cfg.demos, bool) or not isinstance(cfg.demos, int) or cfg.demos < 1:
        raise ValueError(f"--demos: expected an integer >= 1 (demonstrations per task), got {cfg.demos!r}")
    root = record_demos(cfg.task, cfg.demos, cfg.output_dir, cfg.seed, cfg.action_noise)
    info = json.loads((root / "meta" / "info.json").read_text())
    print(f"recorded {info['total_episodes']} demonstrations ({info['total_frames']} frames, {info['total_tasks']} "
          f"task(s), fps {info['fps']}) as a LeRobot v3.0 dataset in {root}", flush=True)
    return root
