"""Observation history on Meta-World: the default decoder trained with `--n-obs-steps 1` against 2.

    python -m benchmarks.obs_history --tasks basketball,box-close --seeds 0 --n-obs-steps 1,2

Each (task, seed, n) run trains `action-decoder train --n-obs-steps n` (flow matching, the CLI's
defaults otherwise) and evaluates the saved policy on the same 50 layouts with `action-decoder
eval`; runs live under --runs and are skipped when their evaluation is there. The summary goes to
--results (JSON): per task and n the success rate, with the binomial standard error
√(p(1 − p)/episodes) of each rate and of the difference n = 2 − n = 1; `--table PAGE` rewrites the
table between the page's markers.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

CLI = [sys.executable, "-m", "action_decoder.cli"]


def run_one(task: str, seed: int, n: int, args) -> dict:
    run = Path(args.runs) / f"{task}_s{seed}_n{n}"
    out = run / "eval.json"
    if not out.is_file():
        run.mkdir(parents=True, exist_ok=True)
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        with open(run / "log.txt", "a") as log:
            if not (run / "train" / "final" / "model.safetensors").is_file():
                resume = ["--resume"] if (run / "train" / "checkpoints" / "last").is_file() else []
                subprocess.run([*CLI, "train", "--task", f"metaworld/{task}", "--steps", str(args.steps),
                                "--seed", str(seed), "--n-obs-steps", str(n), "--eval-episodes", "0",
                                "--no-progress", "--output-dir", str(run / "train"), *resume], stdout=log,
                               stderr=subprocess.STDOUT, check=True, env=env)
            subprocess.run([*CLI, "eval", "--checkpoint", str(run / "train" / "final"), "--episodes", str(args.episodes),
                            "--seed", str(seed), "--output", str(out)], stdout=log, stderr=subprocess.STDOUT,
                           check=True, env=env)
    res = json.loads(out.read_text())
    return {"task": task, "seed": seed, "n_obs_steps": n, "episodes": res["episodes_per_task"],
            "success": res["success_rate"], "boundary_jerk": res["boundary_jerk"]}


def binomial_se(p: float, episodes: int) -> float:
    """Standard error of a success rate p measured on `episodes` independent episodes."""
    return math.sqrt(max(p * (1 - p), 0.0) / episodes)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", default="basketball,box-close,pick-place-wall,soccer,stick-pull",
                   help="comma-separated Meta-World task names")
    p.add_argument("--seeds", default="0", help="comma-separated seeds")
    p.add_argument("--n-obs-steps", default="1,2", help="comma-separated observation-history lengths")
    p.add_argument("--steps", type=int, default=1500, help="training steps per run")
    p.add_argument("--episodes", type=int, default=50, help="evaluation episodes per run")
    p.add_argument("--runs", default="runs/obs_history", help="directory of the runs")
    p.add_argument("--results", default="docs/benchmarks/obs_history.json", help="JSON summary")
    p.add_argument("--table", default=None, help="a Markdown page whose table (between its markers) is rewritten")
    args = p.parse_args(argv)
    rows = []
    for task in args.tasks.split(","):
        for seed in map(int, args.seeds.split(",")):
            for n in map(int, args.n_obs_steps.split(",")):
                rows.append(run_one(task, seed, n, args))
                print(json.dumps(rows[-1]), flush=True)
    for r in rows:
        r["se"] = binomial_se(r["success"], r["episodes"])
    Path(args.results).write_text(json.dumps({"steps": args.steps, "rows": rows}, indent=1) + "\n")
    if args.table:
        page = Path(args.table)
        text = page.read_text()
        start, end = text.index(TABLE_START) + len(TABLE_START), text.index(TABLE_END)
        page.write_text(text[:start] + "\n" + table(rows) + text[end:])


TABLE_START, TABLE_END = "<!-- table: benchmarks.obs_history -->", "<!-- end of table -->"


def table(rows: list[dict]) -> str:
    """Success in % ± binomial SE per task and seed, n = 1 against n = 2, the difference with its SE, and the
    mean squared jerk of the executed actions across chunk switches (`envs.evaluate`'s boundary_jerk)."""
    by = {}
    for r in rows:
        by.setdefault((r["task"], r["seed"]), {})[r["n_obs_steps"]] = r
    lines = ["| task | seed | n = 1 | n = 2 | n = 2 − n = 1 | boundary jerk n = 1 | n = 2 |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    pairs = []
    for (task, seed), got in by.items():
        if 1 not in got or 2 not in got:
            continue
        a, b = got[1], got[2]
        se = math.hypot(a["se"], b["se"])
        pairs.append((a, b))
        lines.append(f"| {task} | {seed} | {100 * a['success']:.0f} ± {100 * a['se']:.0f} | "
                     f"{100 * b['success']:.0f} ± {100 * b['se']:.0f} | {100 * (b['success'] - a['success']):+.0f} ± "
                     f"{100 * se:.0f} | {a['boundary_jerk']:.2f} | {b['boundary_jerk']:.2f} |")
    if pairs:
        k = len(pairs)
        m1, m2 = (sum(p[i]["success"] for p in pairs) / k for i in (0, 1))
        se = math.sqrt(sum(p[0]["se"] ** 2 + p[1]["se"] ** 2 for p in pairs)) / k
        lines.append(f"| **mean ({k} task{'s' if k > 1 else ''})** | | **{100 * m1:.1f}** | **{100 * m2:.1f}** | "
                     f"**{100 * (m2 - m1):+.1f} ± {100 * se:.1f}** | | |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
