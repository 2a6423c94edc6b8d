"""Training-time RTC on its own training chunks: does a prefix-fed chunk continue its demonstration?

Run through `python -m benchmarks rtc --part prefix`. For each task and training seed, the RTC-trained
Meta-World weights of `rtc_modes.train_metaworld` (trained here if missing) sample a chunk for every
second frame of their own demonstrations (the `train --seed` ones) whose next S + MAX_DELAY actions
exist, with the demonstration's first d actions fed in as the committed prefix (`rtc_mode="trained"`;
d = 0: a plain chunk), the same noise in every cell. The error is the mean |chunk − demonstration|
(environment units, all action dimensions) over the rows d..d+S−1, the ones the new chunk executes.
No environment is stepped: a prefix-fed chunk that misses its own training chunks, where the chunk
without a prefix fits them, shows the network has not learnt the conditioning at that number of
sampling steps.
"""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import torch

from benchmarks.rtc_modes import LABEL, MAX_DELAY, H, S, _budget, _seed, perturbed_copies, train_metaworld

FRAME_STRIDE = 2                                # every second frame of the demonstrations
NOISE_SEED = 1


def demo_chunks(task: str, demos: int, seed: int, noise: float, horizon: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(state [N, S_dim], actions [N, H, D]) of every FRAME_STRIDE-th frame of the demonstrations `train
    --demos demos --seed seed --demo-noise noise` trains on, whose first S + MAX_DELAY actions are all
    inside the episode."""
    from action_decoder.data.chunks import ChunkDataset
    from action_decoder.data.demos import load_demos

    ds = ChunkDataset(load_demos(task, demos, seed, noise), horizon)
    items = [ds[i] for i in range(0, len(ds), FRAME_STRIDE)]
    keep = [i for i, it in enumerate(items) if not it["action_is_pad"][: S + MAX_DELAY].any()]
    return (torch.stack([items[i]["state"] for i in keep]), torch.stack([items[i]["actions"] for i in keep]))


@torch.no_grad()
def prefix_errors(policy, state: torch.Tensor, actions: torch.Tensor, steps: int, delays) -> dict[int, float]:
    """{d: mean |chunk − actions| over rows d..d+S−1} with actions' first d rows as the committed prefix."""
    noise = torch.randn(actions.shape, generator=torch.Generator().manual_seed(NOISE_SEED))     # [N, H, D]
    prev = actions[:, : H - S]                                                                   # [N, L, D]
    out = {}
    for d in delays:
        chunk = policy.sample({"state": state}, steps=steps, noise=noise, prev_chunk=prev if d else None,
                              delay=d, rtc_mode="trained" if d else None).actions                # [N, H, D]
        out[d] = float((chunk - actions)[:, d: d + S].abs().mean())
    return out


def run_prefix_fit(task: str, decoder: str, steps: int, args, command: str) -> list[dict]:
    """One row per training seed and delay of the RTC-trained weights of `task` (`--rtc-*` options)."""
    from action_decoder import ActionDecoderPolicy
    from action_decoder.train import TrainConfig

    train_steps = getattr(args, "train_steps", None) or TrainConfig.steps
    rows = []
    for train_seed in getattr(args, "train_seeds", None) or [TrainConfig.seed]:
        ckpt = train_metaworld(task, decoder, Path(args.runs), MAX_DELAY, args.rtc_delay_dist, args.rtc_balance_rows,
                               train_steps, train_seed, getattr(args, "rtc_meanflow_target", None),
                               getattr(args, "rtc_perturbed_prefixes", None))
        policy = ActionDecoderPolicy.from_pretrained(ckpt).eval()
        trained = policy.config.extra["train"]                                  # the `train` options it ran with
        state, actions = demo_chunks(task, trained["demos"], trained["seed"], trained["demo_noise"],
                                     policy.config.action_chunk_size)
        errors = prefix_errors(policy, state, actions, steps, args.delays)
        for d, err in errors.items():
            rows.append({"task": task.split("/")[-1] + "-v3", "decoder": decoder, "steps": steps, "delay": d,
                         "train_steps": train_steps, "train_seed": train_seed, "chunks": len(state),
                         "mean_abs_error": err, "rtc_delay_dist": policy.config.rtc_delay_dist,
                         "rtc_meanflow_target": policy.config.meanflow_target if decoder == "mean_flow" else None,
                         "rtc_perturbed_prefixes": perturbed_copies(policy.config),
                         "checkpoint": str(ckpt), "command": command, "date": time.strftime("%Y-%m-%d"),
                         "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores shared, "
                                    f"{torch.get_num_threads()} torch thread"})
        print(f"[{task}] {LABEL[(decoder, steps)]} seed {train_seed} "
              + ", ".join(f"d={d}: {e:.3f}" for d, e in errors.items()), flush=True)
    return rows


def row_key(r: dict) -> tuple:
    return (r["task"], r["decoder"], r["steps"], r["delay"], _budget(r), _seed(r), r.get("rtc_delay_dist"),
            r.get("rtc_meanflow_target"), r.get("rtc_perturbed_prefixes") or 0)


def weights_label(r: dict) -> str:
    target, copies = r.get("rtc_meanflow_target"), r.get("rtc_perturbed_prefixes")
    return f"{r.get('rtc_delay_dist')} delays" + (f", {target} target" if target else "") + \
        (f", perturbed prefixes {copies}" if copies else "")


def prefix_section(rows: list[dict]) -> list[str]:
    """The prefix-fit table: per task, setting, weights and training seed, the error at each delay."""
    if not rows:
        return []
    meta = sorted({(r["date"], r["machine"], r["command"]) for r in rows})
    delays = sorted({r["delay"] for r in rows})
    by: dict = {}
    for r in rows:
        by.setdefault((r["task"], r["decoder"], r["steps"], weights_label(r), _budget(r), _seed(r)), {})[r["delay"]] = r
    lines = ["## Trained RTC on its own training chunks", "",
             *[f"Measured {d} ({m}) by `{c}`." for d, m, c in meta], "",
             f"The RTC-trained weights (rtc_max_delay = {MAX_DELAY}) sample a chunk for one frame in {FRAME_STRIDE} "
             f"of their own demonstrations, the demonstration's first d actions fed in as the committed prefix "
             f"(d = 0: a plain chunk), the same noise in every cell. Error: the mean |chunk − demonstration| over "
             f"the rows d..d+{S - 1} the new chunk executes (environment units). A prefix-fed chunk that misses "
             f"chunks the plain one fits has not learnt the conditioning. No environment is stepped.", "",
             "| task | setting | weights | training steps | training seed | chunks | "
             + " | ".join(f"d = {d}" for d in delays) + " | worst d ÷ d = 0 |",
             "|---|---|---|---|---|---|" + "---|" * len(delays) + "---|"]
    for (task, decoder, steps, weights, budget, seed), cell in sorted(by.items()):
        errs = [cell[d]["mean_abs_error"] if d in cell else None for d in delays]
        base = cell.get(0, {}).get("mean_abs_error")
        worst = max(e for e in errs if e is not None)
        ratio = f"{worst / base:.1f}×" if base else "–"
        lines.append(f"| {task} | {LABEL[(decoder, steps)]} | {weights} | {budget} | {seed} | "
                     f"{next(iter(cell.values()))['chunks']} | "
                     + " | ".join("–" if e is None else f"{e:.3f}" for e in errs) + f" | {ratio} |")
    return lines + [""]

