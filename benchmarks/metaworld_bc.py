"""Behaviour-cloning benchmark in the MP1 setting: 10 demonstrations per task, Meta-World's
medium, hard and very hard tasks, several seeds (demo subsets), 50 evaluation episodes on
layouts disjoint from the demonstrations, for each decoder and sampling budget.

    python -m benchmarks.metaworld_bc --jobs 2                      # the full grid (hours on CPU)
    python -m benchmarks.metaworld_bc --tasks metaworld/push --seeds 0 --episodes 20   # a taste
    python -m benchmarks.metaworld_bc --tasks metaworld/MT10 --multitask --decoders flow_matching \
        --steps 6000 --seeds 0 --runs runs/metaworld_mt10 --table docs/benchmarks/metaworld_mt10.md

Every (task, seed, decoder) run lives in its own directory under --runs and is skipped when
already complete, so the grid can be stopped and continued. Finished evaluations are merged,
one row each, into --results (docs/benchmarks/metaworld_bc.json), which a later invocation
also skips: the grid can be finished over several invocations. The table in
docs/benchmarks/metaworld_bc.md is rebuilt from the rows of today's recipe (demos and their
recording noise, training steps and batch, episodes, state layout and shift); text below its notes marker
is kept. Beside the decoders stand two references: the plain-MLP policy the issue measured
(`mlp_baseline`) and the scripted expert that made the demonstrations (`scripted_expert`, the
ceiling), on the same evaluation layouts.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from action_decoder.train import DEFAULT_SHIFT, TrainConfig

from .mlp_baseline import N_ACTION_STEPS as MLP_N_ACTION_STEPS

# (decoder, sampler, steps) columns of the table; the first per decoder is its default.
METHODS = [("DDPM", "ode", 10), ("flow_matching", "ode", 10), ("flow_matching", "ode", 1),
           ("mean_flow", "ode", 1), ("mean_flow", "ode", 2), ("mlp_baseline", "ode", 10), ("mlp_baseline", "ode", 1),
           ("scripted_expert", "expert", 1)]
LABELS = {("DDPM", "ode", 10): "DDPM K=10", ("flow_matching", "ode", 10): "FM K=10",
          ("flow_matching", "ode", 1): "FM K=1", ("mean_flow", "ode", 1): "MF K=1",
          ("mean_flow", "ode", 2): "MF K=2", ("mlp_baseline", "ode", 10): "MLP ref. K=10",
          ("mlp_baseline", "ode", 1): "MLP ref. K=1", ("scripted_expert", "expert", 1): "expert"}
CLI = [sys.executable, "-m", "action_decoder.cli"]
# Rows without a batch size were trained with batch 128, and their run directories name only the
# step budget. A run with another batch names it too, so as not to reuse the directory of one of them.
LEGACY_BATCH = 128
NOTES = "<!-- notes: kept when the table above is rebuilt -->"


def _run(cmd: list[str], log: Path) -> None:
    with open(log, "a") as fh:
        subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})


def run_one(task: str, seed: int, decoder: str, args) -> None:
    """Train one policy (if not yet trained), evaluate it at each of its sampling budgets, and merge
    its rows into --results at once (an invocation cut off mid-grid keeps every finished run)."""
    if all(m in args.done.get((task, seed), set()) for m in METHODS if m[0] == decoder):
        return                          # measured by an earlier invocation: kept in --results
    tag = f"_dart{args.demo_noise:g}" if args.demo_noise and decoder != "scripted_expert" else ""
    if decoder not in ("mlp_baseline", "scripted_expert") and args.batch_size != LEGACY_BATCH:  # theirs: fixed
        tag += f"_{args.steps}x{args.batch_size}"
    target = ["--meanflow-target", args.meanflow_target] if decoder == "mean_flow" else []
    if decoder == "mean_flow" and args.meanflow_target != "identity":
        tag += f"_{args.meanflow_target}"
    run = Path(args.runs) / f"{task.split('/')[-1]}_s{seed}{tag}_{decoder}"  # task: one task, or a group (--multitask)
    run.mkdir(parents=True, exist_ok=True)
    log = run / "log.txt"
    if decoder == "scripted_expert":    # the ceiling: the demonstrator on the same evaluation layouts
        if not (run / "eval_expert.json").is_file():
            _run([sys.executable, "-m", "benchmarks.scripted_expert", "--task", task, "--seed", str(seed),
                  "--episodes", str(args.episodes), "--output-dir", str(run)], log)
        _keep(run, args)
        return
    if decoder == "mlp_baseline":       # the reference network: trains and evaluates in one go
        if not (run / "eval_ode_k1.json").is_file():
            _run([sys.executable, "-m", "benchmarks.mlp_baseline", "--task", task, "--seed", str(seed),
                  "--demos", str(args.demos), "--demo-noise", str(args.demo_noise), "--episodes", str(args.episodes),
                  "--output-dir", str(run)], log)
        _keep(run, args)
        return
    if (run / "final" / "model.safetensors").is_file():
        if have := recipe(run):         # empty: a checkpoint without its training config, nothing to compare
            _check_reuse(run, have, {"demos": args.demos, "demo_noise": args.demo_noise,
                                     "train_steps": args.steps, "batch_size": args.batch_size})
    else:
        resume = ["--resume"] if (run / "checkpoints" / "last").is_file() else []
        _run([*CLI, "train", "--task", task, "--decoder", decoder, "--demos", str(args.demos),
              "--demo-noise", str(args.demo_noise), "--steps",
              str(args.steps), "--batch-size", str(args.batch_size), "--seed", str(seed), "--output-dir", str(run),
              "--eval-episodes", "0", *target,
              "--no-progress", *resume], log)
    n = args.n_action_steps            # an evaluation setting: one trained policy serves every n
    for dec, sampler, k in METHODS:
        out = run / f"eval_{sampler}_k{k}_n{n}.json"
        if dec == decoder and out.is_file():
            _check_reuse(out, {"episodes": json.loads(out.read_text())["episodes_per_task"]}, {"episodes": args.episodes})
        if dec == decoder and not out.is_file():
            _run([*CLI, "eval", "--checkpoint", str(run / "final"), "--episodes", str(args.episodes),
                  "--sampler", sampler, "--steps", str(k), "--n-action-steps", str(n), "--seed", str(seed),
                  "--output", str(out)], log)
    _keep(run, args)


def _check_reuse(path: Path, have: dict, want: dict) -> None:
    """A run directory or evaluation kept from an earlier invocation serves only the same settings."""
    other = {k: (have.get(k), v) for k, v in want.items() if have.get(k) != v}
    if other:
        raise SystemExit(f"{path}: made with {', '.join(f'{k}={h}' for k, (h, _) in other.items())}, not "
                         f"{', '.join(f'{k}={w}' for k, (_, w) in other.items())}; pass --runs another directory")


_MERGING = threading.Lock()     # runs finish on several threads; the results file has one writer at a time


def _keep(run: Path, args) -> None:
    with _MERGING:
        merge(args.results, collect(run, "eval_*.json"))


def recipe(run: Path) -> dict:
    """How a run's policy was trained: demos and their action noise, training steps and batch, state
    layout and shift (read from its checkpoint; the MLP reference records its own)."""
    config = run / "final" / "config.json"
    if not config.is_file():
        return {}
    saved = json.loads(config.read_text())
    train = saved["extra"]["train"]
    layout = saved.get("state_layout", "flat")          # absent: saved before layouts existed
    shift = train.get("augment_shift", 0.0)
    if shift is None:                                   # the default of `action-decoder train`
        shift = DEFAULT_SHIFT if layout == "metaworld" else 0.0
    how = {"demos": train["demos"], "demo_noise": train.get("demo_noise", 0.0), "train_steps": train["steps"],
           "batch_size": train["batch_size"], "state_layout": layout, "augment_shift": shift}
    if saved.get("decoder_type") == "mean_flow":        # absent: saved before the field existed
        how["meanflow_target"] = saved.get("meanflow_target", "identity")
    return how


def collect(runs: Path, pattern: str = "*/eval_*.json") -> list[dict]:
    """One row per (task, seed, method) from the eval JSON files present (a multi-task policy
    contributes one row per task); `pattern` "eval_*.json" reads one run directory. Our decoders'
    rows carry the actions executed per chunk; the references' rows do not (the MLP's is fixed by
    its definition, the expert re-plans every step), so they match any."""
    rows = []
    for path in sorted(runs.glob(pattern)):
        res = json.loads(path.read_text())
        how = res.get("recipe") or recipe(path.parent)
        if how:                         # the scripted expert has no recipe: its rows match any
            how = {"demo_noise": 0.0, **how}    # runs from before recording noise existed were clean
        if "n_action_steps" in res:
            how["n_action_steps"] = res["n_action_steps"]
        for task, success in res["per_task"].items():
            rows.append({"task": task, "seed": res.get("seed", 0), "decoder": res["decoder_type"],
                         "sampler": res["sampler"], "steps": res["steps"],
                         "episodes": res.get("episodes_per_task"), **how, "success": success})
    return rows


ROW_KEY = ("task", "seed", "decoder", "sampler", "steps", "episodes", "demos", "demo_noise", "train_steps",
           "batch_size", "state_layout", "augment_shift", "n_action_steps", "meanflow_target")


def merge(results: Path, rows: list[dict]) -> list[dict]:
    """Rows kept in `results` from earlier invocations, replaced by fresh rows of the same run; written
    back (a row per line) so that the grid can be finished over several invocations."""
    def key(r):
        return tuple(str(r.get(k)) for k in ROW_KEY)

    def dated(r):                       # a trained row from before batch sizes were recorded: batch 128
        r = {"batch_size": LEGACY_BATCH, **r} if "train_steps" in r else r
        # a MeanFlow row from before `meanflow_target` existed trained with the MeanFlow identity
        return {"meanflow_target": "identity", **r} if r.get("decoder") == "mean_flow" else r

    kept = {key(r): r for r in map(dated, json.loads(results.read_text()) if results.is_file() else [])}
    kept.update({key(r): r for r in map(dated, rows)})
    merged = sorted(kept.values(), key=key)
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text("[\n" + ",\n".join(json.dumps(r) for r in merged) + "\n]\n")
    return merged


def matching(rows: list[dict], want: dict) -> list[dict]:
    """The rows trained and evaluated as `want` says (other recipes stay in the file, not the table).
    A key a row lacks matches anything: the MLP reference has its own fixed training budget. The MLP
    reference re-plans every `MLP_N_ACTION_STEPS` by its definition, whatever the table's decoders do:
    its rows at another count (recorded; a row without one ran at the default) stay out."""
    def reference(r):
        return r["decoder"] == "mlp_baseline"

    return [r for r in rows
            if not (reference(r) and r.get("n_action_steps", MLP_N_ACTION_STEPS) != MLP_N_ACTION_STEPS)
            and all(r.get(k, v) == v for k, v in want.items() if not (reference(r) and k == "n_action_steps"))]


def tabulate(rows: list[dict]) -> dict:
    """{task: {method: {seed: success}}}."""
    table: dict = {}
    for r in rows:
        table.setdefault(r["task"], {}).setdefault((r["decoder"], r["sampler"], r["steps"]), {})[r["seed"]] = r["success"]
    return table


def write_table(table: dict, path: Path, args, results: Path) -> str:
    methods = [m for m in METHODS if any(m in row for row in table.values())]
    lines = ["| task | " + " | ".join(LABELS[m] for m in methods) + " |",
             "|---|" + "---:|" * len(methods)]
    # Columns are compared on the same runs: the mean row takes the (task, seed) pairs every column has.
    shared = {t: sorted(set.intersection(*(set(table[t].get(m, {})) for m in methods))) for t in table}
    pairs = [(t, s) for t in table for s in shared[t]]
    means = {m: [table[t][m][s] for t, s in pairs] for m in methods}
    for task in sorted(table):
        cells = []
        for m in methods:
            vals = list(table[task].get(m, {}).values())
            if vals:
                sd = f" ± {100 * statistics.stdev(vals):.0f}" if len(vals) > 1 else ""
                cells.append(f"{100 * statistics.mean(vals):.0f}{sd} ({len(vals)})")
            else:
                cells.append("–")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    lines.append(f"| **mean ({len({t for t, _ in pairs})} tasks, {len(pairs)} (task, seed) runs with every column)** | " + " | ".join(
        f"**{100 * statistics.mean(means[m]):.1f}**" if means[m] else "–" for m in methods) + " |")
    # While the seeds fill in, each column's own runs on the same tasks say more than the shared ones.
    tasks = [t for t in table if all(table[t].get(m) for m in methods)]
    if any(len(table[t][m]) > len(shared[t]) for t in tasks for m in methods):
        lines.append(f"| mean of task means, each column's own seeds ({len(tasks)} tasks) | " + " | ".join(
            f"{100 * statistics.mean(statistics.mean(table[t][m].values()) for t in tasks):.1f}" for m in methods) + " |")
    text = ("Success rate in % (mean ± std over seeds; the number of seeds in parentheses). "
            f"{args.demos} demonstrations per task"
            + (f" (recorded with noise of std {args.demo_noise:g} on the executed actions)" if args.demo_noise else "")
            + f", {args.steps} training steps of batch {args.batch_size}, the first {args.n_action_steps} actions "
            f"of each chunk executed before re-planning (the MLP reference: {MLP_N_ACTION_STEPS}), "
            f"{args.episodes} evaluation episodes per seed on layouts disjoint from the demonstrations (seed s: "
            f"demonstrations from layouts s·1000 + k, evaluation on 1 000 000 + s·1000 + j); "
            f"Meta-World state layout (relative positions) and {DEFAULT_SHIFT} m shift augmentation. "
            + (f"MeanFlow trained with `meanflow_target=\"{args.meanflow_target}\"`. "
               if getattr(args, "meanflow_target", "identity") != "identity" else "")
            + f"Built from `{results}` by `python -m benchmarks.metaworld_bc`.\n\n"
            + "\n".join(lines) + "\n")
    notes = path.read_text().partition(NOTES)[2] if path.is_file() else ""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + f"\n{NOTES}" + (notes or "\n"))   # the hand-written part below the table stays
    return text


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="metaworld/medium,metaworld/hard,metaworld/very_hard")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--decoders", nargs="+",
                   default=["DDPM", "flow_matching", "mean_flow", "mlp_baseline", "scripted_expert"],
                   help="mlp_baseline: the plain-MLP flow-matching reference (benchmarks/mlp_baseline.py); "
                        "scripted_expert: the demonstrator itself, the ceiling (benchmarks/scripted_expert.py)")
    p.add_argument("--demos", type=int, default=10)
    p.add_argument("--demo-noise", type=float, default=TrainConfig.demo_noise,
                   help="std of the noise on the expert's executed actions while recording (DART; the table "
                        "keeps one value)")
    p.add_argument("--steps", type=int, default=5000, help="training steps (the main job trains 1500)")
    p.add_argument("--batch-size", type=int, default=TrainConfig.batch_size,
                   help="training batch (the MLP reference: its own 256)")
    p.add_argument("--n-action-steps", type=int, default=TrainConfig.n_action_steps,
                   help="actions executed from each chunk before re-planning (evaluation only: a trained run "
                        "is re-evaluated, not retrained, for another value)")
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--jobs", type=int, default=1, help="runs in parallel (one core each)")
    p.add_argument("--runs", default="runs/metaworld_bc")
    p.add_argument("--table", default="docs/benchmarks/metaworld_bc.md")
    p.add_argument("--results", default=None,
                   help="rows kept across invocations (default: --table with .json); the table is built from them")
    p.add_argument("--report-only", action="store_true",
                   help="train nothing: merge the finished runs into --results and rebuild the table")
    p.add_argument("--meanflow-target", default="identity", choices=["identity", "split"],
                   help="MeanFlow's training target (`train --meanflow-target`); the table shows MeanFlow rows "
                        "of this target beside the other decoders' rows")
    p.add_argument("--multitask", action="store_true",
                   help="train one policy on all of --tasks (task given through the context path)")
    args = p.parse_args(argv)
    from action_decoder.envs import resolve_tasks

    tasks = [args.tasks] if args.multitask else [f"metaworld/{t}" for t in resolve_tasks(args.tasks)]
    if args.multitask and {"mlp_baseline", "scripted_expert"} & set(args.decoders):
        p.error("--multitask: the mlp_baseline and scripted_expert columns are per task; drop them from --decoders")
    results = args.results = Path(args.results or Path(args.table).with_suffix(".json"))
    want = {"demos": args.demos, "demo_noise": args.demo_noise, "train_steps": args.steps,
            "batch_size": args.batch_size, "episodes": args.episodes,
            "state_layout": "metaworld", "augment_shift": DEFAULT_SHIFT, "n_action_steps": args.n_action_steps,
            "meanflow_target": args.meanflow_target}
    args.done = {}
    for r in [] if args.multitask else matching(merge(results, []), want):
        args.done.setdefault((f"metaworld/{r['task']}", r["seed"]), set()).add((r["decoder"], r["sampler"], r["steps"]))
    grid = [] if args.report_only else [(t, s, d) for t in tasks for s in args.seeds for d in args.decoders]
    with ThreadPoolExecutor(args.jobs) as pool:
        for fut in [pool.submit(run_one, *job, args) for job in grid]:
            fut.result()
    rows = merge(results, collect(Path(args.runs)))
    table = tabulate(matching(rows, want))
    if args.meanflow_target != "identity":      # a recipe variant's table: the tasks it was measured on
        table = {t: row for t, row in table.items() if any(m[0] == "mean_flow" for m in row)}
    print(write_table(table, Path(args.table), args, results))


if __name__ == "__main__":
    main()
