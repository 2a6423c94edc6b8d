"""Normalisation statistics (LeRobot's ``meta/stats.json`` form: mean, std, min, max, count).

The std is floored: Meta-World states have constant dimensions (std 0), and dividing by
a zero std would turn them into NaN or huge values. A state dimension whose std is below
``STD_FLOOR`` takes ``STD_FLOOR`` (its nearly constant values would otherwise become unit-scale
inputs). An action dimension takes it only below ``ACTION_CONSTANT_BELOW``, i.e. when it is
constant: an action in metres (an end-effector delta of std 0.003) keeps its own std and reaches
the decoder at unit scale.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping

import numpy as np

from ..normalize import ACTION_CONSTANT_BELOW, SPREAD_FLOOR as STD_FLOOR  # noqa: F401 (re-exported)
STAT_KEYS = ("mean", "std", "min", "max")


def compute_stats(features: Mapping[str, np.ndarray], std_floor: float = STD_FLOOR,
                  constant_below: Mapping[str, float] | None = None) -> dict[str, dict]:
    """Per-dimension mean/std/min/max of each ``[N, dim]`` feature. A std below the feature's
    ``constant_below`` entry (default: ``std_floor`` itself) is replaced by ``std_floor``."""
    stats = {}
    for name, values in features.items():
        below = (constant_below or {}).get(name, std_floor)
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2 or len(values) == 0:
            raise ValueError(f"compute_stats: feature {name!r} must be a non-empty [N, dim] array, got shape {values.shape}")
        std = values.std(0)
        stats[name] = {
            "mean": values.mean(0).astype(np.float32),
            "std": np.where(std < below, std_floor, std).astype(np.float32),
            "min": values.min(0).astype(np.float32),
            "max": values.max(0).astype(np.float32),
            "count": int(len(values)),
        }
    return stats


def read_json(path: str | Path, expected: str):
    """``json.loads`` of a file, with a ValueError naming the file and what it should hold."""
    try:
        return json.loads(Path(path).read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: expected JSON ({expected}), got unreadable content ({err}); "
                         f"fix or delete the file") from None


def save_stats(stats: Mapping[str, Mapping], path: str | Path) -> None:
    """Write statistics as JSON lists."""
    out = {name: {k: np.asarray(v).tolist() if k in STAT_KEYS else v for k, v in s.items()} for name, s in stats.items()}
    Path(path).write_text(json.dumps(out, indent=2))


def load_stats(path: str | Path, dims: Mapping[str, int], std_floor: float = STD_FLOOR) -> dict[str, dict]:
    """Read statistics for the features in ``dims`` (name -> width), flooring the std. A file that
    is not such JSON raises ValueError naming it (delete it and the statistics are recomputed)."""
    raw = read_json(path, "LeRobot statistics: {feature: {mean, std, min, max}}")
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a JSON object {{feature: {{mean, std, min, max}}}}, got {type(raw).__name__}")
    stats = {}
    for name, dim in dims.items():
        if not isinstance(raw.get(name), dict) or any(k not in raw[name] for k in STAT_KEYS):
            found = sorted(raw[name]) if isinstance(raw.get(name), dict) else sorted(raw)
            raise ValueError(f"{path}: expected {name!r} with keys {list(STAT_KEYS)}, got {found}")
        try:
            entry = {k: np.asarray(raw[name][k], dtype=np.float32).reshape(-1) for k in STAT_KEYS}
        except (TypeError, ValueError) as err:
            raise ValueError(f"{path}: expected lists of numbers as {name} for {list(STAT_KEYS)} ({err})") from None
        for k, v in entry.items():
            if v.shape != (dim,):
                raise ValueError(f"{path}: {name}.{k} expected {dim} values, got {v.shape[0]}")
        entry["std"] = np.maximum(entry["std"], std_floor)
        stats[name] = {**entry, "count": raw[name].get("count")}
    return stats
