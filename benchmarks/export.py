"""Inference at the hardware's limit: eager PyTorch, torch.compile and onnxruntime per chunk.

    python -m benchmarks export                    # the page docs/benchmarks/export.md and export.json
    python -m benchmarks export --tiny --no-compile --out outputs/export-smoke   # smoke test
    python -m benchmarks export --device cuda --out outputs/export-gpu   # export_gpu.json, a GPU section of export.md

For each decoder and K (MeanFlow K = 1 and 2, flow matching K = 1 and 10, DDPM K = 10) and each batch
size (1 and 32) on the default Action Expert (hidden 128, 4 layers, chunk 16 × 4, 39-d state), it
times one chunk (`predict_action_chunk` for a given noise) four ways: eager PyTorch (one torch thread),
the torch.compile'd sampler (`compiled.compile_sampler`), and the exported graph in onnxruntime with 1
and with 2 intra-op threads (`runtime.OnnxPolicy`). The four run back to back in each round, their
order alternated and the cases rotated (`timing.rounds`), each timer repeating its call for at least
~20 ms; ratios to eager are medians of per-round ratios. The arithmetic limit is K × the FLOPs of one network call (`torch.utils.flop_counter`) ÷ the
rate this core reaches on the network's largest matmul ([B·N, hidden] @ [hidden, intermediate]),
itself the median over the rounds.

With `--device cuda` the policy runs on the GPU and each case is timed three ways: eager PyTorch,
`compile_sampler` with its CUDA default (mode "reduce-overhead": CUDA graphs, one replay per chunk) and
torch.compile's default mode (inductor kernels, launched one by one); onnxruntime is left out (the
CPU page has it). Timers are CUDA events (`timing.Clock`), and the matmul rate is that of the GPU's
kernels run back to back: a CUDA graph of repeated matmuls, so that no launch gap counts.
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
PATHS = ("eager", "compiled", "inductor", "ort1", "ort2")      # inductor: torch.compile's default mode (CUDA)
BEGIN, END = "<!-- BEGIN GENERATED (python -m benchmarks export) -->", "<!-- END GENERATED -->"
GPU_BEGIN = "<!-- BEGIN GENERATED (python -m benchmarks export --device cuda) -->"
GPU_END = "<!-- END GENERATED (GPU) -->"


def network_flops(policy, batch: int) -> int:
    """FLOPs of one network call (the Action Expert's forward) for `batch` rows."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    cfg = policy.config
    device = next(policy.parameters()).device
    x = torch.zeros(batch, cfg.action_chunk_size, cfg.action_dim, device=device)
    t = torch.zeros(batch, device=device)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        policy.model(x, t, t, torch.zeros(batch, cfg.state_input_dim, device=device))
    return int(counter.get_total_flops())


def matmul_timer(policy, batch: int, clock=None):
    """A timer (seconds per matmul) of the network's largest matmul at this batch, in the policy's
    dtype and on its device, and its FLOPs. On CUDA the matmuls replay as one CUDA graph."""
    import torch

    from action_decoder.expert.action_expert import default_intermediate_size
    from benchmarks.timing import Clock

    cfg = policy.config
    weight = next(policy.parameters())
    kw = {"device": weight.device, "dtype": weight.dtype}
    clock = clock or Clock(weight.device)
    rows = batch * (4 + cfg.action_chunk_size)
    inter = cfg.intermediate_size or default_intermediate_size(cfg.hidden_size)
    a, b = torch.randn(rows, cfg.hidden_size, **kw), torch.randn(cfg.hidden_size, inter, **kw)
    out = torch.empty(rows, inter, **kw)
    flops = 2 * rows * cfg.hidden_size * inter
    if clock.cuda:
        inner = 200
        graph = torch.cuda.CUDAGraph()
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream):              # warm-up (cuBLAS handles, workspaces) off the capture
            for _ in range(3):
                torch.mm(a, b, out=out)
        torch.cuda.current_stream().wait_stream(stream)
        with torch.cuda.graph(graph):
            for _ in range(inner):
                torch.mm(a, b, out=out)
        return (lambda: clock(graph.replay) / inner), flops
    inner = max(1, int(2e5 // (rows * cfg.hidden_size * inter / 1e3)))
    return _timer(lambda: torch.mm(a, b, out=out), inner, clock), flops


def _timer(fn, inner: int, clock=None):
    """A timer: seconds per call of `fn` over `inner` back-to-back calls (`timing.Clock`; CPU by default)."""
    from benchmarks.timing import Clock

    clock = clock or Clock("cpu")
    return lambda: clock(fn, inner)


def build_case(decoder: str, steps: int, batch: int, tiny: bool, compile_: bool, workdir: Path, log,
               device: str = "cpu") -> dict:
    """The callables of one (decoder, K, B) and what the limit needs. CPU: eager, compiled (inductor's
    default), onnxruntime with 1 and 2 threads. CUDA: eager, compiled (compile_sampler's CUDA default,
    CUDA graphs) and inductor (torch.compile's default mode)."""
    import torch

    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from benchmarks.timing import Clock

    cuda = torch.device(device).type == "cuda"
    size = {"hidden_size": 32, "num_hidden_layers": 1} if tiny else {}
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type=decoder, num_inference_timesteps=steps, **size))
    policy = policy.to(device).eval()
    cfg = policy.config
    state = torch.randn(batch, cfg.state_dim).to(device)                     # [B, S]
    noise = torch.randn(batch, cfg.action_chunk_size, cfg.action_dim).to(device)   # [B, H, D]
    batch_dict = {"state": state}
    calls = {"eager": lambda: policy.predict_action_chunk(batch_dict, noise=noise)}
    want = calls["eager"]()                                                  # [B, H, D]
    timings, err, failed = {}, {}, {}
    if not cuda:
        from action_decoder.runtime import OnnxPolicy

        start = time.perf_counter()
        path = policy.export_onnx(workdir / f"{decoder}_k{steps}_b{batch}.onnx", batch_size=batch)
        timings["export_s"] = time.perf_counter() - start
        s_np, n_np = state.numpy(), noise.numpy()
        for threads in (1, 2):
            runner = OnnxPolicy(path, threads=threads)
            calls[f"ort{threads}"] = (lambda r: lambda: r.predict_action_chunk(s_np, n_np))(runner)
        err["ort"] = float(abs(torch.from_numpy(calls["ort1"]()) - want).max())
    if compile_:
        from action_decoder.compiled import compile_sampler

        for name, mode in (("compiled", None), ("inductor", "default"))[:2 if cuda else 1]:
            start = time.perf_counter()
            try:
                fn = compile_sampler(policy, mode=mode)
                got = fn(batch_dict, noise)
                for _ in range(2):           # CUDA graphs record on the second call, replay from the third
                    got = fn(batch_dict, noise)
            except Exception as e:           # one path of one case: the others are still measured
                if not cuda:
                    raise
                failed[name] = f"{type(e).__name__}: {str(e).splitlines()[0][:160] if str(e) else ''}"
                log(f"  {decoder} K={steps} B={batch}: {name} failed ({failed[name]})")
                continue
            err[name] = float((got - want).abs().max())
            Clock(device).sync()
            timings[f"{name}_compile_s"] = time.perf_counter() - start
            calls[name] = (lambda f: lambda: f(batch_dict, noise))(fn)
        if "compiled_compile_s" in timings:
            timings["compile_s"] = timings.pop("compiled_compile_s")
    log(f"  {decoder} K={steps} B={batch}: "
        + ", ".join(f"{k[:-2].replace('_', ' ')} {v:.1f} s" for k, v in timings.items())
        + f", max |diff| {err}")
    mm_timer, mm_flops = matmul_timer(policy, batch, Clock(device))
    return {"calls": calls, "flops_call": network_flops(policy, batch), "mm_timer": mm_timer, "mm_flops": mm_flops,
            "err": err, **timings, **({"failed": failed} if failed else {})}


def measure(cases: dict, reps: int, warmup: int, log, device: str = "cpu") -> dict:
    """Median ms of every path and the paired ratios to eager."""
    import statistics

    from benchmarks.timing import Clock, rounds

    clock = Clock(device)
    timers = {}
    for key, case in cases.items():
        paths = [p for p in PATHS if p in case["calls"]]
        case["paths"] = paths
        timers[key] = []
        for p in paths:                 # each timer runs its own call for >= ~20 ms: a preemption weighs alike
            call = case["calls"][p]
            est = min(_timer(call, 1, clock)() for _ in range(3))
            timers[key].append(_timer(call, max(1, int(0.02 / max(est, 1e-5))), clock))
        timers[key].append(case["mm_timer"])
    log(f"  {reps} rounds (+{warmup} warm-up) of {len(cases)} cases")
    samples = rounds(clock, timers, reps, warmup)
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
                     "export_s": case.get("export_s"), "compile_s": case.get("compile_s"),
                     **{k: case[k] for k in ("inductor_compile_s", "failed") if k in case}})
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


def gpu_table(rows: list, runs: Optional[list] = None) -> str:
    """The GPU latency table; `runs` (one label per row) adds a first column naming each row's run."""
    head = ("| decoder | K | B | eager ms | CUDA graphs ms | inductor ms | CUDA graphs ÷ eager | inductor ÷ eager | "
            "limit ms | eager ÷ limit | CUDA graphs ÷ limit |")
    head = "| run " + head if runs else head
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for i, r in enumerate(rows):
        ms, q, x = r["ms"], r["ratio_to_eager"], r["times_limit"]
        f = lambda d, k, fmt: fmt.format(d[k]) if k in d else "—"      # noqa: E731
        lines.append(("| " + str(runs[i]) + " " if runs else "") +
                     f"| {LABEL[r['decoder']]} | {r['steps']} | {r['batch']} | {ms['eager']:.3f} | "
                     f"{f(ms, 'compiled', '{:.3f}')} | {f(ms, 'inductor', '{:.3f}')} | {f(q, 'compiled', '{:.2f}×')} | "
                     f"{f(q, 'inductor', '{:.2f}×')} | {r['limit_ms']:.4f} | {x['eager']:.0f}× | "
                     f"{f(x, 'compiled', '{:.1f}×')} |")
    return "\n".join(lines)


def gpu_runs(result: dict) -> list:
    """The runs of a GPU result: `{"runs": [...]}` (`--append`) or one run."""
    return result["runs"] if "runs" in result else [result]


def _case(r: dict) -> str:
    return f"{r['decoder']}:{r['steps']} B={r['batch']}"


def render_gpu(result: dict) -> str:
    runs = gpu_runs(result)
    several = len(runs) > 1
    rows = [r for run in runs for r in run["rows"]]
    labels = [i + 1 for i, run in enumerate(runs) for _ in run["rows"]] if several else None
    measured = []
    for i, run in enumerate(runs):
        m = run["machine"]
        measured.append(f"{f'- Run {i + 1}: m' if several else 'M'}easured {m['date']} on {m['machine']} (torch "
                        f"{m['torch']}, CUDA {m.get('cuda')}, Python {m['python']}, float32 weights, float32 matmul "
                        f"precision \"{m.get('float32_matmul_precision')}\", {m['rounds']} rounds + {m['warmup']} "
                        f"warm-up), command `{m['command']}`.")
    cost = []
    for i, r in enumerate(rows):
        c = lambda k: "—" if r.get(k) is None else f"{r[k]:.1f}"      # noqa: E731
        cost.append(("| " + str(labels[i]) + " " if several else "") +
                    f"| {LABEL[r['decoder']]} | {r['steps']} | {r['batch']} | {r['gflops_call'] * 1e3:.2f} | "
                    f"{r['peak_gflops']:.0f} | {c('compile_s')} | {c('inductor_compile_s')} | "
                    f"{max(r['max_abs_diff'].values(), default=float('nan')):.1e} |")
    built = {_case(r) for r in rows}
    skipped = list({s.split(" (")[0]: s for run in runs for s in run.get("skipped") or []      # the last run's reason
                    if s.split(" (")[0] not in built}.values())
    failed = [f"{LABEL[r['decoder']]} K={r['steps']} B={r['batch']} {p}: {why}"
              for r in rows for p, why in r.get("failed", {}).items()]
    cost_head = ("| decoder | K | B | MFLOP per network call | matmul rate GFLOP/s | compile s (CUDA graphs) | "
                 "compile s (inductor) | max abs diff to eager |")
    cost_head = "| run " + cost_head if several else cost_head
    return "\n".join([
        GPU_BEGIN,
        "## On a GPU",
        "",
        "\n".join(measured),
        "",
        "The same cases on the GPU, three ways: eager PyTorch; `compile_sampler` with its CUDA default, mode "
        "\"reduce-overhead\" (the chunk's kernels recorded once as a CUDA graph and replayed with one launch); "
        "and torch.compile's default mode (the same inductor kernels, launched one by one from Python). "
        "onnxruntime is not timed here (the CPU table above has it). Timers are CUDA events after a "
        "synchronize (`benchmarks/timing.Clock`), paired rounds and ratios as above"
        + ("; ratios compare paths within one run, and a case measured in two runs shows both" if several else "")
        + ". The **limit** is K × the "
        "FLOPs of one network call ÷ the rate the GPU reaches on the network's largest matmul at that batch "
        "(float32, as the policy runs: it has no dtype option), timed as 200 matmuls in one CUDA graph, so "
        "that launch gaps do not count: it is the limit of this GPU's kernels at the network's shapes (the "
        "matmul rate column), not of the chip's peak rate.",
        "",
        "### Latency per chunk (GPU)",
        "",
        gpu_table(rows, labels),
        "",
        "### What the limit is made of, and the cost of compiling (GPU)",
        "",
        cost_head,
        "|---" * (cost_head.count("|") - 1) + "|",
        "\n".join(cost),
        *(["", f"Not built: {'; '.join(skipped)}."] if skipped else []),
        *(["", f"Failed to compile (—): {'; '.join(failed)}."] if failed else []),
        GPU_END,
    ])


def write_page(result: dict, page: Path) -> None:
    """Replace this device's generated section of `page` (or append it; a new page gets a title)."""
    gpu = gpu_runs(result)[0]["machine"].get("device", "cpu") == "cuda"
    body, begin, end = (render_gpu(result), GPU_BEGIN, GPU_END) if gpu else (render(result), BEGIN, END)
    text = page.read_text() if page.is_file() else "# Inference at the hardware's limit\n"
    if begin in text:
        head, rest = text.split(begin, 1)
        tail = rest.split(end, 1)[1] if end in rest else ""
        page.write_text(head + body + tail)
    else:
        page.write_text(text.rstrip("\n") + "\n\n" + body + "\n")


def main(argv: Optional[list] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks export", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=30, help="timed rounds (each runs every path of every case)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--cases", default=",".join(f"{d}:{k}" for d, k in CASES), help="decoder:K pairs")
    parser.add_argument("--batches", default=",".join(map(str, BATCHES)))
    parser.add_argument("--tiny", action="store_true", help="tiny network (smoke test)")
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile path")
    parser.add_argument("--out", default="docs/benchmarks",
                        help="directory of export.md and export.json (export_gpu.json with --device cuda)")
    parser.add_argument("--machine", default=None,
                        help="machine named on the page (default: '2-core CPU VM, ...' on cpu, the GPU's name on cuda)")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                        help="cpu (eager, compiled, onnxruntime) or cuda (eager, CUDA graphs, inductor); default cpu")
    parser.add_argument("--append", action="store_true",
                        help="with --device cuda: add this run to --out's export_gpu.json and GPU section instead of "
                             "replacing them")
    parser.add_argument("--build-budget-s", type=float, default=None,
                        help="stop building further cases once building took this many seconds (default: no limit)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    import functools

    import torch

    log = functools.partial(print, flush=True)
    cuda = args.device == "cuda"
    if cuda and not torch.cuda.is_available():
        parser.error(f"--device: cuda needs a CUDA build of torch and a GPU; torch {torch.__version__} sees none")
    if args.append and not cuda:
        parser.error(f"--append: only with --device cuda (the CPU section holds one run), got --device {args.device}")
    torch.set_num_threads(1)
    try:
        cases_arg = [(c.split(":")[0], int(c.split(":")[1])) for c in args.cases.split(",") if c]
        batches = [int(b) for b in args.batches.split(",") if b]
    except (IndexError, ValueError):
        parser.error(f"--cases/--batches: expected decoder:K pairs and integers, got {args.cases!r} / {args.batches!r}")
    if not args.no_compile:              # one compiled ChunkSampler.forward per case and mode
        import torch._dynamo

        for name in ("recompile_limit", "cache_size_limit"):
            if hasattr(torch._dynamo.config, name):
                setattr(torch._dynamo.config, name, max(getattr(torch._dynamo.config, name), 4 * len(cases_arg)
                                                        * len(batches) + 8))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cases, skipped = {}, []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_export_") as tmp:
        for decoder, steps in cases_arg:
            for batch in batches:
                if args.build_budget_s is not None and time.perf_counter() - start > args.build_budget_s:
                    skipped.append(f"{decoder}:{steps} B={batch} (past --build-budget-s {args.build_budget_s:g})")
                    log(f"  skipped {skipped[-1]}")
                    continue
                try:
                    cases[(decoder, steps, batch)] = build_case(decoder, steps, batch, args.tiny,
                                                                not args.no_compile, Path(tmp), log, args.device)
                except Exception as e:     # on a GPU one broken case (a missing diffusers) spares the others
                    if not cuda:
                        raise
                    skipped.append(f"{decoder}:{steps} B={batch} ({type(e).__name__}: {str(e)[:160]})")
                    log(f"  skipped {skipped[-1]}")
        log(f"  built {len(cases)} cases in {time.perf_counter() - start:.0f} s")
        rows = measure(cases, args.rounds, args.warmup, log, args.device)
    order = {(d, k): i for i, (d, k) in enumerate(CASES)}
    rows.sort(key=lambda r: (order.get((r["decoder"], r["steps"]), len(order)), r["steps"], r["batch"]))
    command = " ".join(sys.argv[1:] if argv is None else argv)
    machine = {"date": date.today().isoformat(), "torch": torch.__version__, "python": platform.python_version(),
               "rounds": args.rounds, "warmup": args.warmup, "tiny": args.tiny, "device": args.device}
    if cuda:
        machine.update(machine=args.machine or f"{torch.cuda.get_device_name()} ({os.cpu_count()}-CPU host, one torch "
                       "thread)", cuda=torch.version.cuda, float32_matmul_precision=torch.get_float32_matmul_precision(),
                       date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                       command="python -m benchmarks export " + command)
    else:
        import onnxruntime

        machine.update(machine=args.machine or "2-core CPU VM, one torch thread, shared with other jobs",
                       onnxruntime=onnxruntime.__version__, command="OMP_NUM_THREADS=1 python -m benchmarks export "
                       + command)
    result = {"machine": machine, "rows": rows, **({"skipped": skipped} if skipped else {})}
    path = out / ("export_gpu.json" if cuda else "export.json")
    if args.append and cuda and path.is_file():
        result = {"runs": [*gpu_runs(json.loads(path.read_text())), result]}
    path.write_text(json.dumps(result, indent=1))
    write_page(result, out / "export.md")
    log(gpu_table(rows) if cuda else table(rows))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
