"""Image-conditioned against state-conditioned policies on Meta-World, same demonstrations.

    python -m benchmarks cameras                         # the default grid (hours on this CPU)
    python -m benchmarks cameras --tasks metaworld/drawer-open --decoders flow_matching --steps 50 \
        --episodes 2 --runs outputs/cameras-smoke --results outputs/cameras-smoke/cameras.json \
        --table outputs/cameras-smoke/cameras.md                               # a smoke run

For each (task, seed, decoder) two policies are trained on the same expert demonstrations with
`action-decoder train`: **state** (the full 39-d state, `--state-layout metaworld`) and **image**
(one camera rendered at `--image-size`, `--cameras`; the state it reads is the robot's
proprioception only, `metaworld_proprio`: where objects and goal are comes from the camera).
Both are evaluated closed loop on the same held-out layouts. Per row: success, the training
time (the trainer's own "s of training", this CPU, one torch thread), and the per-chunk latency
at B = 1 of the trained checkpoint (`policy.predict_action_chunk`, the image encoder included)
with the encoder's own share (`policy.model.image_encoder`), medians over rounds in which the two
are timed back to back (`timing.rounds`).

Tasks: Meta-World "easy" tasks (all but the groups of Seo et al. 2022) and "medium" ones whose
targets are visible to a camera (a button, drawer, door, plate, hoop, hole). Run directories under
--runs are reused when complete, so a grid can be stopped and continued; rows are merged into
--results and the table --table is rebuilt from them (text below its notes marker is kept).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Optional

EASY = ("button-press-topdown-v3", "drawer-open-v3", "door-open-v3", "plate-slide-v3")
MEDIUM = ("basketball-v3", "sweep-into-v3")
DECODERS = ("flow_matching", "mean_flow")
CONDITIONS = ("state", "image")
CLI = [sys.executable, "-m", "action_decoder.cli"]
NOTES = "<!-- notes: kept when the table above is rebuilt -->"
GAP_TARGET = 15.0          # points: image success on the easy tasks within this of state success
TRAINED = re.compile(r"\((\d+(?:\.\d+)?) s of training[,)]")
"""The wall time of the trainer's `saved` line ("(W s of training, C s CPU)"; older logs: "(W s of training)")."""


def short_name(task: str) -> str:
    """metaworld/drawer-open, drawer-open-v3 → drawer-open (one run directory for every spelling)."""
    return task.split("/")[-1].removesuffix("-v3")


def difficulty(task: str) -> str:
    from action_decoder.envs.metaworld_tasks import TASK_GROUPS

    name = f"{short_name(task)}-v3"
    return next((group for group, tasks in TASK_GROUPS.items() if name in tasks), "easy")


def train_command(task: str, seed: int, decoder: str, condition: str, args, out: Path) -> list[str]:
    """The `action-decoder train` command of one run (it evaluates closed loop at its end)."""
    cmd = [*CLI, "train", "--task", task, "--decoder", decoder, "--demos", str(args.demos), "--steps", str(args.steps),
           "--batch-size", str(args.batch_size), "--seed", str(seed), "--eval-episodes", str(args.episodes),
           "--output-dir", str(out), "--no-progress"]
    if condition == "image":
        cmd += ["--cameras", args.camera, "--image-size", str(args.image_size), "--image-encoder", args.image_encoder,
                "--image-shift", str(args.image_shift), "--state-layout", "metaworld_proprio"]
    else:
        cmd += ["--state-layout", "metaworld"]
    return cmd


def latency(checkpoint: Path, reps: int, warmup: int = 3) -> dict:
    """Per-chunk latency at B = 1 (ms, median over rounds) and, for a camera policy, the encoder's share."""
    import torch

    from action_decoder import ActionDecoderPolicy

    from .timing import Clock, median, rounds

    policy = ActionDecoderPolicy.from_pretrained(checkpoint).eval()
    cfg = policy.config
    batch = {"state": torch.zeros(1, cfg.state_dim)}
    gen = torch.Generator().manual_seed(0)
    if cfg.uses_cameras:
        batch["images"] = torch.randint(0, 256, (1, len(cfg.cameras), 3, cfg.image_size, cfg.image_size),
                                        dtype=torch.uint8, generator=gen)               # [1, N_cam, 3, S, S]
    clock = Clock(torch.device("cpu"))
    with torch.no_grad():
        timers = [lambda: clock(lambda: policy.predict_action_chunk(batch, generator=gen))]
        if cfg.uses_cameras:
            timers.append(lambda: clock(lambda: policy.model.image_encoder(batch["images"])))
        samples = rounds(clock, {"chunk": timers}, reps, warmup)["chunk"]
    out = {"latency_ms": 1e3 * median([s[0] for s in samples])}
    if cfg.uses_cameras:
        out["encoder_ms"] = 1e3 * median([s[1] for s in samples])
    return out


def run_one(task: str, seed: int, decoder: str, condition: str, args) -> Optional[dict]:
    """Train and evaluate one policy (unless its run directory holds them), then time it; one result row."""
    run = Path(args.runs) / f"{short_name(task)}_s{seed}_{decoder}_{condition}"
    final = run / "final"
    log = run / "log.txt"
    if not list(final.glob("eval_*.json")):
        run.mkdir(parents=True, exist_ok=True)
        with open(log, "w") as fh:
            subprocess.run(train_command(task, seed, decoder, condition, args, run), stdout=fh,
                           stderr=subprocess.STDOUT, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    res = json.loads(sorted(final.glob("eval_*.json"))[0].read_text())
    trained = TRAINED.findall(log.read_text()) if log.is_file() else []
    return {"task": res["results"][0]["task"], "difficulty": difficulty(task), "seed": seed, "decoder": decoder,
            "condition": condition, "success": res["success_rate"], "episodes": res["episodes_per_task"],
            "sampler": res["sampler"], "steps": res["steps"], "train_steps": args.steps, "demos": args.demos,
            "camera": args.camera if condition == "image" else None,
            "image_size": args.image_size if condition == "image" else None,
            "image_shift": args.image_shift if condition == "image" else None,
            "train_s": float(trained[-1]) if trained else None, **latency(final, args.latency_reps)}


def merge(path: Path, rows: list[dict]) -> list[dict]:
    """Rows of `path` with `rows` added, one per (task, seed, decoder, condition); the newest wins."""
    key = lambda r: (r["task"], r["seed"], r["decoder"], r["condition"])  # noqa: E731
    old = json.loads(path.read_text()) if path.is_file() else []
    merged = {key(r): r for r in old}
    merged.update({key(r): r for r in rows})
    out = sorted(merged.values(), key=key)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    return out


def _mean(xs: list) -> Optional[float]:
    xs = [x for x in xs if x is not None]
    return statistics.fmean(xs) if xs else None


def _fmt(x: Optional[float], spec: str = ".1f") -> str:
    return "—" if x is None else format(x, spec)


LABELS = {"flow_matching": "FM", "mean_flow": "MF"}


def build_table(rows: list[dict]) -> str:
    """Markdown: one row per (task, decoder) with state and image success (mean over seeds, %), the
    gap (image − state, points), per-chunk latency (ms; the image policy's encoder share in brackets)
    and training time (s, mean over seeds); then the mean gap per difficulty and decoder, and whether
    the easy tasks meet the target (image within GAP_TARGET points of state)."""
    cells: dict = {}
    for r in rows:
        cells.setdefault((r["difficulty"], r["task"], r["decoder"]), {}).setdefault(r["condition"], []).append(r)
    order = {"easy": 0, "medium": 1, "hard": 2, "very_hard": 3}
    lines = ["| task | difficulty | decoder | state success % | image success % | gap (points) | "
             "state ms / chunk | image ms / chunk (encoder) | state train s | image train s | seeds |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    gaps: dict = {}
    for (diff, task, decoder), by in sorted(cells.items(), key=lambda kv: (order.get(kv[0][0], 9), kv[0][1],
                                                                         kv[0][2])):
        s, i = by.get("state", []), by.get("image", [])
        ss, si = _mean([100 * r["success"] for r in s]), _mean([100 * r["success"] for r in i])
        gap = None if ss is None or si is None else si - ss
        if gap is not None:
            gaps.setdefault((diff, decoder), []).append(gap)
        enc = _mean([r.get("encoder_ms") for r in i])
        image_ms = _fmt(_mean([r.get("latency_ms") for r in i]), ".2f") + ("" if enc is None else f" ({enc:.2f})")
        seeds = sorted({r["seed"] for r in s + i})
        lines.append(f"| {task} | {diff} | {LABELS.get(decoder, decoder)} | {_fmt(ss)} | {_fmt(si)} | "
                     f"{_fmt(gap, '+.1f')} | {_fmt(_mean([r.get('latency_ms') for r in s]), '.2f')} | {image_ms} | "
                     f"{_fmt(_mean([r.get('train_s') for r in s]), '.0f')} | "
                     f"{_fmt(_mean([r.get('train_s') for r in i]), '.0f')} | {len(seeds)} |")
    lines += ["", "| difficulty | decoder | tasks | mean gap (image − state, points) |", "|---|---|---|---|"]
    for (diff, decoder), g in sorted(gaps.items(), key=lambda kv: (order.get(kv[0][0], 9), kv[0][1])):
        lines.append(f"| {diff} | {LABELS.get(decoder, decoder)} | {len(g)} | {statistics.fmean(g):+.1f} |")
    easy = [(decoder, statistics.fmean(g)) for (diff, decoder), g in gaps.items() if diff == "easy"]
    if easy:
        verdict = ", ".join(f"{LABELS.get(d, d)} {'meets' if g >= -GAP_TARGET else 'misses'} it ({g:+.1f})"
                            for d, g in sorted(easy))
        lines += ["", f"Target: image-conditioned success on the easy tasks within {GAP_TARGET:.0f} points of "
                      f"state-conditioned, mean over tasks: {verdict}."]
    return "\n".join(lines) + "\n"


def write_table(path: Path, rows: list[dict], header: str) -> None:
    """Rebuild the generated part of `path`; the text below its notes marker is kept."""
    kept = ""
    if path.is_file() and NOTES in path.read_text():
        kept = path.read_text().split(NOTES, 1)[1]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(header + "\n" + build_table(rows) + "\n" + NOTES + (kept or "\n"))


def encoder_cost(image_size: int = 64, reps: int = 30, warmup: int = 3) -> list[dict]:
    """The image encoder's cost per chunk at B = 1, one camera, for each backbone, on `action-decoder
    train`'s network (hidden 96, 3 layers; flow matching, K = 10): ms of the encoder alone, of a
    whole chunk of the camera policy, and of a chunk of the same policy without cameras, timed back
    to back in each round; the share is encoder ÷ camera chunk."""
    import torch

    from action_decoder import ActionDecoderPolicy, DecoderConfig

    from .timing import Clock, median, rounds

    base = dict(decoder_type="flow_matching", state_dim=39, action_dim=4, hidden_size=96, num_hidden_layers=3,
                num_attention_heads=4, num_key_value_heads=2, state_layout="metaworld")
    torch.manual_seed(0)
    state = ActionDecoderPolicy(DecoderConfig(**base)).eval()
    gen = torch.Generator().manual_seed(0)
    s = torch.rand(1, 39)
    images = torch.randint(0, 256, (1, 1, 3, image_size, image_size), dtype=torch.uint8, generator=gen)
    clock, out = Clock(torch.device("cpu")), []
    for encoder in ("conv", "resnet18"):
        cam = ActionDecoderPolicy(DecoderConfig(**{**base, "state_layout": "metaworld_proprio"},
                                                cameras=("observation.images.corner2",), image_size=image_size,
                                                image_encoder=encoder)).eval()
        with torch.no_grad():
            timers = [lambda: clock(lambda: cam.model.image_encoder(images)),
                      lambda: clock(lambda: cam.predict_action_chunk({"state": s, "images": images}, generator=gen)),
                      lambda: clock(lambda: state.predict_action_chunk({"state": s}, generator=gen))]
            samples = rounds(clock, {encoder: timers}, reps, warmup)[encoder]
        enc, chunk, plain = (1e3 * median([x[i] for x in samples]) for i in range(3))
        out.append({"encoder": encoder, "image_size": image_size, "encoder_ms": enc, "camera_chunk_ms": chunk,
                    "state_chunk_ms": plain, "share": enc / chunk,
                    "encoder_params": sum(p.numel() for p in cam.model.image_encoder.parameters())})
    return out


def encoder_table(rows: list[dict]) -> str:
    """Markdown rows of `encoder_cost`: one per backbone."""
    lines = ["| image encoder (1 camera, B = 1) | params | encoder ms | chunk ms with camera (FM K=10) | "
             "chunk ms, state only | encoder share |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['encoder']}, {r['image_size']} px | {r['encoder_params'] / 1e6:.2f} M | "
                     f"{r['encoder_ms']:.2f} | {r['camera_chunk_ms']:.2f} | {r['state_chunk_ms']:.2f} | "
                     f"{100 * r['share']:.0f} % |")
    return "\n".join(lines) + "\n"


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks cameras", description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", default=",".join(f"metaworld/{t}" for t in EASY + MEDIUM),
                        help="comma-separated Meta-World tasks (default: four easy and two medium ones)")
    parser.add_argument("--decoders", default=",".join(DECODERS))
    parser.add_argument("--conditions", default=",".join(CONDITIONS), help="state, image or both")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--demos", type=int, default=10)
    parser.add_argument("--steps", type=int, default=1500, help="training steps of every policy (the CLI's default)")
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--episodes", type=int, default=50, help="closed-loop episodes per policy")
    parser.add_argument("--camera", default="corner2", help="the Meta-World camera the image policies see")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--image-encoder", default="conv", choices=("conv", "resnet18"))
    parser.add_argument("--image-shift", type=int, default=None,
                        help="training-time random shift of the frames, pixels (default: the config's)")
    parser.add_argument("--latency-reps", type=int, default=30)
    parser.add_argument("--runs", default="runs/cameras")
    parser.add_argument("--results", default="docs/benchmarks/cameras.json")
    parser.add_argument("--table", default="docs/benchmarks/cameras.md")
    parser.add_argument("--encoder-cost", action="store_true",
                        help="only time the image encoders per chunk (no training); prints a markdown table")
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    if args.image_shift is None:
        from action_decoder import DecoderConfig

        args.image_shift = DecoderConfig.image_shift
    if args.encoder_cost:
        print(encoder_table(encoder_cost(args.image_size, args.latency_reps)), flush=True)
        return 0
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    if not conditions or not set(conditions) <= set(CONDITIONS):
        parser.error(f"--conditions: expected a comma-separated subset of {list(CONDITIONS)}, got {args.conditions!r}")
    rows = []
    for task in [t.strip() for t in args.tasks.split(",") if t.strip()]:
        for seed in [int(s) for s in args.seeds.split(",")]:
            for decoder in [d.strip() for d in args.decoders.split(",") if d.strip()]:
                for condition in conditions:
                    row = run_one(task, seed, decoder, condition, args)
                    print(json.dumps(row), flush=True)
                    rows.append(row)
    merged = merge(Path(args.results), rows)
    import datetime
    import platform

    import torch

    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = (f"# Cameras: image- against state-conditioned policies\n\n"
              f"Generated by `{' '.join(['python -m benchmarks cameras', *argv])}` "
              f"on {date}, {platform.processor() or platform.machine()} (torch {torch.__version__}, "
              f"{torch.get_num_threads()} thread(s)); {args.demos} demonstrations per task, {args.steps} training "
              f"steps at batch {args.batch_size}, camera `{args.camera}` at {args.image_size} px "
              f"({args.image_encoder} encoder, training shift {args.image_shift} px). The image policies read the "
              f"hand position and gripper only (`metaworld_proprio`); the state policies the whole 39-d state "
              f"(`metaworld`). Latency: B = 1, the config's sampler, one torch thread.\n")
    write_table(Path(args.table), merged, header)
    print(f"table: {args.table}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
