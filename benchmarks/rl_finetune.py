"""RL fine-tuning benchmark: behaviour-clone a policy from 3 demonstrations, then fine-tune it
with `action-decoder finetune` under a CPU-time budget, and compare success on the same 50
evaluation layouts before and after.

    python -m benchmarks.rl_finetune --jobs 2                                  # the default grid
    python -m benchmarks.rl_finetune --tasks metaworld/push --decoders flow_matching --cpu-minutes 10

Each (task, decoder) run lives in its own directory under --runs (suffixed `_sac` for SAC);
finished steps are skipped and an interrupted fine-tuning resumes, so the grid can be stopped
and continued. The rows of finished runs are merged into docs/benchmarks/rl_finetune.json
(which keeps rows whose run directories are gone), and the table and a plot of the learning
curves are written from it; text below the table's notes marker is kept.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from operator import itemgetter
from pathlib import Path

CLI = [sys.executable, "-m", "action_decoder.cli"]
NOTES = "<!-- notes: kept when the table above is rebuilt -->"


def _run(cmd: list[str], log: Path) -> None:
    with open(log, "a") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})


def _eval(checkpoint: Path, out: Path, sampler: str, args, log: Path, steps: int = 0) -> None:
    if not out.is_file():
        _run([*CLI, "eval", "--checkpoint", str(checkpoint), "--episodes", str(args.episodes), "--sampler", sampler,
              "--seed", "0", "--output", str(out), *(["--steps", str(steps)] if steps else [])], log)


def _sde_steps(args) -> int:
    """K of the fine-tuned policy: `--sde-steps` among the extra options, else finetune's default."""
    from action_decoder.rl.finetune import FinetuneConfig

    extra = args.finetune_args
    return int(extra[extra.index("--sde-steps") + 1]) if "--sde-steps" in extra else FinetuneConfig.sde_steps


def run_one(task: str, decoder: str, args) -> None:
    run = Path(args.runs) / f"{task.split('/')[-1]}_{decoder}{'' if args.algo == 'ppo' else '_' + args.algo}"
    run.mkdir(parents=True, exist_ok=True)
    log = run / "log.txt"
    bc, ft = run / "bc", run / "ft"
    if not (bc / "final" / "model.safetensors").is_file():
        resume = ["--resume"] if (bc / "checkpoints" / "last").is_file() else []
        _run([*CLI, "train", "--task", task, "--decoder", decoder, "--demos", str(args.demos), "--steps",
              str(args.bc_steps), "--hidden-size", "64", "--num-layers", "2", "--seed", "0", "--output-dir", str(bc),
              "--n-action-steps", "8",    # the recipe the RL table was measured with: 8 actions per decision
              "--eval-episodes", "0", "--no-progress", *resume], log)
    _eval(bc / "final", run / "bc_eval.json", "ode", args, log)
    # The fine-tuned policy samples with K = --sde-steps; MeanFlow's BC default is K = 1, so the
    # BC policy is also measured at that K, and the gain is taken over the better of the two.
    k = _sde_steps(args)
    if json.loads((run / "bc_eval.json").read_text())["steps"] != k:
        _eval(bc / "final", run / f"bc_eval_k{k}.json", "ode", args, log, steps=k)
    if not (ft / "final" / "model.safetensors").is_file():
        resume = ["--resume"] if (ft / "checkpoints" / "last").is_file() else []
        _run([*CLI, "finetune", "--checkpoint", str(bc / "final"), "--output-dir", str(ft), "--algo", args.algo,
              "--env-steps", "10000000", "--max-cpu-minutes", str(args.cpu_minutes), "--eval-every", "10",
              *args.finetune_args, *resume], log)
    _eval(ft / "final", run / "ft_eval_sde.json", "sde", args, log)
    _eval(ft / "final", run / "ft_eval_ode.json", "ode", args, log)


def collect(runs: Path) -> list[dict]:
    """One row per finished run under `runs`: success before/after and the evaluation curve."""
    rows = []
    for run in sorted(p for p in runs.iterdir() if (p / "ft_eval_ode.json").is_file()):
        bc = json.loads((run / "bc_eval.json").read_text())
        ft_k = json.loads((run / "ft_eval_ode.json").read_text())["steps"]
        at_k = run / f"bc_eval_k{ft_k}.json"
        bc_at_k = json.loads(at_k.read_text()) if at_k.is_file() else bc
        sde = json.loads((run / "ft_eval_sde.json").read_text())
        ode = json.loads((run / "ft_eval_ode.json").read_text())
        log = json.loads((run / "ft" / "finetune_log.json").read_text())
        last = log["history"][-1]
        cpu = {h["iteration"]: h.get("cpu_s", h["wall_s"]) / 60 for h in log["history"]}
        rows.append({"task": log["task"], "decoder": bc["decoder_type"], "algo": log["config"]["algo"],
                     "bc": bc["success_rate"], "bc_steps": bc["steps"], "bc_at_ft_k": bc_at_k["success_rate"], "ft_k": ft_k,
                     "ft_sde": sde["success_rate"], "ft_ode": ode["success_rate"],
                     "cpu_min": round(last.get("cpu_s", last["wall_s"]) / 60, 2), "env_steps": last["env_steps"],
                     "measured": time.strftime("%Y-%m-%d", time.gmtime((run / "ft_eval_ode.json").stat().st_mtime)),
                     # (CPU minutes, 20-episode SDE success, ODE success) at each evaluation during the run
                     "curve": [[round(cpu.get(e["iteration"], 0.0), 2), e["success_sde"], e["success_ode"]]
                               for e in log["evals"]]})
    return rows


def merge(results: Path, rows: list[dict]) -> list[dict]:
    """Rows kept in `results` from earlier runs, replaced by this run directory's rows for the same
    (task, decoder, algo); written back so that tables and plots can be rebuilt from every run kept."""
    key = itemgetter("task", "decoder", "algo")
    kept = {key(r): r for r in (json.loads(results.read_text()) if results.is_file() else [])}
    kept.update({key(r): r for r in rows})
    merged = sorted(kept.values(), key=key)
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text("[\n" + ",\n".join(json.dumps(r) for r in merged) + "\n]\n")  # a row per line: diffs by row
    return merged


def write_report(rows: list[dict], table: Path, plot: Path, args) -> str:
    lines = ["| task | decoder | algo | BC (ODE, default K) | BC (ODE, fine-tuning's K) | fine-tuned (SDE) | "
             "fine-tuned (ODE) | gain (best over best) | CPU min | env steps | measured |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        gain = 100 * (max(r["ft_sde"], r["ft_ode"]) - max(r["bc"], r["bc_at_ft_k"]))
        lines.append(f"| {r['task']} | {r['decoder']} | {r['algo']} | {100 * r['bc']:.0f} (K={r['bc_steps']}) | "
                     f"{100 * r['bc_at_ft_k']:.0f} (K={r['ft_k']}) | {100 * r['ft_sde']:.0f} | {100 * r['ft_ode']:.0f} | "
                     f"{gain:+.0f} | {r['cpu_min']:.0f} | {r['env_steps']} | {r['measured']} |")
    text = (f"Success in % on the same {args.episodes} evaluation layouts (seed 0) before and after fine-tuning; "
            f"BC from {args.demos} demonstrations (Action Expert hidden 64, 2 layers, {args.bc_steps} steps).\n\n"
            + "\n".join(lines) + "\n\n"
            f"Rebuilt by `python -m benchmarks.rl_finetune` from `{args.results}`; the plot `{plot.name}` holds the "
            "learning curves of the rows that kept one (rows recorded before the curves were stored have none).\n")
    table.parent.mkdir(parents=True, exist_ok=True)
    notes = table.read_text().partition(NOTES)[2] if table.is_file() else ""
    table.write_text(text + f"\n{NOTES}" + (notes or "\n"))   # the hand-written part below the table stays
    curves = [r for r in rows if r["curve"]]
    if curves:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(curves), figsize=(3.6 * len(curves), 3.2), squeeze=False)
        for ax, r in zip(axes[0], curves):
            cpu, sde, ode = zip(*r["curve"])
            ax.plot(cpu, sde, marker="o", label="eval sde (20 ep.)")
            ax.plot(cpu, ode, marker="o", label="eval ode (20 ep.)")
            ax.axhline(r["bc_at_ft_k"], color="gray", ls="--", label=f"BC (K={r['ft_k']}), {args.episodes} ep.")
            ax.set(title=f"{r['task']} {r['decoder']}", xlabel="CPU minutes", ylabel="success", ylim=(-0.02, 1.02))
            ax.grid(alpha=0.3)
        axes[0][0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(plot, dpi=110)
        plt.close(fig)
    return text


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="metaworld/reach,metaworld/reach-wall,metaworld/door-lock",
                   help="tasks whose 3-demo BC policy succeeds in 15-60 %% of episodes (docs/benchmarks/rl_finetune.md)")
    p.add_argument("--decoders", nargs="+", default=["flow_matching", "mean_flow"])
    p.add_argument("--algo", default="ppo", choices=["ppo", "sac"])
    p.add_argument("--demos", type=int, default=3)
    p.add_argument("--bc-steps", type=int, default=2000)
    p.add_argument("--cpu-minutes", type=float, default=45)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--jobs", type=int, default=1, help="runs in parallel (one core each)")
    p.add_argument("--runs", default="runs/rl_finetune")
    p.add_argument("--table", default="docs/benchmarks/rl_finetune.md")
    p.add_argument("--plot", default="docs/benchmarks/rl_finetune.png")
    p.add_argument("--results", default="docs/benchmarks/rl_finetune.json",
                   help="rows of earlier runs, merged with this run directory's and written back")
    p.add_argument("--report-only", action="store_true", help="rebuild the table and plot, run nothing")
    p.add_argument("finetune_args", nargs=argparse.REMAINDER, help="extra `finetune` options after --")
    args = p.parse_args(argv)
    args.finetune_args = [a for a in args.finetune_args if a != "--"]
    from action_decoder.envs import resolve_tasks

    grid = [] if args.report_only else [(f"metaworld/{t}", d) for t in resolve_tasks(args.tasks) for d in args.decoders]
    with ThreadPoolExecutor(args.jobs) as pool:
        for fut in [pool.submit(run_one, *job, args) for job in grid]:
            fut.result()
    print(write_report(merge(Path(args.results), collect(Path(args.runs))), Path(args.table), Path(args.plot), args))


if __name__ == "__main__":
    main()
