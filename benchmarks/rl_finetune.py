"""RL fine-tuning benchmark: behaviour-clone a policy from 3 demonstrations, then fine-tune it
with `action-decoder finetune` at its defaults under a CPU-time budget, and compare success on
the same 50 evaluation layouts before and after.

    python -m benchmarks.rl_finetune --select --jobs 2        # BC sweep over all 50 tasks: the task set and its split
    python -m benchmarks.rl_finetune --tasks report --jobs 2  # the report half, FM and MF: the table
    python -m benchmarks.rl_finetune --tasks dev --seeds 0 1  # the development half, two fine-tuning seeds
    python -m benchmarks.rl_finetune --tasks metaworld/push --decoders flow_matching --cpu-minutes 10
    python -m benchmarks.rl_finetune --tasks report --algo dsrl --seeds 0 1 --jobs 2   # noise-space RL, two seeds

The task set comes from a rule, not by hand (`select`): every Meta-World task whose 3-demo
flow-matching BC policy succeeds in 15–65 % of 50 evaluation episodes (seed 0). The tasks the
defaults were developed on (`TUNED_ON`) belong to the development half; the others are split by a
hash of their name (`half`), fixed before any run. Each (task, decoder) run lives in its own
directory under --runs (suffixed `_sac` or `_dsrl`); fine-tuning seed s > 0 writes `ft_s{s}`. Finished
steps are skipped, an interrupted fine-tuning resumes, and a run whose row is already in --results
(same task, decoder, algorithm, recipe, seed and budget) is not run again, so the grid can be stopped and
continued, on another machine too; a finished run of a smaller env-step budget is continued to the current one in
its directory (its row at the smaller budget stays in --results). The rows of finished runs are merged into
docs/benchmarks/rl_finetune.json (which keeps rows whose run directories are gone), and the table
and a plot of the learning curves are written from it; text below the table's notes marker is kept.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace

from action_decoder.rl.finetune import RUN_OPTIONS, FinetuneConfig

CLI = [sys.executable, "-m", "action_decoder.cli"]
NOTES = "<!-- notes: kept when the table above is rebuilt -->"
RUN_FIELDS = RUN_OPTIONS | {"task", "algo", "sigma", "seed"}
"""`finetune` options that set a run's budget, identity or logging, not its recipe (σ has its own column)."""
BC_DEMOS, BC_STEPS, CPU_MINUTES = 3, 2000, 45.0
"""The protocol's BC (demonstrations, training steps) and fine-tuning budget (CPU-minutes per run)."""
ENV_STEPS = {"dsrl": 200_000}
"""Environment steps per run where the protocol caps them (DSRL, `finetune`'s default); the others stop at the
CPU budget."""
UNCAPPED = 10_000_000
"""The env-step budget of the algorithms the protocol caps by CPU time alone."""
BAND = (0.15, 0.65)
"""The rule's band of 3-demo BC success (flow matching, K = 10, 50 episodes): room to gain, and a
policy that succeeds often enough for its rollouts to carry a signal."""
TUNED_ON = ("door-lock-v3", "push-v3", "push-wall-v3", "reach-v3", "reach-wall-v3", "sweep-into-v3")
"""Tasks `finetune`'s defaults were developed on: development half whatever their hash."""
RULE_DECODER = "flow_matching"


def half(task: str) -> str:
    """"dev" or "report": `TUNED_ON` tasks are dev; the others by the parity of sha256(name)."""
    if task in TUNED_ON:
        return "dev"
    return "report" if int(hashlib.sha256(task.encode()).hexdigest(), 16) % 2 else "dev"


def split(bc: dict[str, float], band: tuple[float, float] = BAND) -> dict:
    """The task set of the protocol from 3-demo BC success per task: the in-band tasks, by half."""
    chosen = sorted(t for t, rate in bc.items() if band[0] <= rate <= band[1])
    return {"band": list(band), "bc": dict(sorted(bc.items())),
            "dev": [t for t in chosen if half(t) == "dev"], "report": [t for t in chosen if half(t) == "report"]}


def select(args) -> dict:
    """BC-train and evaluate every Meta-World task with the benchmark's recipe, then `split`; the
    BC policies are those the fine-tuning runs start from."""
    from action_decoder.envs.metaworld_tasks import all_tasks

    tasks = sorted(all_tasks())
    with ThreadPoolExecutor(args.jobs) as pool:
        runs = list(pool.map(lambda t: train_bc(f"metaworld/{t}", RULE_DECODER, args), tasks))
    bc = {t: json.loads((run / "bc_eval.json").read_text())["success_rate"] for t, run in zip(tasks, runs)}
    chosen = split(bc)
    Path(args.task_set).parent.mkdir(parents=True, exist_ok=True)
    Path(args.task_set).write_text(json.dumps(chosen, indent=1) + "\n")
    return chosen


def resolve_task_spec(spec: str, task_set: Path) -> list[str]:
    """`dev` or `report` (a half of the selected task set), else a Meta-World task spec."""
    if spec in ("dev", "report"):
        if not task_set.is_file():
            raise SystemExit(f"--tasks {spec}: expected the task set {task_set} (run --select first), "
                             f"got no such file")
        return json.loads(task_set.read_text())[spec]
    from action_decoder.envs import resolve_tasks

    return resolve_tasks(spec)


def _run(cmd: list[str], log: Path) -> None:
    with open(log, "a") as fh:
        fh.write("$ " + " ".join(cmd) + "\n")
        fh.flush()
        subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})


def env_budget(algo: str) -> int:
    """The env steps a run of `algo` is given (`ENV_STEPS`)."""
    return ENV_STEPS.get(algo, UNCAPPED)


def _stale(evaluation: Path, checkpoint: Path) -> bool:
    """Whether `evaluation` is missing or older than the weights in `checkpoint` (a continued run's)."""
    weights = checkpoint / "model.safetensors"
    return not evaluation.is_file() or (weights.is_file() and evaluation.stat().st_mtime < weights.stat().st_mtime)


def _eval(checkpoint: Path, out: Path, sampler: str, args, log: Path, steps: int = 0) -> None:
    if _stale(out, checkpoint):
        _run([*CLI, "eval", "--checkpoint", str(checkpoint), "--episodes", str(args.episodes), "--sampler", sampler,
              "--seed", "0", "--output", str(out), *(["--steps", str(steps)] if steps else [])], log)


def planned_config(finetune_args: list[str], algo: str = "ppo"):
    """The `FinetuneConfig` these extra `finetune` options give `algo` (any spelling `finetune` accepts)."""
    import tyro
    from action_decoder.rl.finetune import FinetuneConfig

    return tyro.cli(FinetuneConfig, args=["--checkpoint", "-", "--algo", algo, *finetune_args])


def ft_dir_name(finetune_args: list[str], seed: int, algo: str = "ppo") -> str:
    """The fine-tuning's directory in a (task, decoder) run: `ft` for the defaults, plus the recipe and σ
    where they differ (`ft_lr_warmup_updates-20`) and the seed (`_s1`), so that a recipe never resumes another's run."""
    from action_decoder.rl.finetune import FinetuneConfig

    cfg = planned_config(finetune_args, algo)
    how = recipe(dataclasses.asdict(cfg))
    parts = ["ft", *([how.replace(", ", "_").replace("=", "-")] if how != "defaults" else []),
             *([f"sigma-{cfg.sigma:g}"] if cfg.sigma != FinetuneConfig.sigma else []), *([f"s{seed}"] if seed else [])]
    return "_".join(parts)


def run_dir(task: str, decoder: str, args) -> Path:
    """`<runs>/<task>_<decoder>[_<algo>][_demos-N][_bc-steps-N]`: a BC policy of other settings is never reused."""
    bc = (f"_demos-{args.demos}" if args.demos != BC_DEMOS else "") + \
        (f"_bc-steps-{args.bc_steps}" if args.bc_steps != BC_STEPS else "")
    return Path(args.runs) / f"{task.split('/')[-1]}_{decoder}{'' if args.algo == 'ppo' else '_' + args.algo}{bc}"


def train_bc(task: str, decoder: str, args) -> Path:
    """The BC policy of (task, decoder) and its 50-episode ODE evaluation; returns the run directory."""
    run = run_dir(task, decoder, args)
    run.mkdir(parents=True, exist_ok=True)
    log, bc = run / "log.txt", run / "bc"
    if not (bc / "final" / "model.safetensors").is_file():
        resume = ["--resume"] if (bc / "checkpoints" / "last").is_file() else []
        _run([*CLI, "train", "--task", task, "--decoder", decoder, "--demos", str(args.demos), "--steps",
              str(args.bc_steps), "--hidden-size", "64", "--num-layers", "2", "--seed", "0", "--output-dir", str(bc),
              "--n-action-steps", "8",    # the recipe the RL table was measured with: 8 actions per decision
              "--eval-episodes", "0", "--no-progress", *resume], log)
    _eval(bc / "final", run / "bc_eval.json", "ode", args, log)
    return run


def run_one(task: str, decoder: str, seed: int, args) -> None:
    run = train_bc(task, decoder, args)
    log, bc = run / "log.txt", run / "bc"
    ft = run / ft_dir_name(args.finetune_args, seed, args.algo)
    suffix = ft.name[2:]
    # The fine-tuned policy samples with K = --sde-steps (DSRL: the decoder's own K, or --steps); MeanFlow's
    # BC default is K = 1, so the BC policy is also measured at that K, the sampler and K the gain compares.
    planned = planned_config(args.finetune_args, args.algo)
    k = (planned.steps or json.loads((run / "bc_eval.json").read_text())["steps"]) if args.algo == "dsrl" \
        else planned.sde_steps
    if json.loads((run / "bc_eval.json").read_text())["steps"] != k:
        _eval(bc / "final", run / f"bc_eval_k{k}.json", "ode", args, log, steps=k)
    if (ft / "finetune_log.json").is_file():
        budget = json.loads((ft / "finetune_log.json").read_text())["config"].get("max_cpu_minutes")
        if budget != args.cpu_minutes:
            raise SystemExit(f"--cpu-minutes: {ft} finished a run of {budget} CPU-minutes, not {args.cpu_minutes}; "
                             f"pass --runs another directory to measure another budget")
    smaller = (ft / "finetune_log.json").is_file() and \
        json.loads((ft / "finetune_log.json").read_text())["config"]["env_steps"] < env_budget(args.algo)
    if smaller or not (ft / "final" / "model.safetensors").is_file():      # smaller: continued to the budget
        resume = ["--resume"] if (ft / "checkpoints" / "last").is_file() else []
        _run([*CLI, "finetune", "--checkpoint", str(bc / "final"), "--output-dir", str(ft), "--algo", args.algo,
              "--env-steps", str(env_budget(args.algo)), "--max-cpu-minutes", str(args.cpu_minutes), "--eval-every", "10",
              "--seed", str(seed), *args.finetune_args, *resume], log)
    if args.algo != "dsrl":         # DSRL's policy is the noise actor's mean through the deterministic sampler
        _eval(ft / "final", run / f"ft_eval_sde{suffix}.json", "sde", args, log)
    _eval(ft / "final", run / f"ft_eval_ode{suffix}.json", "ode", args, log)


def _gain(r: dict) -> float:
    """Points gained: the fine-tuned policy's ODE success over the BC policy's at the fine-tuning's K, one
    sampler and one K fixed in advance, so that only the weights differ (a better-of-two on either side
    would add the noise of a maximum)."""
    return round(100 * (r["ft_ode"] - r["bc_at_ft_k"]), 6) + 0.0        # + 0.0: no "-0" for equal rates


def recipe(config: dict) -> str:
    """The `finetune` options a run set away from `FinetuneConfig`'s defaults ("k=v, …"), or
    "defaults"; options a run's config does not record had their default."""
    from action_decoder.rl.finetune import ALGO_DEFAULTS, CRITIC_WARMUP_ITERS, FinetuneConfig, episodes_per_layout

    base = {f.name: f.default for f in dataclasses.fields(FinetuneConfig) if f.name not in RUN_FIELDS}
    config = dict(config)
    for name, by_algo in ALGO_DEFAULTS.items():       # an algorithm's default, None in the config or spelt out
        if config.get(name) == by_algo.get(config.get("algo", "ppo")):
            config[name] = None
    # episodes per layout: None is the algorithm's default (4 with PPO), which logs may also spell out
    group = episodes_per_layout(SimpleNamespace(group_size=config.pop("group_size", None),
                                                algo=config.get("algo", "ppo")))
    if group != episodes_per_layout(SimpleNamespace(group_size=None, algo=config.get("algo", "ppo"))):
        config["group_size"] = group
    warmup = config.pop("critic_warmup_iters", None)      # acts only with a critic (group size 1)
    if group == 1 and warmup not in (None, CRITIC_WARMUP_ITERS.get(config.get("algo", "ppo"))):
        config["critic_warmup_iters"] = warmup
    changed = [f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
               for k, v in sorted(config.items()) if k in base and v != base[k]]
    return ", ".join(changed) or "defaults"


EARLY_ITERS = 20
"""The early phase of a run, where the first Adam steps are largest: its first 20 iterations (128k env steps
at 32 envs × 200 steps)."""


def _updates(h: dict, minibatch_size: int) -> int | None:
    """Policy updates an iteration took: logged as `updates`; in logs without it, one where the iteration
    stopped in its first epoch with two minibatches (the first measured before any update, the second
    after it), else unknown (None)."""
    if "updates" in h:
        return h["updates"]
    two = minibatch_size < h.get("decisions", 0) <= 2 * minibatch_size
    return 1 if two and h.get("epochs") == 1 else None


def early_phase(history: list[dict], minibatch_size: int) -> dict:
    """How far and how fast a PPO run moved over its first `EARLY_ITERS` iterations: the approximate KL of
    its first update (logged as `approx_kl_first_update`; in logs without it, twice iteration 1's mean
    `approx_kl` when that iteration stopped after its first update with two minibatches, the first
    measured before any update), the iterations among them that stopped after one update, KL to BC at
    iterations 10 and 20, and training success over iterations 1–10 and 11–20."""
    first, head = history[0], history[:EARLY_ITERS]
    kl = first.get("approx_kl_first_update")
    if kl is None and _updates(first, minibatch_size) == 1 and "updates" not in first:
        kl = 2 * first["approx_kl"]
    at = {h["iteration"]: h for h in head}
    mean = lambda hs: round(sum(h["success"] for h in hs) / len(hs), 3) if hs else None   # noqa: E731
    return {"first_update_kl": None if kl is None else round(kl, 3),
            "one_update_iters": sum(_updates(h, minibatch_size) == 1 for h in head),
            "kl_bc_it10": round(at[10]["kl_bc"], 2) if 10 in at else None,
            "kl_bc_it20": round(at[20]["kl_bc"], 2) if 20 in at else None,
            "train_success_it1_10": mean(head[:10]), "train_success_it11_20": mean(head[10:20])}


def collect(runs: Path) -> list[dict]:
    """One row per finished fine-tuning under `runs` (each seed its own): success before/after,
    training success at the end of the run, and the evaluation curve."""
    rows = []
    for run in sorted(p for p in runs.iterdir() if (p / "bc_eval.json").is_file()):
        for ft in sorted(d for d in run.glob("ft*") if d.is_dir()):     # ft, ft_s1, …
            suffix = ft.name[2:]
            if _stale(run / f"ft_eval_ode{suffix}.json", ft / "final"):
                continue
            bc = json.loads((run / "bc_eval.json").read_text())
            ft_k = json.loads((run / f"ft_eval_ode{suffix}.json").read_text())["steps"]
            at_k = run / f"bc_eval_k{ft_k}.json"
            bc_at_k = json.loads(at_k.read_text()) if at_k.is_file() else bc
            sde_file = run / f"ft_eval_sde{suffix}.json"
            sde = json.loads(sde_file.read_text()) if sde_file.is_file() else {"success_rate": None}
            ode = json.loads((run / f"ft_eval_ode{suffix}.json").read_text())
            log = json.loads((ft / "finetune_log.json").read_text())
            hist, last = log["history"], log["history"][-1]
            cpu = {h["iteration"]: h.get("cpu_s", h["wall_s"]) / 60 for h in hist}
            tail = hist[-10:]
            bc_config = run / "bc" / "final" / "config.json"
            trained = json.loads(bc_config.read_text())["extra"].get("train", {}) if bc_config.is_file() else {}
            rows.append({"task": log["task"], "decoder": bc["decoder_type"], "algo": log["config"]["algo"],
                         # σ scales the chain methods' SDE; DSRL's policy has none
                         "sigma": None if log["config"]["algo"] == "dsrl" else log["config"].get("sigma"),
                         "recipe": recipe(log["config"]),
                         "cpu_budget": log["config"].get("max_cpu_minutes"), "env_budget": log["config"].get("env_steps"),
                         "bc_demos": trained.get("demos"),
                         "bc_train_steps": trained.get("steps"),
                         "seed": log["config"].get("seed", 0), "half": half(log["task"]),
                         "bc": bc["success_rate"], "bc_steps": bc["steps"], "bc_at_ft_k": bc_at_k["success_rate"],
                         "ft_k": ft_k, "ft_sde": sde["success_rate"], "ft_ode": ode["success_rate"],
                         # training episodes (SDE, fresh layouts, `--max-episode-steps`) of the last 10 iterations
                         "train_success_last10": round(sum(h["success"] for h in tail) / len(tail), 3),
                         "kl_bc_last": round(last["kl_bc"], 2) if "kl_bc" in last else None,
                         "cpu_min": round(last.get("cpu_s", last["wall_s"]) / 60, 2), "env_steps": last["env_steps"],
                         "early": early_phase(hist, log["config"].get("minibatch_size", 512))
                         if log["config"]["algo"] == "ppo" else None,
                         "measured": time.strftime("%Y-%m-%d", time.gmtime((run / f"ft_eval_ode{suffix}.json").stat().st_mtime)),
                         # (CPU minutes, SDE success (None: DSRL), ODE success, env steps) at each evaluation
                         "curve": [[round(cpu.get(e["iteration"], 0.0), 2), e.get("success_sde"), e["success_ode"],
                                    e["env_steps"]] for e in log["evals"]]})
    return rows


def _key(r: dict) -> tuple:
    """A run's identity: what it fine-tuned, how (recipe, σ, budgets) and from which BC policy; rows
    recorded before a field had the protocol's value."""
    return (r["task"], r["decoder"], r["algo"], r.get("recipe", "defaults"), r.get("seed", 0),
            float(r.get("sigma") or FinetuneConfig.sigma), float(r.get("cpu_budget") or CPU_MINUTES),
            int(r.get("bc_demos") or BC_DEMOS), int(r.get("bc_train_steps") or BC_STEPS),
            int(r.get("env_budget") or env_budget(r["algo"])))


def planned_recipe(finetune_args: list[str], algo: str = "ppo") -> str:
    """The recipe (`recipe`) of the runs these extra `finetune` options start with `algo`."""
    return recipe(dataclasses.asdict(planned_config(finetune_args, algo)))


def recorded(results: Path) -> set[tuple]:
    """Keys (`_key`) of the runs whose rows `results` already holds."""
    return {_key(r) for r in json.loads(results.read_text())} if results.is_file() else set()


def merge(results: Path, rows: list[dict]) -> list[dict]:
    """Rows kept in `results` from earlier runs, replaced by this run directory's rows for the same
    (task, decoder, algo, recipe, seed); written back so that tables and plots can be rebuilt from every run kept."""
    kept = {_key(r): r for r in (json.loads(results.read_text()) if results.is_file() else [])}
    kept.update({_key(r): r for r in rows})
    merged = sorted(kept.values(), key=lambda r: (half(r["task"]), *_key(r)))
    results.parent.mkdir(parents=True, exist_ok=True)
    results.write_text("[\n" + ",\n".join(json.dumps(r) for r in merged) + "\n]\n")  # a row per line: diffs by row
    return merged


def _changed(r: dict) -> str:
    """A row's recipe when it differs from the defaults, else "" (rows from before the field: defaults)."""
    return "" if r.get("recipe", "defaults") == "defaults" else r["recipe"]


def _how(r: dict) -> str:
    """The algorithm, σ scale, recipe and an env-step budget other than the protocol's of a row: "ppo",
    "ppo, a = 0.25", "ppo, a = 0.25, lr_schedule=adaptive", "dsrl, env_steps=100000"."""
    how = r["algo"] if r.get("sigma") is None else f"{r['algo']}, a = {r['sigma']:g}"
    how = f"{how}, {_changed(r)}" if _changed(r) else how
    budget = int(r.get("env_budget") or env_budget(r["algo"]))
    return how if budget == env_budget(r["algo"]) else f"{how}, env_steps={budget}"


def _num(r: dict, key: str, scale: float, fmt: str) -> str:
    """A table cell; "–" for rows recorded before the column existed."""
    return "–" if r.get(key) is None else format(scale * r[key], fmt)


GAIN_MARK = 15.0
"""The mean gain (points) whose first crossing in environment steps measures sample efficiency."""
SEED_SPREAD = 20.0
"""Points two fine-tuning seeds of a task may differ by and count as agreeing (the reliability count)."""
PPO_ITERATION_STEPS, PPO_EVAL_EVERY = 32 * 200, 10
"""PPO's default iteration (32 envs × the 200-step cap; dense rewards run every episode to the cap) and the
benchmark's `--eval-every`: rows recorded without env steps in their curve had their evaluations there."""


def curve_steps(r: dict) -> list[tuple[int, float]]:
    """(env steps, ODE success) at each evaluation during a run. Curves recorded before they kept env steps
    (default-recipe PPO rows) evaluated at iterations 0, 10, 20, … and at the last one: their env steps follow."""
    pts = []
    for i, c in enumerate(r.get("curve") or []):
        if len(c) > 3:
            pts.append((int(c[3]), c[2]))
        elif r["algo"] == "ppo" and r.get("recipe", "defaults") == "defaults":
            last = i == len(r["curve"]) - 1
            pts.append((r["env_steps"] if last else i * PPO_EVAL_EVERY * PPO_ITERATION_STEPS, c[2]))
    return pts


def steps_to_mean_gain(rows: list[dict], mark: float = GAIN_MARK) -> int | None:
    """The fewest env steps at which the mean over `rows` of each run's latest evaluated gain (ODE success
    during the run minus BC's at the fine-tuning's K, in points) reaches `mark`; None if it never does."""
    curves = [curve_steps(r) for r in rows]
    if not curves or not all(curves):
        return None
    for x in sorted({x for c in curves for x, _ in c}):
        latest = [next((100 * (ok - r["bc_at_ft_k"]) for at, ok in reversed(c) if at <= x), None)
                  for r, c in zip(rows, curves)]
        if None not in latest and sum(latest) / len(latest) >= mark:
            return x
    return None


def sample_efficiency(rows: list[dict]) -> list[str]:
    """Per (half, decoder): each algorithm's env steps to a mean gain of +15 with its defaults (PPO: the
    protocol's σ scale), over the tasks every such algorithm ran, fastest first with the others' ratio to it."""
    by: dict = {}
    for r in rows:
        if r.get("recipe", "defaults") == "defaults":
            by.setdefault((half(r["task"]), r["decoder"]), {}).setdefault(_how(r), []).append(r)
    lines = []
    for (h, dec), algos in sorted(by.items()):
        common = set.intersection(*({r["task"] for r in rs} for rs in algos.values()))
        if len(algos) < 2 or not common:
            continue
        marks = []
        for how, rs in algos.items():
            rs = [r for r in rs if r["task"] in common]
            if not all(curve_steps(r) for r in rs):
                break
            marks.append((how, steps_to_mean_gain(rs), max(r["env_steps"] for r in rs)))
        hit = [(how, x) for how, x, _ in marks if x is not None]
        if len(marks) < len(algos) or not hit:
            continue
        best_how, best = min(hit, key=lambda m: m[1])
        others = [f"{how} " + (f"{x} ({x / best:.1f}×)" if x is not None else
                               f"never within {most} ({math.floor(10 * most / best) / 10:g}× or more)")
                  for how, x, most in marks if how != best_how]
        lines.append(f"- {h} half, {dec}, defaults over the {len(common)} task(s) both ran: env steps to a mean gain "
                     f"of +{GAIN_MARK:g}: {best_how} {best}; " + "; ".join(others))
    return lines


def summary(rows: list[dict]) -> list[str]:
    """Mean gain per (half, decoder, algo, recipe) over seed-0 rows and over every seed, the runs that end
    more than 5 points below BC, the tasks whose seeds agree within `SEED_SPREAD`, the env steps to a mean
    gain of +15 (and `sample_efficiency`'s comparison), and the seed-to-seed spread where a (task, decoder,
    recipe) ran with several fine-tuning seeds."""
    lines, groups, seeds, every = [], {}, {}, {}
    for r in rows:
        how = _how(r)
        if r.get("seed", 0) == 0:
            groups.setdefault((half(r["task"]), r["decoder"], how), []).append(_gain(r))
        seeds.setdefault((r["task"], r["decoder"], how), []).append(_gain(r))
        every.setdefault((half(r["task"]), r["decoder"], how), []).append(r)
    for (h, dec, how), gains in sorted(groups.items()):
        lines.append(f"- {h} half, {dec} ({how}): mean gain {sum(gains) / len(gains):+.1f} points over "
                     f"{len(gains)} task(s) (seed 0)")
    for (h, dec, how), rs in sorted(every.items()):
        gains = [_gain(r) for r in rs]
        to_mark = steps_to_mean_gain(rs)
        when = f"first reached at {to_mark} env steps" if to_mark is not None else \
            "never reached in the runs' evaluations" if all(curve_steps(r) for r in rs) else \
            "not known (evaluations recorded without env steps)"
        paired = [g for (t, d, w), g in seeds.items() if (half(t), d, w) == (h, dec, how) and len(g) > 1]
        close = (f"; the seeds of {sum(max(g) - min(g) <= SEED_SPREAD for g in paired)} of {len(paired)} task(s) "
                 f"within {SEED_SPREAD:g} points" if paired else "")
        lines.append(f"- {h} half, {dec} ({how}), every seed: mean gain {sum(gains) / len(gains):+.1f} points over "
                     f"{len(rs)} run(s); {sum(g < -5 for g in gains)} end more than 5 points below BC{close}; mean gain "
                     f"+{GAIN_MARK:g} {when}")
    lines += sample_efficiency(rows)
    spread = [(k, g) for k, g in sorted(seeds.items()) if len(g) > 1]
    for (task, dec, how), gains in spread:
        lines.append(f"- noise: {task} {dec} ({how}) gains over fine-tuning seeds: "
                     + ", ".join(f"{g:+.0f}" for g in gains) + f" (range {max(gains) - min(gains):.0f} points)")
    return lines


def task_set_text(task_set: dict, args) -> str:
    """The rule, the split and every task's BC success, from the task set `select` wrote."""
    lo, hi = (round(100 * b) for b in task_set["band"])
    bc = task_set["bc"]
    below = sorted(t for t, r in bc.items() if r < task_set["band"][0])
    above = sorted(t for t, r in bc.items() if r > task_set["band"][1])
    rows = [f"| {t} | {100 * bc[t]:.0f} | {h} |" for h in ("dev", "report") for t in task_set[h]]
    return (f"Task set (`{args.task_set}`): every Meta-World task whose 3-demo flow-matching BC policy (K = 10) "
            f"succeeds in {lo}–{hi} % of {args.episodes} evaluation episodes, seed 0 — {len(rows)} of {len(bc)} tasks. "
            f"Development half: the tasks the defaults were developed on ({', '.join(TUNED_ON)}) and the in-band "
            "tasks whose name's sha256 is even; report half: the others, run once with the final defaults.\n\n"
            "| task | BC success, % | half |\n|---|---:|---|\n" + "\n".join(rows) + "\n\n"
            f"Below the band ({len(below)}): " + (", ".join(f"{t} {100 * bc[t]:.0f}" for t in below) or "none") + ". "
            f"Above it ({len(above)}): " + (", ".join(f"{t} {100 * bc[t]:.0f}" for t in above) or "none") + ".\n\n")


def write_report(rows: list[dict], table: Path, plot: Path, args, task_set: dict | None = None) -> str:
    lines = ["| half | task | decoder | algo, σ scale, options other than the defaults | seed | BC (ODE, default K) | BC (ODE, fine-tuning's K) | fine-tuned (SDE) | "
             "fine-tuned (ODE) | gain (ODE, fine-tuning's K) | training success, last 10 it. | KL to BC | CPU min | "
             "env steps | measured |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {half(r['task'])} | {r['task']} | {r['decoder']} | {_how(r)} | {r.get('seed', 0)} | "
                     f"{100 * r['bc']:.0f} (K={r['bc_steps']}) | {100 * r['bc_at_ft_k']:.0f} (K={r['ft_k']}) | "
                     f"{_num(r, 'ft_sde', 100, '.0f')} | {100 * r['ft_ode']:.0f} | {_gain(r):+.0f} | "
                     f"{_num(r, 'train_success_last10', 100, '.0f')} | {_num(r, 'kl_bc_last', 1, '.1f')} | "
                     f"{r['cpu_min']:.0f} | {r['env_steps']} | {r['measured']} |")
    early, early_lines = [r for r in rows if r.get("early")], []
    if early:
        early_lines = [f"Early phase, first {EARLY_ITERS} iterations (`early_phase`):", "",
                       "| half | task | decoder | recipe | seed | KL of the first update | iterations of one update | "
                       "KL to BC, it. 10 / 20 | training success, it. 1–10 / 11–20 | gain |",
                       "|---|---|---|---|---:|---:|---:|---|---|---:|"]
        for r in early:
            e = r["early"]
            cells = [" / ".join("–" if e[k] is None else format(e[k], fmt) for k in keys)
                     for keys, fmt in ((("first_update_kl",), ".2g"), (("kl_bc_it10", "kl_bc_it20"), ".1f"),
                                       (("train_success_it1_10", "train_success_it11_20"), ".2f"))]
            early_lines.append(f"| {half(r['task'])} | {r['task']} | {r['decoder']} | {_changed(r) or 'defaults'} | "
                               f"{r.get('seed', 0)} | {cells[0]} | {e['one_update_iters']} | {cells[1]} | {cells[2]} | "
                               f"{_gain(r):+.0f} |")
    chosen = task_set_text(task_set, args) if task_set else ""
    text = (f"Success in % on the same {args.episodes} evaluation layouts (seed 0) before and after fine-tuning; "
            f"BC from {args.demos} demonstrations (Action Expert hidden 64, 2 layers, {args.bc_steps} steps). "
            "Training success: the fine-tuning's own episodes (SDE, fresh layouts, 200-step cap) over its last "
            "10 iterations.\n\n" + chosen
            + "\n".join(lines) + "\n\n" + "\n".join(summary(rows)) + ("\n\n" if rows else "")
            + "\n".join(early_lines) + ("\n\n" if early_lines else "")
            + f"Rebuilt by `python -m benchmarks.rl_finetune` from `{args.results}`; the plot `{plot.name}` holds the "
            "learning curves.\n")
    table.parent.mkdir(parents=True, exist_ok=True)
    notes = table.read_text().partition(NOTES)[2] if table.is_file() else ""
    table.write_text(text + f"\n{NOTES}" + (notes or "\n"))   # the hand-written part below the table stays
    panels: dict = {}                       # (task, decoder) -> its runs: every algorithm and seed on one plot
    for r in rows:
        if curve_steps(r):
            panels.setdefault((r["task"], r["decoder"]), []).append(r)
    if panels:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        cols = min(len(panels), 4)
        n_rows = -(-len(panels) // cols)
        fig, axes = plt.subplots(n_rows, cols, figsize=(3.6 * cols, 3.2 * n_rows), squeeze=False)
        for ax, ((task, dec), rs) in zip(axes.flat, sorted(panels.items())):
            for r in rs:
                steps, ode = zip(*curve_steps(r))
                ax.plot([x / 1000 for x in steps], ode, marker="o", ms=3, label=f"{_how(r)} s{r.get('seed', 0)}")
            ax.axhline(rs[0]["bc_at_ft_k"], color="gray", ls="--", label=f"BC (K={rs[0]['ft_k']}), {args.episodes} ep.")
            ax.set(title=f"{task} {dec}", xlabel="thousands of env steps", ylabel="success (evaluations during the run)",
                   ylim=(-0.02, 1.02), xlim=(0, None))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=5)
        for ax in list(axes.flat)[len(panels):]:
            ax.axis("off")
        fig.tight_layout()
        fig.savefig(plot, dpi=110)
        plt.close(fig)
    return text


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--select", action="store_true",
                   help="BC-train and evaluate every task, write the task set (--task-set) and stop")
    p.add_argument("--tasks", default="report",
                   help="'report' or 'dev' (a half of the task set), or Meta-World task names")
    p.add_argument("--decoders", nargs="+", default=["flow_matching", "mean_flow"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0], help="fine-tuning seeds (the BC policy is shared)")
    p.add_argument("--algo", default="ppo", choices=["ppo", "sac", "dsrl"])
    p.add_argument("--demos", type=int, default=BC_DEMOS)
    p.add_argument("--bc-steps", type=int, default=BC_STEPS)
    p.add_argument("--cpu-minutes", type=float, default=CPU_MINUTES)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--jobs", type=int, default=1, help="runs in parallel (one core each)")
    p.add_argument("--runs", default="runs/rl_finetune")
    p.add_argument("--task-set", default="docs/benchmarks/rl_tasks.json", help="written by --select")
    p.add_argument("--table", default="docs/benchmarks/rl_finetune.md")
    p.add_argument("--plot", default="docs/benchmarks/rl_finetune.png")
    p.add_argument("--results", default="docs/benchmarks/rl_finetune.json",
                   help="rows of earlier runs, merged with this run directory's and written back")
    p.add_argument("--report-only", action="store_true", help="rebuild the table and plot, run nothing")
    p.add_argument("finetune_args", nargs=argparse.REMAINDER, help="extra `finetune` options after --")
    args = p.parse_args(argv)
    args.finetune_args = [a for a in args.finetune_args if a != "--"]
    task_set = Path(args.task_set)
    if args.select:
        chosen = select(args)
        print(f"development half: {chosen['dev']}\nreport half: {chosen['report']}")
        return
    grid = [] if args.report_only else [(f"metaworld/{t}", d, s) for t in resolve_task_spec(args.tasks, task_set)
                                        for d in args.decoders for s in args.seeds]
    if grid:
        done, how = recorded(Path(args.results)), planned_recipe(args.finetune_args, args.algo)
        sigma = planned_config(args.finetune_args, args.algo).sigma
        skipped = [(t, d, s) for t, d, s in grid
                   if (t.split("/")[-1], d, args.algo, how, s, float(sigma), float(args.cpu_minutes), args.demos,
                       args.bc_steps, env_budget(args.algo)) in done]
        for task, dec, seed in skipped:
            print(f"{task} {dec} seed {seed}: recorded in {args.results}; delete its row to run it again")
        grid = [job for job in grid if job not in skipped]
    with ThreadPoolExecutor(args.jobs) as pool:
        # every BC policy first: the seeds of one (task, decoder) share it, and two jobs must not train it at once
        for fut in [pool.submit(train_bc, t, d, args) for t, d in dict.fromkeys((t, d) for t, d, _ in grid)]:
            fut.result()
        for fut in [pool.submit(run_one, *job, args) for job in grid]:
            fut.result()
    rows = merge(Path(args.results), collect(Path(args.runs))) if Path(args.runs).is_dir() else \
        merge(Path(args.results), [])
    chosen = json.loads(task_set.read_text()) if task_set.is_file() else None
    print(write_report(rows, Path(args.table), Path(args.plot), args, chosen))


if __name__ == "__main__":
    main()
