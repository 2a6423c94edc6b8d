"""Latency of a real-time-chunking chunk against a plain chunk, on one device, batch 1.

    python -m benchmarks rtc-latency --device cuda --out outputs/rtc_latency_gpu.json

A policy of the default Action Expert with `rtc_max_delay` = 4 (random weights: time does not depend
on them) samples one chunk for one state three ways per (decoder, K): plain (`predict_action_chunk`),
trained RTC (`rtc_mode="trained"`, the d = 4 committed actions fed in clean at every step,
`flows/rtc_trained.py`) and guided RTC (`rtc_mode="guided"`, `flows/rtc.py`). The three run back to
back in each round (`timing.rounds`, CUDA events on a GPU), each timer repeating its call for at least
~20 ms; ratios to plain are medians of per-round ratios.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Optional

SETTINGS = (("flow_matching", 10), ("mean_flow", 1))
MODES = ("plain", "trained", "guided")


def build(decoder: str, steps: int, delay: int, device: str, tiny: bool) -> dict:
    """The three callables of one (decoder, K): plain, trained RTC and guided RTC chunks, batch 1."""
    import torch

    from action_decoder import ActionDecoderPolicy, DecoderConfig

    size = {"hidden_size": 32, "num_hidden_layers": 1} if tiny else {}
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type=decoder, num_inference_timesteps=steps,
                                               rtc_max_delay=delay, **size)).to(device).eval()
    cfg = policy.config
    batch = {"state": torch.randn(1, cfg.state_dim, device=device)}                       # [1, S]
    noise = torch.randn(1, cfg.action_chunk_size, cfg.action_dim, device=device)          # [1, H, D]
    prev = torch.randn(1, cfg.action_chunk_size - cfg.n_action_steps, cfg.action_dim, device=device)  # [1, L, D]
    calls = {"plain": lambda: policy.predict_action_chunk(batch, noise=noise)}
    for mode in MODES[1:]:
        calls[mode] = (lambda m: lambda: policy.predict_action_chunk(batch, noise=noise, prev_chunk=prev,
                                                                     delay=delay, rtc_mode=m))(mode)
    got = calls["trained"]()                                                              # [1, H, D]
    if not torch.equal(got[:, :delay], prev[:, :delay]):
        raise AssertionError(f"{decoder} K={steps}: the trained RTC chunk does not keep its {delay} committed actions")
    return calls


def main(argv: Optional[list] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks rtc-latency", description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"], help="where the policy runs (default cpu)")
    parser.add_argument("--settings", default=",".join(f"{d}:{k}" for d, k in SETTINGS), help="decoder:K pairs")
    parser.add_argument("--delay", type=int, default=4, help="committed actions d, also the policy's rtc_max_delay")
    parser.add_argument("--rounds", type=int, default=20, help="timed rounds (each runs every mode of every setting)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed rounds first")
    parser.add_argument("--tiny", action="store_true", help="tiny network (smoke test)")
    parser.add_argument("--out", default=None, help="JSON file of the rows (default: print only)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    import torch

    from benchmarks.timing import Clock, rounds

    log = functools.partial(print, flush=True)
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error(f"--device: cuda needs a CUDA build of torch and a GPU; torch {torch.__version__} sees none")
    try:
        settings = [(s.split(":")[0], int(s.split(":")[1])) for s in args.settings.split(",") if s]
    except (IndexError, ValueError):
        parser.error(f"--settings: expected decoder:K pairs such as flow_matching:10, got {args.settings!r}")
    torch.set_num_threads(1)
    clock = Clock(args.device)
    timers = {}
    for decoder, steps in settings:
        calls = build(decoder, steps, args.delay, args.device, args.tiny)
        timers[(decoder, steps)] = []
        est = {}
        for mode in MODES:
            call = calls[mode]
            est[mode] = min(clock(call) for _ in range(3))
            inner = max(1, int(0.02 / max(est[mode], 1e-5)))
            timers[(decoder, steps)].append((lambda c, n: lambda: clock(c, n))(call, inner))
        log(f"  {decoder} K={steps}: built; one chunk ≈ " + ", ".join(f"{m} {1e3 * v:.2f} ms" for m, v in est.items()))
    samples = rounds(clock, timers, args.rounds, args.warmup)
    rows = []
    for (decoder, steps), got in samples.items():
        ms = {m: 1e3 * statistics.median(s[i] for s in got) for i, m in enumerate(MODES)}
        ratio = {m: statistics.median(s[i] / s[0] for s in got) for i, m in enumerate(MODES) if i}
        rows.append({"decoder": decoder, "steps": steps, "batch": 1, "delay": args.delay, "ms": ms,
                     "ratio_to_plain": ratio})
        log(f"{decoder} K={steps} B=1 d={args.delay}: plain {ms['plain']:.3f} ms, trained {ms['trained']:.3f} ms "
            f"({ratio['trained']:.2f}×), guided {ms['guided']:.3f} ms ({ratio['guided']:.2f}×)")
    device = torch.cuda.get_device_name() if args.device == "cuda" else f"{os.cpu_count()}-CPU host"
    result = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "device": args.device,
              "machine": f"{device}, one torch thread", "torch": torch.__version__,
              "python": platform.python_version(), "rounds": args.rounds, "warmup": args.warmup, "tiny": args.tiny,
              "command": "python -m benchmarks rtc-latency " + " ".join(sys.argv[1:] if argv is None else argv),
              "rows": rows}
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
