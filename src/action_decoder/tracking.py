"""What a run reports as it goes: scalars to TensorBoard, to Weights & Biases (opt-in) and to a
JSON-lines log, so a run can be watched, compared with others, and keeps its curve when killed.

    <run_dir>/events.out.tfevents.*   TensorBoard, one run per directory (`tensorboard --logdir outputs`)
    <run_dir>/train_log.jsonl         one JSON object per log step (finetune: finetune_log.jsonl)
    <run_dir>/wandb/, wandb_run_id    with --wandb: W&B's local files and the id a resume continues
"""

from __future__ import annotations

import json
import os
import re
import secrets
import sys
import time
from pathlib import Path
from typing import Optional

from .run_dir import CKPT_DIR, FINAL, FINAL_STEP, LOG_FILES, _writing

"""The JSON-lines logs of `train` and `finetune`, in their run directories."""
WANDB_ID_FILE = "wandb_run_id"


def require_wandb(enabled: bool) -> None:
    """With --wandb, refuse in one line (before any work) when the wandb package is missing."""
    if not enabled:
        return
    try:
        import wandb  # noqa: F401
    except ImportError:
        raise ValueError('--wandb: needs the wandb package (pip install "action-decoder[wandb]"), which is not '
                         'installed') from None


def read_jsonl(path: Path) -> list[dict]:
    """The rows of a JSON-lines log ([] when it does not exist); a line cut short by a kill is skipped."""
    rows = []
    if Path(path).is_file():
        for line in Path(path).read_text().splitlines():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return rows


def _keep_through(path: Path, step: int) -> None:
    """Drop the rows of `path` past `step` (written by a run that was killed after its last checkpoint)."""
    if not path.is_file():
        return
    rows = [r for r in read_jsonl(path) if r.get("step", 0) <= step]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("".join(json.dumps(r) + "\n" for r in rows))
    os.replace(tmp, path)


def _after_existing_event_files(run_dir: Path) -> None:
    """Wait, if need be, until the clock's second is past every event file's in `run_dir`. TensorBoard reads
    a directory's files in name order, `events.out.tfevents.<second>.<host>.<pid>…`: a file opened in the
    same second as an earlier one, by a process of a lower pid (a resume right after a killed run), would
    be read before it, and the earlier run's events past the restart would outlive its purge marker."""
    seconds = [int(m.group(1)) for f in run_dir.glob("events.out.tfevents.*")
               if (m := re.match(r"events\.out\.tfevents\.(\d+)\.", f.name))]
    while seconds and int(time.time()) <= max(seconds):
        time.sleep(0.05)


def _start_wandb(run_dir: Path, project: str, job_type: str, config: dict, name: str, resume: Optional[bool]):
    """A W&B run logging into `run_dir/wandb`. `resume` False: a new run, its id kept in
    `run_dir/wandb_run_id`; True: the run that file names continues (a new one if there is none);
    None: a run of its own (an evaluation)."""
    import wandb

    ids = {}
    if resume is not None:
        id_file = run_dir / WANDB_ID_FILE
        run_id = id_file.read_text().strip() if resume and id_file.is_file() else secrets.token_hex(4)
        id_file.write_text(run_id)
        ids = {"id": run_id, "resume": "allow"}
    return wandb.init(project=project, dir=str(run_dir), name=name, group=run_dir.name, job_type=job_type,
                      config=config, **ids)


class RunLogger:
    """Fans a run's scalars out to TensorBoard event files in `run_dir`, an optional W&B run, and
    `run_dir/<jsonl>` (one JSON object per `log` call, flushed at once). Every call flushes the
    events too, so TensorBoard shows a run while it trains and a killed run keeps its curve.

    `start_step`: the step a run starts or resumes from. The log's rows past it are dropped and
    TensorBoard is told to drop its events past it (the restart marker `purge_step = start_step + 1`), so a
    resumed run shows each step once. None: add to what is there (an evaluation of a finished run).
    `wandb_project`: also log to W&B (None: off); a run resumed past step 0 continues its W&B run.
    """

    def __init__(self, run_dir: Path, jsonl: Optional[str] = None, start_step: Optional[int] = 0,
                 wandb_project: Optional[str] = None, job_type: str = "train", config: Optional[dict] = None,
                 name: Optional[str] = None):
        try:
            import tensorboard  # noqa: F401  (torch.utils.tensorboard writes through it)
        except ImportError:
            raise ValueError('tensorboard: run logs need the tensorboard package, a dependency of action-decoder '
                             '(pip install "tensorboard>=2.18")') from None
        from torch.utils.tensorboard import SummaryWriter

        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.jsonl = None if jsonl is None else self.run_dir / jsonl
        if self.jsonl is not None and start_step is not None:
            with _writing(self.jsonl, self.run_dir):
                _keep_through(self.jsonl, start_step)
        _after_existing_event_files(self.run_dir)
        self.events = SummaryWriter(str(self.run_dir), purge_step=None if start_step is None else start_step + 1)
        self.wandb = None
        self._wandb_prefixes: set[str] = set()
        if wandb_project is not None:
            self.wandb = _start_wandb(self.run_dir, wandb_project, job_type, config or {},
                                      name or self.run_dir.absolute().name,
                                      resume=None if start_step is None else start_step > 0)

    def log(self, step: int, values: dict, prefix: str, record: bool = True) -> None:
        """Each number of `values` as the scalar `<prefix>/<key>` at `step` (TensorBoard's x axis, and
        W&B's through `<prefix>/step`); with `record`, `{"step": step, **values}` as one line of the jsonl."""
        scalars = {f"{prefix}/{k}": float(v) for k, v in values.items()
                   if k != "step" and isinstance(v, (int, float))}
        for tag, value in scalars.items():
            self.events.add_scalar(tag, value, step)
        self.events.flush()
        if self.wandb is not None:
            if prefix not in self._wandb_prefixes:
                self.wandb.define_metric(f"{prefix}/step")
                self.wandb.define_metric(f"{prefix}/*", step_metric=f"{prefix}/step")
                self._wandb_prefixes.add(prefix)
            self.wandb.log({f"{prefix}/step": step, **scalars})
        if record and self.jsonl is not None:
            with _writing(self.jsonl, self.run_dir), open(self.jsonl, "a") as f:
                f.write(json.dumps({"step": step, **values}) + "\n")
                f.flush()

    def close(self) -> None:
        self.events.close()
        if self.wandb is not None:
            self.wandb.finish()
            self.wandb = None

    def __enter__(self) -> "RunLogger":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def checkpoint_run(checkpoint: Path) -> tuple[Optional[Path], int]:
    """The run directory a checkpoint belongs to and the step it holds: `<run>/final` at the step its
    `FINAL_STEP` file names (a `final/` without one: the run's last logged step), `<run>/checkpoints/step_N`
    at its N-th step (finetune: N-th iteration, at that iteration's env steps). (None, 0) for a
    checkpoint outside a run directory, or a `final/` beside no run log."""
    ckpt = Path(checkpoint).absolute()
    if ckpt.name == FINAL:
        run_dir, index = ckpt.parent, None
    elif ckpt.parent.name == CKPT_DIR and re.fullmatch(r"step_\d+", ckpt.name):
        run_dir, index = ckpt.parent.parent, int(ckpt.name[len("step_"):])
    else:
        return None, 0
    rows = next((rows for rows in (read_jsonl(run_dir / name) for name in LOG_FILES) if rows), [])
    if index is None:
        try:
            return run_dir, int(json.loads((ckpt / FINAL_STEP).read_text())["step"])
        except (OSError, ValueError, KeyError, TypeError):
            return (run_dir, int(rows[-1]["step"])) if rows else (None, 0)
    return run_dir, next((int(r["step"]) for r in rows if r.get("iteration", r.get("step")) == index), index)


def log_evaluation(summary: dict, checkpoint: Path, written: Optional[Path],
                   wandb_project: Optional[str] = None) -> Optional[Path]:
    """An evaluation's success rate and success per task as TensorBoard scalars
    `eval/<setting>/success_rate` and `eval/<setting>/success/<task>` (`<setting>`: the summary's file
    name, e.g. `sde_k10_n4_seed0`), in the run directory of the checkpoint at its step
    (`checkpoint_run`), else next to the summary at step 0; also to W&B with `wandb_project`.
    Returns the events' directory (None: not written, one warning line says why)."""
    run_dir, step = checkpoint_run(checkpoint)
    target = run_dir or (written.parent if written is not None else None)
    if target is None:
        return None
    setting = written.stem.removeprefix("eval_") if written is not None else \
        f"{summary['sampler']}_k{summary['steps']}_n{summary['n_action_steps']}_seed{summary['seed']}"
    values = {"success_rate": summary["success_rate"],
              **{f"success/{task}": rate for task, rate in summary["per_task"].items()}}
    config = {k: v for k, v in summary.items() if k not in ("results", "per_task")}
    try:
        logger = RunLogger(target, start_step=None, wandb_project=wandb_project, job_type="eval", config=config,
                           name=f"{target.absolute().name}/{setting}")
    except OSError as err:
        print(f"action-decoder: warning: TensorBoard events not written: cannot write {target} "
              f"({err.strerror or err})", file=sys.stderr, flush=True)
        return None
    with logger:
        logger.log(step, values, f"eval/{setting}", record=False)
    return target
