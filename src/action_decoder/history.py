"""`ObservationHistory`: the last n observations of each of B environments, stacked for a policy
that conditions on `n_obs_steps` of them.

At an episode's start there are fewer than n: the first observation stands in for the missing
ones and `observation_is_pad` marks them, as LeRobot's datasets (their `*_is_pad` masks at
negative delta indices) and its policies' observation queues do. Works on torch tensors and on
numpy arrays alike (what is pushed is what comes back).
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import numpy as np
import torch

PAD_KEY = "observation_is_pad"


def _stack(frames: list, dim: int):
    return torch.stack(frames, dim) if isinstance(frames[0], torch.Tensor) else np.stack(frames, dim)


def _copy(x):
    return x.clone() if isinstance(x, torch.Tensor) else np.array(x, copy=True)


class ObservationHistory:
    """push({key: [B, ...]}) → {key: [B, n, ...] (oldest first), "observation_is_pad": [B, n] bool}.

    Each key keeps its own last n pushes, so keys may be pushed at different times (camera frames
    only when they are rendered, e.g.). `reset()` forgets every row (a new episode everywhere),
    `reset(rows)` only those rows (one env of several starting its next episode): the next push
    fills their history with that observation. A push whose batch size differs from the last
    one's starts every row afresh. n = 1 returns each observation with a step axis of 1."""

    def __init__(self, n_obs_steps: int):
        if isinstance(n_obs_steps, bool) or not isinstance(n_obs_steps, (int, np.integer)) or n_obs_steps < 1:
            raise ValueError(f"n_obs_steps: expected a positive integer number of observations, got {n_obs_steps!r}")
        self.n = int(n_obs_steps)
        """The number of observations kept per row."""
        self._frames: dict[str, list] = {}      # key -> the last n pushes, each [B, ...]
        self._seen: dict[str, np.ndarray] = {}  # key -> [B] observations pushed since each row's reset (≤ n)
        self._batch: Optional[int] = None

    def reset(self, rows: Optional[Sequence[int]] = None) -> None:
        """Forget the history of every row (None) or of the rows at the given positions."""
        if rows is None:
            self._frames, self._seen, self._batch = {}, {}, None
            return
        for seen in self._seen.values():
            seen[np.asarray(rows, dtype=np.int64)] = 0

    def push(self, observation: Mapping[str, Any]) -> dict:
        """Append one observation per row; returns the stacked history of the keys pushed now."""
        sizes = {k: len(x) for k, x in observation.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(f"observation: expected one batch size for every key, got {sizes}")
        b = next(iter(sizes.values()))
        if b != self._batch:
            self.reset()
            self._batch = b
        out = {}
        for key, x in observation.items():
            x = _copy(x)                # the caller may reuse its buffer for the next observation
            seen = self._seen.setdefault(key, np.zeros(b, dtype=np.int64))
            frames = self._frames.get(key)
            if frames is None or not seen.any():
                frames = [x] * self.n
            else:
                frames = frames[1:] + [x]
                fresh = np.flatnonzero(seen == 0)
                if len(fresh):          # rows starting an episode: their first observation stands in for all
                    index = torch.as_tensor(fresh) if isinstance(x, torch.Tensor) else fresh
                    frames = [_copy(f) for f in frames]
                    for f in frames[:-1]:
                        f[index] = x[index]
            self._frames[key] = frames
            np.minimum(seen + 1, self.n, out=seen)
            out[key] = _stack(frames, 1)                                        # [B, n, ...]
        seen = next(iter(self._seen[k] for k in observation))
        pad = np.arange(self.n)[None, :] < (self.n - seen)[:, None]          # [B, n] True: a stand-in
        first = next(iter(observation.values()))
        out[PAD_KEY] = torch.from_numpy(pad).to(first.device) if isinstance(first, torch.Tensor) else pad
        return out
