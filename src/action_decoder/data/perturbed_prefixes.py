"""Perturbed committed prefixes, labelled by the scripted expert: training data for training-time RTC.

Training-time real-time chunking feeds a chunk's first d actions to the network as a committed
prefix. In a deterministic expert's demonstrations that prefix is a function of the chunk's state,
so a network that ignores it fits them as well as one that reads it; in closed loop the prefix
comes from a plan made from an older observation, and such a network plans as if it had not been
executed.

Perturbed prefixes make the prefix carry information, without a policy to roll out (`relabel` rolls
one out). At every demonstration frame, ``copies`` times: a prefix length d is drawn uniformly from
1..``max_delay``; the prefix is the expert's own actions from a time shifted by an offset drawn
uniformly from −``shift``..``shift`` control steps (its recorded past actions before the frame, its
plan from the frame's state after it), plus Gaussian noise of std ``noise`` in the env's action
units, clipped to [−1, 1]; the label is that prefix executed from the frame's state, then the
expert's continuation from the state it reaches (`demos.expert_continuation`, simulated and
rewound). Each copy is stored as one more episode with the demonstration's states, the labels as
``action.continuation`` and d as ``action.prefix_length``, which training feeds in as the clean
prefix (`data.chunks`, `flows.rtc_trained`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class PerturbedPrefixes:
    """How many perturbed prefixes each demonstration frame gets, and how they are drawn (module doc); a bad
    value is refused in one line naming the option of `train` and `record` that sets it."""

    copies: int
    max_delay: int
    noise: float = 0.2
    shift: int = 2

    def __post_init__(self) -> None:
        for name, value, low in (("--perturbed-prefixes", self.copies, 1), ("--rtc-max-delay", self.max_delay, 1),
                                 ("--perturbed-prefix-shift", self.shift, 0)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float)) or not 0 <= self.noise <= 1:
            raise ValueError(f"--perturbed-prefix-noise: expected a standard deviation in [0, 1] (env action units; "
                             f"actions span [-1, 1]), got {self.noise!r}")

    def suffix(self) -> str:
        """The demonstration cache's name part: -pp<copies>d<max delay>n<noise>s<shift>."""
        return f"-pp{self.copies}d{self.max_delay}n{self.noise:g}s{self.shift}"

    def record(self) -> dict:
        """What info.json's source keeps of them."""
        return asdict(self)


def perturbed_labels(past: np.ndarray, plan: np.ndarray, spec: PerturbedPrefixes, rng: np.random.Generator,
                     continuation: Callable[[np.ndarray], np.ndarray]) -> list[tuple[np.ndarray, int]]:
    """``spec.copies`` labels for one frame: ``(label [K, D], d)`` each, ``label = continuation(prefix)``
    for a prefix ``[d, D]`` drawn as the module doc says from the expert's actions ``past [t, D]`` (before
    the frame) and ``plan [L, D]`` (its plan from the frame's state; row 0 is its action there). Offsets
    that run past either end take the nearest action there."""
    seq = np.concatenate([past.reshape(-1, plan.shape[1]), plan])                  # [t + L, D]; row t is now
    now, labels = len(past), []
    for _ in range(spec.copies):
        d = int(rng.integers(1, spec.max_delay + 1))
        rows = np.clip(now + int(rng.integers(-spec.shift, spec.shift + 1)) + np.arange(d), 0, len(seq) - 1)
        prefix = np.clip(seq[rows] + spec.noise * rng.standard_normal((d, plan.shape[1])), -1.0, 1.0)
        labels.append((continuation(prefix.astype(np.float32)), d))
    return labels
