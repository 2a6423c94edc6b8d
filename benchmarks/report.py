"""Markdown tables, results.json and the plot under docs/benchmarks/.

README.md is regenerated between the BEGIN/END GENERATED markers only; text outside them
(the hand-written reading of the results) is kept.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

BEGIN, END = "<!-- BEGIN GENERATED (python -m benchmarks) -->", "<!-- END GENERATED -->"
PLOT_NAME, JSON_NAME = "benchmarks.png", "results.json"

DEFAULT_HEAD = """# Benchmarks

Regenerate everything between the markers below (tables, `results.json`, `benchmarks.png`)
from the repository root with:

```bash
OMP_NUM_THREADS=1 python -m benchmarks            # default, < 30 min on one core
OMP_NUM_THREADS=1 python -m benchmarks --quick    # < 3 min, into outputs/benchmarks-quick/ unless --out
```

"""


def _f(x, fmt="{:.2f}", none="—"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return fmt.format(x)


def _status(value, target):
    if target is None or value is None:
        return ""
    return "✅" if value <= target else f"❌ (+{value - target:.2f})"


def _table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(out)


def render(results: dict, plot_name: str | None) -> str:
    m = results["machine"]
    c = results["config"]
    lines = ["## Machine", "",
             f"- CPU: {m['cpu']} ({m['logical_cpus']} logical CPUs, shared; load average at start "
             f"{', '.join(f'{x:.2f}' for x in m.get('load_average', ()))})",
             f"- torch {m['torch']}, diffusers {m['diffusers']}, Python {m['python']}; "
             f"**{m['threads']} torch thread(s)**; device `{m['device']}`"
             + (f" ({m['gpu']})" if "gpu" in m else "") + f"; timer: {m['timer']}",
             f"- date: {m['date']}; mode `{m['mode']}`: {c['reps']} timed rounds per sampler "
             f"({c['train_reps']} per training step) after {c['warmup']} warm-up rounds; "
             "every figure is a median over rounds, every ratio a median of per-round ratios "
             "whose two timings ran back to back (order alternated, entries rotated).", ""]
    if plot_name:
        lines += [f"![benchmarks]({plot_name})", ""]

    for sec in results.get("sampling", []):
        lines += [f"## 1. Sampler overhead — {sec['size']}, B={sec['batch']}", "",
                  "overhead = time of one K-step sampling call ÷ (K × time of one call of the bound "
                  "network callable, same inputs). 1.00 is the physical limit. *own ms*: the sampler "
                  "with a free network (`lambda x, t: x`) — its own cost per call, immune to the "
                  "network's timing noise; *1 + own/(K·call)*: the overhead that cost implies.", ""]
        rows = [[r["sampler"], _f(r["call_ms"], "{:.3f}"), _f(r["sample_ms"], "{:.3f}"),
                 f"**{_f(r['overhead'], '{:.3f}')}**", _f(r.get("own_ms"), "{:.3f}"),
                 _f(r.get("predicted"), "{:.3f}"), _f(r["target"], "≤ {:.2f}", ""),
                 _status(r["overhead"], r["target"])] for r in sec["rows"]]
        lines += [_table(["sampler", "net call ms", "sampling ms", "overhead", "own ms",
                          "1 + own/(K·call)", "target", ""], rows), ""]
        d = sec["ddpm_scheduler"]
        lines += [f"diffusers DPM-Solver scheduler alone (`set_timesteps` + K `step`s, no network): "
                  f"{d['scheduler_ms']:.3f} ms = {d['per_step_us']:.0f} µs per step = "
                  f"**{100 * d['share_of_sample']:.1f} %** of the `sample_ddpm` call.", ""]

    for sec in results.get("training", []):
        if not sec["rows"]:
            continue
        lines += [f"## 2. Training step — {sec['size']}, batch {sec['batch']}", "",
                  "`policy(batch).loss.backward()` + AdamW step (zero_grad included), same network "
                  "init and batch; ratio to the flow-matching step of the same round.", ""]
        rows = [[r["decoder"], _f(r["step_ms"], "{:.1f}"), f"**{_f(r['vs_fm'], '{:.2f}')}×**",
                 _f(r["target"], "≤ {:.2f}×", ""), _status(r["vs_fm"], r["target"])] for r in sec["rows"]]
        lines += [_table(["decoder", "step ms", "÷ FM step", "target", ""], rows), ""]

    for sec in results.get("peers", []):
        lines += [f"## 3. Peers — {sec['size']}, B={sec['batch']}", "",
                  "Same network, same noise. ours ÷ peer < 1 means ours is faster.", ""]
        rows = [[r["sampler"], r["peer"], _f(r["ours_ms"], "{:.3f}"), _f(r["peer_ms"], "{:.3f}"),
                 f"**{_f(r['ours_over_peer'], '{:.3f}')}**", f"{r['max_abs_diff']:.1e}",
                 "✅" if r["agree"] else "❌"] for r in sec["rows"]]
        lines += [_table(["sampler", "peer", "ours ms", "peer ms", "ours ÷ peer", "max abs diff",
                          "same (≤ 1e-4)"], rows), ""]
    if results.get("peers"):
        lines += ["LeRobot was not benchmarked: `pip install lerobot` pulls its own pinned torch and a "
                  "large dependency tree (datasets, gymnasium, …) into the shared environment; its "
                  "flow-matching Euler helper is the same `x += dt·v` loop as the diffusers one above.", ""]

    q = results.get("quality")
    if q is not None:
        lines += ["## 4. Quality vs latency (10-demonstration Meta-World benchmark)", ""]
        if any(r["n"] for r in q["rows"]):
            lines += [(f"Read from eval JSON files under `{q['dir']}`; latency is the median per-chunk "
                       "time at B = 1 of the checkpoint named in the JSON (or its `latency_ms`)."), ""]
            rows = [[r["decoder"], r["sampler"], r["steps"], r.get("n_action_steps") or "–",
                     _f(r["success_rate"], "{:.1%}", "not measured"),
                     _f(r["latency_ms"], "{:.2f}", "not measured"), r["n"] or ""] for r in q["rows"]]
            lines += [_table(["decoder", "sampler", "K", "actions per chunk", "success rate", "latency ms / chunk",
                              "task results"], rows), ""]
        else:
            lines += [("Not part of this run"
                       + (f" (no eval summaries under `{q['dir']}`)" if q["dir"] else "")
                       + ": success per decoder and K over 17 tasks × 3 seeds is in "
                       "the Meta-World grid (`docs/benchmarks/metaworld_bc.md`), and a chunk's latency is K × the network "
                       "call of section 1. `--quality-dir DIR` puts both in one table, from the summaries "
                       "(`eval_*.json`) that `action-decoder eval` writes (any depth; keys `decoder_type`, "
                       "`sampler`, `steps`, `success_rate`, `checkpoint`, optional `latency_ms`)."), ""]

    mem = [s for s in results.get("training", []) if "memory" in s]
    if mem:
        lines += ["## 5. Memory of one training step", "",
                  f"Measured: {mem[0]['memory']['what']}"
                  + ("" if results["machine"]["device"].startswith("cuda")
                     else " — the CPU analogue of `torch.cuda.max_memory_allocated()`")
                  + "; weights and optimizer state that exist "
                  "before the step are not counted, gradients created by it are.", ""]
        names = list(mem[0]["memory"]["bytes"])
        header = ["decoder"] + [f"{s['size_name']} (batch {s['batch']}) MiB" for s in mem] + \
                 [f"÷ FM ({s['size_name']})" for s in mem]
        rows = []
        for n in names:
            vals = [s["memory"]["bytes"][n] for s in mem]
            fms = [s["memory"]["bytes"]["FM"] for s in mem]
            rows.append([n] + [f"{v / 2**20:.2f}" for v in vals] + [f"{v / f:.2f}×" for v, f in zip(vals, fms)])
        lines += [_table(header, rows), ""]
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samp, train = results.get("sampling", []), [s for s in results.get("training", []) if s["rows"]]
    panels = [p for p in (samp, train) if p]
    if not panels:
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 4.8), squeeze=False)
    ax_i = 0
    if samp:
        ax = axes[0, ax_i]
        ax_i += 1
        labels = [r["sampler"].rsplit(", K=", 1)[0].replace(" (boundary u(x,t,t))", "")
                  .replace(" (policy.predict_action_chunk)", " (policy)") + f" K={r['steps']}"
                  for r in samp[0]["rows"]]
        width = 0.8 / len(samp)
        for j, sec in enumerate(samp):
            xs = [i + j * width for i in range(len(labels))]
            ax.bar(xs, [r["overhead"] for r in sec["rows"]], width, label=f"{sec['size_name']} (B={sec['batch']})")
        ax.axhline(1.0, color="k", lw=0.8)
        ax.axhline(1.05, color="g", ls="--", lw=0.8, label="target ODE/MF 1.05")
        ax.axhline(1.15, color="orange", ls="--", lw=0.8, label="target SDE 1.15")
        ax.set_xticks([i + 0.4 - width / 2 for i in range(len(labels))], labels, rotation=35, ha="right",
                      fontsize=7)
        ax.set_ylabel("sampling time ÷ (K × network call)")
        ax.set_ylim(0.9, max(1.3, max(r["overhead"] for s in samp for r in s["rows"]) * 1.05))
        ax.set_title("Sampler overhead (1.0 = physical limit)")
        ax.legend(fontsize=7)
    if train:
        ax = axes[0, ax_i]
        labels = [r["decoder"] for r in train[0]["rows"]]
        width = 0.8 / len(train)
        for j, sec in enumerate(train):
            xs = [i + j * width for i in range(len(labels))]
            ax.bar(xs, [r["vs_fm"] for r in sec["rows"]], width, label=f"{sec['size_name']} (batch {sec['batch']})")
        ax.axhline(1.5, color="orange", ls="--", lw=0.8, label="target MF 1.5×")
        ax.axhline(1.25, color="g", ls=":", lw=0.8, label="stretch 1.25×")
        ax.set_xticks([i + 0.4 - width / 2 for i in range(len(labels))], labels, rotation=25, ha="right",
                      fontsize=7)
        ax.set_ylabel("training step ÷ FM training step")
        ax.set_title("Training step cost")
        ax.legend(fontsize=7)
    fig.suptitle(f"action_decoder — {results['machine']['cpu']}, torch {results['machine']['torch']}, "
                 f"{results['machine']['threads']} thread(s)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(results: dict, out: Path, plot: bool = True) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    (out / JSON_NAME).write_text(json.dumps(results, indent=1, default=str) + "\n")
    plot_name = None
    if plot:
        globals()["plot"](results, out / PLOT_NAME)
        plot_name = PLOT_NAME if (out / PLOT_NAME).exists() else None
    body = f"{BEGIN}\n{render(results, plot_name)}\n{END}"
    readme = out / "README.md"
    if readme.exists() and BEGIN in (text := readme.read_text()) and END in text:
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        new = head + body + tail
    else:
        new = DEFAULT_HEAD + body + "\n"
    readme.write_text(new)
    return readme
