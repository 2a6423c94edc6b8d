"""Benchmark suite of action_decoder (issue 6): sampler overhead, training step, peers, quality, memory.

Run from the repository root:  ``python -m benchmarks [--quick] [--out docs/benchmarks]``.
Every figure is a ratio of two timings taken side by side in the same round (interleaved,
order rotated per round), median over rounds after warm-up, one torch thread on CPU; on a
GPU the timings come from CUDA events.
"""

from .suite import BenchConfig, run_suite  # noqa: F401
