"""Multimodal benchmark: decoders on tasks whose demonstrations have two modes and averaging fails.

    OMP_NUM_THREADS=1 python -m benchmarks multimodal            # → docs/benchmarks/multimodal.{md,json}
    python -m benchmarks multimodal --quick                       # fewer steps → outputs/multimodal-quick/
    python -m benchmarks multimodal --only synthetic --decoders mean_flow --recipe one_step_share=0.25
    python -m benchmarks multimodal --only synthetic --decoders mean_flow --recipe distill=1   # FM teacher
    python -m benchmarks multimodal --only obstacle --steps 12000 --device cuda   # train and sample on a GPU

(a) synthetic: state s ~ N(0, I₄); the chunk [16, 4] is one of two routes
    0.5·s·h ± sin(πh)·(1, −0.6, 0.8, 0.4), h ∈ [0, 1], 50/50 (mode separation ≈ 1.0 RMS).
(b) obstacle routes: a 2-D point mass passes a disc obstacle above or below (`envs.obstacle_routes`),
    start, obstacle and goal on one axis, the scripted expert choosing 50/50 per episode; closed loop,
    re-planning every 8 actions.
Each decoder is trained once per task through `ActionDecoderPolicy` (hidden 64, 2 layers, batch 128,
AdamW 1e-3, warm-up + cosine, weight EMA as `train.py`) and sampled at each column's K.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import math
import platform
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

import action_decoder.policy as policy_mod
from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.cli import check_device
from action_decoder.flows import losses
from action_decoder.train import lr_factor, weight_average

# column: (label, decoder_type, sampler, K)
COLUMNS = [("DDPM K=10", "DDPM", "ode", 10), ("FM K=1", "flow_matching", "ode", 1),
           ("FM K=10", "flow_matching", "ode", 10), ("MF K=1", "mean_flow", "ode", 1),
           ("MF K=2", "mean_flow", "ode", 2), ("FM-SDE K=10", "flow_matching", "sde", 10)]
RECIPE_FIELDS = {"ratio": "meanflow_ratio_r_neq_t", "time_dist": "meanflow_time_dist",
                 "adaptive_p": "meanflow_adaptive_p", "adaptive_c": "meanflow_adaptive_c",
                 "flow_prediction": "flow_prediction", "dudt": "meanflow_dudt", "target": "meanflow_target",
                 "one_step_share": "meanflow_one_step_share"}
STRING_KEYS = ("time_dist", "flow_prediction", "tangent", "dudt", "target")
LOSS_OPTIONS = ("tangent",)   # `meanflow_loss` keywords with no config field (measured, not adopted)
TRAIN_OPTIONS = ("distill",)   # recipe keys of this benchmark's training loop (measured, not in the library)
TEACHER_STEPS = 10             # Euler steps of the flow-matching teacher's ODE for `distill`
RECIPE_KEYS = sorted((*RECIPE_FIELDS, *LOSS_OPTIONS, *TRAIN_OPTIONS))


# ----------------------------------------------------------------------------------------- metrics

def mode_metrics(samples: torch.Tensor, modes: torch.Tensor, tol: float) -> dict:
    """Samples [N, S, H, D] (S per state) against the true conditional: modes [N, M, H, D], equal weights.

    Distances are RMS over H×D. on_mode: share of samples within `tol` of their nearest mode.
    majority_share: share of the most frequent mode among all on-mode samples (1/M is balanced).
    coverage: share of states whose S samples put at least one on-mode sample on every mode.
    energy: energy distance between each state's S samples and the exact mixture (closed form on
    the reference side, V-statistic on the samples, so exactly 0 for samples split evenly on the
    modes and ≥ 0 always), averaged over states.
    """
    M = modes.shape[1]
    rms = lambda a, b: (a - b).square().mean((-2, -1)).sqrt()
    to_mode = rms(samples[:, :, None], modes[:, None])                          # [N, S, M]
    dist, which = to_mode.min(2)                                                 # [N, S]
    on = dist < tol
    counts = torch.stack([((which == m) & on).sum(1) for m in range(M)], 1)     # [N, M]
    total = counts.sum()
    pairs = rms(samples[:, :, None], samples[:, None]).mean((1, 2))             # [N] E|X − X'|
    spread = rms(modes[:, :, None], modes[:, None]).mean((1, 2))                # [N] E|Y − Y'|
    energy = 2 * to_mode.mean((1, 2)) - pairs - spread                           # [N]
    return {"on_mode": on.float().mean().item(),
            "majority_share": (counts.sum(0).max() / total).item() if total > 0 else float("nan"),
            "coverage": (counts > 0).all(1).float().mean().item(),
            "energy": energy.clamp(min=0).mean().item(),
            "rms_to_nearest": dist.mean().item()}


# ------------------------------------------------------------------------------------------- tasks

def routes(state: torch.Tensor, H: int = 16) -> torch.Tensor:
    """The two routes [B, 2, H, 4] for states [B, 4]: a shared state-dependent base ± a bend."""
    h = torch.linspace(0, 1, H)
    base = 0.5 * state[:, None, :] * h[None, :, None]                                   # [B, H, 4]
    bend = torch.sin(math.pi * h)[:, None] * torch.tensor([1.0, -0.6, 0.8, 0.4])        # [H, 4]
    return torch.stack([base + bend, base - bend], 1)


def synthetic_batch(gen: torch.Generator, batch: int):
    state = torch.randn(batch, 4, generator=gen)                                         # [B, 4]
    pick = torch.randint(0, 2, (batch,), generator=gen)
    return state, routes(state)[torch.arange(batch), pick]                               # [B, H, 4]


def separation() -> float:
    """RMS distance between the two synthetic routes (state-independent)."""
    r = routes(torch.zeros(1, 4))
    return (r[0, 0] - r[0, 1]).square().mean().sqrt().item()


def dataset_batch(states: torch.Tensor, chunks: torch.Tensor):
    def draw(gen: torch.Generator, batch: int):
        i = torch.randint(0, states.shape[0], (batch,), generator=gen)
        return states[i], chunks[i]
    return draw


# ---------------------------------------------------------------------------------------- training

@dataclass
class Budget:
    steps: int = 1500
    batch: int = 128
    hidden: int = 64
    layers: int = 2
    eval_states: int = 256
    samples: int = 8
    episodes: int = 50
    demos: int = 100
    latency_reps: int = 30
    recipe: dict = field(default_factory=dict)
    device: str = "cpu"        # where the policy trains and samples; data and environments stay on the CPU
    log_every: int = 0         # print the training step and loss to stderr every this many steps (0: never)
    rtc_max_delay: int = 0     # training-time real-time chunking (DecoderConfig.rtc_max_delay; 0: off)
    rtc_delay_dist: str = DecoderConfig.rtc_delay_dist   # how its delays are drawn (DecoderConfig.rtc_delay_dist)
    rtc_balance_rows: bool = False   # its loss rows weighted 1/P(d <= j) (DecoderConfig.rtc_balance_rows)


def parse_recipe(items: list[str], flag: str = "--recipe") -> dict:
    """{key: value} from KEY=VALUE strings with keys in RECIPE_KEYS (numbers as floats, STRING_KEYS as given)."""
    recipe = {}
    for kv in items:
        key, sep, value = kv.partition("=")
        if not sep or key not in RECIPE_KEYS:
            raise ValueError(f"{flag}: expected KEY=VALUE with KEY in {RECIPE_KEYS}, got {kv!r}")
        try:
            recipe[key] = value if key in STRING_KEYS else float(value)
        except ValueError:
            raise ValueError(f"{flag}: expected a number for {key}, got {value!r}") from None
    return recipe


def use_loss_options(options: dict) -> None:
    """Make the policy's MeanFlow loss take `options` (keywords of `meanflow_loss`) in this process."""
    policy_mod.meanflow_loss = functools.partial(losses.meanflow_loss, **options) if options else losses.meanflow_loss


def make_policy(decoder: str, state_dim: int, action_dim: int, b: Budget) -> ActionDecoderPolicy:
    extra = {"flow_prediction": "sample" if decoder == "mean_flow" else "velocity"}
    extra.update({RECIPE_FIELDS[k]: v for k, v in b.recipe.items()
                  if k in RECIPE_FIELDS} if decoder == "mean_flow" else {})
    use_loss_options({k: v for k, v in b.recipe.items() if k in LOSS_OPTIONS})
    cfg = DecoderConfig(decoder_type=decoder, state_dim=state_dim, action_dim=action_dim, action_chunk_size=16,
                        hidden_size=b.hidden, num_hidden_layers=b.layers, num_attention_heads=4,
                        num_key_value_heads=2, normalization_mode="identity", prediction_type="sample",
                        rtc_max_delay=b.rtc_max_delay, rtc_delay_dist=b.rtc_delay_dist,
                        rtc_balance_rows=b.rtc_balance_rows, **extra)
    return ActionDecoderPolicy(cfg)


def distillation_term(student, teacher, state: torch.Tensor, noise: torch.Generator) -> torch.Tensor:
    """Mean squared distance between the student's one-step chunk and a flow-matching teacher's
    K = TEACHER_STEPS ODE chunk from the same noise (the teacher's noise → data coupling)."""
    cfg = student.config
    z = torch.randn(state.shape[0], cfg.action_chunk_size, cfg.action_dim, generator=noise,
                    device=state.device)                                                         # [B, H, D]
    with torch.no_grad():
        target = teacher.sample({"state": state}, sampler="ode", steps=TEACHER_STEPS, noise=z).actions
    one = student.sample({"state": state}, sampler="ode", steps=1, noise=z).actions           # [B, H, D]
    return (one - target).square().mean()


def optimizer_step(policy, batch: dict, noise: torch.Generator, opt, sched, params, teacher=None,
                   distill: float = 0.0) -> torch.Tensor:
    """One AdamW step on the policy's loss (plus `distill` × `distillation_term` with a teacher),
    gradients clipped at norm 1, then the schedule; returns the loss."""
    loss = policy.compute_loss(batch, noise).loss
    if teacher is not None and distill > 0:
        loss = loss + distill * distillation_term(policy, teacher, batch["state"], noise)
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, 1.0)
    opt.step()
    sched.step()
    return loss


def train(decoder: str, draw, state_dim: int, action_dim: int, b: Budget, seed: int) -> tuple:
    """Train with train.py's optimiser, schedule and weight EMA; returns (EMA policy in eval mode, s).

    With recipe `distill` = λ (MeanFlow only), a flow-matching teacher is trained first on the same
    budget and the student's loss adds λ × `distillation_term`; the seconds include the teacher's."""
    distill = float(b.recipe.get("distill", 0.0)) if decoder == "mean_flow" else 0.0
    teacher, teacher_s = None, 0.0
    if distill > 0:
        teacher, teacher_s = train("flow_matching", draw, state_dim, action_dim,
                                   Budget(**{**b.__dict__, "recipe": {}}), seed)
        teacher.requires_grad_(False)
    torch.manual_seed(seed)
    policy = make_policy(decoder, state_dim, action_dim, b).to(b.device)
    policy.sigma.requires_grad_(False)
    params = [p for p in policy.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=1e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: lr_factor(s, 100, b.steps))
    ema = weight_average(policy, 0.999)
    data = torch.Generator().manual_seed(seed * 1000)                    # batches are drawn on the CPU
    noise = torch.Generator(b.device).manual_seed(seed * 1000 + 500)     # the loss's noise, on the policy's device
    t0 = time.process_time()
    for step in range(1, b.steps + 1):
        state, actions = draw(data, b.batch)
        batch = {"state": state.to(b.device), "actions": actions.to(b.device)}
        loss = optimizer_step(policy, batch, noise, opt, sched, params, teacher, distill)
        ema.update_parameters(policy)
        if b.log_every and step % b.log_every == 0:
            print(json.dumps({"decoder": decoder, "step": step, "of": b.steps, "loss": round(loss.item(), 5),
                              "cpu_s": round(time.process_time() - t0, 1)}), file=sys.stderr, flush=True)
    trained = ema.module.eval()
    return trained, round(time.process_time() - t0 + teacher_s, 1)


def device_of(policy) -> torch.device:
    return next(policy.parameters()).device


def sample(policy, state: torch.Tensor, sampler: str, steps: int, seed: int) -> torch.Tensor:
    """Chunks [B, H, D] on the CPU for states [B, S] (any device)."""
    device = device_of(policy)
    with torch.no_grad():
        return policy.sample({"state": state.to(device)}, sampler=sampler, steps=steps,
                             generator=torch.Generator(device).manual_seed(seed)).actions.cpu()   # [B, H, D]


def latency_ms(policy, state_dim: int, sampler: str, steps: int, reps: int) -> float:
    """Median wall time of one chunk (batch 1, back on the CPU) over `reps` calls after 3 warm-up calls."""
    state = torch.zeros(1, state_dim)
    times = []
    for i in range(reps + 3):
        t0 = time.perf_counter()
        sample(policy, state, sampler, steps, i)                         # .cpu() waits for the GPU
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times[3:])


# --------------------------------------------------------------------------------------- the tasks

def run_synthetic(decoders: list, b: Budget, seed: int) -> dict:
    tol = 0.1 * separation()
    state = torch.randn(b.eval_states, 4, generator=torch.Generator().manual_seed(12345))
    modes = routes(state)                                                                # [N, 2, H, 4]
    rep = state.repeat_interleave(b.samples, 0)                                          # [N·S, 4]
    out = {}
    for decoder in decoders:
        policy, train_s = train(decoder, synthetic_batch, 4, 4, b, seed)
        for label, dec, sampler, k in COLUMNS:
            if dec != decoder:
                continue
            chunk = sample(policy, rep, sampler, k, 777).reshape(b.eval_states, b.samples, 16, 4)
            out[label] = {**mode_metrics(chunk, modes, tol), "latency_ms": latency_ms(policy, 4, sampler, k,
                                                                                       b.latency_reps),
                          "train_cpu_s": train_s}
            print(json.dumps({"task": "synthetic", "column": label, **out[label]}), flush=True)
    return out


def run_obstacle(decoders: list, b: Budget, seed: int) -> dict:
    from action_decoder.envs.obstacle_routes import OBS_DIM, ACTION_DIM, expert_dataset, rollout

    states, chunks = expert_dataset(b.demos, seed)
    out = {}
    for decoder in decoders:
        policy, train_s = train(decoder, dataset_batch(states, chunks), OBS_DIM, ACTION_DIM, b, seed)
        for label, dec, sampler, k in COLUMNS:
            if dec != decoder:
                continue
            gen = torch.Generator(b.device).manual_seed(777)

            def act(obs, policy=policy, sampler=sampler, k=k, gen=gen):
                with torch.no_grad():
                    return policy.sample({"state": torch.from_numpy(obs)[None].to(b.device)}, sampler=sampler,
                                         steps=k, generator=gen).actions[0].cpu().numpy()
            res = [rollout(act, 1_000_000 + seed * 1000 + j) for j in range(b.episodes)]
            ok = [r for r in res if r["success"]]
            out[label] = {"success": len(ok) / len(res),
                          "collided": sum(r["collided"] for r in res) / len(res),
                          "above_share": (sum(r["route"] == 1 for r in ok) / len(ok)) if ok else float("nan"),
                          "latency_ms": latency_ms(policy, OBS_DIM, sampler, k, b.latency_reps),
                          "train_cpu_s": train_s}
            print(json.dumps({"task": "obstacle", "column": label, **out[label]}), flush=True)
    return out


# ------------------------------------------------------------------------------------------ report

def table(results: dict) -> str:
    cols = [c[0] for c in COLUMNS if any(c[0] in r for r in results.values())]
    rows = [("synthetic", "on_mode", "on a mode (RMS < 0.1 × separation)", "{:.0%}"),
            ("synthetic", "majority_share", "majority mode's share (50 % balanced)", "{:.0%}"),
            ("synthetic", "coverage", "states with both modes in 8 samples (exact: 99 %)", "{:.0%}"),
            ("synthetic", "energy", "energy distance to the true conditional (midpoint: 0.5)", "{:.3f}"),
            ("synthetic", "latency_ms", "latency per chunk, ms (synthetic net)", "{:.2f}"),
            ("obstacle", "success", "obstacle routes: success", "{:.0%}"),
            ("obstacle", "collided", "obstacle routes: collisions", "{:.0%}"),
            ("obstacle", "above_share", "obstacle routes: share passing above (of successes)", "{:.0%}"),
            ("obstacle", "latency_ms", "latency per chunk, ms (obstacle net)", "{:.2f}")]
    lines = ["| metric | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for task, key, name, fmt in rows:
        if task not in results:
            continue
        cells = [fmt.format(results[task][c][key]) if c in results[task] and results[task][c][key] == results[task][c][key]
                 else "–" for c in cols]                                               # NaN (no on-mode sample): –
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks multimodal", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="300 training steps, fewer samples (→ outputs/)")
    p.add_argument("--tiny", action="store_true", help="a smoke test in seconds (→ outputs/)")
    p.add_argument("--only", choices=["synthetic", "obstacle"], default=None)
    p.add_argument("--decoders", nargs="+", default=["DDPM", "flow_matching", "mean_flow"],
                   choices=["DDPM", "flow_matching", "mean_flow"])
    p.add_argument("--steps", type=int, default=None, help="training steps (default 1500)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--recipe", nargs="*", default=[], metavar="KEY=VALUE",
                   help=f"MeanFlow recipe overrides, keys {RECIPE_KEYS}")
    p.add_argument("--dudt", choices=["jvp", "finite_difference"], default=None,
                   help="MeanFlow's du/dt in training (DecoderConfig.meanflow_dudt; default: the config's)")
    p.add_argument("--device", default="cpu",
                   help="where the policies train and sample: cpu (default, one thread), cuda[:N] or auto")
    p.add_argument("--log-every", type=int, default=0, metavar="N",
                   help="print the training step and loss to stderr every N steps (default: never)")
    p.add_argument("--out", default=None, help="directory for the JSON (default docs/benchmarks/multimodal.json "
                   "for the full run; else outputs/multimodal[-quick]/multimodal_run.json)")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    check_device(a.device)
    if a.device == "auto":
        a.device = "cuda" if torch.cuda.is_available() else "cpu"
    b = Budget()
    if a.quick:
        b = Budget(steps=300, eval_states=128, episodes=20, demos=50, latency_reps=10)
    if a.tiny:
        b = Budget(steps=3, hidden=32, layers=1, eval_states=4, samples=4, episodes=1, demos=2, latency_reps=1)
    if a.steps is not None:
        b.steps = a.steps
    b.device = a.device
    if a.log_every < 0:
        raise ValueError(f"--log-every: expected a number of steps ≥ 0, got {a.log_every}")
    b.log_every = a.log_every
    b.recipe.update(parse_recipe(a.recipe))
    if a.dudt is not None:
        b.recipe["dudt"] = a.dudt
    tasks = [a.only] if a.only else ["synthetic", "obstacle"]
    try:
        results = {t: (run_synthetic if t == "synthetic" else run_obstacle)(a.decoders, b, a.seed) for t in tasks}
    finally:
        use_loss_options({})
    full = (not (a.quick or a.tiny or a.only or a.recipe or a.steps is not None) and len(set(a.decoders)) == 3
            and a.device == "cpu")
    out = Path(a.out or ("docs/benchmarks" if full else "outputs/multimodal-quick" if a.quick or a.tiny
                         else "outputs/multimodal"))
    out.mkdir(parents=True, exist_ok=True)
    meta = {"date": datetime.date.today().isoformat(), "machine": platform.processor() or platform.machine(),
            "torch": torch.__version__, "threads": torch.get_num_threads(), "seed": a.seed,
            "device": torch.cuda.get_device_name(a.device) if a.device.startswith("cuda") else a.device,
            "budget": b.__dict__, "argv": argv}
    name = "multimodal" if full else "multimodal_run"                 # a partial run never replaces the table's
    (out / f"{name}.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(table(results))
    return 0
