"""A MeanFlow train step against a flow-matching one, per way of getting du/dt (issue 28).

    python -m benchmarks.train_step_cost                 # timing table (paired rounds), both sizes
    python -m benchmarks.train_step_cost --quality       # + the synthetic two-route task, jvp vs fd
    python -m benchmarks.train_step_cost --precision-only [--checkpoint DIR]   # du/dt error vs step
    python -m benchmarks.train_step_cost --device cuda --autocast none,bf16 --inner 20 --out docs/benchmarks/meanflow_cost_gpu.json

Timing: one AdamW step (zero_grad, loss, backward, step) of the CLI's recipe: batch 128, MeanFlow
with r ≠ t on 0.25 of the rows, uniform times, p = 0.5, the clean-chunk head; flow matching with
the velocity head. Each round runs every (variant, FM) pair back to back, pairs in a rotated order
and the two timers of a pair in alternating order (`timing.rounds`); the ratio is taken per round,
then the median and the quartiles over rounds are reported. Variants:

- "jvp": `meanflow_dudt="jvp"` (torch.func.jvp on the r ≠ t rows, a plain call on the others).
- "finite_difference": `meanflow_dudt="finite_difference"` through `compute_loss`, the batching
  `meanflow_loss` chooses for the device (`fd_one_call=None`: one call on CUDA, two elsewhere).
- "fd, one call (B + 2n rows)" / "fd, two calls (B, then 2n rows)": the same central difference
  with its 2n shifted rows in u's grad call, or in a second, no-grad call (`fd_one_call=True` /
  `False`). Under autocast only two calls exist (the difference runs in float32).
- "forward difference (n rows)": (u(z + h·v, t + h, r) − u)/h with h = 1e-5 in a no-grad call
  over n rows (this module's own loss); it reuses u but is ~10× less accurate.

`--device cuda --autocast none,bf16 --inner 20` times the same steps on a GPU, each timer over
20 back-to-back steps between CUDA events, in float32 and under bf16 autocast.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import functools
import json
import os
import platform
import sys
from pathlib import Path
from typing import Callable, Dict, List, Optional

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

from action_decoder import ActionDecoderPolicy, DecoderConfig  # noqa: E402
from action_decoder.flows import losses  # noqa: E402
from action_decoder.flows.paths import interpolate  # noqa: E402

from .timing import Clock, rounds  # noqa: E402

SIZES = {   # name: (hidden, layers, heads, kv heads)
    "CLI default (hidden 96, 3 layers)": (96, 3, 4, 2),            # TrainConfig's network
    "large (hidden 128, 4 layers)": (128, 4, 4, 2),                # suite.py's "large", DecoderConfig's default
}
BATCH = 128                                                        # TrainConfig.batch_size
FORWARD_STEP = 1e-5


def _policy(decoder: str, size: tuple, **kw) -> ActionDecoderPolicy:
    hidden, layers, heads, kv = size
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type=decoder, hidden_size=hidden, num_hidden_layers=layers, num_attention_heads=heads,
                        num_key_value_heads=kv, state_dim=39, action_dim=4, action_chunk_size=16,
                        flow_prediction="sample" if decoder == "mean_flow" else "velocity", **kw)
    return ActionDecoderPolicy(cfg).train()


def _fd_loss(policy: ActionDecoderPolicy, batch: dict, one_call: bool) -> torch.Tensor:
    """The library's MeanFlow loss (`compute_loss`'s arguments) with du/dt by central difference,
    its 2n shifted rows in u's call (`one_call`) or in a second, no-grad call."""
    cfg = policy.config
    cond = policy._prepare(batch)
    a = policy.normalizers["actions"].normalize(batch["actions"].float())            # [B, H, D]
    return losses.meanflow_loss(policy._flow_net, a, None, cond, ratio_r_neq_t=cfg.meanflow_ratio_r_neq_t,
                                time_mean=cfg.meanflow_time_mean, time_std=cfg.meanflow_time_std,
                                adaptive_p=cfg.meanflow_adaptive_p, adaptive_c=cfg.meanflow_adaptive_c,
                                time_dist=cfg.meanflow_time_dist, dudt="finite_difference",
                                fd_one_call=one_call)


def _forward_difference_loss(policy: ActionDecoderPolicy, batch: dict) -> torch.Tensor:
    """The library's MeanFlow loss with du/dt by a forward difference (u reused, n extra rows)."""
    cfg = policy.config
    cond = policy._prepare(batch)
    a = policy.normalizers["actions"].normalize(batch["actions"].float())            # [B, H, D]
    B = a.shape[0]
    t, r, n = losses.sample_meanflow_times(B, cfg.meanflow_ratio_r_neq_t, cfg.meanflow_time_mean,
                                           cfg.meanflow_time_std, device=a.device, dist=cfg.meanflow_time_dist)
    e = torch.randn(a.shape, device=a.device)
    z, v = interpolate(e, a, t), a - e
    net, head = policy._flow_net, slice(0, n)
    u = net(z, t, r, **cond)
    with torch.no_grad():
        dudt = (net(z[head] + FORWARD_STEP * v[head], t[head] + FORWARD_STEP, r[head],
                    **losses.slice_cond(cond, head)) - u[head]) / FORWARD_STEP
    target = torch.cat([v[head] - (t[head] - r[head]).reshape(-1, 1, 1) * dudt, v[n:]])
    return losses._adaptive_mean(u - target, cfg.meanflow_adaptive_p, cfg.meanflow_adaptive_c)


def _step(policy: ActionDecoderPolicy, batch: dict, loss: Callable, autocast: Optional[torch.dtype] = None
          ) -> Callable[[], None]:
    """One AdamW step of `policy` on `batch` (on the batch's device), the loss under autocast to
    `autocast` when given (weights and optimizer stay float32: mixed-precision training)."""
    device = batch["actions"].device
    policy.to(device)
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-4)

    def step():
        opt.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=autocast or torch.float32, enabled=autocast is not None):
            value = loss(policy, batch)
        value.backward()
        opt.step()
    step()                                                                     # the optimizer state
    return step


def variants(size: tuple, batch: dict, autocast: Optional[torch.dtype] = None) -> Dict[str, Callable[[], None]]:
    lib = lambda p, b: p.compute_loss(b).loss                                  # noqa: E731
    step = functools.partial(_step, autocast=autocast)
    one_call = {} if autocast else {"fd, one call (B + 2n rows)": step(
        _policy("mean_flow", size), batch, functools.partial(_fd_loss, one_call=True))}
    return {
        "FM": step(_policy("flow_matching", size), batch, lib),
        "jvp": step(_policy("mean_flow", size, meanflow_dudt="jvp"), batch, lib),
        "finite_difference": step(_policy("mean_flow", size, meanflow_dudt="finite_difference"), batch, lib),
        **one_call,
        "fd, two calls (B, then 2n rows)": step(_policy("mean_flow", size), batch,
                                                functools.partial(_fd_loss, one_call=False)),
        "forward difference (n rows)": step(_policy("mean_flow", size), batch, _forward_difference_loss),
    }


def _quantile(xs: List[float], q: float) -> float:
    """The q-quantile, interpolating linearly between order statistics at position q·(n − 1)
    (q = 0.5: the median, the mean of the two middle values for an even count)."""
    xs = sorted(xs)
    pos = q * (len(xs) - 1)
    lo = int(pos)
    return xs[lo] + (xs[min(lo + 1, len(xs) - 1)] - xs[lo]) * (pos - lo)


def time_size(name: str, size: tuple, reps: int, warmup: int, device: str = "cpu",
              autocast: Optional[torch.dtype] = None, inner: int = 1) -> dict:
    """Paired rounds of each MeanFlow variant's step against the FM step; on CUDA each timer
    covers `inner` back-to-back steps between two events (a step of these networks is a few ms)."""
    g = torch.Generator().manual_seed(3)
    batch = {"state": torch.randn(BATCH, 39, generator=g).to(device),
             "actions": torch.randn(BATCH, 16, 4, generator=g).to(device)}
    steps = variants(size, batch, autocast)
    clock = Clock(torch.device(device))
    fm = steps["FM"]
    timers = {k: [lambda s=s: clock(s, inner), lambda: clock(fm, inner)] for k, s in steps.items() if k != "FM"}
    raw = rounds(clock, timers, reps, warmup)
    fm_ms = [s[1] * 1e3 for k in raw for s in raw[k]]
    rows = [{"variant": "FM", "step_ms": _quantile(fm_ms, 0.5), "vs_fm": 1.0, "q25": 1.0, "q75": 1.0}]
    for k, samples in raw.items():
        ratio = [s[0] / s[1] for s in samples]
        rows.append({"variant": k, "step_ms": _quantile([s[0] * 1e3 for s in samples], 0.5),
                     "vs_fm": _quantile(ratio, 0.5), "q25": _quantile(ratio, 0.25), "q75": _quantile(ratio, 0.75),
                     "min": min(ratio), "max": max(ratio), "ratios": ratio})
    return {"size": name, "batch": BATCH, "rounds": reps, "rows": rows, "device": device,
            "autocast": str(autocast).replace("torch.", "") if autocast else "none"}


def quality(seeds: List[int], steps: int, methods=("jvp", "finite_difference"), tiny: bool = False,
            save_dir: Optional[str] = None) -> List[dict]:
    """The multimodal benchmark's synthetic two-route task (`benchmarks/multimodal.py`, the "MF K=1"
    model: clean-chunk head, hidden 64, 2 layers, batch 128, weight EMA), trained with each du/dt.

    Per (method, seed): on-route share, coverage and energy distance at K = 1 and 2 (256 states ×
    8 samples); `train_loss`: the mean training loss over the last 100 steps (each method's own
    target); `heldout_loss`: the EMA model's MeanFlow loss with the exact JVP target on 16 fixed
    batches of 128 (the same batches and noise for every run). `save_dir`: each EMA model is saved
    there as `mf_<dudt>_seed<seed>/` (for `--precision-only --checkpoint`)."""
    from . import multimodal as mm

    b = mm.Budget(steps=steps) if not tiny else mm.Budget(steps=steps, hidden=32, layers=1, eval_states=4, samples=4)
    tol = 0.1 * mm.separation()
    state = torch.randn(b.eval_states, 4, generator=torch.Generator().manual_seed(12345))
    modes, rep = mm.routes(state), state.repeat_interleave(b.samples, 0)                # [N, 2, H, 4], [N·S, 4]
    out, make = [], mm.make_policy
    for dudt in methods:
        for seed in seeds:
            logged: List[float] = []

            def logging_policy(*args, **kw):
                policy = make(*args, **kw)
                step = policy.compute_loss
                policy.compute_loss = lambda *x, **y: _logged(step(*x, **y), logged)
                return policy
            mm.make_policy, b.recipe = logging_policy, {"dudt": dudt}       # train() looks it up here
            try:
                policy, train_s = mm.train("mean_flow", mm.synthetic_batch, 4, 4, b, seed)
            finally:
                mm.make_policy = make
            res = {"dudt": dudt, "seed": seed, "steps": steps, "train_cpu_s": train_s,
                   "train_loss": sum(logged[-100:]) / len(logged[-100:]), "heldout_loss": _heldout(policy, mm)}
            for k in (1, 2):
                chunk = mm.sample(policy, rep, "ode", k, 777).reshape(b.eval_states, b.samples, 16, 4)
                res[f"K{k}"] = mm.mode_metrics(chunk, modes, tol)
            if save_dir:
                policy.save_pretrained(Path(save_dir) / f"mf_{dudt}_seed{seed}")
            print(json.dumps(res), flush=True)
            out.append(res)
    return out


def _logged(output, log: List[float]):
    log.append(output.loss.item())
    return output


def _heldout(policy: ActionDecoderPolicy, mm, batches: int = 16) -> float:
    """Mean MeanFlow loss (exact JVP target, no grad on weights) over fixed synthetic batches."""
    exact = copy.deepcopy(policy)
    exact.config.meanflow_dudt = "jvp"
    data, noise = torch.Generator().manual_seed(99), torch.Generator().manual_seed(98)
    total = 0.0
    for _ in range(batches):
        state, actions = mm.synthetic_batch(data, 128)
        with torch.no_grad():
            total += ActionDecoderPolicy.compute_loss(exact, {"state": state, "actions": actions}, noise).loss.item()
    return total / batches


def quality_table(rows: List[dict]) -> str:
    lines = ["| seed | du/dt | on a route K=1 | K=2 | coverage K=1 | energy K=1 | K=2 | rms to route K=1 | "
             "train loss (last 100) | held-out loss (JVP target) | train CPU s |", "|---" * 11 + "|"]
    for r in rows:
        k1, k2 = r["K1"], r["K2"]
        lines.append(f"| {r['seed']} | {r['dudt']} | {k1['on_mode']:.0%} | {k2['on_mode']:.0%} | {k1['coverage']:.0%} | "
                     f"{k1['energy']:.3f} | {k2['energy']:.3f} | {k1['rms_to_nearest']:.3f} | {r['train_loss']:.3f} | "
                     f"{r['heldout_loss']:.3f} | {r['train_cpu_s']:.0f} |")
    return "\n".join(lines)


def precision(checkpoint: Optional[str] = None, batch: int = 256) -> dict:
    """Error of the float32 target v − (t − r)·du/dt per way of getting du/dt, against the float64
    JVP, on the CLI's network (random weights, clean-chunk head) or a saved MeanFlow checkpoint;
    random chunks, states N(0, 0.3²) (checkpoint) or N(0, 1), times uniform with r ≠ t on all rows."""
    torch.manual_seed(0)
    if checkpoint:
        policy = ActionDecoderPolicy.from_pretrained(checkpoint)
    else:
        policy = _policy("mean_flow", next(iter(SIZES.values())))
    policy.eval()
    g = torch.Generator().manual_seed(1)
    state = torch.randn(batch, policy.config.state_dim, generator=g) * (0.3 if checkpoint else 1.0)
    a = 0.5 * torch.randn(batch, 16, policy.config.action_dim, generator=g)
    t, r, _ = losses.sample_meanflow_times(batch, 1.0, 0.4, 1.0, g, dist="uniform")
    e = torch.randn(a.shape, generator=g)
    z, v = interpolate(e, a, t), a - e
    p64 = copy.deepcopy(policy).double()

    def bound(pol, dtype):
        cond = pol._prepare({"state": state.to(dtype)})
        return lambda x, tt, rr: pol._flow_net(x, tt, rr, **cond)

    f32, f64 = bound(policy, torch.float32), bound(p64, torch.float64)
    gap = (t - r).double()[:, None, None]
    with torch.no_grad():
        ref = torch.func.jvp(f64, (z.double(), t.double(), r.double()),
                             (v.double(), torch.ones_like(t).double(), torch.zeros_like(r).double()))[1]
        target = v.double() - gap * ref
        rms = lambda x: x.square().mean().sqrt().item()                                  # noqa: E731
        err = lambda d: {"rms": rms(gap * (d.double() - ref)), "max": (gap * (d.double() - ref)).abs().max().item()}  # noqa: E731
        out = {"network": checkpoint or "CLI default, random weights", "target_rms": rms(target),
               "dudt_rms": rms(ref), "dudt_max": ref.abs().max().item(),
               "jvp_float32": err(torch.func.jvp(f32, (z, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))[1]),
               "steps": []}
        for h in (1e-4, 3e-5, 1e-5, 3e-6):
            central = (f32(z + h * v, t + h, r) - f32(z - h * v, t - h, r)) / (2 * h)
            forward = (f32(z + h * v, t + h, r) - f32(z, t, r)) / h
            out["steps"].append({"h": h, "central": err(central), "forward": err(forward)})
    return out


def precision_table(prec: List[dict]) -> str:
    lines = ["| network | target rms | du/dt | step h | central: rms / max error | forward: rms / max error |",
             "|---|---|---|---|---|---|"]
    for p in prec:
        j = p["jvp_float32"]
        lines.append(f"| {p['network']} | {p['target_rms']:.2f} | JVP in float32 | – | {j['rms']:.1e} / {j['max']:.1e} | |")
        for s in p["steps"]:
            c, f = s["central"], s["forward"]
            lines.append(f"| | | difference | {s['h']:.0e} | {c['rms']:.1e} / {c['max']:.1e} | "
                         f"{f['rms']:.1e} / {f['max']:.1e} |")
    return "\n".join(lines)


def table(results: List[dict]) -> str:
    # Runs on a GPU or under autocast name their autocast and keep two decimals of a millisecond.
    settings = any(res.get("device", "cpu") != "cpu" or res.get("autocast", "none") != "none" for res in results)
    lines = ["| network (batch 128) | " + ("autocast | " if settings else "") + "variant | step ms (median) | "
             "÷ FM step (median) | quartiles | min–max |", "|---" * (7 if settings else 6) + "|"]
    for res in results:
        for row in res["rows"]:
            spread = "" if row["variant"] == "FM" else f"{row['q25']:.2f}–{row['q75']:.2f}"
            full = "" if row["variant"] == "FM" else f"{row['min']:.2f}–{row['max']:.2f}"
            ms = f"{row['step_ms']:.2f}" if settings else f"{row['step_ms']:.0f}"
            lines.append(f"| {res['size']} | " + (f"{res['autocast']} | " if settings else "") + f"{row['variant']} | {ms} | "
                         f"{row['vs_fm']:.2f} | {spread} | {full} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.train_step_cost", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reps", type=int, default=20, help="timed rounds per network size")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--quality", action="store_true", help="also train the synthetic two-route task")
    p.add_argument("--quality-steps", type=int, default=1500)
    p.add_argument("--seeds", default="0", help="comma-separated seeds of the quality runs")
    p.add_argument("--quality-only", action="store_true", help="only the quality runs")
    p.add_argument("--dudt", default="jvp,finite_difference", help="comma-separated methods of the quality runs")
    p.add_argument("--save-models", default=None, metavar="DIR", help="save each quality run's EMA model under DIR")
    p.add_argument("--precision-only", action="store_true", help="only the du/dt error table (seconds)")
    p.add_argument("--checkpoint", action="append", default=[],
                   help="a MeanFlow checkpoint whose du/dt error to measure too (repeatable)")
    p.add_argument("--device", default="cpu", help="where to time the steps (cpu or cuda)")
    p.add_argument("--autocast", default="none", help="comma-separated: none, bf16 (timing under torch.autocast)")
    p.add_argument("--inner", type=int, default=1, help="back-to-back steps per timer (CUDA: 10 or more)")
    p.add_argument("--out", default=None, help="JSON results (default: docs/benchmarks/meanflow_cost.json; "
                   "meanflow_cost_precision.json / _quality.json with --precision-only / --quality-only)")
    a = p.parse_args(argv)
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    casts = {"none": None, "bf16": torch.bfloat16}
    for c in a.autocast.split(","):
        if c not in casts:
            p.error(f"--autocast: expected a comma-separated list of {list(casts)}, got {a.autocast!r}")
    if a.device.startswith("cuda") and not torch.cuda.is_available():
        p.error(f"--device: expected a device this torch can use, got {a.device!r} (torch.cuda.is_available() is False)")
    machine = (f"{torch.cuda.get_device_name(a.device)}, torch {torch.__version__}" if a.device.startswith("cuda")
               else f"{os.cpu_count()}-core CPU, torch {torch.__version__}, {torch.get_num_threads()} thread(s)")
    results = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
               "machine": machine,
               "python": platform.python_version(), "command": "python -m benchmarks.train_step_cost "
               + " ".join(sys.argv[1:] if argv is None else argv), "timing": []}
    if not a.quality_only:
        results["precision"] = [precision(c) for c in [None, *a.checkpoint]]
        print(precision_table(results["precision"]), flush=True)
    if not (a.precision_only or a.quality_only):
        for name, size in SIZES.items():
            for c in a.autocast.split(","):
                print(f"[train_step_cost] {name}, batch {BATCH}, {a.device}, autocast {c}, {a.reps} rounds", flush=True)
                results["timing"].append(time_size(name, size, a.reps, a.warmup, a.device, casts[c], a.inner))
        print(table(results["timing"]), flush=True)
    if a.quality or a.quality_only:
        results["quality"] = quality([int(s) for s in a.seeds.split(",")], a.quality_steps, a.dudt.split(","),
                                     save_dir=a.save_models)
        print(quality_table(results["quality"]), flush=True)
    part = "_precision" if a.precision_only else "_quality" if a.quality_only else ""
    a.out = a.out or f"docs/benchmarks/meanflow_cost{part}.json"
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=1) + "\n")
    print(f"[train_step_cost] wrote {a.out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
