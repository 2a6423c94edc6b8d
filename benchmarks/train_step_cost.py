"""A MeanFlow train step against a flow-matching one, per way of getting du/dt (issue 28).

    python -m benchmarks.train_step_cost                 # timing table (paired rounds), both sizes
    python -m benchmarks.train_step_cost --quality       # + the synthetic two-route task, jvp vs fd

Timing: one AdamW step (zero_grad, loss, backward, step) of the CLI's recipe: batch 128, MeanFlow
with r ≠ t on 0.25 of the rows, uniform times, p = 0.5, the clean-chunk head; flow matching with
the velocity head. Each round runs every (variant, FM) pair back to back, pairs in a rotated order
and the two timers of a pair in alternating order (`timing.rounds`); the ratio is taken per round,
then the median and the quartiles over rounds are reported. Variants:

- "jvp": `meanflow_dudt="jvp"` (torch.func.jvp on the r ≠ t rows, a plain call on the others).
- "finite_difference": `meanflow_dudt="finite_difference"` (u in one call over B rows, du/dt by
  a central difference in one no-grad call over 2n rows).
- "fd, one call (B + 2n rows)": the same central difference with its 2n rows in the grad call
  (this module's own loss, built from the library's pieces), to compare with the second call.
- "forward difference (n rows)": (u(z + h·v, t + h, r) − u)/h with h = 1e-5 in a no-grad call
  over n rows (this module's own loss); it reuses u but is ~10× less accurate.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import importlib.util
import json
import os
import platform
import sys
from pathlib import Path
from typing import Callable, Dict, List

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


def _local_loss(policy: ActionDecoderPolicy, batch: dict, how: str) -> torch.Tensor:
    """The library's MeanFlow loss with du/dt computed `how` ("one_call" or "forward")."""
    cfg = policy.config
    cond = policy._prepare(batch)
    a = policy.normalizers["actions"].normalize(batch["actions"].float())            # [B, H, D]
    B = a.shape[0]
    t, r, n = losses.sample_meanflow_times(B, cfg.meanflow_ratio_r_neq_t, cfg.meanflow_time_mean,
                                           cfg.meanflow_time_std, dist=cfg.meanflow_time_dist)
    e = torch.randn(a.shape)
    z, v = interpolate(e, a, t), a - e
    net, head = policy._flow_net, slice(0, n)
    if how == "one_call":
        h = losses.fd_step(z.dtype)
        rows = lambda x, y, w: torch.cat([x, y, w])                                        # noqa: E731
        c3 = {k: losses._map_tensors(c, lambda x: rows(x, x[head], x[head])) for k, c in cond.items()}
        out = net(rows(z, z[head] + h * v[head], z[head] - h * v[head]), rows(t, t[head] + h, t[head] - h),
                  rows(r, r[head], r[head]), **c3)                                          # [B + 2n, H, D]
        u, dudt = out[:B], ((out[B:B + n] - out[B + n:]) / (2 * h)).detach()
    else:
        u = net(z, t, r, **cond)
        with torch.no_grad():
            dudt = (net(z[head] + FORWARD_STEP * v[head], t[head] + FORWARD_STEP, r[head],
                        **losses.slice_cond(cond, head)) - u[head]) / FORWARD_STEP
    target = torch.cat([v[head] - (t[head] - r[head]).reshape(-1, 1, 1) * dudt, v[n:]])
    error = (u - target).square().mean((1, 2))
    return ((error.detach() + cfg.meanflow_adaptive_c).pow(-cfg.meanflow_adaptive_p) * error).mean()


def _step(policy: ActionDecoderPolicy, batch: dict, loss: Callable) -> Callable[[], None]:
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-4)

    def step():
        opt.zero_grad(set_to_none=True)
        loss(policy, batch).backward()
        opt.step()
    step()                                                                     # the optimizer state
    return step


def variants(size: tuple, batch: dict) -> Dict[str, Callable[[], None]]:
    lib = lambda p, b: p.compute_loss(b).loss                                  # noqa: E731
    return {
        "FM": _step(_policy("flow_matching", size), batch, lib),
        "jvp": _step(_policy("mean_flow", size, meanflow_dudt="jvp"), batch, lib),
        "finite_difference": _step(_policy("mean_flow", size, meanflow_dudt="finite_difference"), batch, lib),
        "fd, one call (B + 2n rows)": _step(_policy("mean_flow", size), batch,
                                            functools.partial(_local_loss, how="one_call")),
        "forward difference (n rows)": _step(_policy("mean_flow", size), batch,
                                             functools.partial(_local_loss, how="forward")),
    }


def _quantile(xs: List[float], q: float) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


def time_size(name: str, size: tuple, reps: int, warmup: int) -> dict:
    g = torch.Generator().manual_seed(3)
    batch = {"state": torch.randn(BATCH, 39, generator=g), "actions": torch.randn(BATCH, 16, 4, generator=g)}
    steps = variants(size, batch)
    clock = Clock(torch.device("cpu"))
    fm = steps["FM"]
    timers = {k: [lambda s=s: clock(s), lambda: clock(fm)] for k, s in steps.items() if k != "FM"}
    raw = rounds(clock, timers, reps, warmup)
    fm_ms = [s[1] * 1e3 for k in raw for s in raw[k]]
    rows = [{"variant": "FM", "step_ms": _quantile(fm_ms, 0.5), "vs_fm": 1.0, "q25": 1.0, "q75": 1.0}]
    for k, samples in raw.items():
        ratio = [s[0] / s[1] for s in samples]
        rows.append({"variant": k, "step_ms": _quantile([s[0] * 1e3 for s in samples], 0.5),
                     "vs_fm": _quantile(ratio, 0.5), "q25": _quantile(ratio, 0.25), "q75": _quantile(ratio, 0.75),
                     "min": min(ratio), "max": max(ratio)})
    return {"size": name, "batch": BATCH, "rounds": reps, "rows": rows}


def quality(seeds: List[int], steps: int) -> List[dict]:
    """scripts/meanflow_norm_ablation.py's synthetic two-route task, jvp vs finite difference."""
    path = Path(__file__).resolve().parents[1] / "scripts" / "meanflow_norm_ablation.py"
    spec = importlib.util.spec_from_file_location("meanflow_norm_ablation", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = []
    for dudt in ("jvp", "finite_difference"):
        mod.DecoderConfig = functools.partial(DecoderConfig, meanflow_dudt=dudt)
        for seed in seeds:
            res = {"dudt": dudt, **mod.synthetic(seed, steps, 128)}
            print(json.dumps(res), flush=True)
            out.append(res)
    return out


def table(results: List[dict]) -> str:
    lines = ["| network (batch 128) | variant | step ms (median) | ÷ FM step (median) | quartiles | min–max |",
             "|---|---|---|---|---|---|"]
    for res in results:
        for row in res["rows"]:
            spread = "" if row["variant"] == "FM" else f"{row['q25']:.2f}–{row['q75']:.2f}"
            full = "" if row["variant"] == "FM" else f"{row['min']:.2f}–{row['max']:.2f}"
            lines.append(f"| {res['size']} | {row['variant']} | {row['step_ms']:.0f} | {row['vs_fm']:.2f} | "
                         f"{spread} | {full} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.train_step_cost", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reps", type=int, default=20, help="timed rounds per network size")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--quality", action="store_true", help="also train the synthetic two-route task")
    p.add_argument("--quality-steps", type=int, default=1500)
    p.add_argument("--seeds", default="0", help="comma-separated seeds of the quality runs")
    p.add_argument("--out", default="docs/benchmarks/meanflow_cost.json")
    a = p.parse_args(argv)
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    results = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
               "machine": f"{os.cpu_count()}-core CPU, torch {torch.__version__}, {torch.get_num_threads()} thread(s)",
               "python": platform.python_version(), "command": "python -m benchmarks.train_step_cost "
               + " ".join(sys.argv[1:] if argv is None else argv), "timing": []}
    for name, size in SIZES.items():
        print(f"[train_step_cost] {name}, batch {BATCH}, {a.reps} rounds", flush=True)
        results["timing"].append(time_size(name, size, a.reps, a.warmup))
    print(table(results["timing"]), flush=True)
    if a.quality:
        results["quality"] = quality([int(s) for s in a.seeds.split(",")], a.quality_steps)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(results, indent=1) + "\n")
    print(f"[train_step_cost] wrote {a.out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
