"""Serving round trip: `action-decoder serve` with LeRobot's own `RobotClient` on loopback.

Run in an environment with LeRobot and grpcio (scripts/lerobot_integration.sh builds one):

    python -m benchmarks serve [--seconds 10] [--train-steps 200] [--out DIR]

Two checkpoints of the default architecture (hidden 96, 3 layers, chunk H = 16) are trained on
the LeRobot-written fixture tests/data/lerobot/v30_toy (6-d state, 3-d action, two tasks): MF-1
(mean_flow, 1 step, trained with --rtc-max-delay 4: real-time chunking "trained") and FM-10
(flow_matching, 10 Euler steps: "guided"). Each is served (`action-decoder serve`, a subprocess)
with real-time chunking on and off (and with `--compile`: MF-1 with trained RTC, FM-10 without
RTC, compiled at the first observation), and LeRobot's `RobotClient` drives the plugin's simulated
robot (`--robot.type=action_decoder_sim`) at --fps for --seconds, with `actions_per_chunk` 12,
`chunk_size_threshold` 0.5 and `aggregate_fn_name` latest_only (RTC on and off) or
weighted_average (the client's default; RTC on).

Server side (its --log-chunks records): compute per chunk (observation → timed actions: the
checkpoint's pre-processing, sampling, post-processing) and sampling alone, in ms; the delay
in control steps it estimated and the rows it committed. Client side, at each chunk's arrival
(read, not changed: the client's own merge runs): actions still queued, incoming rows already
executed (dropped by the client), rows merged into queued timesteps and rows appended, and how
far the new chunk is from the queued actions it merges into (mean |new − queued| over merged
rows and action dimensions, robot units; apart on the rows the server committed and the others)
— what the client's aggregate function blends.
"""

from __future__ import annotations

import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from datetime import date
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "data" / "lerobot" / "v30_toy"
TASK = "push the block"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serve_subprocess(checkpoint, log, *extra: str, timeout: float = 120.0):
    """`python -m action_decoder.cli serve` on a free loopback port, this checkout's code first; yields
    (port, process); SIGTERM at the end. A server that does not start raises RuntimeError with its stderr."""
    port = free_port()
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "lerobot_policy_action_decoder" / "src"),
                                          os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "action_decoder.cli", "serve", "--checkpoint", str(checkpoint),
                             "--port", str(port), "--log-chunks", str(log), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lines: list = []
    threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True).start()
    deadline = time.time() + timeout
    while not any("action-decoder serve:" in line for line in lines):
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            raise RuntimeError(f"serve did not start (exit {proc.returncode}): {proc.stderr.read()[-2000:]}")
        time.sleep(0.1)
    try:
        yield port, proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def drive_client(port: int, checkpoint, workdir, actions: int, seconds: float, fps: int = 30,
                 actions_per_chunk: int = 12, threshold: float = 0.5, aggregate: str = "latest_only",
                 state_dim: int = 6, action_dim: int = 3, warmup: float = 0.0):
    """LeRobot's RobotClient with the simulated robot until it executed `actions` actions or `seconds`
    passed (counted from the first chunk's arrival when `warmup` > 0, waiting for it at most `warmup`
    seconds: a compiling server's first chunk). Returns (robot, arrivals): per received chunk, (the queue {timestep: action} and the last
    executed timestep just before the client merged it, the chunk's TimedActions)."""
    old = os.getcwd()
    os.chdir(workdir)                                 # LeRobot's loggers write ./logs/
    try:
        from lerobot.async_inference.configs import RobotClientConfig
        from lerobot.async_inference.robot_client import RobotClient
        from lerobot_policy_action_decoder.sim_robot import SimRobotConfig

        cfg = RobotClientConfig(policy_type="action_decoder", pretrained_name_or_path=str(checkpoint),
                                robot=SimRobotConfig(state_dim=state_dim, action_dim=action_dim),
                                actions_per_chunk=actions_per_chunk, task=TASK, server_address=f"127.0.0.1:{port}",
                                fps=fps, chunk_size_threshold=threshold, aggregate_fn_name=aggregate)
        client = RobotClient(cfg)
        arrivals: list = []
        merge = client._aggregate_action_queues

        def watched(incoming, fn=None):               # read the queue; the client's own merge runs unchanged
            with client.action_queue_lock:
                queued = {a.get_timestep(): a.get_action() for a in list(client.action_queue.queue)}
            with client.latest_action_lock:
                latest = client.latest_action
            arrivals.append((queued, latest, list(incoming)))
            return merge(incoming, fn)

        client._aggregate_action_queues = watched
        if not client.start():
            raise RuntimeError("RobotClient could not start against the server (see its log above)")
        receiver = threading.Thread(target=client.receive_actions, daemon=True)
        control = threading.Thread(target=client.control_loop, kwargs={"task": TASK}, daemon=True)
        receiver.start()
        control.start()
        first = time.time() + warmup
        while warmup and not arrivals and time.time() < first:
            time.sleep(0.02)
        deadline = time.time() + seconds
        while len(client.robot.executed) < actions and time.time() < deadline:
            time.sleep(0.02)
        client.stop()
        control.join(timeout=5)
        receiver.join(timeout=5)
        return client.robot, arrivals
    finally:
        os.chdir(old)


def arrival_stats(arrivals, records: list) -> dict:
    """Queue behaviour at each chunk's arrival (module docstring), as medians and means; `records` are
    the server's, in the same order (one client, one chunk per GetActions). The gap is split into the
    chunk's committed rows (the server's previous chunk, copied) and the rest."""
    queued, dropped, merged, appended, committed_gap, free_gap = [], [], [], [], [], []
    for i, ((queue, latest, incoming), record) in enumerate(zip(arrivals, records)):
        live = [(j, a) for j, a in enumerate(incoming) if a.get_timestep() > latest]
        hit = [(j, a) for j, a in live if a.get_timestep() in queue]
        if i:                                          # the first chunk arrives to an empty queue
            queued.append(len(queue))
        dropped.append(len(incoming) - len(live))
        merged.append(len(hit))
        appended.append(len(live) - len(hit))
        for j, a in hit:
            gap = float((a.get_action() - queue[a.get_timestep()]).abs().mean())
            (committed_gap if j < record["committed"] else free_gap).append(gap)
    med = lambda xs: statistics.median(xs) if xs else float("nan")  # noqa: E731
    mean = lambda xs: statistics.fmean(xs) if xs else float("nan")  # noqa: E731
    return {"chunks_received": len(arrivals), "queued_median": med(queued), "queued_min": min(queued, default=0),
            "dropped_median": med(dropped), "merged_median": med(merged), "appended_median": med(appended),
            "gap_committed": mean(committed_gap), "gap_free": mean(free_gap)}


COMPILE_S = 120.0    # the longest a --compile arm's client waits for its first chunk (the compiler's)


def server_stats(records: list) -> dict:
    later = records[1:] or records                    # the first chunk pays one-off costs
    q = lambda xs, p: sorted(xs)[min(len(xs) - 1, int(p * len(xs)))]  # noqa: E731
    compute = [r["compute_ms"] for r in later]
    sample = [r["sample_ms"] for r in later]
    return {"chunks_served": len(records), "compute_ms_median": statistics.median(compute),
            "compute_ms_p90": q(compute, 0.9), "sample_ms_median": statistics.median(sample),
            "delay_median": statistics.median([r["delay"] for r in later]),
            "committed_median": statistics.median([r["committed"] for r in later]),
            "rtc_modes": sorted({r["rtc_mode"] for r in later if r["rtc_mode"]})}


def train_checkpoints(work: Path, steps: int, tiny: bool) -> dict:
    from action_decoder.train import TrainConfig, train

    arch = dict(hidden_size=32, num_layers=1, num_heads=2, num_kv_heads=1) if tiny else {}
    common = dict(dataset=str(FIXTURE), steps=steps, batch_size=32, eval_episodes=0, progress=False, seed=0, **arch)
    runs = {"MF-1": dict(decoder="mean_flow", rtc_max_delay=4, output_dir=str(work / "mf")),
            "FM-10": dict(decoder="flow_matching", output_dir=str(work / "fm"))}
    # a run already in --out is served again (its final/), not retrained
    return {name: Path(run["output_dir"]) / "final" if (Path(run["output_dir"]) / "final").is_dir()
            else train(TrainConfig(**run, **common)) for name, run in runs.items()}


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m benchmarks serve", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0, help="client run per arm, in seconds (default 10)")
    parser.add_argument("--fps", type=int, default=30, help="the client's control frequency in Hz (default 30)")
    parser.add_argument("--train-steps", type=int, default=200, help="training steps per checkpoint (default 200)")
    parser.add_argument("--tiny", action="store_true", help="tiny networks (smoke run)")
    parser.add_argument("--no-compile", action="store_true", help="leave out the --compile arms")
    parser.add_argument("--out", default=None, help="directory of the runs and serve.json (default: a temporary "
                        "directory); runs already there are served again")
    args = parser.parse_args(argv)
    work = Path(args.out or tempfile.mkdtemp(prefix="bench_serve_"))
    work.mkdir(parents=True, exist_ok=True)
    ckpts = train_checkpoints(work, args.train_steps, args.tiny)
    rows = []
    for name, ckpt in ckpts.items():
        # (RTC, client aggregate, --compile): compiled with RTC where the checkpoint has trained RTC (MF-1), else off
        arms = [(True, "latest_only", False), (False, "latest_only", False), (True, "weighted_average", False)]
        arms += [] if args.no_compile else [(name == "MF-1", "latest_only", True)]
        for rtc, aggregate, compiled in arms:
            log = work / f"{name}_{'rtc' if rtc else 'plain'}_{aggregate}{'_compiled' if compiled else ''}.jsonl"
            log.unlink(missing_ok=True)
            extra = [*([] if rtc else ["--no-rtc"]), *(["--compile"] if compiled else [])]
            with serve_subprocess(ckpt, log, "--fps", str(args.fps), *extra) as (port, _):
                robot, arrivals = drive_client(port, ckpt, work, actions=int(args.seconds * args.fps) * 10,
                                               seconds=args.seconds, fps=args.fps, aggregate=aggregate,
                                               warmup=COMPILE_S if compiled else 0.0)
            records = [json.loads(line) for line in log.read_text().splitlines()]
            rows.append({"checkpoint": name, "rtc": rtc, "aggregate": aggregate, "compiled": compiled,
                         "executed": len(robot.executed), **server_stats(records), **arrival_stats(arrivals, records)})
            print(json.dumps(rows[-1]), flush=True)
    meta = {"date": date.today().isoformat(), "machine": f"{os.cpu_count()}-core {platform.machine()} CPU, "
            f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}", "python": platform.python_version(),
            "command": "python -m benchmarks serve " + " ".join(argv if argv is not None else sys.argv[1:])}
    (work / "serve.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"| checkpoint | sampler | RTC | client aggregate | chunks | actions executed in {args.seconds:g} s | compute ms "
          "(median / p90) | sampling ms | delay (steps) | committed | queued at arrival (median / min) | dropped | "
          "merged | appended | gap, committed rows | gap, other merged rows |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['checkpoint']} | {'compiled' if r.get('compiled') else 'eager'} | {', '.join(r['rtc_modes']) or 'off'} "
              f"| {r['aggregate']} | {r['chunks_served']} | "
              f"{r['executed']} | {r['compute_ms_median']:.1f} / {r['compute_ms_p90']:.1f} | "
              f"{r['sample_ms_median']:.1f} | {r['delay_median']:g} | {r['committed_median']:g} | "
              f"{r['queued_median']:g} / {r['queued_min']} | {r['dropped_median']:g} | {r['merged_median']:g} | "
              f"{r['appended_median']:g} | {r['gap_committed']:.3f} | {r['gap_free']:.3f} |")
    print(f"{meta['date']}, {meta['machine']}, {meta['command']}; results in {work / 'serve.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
