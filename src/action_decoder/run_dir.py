"""A run's output directory: its lock, atomic checkpoints, and the checkpoint a resume continues from.

    <out>/.lock                      held by the run that writes here (flock)
    <out>/checkpoints/step_NNNNNNN   save_pretrained + the training state, the last two kept:
                                     training_state.safetensors (tensors: optimizer moments, RNG
                                     states, the weight average) + training_state.json (the rest);
                                     no pickle, so resuming never runs code from a file
    <out>/checkpoints/last           names the newest step (written atomically)
    <out>/final                      save_pretrained of the result
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import random
import shutil
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from safetensors.torch import load_file
from safetensors.torch import save as tensors_to_bytes

from . import model_card
from .policy import ActionDecoderPolicy

CKPT_DIR, LAST, FINAL, LOCK = "checkpoints", "last", "final", ".lock"
STATE_JSON, STATE_TENSORS = "training_state.json", "training_state.safetensors"
LOG_FILES = ("train_log.jsonl", "finetune_log.jsonl")
FINAL_STEP = "step.json"
"""In `final/`: {"step": N}, the logged step its weights come from (train: optimizer steps; finetune: env steps)."""
LEGACY_STATE = "training_state.pt"
STATE_FORMAT = "action-decoder training state 1"


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def _encode(obj, tensors: dict, key: str):
    """`obj` as JSON, its tensors moved into `tensors` under their path (`key`). Tuples, NumPy
    arrays and dicts with non-string keys are tagged so that `_decode` rebuilds them exactly."""
    if isinstance(obj, torch.Tensor):
        tensors[key] = obj.detach().cpu().clone().contiguous()     # its own storage: safetensors refuses shared ones
        return {"__tensor__": key}
    if isinstance(obj, np.ndarray):
        return {"__ndarray__": obj.tolist(), "dtype": str(obj.dtype)}
    if isinstance(obj, tuple):
        return {"__tuple__": [_encode(v, tensors, f"{key}.{i}") for i, v in enumerate(obj)]}
    if isinstance(obj, list):
        return [_encode(v, tensors, f"{key}.{i}") for i, v in enumerate(obj)]
    if isinstance(obj, dict):
        if all(isinstance(k, str) and not k.startswith("__") for k in obj):
            return {k: _encode(v, tensors, f"{key}.{k}") for k, v in obj.items()}
        return {"__items__": [[_encode(k, tensors, f"{key}.{i}k"), _encode(v, tensors, f"{key}.{i}")]
                              for i, (k, v) in enumerate(obj.items())]}
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    if isinstance(obj, (np.integer, np.floating)):
        return obj.item()
    raise TypeError(f"training state {key}: cannot store a {type(obj).__name__} (tensors, numbers, strings, "
                    f"lists, tuples, dicts and NumPy arrays only)")


def _decode(obj, tensors: dict):
    if isinstance(obj, list):
        return [_decode(v, tensors) for v in obj]
    if not isinstance(obj, dict):
        return obj
    if "__tensor__" in obj:
        return tensors[obj["__tensor__"]]
    if "__ndarray__" in obj:
        return np.asarray(obj["__ndarray__"], dtype=obj["dtype"])
    if "__tuple__" in obj:
        return tuple(_decode(v, tensors) for v in obj["__tuple__"])
    if "__items__" in obj:
        return {_decode(k, tensors): _decode(v, tensors) for k, v in obj["__items__"]}
    return {k: _decode(v, tensors) for k, v in obj.items()}


def save_state(state: dict, directory: Path) -> None:
    """Write a training state (nested dicts, lists and tuples of tensors, numbers, strings and NumPy
    arrays) as `training_state.safetensors` + `training_state.json`: `load_state` gives it back
    bit for bit, and neither file is a pickle."""
    tensors: dict = {}
    encoded = _encode(state, tensors, "state")
    # Serialised in memory, written by Python: a full disk raises OSError (ENOSPC), not safetensors' own error.
    (directory / STATE_TENSORS).write_bytes(tensors_to_bytes(tensors, metadata={"format": STATE_FORMAT}))
    (directory / STATE_JSON).write_text(json.dumps({"format": STATE_FORMAT, "state": encoded}))


def load_state(directory: Path) -> dict:
    """The training state `save_state` wrote in `directory` (ValueError in one line otherwise)."""
    if not (directory / STATE_JSON).is_file() and (directory / LEGACY_STATE).is_file():
        raise ValueError(f"{LEGACY_STATE} is a pickled training state, which this version does not load "
                         f"(expected {STATE_JSON}); continue that run with the version that wrote it")
    try:
        saved = json.loads((directory / STATE_JSON).read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"{directory / STATE_JSON}: not a readable training state ({err})") from None
    if not isinstance(saved, dict) or saved.get("format") != STATE_FORMAT:
        raise ValueError(f"{directory / STATE_JSON}: expected format {STATE_FORMAT!r}, got "
                         f"{saved.get('format') if isinstance(saved, dict) else type(saved).__name__!r}")
    try:
        tensors = load_file(str(directory / STATE_TENSORS))
    except Exception as err:    # safetensors raises its own error type for a damaged file
        raise ValueError(f"{directory / STATE_TENSORS}: not a readable safetensors file ({err})") from None
    try:
        return _decode(saved["state"], tensors)
    except KeyError as err:
        raise ValueError(f"{directory / STATE_TENSORS}: tensor {err} is missing") from None


def _disk_error(err: BaseException, target: Path, out: Path) -> OSError:
    """One line for a failed write: what could not be written, why, and what is still intact."""
    root = target.parent if target.parent.exists() else out
    full = getattr(err, "errno", None) in (errno.ENOSPC, errno.EDQUOT)
    with contextlib.suppress(OSError):
        full = full or shutil.disk_usage(root).free < 2**20        # torch's writer raises RuntimeError
    why = "no space left on device" if full else (str(err).strip().splitlines() or [type(err).__name__])[-1]
    kept = last_checkpoint(out)
    keep = f"the previous checkpoint {kept} is intact" if kept else "no earlier checkpoint exists"
    return OSError(errno.ENOSPC if full else getattr(err, "errno", None) or errno.EIO,
                   f"cannot write {target}: {why}; {keep} (free space, then continue with --resume)")


@contextlib.contextmanager
def _writing(target: Path, out: Path, tmp: Optional[Path] = None):
    """Turn a failed write (full disk, read-only directory) into one line, removing `tmp`."""
    try:
        yield
    except (OSError, RuntimeError) as err:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        raise _disk_error(err, target, out) from None


def write_checkpoint(out: Path, step: int, policy, state: dict) -> Path:
    """Write `checkpoints/step_N` (policy + `save_state(state)`) through a temporary directory
    and a rename, then point `checkpoints/last` at it (also atomically): a crash or a full disk
    leaves the previous checkpoint intact (a full disk raises OSError saying so). Keeps the last two."""
    root = out / CKPT_DIR
    final = root / f"step_{step:07d}"
    tmp = root / f".tmp_step_{step:07d}"
    with _writing(final, out, tmp):
        root.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(tmp, ignore_errors=True)
        policy.save_pretrained(tmp)
        save_state(state, tmp)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
        pointer = root / (LAST + ".tmp")
        pointer.write_text(final.name)
        os.replace(pointer, root / LAST)
    for old in sorted(root.glob("step_*"))[:-2]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def save_final(out: Path, policy, step: int, name: str = FINAL) -> Path:
    """`out/final` (or `out/<name>`) in `save_pretrained` format with `FINAL_STEP` (the logged `step` of
    these weights), replaced atomically. When the weights are those the old directory holds (a finished
    run resumed), its measured results and evaluation files stay."""
    final, tmp = out / name, out / f".tmp_{name}"
    with _writing(final, out, tmp):
        shutil.rmtree(tmp, ignore_errors=True)
        same = model_card.carried_results(model_card.read_results(final), model_card.weights_digest(policy.state_dict()))
        before = getattr(policy, "_card_results", [])
        policy._card_results = before + same
        try:
            policy.save_pretrained(tmp)
        finally:
            policy._card_results = before
        (tmp / FINAL_STEP).write_text(json.dumps({"step": int(step)}) + "\n")
        if same:                                    # eval_*.json / .png / .mp4 of these weights
            for path in final.iterdir():
                if path.is_file() and not (tmp / path.name).exists():
                    shutil.copy2(path, tmp / path.name)
        shutil.rmtree(final, ignore_errors=True)
        os.replace(tmp, final)
    return final


@contextlib.contextmanager
def run_dir_lock(out: Path, option: str = "--output-dir"):
    """Hold an exclusive lock on `out/.lock` (created with `out`) while the block runs.

    A second run on the same directory fails at once with one line naming the holder's pid,
    instead of both writing checkpoints into it. The kernel drops the lock when its process
    ends, killed or not, so a lock file left behind never blocks a later run. `out` must be a
    directory or not exist yet; anything else is refused before any work starts. A run that ends in an
    error (a refused option, a missing dataset) before writing anything takes back the lock file, and
    the directory when it made it: no directory is left holding only `.lock`."""
    import fcntl

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{option}: expected a directory (new or from an earlier run), got the file {out}")
    made_dir, made_lock = not out.exists(), not (out / LOCK).exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise ValueError(f"{option}: cannot write to {out} ({err.strerror})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise ValueError(f"{option}: {out} is in use by another run (pid {holder}); wait for it to end "
                         f"or choose another directory") from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode(), 0)
        yield out
    except BaseException:
        if made_lock and [p.name for p in out.iterdir()] == [LOCK]:     # nothing written but the lock
            with contextlib.suppress(OSError):
                (out / LOCK).unlink()                                   # while still held
                if made_dir:
                    out.rmdir()
        raise
    finally:
        os.close(fd)


def existing_run(out: Path) -> Optional[str]:
    """What in `out` shows an earlier training or fine-tuning run (a checkpoint, `final/`, a run log),
    or None: a new run must not write over it."""
    if last_checkpoint(out) is not None or (out / CKPT_DIR / LAST).exists():
        return f"checkpoints in {out / CKPT_DIR}"
    if (out / FINAL).exists():
        return f"a final policy {out / FINAL}"
    logs = [out / name for name in LOG_FILES if (out / name).is_file() and (out / name).stat().st_size > 0]
    return f"the run log {logs[0]}" if logs else None


def last_checkpoint(out: Path) -> Optional[Path]:
    """The newest `checkpoints/step_*` that holds a training state (None: no checkpoint; a pickled
    `training_state.pt` counts, so that a run never overwrites one, and `load_state` refuses it).

    Newest by step, not by the `last` pointer, so that a deleted or half-written target does
    not hide an intact older checkpoint. `resume_checkpoint` also checks that it loads."""
    steps = sorted((out / CKPT_DIR).glob("step_*"), reverse=True)
    return next((p for p in steps if (p / STATE_JSON).is_file() or (p / LEGACY_STATE).is_file()), None)


def resume_checkpoint(out: Path, device: torch.device) -> Optional[tuple[Path, ActionDecoderPolicy, dict, str]]:
    """The newest checkpoint of `out` whose config, weights and training state load:
    (path, policy, training state, a note saying why it is not the one `last` names, or "").
    None when `out` has no checkpoint; ValueError when it has some but none loads."""
    root = out / CKPT_DIR
    pointer = root / LAST
    named = pointer.read_text(errors="replace").strip() if pointer.is_file() else None
    skipped = {}
    for path in sorted(root.glob("step_*"), reverse=True):
        try:
            policy = ActionDecoderPolicy.from_pretrained(path, map_location=device)
            state = load_state(path)
        except Exception as err:   # any failure to load means: not intact, try the next one
            skipped[path.name] = (str(err).strip().splitlines() or [type(err).__name__])[0][:120]
            continue
        if named == path.name:
            return path, policy, state, ""
        if named is None:
            why = f"{pointer} is missing"
        elif named in skipped:
            why = f"{pointer} names {named}, which does not load ({skipped[named]})"
        elif not (root / named).exists():
            why = f"{pointer} names {named}, which is missing"
        else:
            why = f"{pointer} names {named}, older than {path.name}"
        return path, policy, state, why
    if skipped:
        raise ValueError(f"--resume: no intact checkpoint in {root}: "
                         + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    return None
