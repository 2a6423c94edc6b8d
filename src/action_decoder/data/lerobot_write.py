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
``action.continuation``, ``action.prefix_length``) are declared in ``info.json`` like any other
feature, so LeRobot loads them too. ``action.continuation`` (``[K, D]`` per frame) is stored and
declared flat, shape ``[K·D]``: LeRobot casts a 2-d feature to an Arrow extension type that plain
list columns do not match, and a flat vector loads everywhere; our reader reshapes it by the
action width.

Statistics are exact over the frames they describe (``np.quantile``), with the raw std: LeRobot
adds its own epsilon when normalising, and this library's reader floors the std when loading.

Cameras (an episode's ``"images": {key: uint8 [L, H, W, 3]}``) become v3.0 video features: one
H.264 (yuv420p) file per camera, ``videos/{key}/chunk-000/file-000.mp4``, holding the episodes one
after another; each episode's ``videos/{key}/from_timestamp``/``to_timestamp`` (seconds) in
meta/episodes say where it lies. Their statistics are per channel, ``[3, 1, 1]``, of pixel values
in [0, 1], as LeRobot stores them (exact here, over every pixel of every frame).
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

from .episodes import ACTION, CONTINUATION, PREFIX_LENGTH, STATE
from .video import write_video

CODEBASE_VERSION = "v3.0"
CHUNK_SIZE = 1000                      # files per chunk folder
DATA_FILE_SIZE_IN_MB = 100             # a data file is closed once it holds this much (episodes never split)
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
VIDEO_COLUMNS = {"chunk_index": pa.int64(), "file_index": pa.int64(), "from_timestamp": pa.float64(),
                 "to_timestamp": pa.float64()}
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
SCALARS = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
           "task_index": "int64", "next.reward": "float32", "next.success": "bool", "next.done": "bool",
           PREFIX_LENGTH: "int64"}
OPTIONAL = ("next.reward", "next.success", CONTINUATION, PREFIX_LENGTH, "seed")     # per episode: all or none
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


def _image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's statistics of a camera, ``frames [N, H, W, 3]`` uint8: per channel ``[3, 1, 1]`` of
    values in [0, 1], ``count [1]`` frames. Exact, from each channel's 256-level histogram."""
    hist = np.stack([np.bincount(frames[..., c].reshape(-1), minlength=256) for c in range(3)])   # [3, 256]
    levels, total = np.arange(256) / 255.0, hist[0].sum()
    mean = hist @ levels / total
    std = np.sqrt(np.maximum(hist @ levels**2 / total - mean**2, 0.0))
    cum = np.cumsum(hist, axis=1)                                              # [3, 256]

    def quantile(q: float) -> np.ndarray:          # np.quantile's linear rule on the sorted pixel values
        pos = q * (total - 1)
        lo, hi = np.floor(pos), np.ceil(pos)
        at = lambda k: levels[[np.searchsorted(cum[c], k, side="right") for c in range(3)]]
        return at(lo) + (pos - lo) * (at(hi) - at(lo))

    shaped = lambda v: np.asarray(v, np.float64).reshape(3, 1, 1)
    return {"min": shaped(levels[(hist > 0).argmax(1)]), "max": shaped(levels[255 - (hist[:, ::-1] > 0).argmax(1)]),
            "mean": shaped(mean), "std": shaped(std), "count": np.array([len(frames)], np.int64),
            **{k: shaped(quantile(q)) for k, q in QUANTILES.items()}}


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
    if PREFIX_LENGTH in ep:
        columns[PREFIX_LENGTH] = np.asarray(ep[PREFIX_LENGTH], np.int64)                  # [L]
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
    state, action, more = next(iter(shapes))
    if len(shapes) > 1 or len(state or ()) != 1 or len(action or ()) != 1 or \
            (more is not None and (len(more) != 2 or more[-1] != action[0])):
        raise ValueError(f"write_episodes: expected {STATE} [L, S], {ACTION} [L, D] (and {CONTINUATION} [L, K, D]) "
                         f"with the same widths in every episode, got per-frame shapes {sorted(shapes, key=str)}")
    _check_images(episodes)
    if PREFIX_LENGTH in episodes[0]:
        _check_prefix_lengths(episodes, more)
    for e, ep in enumerate(episodes):
        keys = [k for k in (STATE, ACTION, *OPTIONAL[:-1]) if k in ep]
        length, task = len(ep[ACTION]), ep.get("task_index")
        if length < 1 or any(len(ep[k]) != length for k in keys):
            raise ValueError(f"write_episodes: episode {e} expected >= 1 frame and the same length for {keys}, "
                             f"got {[len(ep[k]) for k in keys]}")
        if not isinstance(task, (int, np.integer)) or not 0 <= task < len(tasks):
            raise ValueError(f"write_episodes: episode {e} task_index expected an int in 0..{len(tasks) - 1}, got {task!r}")


def _check_prefix_lengths(episodes: Sequence[dict], continuation: tuple | None) -> None:
    """``action.prefix_length``: with ``action.continuation [L, K, D]``, integers [L] in 0..K-1."""
    if continuation is None:
        raise ValueError(f"write_episodes: {PREFIX_LENGTH} counts rows of {CONTINUATION}; expected both, got no "
                         f"{CONTINUATION}")
    for e, ep in enumerate(episodes):
        given = np.asarray(ep[PREFIX_LENGTH])
        if not np.issubdtype(given.dtype, np.integer) or given.shape != (len(ep[ACTION]),) or \
                not ((0 <= given) & (given < continuation[0])).all():
            span = f" in {given.min()}..{given.max()}" if given.size and given.dtype.kind in "iuf" else ""
            raise ValueError(f"write_episodes: episode {e} {PREFIX_LENGTH} expected integers [{len(ep[ACTION])}] in "
                             f"0..{continuation[0] - 1} (rows of {CONTINUATION}), got {given.dtype} "
                             f"{list(given.shape)}{span}")


def _check_images(episodes: Sequence[dict]) -> None:
    """``images``: in every episode or none, the same camera keys, uint8 ``[L, H, W, 3]`` of one size."""
    if len({"images" in ep for ep in episodes}) > 1:
        raise ValueError("write_episodes: images expected in every episode or in none, got them in some")
    if "images" not in episodes[0]:
        return
    first = episodes[0]["images"]
    if not isinstance(first, dict) or not first or not all(isinstance(k, str) and k for k in first):
        raise ValueError(f"write_episodes: images expected {{camera key: uint8 [L, H, W, 3]}}, got "
                         f"{type(first).__name__} {list(first) if isinstance(first, dict) else ''}")
    sizes = {k: np.shape(v)[1:] for k, v in first.items()}
    for e, ep in enumerate(episodes):
        if not isinstance(ep["images"], dict) or list(ep["images"]) != list(first):
            raise ValueError(f"write_episodes: episode {e} images expected the cameras {list(first)}, got "
                             f"{list(ep['images']) if isinstance(ep['images'], dict) else type(ep['images']).__name__}")
        for key, frames in ep["images"].items():
            frames = np.asarray(frames)
            if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[3] != 3 or \
                    len(frames) != len(ep[ACTION]) or frames.shape[1:] != sizes[key]:
                raise ValueError(f"write_episodes: episode {e} images[{key!r}] expected uint8 [{len(ep[ACTION])}, H, W, 3] "
                                 f"(one frame per action, one size per camera: {list(sizes[key])}), got {frames.dtype} "
                                 f"{list(frames.shape)}")


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
    ``seed`` (kept as an episode column), optional ``action.continuation [L, K, D]`` (with optional
    ``action.prefix_length [L]``, the committed rows each continuation starts with) and optional
    ``images``: ``{camera key: uint8 [L, H, W, 3]}`` (e.g. ``observation.images.corner2``; even H
    and W), written as H.264 video features.
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
    cameras = {k: np.shape(v)[1:] for k, v in first.get("images", {}).items()}         # key -> (H, W, 3)
    videos = {k: {"dtype": "video", "shape": list(shape), "names": ["height", "width", "channels"]}
              for k, shape in cameras.items()}
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
                     **{f"videos/{k}/{c}": v for k in cameras for c, v in zip(
                         VIDEO_COLUMNS, (0, 0, start / fps, (start + len(ep[ACTION])) / fps))},
                     **{f"stats/{k}/{s}": v for k in features for s, v in _stats(columns[k]).items()},
                     **{f"stats/{k}/{s}": v for k in cameras for s, v in _image_stats(ep["images"][k]).items()},
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
                for width in reversed(values.shape[1:] if features[field.name]["shape"] != [1] else ()):
                    array = pa.FixedSizeListArray.from_arrays(array, width)
                arrays.append(array.cast(field.type))
            path = root / DATA_PATH.format(chunk_index=file_no // CHUNK_SIZE, file_index=file_no % CHUNK_SIZE)
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(pa.Table.from_arrays(arrays, schema=schema), path)
        for key in cameras:
            frames = np.concatenate([ep["images"][key] for ep in episodes])                 # [N, H, W, 3]
            path = root / VIDEO_PATH.format(video_key=key, chunk_index=0, file_index=0)
            videos[key]["info"] = write_video(path, frames, fps)
        _write_episode_rows(root, rows, features, videos)
        _write_tasks(root, list(tasks))
        stats = {k: _stats(np.concatenate(v)) for k, v in all_columns.items()}
        stats.update({k: _image_stats(np.concatenate([ep["images"][k] for ep in episodes])) for k in cameras})
        (root / "meta" / "stats.json").write_text(json.dumps(
            {k: {s: v.tolist() for s, v in st.items()} for k, st in stats.items()}, indent=4))
        info = {"codebase_version": CODEBASE_VERSION, "robot_type": None, "total_episodes": len(episodes),
                "total_frames": start, "total_tasks": len(tasks), "chunks_size": CHUNK_SIZE,
                "data_files_size_in_mb": data_file_size_in_mb, "video_files_size_in_mb": 200, "fps": fps,
                "splits": {"train": f"0:{len(episodes)}"}, "data_path": DATA_PATH,
                "video_path": VIDEO_PATH if cameras else None,
                "features": {STATE: features[STATE], ACTION: features[ACTION], **videos, **features},
                **(info_extra or {})}
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


def _write_episode_rows(root: Path, rows: list[dict], features: dict, videos: dict) -> None:
    """``meta/episodes/chunk-000/file-000.parquet`` with LeRobot's column types: ``tasks``
    list<string>, stats lists of float64 (min/max of int64 and bool features keep their type),
    camera stats ``[3, 1, 1]`` lists of lists of lists."""
    listed = lambda t: pa.list_(pa.field("element", t))
    types = {"episode_index": pa.int64(), "tasks": listed(pa.string()), "length": pa.int64(),
             "data/chunk_index": pa.int64(), "data/file_index": pa.int64(), "dataset_from_index": pa.int64(),
             "dataset_to_index": pa.int64(),
             **{f"videos/{k}/{c}": t for k in videos for c, t in VIDEO_COLUMNS.items()}}
    for k, ft in features.items():
        for s in ("min", "max", "mean", "std", "count", *QUANTILES):
            element = pa.int64() if s == "count" else (ARROW[ft["dtype"]] if s in ("min", "max") and ft["dtype"] != "float32"
                                                       else pa.float64())
            types[f"stats/{k}/{s}"] = pa.list_(pa.field("element", element))
            for _ in ft["shape"][1:] if s != "count" else ():                 # [K, D] stats: lists of lists
                types[f"stats/{k}/{s}"] = pa.list_(pa.field("element", types[f"stats/{k}/{s}"]))
    for k in videos:
        for s in ("min", "max", "mean", "std", "count", *QUANTILES):
            types[f"stats/{k}/{s}"] = listed(pa.int64()) if s == "count" else listed(listed(listed(pa.float64())))
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
