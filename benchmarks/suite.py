"""The sections of issue 6: sampler overhead, training step, peers, memory, quality vs latency."""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch

from action_decoder import (ActionDecoderPolicy, DecoderConfig, sample_ddpm, sample_meanflow,
                            sample_ode, sample_sde, velocity_from_meanflow)
from action_decoder.flows.ddpm import inference_scheduler

from .timing import Clock, median, peak_step_memory, rounds

SECTIONS = ("sampling", "training", "peers", "memory", "quality")
PEER_TOL = 1e-4       # max |ours − peer| allowed for "same outputs" (float32, 10 steps)


@dataclass
class NetSize:
    """One Action Expert size and the batch it is timed at."""

    name: str
    hidden_size: int
    num_hidden_layers: int
    num_attention_heads: int
    num_key_value_heads: int
    batch: int              # sampling batch
    train_batch: int        # training batch

    def config(self, decoder_type: str = "flow_matching", **kw) -> DecoderConfig:
        return DecoderConfig(decoder_type=decoder_type, hidden_size=self.hidden_size,
                             num_hidden_layers=self.num_hidden_layers,
                             num_attention_heads=self.num_attention_heads,
                             num_key_value_heads=self.num_key_value_heads,
                             state_dim=39, action_dim=4, action_chunk_size=16, **kw)

    def label(self) -> str:
        return (f"{self.name}: hidden {self.hidden_size}, {self.num_hidden_layers} layers, "
                f"{self.num_attention_heads}/{self.num_key_value_heads} heads, H=16, D=4, state 39")


# Where each mode writes unless told (--out): a quick or tiny run is a smoke check whose
# numbers must not replace the committed tables of docs/benchmarks/.
OUT_DIRS = {"default": "docs/benchmarks", "quick": "outputs/benchmarks-quick", "tiny": "outputs/benchmarks-quick"}


@dataclass
class BenchConfig:
    mode: str = "default"
    sizes: List[NetSize] = field(default_factory=list)
    steps: int = 10                      # K for ODE, SDE, DDPM
    mf_steps: Tuple[int, ...] = (1, 2, 4)
    mf_ratios: Tuple[float, ...] = (0.25, 0.5, 1.0)
    reps: int = 40                       # timed rounds (sampling, peers)
    train_reps: int = 20                 # timed rounds (training)
    warmup: int = 3
    latency_reps: int = 20
    device: str = "cpu"
    out: str = "docs/benchmarks"         # preset(): only the full run writes the committed tables
    quality_dir: Optional[str] = None
    sections: Tuple[str, ...] = SECTIONS
    plot: bool = True

    @classmethod
    def preset(cls, mode: str, **kw) -> "BenchConfig":
        small = NetSize("small", 64, 2, 4, 2, batch=1, train_batch=32)
        large = NetSize("large", 128, 4, 4, 2, batch=8, train_batch=32)   # library default network
        if mode == "default":
            cfg = cls(mode=mode, sizes=[small, large], reps=60, train_reps=30, warmup=3)
        elif mode == "quick":
            cfg = cls(mode=mode, sizes=[small, dataclasses.replace(large, train_batch=16)], reps=12,
                      train_reps=6, warmup=2, latency_reps=5)
        elif mode == "tiny":
            tiny = NetSize("tiny", 32, 1, 2, 1, batch=1, train_batch=4)
            cfg = cls(mode=mode, sizes=[tiny], steps=3, mf_steps=(1, 2), mf_ratios=(0.5,), reps=3,
                      train_reps=2, warmup=1, latency_reps=2)
        else:
            raise ValueError(f"mode: expected 'default', 'quick' or 'tiny', got {mode!r}")
        bad = set(kw.get("sections", ())) - set(SECTIONS)
        if bad:
            raise ValueError(f"sections: unknown {sorted(bad)}; expected a subset of {list(SECTIONS)}")
        return dataclasses.replace(cfg, **{"out": OUT_DIRS[mode], **kw})


def _policy(cfg: DecoderConfig, device: torch.device, seed: int = 0) -> ActionDecoderPolicy:
    torch.manual_seed(seed)          # the same weights for every decoder of one size
    return ActionDecoderPolicy(cfg).to(device)


def _ratio_stats(samples: List[List[float]], num: int, den: int, den_scale: float = 1.0) -> dict:
    ratios = [s[num] / (s[den] * den_scale) for s in samples]
    return {"ratio": median(ratios), "num_ms": median([s[num] for s in samples]) * 1e3,
            "den_ms": median([s[den] for s in samples]) * 1e3}


# --------------------------------------------------------------------------- 1. sampler overhead
@torch.no_grad()
def bench_sampling(bc: BenchConfig, size: NetSize, clock: Clock) -> dict:
    device = torch.device(bc.device)
    cfg = size.config("flow_matching")
    ddpm_cfg = size.config("DDPM")
    policy = _policy(cfg, device).eval()
    B, K = size.batch, bc.steps
    batch = {"state": torch.randn(B, 39, device=device)}
    bound = policy.bind(batch)
    noise = torch.randn(B, 16, 4, device=device, generator=torch.Generator(device).manual_seed(1))
    t = torch.full((B,), 0.5, device=device)
    r = torch.full((B,), 0.75, device=device)
    steps_int = torch.full((B,), 500, dtype=torch.long, device=device)
    gen = torch.Generator(device).manual_seed(2)
    mf_velocity = velocity_from_meanflow(bound.avg_velocity, "boundary")

    def case(sampler, call, k, null=None):
        timers = [lambda: clock(sampler), lambda: clock(lambda: [call() for _ in range(k)])]
        return timers + ([lambda: clock(null, inner=5)] if null is not None else [])

    # A free "network" (returns its input): what the sampler itself costs per call.
    null_v = lambda x, t: x                                      # noqa: E731
    null_u = lambda x, t, r: x                                   # noqa: E731
    null_out = lambda x, s: x                                    # noqa: E731

    v_call = lambda: bound.velocity(noise, t)                     # noqa: E731
    u_call = lambda: bound.avg_velocity(noise, t, r)              # noqa: E731
    uu_call = lambda: bound.avg_velocity(noise, t, t)             # noqa: E731
    eps_call = lambda: bound.model_output(noise, steps_int)       # noqa: E731
    cases = {f"FM-ODE (Euler), K={K}": (case(lambda: sample_ode(bound.velocity, noise, K), v_call, K,
                                             lambda: sample_ode(null_v, noise, K)), K, "ode")}
    for k in bc.mf_steps:
        cases[f"MF, K={k}"] = (case(lambda k=k: sample_meanflow(bound.avg_velocity, noise, k), u_call, k,
                                    lambda k=k: sample_meanflow(null_u, noise, k)), k, "ode")
    sde = dict(sigma=policy.sigma, generator=gen, return_logprob=True, clip_t=cfg.flow_sde_clip_t)
    cases[f"FM-SDE + log-prob, K={K}"] = (
        case(lambda: sample_sde(bound.velocity, noise, K, **sde), v_call, K,
             lambda: sample_sde(null_v, noise, K, **sde)), K, "sde")
    cases[f"MF-SDE + log-prob (boundary u(x,t,t)), K={K}"] = (
        case(lambda: sample_sde(mf_velocity, noise, K, **sde), uu_call, K,
             lambda: sample_sde(velocity_from_meanflow(null_u, "boundary"), noise, K, **sde)), K, "sde")
    cases[f"DDPM (DPM-Solver++ 2M, diffusers), K={K}"] = (
        case(lambda: sample_ddpm(bound.model_output, noise, ddpm_cfg, K), eps_call, K,
             lambda: sample_ddpm(null_out, noise, ddpm_cfg, K)), K, "ddpm")
    cases[f"FM-ODE end to end (policy.predict_action_chunk), K={K}"] = (
        case(lambda: policy.predict_action_chunk(batch, sampler="ode", steps=K, noise=noise), v_call, K),
        K, "policy")

    # The diffusers scheduler alone: set_timesteps + K steps on a fixed model output.
    sched = inference_scheduler(ddpm_cfg)
    fixed_out = torch.zeros_like(noise)

    def sched_only():
        sched.set_timesteps(K, device=device)
        x = noise
        for s in sched.timesteps:
            x = sched.step(fixed_out, s, x).prev_sample
        return x

    timers = {name: c[0] for name, c in cases.items()}
    timers["_ddpm_scheduler"] = [lambda: clock(sched_only),
                                 lambda: clock(lambda: sample_ddpm(bound.model_output, noise, ddpm_cfg, K))]
    raw = rounds(clock, timers, bc.reps, bc.warmup)
    rows = []
    for name, (_, k, kind) in cases.items():
        st = _ratio_stats(raw[name], 0, 1)
        target = 1.15 if kind == "sde" else (1.05 if kind in ("ode",) else None)
        own = median([x[2] for x in raw[name]]) * 1e3 if len(raw[name][0]) > 2 else None
        call_ms = st["den_ms"] / k
        rows.append({"sampler": name, "steps": k, "kind": kind, "overhead": st["ratio"],
                     "sample_ms": st["num_ms"], "call_ms": call_ms, "target": target,
                     "own_ms": own, "predicted": None if own is None else 1 + own / (k * call_ms)})
    sch = _ratio_stats(raw["_ddpm_scheduler"], 0, 1)
    return {"size": size.label(), "size_name": size.name, "batch": B, "rows": rows,
            "ddpm_scheduler": {"scheduler_ms": sch["num_ms"], "per_step_us": sch["num_ms"] * 1e3 / K,
                               "share_of_sample": sch["ratio"], "sample_ms": sch["den_ms"]}}


# --------------------------------------------------------------------------- 2. training step
MF_DEFAULT_ROW = "MF (default: r≠t on 0.25 of rows, du/dt by finite difference)"


def _train_variants(bc: BenchConfig, size: NetSize) -> Dict[str, DecoderConfig]:
    variants = {"FM": size.config("flow_matching"), MF_DEFAULT_ROW: size.config("mean_flow")}
    for q in bc.mf_ratios:
        variants[f"MF (r≠t on {q:g} of rows, du/dt by JVP)"] = size.config(
            "mean_flow", meanflow_ratio_r_neq_t=q, meanflow_dudt="jvp")
    variants["DDPM"] = size.config("DDPM")
    return variants


def _train_step(policy, opt, batch):
    def step():
        opt.zero_grad(set_to_none=True)
        policy(batch).loss.backward()
        opt.step()
    return step


def bench_training(bc: BenchConfig, size: NetSize, clock: Clock, memory: bool, timing: bool) -> dict:
    device = torch.device(bc.device)
    B = size.train_batch
    g = torch.Generator().manual_seed(3)
    batch = {"state": torch.randn(B, 39, generator=g).to(device),
             "actions": torch.randn(B, 16, 4, generator=g).to(device)}
    steps = {}
    for name, cfg in _train_variants(bc, size).items():
        policy = _policy(cfg, device).train()
        opt = torch.optim.AdamW(policy.parameters(), lr=1e-4)
        steps[name] = _train_step(policy, opt, batch)
        steps[name]()                                            # creates the optimizer state
    out = {"size": size.label(), "size_name": size.name, "batch": B, "rows": []}
    if timing:
        fm = steps["FM"]
        timers = {name: [lambda s=s: clock(s), lambda: clock(fm)] for name, s in steps.items()}
        raw = rounds(clock, timers, bc.train_reps, bc.warmup)
        for name in steps:
            st = _ratio_stats(raw[name], 0, 1)
            target = 1.25 if name == MF_DEFAULT_ROW else (1.5 if name.startswith("MF") else None)
            out["rows"].append({"decoder": name, "step_ms": st["num_ms"], "vs_fm": st["ratio"],
                                "target": target})
    if memory:
        mem = {}
        for name, s in steps.items():
            s()
            clock.sync()
            mem[name], what = peak_step_memory(s, device)
        out["memory"] = {"what": what, "bytes": mem}
    return out


# --------------------------------------------------------------------------- 3. peers
@torch.no_grad()
def bench_peers(bc: BenchConfig, size: NetSize, clock: Clock) -> dict:
    import diffusers
    import numpy as np

    device = torch.device(bc.device)
    cfg = size.config("flow_matching")
    ddpm_cfg = size.config("DDPM")
    policy = _policy(cfg, device).eval()
    B, K = size.batch, bc.steps
    bound = policy.bind({"state": torch.randn(B, 39, device=device)})
    noise = torch.randn(B, 16, 4, device=device, generator=torch.Generator(device).manual_seed(4))

    # diffusers FlowMatchEulerDiscreteScheduler: sigma = 1 is noise; their model output is
    # dx/dsigma = noise − data = −v_ours, and t_ours = 1 − sigma = 1 − timestep/N.
    fm_sched = diffusers.FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=1.0)
    n_train = fm_sched.config.num_train_timesteps
    sigmas = np.linspace(1.0, 0.0, K + 1)[:-1]     # uniform grid = our default grid (an array: diffusers 0.30)

    def peer_fm():
        fm_sched.set_timesteps(sigmas=sigmas, device=device)
        x = noise
        for ts in fm_sched.timesteps:
            tt = (1.0 - ts / n_train).expand(B).to(noise.dtype)
            x = fm_sched.step(-bound.velocity(x, tt), ts, x).prev_sample
        return x

    # A diffusers-pipeline-style DPM-Solver loop with a fresh scheduler of the same config.
    dpm = diffusers.DPMSolverMultistepScheduler.from_config(inference_scheduler(ddpm_cfg).config)

    def peer_dpm():
        dpm.set_timesteps(K, device=device)
        x = noise
        for ts in dpm.timesteps:
            x = dpm.step(bound.model_output(x, ts.expand(B)), ts, x).prev_sample
        return x

    ours_fm = lambda: sample_ode(bound.velocity, noise, K)                      # noqa: E731
    ours_dpm = lambda: sample_ddpm(bound.model_output, noise, ddpm_cfg, K)      # noqa: E731
    pairs = {
        "FM Euler": ("diffusers FlowMatchEulerDiscreteScheduler loop", ours_fm, peer_fm),
        "DDPM DPM-Solver++": ("diffusers DPMSolverMultistepScheduler pipeline-style loop", ours_dpm, peer_dpm),
    }
    raw = rounds(clock, {n: [lambda o=o: clock(o), lambda p=p: clock(p)] for n, (_, o, p) in pairs.items()},
                 bc.reps, bc.warmup)
    rows = []
    for name, (peer, ours, theirs) in pairs.items():
        diff = float((ours().float() - theirs().float()).abs().max())
        st = _ratio_stats(raw[name], 0, 1)
        rows.append({"sampler": f"{name}, K={K}", "peer": peer, "ours_ms": st["num_ms"],
                     "peer_ms": st["den_ms"], "ours_over_peer": st["ratio"], "max_abs_diff": diff,
                     "agree": diff <= PEER_TOL})
    return {"size": size.label(), "size_name": size.name, "batch": B, "rows": rows}


# --------------------------------------------------------------------------- 4. quality vs latency
QUALITY_ROWS = [("DDPM", "ode", 1), ("DDPM", "ode", 5), ("DDPM", "ode", 10),
                ("flow_matching", "ode", 1), ("flow_matching", "ode", 5), ("flow_matching", "ode", 10),
                ("mean_flow", "ode", 1), ("mean_flow", "ode", 2),
                ("flow_matching", "sde", 10), ("mean_flow", "sde", 10)]


def _latency_ms(checkpoint: str, sampler: str, steps: int, bc: BenchConfig, clock: Clock) -> Optional[float]:
    """Median per-chunk latency (B = 1) of a saved policy, or None when it cannot be loaded."""
    path = Path(checkpoint)
    if not (path / "config.json").is_file():
        return None
    try:
        policy = ActionDecoderPolicy.from_pretrained(path, map_location=bc.device).eval()
    except (ValueError, FileNotFoundError, OSError):
        return None
    cfg = policy.config
    batch = {"state": torch.zeros(1, cfg.state_dim, device=bc.device)}
    tasks = list(cfg.extra.get("tasks") or [])
    if cfg.context_dim is not None and len(tasks) > 1:
        ctx = torch.zeros(1, 1, cfg.context_dim, device=bc.device)
        ctx[0, 0, 0] = 1.0
        batch["context"] = ctx
    fn = lambda: policy.predict_action_chunk(batch, sampler=sampler, steps=steps)  # noqa: E731
    with torch.no_grad():
        for _ in range(2):
            fn()
        return median([clock(fn) for _ in range(bc.latency_reps)]) * 1e3


def bench_quality(bc: BenchConfig, clock: Clock) -> dict:
    """Success and chunk latency per (decoder, sampler, K, actions executed per chunk) from the eval
    summaries under `bc.quality_dir`; success is the mean over every (summary, task) result, so a
    multi-task summary counts once per task."""
    found: Dict[tuple, list] = {}
    if bc.quality_dir:
        for p in sorted(Path(bc.quality_dir).rglob("*.json")):
            try:
                d = json.loads(p.read_text())
            except (OSError, json.JSONDecodeError):
                continue
            if not isinstance(d, dict) or "success_rate" not in d or "decoder_type" not in d:
                continue
            key = (d["decoder_type"], d.get("sampler") or "ode", int(d.get("steps") or 0), d.get("n_action_steps"))
            found.setdefault(key, []).append((p, d))
    keys = [k for q in QUALITY_ROWS for k in (sorted((f for f in found if f[:3] == q), key=str) or [(*q, None)])]
    keys += sorted((k for k in found if k[:3] not in QUALITY_ROWS), key=str)
    rows = []
    for key in keys:
        dec, sampler, k, n_exec = key
        entries = found.get(key, [])
        results = [float(v) for _, d in entries for v in (d.get("per_task") or {"": d["success_rate"]}).values()]
        row = {"decoder": dec, "sampler": sampler, "steps": k, "n_action_steps": n_exec, "n": len(results),
               "success_rate": None, "latency_ms": None, "source": None}
        if entries:
            row["success_rate"] = sum(results) / len(results)
            lat = [float(d["latency_ms"]) for _, d in entries if "latency_ms" in d]
            if not lat:
                lat = [x for x in (_latency_ms(str(d.get("checkpoint", "")), sampler, k, bc, clock)
                                   for _, d in entries[:1]) if x is not None]
            row["latency_ms"] = median(lat) if lat else None
            row["source"] = ", ".join(str(p) for p, _ in entries[:3]) + (" …" if len(entries) > 3 else "")
        rows.append(row)
    return {"dir": bc.quality_dir, "rows": rows}


# --------------------------------------------------------------------------- driver
def machine_info(bc: BenchConfig) -> dict:
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import os

    info = {"cpu": cpu, "logical_cpus": os.cpu_count(), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "device": bc.device,
            "date": datetime.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"),
            "python": platform.python_version(), "mode": bc.mode,
            "timer": "CUDA events" if torch.device(bc.device).type == "cuda" else "time.perf_counter"}
    try:
        import diffusers
        info["diffusers"] = diffusers.__version__
    except ImportError:
        info["diffusers"] = "not installed"
    if torch.device(bc.device).type == "cuda":
        info["gpu"] = torch.cuda.get_device_name()
    try:
        info["load_average"] = os.getloadavg()
    except OSError:
        pass
    return info


def run_suite(bc: BenchConfig, log=print) -> dict:
    from .report import write_report

    clock = Clock(torch.device(bc.device))
    results: dict = {"machine": machine_info(bc), "config": {
        "steps": bc.steps, "mf_steps": list(bc.mf_steps), "reps": bc.reps, "train_reps": bc.train_reps,
        "warmup": bc.warmup, "sizes": [dataclasses.asdict(s) for s in bc.sizes]}}
    if "sampling" in bc.sections:
        results["sampling"] = []
        for size in bc.sizes:
            log(f"[bench] sampler overhead: {size.label()} (B={size.batch})", flush=True)
            results["sampling"].append(bench_sampling(bc, size, clock))
    if "training" in bc.sections or "memory" in bc.sections:
        results["training"] = []
        for size in bc.sizes:
            log(f"[bench] training step / memory: {size.label()} (B={size.train_batch})", flush=True)
            results["training"].append(bench_training(bc, size, clock, memory="memory" in bc.sections,
                                                      timing="training" in bc.sections))
    if "peers" in bc.sections:
        results["peers"] = []
        for size in bc.sizes:
            log(f"[bench] peers: {size.label()} (B={size.batch})", flush=True)
            results["peers"].append(bench_peers(bc, size, clock))
    if "quality" in bc.sections:
        log(f"[bench] quality vs latency (from {bc.quality_dir or 'no --quality-dir'})", flush=True)
        results["quality"] = bench_quality(bc, clock)
    path = write_report(results, Path(bc.out), plot=bc.plot)
    log(f"[bench] wrote {path}", flush=True)
    return results


def finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)
