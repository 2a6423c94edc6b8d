"""In-memory episodes of (state, action, task) frames: the one form every dataset takes.

Subsets and concatenations recompute the normalisation statistics, so a policy trained on
the first k demonstrations never sees statistics of the held-back ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from .stats import ACTION_CONSTANT_BELOW, compute_stats

STATE = "observation.state"   # LeRobot feature names
ACTION = "action"
CONTINUATION = "action.continuation"
CONSTANT_BELOW = {ACTION: ACTION_CONSTANT_BELOW}   # data/stats.py: why actions keep small stds
"""Optional per-frame ``[K, D]``: the demonstrator's own next K actions from this frame's state
(recorded with noise, the frames that follow do not show them; see ``demos.py``)."""
PREFIX_LENGTH = "action.prefix_length"
"""Optional per-frame int, with ``CONTINUATION``: how many of the continuation's first rows are a committed
prefix the policy executed (``relabel.py``); the rest continue from the state that prefix reaches. 0: the
whole continuation is the demonstrator's from this frame's state."""


@dataclass
class EpisodeDataset:
    """Frames ``states [N, S]``, ``actions [N, D]``, ``task_index [N]`` stored episode after
    episode; episode ``e`` spans ``episode_starts[e] : episode_starts[e] + episode_lengths[e]``.
    ``continuations [N, K, D]``, when present, are the chunk targets (``CONTINUATION``);
    ``prefix_lengths [N]`` (int64, with them, ``PREFIX_LENGTH``) count the committed rows each starts with.

    ``images``, when present: camera key (``observation.images.<name>``) -> uint8 ``[N, H, W, 3]``,
    one frame per dataset frame (the observation ``states[i]`` was recorded with), every camera at
    one size, decoded in memory: N·H·W·3 bytes per camera (12 kB a frame at 64×64). ``cameras``
    is their order."""

    states: np.ndarray
    actions: np.ndarray
    task_index: np.ndarray
    episode_lengths: np.ndarray
    tasks: list[str]
    fps: float | None
    episode_ids: np.ndarray | None = None
    root: Path | None = None
    stats: dict = field(default_factory=dict)
    continuations: np.ndarray | None = None
    images: dict[str, np.ndarray] | None = None
    prefix_lengths: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.states = np.ascontiguousarray(self.states, dtype=np.float32)
        self.actions = np.ascontiguousarray(self.actions, dtype=np.float32)
        if self.continuations is not None:
            self.continuations = np.ascontiguousarray(self.continuations, dtype=np.float32)
            if self.continuations.ndim != 3 or self.continuations.shape[0::2] != self.actions.shape:
                raise ValueError(f"EpisodeDataset.continuations: expected [frames, K, action dim] = "
                                 f"[{len(self.actions)}, K, {self.actions.shape[1]}], got {self.continuations.shape}")
        if self.prefix_lengths is not None:
            self._check_prefix_lengths()
        self.task_index = np.asarray(self.task_index, dtype=np.int64)
        self.episode_lengths = np.asarray(self.episode_lengths, dtype=np.int64)
        n = int(self.episode_lengths.sum())
        for name, arr, ndim in (("states", self.states, 2), ("actions", self.actions, 2), ("task_index", self.task_index, 1)):
            if arr.ndim != ndim or len(arr) != n:
                raise ValueError(
                    f"EpisodeDataset.{name}: expected {n} frames (sum of episode_lengths) with {ndim} dims, got shape {arr.shape}"
                )
        if (self.episode_lengths < 1).any():
            raise ValueError(
                f"EpisodeDataset.episode_lengths: expected every episode to have >= 1 frame, got {self.episode_lengths.tolist()}"
            )
        if n and not 0 <= self.task_index.min() <= self.task_index.max() < len(self.tasks):
            raise ValueError(
                f"EpisodeDataset.task_index: expected values in [0, {len(self.tasks)}) (one per task), "
                f"got [{self.task_index.min()}, {self.task_index.max()}]"
            )
        if self.images is not None:
            self.images = {k: np.ascontiguousarray(v) for k, v in self.images.items()} or None
        for key, frames in (self.images or {}).items():
            first = next(iter(self.images.values()))
            if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[0] != n or frames.shape[3] != 3 \
                    or frames.shape != first.shape:
                raise ValueError(f"EpisodeDataset.images[{key!r}]: expected uint8 [{n}, H, W, 3] (one RGB frame per "
                                 f"dataset frame, H and W the same for every camera), got {frames.dtype} "
                                 f"{list(frames.shape)} (first camera {list(first.shape)})")
        if self.episode_ids is None:
            self.episode_ids = np.arange(len(self.episode_lengths))
        if not self.stats:
            self.stats = compute_stats({STATE: self.states, ACTION: self.actions}, constant_below=CONSTANT_BELOW)

    def _check_prefix_lengths(self) -> None:
        given = np.asarray(self.prefix_lengths)
        k = None if self.continuations is None else self.continuations.shape[1]
        if k is None or given.shape != (len(self.actions),) or not np.issubdtype(given.dtype, np.integer) or \
                (len(given) and not 0 <= given.min() <= given.max() < k):
            span = f" in {given.min()}..{given.max()}" if given.size and given.dtype.kind in "iuf" else ""
            raise ValueError(f"EpisodeDataset.prefix_lengths: expected integers [{len(self.actions)}] in 0..K-1 beside "
                             f"continuations [frames, K, D] ({'none given' if k is None else f'K = {k}'}), got "
                             f"{given.dtype} {list(given.shape)}{span}")
        self.prefix_lengths = given.astype(np.int64)

    @property
    def cameras(self) -> list[str]:
        """The camera keys of ``images``, in order ([] without images)."""
        return list(self.images or {})

    @property
    def episode_starts(self) -> np.ndarray:
        return np.concatenate([[0], np.cumsum(self.episode_lengths)[:-1]]).astype(np.int64)

    @property
    def num_episodes(self) -> int:
        return len(self.episode_lengths)

    @property
    def num_frames(self) -> int:
        return len(self.states)

    def select(self, episodes: int | Sequence[int]) -> "EpisodeDataset":
        """The first ``episodes`` episodes (an int), or those at the given positions."""
        picks = np.arange(episodes) if isinstance(episodes, (int, np.integer)) else np.asarray(episodes, dtype=np.int64)
        if picks.ndim != 1 or len(picks) == 0 or picks.min() < 0 or picks.max() >= self.num_episodes:
            raise ValueError(
                f"episodes: expected a count in [1, {self.num_episodes}] or positions in [0, {self.num_episodes}), got {episodes!r}"
            )
        starts = self.episode_starts
        frames = np.concatenate([np.arange(starts[e], starts[e] + self.episode_lengths[e]) for e in picks])
        return EpisodeDataset(
            self.states[frames], self.actions[frames], self.task_index[frames], self.episode_lengths[picks],
            list(self.tasks), self.fps, self.episode_ids[picks], self.root,
            continuations=None if self.continuations is None else self.continuations[frames],
            images=None if self.images is None else {k: v[frames] for k, v in self.images.items()},
            prefix_lengths=None if self.prefix_lengths is None else self.prefix_lengths[frames],
        )


def concat_datasets(datasets: Sequence[EpisodeDataset]) -> EpisodeDataset:
    """One multi-task dataset: task lists are merged by name and ``task_index`` remapped."""
    if not datasets:
        raise ValueError("concat_datasets: expected at least one EpisodeDataset, got none")
    widths = {(d.states.shape[1], d.actions.shape[1]) for d in datasets}
    fps = {d.fps for d in datasets}
    if len(widths) > 1 or len(fps) > 1:
        raise ValueError(f"concat_datasets: expected equal (state dim, action dim) and fps, got {sorted(widths)} and {list(fps)}")
    kinds = {None if d.continuations is None else d.continuations.shape[1] for d in datasets}
    if len(kinds) > 1:
        raise ValueError(f"concat_datasets: expected every dataset with {CONTINUATION} of one length, or none, "
                         f"got lengths {sorted(map(str, kinds))}")
    cameras = {(tuple(d.cameras), None if d.images is None else next(iter(d.images.values())).shape[1:])
               for d in datasets}
    if len(cameras) > 1:
        raise ValueError(f"concat_datasets: expected the same cameras at one image size in every dataset, got "
                         f"{sorted(cameras, key=str)} (cameras, [H, W, 3])")
    tasks = list(dict.fromkeys(t for d in datasets for t in d.tasks))
    remapped = [np.asarray([tasks.index(t) for t in d.tasks], dtype=np.int64)[d.task_index] for d in datasets]
    return EpisodeDataset(
        np.concatenate([d.states for d in datasets]),
        np.concatenate([d.actions for d in datasets]),
        np.concatenate(remapped),
        np.concatenate([d.episode_lengths for d in datasets]),
        tasks,
        fps.pop(),
        continuations=None if kinds == {None} else np.concatenate([d.continuations for d in datasets]),
        images=None if datasets[0].images is None else {k: np.concatenate([d.images[k] for d in datasets])
                                                         for k in datasets[0].cameras},
        prefix_lengths=None if all(d.prefix_lengths is None for d in datasets) else np.concatenate(
            [np.zeros(d.num_frames, np.int64) if d.prefix_lengths is None else d.prefix_lengths for d in datasets]),
    )
