"""Real-time chunking modes: naive switching, guidance (`rtc_mode="guided"`) and training-time RTC
(`rtc_mode="trained"`), on multimodal chunks and on Meta-World. Run through `python -m benchmarks rtc`.

Every new chunk is planned while the robot executes the old chunk's next d actions (d = delay) and
takes over after them; a new plan starts every s = 4 of H = 16 actions. Arms:
naive: the new chunk, sampled without the old one, takes over after the d old actions;
guided: `flows/rtc.py` on weights trained without RTC (FM: ΠGDM guidance over the overlap; MeanFlow:
  the J = I pull over the executed rows, an output blend at K = 1);
trained: the d committed actions fed in clean at t = 1 (`flows/rtc_trained.py`) on weights trained with
  rtc_max_delay = 4 (delays drawn by `--rtc-delay-dist`, `DecoderConfig.rtc_delay_dist`).
naive and guided use the weights trained without RTC; trained uses the RTC-trained ones.

(a) synthetic two-route chunks (`benchmarks.multimodal.routes`): for each state the committed plan is one
    route A (drawn 50/50); prev_chunk is route A over the new chunk's steps, and the executed rows
    d..d+s−1 of the new chunk keep the route when they are nearer A than B and within a quarter of the
    A–B distance of A (RMS over those rows). Jerk: mean |c_k+1 − 2c_k + c_k−1|² over the two stencils
    around the switch, c being the executed sequence (route A before the switch, the new chunk after).
(b) obstacle routes, closed loop (`envs.obstacle_routes`): at each re-plan before the point passes the
    obstacle, the side (above/below) of the positions the old chunk planned for the new chunk's executed
    rows against the side of the positions actually planned (the d old actions, then the new chunk's);
    success, collisions, and the boundary jerk of the executed actions.
Latency: batch 1, median CPU time over interleaved plain and RTC calls of the same weights.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import platform
import statistics
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from action_decoder.train import TrainConfig

S, H = 4, 16                                   # actions executed per chunk, chunk length
DELAYS = (0, 1, 2, 4)
MAX_DELAY = 4                                  # rtc_max_delay of the RTC-trained weights
SETTINGS = (("flow_matching", 10), ("mean_flow", 1), ("mean_flow", 2))
LABEL = {("flow_matching", 10): "FM K=10", ("mean_flow", 1): "MF K=1", ("mean_flow", 2): "MF K=2"}
ARMS = ("naive", "guided", "trained")


# ----------------------------------------------------------------------------------------- shared
def chunk(policy, state: torch.Tensor, steps: int, arm: str, prev, delay: int, generator) -> torch.Tensor:
    """One chunk per state [B, H, D] for an arm; prev [B, L, D] or None (an episode's first plan)."""
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")          # the 1-step MeanFlow blend warning: the arm is measured
        if arm == "naive" or prev is None:
            return policy.sample({"state": state}, steps=steps, generator=generator).actions
        return policy.sample({"state": state}, steps=steps, generator=generator, prev_chunk=prev, delay=delay,
                             rtc_mode=arm).actions


def latency_ms(policy, steps: int, arm: str, reps: int) -> tuple[float, float]:
    """(plain, arm) median ms of one chunk for one state, interleaved, the arm at the largest delay: the
    process's CPU time (one torch thread), which a shared machine's other processes do not inflate."""
    cfg = policy.config
    state = torch.zeros(1, cfg.state_dim)
    prev = torch.zeros(1, H - S, cfg.action_dim)
    times = {"plain": [], "arm": []}
    for rep in range(reps + 3):
        for name, a in (("plain", "naive"), ("arm", arm)):
            t0 = time.process_time()
            chunk(policy, state, steps, a, prev, MAX_DELAY, torch.Generator().manual_seed(rep))
            if rep >= 3:
                times[name].append(time.process_time() - t0)
    return 1000 * statistics.median(times["plain"]), 1000 * statistics.median(times["arm"])


def retime(args) -> None:
    """Re-measure the latency of every row of --multimodal-json and --modes-json at its largest delay."""
    from action_decoder import ActionDecoderPolicy

    for path in (Path(args.multimodal_json), Path(args.modes_json)):
        if not path.is_file():
            continue
        rows = json.loads(path.read_text())
        for r in rows:
            if r.get("latency_ms") is None:
                continue
            if "checkpoint" in r:
                ckpt = r["checkpoint"]
            else:
                suffix = rtc_suffix(MAX_DELAY, r.get("rtc_delay_dist") or "uniform", bool(r.get("rtc_balance_rows"))) \
                    if r["arm"] == "trained" else ""
                ckpt = Path(args.runs) / "multimodal" / f"{r['task']}-{r['decoder']}{suffix}-seed{r['seed']}"
            policy = ActionDecoderPolicy.from_pretrained(ckpt).eval()
            plain, armed = latency_ms(policy, r["steps"], r["arm"], args.latency_reps)
            r.update(latency_plain_ms=plain, latency_ms=armed if r["arm"] != "naive" else plain,
                     latency_timed=f"{time.strftime('%Y-%m-%d')}, CPU time")
            print(f"{r['task']} {LABEL[(r['decoder'], r['steps'])]} {r['arm']}: {plain:.2f} -> {armed:.2f} ms", flush=True)
        path.write_text(json.dumps(rows, indent=1))


COST_RUNTIMES = ("eager", "onnxruntime", "compiled")


def _cost_calls(policy, runtime: str, state: torch.Tensor, prev: torch.Tensor, steps: int, workdir: Path) -> dict:
    """{"naive": call, "trained": call}: one plain chunk and one trained-RTC chunk (d = MAX_DELAY) for one state,
    in `runtime`: eager PyTorch (`policy.sample`), onnxruntime (the plain graph against the `--rtc` graph, one
    thread) or `compile_sampler` (its device's default mode, plain against rtc=True)."""
    cfg = policy.config
    if runtime == "eager":
        counter = itertools.count()                   # a fresh noise seed per call
        return {arm: (lambda a: lambda: chunk(policy, state, steps, a, prev, MAX_DELAY,
                                              torch.Generator(state.device).manual_seed(next(counter))))(arm)
                for arm in ("naive", "trained")}
    noise = torch.randn(1, H, cfg.action_dim, generator=torch.Generator().manual_seed(0)).to(state.device)
    if runtime == "onnxruntime":
        from action_decoder.runtime import OnnxPolicy

        plain = OnnxPolicy(policy.export_onnx(workdir / f"{cfg.decoder_type}_k{steps}.onnx", steps=steps), threads=1)
        rtc = OnnxPolicy(policy.export_onnx(workdir / f"{cfg.decoder_type}_k{steps}_rtc.onnx", steps=steps, rtc=True),
                         threads=1)
        s, n, c = state.cpu().numpy(), noise.cpu().numpy(), prev.cpu().numpy()
        return {"naive": lambda: plain.predict_action_chunk(s, n),
                "trained": lambda: rtc.predict_action_chunk(s, n, committed=c, delay=MAX_DELAY)}
    from action_decoder.compiled import compile_sampler

    plain, rtc = compile_sampler(policy, steps=steps), compile_sampler(policy, steps=steps, rtc=True)
    batch = {"state": state}
    calls = {"naive": lambda: plain(batch, noise), "trained": lambda: rtc(batch, noise, prev_chunk=prev, delay=MAX_DELAY)}
    for _ in range(3):                         # compile; CUDA graphs record on the second call, replay from the third
        for call in calls.values():
            call()
    return calls


def chunk_cost(args, command: str) -> list[dict]:
    """Plain against trained-RTC chunks (d = 4) at batch 1 on a network of `action-decoder train`'s default
    size (hidden 96, 3 layers, H = 16, Meta-World's 39-d state, random weights: the cost does not depend on
    them), each setting and runtime (--cost-runtimes: eager, onnxruntime on a CPU, compiled) interleaved,
    --latency-reps calls each. CPU: the process's CPU time; CUDA: wall time between synchronisations. Rows
    to --cost-json."""
    import tempfile

    from action_decoder import ActionDecoderPolicy, DecoderConfig

    device = torch.device(args.device)
    runtimes = [r for r in args.cost_runtimes if not (r == "onnxruntime" and device.type == "cuda")]
    rows = []
    workdir = tempfile.TemporaryDirectory(prefix="rtc_cost_")
    for decoder, steps in args.settings:
        torch.manual_seed(0)
        cfg = DecoderConfig(decoder_type=decoder, state_dim=39, action_dim=4, action_chunk_size=H, hidden_size=96,
                            num_hidden_layers=3, num_attention_heads=4, num_key_value_heads=2, rtc_max_delay=MAX_DELAY,
                            num_inference_timesteps=steps, n_action_steps=S,
                            flow_prediction="sample" if decoder == "mean_flow" else "velocity")
        stats = {k: {"mean": torch.zeros(n), "std": torch.ones(n), "min": -torch.ones(n), "max": torch.ones(n)}
                 for k, n in (("state", 39), ("actions", 4))}
        policy = ActionDecoderPolicy(cfg, stats).to(device).eval()
        state, prev = torch.zeros(1, 39, device=device), torch.zeros(1, H - S, 4, device=device)
        clock = time.process_time if device.type == "cpu" else time.perf_counter
        for runtime in runtimes:
            calls = _cost_calls(policy, runtime, state, prev, steps, Path(workdir.name))
            times = {"naive": [], "trained": []}
            with torch.no_grad():
                for rep in range(args.latency_reps + 10):
                    for arm in times:
                        if device.type == "cuda":
                            torch.cuda.synchronize(device)
                        t0 = clock()
                        calls[arm]()
                        if device.type == "cuda":
                            torch.cuda.synchronize(device)
                        if rep >= 10:
                            times[arm].append(clock() - t0)
            plain, trained = (1000 * statistics.median(times[a]) for a in ("naive", "trained"))
            rows.append({"decoder": decoder, "steps": steps, "delay": MAX_DELAY, "runtime": runtime, "plain_ms": plain,
                         "trained_ms": trained, "ratio": trained / plain, "reps": args.latency_reps,
                         "device": str(device), "clock": "CPU time" if device.type == "cpu" else "wall time, synchronised",
                         "torch": torch.__version__, "command": command, "date": time.strftime("%Y-%m-%d"),
                         "machine": (torch.cuda.get_device_name(device) if device.type == "cuda" else
                                     f"{platform.machine()}, {os.cpu_count()} CPU cores shared, "
                                     f"{torch.get_num_threads()} torch thread")})
            print(f"{LABEL[(decoder, steps)]} {device} {runtime}: plain {plain:.3f} ms, trained (d = {MAX_DELAY}) "
                  f"{trained:.3f} ms, {trained / plain:.3f}x", flush=True)
    workdir.cleanup()
    out = Path(args.cost_json)
    old = json.loads(out.read_text()) if out.is_file() else []
    key = lambda r: (r["decoder"], r["steps"], r["device"], r["machine"], r.get("runtime", "eager"))   # noqa: E731
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps([r for r in old if key(r) not in {key(n) for n in rows}] + rows, indent=1))
    return rows


def switch_jerk(seq: np.ndarray, switch: int) -> float:
    """Mean squared second difference of seq [T, D] over the stencils centred at switch − 1 and switch."""
    centres = [c for c in (switch - 1, switch) if 1 <= c <= len(seq) - 2]
    return float(np.mean([np.square(seq[c + 1] - 2 * seq[c] + seq[c - 1]).sum() for c in centres]))


def rtc_target(decoder: str, max_delay: int, meanflow_target: str | None = None) -> str:
    """The MeanFlow target of weights trained with `max_delay`: `meanflow_target`, or the library's default for
    them (None); "identity" for flow matching and for weights trained without RTC."""
    from action_decoder import DecoderConfig

    if decoder != "mean_flow" or not max_delay:
        return "identity"
    return meanflow_target or DecoderConfig(decoder_type=decoder, rtc_max_delay=max_delay).meanflow_target


def trained_policies(task: str, decoder: str, budget, seed: int, runs: Path, draw, state_dim: int,
                     action_dim: int, arms=ARMS, meanflow_target: str | None = None) -> dict:
    """{"plain": policy, "rtc": policy, "train_cpu_s": {...}} (the weights `arms` need): trained once
    (benchmarks.multimodal.train), kept under runs/<task>-<decoder>[-rtc4[<dist>][bal][split][os<share>]][budget_suffix]-seed<s>
    (os<share>: the one-step share the library resolves for these weights; a --mm-recipe override is named by
    budget_suffix); the RTC-trained MeanFlow weights with `meanflow_target` (None: the library's default, `rtc_target`)."""
    from action_decoder import ActionDecoderPolicy
    from benchmarks.multimodal import Budget, train

    out = {"train_cpu_s": {}}
    need = {"rtc" if a == "trained" else "plain" for a in arms}
    for key, max_delay in (("plain", 0), ("rtc", MAX_DELAY)):
        if key not in need:
            continue
        target = rtc_target(decoder, max_delay, meanflow_target)
        share = rtc_one_step_share(decoder, max_delay, target)
        path = runs / (f"{task}-{decoder}"
                       f"{rtc_suffix(max_delay, budget.rtc_delay_dist, budget.rtc_balance_rows, target, share)}"
                       f"{budget_suffix(budget)}-seed{seed}")
        if not (path / "model.safetensors").is_file():
            recipe = {**budget.recipe, **({"target": target} if decoder == "mean_flow" else {})}
            b = Budget(**{**budget.__dict__, "rtc_max_delay": max_delay, "recipe": recipe})
            policy, cpu_s = train(decoder, draw, state_dim, action_dim, b, seed)
            policy.save_pretrained(path)
            (path / "train_cpu_s.json").write_text(json.dumps(cpu_s))
        out[key] = ActionDecoderPolicy.from_pretrained(path).eval()
        out["train_cpu_s"][key] = json.loads((path / "train_cpu_s.json").read_text())
    return out


def cells(pols_by_decoder: dict, arms=ARMS):
    """(decoder, steps, its arms' policies, delay, arm) of every cell whose decoder was trained."""
    for decoder, steps in SETTINGS:
        pols = pols_by_decoder.get(decoder)
        if pols is not None:
            for d in DELAYS:
                for arm in ARMS:
                    if arm in arms:
                        yield decoder, steps, pols, d, arm


def arm_policy(pols: dict, arm: str):
    return pols["rtc"] if arm == "trained" else pols["plain"]


# ----------------------------------------------------------------------------------------- synthetic
def route_rows(state: torch.Tensor, sign: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Route rows [B, len(rows), 4] of `benchmarks.multimodal.routes` at (possibly negative) rows j, h = j/(H−1),
    sign ±1 per state: the route continued before the chunk's first row for the jerk stencils."""
    h = rows.to(state.dtype) / (H - 1)
    base = 0.5 * state[:, None, :] * h[None, :, None]
    bend = torch.sin(math.pi * h)[:, None] * torch.tensor([1.0, -0.6, 0.8, 0.4])
    return base + sign[:, None, None] * bend


def run_synthetic(pols_by_decoder: dict, states: int, samples: int, seed: int, arms=ARMS) -> list[dict]:
    from benchmarks.multimodal import mode_metrics, routes, separation

    gen = torch.Generator().manual_seed(4242 + seed)
    state = torch.randn(states, 4, generator=gen).repeat_interleave(samples, 0)             # [N, 4]
    n = state.shape[0]
    sign = torch.where(torch.rand(n, generator=gen) < 0.5, 1.0, -1.0)                     # committed route A
    committed = route_rows(state, sign, torch.arange(-2, H))                              # [N, H + 2, 4]
    other = route_rows(state, -sign, torch.arange(H))
    prev = committed[:, 2: 2 + H - S]                                                      # [N, L, 4]
    rows = []
    for decoder, steps, pols, d, arm in cells(pols_by_decoder, arms):
        gens = [torch.Generator().manual_seed(seed * 100_000 + i) for i in range(n)]
        new = chunk(arm_policy(pols, arm), state, steps, arm, prev, d, gens)      # [N, H, 4]
        ex = slice(d, d + S)
        dist_a = (new[:, ex] - committed[:, 2:][:, ex]).square().mean((1, 2)).sqrt()
        dist_b = (new[:, ex] - other[:, ex]).square().mean((1, 2)).sqrt()
        gap = (committed[:, 2:][:, ex] - other[:, ex]).square().mean((1, 2)).sqrt()
        keep = (dist_a < dist_b) & (dist_a < 0.25 * gap)
        off = (dist_a >= 0.25 * gap) & (dist_b >= 0.25 * gap)
        seq = torch.cat([committed[:, : 2 + d], new[:, d:]], 1).numpy()           # executed: A, then new
        jerk = float(np.mean([switch_jerk(s, 2 + d) for s in seq]))
        row = {"task": "synthetic", "decoder": decoder, "steps": steps, "delay": d, "arm": arm,
               "samples": n, "route_consistency": keep.float().mean().item(),
               "off_route": off.float().mean().item(), "switch_jerk": jerk}
        if d == 0 and arm != "guided":
            modes = routes(state[::samples])                                       # [states, 2, H, 4]
            free = chunk(arm_policy(pols, arm), state, steps, "naive", None, 0, gens)
            row["mode_metrics"] = mode_metrics(free.reshape(states, samples, H, 4), modes,
                                               0.1 * separation())
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "mode_metrics"}), flush=True)
    return rows


# ----------------------------------------------------------------------------------------- obstacle
def obstacle_episode(policy, steps: int, arm: str, d: int, layout: int, noise_seed: int) -> dict:
    """One closed-loop episode with inference delay d; re-plans every S actions."""
    from action_decoder.envs.obstacle_routes import SPEED, ObstacleRoutesEnv

    env = ObstacleRoutesEnv()
    obs, _ = env.reset(seed=layout)
    plan_i = 0

    def plan(prev):
        nonlocal plan_i
        g = torch.Generator().manual_seed(noise_seed * 1000 + plan_i)
        plan_i += 1
        p = None if prev is None else torch.from_numpy(prev)[None]
        return np.clip(chunk(policy, torch.from_numpy(obs)[None], steps, arm, p, d, g)[0].numpy(), -1, 1)

    current = plan(None)
    queue, executed, switches, checks = list(current[: S + d]), [], [], []
    info, done, truncated = {"success": False, "collided": False}, False, False
    while not (done or truncated):
        if len(queue) == d:
            new = plan(current[S:].astype(np.float32))
            pos, centre = obs[:2].astype(np.float64), obs[4:6].astype(np.float64)
            if pos[0] < centre[0]:                        # the route is still open
                old_path = pos + SPEED * np.cumsum(current[S: S + d + S], 0)             # old plan, new steps 0..d+S−1
                new_path = pos + SPEED * np.cumsum(np.concatenate([np.array(queue).reshape(-1, 2),
                                                                   new[d: d + S]]), 0)
                side = lambda path: np.sign(path[d: d + S, 1].mean() - centre[1])         # noqa: E731
                checks.append(bool(side(old_path) == side(new_path)))
            switches.append(len(executed) + d)
            queue = queue + list(new[d: d + S])
            current = new
        a = queue.pop(0)
        obs, _, done, truncated, info = env.step(a)
        executed.append(a)
    seq = np.asarray(executed)
    jerks = [switch_jerk(seq, k) for k in switches if 1 <= k - 1 and k + 1 <= len(seq) - 1]
    return {"success": bool(info["success"]), "collided": bool(info["collided"]), "checks": checks,
            "jerks": jerks}


def run_obstacle(pols_by_decoder: dict, episodes: int, seed: int, arms=ARMS) -> list[dict]:
    rows = []
    for decoder, steps, pols, d, arm in cells(pols_by_decoder, arms):
        res = [obstacle_episode(arm_policy(pols, arm), steps, arm, d, 1_000_000 + seed * 1000 + j, j)
               for j in range(episodes)]
        checks = [c for r in res for c in r["checks"]]
        jerks = [j for r in res for j in r["jerks"]]
        row = {"task": "obstacle", "decoder": decoder, "steps": steps, "delay": d, "arm": arm,
               "episodes": episodes, "success": sum(r["success"] for r in res) / episodes,
               "collided": sum(r["collided"] for r in res) / episodes,
               "replans_checked": len(checks),
               "route_consistency": sum(checks) / len(checks) if checks else float("nan"),
               "switch_jerk": float(np.mean(jerks)) if jerks else float("nan")}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def run_multimodal(args, command: str) -> None:
    """Train (once) and measure (a) and (b) for --settings' decoders; rows to --multimodal-json."""
    from action_decoder.envs.obstacle_routes import ACTION_DIM, OBS_DIM, expert_dataset
    from benchmarks.multimodal import Budget, dataset_batch, parse_recipe, synthetic_batch

    budget = Budget(steps=args.mm_train_steps, hidden=args.mm_hidden_size, layers=args.mm_num_layers,
                    rtc_delay_dist=args.rtc_delay_dist, rtc_balance_rows=args.rtc_balance_rows,
                    recipe=parse_recipe(args.mm_recipe, "--mm-recipe"))
    runs = Path(args.runs) / "multimodal"
    decoders = sorted({d for d, _ in args.settings})
    out = Path(args.multimodal_json)
    for task in args.multimodal:
        if task == "synthetic":
            pols = {dec: trained_policies("synthetic", dec, budget, args.seed, runs, synthetic_batch, 4, 4, args.arms,
                                          args.rtc_meanflow_target) for dec in decoders}
            new = run_synthetic(pols, args.mm_states, args.mm_samples, args.seed, args.arms)
        else:
            states, chunks = expert_dataset(budget.demos, args.seed)
            pols = {dec: trained_policies("obstacle", dec, budget, args.seed, runs, dataset_batch(states, chunks),
                                          OBS_DIM, ACTION_DIM, args.arms, args.rtc_meanflow_target) for dec in decoders}
            new = run_obstacle(pols, args.mm_episodes, args.seed, args.arms)
        for r in new:
            p = pols[r["decoder"]]
            plain, armed = latency_ms(arm_policy(p, r["arm"]), r["steps"], r["arm"], args.latency_reps) \
                if r["delay"] == DELAYS[-1] else (None, None)
            r.update(latency_plain_ms=plain, latency_ms=armed, seed=args.seed, train_cpu_s=p["train_cpu_s"],
                     rtc_delay_dist=budget.rtc_delay_dist if r["arm"] == "trained" else None,
                     rtc_balance_rows=budget.rtc_balance_rows if r["arm"] == "trained" else None,
                     rtc_meanflow_target=p["rtc"].config.meanflow_target
                     if r["arm"] == "trained" and r["decoder"] == "mean_flow" else None,
                     rtc_meanflow_one_step_share=p["rtc"].config.meanflow_one_step_share
                     if r["arm"] == "trained" and r["decoder"] == "mean_flow" else None,
                     train_steps=budget.steps, hidden_size=budget.hidden, num_layers=budget.layers,
                     **({"recipe": budget.recipe} if budget.recipe else {}),
                     command=command, date=time.strftime("%Y-%m-%d"),
                     machine=f"{platform.machine()}, {os.cpu_count()} CPU cores shared, "
                             f"{torch.get_num_threads()} torch thread")
        key = lambda r: (r["task"], r["decoder"], r["steps"], r["delay"], arm_label(r), r["seed"])  # noqa: E731
        rows = json.loads(out.read_text()) if out.is_file() else []                              # read now: runs may overlap
        rows = [r for r in rows if key(r) not in {key(n) for n in new}] + new
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(rows, indent=1))


# ----------------------------------------------------------------------------------------- the page
def _pct(x) -> str:
    return "–" if x is None or x != x else f"{100 * x:.0f} %"


def _dists(rows: list[dict]) -> str:
    """How the trained rows' weights drew their delays (rows without the field: uniform)."""
    got = sorted({(r.get("rtc_delay_dist") or "uniform") + (", rows balanced" if r.get("rtc_balance_rows") else "")
                  for r in rows if r["arm"] == "trained"})
    return "delays drawn " + (" and ".join(got) if got else "–") + " on 0.." + str(MAX_DELAY)


def multimodal_section(rows: list[dict]) -> list[str]:
    if not rows:
        return ["## Multimodal chunks: does the new chunk keep the committed route?", "",
                "Not yet measured.", ""]
    syn = {(r["decoder"], r["steps"], r["delay"], arm_label(r)): r for r in rows if r["task"] == "synthetic"}
    obs = {(r["decoder"], r["steps"], r["delay"], arm_label(r)): r for r in rows if r["task"] == "obstacle"}
    meta = sorted({(r["date"], r["machine"], r["command"]) for r in rows})
    n_syn = sorted({r["samples"] for r in syn.values()})
    n_obs = sorted({r["episodes"] for r in obs.values()})
    lines = ["## Multimodal chunks: does the new chunk keep the committed route?", "",
             *[f"Measured {d} ({m}) by `{c}`." for d, m, c in meta], "",
             f"Synthetic: {'/'.join(map(str, n_syn))} re-plans per cell (states × samples), the committed route "
             f"drawn 50/50. Obstacle routes: {'/'.join(map(str, n_obs))} closed-loop episodes per cell, "
             f"re-planning every {S} actions; route consistency over the re-plans made before the point passes "
             f"the obstacle (count in the JSON). Each policy trains {rows[0]['train_steps']} steps "
             f"(benchmarks/multimodal.py's budget); naive and guided use the weights trained without RTC, trained "
             f"the weights trained with rtc_max_delay = {MAX_DELAY} (synthetic: {_dists(list(syn.values()))}; obstacle: "
             f"{_dists(list(obs.values()))}). Chunk ms: batch 1, the median CPU time of "
             f"interleaved calls (one torch thread), the arm at d = {DELAYS[-1]} against a plain chunk of the same "
             f"weights. –: not measured.", "",
             "| setting | d | arm | synthetic: route kept | synthetic: off both routes | synthetic: switch jerk | "
             "obstacle: route kept | obstacle: success | obstacle: switch jerk | chunk ms (plain → arm) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for setting in SETTINGS:
        for d in DELAYS:
            for arm in arm_labels(rows):
                k = (*setting, d, arm)
                s, o = syn.get(k), obs.get(k)
                if s is None and o is None:
                    continue
                lat = next((x for x in (s, o) if x and x.get("latency_ms") is not None), None)
                ms = "–" if lat is None else f"{lat['latency_plain_ms']:.1f} → {lat['latency_ms']:.1f} " \
                                              f"({lat['latency_ms'] / lat['latency_plain_ms']:.2f}×)"
                sj = "–" if not s else f"{s['switch_jerk']:.4f}"
                oj = "–" if not o or o["switch_jerk"] != o["switch_jerk"] else f"{o['switch_jerk']:.4f}"
                lines.append(f"| {LABEL[setting]} | {d} | {arm} | {_pct(s and s['route_consistency'])} | "
                             f"{_pct(s and s['off_route'])} | {sj} | {_pct(o and o['route_consistency'])} | "
                             f"{_pct(o and o['success'])} | {oj} | {ms} |")
    mm = [r for r in rows if r.get("mode_metrics")]
    if mm:
        lines += ["", "Without a prefix (d = 0, no previous chunk): the weights trained with RTC against those "
                  "trained without, synthetic task (benchmarks/multimodal.py's metrics).", "",
                  "| setting | weights | on a mode | majority share | energy distance |", "|---|---|---|---|---|"]
        for r in sorted(mm, key=lambda r: (r["decoder"], r["steps"], arm_label(r))):
            m = r["mode_metrics"]
            weights = "plain" if r["arm"] != "trained" else "RTC-trained" + arm_label(r)[len("trained"):]
            lines.append(f"| {LABEL[(r['decoder'], r['steps'])]} | {weights} "
                         f"| {_pct(m['on_mode'])} | {_pct(m['majority_share'])} | {m['energy']:.3f} |")
    return lines + [""]


# ----------------------------------------------------------------------------------------- Meta-World
def rtc_suffix(max_delay: int, delay_dist: str, balance_rows: bool = False, meanflow_target: str = "identity",
               one_step_share: float = 0.0, perturbed_prefixes: int = 0) -> str:
    """The run directory's suffix of RTC-trained weights: -rtc<N>, the delay distribution unless uniform,
    "bal" with balanced row weights, "split" with MeanFlow's interval-consistency target, os<share> with
    MeanFlow rows at (t, r) = (0, 1) (`DecoderConfig.meanflow_one_step_share`) and pp<copies> with
    demonstrations' perturbed-prefix copies (`train --perturbed-prefixes`)."""
    return (f"-rtc{max_delay}{'' if delay_dist == 'uniform' else delay_dist}{'bal' if balance_rows else ''}"
            f"{'split' if meanflow_target == 'split' else ''}"
            f"{f'os{one_step_share:g}' if one_step_share else ''}"
            f"{f'pp{perturbed_prefixes}' if perturbed_prefixes else ''}") if max_delay else ""


def rtc_perturbed_prefixes(decoder: str, max_delay: int, copies: int | None = None) -> int:
    """The perturbed-prefix copies `action-decoder train` gives the generated demonstrations of `decoder` with
    --rtc-max-delay `max_delay` and --perturbed-prefixes `copies` (None: its default)."""
    from action_decoder.train import perturbed_prefixes

    cfg = TrainConfig(decoder=decoder, rtc_max_delay=max_delay, perturbed_prefixes=copies)
    return getattr(perturbed_prefixes(cfg), "copies", 0)


def rtc_one_step_share(decoder: str, max_delay: int, meanflow_target: str) -> float:
    """The share of MeanFlow rows at (t, r) = (0, 1) that `DecoderConfig` resolves for these weights by default."""
    from action_decoder import DecoderConfig

    return DecoderConfig(decoder_type=decoder, rtc_max_delay=max_delay, meanflow_target=meanflow_target) \
        .meanflow_one_step_share


def budget_suffix(budget) -> str:
    """The run directory's suffix of a multimodal training budget other than `benchmarks.multimodal.Budget`'s:
    -<N>steps, -h<hidden>x<layers>, and -<key><value> per recipe override (sorted by key), so that weights of
    another budget or recipe are never reused."""
    from benchmarks.multimodal import Budget

    base = Budget()
    return (f"-{budget.steps}steps" if budget.steps != base.steps else "") + \
        (f"-h{budget.hidden}x{budget.layers}" if (budget.hidden, budget.layers) != (base.hidden, base.layers) else "") + \
        "".join(f"-{k}{v:g}" if isinstance(v, float) else f"-{k}{v}" for k, v in sorted(budget.recipe.items()))


def run_suffix(train_steps: int, train_seed: int) -> str:
    """The run directory's suffix of a training budget and seed other than `action-decoder train`'s defaults."""
    return (f"-{train_steps}steps" if train_steps != TrainConfig.steps else "") + \
        (f"-seed{train_seed}" if train_seed != TrainConfig.seed else "")


def train_metaworld(task: str, decoder: str, runs: Path, max_delay: int, delay_dist: str = "uniform",
                    balance_rows: bool = False, train_steps: int | None = None, train_seed: int | None = None,
                    meanflow_target: str | None = None, perturbed_prefixes: int | None = None) -> Path:
    """`action-decoder train` defaults (plus --rtc-max-delay, --rtc-delay-dist, --rtc-balance-rows, --steps,
    --seed, --perturbed-prefixes, None: train's default for these weights, and for RTC-trained MeanFlow
    --meanflow-target, None: train's default, and the one-step share the library resolves for it), once (an
    interrupted run continues from its newest checkpoint), under
    runs/<task>-<decoder>[-rtc<N>[<dist>][bal][split][os<share>][pp<copies>]][-<steps>steps][-seed<s>]."""
    import subprocess
    import sys

    train_steps = TrainConfig.steps if train_steps is None else train_steps
    train_seed = TrainConfig.seed if train_seed is None else train_seed
    target = rtc_target(decoder, max_delay, meanflow_target)
    share = rtc_one_step_share(decoder, max_delay, target)
    copies = rtc_perturbed_prefixes(decoder, max_delay, perturbed_prefixes) if max_delay else 0
    out = runs / (f"{task.split('/')[-1]}-{decoder}"
                  f"{rtc_suffix(max_delay, delay_dist, balance_rows, target, share, copies)}"
                  f"{run_suffix(train_steps, train_seed)}")
    if not (out / "final" / "model.safetensors").is_file():
        cmd = [sys.executable, "-m", "action_decoder.cli", "train", "--task", task, "--decoder", decoder,
               "--output-dir", str(out), "--eval-episodes", "0", "--no-progress",
               "--steps", str(train_steps), "--seed", str(train_seed)]
        cmd += ["--rtc-max-delay", str(max_delay), "--rtc-delay-dist", delay_dist,
                "--perturbed-prefixes", str(copies)] if max_delay else []
        cmd += ["--rtc-balance-rows"] if max_delay and balance_rows else []
        cmd += ["--resume"] if (out / "checkpoints").is_dir() else []
        cmd += ["--meanflow-target", target, "--meanflow-one-step-share", f"{share:g}"] \
            if decoder == "mean_flow" and max_delay else []
        out.mkdir(parents=True, exist_ok=True)
        with open(out.parent / f"{out.name}.log", "a") as fh:
            subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True,
                           env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    return out / "final"


def run_metaworld(task: str, decoder: str, steps: int, args, command: str) -> list[dict]:
    """Each (training seed, arm, delay) of one task and setting: success, boundary jerk, latency; the same
    noise per (episode, plan) in every arm."""
    from action_decoder import ActionDecoderPolicy
    from action_decoder.envs import evaluate
    from action_decoder.evaluate import make_policy_fn

    train_steps = getattr(args, "train_steps", None) or TrainConfig.steps
    rows = []
    for train_seed in getattr(args, "train_seeds", None) or [TrainConfig.seed]:
        need = {"rtc" if a == "trained" else "plain" for a in args.arms}        # train only the weights needed
        ckpts = {k: train_metaworld(task, decoder, Path(args.runs), MAX_DELAY if k == "rtc" else 0,
                                    args.rtc_delay_dist, args.rtc_balance_rows, train_steps, train_seed,
                                    getattr(args, "rtc_meanflow_target", None),
                                    getattr(args, "rtc_perturbed_prefixes", None))
                 for k in sorted(need)}
        pols = {k: ActionDecoderPolicy.from_pretrained(v).eval() for k, v in ckpts.items()}
        for arm in args.arms:
            policy = arm_policy(pols, arm)
            plain_ms, arm_ms = latency_ms(policy, steps, arm, args.latency_reps)
            for d in args.delays:
                fn = make_policy_fn(policy, 1, None, steps, torch.Generator().manual_seed(args.seed),
                                    rtc_mode=None if arm == "naive" else arm)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = evaluate(fn, task, episodes=args.episodes, seed=args.seed, n_action_steps=S,
                                   num_envs=args.num_envs, delay=d, rtc=arm != "naive")
                rows.append({"task": res["task"], "decoder": decoder, "steps": steps, "delay": d, "arm": arm,
                             "train_steps": train_steps, "train_seed": train_seed,
                             "episodes": args.episodes, "seed": args.seed, "successes": int(sum(res["successes"])),
                             "success_rate": res["success_rate"], "boundary_jerk": res["boundary_jerk"],
                             "boundaries": res["boundaries"], "episode_boundary_jerk": res["episode_boundary_jerk"],
                             "latency_plain_ms": plain_ms, "latency_ms": arm_ms if arm != "naive" else plain_ms,
                             "checkpoint": str(ckpts["rtc" if arm == "trained" else "plain"]), "command": command,
                             "rtc_delay_dist": pols["rtc"].config.rtc_delay_dist if arm == "trained" else None,
                             "rtc_balance_rows": pols["rtc"].config.rtc_balance_rows if arm == "trained" else None,
                             "rtc_meanflow_target": pols["rtc"].config.meanflow_target
                             if arm == "trained" and decoder == "mean_flow" else None,
                             "rtc_meanflow_one_step_share": pols["rtc"].config.meanflow_one_step_share
                             if arm == "trained" and decoder == "mean_flow" else None,
                             "rtc_perturbed_prefixes": perturbed_copies(pols["rtc"].config)
                             if arm == "trained" else None,
                             "date": time.strftime("%Y-%m-%d"),
                             "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores shared, "
                                        f"{torch.get_num_threads()} torch thread"})
                print(f"[{res['task']}] {LABEL[(decoder, steps)]} train {train_steps} steps seed {train_seed} "
                      f"d={d} {arm}: success {res['success_rate']:.2f}, boundary jerk {res['boundary_jerk']:.4g}, "
                      f"chunk {rows[-1]['latency_ms']:.1f} ms", flush=True)
    return rows


def _budget(r: dict) -> int:
    return r.get("train_steps", TrainConfig.steps)


def _seed(r: dict) -> int:
    return r.get("train_seed", TrainConfig.seed)


def perturbed_copies(config) -> int:
    """The perturbed-prefix copies a checkpoint's demonstrations had (`train --perturbed-prefixes`, saved
    resolved; checkpoints that predate it had none)."""
    return int(config.extra.get("train", {}).get("perturbed_prefixes") or 0)


def arm_label(r: dict) -> str:
    """The row's arm, naming the MeanFlow target of RTC-trained weights when it is not the identity, their
    share of rows at (t, r) = (0, 1) when it is not 0 and their demonstrations' perturbed-prefix copies."""
    share, copies = r.get("rtc_meanflow_one_step_share"), r.get("rtc_perturbed_prefixes")
    return r["arm"] + (", split target" if r.get("rtc_meanflow_target") == "split" else "") + \
        (f", one-step rows {share:g}" if share else "") + (f", perturbed prefixes {copies}" if copies else "")


def arm_labels(rows: list[dict]) -> list[str]:
    """The arm labels of `rows` in ARMS' order (the identity target before the split one)."""
    return sorted({arm_label(r) for r in rows}, key=lambda a: (ARMS.index(a.split(",")[0]), a))


def row_key(r: dict) -> tuple:
    """What one Meta-World row measures; rows without a training budget or seed used the CLI's defaults."""
    return (r["task"], r["decoder"], r["steps"], r["delay"], arm_label(r), r["seed"], _budget(r), _seed(r))


def seed_spread(got: list[dict]) -> str:
    """Standard deviation over training seeds of the success pooled over tasks (%), when at least two seeds
    cover the same tasks; "–" otherwise."""
    by_seed: dict = {}
    for r in got:
        by_seed.setdefault(_seed(r), []).append(r)
    if len(by_seed) < 2 or len({frozenset(x["task"] for x in v) for v in by_seed.values()}) != 1:
        return "–"
    rates = [100 * sum(x["successes"] for x in v) / sum(x["episodes"] for x in v) for v in by_seed.values()]
    return f"{statistics.stdev(rates):.1f}"


def metaworld_section(rows: list[dict], tasks: list[str]) -> list[str]:
    head = ["## Meta-World: naive, guided and trained", ""]
    if not rows:
        return head + ["Not yet measured.", ""]
    meta = sorted({(r["date"], r["machine"], r["command"]) for r in rows})
    measured = sorted({r["task"] for r in rows})
    eps = sorted({r["episodes"] for r in rows})
    lines = head + [*[f"Measured {d} ({m}) by `{c}`." for d, m, c in meta], "",
                    f"Tasks measured: {', '.join(measured)}; not yet measured: "
                    f"{', '.join(t for t in (x.split('/')[-1] + '-v3' for x in tasks) if t not in measured) or 'none'}. "
                    f"{'/'.join(map(str, eps))} episodes per task and cell, evaluation seed(s) "
                    f"{', '.join(map(str, sorted({r['seed'] for r in rows})))}, re-planning every {S} of {H} actions. "
                    f"Success noise: ±{100 * (0.25 / min(eps)) ** 0.5:.1f} points (binomial at 50 % over "
                    f"{min(eps)} episodes); two cells differ beyond noise above "
                    f"{2 * 2 ** 0.5 * 100 * (0.25 / min(eps)) ** 0.5:.0f} points. One table per training budget "
                    f"(`train --steps`); success is pooled over tasks and training seeds (`train --seed`), and "
                    f"seed SD is the standard deviation over training seeds of the success pooled over tasks. "
                    f"Boundary jerk as in the table below, ± its standard error over episodes. naive and guided use "
                    f"weights trained without RTC, trained weights trained with rtc_max_delay = {MAX_DELAY} "
                    f"({_dists(rows)}). Chunk ms: batch 1, the median CPU time of interleaved "
                    f"calls (one torch thread), the arm at d = {MAX_DELAY} against a plain chunk of the same weights. "
                    f"Settings, delays and arms not listed are not measured."
                    + (" \"trained, split target\": MeanFlow weights trained with RTC and the interval-consistency "
                       "target (`train --meanflow-target split`); \"trained\": the MeanFlow identity."
                       if any(r.get("rtc_meanflow_target") == "split" for r in rows) else "")
                    + (" \"perturbed prefixes N\": RTC-trained on demonstrations with N perturbed-prefix copies of each "
                       "frame (`train --perturbed-prefixes N`); without it, on the demonstrations alone."
                       if any(r.get("rtc_perturbed_prefixes") for r in rows) else ""), ""]
    for budget in sorted({_budget(r) for r in rows}):
        at = [r for r in rows if _budget(r) == budget]
        lines += [f"### Trained {budget} steps", "",
                  "| setting | d | arm | tasks | training seeds | success | seed SD | boundary jerk | chunk ms (plain → arm) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for setting in SETTINGS:
            for d in DELAYS:
                for arm in arm_labels(at):
                    got = [r for r in at if (r["decoder"], r["steps"]) == setting and r["delay"] == d
                           and arm_label(r) == arm]
                    if not got:
                        continue
                    succ = 100 * sum(r["successes"] for r in got) / sum(r["episodes"] for r in got)
                    nb = sum(r["boundaries"] for r in got)
                    jerk = sum(r["boundary_jerk"] * r["boundaries"] for r in got) / max(1, nb)
                    per = [j for r in got for j in r["episode_boundary_jerk"] if j is not None]
                    se = statistics.stdev(per) / len(per) ** 0.5 if len(per) > 1 else float("nan")
                    p_ms = statistics.mean(r["latency_plain_ms"] for r in got)
                    a_ms = statistics.mean(r["latency_ms"] for r in got)
                    lines.append(f"| {LABEL[setting]} | {d} | {arm} | {len({r['task'] for r in got})} | "
                                 f"{', '.join(map(str, sorted({_seed(r) for r in got})))} | {succ:.1f} | "
                                 f"{seed_spread(got)} | {jerk:.4f} ± {se:.4f} | "
                                 f"{p_ms:.1f} → {a_ms:.1f} ({a_ms / p_ms:.2f}×) |")
        lines += ["", *per_task_section(at), ""]
    return lines


def per_task_section(rows: list[dict]) -> list[str]:
    """Success per task (%) of each setting and arm at each delay measured, the mean over training seeds: the
    pooled rows above can mix task sets."""
    tasks = sorted({r["task"] for r in rows})
    delays = sorted({r["delay"] for r in rows})
    by: dict = {}
    for r in rows:
        by.setdefault((r["task"], r["decoder"], r["steps"], arm_label(r), r["delay"]), []).append(r["success_rate"])
    seeds = len({_seed(r) for r in rows})
    lines = [f"Success per task (%), at d = {' / '.join(map(str, delays))}"
             f"{f', the mean over {seeds} training seeds' if seeds > 1 else ''}:", "",
             "| setting | arm | " + " | ".join(tasks) + " |", "|---|---|" + "---|" * len(tasks)]
    for setting in SETTINGS:
        for arm in arm_labels(rows):
            if not any((t, *setting, arm, d) in by for t in tasks for d in delays):
                continue
            cell = lambda t: " / ".join("–" if (t, *setting, arm, d) not in by else       # noqa: E731
                                        f"{100 * statistics.mean(by[(t, *setting, arm, d)]):.0f}" for d in delays)
            lines.append(f"| {LABEL[setting]} | {arm} | " + " | ".join(cell(t) for t in tasks) + " |")
    return lines


def cost_section(rows: list[dict]) -> list[str]:
    """The cost part's rows: plain against trained-RTC chunks at batch 1, per device."""
    if not rows:
        return []
    meta = sorted({(r["date"], r["machine"], r["command"]) for r in rows})
    lines = ["## Chunk cost: plain against trained RTC", "",
             *[f"Measured {d} ({m}) by `{c}`." for d, m, c in meta], "",
             f"Batch 1, a network of `action-decoder train`'s default size (hidden 96, 3 layers, H = {H}, a 39-d "
             f"state) with random weights, the trained arm at d = {MAX_DELAY}; median over interleaved calls (CPU: "
             f"the process's CPU time; CUDA: wall time between synchronisations). Runtimes: eager PyTorch "
             f"(`policy.sample`); onnxruntime, one thread, the plain graph against the `export --rtc` graph "
             f"(`OnnxPolicy.predict_action_chunk`); compiled, `compile_sampler` against `compile_sampler(rtc=True)` "
             f"(inductor's default mode on a CPU, CUDA graphs on a GPU). Target: ≤ 1.05×.", "",
             "| setting | device | runtime | calls | plain ms | trained ms | trained ÷ plain |",
             "|---|---|---|---|---|---|---|"]
    order = {r: i for i, r in enumerate(COST_RUNTIMES)}
    for r in sorted(rows, key=lambda r: (r["machine"] != rows[0]["machine"], r["machine"],
                                         order.get(r.get("runtime", "eager"), 9), r["decoder"], r["steps"])):
        lines.append(f"| {LABEL[(r['decoder'], r['steps'])]} | {r['machine']} | {r.get('runtime', 'eager')} | {r['reps']} "
                     f"| {r['plain_ms']:.3f} | {r['trained_ms']:.3f} | {r['ratio']:.3f}× |")
    return lines + [""]
