"""`action-decoder serve`: the options, and the bookkeeping of real-time chunking on a policy server.

The server itself (gRPC, LeRobot's async-inference messages) lives in the plugin distribution
(`lerobot_policy_action_decoder.serve`), where LeRobot is installed; this module needs neither.

Timesteps follow LeRobot's `RobotClient`: it labels an observation with the timestep of the last
action it executed (0 before the first), drops every received action whose timestep it has already
executed, and merges the rest into its queue by timestep. A chunk computed from an observation
labelled k therefore starts at k + 1 once the client has executed action k (any chunk of this
connection was sent), and at k for the connection's first observation (nothing executed yet).

Real-time chunking. While the server computes a chunk, the client keeps executing the previous
chunk: the new chunk's first `delay` rows are those actions (committed), and the policy conditions
on them (`ActionDecoderPolicy.sample(prev_chunk=..., delay=...)`). The client holds only the rows
it was sent (`actions_per_chunk`), so the previous chunk's rows beyond them are never executed
and are not used. The delay is counted in control steps, from the latency the server measures:
the observation's trip to the server (its client timestamp; loopback or synchronised clocks), the
time it waited there, and the longest recent compute time; an overestimate is safe (the extra
rows are the previous chunk's own actions), an underestimate leaves the client a row or two of
the new chunk that does not continue what it executed.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Sequence

SERVER_MODULE = "lerobot_policy_action_decoder.serve"
INSTALL_HINT = ("pip install 'lerobot>=0.4.3' and the plugin with its serve extra "
                "(pip install './lerobot_policy_action_decoder[serve]' from this repository)")


@dataclass
class ServeConfig:
    """`action-decoder serve`: an async policy server that LeRobot's `RobotClient` talks to."""

    checkpoint: str
    """Checkpoint directory: `action-decoder train`'s (or a run's checkpoints/last) or a LeRobot pretrained_model of the plugin."""
    host: str = "127.0.0.1"
    """Address to listen on (0.0.0.0: every interface)."""
    port: int = 8080
    """TCP port to listen on."""
    fps: float = 30.0
    """The client's control frequency in Hz (RobotClient --fps); converts latency to control steps."""
    delay: Optional[int] = None
    """Inference delay in control steps, fixed; default: measured per chunk from the server's latency and --fps."""
    rtc: bool = True
    """Real-time chunking: condition each chunk on the previous chunk's actions executed meanwhile (flow_matching, mean_flow)."""
    rtc_mode: Literal["auto", "trained", "guided"] = "auto"
    """auto: trained where the checkpoint was trained for the delay (--rtc-max-delay), else guided."""
    steps: Optional[int] = None
    """Sampling steps per chunk; default: the checkpoint's num_inference_timesteps."""
    compile: bool = False
    """Sample with the torch.compile'd sampler, compiled at the first observation (with --rtc: trained RTC, at most rtc_max_delay committed rows)."""
    obs_timeout: float = 2.0
    """Seconds a GetActions call waits for an observation before it returns empty."""
    seed: int = 0
    """Seed of the sampling noise."""
    log_chunks: Optional[str] = None
    """JSON-lines file with one record per chunk served (timesteps, delay, milliseconds); default: none."""


def check_serve_config(cfg: ServeConfig) -> None:
    """One ValueError line for an option out of range (before LeRobot is imported)."""
    if not 1 <= cfg.port <= 65535:
        raise ValueError(f"--port: expected a TCP port in 1..65535, got {cfg.port}")
    if not (cfg.fps > 0 and math.isfinite(cfg.fps)):
        raise ValueError(f"--fps: expected the client's control frequency in Hz (> 0), got {cfg.fps}")
    if cfg.delay is not None and cfg.delay < 0:
        raise ValueError(f"--delay: expected a non-negative number of control steps, got {cfg.delay}")
    if cfg.steps is not None and cfg.steps < 1:
        raise ValueError(f"--steps: expected a positive number of sampling steps, got {cfg.steps}")
    if not (cfg.obs_timeout > 0 and math.isfinite(cfg.obs_timeout)):
        raise ValueError(f"--obs-timeout: expected a positive number of seconds, got {cfg.obs_timeout}")
    if not Path(cfg.checkpoint).expanduser().exists():
        raise ValueError(f"--checkpoint: {cfg.checkpoint} does not exist; expected a checkpoint directory "
                         f"(action-decoder train's, or a LeRobot pretrained_model of the action_decoder plugin)")


def run_serve(cfg: ServeConfig) -> None:
    """Serve until interrupted (Ctrl-C). Without LeRobot or grpcio: one ValueError line naming what to install."""
    check_serve_config(cfg)
    try:
        server = importlib.import_module(SERVER_MODULE)
    except ModuleNotFoundError as err:
        raise ValueError(f"serve: needs LeRobot's async inference (module {err.name!r} is not installed): "
                         f"{INSTALL_HINT}") from None
    server.serve(cfg)


# ---------------------------------------------------------------------- bookkeeping (pure)
def delay_steps(seconds: float, fps: float) -> int:
    """Control steps a client at `fps` Hz executes within `seconds`: ⌈seconds·fps⌉ (0 for none).

    Rounded up: the client executes ⌊seconds·fps⌋ or one more, depending on where its tick falls."""
    if not (seconds >= 0 and math.isfinite(seconds)):
        raise ValueError(f"seconds: expected a finite latency >= 0, got {seconds}")
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps: expected a control frequency > 0 in Hz, got {fps}")
    return max(0, math.ceil(seconds * fps - 1e-9))


def expected_latency(uplink_s: float, waited_s: float, recent_compute_s: Sequence[float], window: int = 10) -> float:
    """Seconds from the observation's capture at the client to the chunk's arrival there:
    the uplink twice (the reply travels back the same way), the time the observation has
    waited at the server, and the longest of the last `window` compute times (0 before any)."""
    recent = list(recent_compute_s)[-window:] if window > 0 else []
    return 2 * max(0.0, uplink_s) + max(0.0, waited_s) + (max(recent) if recent else 0.0)


@dataclass(frozen=True)
class ChunkPlan:
    """Where a new chunk goes and what it continues.

    `start`: the client timestep of the new chunk's row 0. `prev_from`: the row of the previous
    chunk at that timestep. `overlap` L: how many rows of the previous chunk the client still
    holds from there on (the new chunk's rows 0..L−1 coincide with them). `delay` d ≤ L: the rows
    the client executes while the new chunk is computed; the new chunk's rows 0..d−1 are those."""

    start: int
    prev_from: int = 0
    overlap: int = 0
    delay: int = 0


def plan_chunk(obs_timestep: int, prev_start: Optional[int], prev_sent: int, delay: int, horizon: int) -> ChunkPlan:
    """The `ChunkPlan` of a chunk for the observation labelled `obs_timestep`, after a previous chunk
    that started at `prev_start` (None: none since the client connected) of which `prev_sent` rows were sent;
    `delay` is the estimated inference delay in control steps and `horizon` H the chunk length.

    The committed rows are capped at H − 1 (one row at least is the new chunk's own) and at the
    overlap (rows the client does not hold are never executed)."""
    for name, value in (("obs_timestep", obs_timestep), ("prev_sent", prev_sent), ("delay", delay)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name}: expected a non-negative integer, got {value!r}")
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"horizon: expected a positive chunk length, got {horizon!r}")
    if prev_start is None:
        return ChunkPlan(start=obs_timestep)
    start = obs_timestep + 1
    prev_from = start - prev_start
    if prev_from < 0 or prev_from >= prev_sent:        # older than the previous chunk, or past its end
        return ChunkPlan(start=start)
    overlap = min(prev_sent - prev_from, horizon)
    return ChunkPlan(start=start, prev_from=prev_from, overlap=overlap, delay=min(delay, overlap, horizon - 1))


def chunk_timing(obs_timestamp: float, obs_timestep: int, start: int, rows: int, fps: float) -> list[tuple[float, int]]:
    """(timestamp, timestep) of each of `rows` actions from timestep `start`: the observation's client
    timestamp advanced by one control period per timestep past the observation's."""
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"fps: expected a control frequency > 0 in Hz, got {fps}")
    return [(obs_timestamp + (start + i - obs_timestep) / fps, start + i) for i in range(rows)]


def control_rate(samples: Sequence[tuple[float, int]]) -> Optional[float]:
    """The client's control frequency in Hz from its observations' (timestamp, timestep) pairs, in the
    order sent: the median of Δtimestep/Δtimestamp over consecutive pairs whose timestep advanced
    (the client executed actions between them); None before there is one."""
    rates = [(b[1] - a[1]) / (b[0] - a[0]) for a, b in zip(samples, samples[1:]) if b[1] > a[1] and b[0] > a[0]]
    if not rates:
        return None
    rates.sort()
    mid = len(rates) // 2
    return rates[mid] if len(rates) % 2 else (rates[mid - 1] + rates[mid]) / 2


def rate_mismatch(measured: Optional[float], fps: float, tolerance: float = 0.25) -> bool:
    """Whether a measured control rate is more than `tolerance` (relative) away from --fps."""
    return measured is not None and abs(measured - fps) > tolerance * fps


def should_predict(obs_timestep: int, must_go: bool, last_predicted: Optional[int]) -> bool:
    """Whether an observation earns a chunk: the client says it must (its queue ran empty), or it is
    newer than the last observation a chunk was computed for (the client sends one every control
    step while its queue is below its threshold; older or repeated ones are stale)."""
    return bool(must_go) or last_predicted is None or obs_timestep > last_predicted
