"""Training samples for chunking policies: one per frame, the state and the next H actions.

Near an episode's end the chunk is completed by repeating the last action and marked in
``action_is_pad`` (LeRobot's convention), so every frame is a training sample and the
loss can ignore, or keep, the padded part. A dataset that stores each frame's own
continuation (demonstrations recorded with noise) gives its first H actions instead, and one that
also counts the committed rows each continuation starts with (``action.prefix_length``, written by
``relabel``) gives that count as ``rtc_delay``: training-time RTC then feeds exactly those rows in as
the chunk's clean prefix.

With observation history (``n_obs_steps`` n > 1) each sample holds the frame's observation and the
n − 1 before it, as LeRobot's ``observation_delta_indices`` = range(1 − n, 1) gives them: before an
episode's first frame that frame is repeated, and ``observation_is_pad`` marks the repeats.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from .episodes import CONTINUATION, PREFIX_LENGTH, EpisodeDataset


class ChunkDataset(Dataset):
    """``{"state": [S], "actions": [H, D], "action_is_pad": [H] bool, "task_index": int}`` per frame,
    and ``"images"``: uint8 ``[N_cam, 3, H_img, W_img]`` (channel-first, cameras in the dataset's
    order) of the frame the chunk starts at, when the dataset has cameras. With ``n_obs_steps`` n > 1
    the observations gain a step axis, oldest first: ``"state": [n, S]``, ``"images": [n, N_cam, 3,
    H_img, W_img]``, and ``"observation_is_pad": [n] bool`` (True: the episode's first frame standing in
    for a frame before it). Datasets with ``prefix_lengths`` add ``"rtc_delay": int``, the committed rows
    the chunk starts with (0: none; training-time RTC draws the delay).

    ``episodes`` keeps the first k episodes (an int) or those at given positions, e.g. for
    demo-count experiments; for several tasks pass ``concat_datasets([...])``.
    """

    def __init__(self, dataset: EpisodeDataset, horizon: int, episodes: int | Sequence[int] | None = None,
                 n_obs_steps: int = 1):
        if not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon: expected an integer >= 1, got {horizon!r}")
        if isinstance(n_obs_steps, bool) or not isinstance(n_obs_steps, (int, np.integer)) or n_obs_steps < 1:
            raise ValueError(f"n_obs_steps: expected an integer >= 1 (observations per sample), got {n_obs_steps!r}")
        self.n_obs_steps = int(n_obs_steps)
        if episodes is not None:
            dataset = dataset.select(episodes)
        self.dataset, self.horizon = dataset, int(horizon)
        self.states = torch.from_numpy(dataset.states)
        self.actions = torch.from_numpy(dataset.actions)
        self.continuations = None
        if dataset.continuations is not None:
            if horizon > dataset.continuations.shape[1]:
                raise ValueError(f"horizon: expected at most the {dataset.continuations.shape[1]} actions the "
                                 f"dataset's {CONTINUATION} holds per frame, got {horizon}")
            self.continuations = torch.from_numpy(dataset.continuations[:, :horizon])   # [N, H, D]
        self.prefix_lengths = None
        if dataset.prefix_lengths is not None:
            if len(dataset.prefix_lengths) and dataset.prefix_lengths.max() >= horizon:
                raise ValueError(f"horizon: expected more than the {dataset.prefix_lengths.max()} committed rows the "
                                 f"dataset's {PREFIX_LENGTH} gives a frame (rows must remain to learn), got {horizon}")
            self.prefix_lengths = dataset.prefix_lengths.tolist()
        self.images = [torch.from_numpy(v) for v in (dataset.images or {}).values()]   # N_cam × [N, H, W, 3]
        self.task_index = dataset.task_index.tolist()
        ends = dataset.episode_starts + dataset.episode_lengths - 1
        self.last_frame = torch.from_numpy(np.repeat(ends, dataset.episode_lengths))
        self.first_frame = torch.from_numpy(np.repeat(dataset.episode_starts, dataset.episode_lengths))
        self.obs_offsets = torch.arange(1 - self.n_obs_steps, 1)                  # [n]: LeRobot's delta indices
        self.offsets = torch.arange(self.horizon)

    @property
    def stats(self) -> dict:
        return self.dataset.stats

    @property
    def tasks(self) -> list[str]:
        return self.dataset.tasks

    def __len__(self) -> int:
        return len(self.states)

    def __getitem__(self, i: int) -> dict:
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} frames")
        i = i % len(self)
        if self.continuations is not None:
            item = {"state": self.states[i], "actions": self.continuations[i],
                    "action_is_pad": torch.zeros(self.horizon, dtype=torch.bool), "task_index": self.task_index[i]}
            if self.prefix_lengths is not None:
                item["rtc_delay"] = self.prefix_lengths[i]
        else:
            wanted = i + self.offsets
            last = self.last_frame[i]
            item = {"state": self.states[i], "actions": self.actions[torch.clamp(wanted, max=last)],
                    "action_is_pad": wanted > last, "task_index": self.task_index[i]}
        if self.n_obs_steps > 1:
            wanted = i + self.obs_offsets                                         # [n]
            frames = torch.clamp(wanted, min=self.first_frame[i])
            item["state"], item["observation_is_pad"] = self.states[frames], wanted < self.first_frame[i]  # [n, S], [n]
            if self.images:
                item["images"] = torch.stack([cam[frames] for cam in self.images], 1).permute(0, 1, 4, 2, 3)
            return item                                                           # images [n, N_cam, 3, H, W]
        if self.images:
            item["images"] = torch.stack([frames[i] for frames in self.images]).permute(0, 3, 1, 2)  # [N_cam, 3, H, W]
        return item
