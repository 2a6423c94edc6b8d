"""Writing datasets in LeRobot's v3.0 layout (what LeRobot ≥ 0.4 loads with
``LeRobotDataset(repo_id, root=DIR)``):

    <root>/data/chunk-000/file-000.parquet              frames of many episodes per file
    <root>/meta/episodes/chunk-000/file-000.parquet     one row per episode: tasks, length, the
                                                        data file and global frame range, per-episode stats
    <root>/meta/tasks.parquet                           task strings (the pandas index) -> task_index
    <root>/meta/stats.json                              min/max/mean/std/count and q01…q99 per feature
    <root>/meta/info.json                               codebase_version "v3.0", fps, features, totals

The schema follows what LeRobot 0.4.4 itself writes (column types, list field names, the
``huggingface`` schema metadata of data files, the pandas index column of ``tasks.parquet``).
Columns beyond LeRobot's own (``next.reward``, ``next.success``, ``next.done``,
``action.continuation``) are declared in ``info.json`` like any other feature, so LeRobot loads
them too. ``action.continuation`` (``[K, D]`` per frame) is stored and declared flat, shape
``[K·D]``: LeRobot casts a 2-d feature to an Arrow extension type that plain list columns do not
match, and a flat vector loads everywhere; our reader reshapes it by the action width.

Statistics are exact over the frames they describe (``np.quantile``), with the raw std: LeRobot
adds its own epsilon when normalising, and this library's reader floors the std when loading.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .episodes import ACTION, CONTINUATION, STATE

CODEBASE_VERSION = "v3.0"
CHUNK_SIZE = 1000                      # files per chunk folder
DATA_FILE_SIZE_IN_MB = 100             # a data file is closed once it holds this much (episodes never split)
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
SCALARS = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
           "task_index": "int64", "next.reward": "float32", "next.success": "bool", "next.done": "bool"}
OPTIONAL = ("next.reward", "next.success", CONTINUATION, "seed")     # per episode: all or none
ARROW = {"float32": pa.float32(), "int64": pa.int64(), "bool": pa.bool_()}


def _array_type(shape: list[int]) -> pa.DataType:
    """Per-frame float32 array of ``shape`` as nested fixed-size lists: ``[w]`` is LeRobot's
    ``fixed_size_list<element: float>[w]``; ``[K, D]`` nests one more level."""
    out = pa.float32()
    for width in reversed(shape):
        out = pa.list_(pa.field("element", out), width)
    return out


def _hf_feature(ft: dict) -> dict:
    """The ``datasets`` feature JSON LeRobot writes into each data file's schema metadata."""
    value = {"dtype": ft["dtype"], "_type": "Value"}
    if len(ft["shape"]) == 2:
        return {"shape": ft["shape"], "dtype": ft["dtype"], "_type": "Array2D"}
    return value if ft["shape"] == [1] else {"feature": value, "length": ft["shape"][0], "_type": "List"}


def _stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-feature statistics of ``values [N, ...]`` over frames (scalars ``[N]`` give
    ``[1]``-shaped stats): min/max in the data's dtype, the rest float64, ``count [1]``."""
    values = values[:, None] if values.ndim == 1 else values
    as_float = values.astype(np.float64)
    out = {"min": values.min(0), "max": values.max(0), "mean": as_float.mean(0), "std": as_float.std(0),
           "count": np.array([len(values)], np.int64)}
    return {**out, **{k: np.quantile(as_float, q, axis=0) for k, q in QUANTILES.items()}}


def _episode_columns(ep: dict, e: int, start: int, fps: float) -> dict[str, np.ndarray]:
    """Frame columns of episode ``e`` whose first frame has global index ``start``; vectors [L, W]."""
    length = len(ep[ACTION])
    columns = {
        STATE: np.asarray(ep[STATE], np.float32), ACTION: np.asarray(ep[ACTION], np.float32),
        "timestamp": (np.arange(length) / fps).astype(np.float32), "frame_index": np.arange(length, dtype=np.int64),
        "episode_index": np.full(length, e, np.int64), "index": np.arange(start, start + length, dtype=np.int64),
        "task_index": np.full(length, int(ep["task_index"]), np.int64),
    }
    if "next.reward" in ep:
        columns["next.reward"] = np.asarray(ep["next.reward"], np.float32)
    if "next.success" in ep:
        columns["next.success"] = np.asarray(ep["next.success"], bool)
    if "next.reward" in ep or "next.success" in ep:
        columns["next.done"] = np.arange(length) == length - 1
    if CONTINUATION in ep:
        columns[CONTINUATION] = np.asarray(ep[CONTINUATION], np.float32)                  # [L, K, D]
    return columns


def _check(episodes: Sequence[dict], tasks: Sequence[str], fps: float) -> None:
    if not episodes:
        raise ValueError("write_episodes: expected at least one episode, got none")
    if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
        raise ValueError(f"write_episodes: fps expected a positive number, got {fps!r}")
    if not tasks or not all(isinstance(t, str) and t for t in tasks) or len(set(tasks)) != len(tasks):
        raise ValueError(f"write_episodes: tasks expected distinct non-empty strings, got {list(tasks)!r}")
    for key in OPTIONAL:
        if len({key in ep for ep in episodes}) > 1:
            raise ValueError(f"write_episodes: {key} expected in every episode or in none, got it in some")
    shapes = {tuple(np.shape(ep[k])[1:] if k in ep else None for k in (STATE, ACTION, CONTINUATION)) for ep in episodes}
    if len(shapes) > 1 or len(next(iter(shapes))[0] or ()) != 1 or len(next(iter(shapes))[1] or ()) != 1:
        raise ValueError(f"write_episodes: expected {STATE} [L, S], {ACTION} [L, D] (and {CONTINUATION} [L, K, D]) "
                         f"with the same widths in every episode, got per-frame shapes {sorted(shapes, key=str)}")
    for e, ep in enumerate(episodes):
        keys = [k for k in (STATE, ACTION, *OPTIONAL[:-1]) if k in ep]
        length, task = len(ep[ACTION]), ep.get("task_index")
        if length < 1 or any(len(ep[k]) != length for k in keys):
            raise ValueError(f"write_episodes: episode {e} expected >= 1 frame and the same length for {keys}, "
                             f"got {[len(ep[k]) for k in keys]}")
        if not isinstance(task, (int, np.integer)) or not 0 <= task < len(tasks):
            raise ValueError(f"write_episodes: episode {e} task_index expected an int in 0..{len(tasks) - 1}, got {task!r}")


def write_episodes(
    root: str | Path,
    episodes: Sequence[dict[str, np.ndarray]],
    tasks: Sequence[str],
    fps: float,
    info_extra: dict | None = None,
    names: dict[str, list[str]] | None = None,
    data_file_size_in_mb: float = DATA_FILE_SIZE_IN_MB,
    overwrite: bool = False,
) -> Path:
    """Write ``episodes`` as a LeRobot v3.0 dataset under ``root`` and return ``root``.

    Each episode is a dict with ``observation.state [L, S]``, ``action [L, D]``, ``task_index``
    (int into ``tasks``, the task strings), ``next.reward [L]``, ``next.success [L]``, optional
    ``seed`` (kept as an episode column) and optional ``action.continuation [L, K, D]``.
    Without ``next.reward``/``next.success`` those columns and ``next.done`` are left out.
    ``info_extra`` is merged into ``info.json`` (e.g. ``{"env": "metaworld", "robot_type": ...}``);
    ``names`` gives per-dimension names of vector features (e.g. ``{"action": ["dx", "dy", "grip"]}``).
    Episodes are packed into data files of about ``data_file_size_in_mb`` each. ``info.json`` is
    written last, so a dataset with it is complete.

    ``root`` must be new or empty, as for LeRobot's own ``create``: a dataset is never replaced by
    accident. With ``overwrite=True`` a directory holding a dataset (``meta/info.json``) is replaced
    as a whole (written beside it, then swapped in, so no stale file of the old one survives);
    any other non-empty directory is still refused.
    """
    root = Path(root)
    _check(episodes, list(tasks), fps)
    if overwrite and (root / "meta" / "info.json").is_file():
        tmp = Path(tempfile.mkdtemp(prefix=f".{root.name}.", dir=root.parent))
        write_episodes(tmp, episodes, tasks, fps, info_extra, names, data_file_size_in_mb)
        replace_dir(tmp, root)
        return root
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise ValueError(f"write_episodes: expected an empty or new directory, got {root} (not empty"
                         f"{'' if overwrite else '; overwrite=True replaces a dataset'})")
    fps = int(fps) if float(fps).is_integer() else float(fps)
    first = episodes[0]
    columns = _episode_columns(first, 0, 0, fps)
    features = {k: {"dtype": SCALARS.get(k, "float32"), "shape": list(v.shape[1:]) or [1], "names": None}
                for k, v in columns.items()}
    for key, value in (names or {}).items():
        if key not in features or features[key]["shape"] == [1] or len(value) != features[key]["shape"][0]:
            raise ValueError(f"write_episodes: names expected {{vector feature: one name per dimension}} for "
                             f"{[k for k, f in features.items() if f['shape'] != [1]]}, got {key!r}: {value!r}")
        features[key]["names"] = list(value)
    schema = pa.schema([pa.field(k, _array_type(ft["shape"]) if ft["shape"] != [1] else ARROW[ft["dtype"]])
                        for k, ft in features.items()],
                       metadata={"huggingface": json.dumps({"info": {"features": {k: _hf_feature(ft) for k, ft in
                                                                                    features.items()}}})})

    # Frames, packed into files; one metadata row per episode.
    rows, files, pending, pending_bytes, start = [], [], [], 0, 0
    all_columns: dict[str, list[np.ndarray]] = {k: [] for k in features}
    for e, ep in enumerate(episodes):
        columns = _episode_columns(ep, e, start, fps)
        for k, v in columns.items():
            all_columns[k].append(v)
        file_no = len(files)
        rows.append({"episode_index": e, "tasks": [tasks[int(ep["task_index"])]], "length": len(ep[ACTION]),
                     "data/chunk_index": file_no // CHUNK_SIZE, "data/file_index": file_no % CHUNK_SIZE,
                     "dataset_from_index": start, "dataset_to_index": start + len(ep[ACTION]),
                     **{f"stats/{k}/{s}": v for k in features for s, v in _stats(columns[k]).items()},
                     "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                     **({"seed": int(ep["seed"])} if "seed" in ep else {})})
        pending.append(columns)
        pending_bytes += sum(v.nbytes for v in columns.values())
        start += len(ep[ACTION])
        if pending_bytes >= data_file_size_in_mb * 2**20 or e == len(episodes) - 1:
            files.append(pending)
            pending, pending_bytes = [], 0
    try:
        for file_no, parts in enumerate(files):
            arrays = []
            for field in schema:
                values = np.concatenate([p[field.name] for p in parts])                # [N, ...]
                array = pa.array(values.reshape(-1), type=ARROW[features[field.name]["dtype"]])
                for width in reversed(values.shape[1:]):
                    array = pa.FixedSizeListArray.from_arrays(array, width)
                arrays.append(array.cast(field.type))
            path = root / DATA_PATH.format(chunk_index=file_no // CHUNK_SIZE, file_index=file_no % CHUNK_SIZE)
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(pa.Table.from_arrays(arrays, schema=schema), path)
        _write_episode_rows(root, rows, features)
        _write_tasks(root, list(tasks))
        stats = {k: _stats(np.concatenate(v)) for k, v in all_columns.items()}
        (root / "meta" / "stats.json").write_text(json.dumps(
            {k: {s: v.tolist() for s, v in st.items()} for k, st in stats.items()}, indent=4))
        info = {"codebase_version": CODEBASE_VERSION, "robot_type": None, "total_episodes": len(episodes),
                "total_frames": start, "total_tasks": len(tasks), "chunks_size": CHUNK_SIZE,
                "data_files_size_in_mb": data_file_size_in_mb, "video_files_size_in_mb": 200, "fps": fps,
                "splits": {"train": f"0:{len(episodes)}"}, "data_path": DATA_PATH, "video_path": None,
                "features": features, **(info_extra or {})}
        (root / "meta" / "info.json").write_text(json.dumps(info, indent=4))   # last: marks the dataset complete
    except BaseException:
        shutil.rmtree(root, ignore_errors=True)       # no half-written dataset left behind
        raise
    return root


def replace_dir(new: Path, final: Path) -> None:
    """Move the finished directory ``new`` to ``final``, replacing what is there. If another process
    puts its own ``final`` in place first, ``new`` is dropped."""
    old = None
    if final.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{final.name}.old.", dir=final.parent))
        try:
            os.rename(final, old / final.name)
        except OSError:
            pass
    try:
        os.rename(new, final)
    except OSError:
        shutil.rmtree(new)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _write_episode_rows(root: Path, rows: list[dict], features: dict) -> None:
    """``meta/episodes/chunk-000/file-000.parquet`` with LeRobot's column types: ``tasks``
    list<string>, stats lists of float64 (min/max of int64 and bool features keep their type)."""
    types = {"episode_index": pa.int64(), "tasks": pa.list_(pa.field("element", pa.string())), "length": pa.int64(),
             "data/chunk_index": pa.int64(), "data/file_index": pa.int64(), "dataset_from_index": pa.int64(),
             "dataset_to_index": pa.int64()}
    for k, ft in features.items():
        for s in ("min", "max", "mean", "std", "count", *QUANTILES):
            element = pa.int64() if s == "count" else (ARROW[ft["dtype"]] if s in ("min", "max") and ft["dtype"] != "float32"
                                                       else pa.float64())
            types[f"stats/{k}/{s}"] = pa.list_(pa.field("element", element))
            for _ in ft["shape"][1:] if s != "count" else ():                 # [K, D] stats: lists of lists
                types[f"stats/{k}/{s}"] = pa.list_(pa.field("element", types[f"stats/{k}/{s}"]))
    types.update({"meta/episodes/chunk_index": pa.int64(), "meta/episodes/file_index": pa.int64()})
    if "seed" in rows[0]:
        types["seed"] = pa.int64()
    columns = {k: pa.array([np.asarray(r[k]).tolist() for r in rows], type=t) for k, t in types.items()}
    path = root / EPISODES_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.table(columns), path)


def _write_tasks(root: Path, tasks: list[str]) -> None:
    """``meta/tasks.parquet`` as pandas writes LeRobot's DataFrame: ``task_index`` int64 with the
    task strings as the (unnamed) index, so ``pd.read_parquet(...).iloc[i].name`` is task ``i``."""
    pandas_meta = {
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "str",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [{"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
                     "metadata": None},
                    {"name": None, "field_name": "__index_level_0__", "pandas_type": "object", "numpy_type": "str",
                     "metadata": None}],
        "attributes": {}, "creator": {"library": "pyarrow", "version": pa.__version__}, "pandas_version": "3.1.1",
    }
    schema = pa.schema([pa.field("task_index", pa.int64()), pa.field("__index_level_0__", pa.large_string())],
                       metadata={"pandas": json.dumps(pandas_meta)})
    table = pa.table({"task_index": pa.array(range(len(tasks)), pa.int64()),
                      "__index_level_0__": pa.array(tasks, pa.large_string())}, schema=schema)
    pq.write_table(table, root / "meta" / "tasks.parquet")
