"""Reading datasets in LeRobot's on-disk layout (v2.0 style; ``lerobot_write`` writes v3.0):

    <root>/data/chunk-000/episode_000000.parquet   one file per episode
    <root>/meta/info.json                          fps, features and shapes, totals
    <root>/meta/tasks.jsonl                        {"task_index", "task"} per line
    <root>/meta/episodes.jsonl                     {"episode_index", "tasks", "length", ...}
    <root>/meta/stats.json                         mean/std/min/max per feature

Reading takes any parquet files under ``data/`` (so users' own recordings load too) and
needs only ``observation.state``, ``action``, ``episode_index`` and ``frame_index``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .episodes import ACTION, CONTINUATION, STATE, EpisodeDataset
from .stats import load_stats, read_json

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


def _read_tasks(root: Path, count: int) -> list[str]:
    path = root / "meta" / "tasks.jsonl"
    if (root / "meta" / "tasks.parquet").exists():   # v3.0: task strings are the pandas index, in task_index order
        try:
            table = pq.read_table(root / "meta" / "tasks.parquet")
        except (pa.ArrowException, OSError) as err:
            raise ValueError(f"{root / 'meta' / 'tasks.parquet'}: expected a parquet table of task strings, "
                             f"got unreadable content ({err})") from None
        return [str(t) for t in table.sort_by("task_index")["__index_level_0__"].to_pylist()]
    if not path.exists():
        return [f"task_{i}" for i in range(count)]
    try:
        lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        entries = sorted((int(d["task_index"]), str(d["task"])) for d in lines)
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: expected one JSON object {{\"task_index\": int, \"task\": str}} per line, "
                         f"got unreadable content ({type(err).__name__}: {err})") from None
    if [i for i, _ in entries] != list(range(len(entries))) or len(entries) < count:
        raise ValueError(f"{path}: expected task_index 0..{count - 1} each once, got {[i for i, _ in entries]}")
    return [t for _, t in entries]


def load_dataset(root: str | Path) -> EpisodeDataset:
    """Load a dataset in LeRobot layout, validating columns, frame order and finiteness.

    ``task_index`` defaults to 0 when the column is absent; statistics come from
    ``meta/stats.json`` when present (std floored), otherwise they are computed.
    """
    root = Path(root).expanduser()
    files = sorted((root / "data").rglob("*.parquet"))
    if not files:
        raise ValueError(f"load_dataset: expected parquet files under {root / 'data'}, found none")
    tables = []
    for path in files:
        try:
            table = pq.read_table(path)
        except (pa.ArrowException, OSError) as err:
            raise ValueError(f"{path}: expected a parquet episode file, got unreadable content ({err})") from None
        if table.num_rows == 0:
            raise ValueError(f"{path}: expected an episode with at least one frame, got an empty file (0 rows); "
                             f"delete it or record the episode again")
        missing = [c for c in REQUIRED_COLUMNS if c not in table.column_names]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing}; expected at least {list(REQUIRED_COLUMNS)}, got {table.column_names}")
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
    checked = ((STATE, states), (ACTION, actions)) + (() if continuations is None else
                                                      ((CONTINUATION, continuations.reshape(len(actions), -1)),))
    for name, values in checked:
        bad = ~np.isfinite(values).all(axis=1)
        if bad.any():
            row = int(np.argmax(bad))
            raise ValueError(f"{root}: column {name!r} has NaN/Inf values in episode {episode[row]} (frame {frame[row]})")

    info_path = root / "meta" / "info.json"
    info = read_json(info_path, "LeRobot dataset info with \"fps\"") if info_path.exists() else {}
    fps = info.get("fps") if isinstance(info, dict) else None
    tasks = _read_tasks(root, int(task.max()) + 1)
    stats_path = root / "meta" / "stats.json"
    stats = load_stats(stats_path, {STATE: states.shape[1], ACTION: actions.shape[1]}) if stats_path.exists() else {}
    return EpisodeDataset(states, actions, task, lengths, tasks, fps, ids, root, stats, continuations)
