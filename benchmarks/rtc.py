"""Real-time chunking benchmark: naive switching, guided and training-time RTC under simulated inference delay.

    python -m benchmarks rtc                     # = python -m benchmarks.rtc; multimodal chunks, then Meta-World
    python -m benchmarks rtc --part multimodal   # the synthetic two-route chunks and the obstacle routes only
    python -m benchmarks rtc --part metaworld --tasks metaworld/push --episodes 10   # a taste
    python -m benchmarks rtc --part horizons     # guidance horizons (overlap vs execution) on Meta-World
    python -m benchmarks rtc --part prefix --settings mean_flow:1 mean_flow:2   # trained RTC on its training chunks

--part multimodal and metaworld compare naive / guided / trained (`benchmarks/rtc_modes.py`), rows in
--multimodal-json and --modes-json. --part prefix feeds the RTC-trained Meta-World weights their own
demonstrations' prefixes (`benchmarks/rtc_prefix_fit.py`), rows in --prefix-json. --part horizons (below)
compares the guidance horizons.

For each task it trains (once, with `action-decoder train` defaults, no evaluation) a flow-matching
and a MeanFlow policy under --runs/<task>-<decoder>/, then evaluates closed loop, re-planning every
n_action_steps = 4 of 16 actions, for each sampling setting (FM K = 10, MF K = 1, MF K = 2), each
delay d, naive switching and RTC with each --horizons value (`rtc_horizon`: "overlap", the paper's,
guides every row the previous chunk covers; "execution" only the rows the new chunk executes):
success and the boundary jerk (mean squared second difference of the executed actions over the
stencils that span a chunk switch, `envs.evaluate`). Every evaluation draws the same noise per
(episode, plan) in all arms, so the arms differ only by RTC. Per-chunk latency is timed for one state (batch 1) on this machine's threads, plain and RTC
calls interleaved, the median over --latency-reps calls each. Rows go to --json; the page
--table is rebuilt from them (text under the notes marker is kept).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

TASKS = ["metaworld/push", "metaworld/basketball", "metaworld/pick-place", "metaworld/door-open",
         "metaworld/stick-pull"]
SETTINGS = [("flow_matching", 10), ("mean_flow", 1), ("mean_flow", 2)]
LABEL = {("flow_matching", 10): "FM K=10", ("mean_flow", 1): "MF K=1", ("mean_flow", 2): "MF K=2"}
NOTES = "<!-- notes: kept when the table above is rebuilt -->"


def train(task: str, decoder: str, runs: Path) -> Path:
    out = runs / f"{task.split('/')[-1]}-{decoder}"
    if not (out / "final" / "model.safetensors").is_file():
        cmd = [sys.executable, "-m", "action_decoder.cli", "train", "--task", task, "--decoder", decoder,
               "--output-dir", str(out), "--eval-episodes", "0", "--no-progress"]
        out.mkdir(parents=True, exist_ok=True)
        with open(out.with_suffix(".log"), "a") as fh:
            subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True,
                           env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    return out / "final"


def chunk_latency(policy, steps: int, delay: int, reps: int) -> tuple[float, float]:
    """Median seconds of one plain and one RTC chunk for one state (batch 1), interleaved."""
    import torch

    cfg = policy.config
    batch = {"state": torch.zeros(1, cfg.state_dim)}
    prev = torch.zeros(1, cfg.action_chunk_size - cfg.n_action_steps, cfg.action_dim)
    calls = {"plain": lambda: policy.predict_action_chunk(batch, steps=steps),
             "rtc": lambda: policy.predict_action_chunk(batch, steps=steps, prev_chunk=prev, delay=delay)}
    times = {k: [] for k in calls}
    for rep in range(reps + 3):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            if rep >= 3:                                   # the first calls warm up
                times[name].append(time.perf_counter() - start)
    return statistics.median(times["plain"]), statistics.median(times["rtc"])


def evaluate_grid(task: str, ckpt: Path, decoder: str, steps: int, args) -> list[dict]:
    import torch

    from action_decoder import ActionDecoderPolicy
    from action_decoder.envs import evaluate
    from action_decoder.evaluate import make_policy_fn

    policy = ActionDecoderPolicy.from_pretrained(ckpt).eval()
    plain, rtc = chunk_latency(policy, steps, max(args.delays), args.latency_reps)
    rows = []
    for delay in args.delays:
        for arm in ["naive", *args.horizons]:
            use_rtc = arm != "naive"
            if use_rtc:
                policy.config.rtc_horizon = arm
            fn = make_policy_fn(policy, 1, None, steps, torch.Generator().manual_seed(args.seed))
            res = evaluate(fn, task, episodes=args.episodes, seed=args.seed, n_action_steps=policy.config.n_action_steps,
                           num_envs=args.num_envs, delay=delay, rtc=use_rtc)
            rows.append({"task": res["task"], "decoder": decoder, "steps": steps, "delay": delay, "rtc": use_rtc,
                         "rtc_horizon": arm if use_rtc else None,
                         "episodes": args.episodes, "seed": args.seed, "success_rate": res["success_rate"],
                         "successes": int(sum(res["successes"])), "boundary_jerk": res["boundary_jerk"],
                         "boundaries": res["boundaries"], "jerk": res["jerk"],
                         "episode_boundary_jerk": res["episode_boundary_jerk"],
                         "latency_ms": 1000 * (rtc if use_rtc else plain), "checkpoint": str(ckpt)})
            print(f"[{res['task']}] {LABEL[(decoder, steps)]} d={delay} {arm}: "
                  f"success {res['success_rate']:.2f}, boundary jerk {res['boundary_jerk']:.4g}, "
                  f"chunk {rows[-1]['latency_ms']:.1f} ms", flush=True)
    return rows


def retime(path: Path, args) -> None:
    """Replace the latency of every row in `path` by a fresh timing of its checkpoint and setting."""
    import torch

    from action_decoder import ActionDecoderPolicy

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    rows = json.loads(path.read_text())
    for ckpt, steps in sorted({(r["checkpoint"], r["steps"]) for r in rows}):
        policy = ActionDecoderPolicy.from_pretrained(ckpt).eval()
        plain, rtc = chunk_latency(policy, steps, max(r["delay"] for r in rows), args.latency_reps)
        print(f"{ckpt} K={steps}: plain {1000 * plain:.1f} ms, RTC {1000 * rtc:.1f} ms", flush=True)
        for r in rows:
            if (r["checkpoint"], r["steps"]) == (ckpt, steps):
                r["latency_ms"] = 1000 * (rtc if r["rtc"] else plain)
    path.write_text(json.dumps(rows, indent=1))


def _standard_error(values: list) -> float:
    """Standard error of the mean of per-episode values (nan with fewer than two)."""
    return statistics.stdev(values) / len(values) ** 0.5 if len(values) > 1 else float("nan")


def arm(row: dict) -> str:
    """"naive", or the RTC horizon the row was sampled with (rows without one used the whole overlap)."""
    return (row.get("rtc_horizon") or "overlap") if row["rtc"] else "naive"


ARMS = ("naive", "overlap", "execution")


DEFAULT_ARM = {"flow_matching": "overlap", "mean_flow": "execution"}     # rtc_horizon="auto"


def _pool(rows: list[dict]) -> tuple[float, float, float, float]:
    """Success %, boundary jerk (pooled by stencil), its standard error over episodes, mean chunk ms."""
    succ = 100 * sum(x["successes"] for x in rows) / sum(x["episodes"] for x in rows)
    jerk = sum(x["boundary_jerk"] * x["boundaries"] for x in rows) / max(1, sum(x["boundaries"] for x in rows))
    se = _standard_error([j for x in rows for j in x.get("episode_boundary_jerk", []) if j is not None])
    return succ, jerk, se, statistics.mean(x["latency_ms"] for x in rows)


def tabulate(rows: list[dict], delays: list[int]) -> list[str]:
    """One line per (setting, delay, RTC arm): the arm against naive switching on the same tasks and seeds."""
    lines = ["| setting | d | RTC horizon | tasks | success naive | success RTC | Δ success | boundary jerk naive | "
             "boundary jerk RTC | jerk ÷ naive | chunk ms plain | chunk ms RTC | cost ÷ plain |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for setting in SETTINGS:
        for d in delays:
            for a in ARMS[1:]:
                rtc = [x for x in rows if (x["decoder"], x["steps"]) == setting and x["delay"] == d and arm(x) == a]
                cells = {(x["task"], x["seed"]) for x in rtc}
                naive = [x for x in rows if (x["decoder"], x["steps"]) == setting and x["delay"] == d
                         and arm(x) == "naive" and (x["task"], x["seed"]) in cells]
                if not rtc or not naive:
                    continue
                (s0, j0, e0, m0), (s1, j1, e1, m1) = _pool(naive), _pool(rtc)
                label = a + (" (default)" if DEFAULT_ARM[setting[0]] == a else "")
                lines.append(f"| {LABEL[setting]} | {d} | {label} | {len({t for t, _ in cells})} | {s0:.1f} | {s1:.1f} | "
                             f"{s1 - s0:+.1f} | {j0:.4f} ± {e0:.4f} | {j1:.4f} ± {e1:.4f} | {j1 / j0:.2f} | {m0:.1f} | "
                             f"{m1:.1f} | {m1 / m0:.2f}× |")
    return lines


def per_task(rows: list[dict], delays: list[int]) -> list[str]:
    tasks = sorted({r["task"] for r in rows})
    arms = [a for a in ARMS if any(arm(r) == a for r in rows)]
    head = "| setting | d | " + " | ".join(f"{t} {' / '.join(arms)}" for t in tasks) + " |"
    lines = [head, "|---|---|" + "---|" * len(tasks)]
    for setting in SETTINGS:
        for d in delays:
            cells = []
            for t in tasks:
                got = {a: [x for x in rows if x["task"] == t and (x["decoder"], x["steps"]) == setting
                           and x["delay"] == d and arm(x) == a] for a in arms}
                cells.append(" / ".join(f"{100 * sum(x['successes'] for x in v) / sum(x['episodes'] for x in v):.0f}"
                                        if v else "–" for v in got.values()))
            if any(set(c.split(" / ")) != {"–"} for c in cells):
                lines.append(f"| {LABEL[setting]} | {d} | " + " | ".join(cells) + " |")
    return lines


INTRO = ("Inference takes d control steps; the robot executes the old chunk's next d actions meanwhile, and the new "
         "chunk takes over after them. naive: the new chunk switches in unconditioned; guided: `rtc_mode=\"guided\"` "
         "(`flows/rtc.py`, weights trained without RTC); trained: `rtc_mode=\"trained\"` (`flows/rtc_trained.py`, "
         "weights trained with `--rtc-max-delay 4` and the delay distribution each section names), the committed "
         "actions fed in clean. "
         "Route kept: the share of re-plans whose executed rows stay on the committed route.")


def merge_rows(path: Path, new: list[dict], key) -> None:
    """Write `new` into the JSON rows at `path`, replacing the rows that measure the same thing (`key`); read
    at write time, so that runs of other tasks may overlap."""
    old = json.loads(path.read_text()) if path.is_file() else []
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps([r for r in old if key(r) not in {key(n) for n in new}] + new, indent=1))


def _load(path) -> list:
    return json.loads(Path(path).read_text()) if path and Path(path).is_file() else []


def write_page(rows: list[dict], path: Path, args, command: str) -> None:
    delays = sorted({r["delay"] for r in rows})
    n = {r["task"] for r in rows}
    eps = sorted({r["episodes"] for r in rows})
    # Run-to-run noise of a success rate over N episodes: the binomial standard error at p = 0.5 bounds it.
    seeds = sorted({r["seed"] for r in rows})
    cells = {}                                       # episodes per (setting, delay, arm) cell of the table
    for r in rows:
        key = (r["decoder"], r["steps"], r["delay"], arm(r))
        cells[key] = cells.get(key, 0) + r["episodes"]
    counts = sorted(set(cells.values()), reverse=True)
    noise_text = "; ".join(f"±{100 * (0.25 / c) ** 0.5:.1f} points over {c} episodes (beyond noise: more than "
                           f"{2 * 2 ** 0.5 * 100 * (0.25 / c) ** 0.5:.0f} points)" for c in counts) or "not measured"
    from benchmarks.rtc_modes import cost_section, metaworld_section, multimodal_section
    from benchmarks.rtc_prefix_fit import prefix_section

    top = ["# Real-time chunking: naive switching, guided and trained RTC", "", INTRO, "",
           *multimodal_section(_load(getattr(args, "multimodal_json", None))),
           *metaworld_section(_load(getattr(args, "modes_json", None)), getattr(args, "tasks", None) or TASKS),
           *prefix_section(_load(getattr(args, "prefix_json", None))),
           *cost_section(_load(getattr(args, "cost_json", None)))]
    head = [
        "## Guidance horizons: overlap vs execution (weights trained without RTC)", "",
        f"Generated by `{command}` on {', '.join(sorted({r['date'] for r in rows}))} ({os.uname().machine}, "
        f"{os.cpu_count()} CPU cores shared, {os.environ.get('OMP_NUM_THREADS', '?')} torch thread per process).", "",
        f"Tasks: {', '.join(sorted(n))}; {'/'.join(map(str, eps))} episodes per task, seed and cell, "
        f"evaluation seeds {', '.join(map(str, seeds))} (pooled), "
        f"re-planning every 4 of 16 actions; d = simulated inference time in control steps. All arms draw "
        f"the same noise for each (episode, plan). RTC, overlap: the paper's guidance over the whole overlap "
        f"(H − s rows); RTC, execution: only over the rows the new chunk executes (d + s). Success is over the "
        f"episodes of a row's tasks ({'/'.join(map(str, eps))} per task and seed); its run-to-run noise, estimated as the binomial "
        f"standard error at 50 %, and the difference two cells must exceed to be beyond noise (2 standard "
        f"errors of a difference), depend on that count: {noise_text}. Boundary jerk: "
        f"mean |a_k+1 − 2a_k + a_k−1|² over the stencils that span a chunk switch (all four action "
        f"dimensions, gripper included), ± the standard error over episodes of each episode's mean (its "
        f"run-to-run noise). Chunk ms: one state, median over {args.latency_reps} interleaved calls; "
        f"RTC timed at d = {max(delays) if delays else 0} (vector–Jacobian products included).", "",
    ]
    body = ["### Over all tasks", "", *tabulate(rows, delays), "", "### Success per task (%)", "",
            *per_task(rows, delays), ""]
    notes = [NOTES, ""]
    if path.is_file() and NOTES in path.read_text():
        notes = [NOTES + path.read_text().split(NOTES, 1)[1].rstrip("\n"), ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(top + head + body + notes))


def main(argv=None) -> None:
    from action_decoder.config import RTC_DELAY_DISTS, DecoderConfig
    from action_decoder.train import TrainConfig
    from benchmarks.multimodal import Budget

    mm_budget = Budget()
    p = argparse.ArgumentParser(prog="python -m benchmarks rtc", description=__doc__.split("\n\n")[0])
    p.add_argument("--part", choices=["all", "multimodal", "metaworld", "horizons", "latency", "cost", "prefix"],
                   default="all",
                   help="all: multimodal, then metaworld (naive / guided / trained); horizons: the guidance horizons; "
                        "latency: re-time the rows of --multimodal-json and --modes-json; cost: plain against "
                        "trained-RTC chunks at batch 1 on --device, no checkpoints")
    p.add_argument("--device", default="cpu", help="cost part: the torch device (cpu, cuda)")
    p.add_argument("--cost-json", default="docs/benchmarks/rtc_cost.json", help="cost part: rows")
    p.add_argument("--cost-runtimes", nargs="+", default=["eager", "onnxruntime", "compiled"],
                   choices=["eager", "onnxruntime", "compiled"],
                   help="cost part: runtimes timed (onnxruntime on a CPU only)")
    p.add_argument("--tasks", nargs="+", default=TASKS)
    p.add_argument("--delays", nargs="+", type=int, default=None,
                   help="simulated inference delays in control steps (default 0 1 2 4; horizons: 0 2 4)")
    p.add_argument("--settings", nargs="+", default=[f"{d}:{k}" for d, k in SETTINGS],
                   help="decoder:steps pairs among " + ", ".join(f"{d}:{k}" for d, k in SETTINGS))
    p.add_argument("--arms", nargs="+", default=["naive", "guided", "trained"], choices=["naive", "guided", "trained"],
                   help="metaworld part: the arms evaluated")
    p.add_argument("--horizons", nargs="+", default=["overlap", "execution"], choices=["overlap", "execution"],
                   help="horizons part: the RTC arms, rtc_horizon values, each evaluated beside naive switching")
    p.add_argument("--multimodal", nargs="+", default=["synthetic", "obstacle"], choices=["synthetic", "obstacle"],
                   help="multimodal part: the tasks")
    p.add_argument("--mm-train-steps", type=int, default=mm_budget.steps, help="multimodal part: training steps per policy")
    p.add_argument("--mm-hidden-size", type=int, default=mm_budget.hidden,
                   help="multimodal part: hidden size of every policy trained")
    p.add_argument("--mm-num-layers", type=int, default=mm_budget.layers,
                   help="multimodal part: transformer layers of every policy trained")
    p.add_argument("--mm-recipe", nargs="*", default=[], metavar="KEY=VALUE",
                   help="multimodal part: MeanFlow recipe overrides of every policy trained "
                        "(the keys of `python -m benchmarks multimodal --recipe`)")
    p.add_argument("--mm-states", type=int, default=256, help="synthetic: states per cell")
    p.add_argument("--mm-samples", type=int, default=4, help="synthetic: re-plans per state")
    p.add_argument("--mm-episodes", type=int, default=50, help="obstacle routes: episodes per cell")
    p.add_argument("--episodes", type=int, default=None, help="Meta-World episodes per task and cell (default 50; horizons: 20)")
    p.add_argument("--seed", type=int, default=0, help="evaluation seed; rows of several seeds are pooled")
    p.add_argument("--num-envs", type=int, default=10)
    p.add_argument("--latency-reps", type=int, default=30)
    p.add_argument("--rtc-delay-dist", default=DecoderConfig.rtc_delay_dist, choices=list(RTC_DELAY_DISTS),
                   help="metaworld part: the delay distribution of the RTC-trained weights (train --rtc-delay-dist)")
    p.add_argument("--train-steps", type=int, default=TrainConfig.steps,
                   help="metaworld part: optimizer steps of every policy trained (train --steps)")
    p.add_argument("--train-seeds", nargs="+", type=int, default=[TrainConfig.seed],
                   help="metaworld part: training seeds, one policy pair each (train --seed)")
    p.add_argument("--rtc-meanflow-target", default=None, choices=["identity", "split"],
                   help="the MeanFlow target of the RTC-trained weights (train "
                        "--meanflow-target; default: train's, split)")
    p.add_argument("--rtc-perturbed-prefixes", type=int, default=None,
                   help="metaworld part: perturbed-prefix copies of each frame for the RTC-trained weights "
                        "(train --perturbed-prefixes; default: train's)")
    p.add_argument("--rtc-balance-rows", action="store_true",
                   help="the RTC-trained weights weight loss row j by 1/P(d <= j) (train --rtc-balance-rows)")
    p.add_argument("--runs", default="outputs/rtc", help="checkpoints: <runs>/<task>-<decoder>[-rtc4[exp][bal][split][os<share>][pp<copies>]]/final")
    p.add_argument("--json", default="docs/benchmarks/rtc.json", help="horizons part: rows")
    p.add_argument("--multimodal-json", default="docs/benchmarks/rtc_multimodal.json")
    p.add_argument("--modes-json", default="docs/benchmarks/rtc_modes.json")
    p.add_argument("--prefix-json", default="docs/benchmarks/rtc_prefix.json",
                   help="prefix part: rows (trained RTC fed its own demonstrations' prefixes)")
    p.add_argument("--table", default="docs/benchmarks/rtc.md")
    p.add_argument("--page-only", action="store_true", help="rebuild --table from the JSON rows, run nothing")
    p.add_argument("--latency-only", action="store_true",
                   help="re-time the chunks of the rows in --json (same checkpoints), keep their success and jerk")
    args = p.parse_args(argv)
    command = "python -m benchmarks rtc " + " ".join(argv if argv is not None else sys.argv[1:])
    page = lambda rows: write_page(rows, Path(args.table), args,                        # noqa: E731
                                   " ; ".join(sorted({r.get("command", "") for r in rows} - {""}))
                                   or "python -m benchmarks rtc --part horizons")
    if args.latency_only:
        retime(Path(args.json), args)
        args.page_only = True
    if args.part == "cost":
        from benchmarks.rtc_modes import chunk_cost

        args.settings = [(d, int(k)) for d, _, k in (x.partition(":") for x in args.settings)]
        chunk_cost(args, command)
        return
    if args.part == "latency":
        from benchmarks.rtc_modes import retime as retime_modes

        retime_modes(args)
        args.page_only = True
    if args.page_only:
        page(json.loads(Path(args.json).read_text()))
        return
    settings = []
    for s in args.settings:
        decoder, _, steps = s.partition(":")
        if (decoder, int(steps or 0)) not in SETTINGS:
            raise SystemExit(f"--settings: expected decoder:steps among {[f'{d}:{k}' for d, k in SETTINGS]}, got {s!r}")
        settings.append((decoder, int(steps)))
    args.settings = settings
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    out = Path(args.json)
    rows = json.loads(out.read_text()) if out.is_file() else []
    if args.part in ("all", "multimodal"):
        from benchmarks.rtc_modes import run_multimodal

        run_multimodal(args, command)
        page(rows)
    if args.part in ("all", "metaworld"):
        from benchmarks.rtc_modes import row_key as key
        from benchmarks.rtc_modes import run_metaworld

        args.delays = args.delays or [0, 1, 2, 4]
        args.episodes = args.episodes or 50
        for task in args.tasks:
            for decoder, steps in settings:
                merge_rows(Path(args.modes_json), run_metaworld(task, decoder, steps, args, command), key)
                page(rows)
    if args.part == "prefix":
        from benchmarks.rtc_prefix_fit import row_key as key
        from benchmarks.rtc_prefix_fit import run_prefix_fit

        args.delays = args.delays or [0, 1, 2, 4]
        for task in args.tasks:
            for decoder, steps in settings:
                merge_rows(Path(args.prefix_json), run_prefix_fit(task, decoder, steps, args, command), key)
                page(rows)
    if args.part == "horizons":
        args.delays = args.delays or [0, 2, 4]
        args.episodes = args.episodes or 20
        for task in args.tasks:
            for decoder, steps in settings:
                ckpt = train(task, decoder, Path(args.runs))
                new = [{**r, "command": command, "date": time.strftime("%Y-%m-%d")}
                       for r in evaluate_grid(task, ckpt, decoder, steps, args)]
                key = lambda r: (r["task"], r["decoder"], r["steps"], r["delay"], arm(r), r["seed"])  # noqa: E731
                rows = [r for r in rows if key(r) not in {key(n) for n in new}] + new
                out.parent.mkdir(parents=True, exist_ok=True)
                out.write_text(json.dumps(rows, indent=1))
                page(rows)


if __name__ == "__main__":
    main()
