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
Camera features (``dtype`` "video" or "image", listed by `camera_keys`) load as uint8 frames
(`load_dataset`'s ``cameras`` and ``image_size``):

    v3.0 video  videos/{key}/chunk-000/file-000.mp4 (``video_path``), several episodes per file; the
                episode starts at ``videos/{key}/from_timestamp`` (a column of meta/episodes), so a
                row's frame is at ``from_timestamp + timestamp``
    v2.x video  ``video_path`` (videos/chunk-000/{key}/episode_000000.mp4), one file per episode
                and camera; a row's frame is at ``timestamp``
    image       a parquet column of LeRobot's struct {bytes: PNG, path}, one image per row
Writing (`lerobot_write.write_episodes`) produces the v3.0 layout LeRobot ≥ 0.4 loads.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .episodes import ACTION, CONTINUATION, PREFIX_LENGTH, STATE, EpisodeDataset
from .stats import read_json
from .video import decode_png, image_hw, read_frames

REQUIRED_COLUMNS = (STATE, ACTION, "episode_index", "frame_index")


def _matrix(table: pa.Table, name: str, path: Path) -> np.ndarray:
    column = table[name].combine_chunks()
    if (pa.types.is_floating(column.type) or pa.types.is_integer(column.type)) and not column.null_count:
        # LeRobot stores a feature of shape [1] as a plain number per frame
        return column.to_numpy(zero_copy_only=False).astype(np.float32).reshape(len(column), 1)
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


def _task_index(table: pa.Table, path: Path) -> np.ndarray:
    """The ``task_index`` column as int64 ``[N]`` (0 for every frame when the column is absent)."""
    if "task_index" not in table.column_names:
        return np.zeros(table.num_rows, np.int64)
    column = table["task_index"].combine_chunks()
    if column.null_count or not pa.types.is_integer(column.type):
        raise ValueError(f"{path}: column 'task_index' expected an integer per frame, got type {column.type} "
                         f"with {column.null_count} nulls")
    task = column.to_numpy(zero_copy_only=False).astype(np.int64)
    if len(task) and task.min() < 0:
        raise ValueError(f"{path}: column 'task_index' expected indices >= 0 into meta/tasks, got {int(task.min())}")
    return task


V2, V3 = ("v2.0", "v2.1"), ("v3.0",)
CAMERA_DTYPES = ("video", "image")


def check_dataset_dir(root: str | Path, field: str = "load_dataset") -> None:
    """Refuse, naming `field`, a path that is missing or a file: a dataset is a directory."""
    root = Path(root).expanduser()
    if not root.exists():
        raise ValueError(f"{field}: {root} does not exist; expected a LeRobot dataset directory (meta/info.json "
                         f"and data/*.parquet)")
    if not root.is_dir():
        raise ValueError(f"{field}: {root} is a file; expected a LeRobot dataset directory (meta/info.json and "
                         f"data/*.parquet), e.g. the directory that holds it")


def read_info(root: str | Path) -> dict:
    """``meta/info.json`` of a dataset ({} when the file is absent)."""
    path = Path(root).expanduser() / "meta" / "info.json"
    if not path.exists():
        return {}
    info = read_json(path, "LeRobot dataset info with \"codebase_version\", \"fps\" and \"features\"")
    if not isinstance(info, dict):
        raise ValueError(f"{path}: expected a JSON object with \"codebase_version\", \"fps\" and \"features\", "
                         f"got {type(info).__name__}")
    if not isinstance(info.get("features", {}), dict):
        raise ValueError(f"{path}: \"features\" expected an object of feature name -> {{\"dtype\", \"shape\"}}, "
                         f"got {info['features']!r:.80}")
    fps = info.get("fps")
    if fps is not None and (isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0):
        raise ValueError(f"{path}: \"fps\" expected a positive number of frames per second, got {fps!r}")
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


def _read_frames(path: Path, image_keys: tuple[str, ...] = ()) -> pa.Table:
    """The columns of one data file the policy uses, with the ``image_keys`` columns (PNG cells)."""
    try:
        names = pq.read_schema(path).names
    except (pa.ArrowException, OSError) as err:
        raise ValueError(f"{path}: expected a parquet episode file, got unreadable content ({err})") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; expected at least {list(REQUIRED_COLUMNS)}, got {names}")
    return _read_parquet(path, "a parquet episode file",
                         [c for c in names if c in REQUIRED_COLUMNS + ("task_index", "timestamp", CONTINUATION,
                                                                       PREFIX_LENGTH) + image_keys])


def _prefix_lengths(table: pa.Table, path: Path, has_continuation: bool) -> np.ndarray | None:
    """The ``action.prefix_length`` column [N] int64, or None without it; it needs ``action.continuation``."""
    if PREFIX_LENGTH not in table.column_names:
        return None
    column = table[PREFIX_LENGTH]
    if not has_continuation or not pa.types.is_integer(column.type):
        raise ValueError(f"{path}: column {PREFIX_LENGTH!r} expected integers beside {CONTINUATION!r} (the committed "
                         f"rows each continuation starts with), got {column.type}"
                         f"{'' if has_continuation else f' and no {CONTINUATION!r}'}")
    return column.to_numpy().astype(np.int64)


def select_cameras(info: dict, cameras, root: Path) -> list[str]:
    """The camera keys to load: all of the dataset's for None, else ``cameras`` checked against them."""
    available = camera_keys(info)
    if cameras is None:
        return available
    if isinstance(cameras, str) or not all(isinstance(c, str) for c in cameras):
        raise ValueError(f"cameras: expected a list of camera feature keys (of {available}), got {cameras!r}")
    unknown = [c for c in cameras if c not in available]
    if unknown or len(set(cameras)) != len(cameras):
        raise ValueError(f"cameras: expected distinct camera feature keys of {root} (available: "
                         f"{', '.join(available) or 'none'}), got {list(cameras)}")
    return list(cameras)


def _episode_table(root: Path) -> dict[int, dict]:
    """v3.0 ``meta/episodes`` rows by episode index."""
    rows = {}
    for f in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        names = pq.read_schema(f).names
        table = _read_parquet(f, "LeRobot episodes", [c for c in names if not c.startswith("stats/")])
        rows.update({int(r["episode_index"]): r for r in table.to_pylist()})
    return rows


def _video_frames(root: Path, info: dict, version: str, key: str, episode: np.ndarray, timestamps: np.ndarray,
                  size: tuple[int, int] | None) -> np.ndarray:
    """Frames ``[N, H, W, 3]`` of video feature ``key`` for rows (``episode [N]``, ``timestamps [N]``),
    each video file decoded once."""
    template, fps = info.get("video_path"), float(info.get("fps") or 0)
    if not template or fps <= 0:
        raise ValueError(f"{root / 'meta' / 'info.json'}: feature {key!r} is a video; expected \"video_path\" "
                         f"and \"fps\", got {template!r} and {info.get('fps')!r}")
    episodes = _episode_table(root) if version in V3 else {}
    sources: dict[Path, list[tuple[int, float]]] = {}          # video file -> [(episode, start s)]
    for e in np.unique(episode).tolist():
        if version in V3:
            row = episodes.get(e, {})
            columns = [f"videos/{key}/{c}" for c in ("chunk_index", "file_index", "from_timestamp")]
            if any(row.get(c) is None for c in columns):
                raise ValueError(f"{root / 'meta' / 'episodes'}: episode {e} expected columns {columns}, got none "
                                 f"for camera {key!r}")
            chunk, file, start = (row[c] for c in columns)
            path = root / template.format(video_key=key, chunk_index=chunk, file_index=file)
        else:
            chunk, start = e // int(info.get("chunks_size") or 1000), 0.0
            path = root / template.format(video_key=key, episode_chunk=chunk, episode_index=e)
        sources.setdefault(path, []).append((e, float(start)))
    out = None
    for path, parts in sources.items():
        rows = np.concatenate([np.flatnonzero(episode == e) for e, _ in parts])
        shifted = np.concatenate([timestamps[episode == e] + start for e, start in parts])
        frames = read_frames(path, shifted, fps, size)                     # [n, H, W, 3]
        if out is None:
            out = np.empty((len(episode), *frames.shape[1:]), np.uint8)
        if frames.shape[1:] != out.shape[1:]:
            raise ValueError(f"{path}: expected frames of {list(out.shape[1:])} as in the camera's other files, got "
                             f"{list(frames.shape[1:])}; pass image_size to resize them to one size")
        out[rows] = frames
    return out


def _image_column(table: pa.Table, key: str, path: Path, size: tuple[int, int] | None, root: Path) -> np.ndarray:
    """``[rows, H, W, 3]`` from a ``dtype: image`` column (PNG bytes per row)."""
    frames = [decode_png(cell, f"{path}: column {key!r} row {i}", size, root)
              for i, cell in enumerate(table[key].to_pylist())]
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        raise ValueError(f"{path}: column {key!r} expected images of one size, got {sorted(shapes)}; pass "
                         f"image_size to resize them")
    return np.stack(frames)


def load_dataset(root: str | Path, cameras: list[str] | None = None,
                 image_size: int | tuple[int, int] | None = None) -> EpisodeDataset:
    """Load a LeRobot dataset (format v3.0, v2.1 or v2.0; see the module docstring): frames, episode
    boundaries, fps and task strings, validating columns, frame order and finiteness.

    ``cameras``: the camera features to load (their keys, e.g. ``observation.images.top``); None
    loads all of them, ``[]`` none. Their frames are decoded once, here, to uint8 ``[N, H, W, 3]``
    per camera (N·H·W·3 bytes each: 12 kB a frame at 64×64), resized to ``image_size`` (``(H, W)``
    or an int for a square; None keeps the native size, which must then agree across cameras).

    The same recording in v3.0 and in v2.1 loads identically. ``task_index`` defaults to 0 when
    the column is absent. Normalisation statistics are computed from the frames (mean, std floored,
    min, max), never read from ``meta/stats.json`` or ``episodes_stats.jsonl``: exact, the same for
    every layout, and what a subset of episodes recomputes too (LeRobot aggregates its per-episode
    statistics to the same mean and std).
    """
    root = Path(root).expanduser()
    check_dataset_dir(root)
    info = read_info(root)
    version = info.get("codebase_version", "v2.0")
    if version not in V2 + V3:
        raise ValueError(f"{root / 'meta' / 'info.json'}: codebase_version expected one of {list(V2 + V3)}, "
                         f"got {version!r}")
    keys, size = select_cameras(info, cameras, root), image_hw(image_size)
    image_keys = tuple(k for k in keys if info["features"][k]["dtype"] == "image")
    files = sorted((root / "data").rglob("*.parquet"))
    if not files:
        raise ValueError(f"load_dataset: expected parquet files under {root / 'data'}, found none")
    tables, times, pictures = [], [], {k: [] for k in image_keys}
    for path in files:
        table = _read_frames(path, image_keys)
        if table.num_rows == 0:
            raise ValueError(f"{path}: expected an episode with at least one frame, got an empty file (0 rows); "
                             f"delete it or record the episode again")
        states, actions = _matrix(table, STATE, path), _matrix(table, ACTION, path)
        task = _task_index(table, path)
        more = _matrix(table, CONTINUATION, path) if CONTINUATION in table.column_names else None
        committed = _prefix_lengths(table, path, more is not None)
        times.append(table["timestamp"].to_numpy().astype(np.float64) if "timestamp" in table.column_names else
                     table["frame_index"].to_numpy() / float(info.get("fps") or 1))
        for key in image_keys:
            if key not in table.column_names:
                raise ValueError(f"{path}: expected column {key!r} (a camera feature of info.json), got "
                                 f"{table.column_names}")
            pictures[key].append(_image_column(table, key, path, size, root))
        tables.append((states, actions, table["episode_index"].to_numpy(), table["frame_index"].to_numpy(), task,
                       more, committed))
    widths = sorted({(s.shape[1], a.shape[1], None if c is None else c.shape[1], p is None)
                     for s, a, *_, c, p in tables}, key=str)   # None (no continuation) does not compare with ints
    if len(widths) > 1:
        raise ValueError(f"{root}: expected the same (state, action, {CONTINUATION}) widths and {PREFIX_LENGTH} "
                         f"present in every file or none, got {widths} (widths, {PREFIX_LENGTH} absent)")
    states, actions, episode, frame, task = (np.concatenate(parts) for parts in list(zip(*tables))[:5])
    continuations = None if tables[0][5] is None else np.concatenate([t[5] for t in tables])
    prefix_lengths = None if tables[0][6] is None else np.concatenate([t[6] for t in tables])

    order = np.lexsort((frame, episode))
    states, actions, episode, frame, task = states[order], actions[order], episode[order], frame[order], task[order]
    if continuations is not None:
        if continuations.shape[1] % actions.shape[1]:
            raise ValueError(f"{root}: column {CONTINUATION!r} expected K × {actions.shape[1]} values per frame "
                             f"(K actions), got {continuations.shape[1]}")
        declared = ((info.get("features") or {}).get(CONTINUATION) or {}).get("shape")
        width = continuations.shape[1]
        if declared is not None and list(declared) != [width // actions.shape[1], actions.shape[1]]:
            raise ValueError(f"{root / 'meta' / 'info.json'}: feature {CONTINUATION!r} expected shape "
                             f"[{width // actions.shape[1]}, {actions.shape[1]}] ({width} values per frame, "
                             f"action width {actions.shape[1]}), got {declared}")
        continuations = continuations[order].reshape(len(actions), -1, actions.shape[1])  # [N, K, D]
        if prefix_lengths is not None:
            prefix_lengths = prefix_lengths[order]
            if not ((0 <= prefix_lengths) & (prefix_lengths < continuations.shape[1])).all():
                row = int(np.argmax((prefix_lengths < 0) | (prefix_lengths >= continuations.shape[1])))
                raise ValueError(f"{root}: column {PREFIX_LENGTH!r} expected 0..{continuations.shape[1] - 1} (rows of "
                                 f"{CONTINUATION}), got {prefix_lengths[row]} in episode {episode[row]} (frame "
                                 f"{frame[row]})")
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
    timestamps = np.concatenate(times)[order]
    for key in image_keys:
        if len({p.shape[1:] for p in pictures[key]}) > 1:
            raise ValueError(f"{root}: column {key!r} expected images of one size in every file, got "
                             f"{sorted({p.shape[1:] for p in pictures[key]})}; pass image_size to resize them")
    images = {k: np.concatenate(pictures[k])[order] if k in image_keys else
              _video_frames(root, info, version, k, episode, timestamps, size) for k in keys}
    return EpisodeDataset(states, actions, task, lengths, tasks, info.get("fps"), ids, root, {}, continuations,
                          images or None, prefix_lengths)
