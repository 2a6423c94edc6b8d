"""Reading datasets in LeRobot's on-disk layouts.

Reading (`load_dataset`) picks the layout from ``meta/info.json``'s ``codebase_version``:

    v3.0   data/chunk-000/file-000.parquet          many episodes per file
           meta/episodes/chunk-000/file-000.parquet {"episode_index", "tasks", "length", ...}
           meta/tasks.parquet                        task strings (a "task" column, or the pandas
                                                     index LeRobot writes) with their task_index
    v2.1   data/chunk-000/episode_000000.parquet    one file per episode
    v2.0   meta/episodes.jsonl, meta/tasks.jsonl    {"episode_index", "length"}, {"task_index", "task"}

Every layout's frames come from the parquet files under ``data/`` (any names, so users' own
recordings load too; a dataset without ``info.json`` is read this way); only
``observation.state``, ``action``, ``episode_index`` and ``frame_index`` are required.
Camera features (``dtype`` "video" or "image") are listed by `camera_keys`, not loaded.
Writing (`lerobot_write.write_episodes`) produces the v3.0 layout LeRobot ≥ 0.4 loads.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .episodes import ACTION, CONTINUATION, STATE, EpisodeDataset
from .stats import read_json

REQUIRED_COLUMNS = (STATE, ACTION, "episode_index", "frame_index")


def _matrix(table: pa.Table, name: str, path: Path) -> np.ndarray:
    column = table[name].combine_chunks()
    if not (pa.types.is_list(column.type) or pa.types.is_large_list(column.type) or pa.types.is_fixed_size_list(column.type)):
        raise ValueError(f"{path}: column {name!r} expected a list of floats per frame, got type {column.type}")
    widths = pc.list_value_length(column).to_numpy(zero_copy_only=False)
    if column.null_count or len(set(widths.tolist())) > 1:
        raise ValueError(
            f"{path}: column {name!r} expected the same number of values in every frame, "
            f"got lengths {sorted(set(widths.tolist()))} and {column.null_count} nulls"
        )
    values = column.flatten()
    while pa.types.is_fixed_size_list(values.type):   # [K, D] per frame (v3.0 action.continuation)
        values = values.flatten()
    return values.to_numpy(zero_copy_only=False).astype(np.float32).reshape(len(column), -1)


V2, V3 = ("v2.0", "v2.1"), ("v3.0",)
CAMERA_DTYPES = ("video", "image")


def read_info(root: str | Path) -> dict:
    """``meta/info.json`` of a dataset ({} when the file is absent)."""
    path = Path(root).expanduser() / "meta" / "info.json"
    if not path.exists():
        return {}
    info = read_json(path, "LeRobot dataset info with \"codebase_version\", \"fps\" and \"features\"")
    if not isinstance(info, dict):
        raise ValueError(f"{path}: expected a JSON object with \"codebase_version\", \"fps\" and \"features\", "
                         f"got {type(info).__name__}")
    return info


def camera_keys(info: dict) -> list[str]:
    """The features of ``info.json`` that are camera frames (``dtype`` "video" or "image")."""
    features = info.get("features") or {}
    return [k for k, v in features.items() if isinstance(v, dict) and v.get("dtype") in CAMERA_DTYPES]


def _tasks_v2(root: Path, count: int) -> list[str]:
    path = root / "meta" / "tasks.jsonl"
    if not path.exists():
        return [f"task_{i}" for i in range(count)]
    try:
        lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        entries = sorted((int(d["task_index"]), str(d["task"])) for d in lines)
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: expected one JSON object {{\"task_index\": int, \"task\": str}} per line, "
                         f"got unreadable content ({type(err).__name__}: {err})") from None
    return _check_tasks(path, entries, count)


def _tasks_v3(root: Path, count: int) -> list[str]:
    """``meta/tasks.parquet``: the task string is a ``task`` column or, as LeRobot writes it (a
    pandas frame indexed by task), the index column ``__index_level_0__``."""
    path = root / "meta" / "tasks.parquet"
    table = _read_parquet(path, "LeRobot tasks with columns task_index and task")
    name = next((c for c in ("task", "__index_level_0__") if c in table.column_names), None)
    if name is None or "task_index" not in table.column_names:
        raise ValueError(f"{path}: expected columns task_index and task (or the pandas index "
                         f"__index_level_0__), got {table.column_names}")
    entries = sorted(zip(table["task_index"].to_pylist(), map(str, table[name].to_pylist())))
    return _check_tasks(path, entries, count)


def _check_tasks(path: Path, entries: list[tuple[int, str]], count: int) -> list[str]:
    if [i for i, _ in entries] != list(range(len(entries))) or len(entries) < count:
        raise ValueError(f"{path}: expected task_index 0..{count - 1} each once, got {[i for i, _ in entries]}")
    return [t for _, t in entries]


def _episode_lengths(root: Path, version: str) -> tuple[Path, dict[int, int]] | None:
    """(file, {episode_index: length}) from the episode metadata, None where there is none."""
    if version in V3:
        files = sorted((root / "meta" / "episodes").rglob("*.parquet"))
        if not files:
            return None
        tables = [_read_parquet(f, "LeRobot episodes with columns episode_index and length") for f in files]
        for f, t in zip(files, tables):
            if not {"episode_index", "length"} <= set(t.column_names):
                raise ValueError(f"{f}: expected columns episode_index and length, got {t.column_names[:8]}")
        pairs = [(e, n) for t in tables for e, n in zip(t["episode_index"].to_pylist(), t["length"].to_pylist())]
        return root / "meta" / "episodes", dict(pairs)
    path = root / "meta" / "episodes.jsonl"
    if not path.exists():
        return None
    try:
        lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        return path, {int(d["episode_index"]): int(d["length"]) for d in lines}
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: expected one JSON object {{\"episode_index\": int, \"length\": int, ...}} per "
                         f"line, got unreadable content ({type(err).__name__}: {err})") from None


def _read_parquet(path: Path, expected: str, columns: list[str] | None = None) -> pa.Table:
    if not path.exists():
        raise ValueError(f"{path}: expected {expected}, the file is missing")
    try:
        return pq.read_table(path, columns=columns)
    except (pa.ArrowException, OSError) as err:
        raise ValueError(f"{path}: expected parquet ({expected}), got unreadable content ({err})") from None


def _read_frames(path: Path) -> pa.Table:
    """The columns of one data file the policy uses (camera columns are not loaded)."""
    try:
        names = pq.read_schema(path).names
    except (pa.ArrowException, OSError) as err:
        raise ValueError(f"{path}: expected a parquet episode file, got unreadable content ({err})") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; expected at least {list(REQUIRED_COLUMNS)}, got {names}")
    return _read_parquet(path, "a parquet episode file",
                         [c for c in names if c in REQUIRED_COLUMNS + ("task_index", CONTINUATION)])


def load_dataset(root: str | Path) -> EpisodeDataset:
    """Load a LeRobot dataset (format v3.0, v2.1 or v2.0; see the module docstring): frames, episode
    boundaries, fps and task strings, validating columns, frame order and finiteness.

    The same recording in v3.0 and in v2.1 loads identically. ``task_index`` defaults to 0 when
    the column is absent. Normalisation statistics are computed from the frames (mean, std floored,
    min, max), never read from ``meta/stats.json`` or ``episodes_stats.jsonl``: exact, the same for
    every layout, and what a subset of episodes recomputes too (LeRobot aggregates its per-episode
    statistics to the same mean and std).
    """
    root = Path(root).expanduser()
    info = read_info(root)
    version = info.get("codebase_version", "v2.0")
    if version not in V2 + V3:
        raise ValueError(f"{root / 'meta' / 'info.json'}: codebase_version expected one of {list(V2 + V3)}, "
                         f"got {version!r}")
    files = sorted((root / "data").rglob("*.parquet"))
    if not files:
        raise ValueError(f"load_dataset: expected parquet files under {root / 'data'}, found none")
    tables = []
    for path in files:
        table = _read_frames(path)
        if table.num_rows == 0:
            raise ValueError(f"{path}: expected an episode with at least one frame, got an empty file (0 rows); "
                             f"delete it or record the episode again")
        states, actions = _matrix(table, STATE, path), _matrix(table, ACTION, path)
        task = table["task_index"].to_numpy() if "task_index" in table.column_names else np.zeros(len(table), np.int64)
        more = _matrix(table, CONTINUATION, path) if CONTINUATION in table.column_names else None
        tables.append((states, actions, table["episode_index"].to_numpy(), table["frame_index"].to_numpy(), task,
                       more))
    widths = sorted({(s.shape[1], a.shape[1], None if c is None else c.shape[1]) for s, a, *_, c in tables},
                    key=str)   # None (no continuation) does not compare with ints
    if len(widths) > 1:
        raise ValueError(f"{root}: expected the same (state, action, {CONTINUATION}) widths in every file, "
                         f"got {widths}")
    states, actions, episode, frame, task = (np.concatenate(parts) for parts in list(zip(*tables))[:5])
    continuations = None if tables[0][5] is None else np.concatenate([t[5] for t in tables])

    order = np.lexsort((frame, episode))
    states, actions, episode, frame, task = states[order], actions[order], episode[order], frame[order], task[order]
    if continuations is not None:
        if continuations.shape[1] % actions.shape[1]:
            raise ValueError(f"{root}: column {CONTINUATION!r} expected K × {actions.shape[1]} values per frame "
                             f"(K actions), got {continuations.shape[1]}")
        continuations = continuations[order].reshape(len(actions), -1, actions.shape[1])  # [N, K, D]
    ids, starts, lengths = np.unique(episode, return_index=True, return_counts=True)
    for i, start, length in zip(ids, starts, lengths):
        if not np.array_equal(frame[start:start + length], np.arange(length)):
            raise ValueError(
                f"{root}: episode {i} expected frame_index 0..{length - 1} each once, got {frame[start:start + length][:10].tolist()}..."
            )
    meta = _episode_lengths(root, version)
    if meta is not None and meta[1] != dict(zip(ids.tolist(), lengths.tolist())):
        path, want = meta
        found = dict(zip(ids.tolist(), lengths.tolist()))
        diff = sorted(set(want) ^ set(found)) or [e for e in want if want[e] != found[e]]
        raise ValueError(f"{path}: expected the episodes and lengths the data files hold, got a mismatch at "
                         f"episode(s) {diff[:10]} (metadata {[want.get(e) for e in diff[:10]]} frames, data "
                         f"{[found.get(e) for e in diff[:10]]})")
    checked = ((STATE, states), (ACTION, actions)) + (() if continuations is None else
                                                      ((CONTINUATION, continuations.reshape(len(actions), -1)),))
    for name, values in checked:
        bad = ~np.isfinite(values).all(axis=1)
        if bad.any():
            row = int(np.argmax(bad))
            raise ValueError(f"{root}: column {name!r} has NaN/Inf values in episode {episode[row]} (frame {frame[row]})")

    count = int(task.max()) + 1
    tasks = _tasks_v3(root, count) if version in V3 else _tasks_v2(root, count)
    return EpisodeDataset(states, actions, task, lengths, tasks, info.get("fps"), ids, root, {}, continuations)
