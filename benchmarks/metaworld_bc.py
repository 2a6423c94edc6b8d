"""Behaviour-cloning benchmark in the MP1 setting: 10 demonstrations per task, Meta-World's
medium, hard and very hard tasks, several seeds (demo subsets), 50 evaluation episodes on
layouts disjoint from the demonstrations, for each decoder and sampling budget.

    python -m benchmarks.metaworld_bc --jobs 2                      # the full grid (hours on CPU)
    python -m benchmarks.metaworld_bc --tasks metaworld/push --seeds 0 --episodes 20   # a taste
    python -m benchmarks.metaworld_bc --tasks metaworld/MT10 --multitask --decoders flow_matching \
        --steps 6000 --seeds 0 --runs runs/metaworld_mt10 --table docs/benchmarks/metaworld_mt10.md

Every (task, seed, decoder) run lives in its own directory under --runs and is skipped when
already complete, so the grid can be stopped and continued. The table is written to
docs/benchmarks/metaworld_bc.md from whatever runs exist.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

# (decoder, sampler, steps) columns of the table; the first per decoder is its default.
METHODS = [("DDPM", "ode", 10), ("flow_matching", "ode", 10), ("flow_matching", "ode", 1),
           ("mean_flow", "ode", 1), ("mean_flow", "ode", 2), ("mlp_baseline", "ode", 10), ("mlp_baseline", "ode", 1)]
LABELS = {("DDPM", "ode", 10): "DDPM K=10", ("flow_matching", "ode", 10): "FM K=10",
          ("flow_matching", "ode", 1): "FM K=1", ("mean_flow", "ode", 1): "MF K=1",
          ("mean_flow", "ode", 2): "MF K=2", ("mlp_baseline", "ode", 10): "MLP ref. K=10",
          ("mlp_baseline", "ode", 1): "MLP ref. K=1"}
CLI = [sys.executable, "-m", "action_decoder.cli"]


def _run(cmd: list[str], log: Path) -> None:
    with open(log, "a") as fh:
        subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})


def run_one(task: str, seed: int, decoder: str, args) -> None:
    """Train one policy (if not yet trained), then evaluate it at each of its sampling budgets."""
    run = Path(args.runs) / f"{task.split('/')[-1]}_s{seed}_{decoder}"     # task: one task, or a group (--multitask)
    run.mkdir(parents=True, exist_ok=True)
    log = run / "log.txt"
    if decoder == "mlp_baseline":       # the reference network: trains and evaluates in one go
        if not (run / "eval_ode_k1.json").is_file():
            _run([sys.executable, "-m", "benchmarks.mlp_baseline", "--task", task, "--seed", str(seed),
                  "--demos", str(args.demos), "--episodes", str(args.episodes), "--output-dir", str(run)], log)
        return
    if not (run / "final" / "model.safetensors").is_file():
        resume = ["--resume"] if (run / "checkpoints" / "last").is_file() else []
        _run([*CLI, "train", "--task", task, "--decoder", decoder, "--demos", str(args.demos), "--steps",
              str(args.steps), "--seed", str(seed), "--output-dir", str(run), "--eval-episodes", "0",
              "--no-progress", *resume], log)
    for dec, sampler, k in METHODS:
        out = run / f"eval_{sampler}_k{k}.json"
        if dec == decoder and not out.is_file():
            _run([*CLI, "eval", "--checkpoint", str(run / "final"), "--episodes", str(args.episodes),
                  "--sampler", sampler, "--steps", str(k), "--seed", str(seed), "--output", str(out)], log)


def collect(runs: Path) -> dict:
    """{task: {method: [success per seed]}} from the eval JSON files present (a multi-task
    policy contributes one entry per task)."""
    table: dict = {}
    for path in sorted(runs.glob("*/eval_*.json")):
        res = json.loads(path.read_text())
        method = (res["decoder_type"], res["sampler"], res["steps"])
        for task, success in res["per_task"].items():
            table.setdefault(task, {}).setdefault(method, []).append(success)
    return table


def write_table(table: dict, path: Path, args) -> str:
    methods = [m for m in METHODS if any(m in row for row in table.values())]
    lines = ["| task | " + " | ".join(LABELS[m] for m in methods) + " |",
             "|---|" + "---:|" * len(methods)]
    means = {m: [] for m in methods}
    for task in sorted(table):
        cells = []
        for m in methods:
            vals = table[task].get(m, [])
            if vals:
                means[m].append(statistics.mean(vals))
                sd = f" ± {100 * statistics.stdev(vals):.0f}" if len(vals) > 1 else ""
                cells.append(f"{100 * statistics.mean(vals):.0f}{sd} ({len(vals)})")
            else:
                cells.append("–")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    lines.append("| **mean** | " + " | ".join(
        f"**{100 * statistics.mean(means[m]):.1f}**" if means[m] else "–" for m in methods) + " |")
    text = ("Success rate in % (mean ± std over seeds; the number of seeds in parentheses). "
            f"{args.demos} demonstrations per task, {args.steps} training steps, "
            f"{args.episodes} evaluation episodes per seed on layouts disjoint from the demonstrations.\n\n"
            + "\n".join(lines) + "\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="metaworld/medium,metaworld/hard,metaworld/very_hard")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--decoders", nargs="+", default=["DDPM", "flow_matching", "mean_flow", "mlp_baseline"],
                   help="mlp_baseline: the plain-MLP flow-matching reference (benchmarks/mlp_baseline.py)")
    p.add_argument("--demos", type=int, default=10)
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--jobs", type=int, default=1, help="runs in parallel (one core each)")
    p.add_argument("--runs", default="runs/metaworld_bc")
    p.add_argument("--table", default="docs/benchmarks/metaworld_bc.md")
    p.add_argument("--multitask", action="store_true",
                   help="train one policy on all of --tasks (task given through the context path)")
    args = p.parse_args(argv)
    from action_decoder.envs import resolve_tasks

    tasks = [args.tasks] if args.multitask else [f"metaworld/{t}" for t in resolve_tasks(args.tasks)]
    if args.multitask and "mlp_baseline" in args.decoders:
        p.error("--multitask: the mlp_baseline reference has no task conditioning; drop it from --decoders")
    grid = [(t, s, d) for t in tasks for s in args.seeds for d in args.decoders]
    with ThreadPoolExecutor(args.jobs) as pool:
        for fut in [pool.submit(run_one, *job, args) for job in grid]:
            fut.result()
    print(write_table(collect(Path(args.runs)), Path(args.table), args))


if __name__ == "__main__":
    main()
