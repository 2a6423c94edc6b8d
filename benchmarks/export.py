"""Inference at the hardware's limit: eager PyTorch, torch.compile and onnxruntime per chunk.

    python -m benchmarks export                    # the page docs/benchmarks/export.md and export.json
    python -m benchmarks export --tiny --no-compile --out outputs/export-smoke   # smoke test

For each decoder and K (MeanFlow K = 1 and 2, flow matching K = 1 and 10, DDPM K = 10) and each batch
size (1 and 32) on the default Action Expert (hidden 128, 4 layers, chunk 16 × 4, 39-d state), it
times one chunk (`predict_action_chunk` for a given noise) four ways: eager PyTorch (one torch thread),
the torch.compile'd sampler (`compiled.compile_sampler`), and the exported graph in onnxruntime with 1
and with 2 intra-op threads (`runtime.OnnxPolicy`). The four run back to back in each round, their
order alternated and the cases rotated (`timing.rounds`), each timer repeating its call for at least
~20 ms; ratios to eager are medians of per-round ratios. The arithmetic limit is K × the FLOPs of one network call (`torch.utils.flop_counter`) ÷ the
rate this core reaches on the network's largest matmul ([B·N, hidden] @ [hidden, intermediate]),
itself the median over the rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from datetime import date
from pathlib import Path
from typing import Optional

CASES = (("mean_flow", 1), ("mean_flow", 2), ("flow_matching", 1), ("flow_matching", 10), ("DDPM", 10))
BATCHES = (1, 32)
PATHS = ("eager", "compiled", "ort1", "ort2")
BEGIN, END = "<!-- BEGIN GENERATED (python -m benchmarks export) -->", "<!-- END GENERATED -->"


def network_flops(policy, batch: int) -> int:
    """FLOPs of one network call (the Action Expert's forward) for `batch` rows."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    cfg = policy.config
    x = torch.zeros(batch, cfg.action_chunk_size, cfg.action_dim)
    t = torch.zeros(batch)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        policy.model(x, t, t, torch.zeros(batch, cfg.state_input_dim))
    return int(counter.get_total_flops())


def matmul_timer(policy, batch: int):
    """A timer of the network's largest matmul at this batch, and its FLOPs."""
    import torch

    from action_decoder.expert.action_expert import default_intermediate_size

    cfg = policy.config
    rows = batch * (4 + cfg.action_chunk_size)
    inter = cfg.intermediate_size or default_intermediate_size(cfg.hidden_size)
    a, b = torch.randn(rows, cfg.hidden_size), torch.randn(cfg.hidden_size, inter)
    out = torch.empty(rows, inter)
    inner = max(1, int(2e5 // (rows * cfg.hidden_size * inter / 1e3)))

    def timer() -> float:
        start = time.perf_counter()
        for _ in range(inner):
            torch.mm(a, b, out=out)
        return (time.perf_counter() - start) / inner

    return timer, 2 * rows * cfg.hidden_size * inter


def _timer(fn, inner: int):
    def timer() -> float:
        start = time.perf_counter()
        for _ in range(inner):
            fn()
        return (time.perf_counter() - start) / inner
    return timer


def build_case(decoder: str, steps: int, batch: int, tiny: bool, compile_: bool, workdir: Path, log) -> dict:
    """The four callables of one (decoder, K, B) and what the limit needs."""
    import torch

    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from action_decoder.runtime import OnnxPolicy

    size = {"hidden_size": 32, "num_hidden_layers": 1} if tiny else {}
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type=decoder, num_inference_timesteps=steps, **size)).eval()
    cfg = policy.config
    state = torch.randn(batch, cfg.state_dim)
    noise = torch.randn(batch, cfg.action_chunk_size, cfg.action_dim)
    batch_dict = {"state": state}
    calls = {"eager": lambda: policy.predict_action_chunk(batch_dict, noise=noise)}
    timings = {}
    start = time.perf_counter()
    path = policy.export_onnx(workdir / f"{decoder}_k{steps}_b{batch}.onnx", batch_size=batch)
    timings["export_s"] = time.perf_counter() - start
    s_np, n_np = state.numpy(), noise.numpy()
    want = calls["eager"]()
    for threads in (1, 2):
        runner = OnnxPolicy(path, threads=threads)
        calls[f"ort{threads}"] = (lambda r: lambda: r.predict_action_chunk(s_np, n_np))(runner)
    err = {"ort": float(abs(torch.from_numpy(calls["ort1"]()) - want).max())}
    if compile_:
        from action_decoder.compiled import compile_sampler

        fn = compile_sampler(policy)
        start = time.perf_counter()
        got = fn(batch_dict, noise)
        timings["compile_s"] = time.perf_counter() - start
        err["compiled"] = float((got - want).abs().max())
        calls["compiled"] = lambda: fn(batch_dict, noise)
    log(f"  {decoder} K={steps} B={batch}: export {timings['export_s']:.1f} s"
        + (f", compile {timings['compile_s']:.1f} s" if compile_ else "") + f", max |diff| {err}")
    mm_timer, mm_flops = matmul_timer(policy, batch)
    return {"calls": calls, "flops_call": network_flops(policy, batch), "mm_timer": mm_timer, "mm_flops": mm_flops,
            "err": err, **timings}


def measure(cases: dict, reps: int, warmup: int, log) -> dict:
    """Median ms of every path and the paired ratios to eager."""
    import statistics

    from benchmarks.timing import Clock, rounds

    timers = {}
    for key, case in cases.items():
        paths = [p for p in PATHS if p in case["calls"]]
        case["paths"] = paths
        timers[key] = []
        for p in paths:                 # each timer runs its own call for >= ~20 ms: a preemption weighs alike
            call = case["calls"][p]
            est = min(_timer(call, 1)() for _ in range(3))
            timers[key].append(_timer(call, max(1, int(0.02 / max(est, 1e-5)))))
        timers[key].append(case["mm_timer"])
    log(f"  {reps} rounds (+{warmup} warm-up) of {len(cases)} cases")
    samples = rounds(Clock("cpu"), timers, reps, warmup)
    rows = []
    for key, case in cases.items():
        decoder, steps, batch = key
        got = samples[key]
        paths = case["paths"]
        ms = {p: 1e3 * statistics.median(s[i] for s in got) for i, p in enumerate(paths)}
        ratio = {p: statistics.median(s[i] / s[0] for s in got) for i, p in enumerate(paths) if i}
        peak = statistics.median(case["mm_flops"] / s[-1] for s in got)          # FLOP/s
        limit_ms = 1e3 * steps * case["flops_call"] / peak
        rows.append({"decoder": decoder, "steps": steps, "batch": batch, "ms": ms, "ratio_to_eager": ratio,
                     "limit_ms": limit_ms, "gflops_call": case["flops_call"] / 1e9, "peak_gflops": peak / 1e9,
                     "times_limit": {p: ms[p] / limit_ms for p in paths}, "max_abs_diff": case["err"],
                     "export_s": case["export_s"], "compile_s": case.get("compile_s")})
    return rows


LABEL = {"mean_flow": "MeanFlow", "flow_matching": "Flow matching", "DDPM": "DDPM (DPM-Solver++)"}


def table(rows: list) -> str:
    head = ("| decoder | K | B | eager ms | compiled ms | ORT 1 thr ms | ORT 2 thr ms | compiled ÷ eager | "
            "ORT 1 ÷ eager | ORT 2 ÷ eager | limit ms | eager ÷ limit | ORT 1 ÷ limit |")
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for r in rows:
        ms, q, x = r["ms"], r["ratio_to_eager"], r["times_limit"]
        f = lambda d, k, fmt: fmt.format(d[k]) if k in d else "—"      # noqa: E731
        lines.append(f"| {LABEL[r['decoder']]} | {r['steps']} | {r['batch']} | {ms['eager']:.2f} | "
                     f"{f(ms, 'compiled', '{:.2f}')} | {ms['ort1']:.2f} | {ms['ort2']:.2f} | "
                     f"{f(q, 'compiled', '{:.2f}×')} | {q['ort1']:.2f}× | {q['ort2']:.2f}× | {r['limit_ms']:.3f} | "
                     f"{x['eager']:.1f}× | {x['ort1']:.1f}× |")
    return "\n".join(lines)


def render(result: dict) -> str:
    m = result["machine"]
    rows = result["rows"]
    cost = []
    for r in rows:
        compile_s = "—" if r["compile_s"] is None else f"{r['compile_s']:.0f}"
        cost.append(f"| {LABEL[r['decoder']]} | {r['steps']} | {r['batch']} | {r['gflops_call'] * 1e3:.2f} | "
                    f"{r['peak_gflops']:.1f} | {r['export_s']:.1f} | {compile_s} | "
                    f"{max(r['max_abs_diff'].values()):.1e} |")
    cost = "\n".join(cost)
    return "\n".join([
        BEGIN,
        f"Measured {m['date']} on {m['machine']} (torch {m['torch']}, onnxruntime {m['onnxruntime']}, "
        f"{m['rounds']} rounds + {m['warmup']} warm-up), command `{m['command']}`.",
        "",
        "### Latency per chunk",
        "",
        table(rows),
        "",
        "### What the limit is made of, and the cost of getting there",
        "",
        "| decoder | K | B | MFLOP per network call | matmul rate GFLOP/s | export s | compile s | max abs diff to eager |",
        "|---|---|---|---|---|---|---|---|",
        cost,
        END,
    ])


def write_page(result: dict, page: Path) -> None:
    body = render(result)
    if page.is_file() and BEGIN in page.read_text():
        text = page.read_text()
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1] if END in rest else ""
        page.write_text(head + body + tail)
    else:
        page.write_text("# Inference at the hardware's limit\n\n" + body + "\n")


def main(argv: Optional[list] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks export", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=30, help="timed rounds (each runs every path of every case)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--cases", default=",".join(f"{d}:{k}" for d, k in CASES), help="decoder:K pairs")
    parser.add_argument("--batches", default=",".join(map(str, BATCHES)))
    parser.add_argument("--tiny", action="store_true", help="tiny network (smoke test)")
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile path")
    parser.add_argument("--out", default="docs/benchmarks", help="directory of export.md and export.json")
    parser.add_argument("--machine", default="2-core CPU VM, one torch thread, shared with other jobs")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    import onnxruntime
    import torch

    torch.set_num_threads(1)
    cases_arg = [(c.split(":")[0], int(c.split(":")[1])) for c in args.cases.split(",") if c]
    batches = [int(b) for b in args.batches.split(",") if b]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cases = {}
    with tempfile.TemporaryDirectory(prefix="bench_export_") as tmp:
        for decoder, steps in cases_arg:
            for batch in batches:
                cases[(decoder, steps, batch)] = build_case(decoder, steps, batch, args.tiny, not args.no_compile,
                                                            Path(tmp), print)
        rows = measure(cases, args.rounds, args.warmup, print)
    result = {"machine": {"date": date.today().isoformat(), "machine": args.machine, "torch": torch.__version__,
                          "onnxruntime": onnxruntime.__version__, "python": platform.python_version(),
                          "rounds": args.rounds, "warmup": args.warmup, "tiny": args.tiny,
                          "command": "OMP_NUM_THREADS=1 python -m benchmarks export " + " ".join(
                              sys.argv[1:] if argv is None else argv)},
              "rows": rows}
    (out / "export.json").write_text(json.dumps(result, indent=1))
    write_page(result, out / "export.md")
    print(table(rows), flush=True)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
