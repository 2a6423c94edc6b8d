"""Timing and memory instruments: wall clock (CPU) or CUDA events, round-robin rounds, medians."""

from __future__ import annotations

import statistics
import time
from typing import Callable, Dict, List, Sequence

import torch
from torch.multiprocessing.reductions import StorageWeakRef
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten


class Clock:
    """Seconds per call of `fn` over `inner` back-to-back calls.

    CPU: `time.perf_counter`. CUDA: a synchronize first (work queued before is not counted), a pair
    of CUDA events on the current stream around the calls, then a wait on the end event. The events
    span the GPU's timeline from the first launch to the last kernel's end, so a launch-bound call
    (the GPU idle between kernels while Python issues the next) is timed with its launch gaps.
    """

    def __init__(self, device: torch.device) -> None:
        self.cuda = torch.device(device).type == "cuda"

    def __call__(self, fn: Callable[[], object], inner: int = 1) -> float:
        if self.cuda:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            torch.cuda.synchronize()
            start.record()
            for _ in range(inner):
                fn()
            end.record()
            end.synchronize()
            return start.elapsed_time(end) / 1e3 / inner
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        return (time.perf_counter() - t0) / inner

    def sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()


def median(xs: Sequence[float]) -> float:
    return float(statistics.median(xs)) if xs else float("nan")


def rounds(clock: Clock, pairs: Dict[str, Sequence[Callable[[], float]]], reps: int,
           warmup: int) -> Dict[str, List[List[float]]]:
    """Run every entry's timers once per round, entries in a rotated order each round.

    `pairs[name]` is a list of timers (each returns seconds); within an entry the timers run
    back to back, their order reversed every other round, so that a ratio of two timers of
    one entry compares measurements taken within milliseconds of each other.
    Returns name -> list over rounds of [seconds of timer 0, seconds of timer 1, ...].
    """
    names = list(pairs)
    out: Dict[str, List[List[float]]] = {n: [] for n in names}
    for r in range(warmup + reps):
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            timers = list(enumerate(pairs[name]))
            if r % 2:
                timers.reverse()
            sample = [0.0] * len(timers)
            for i, timer in timers:
                sample[i] = timer()
            if r >= warmup:
                out[name].append(sample)
    return out


class PeakTensorMemory(TorchDispatchMode):
    """Peak bytes of tensor storages allocated inside the `with` block and alive at once.

    Counted at op boundaries through the dispatcher (forward, backward, forward-mode AD and
    the optimizer all dispatch ops): each op output whose storage is new (not an input's
    storage) is added, and storages are dropped when freed. It is the CPU analogue of
    `torch.cuda.max_memory_allocated() − memory_allocated()` before the block, minus the
    allocator's rounding and the scratch space inside single kernels; it does not count
    memory that existed before the block (weights, optimizer state from earlier steps).
    """

    def __init__(self) -> None:
        super().__init__()
        self.live: dict = {}
        self.current = 0
        self.peak = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for key in [k for k, (ref, _) in self.live.items() if ref.expired()]:
            self.current -= self.live.pop(key)[1]
        inputs = {StorageWeakRef(a.untyped_storage()).cdata
                  for a in tree_flatten((args, kwargs))[0] if isinstance(a, torch.Tensor)}
        for o in tree_flatten(out)[0]:
            if isinstance(o, torch.Tensor) and o.device.type != "meta":
                storage = o.untyped_storage()
                ref = StorageWeakRef(storage)
                if ref.cdata in inputs or ref.cdata in self.live:
                    continue
                self.live[ref.cdata] = (ref, storage.nbytes())
                self.current += storage.nbytes()
        self.peak = max(self.peak, self.current)
        return out


def peak_step_memory(step: Callable[[], object], device: torch.device) -> tuple[float, str]:
    """(peak extra bytes of one call of `step`, what the number measures)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()
        base = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        step()
        torch.cuda.synchronize()
        return float(torch.cuda.max_memory_allocated() - base), "torch.cuda.max_memory_allocated − allocated before"
    mode = PeakTensorMemory()
    with mode:
        step()
    return float(mode.peak), "peak live tensor storage allocated during the step (dispatcher-level count)"
