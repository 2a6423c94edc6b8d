"""`action-decoder serve`: an async policy server for LeRobot's `RobotClient`, unchanged.

It speaks LeRobot's async-inference protocol (the `transport.AsyncInference` gRPC service:
`Ready`, `SendPolicyInstructions`, `SendObservations`, `GetActions`, with LeRobot's pickled
`RemotePolicyConfig`, `TimedObservation` and lists of `TimedAction`) and serves one checkpoint,
chosen when the server starts: a library checkpoint (`action-decoder train`, normalising inside
the policy) or a LeRobot `pretrained_model` of this plugin (normalising in its saved processors).

The client's policy instructions are checked against it, not obeyed: `policy_type` must be
`action_decoder` and `pretrained_name_or_path` must name the served checkpoint (a refusal is one
line in the client's log, with the value to use); `actions_per_chunk` (1..H rows sent per chunk),
`policy_device` (where the policy runs) and `rename_map` (observation keys) are honoured.

Each chunk: the latest observation newer than the last one served (or one the client says must
go) → LeRobot's observation layout (`observation.state` from the robot's named values, camera
frames in [0, 1], the task string) → the checkpoint's own preprocessing → a chunk, conditioned on
the committed prefix of the previous chunk (real-time chunking, `action_decoder.serving`) → the
checkpoint's postprocessing → `actions_per_chunk` timed actions.
"""

from __future__ import annotations

import json
import logging
import pickle  # nosec: LeRobot's protocol pickles its payloads; serve trusted clients only
import queue
import signal
import sys
import threading
import time
from collections import deque
from concurrent import futures
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import grpc
import numpy as np
import torch
from torch import Tensor

from action_decoder import ActionDecoderPolicy as CorePolicy
from action_decoder.cli import check_device
from action_decoder.flows.paths import randn_rows
from action_decoder.policy import follow_last
from action_decoder.serving import (ServeConfig, chunk_timing, control_rate, delay_steps, expected_latency, plan_chunk,
                                    rate_mismatch, should_predict)
from lerobot.async_inference.helpers import RemotePolicyConfig, TimedAction, TimedObservation
from lerobot.transport import services_pb2, services_pb2_grpc
from lerobot.transport.utils import receive_bytes_in_chunks

from .convert import STATE, TASK, to_core_batch

POLICY_TYPE = "action_decoder"
IMAGES = "observation.images."
log = logging.getLogger("action_decoder.serve")


@dataclass
class Served:
    """A loaded checkpoint: the core policy that samples chunks, and the conversions around it.

    `prepare` maps a LeRobot observation (batch of one) to the core batch (through the
    checkpoint's preprocessor for a LeRobot layout); `to_env` maps chunk rows [N, D] from the
    policy's units to the robot's (the postprocessor for a LeRobot layout; the identity for a
    library checkpoint, whose policy un-normalises itself)."""

    path: Path
    layout: str                                   # "library" | "lerobot"
    core: CorePolicy
    state_dim: int
    cameras: list
    prepare: Callable[[dict], dict]
    to_env: Callable[[Tensor], Tensor]

    @property
    def horizon(self) -> int:
        return self.core.config.action_chunk_size


def load_checkpoint(name: str) -> Served:
    """The `Served` checkpoint of a library directory or a plugin `pretrained_model`; one ValueError line otherwise."""
    path = follow_last(name).expanduser()
    config = path / "config.json"
    if not config.is_file():
        raise ValueError(f"--checkpoint: {path} has no config.json; expected a checkpoint directory (action-decoder "
                         f"train's final/ or checkpoints/step_N, or a LeRobot pretrained_model of the plugin)")
    try:
        meta = json.loads(config.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"--checkpoint: {config} is not JSON ({err})") from None
    kind = meta.get("type")
    if kind is not None and kind != POLICY_TYPE:
        raise ValueError(f"--checkpoint: {path} is a LeRobot checkpoint of policy type {kind!r}; this server serves "
                         f"{POLICY_TYPE!r} checkpoints (LeRobot's own policy_server serves {kind!r})")
    served = _load_lerobot(path) if kind == POLICY_TYPE else _load_library(path)
    n_obs = served.core.config.n_obs_steps
    if n_obs > 1:
        raise ValueError(f"--checkpoint: {path} conditions on n_obs_steps={n_obs} consecutive observations, and "
                         f"LeRobot's RobotClient sends an observation only when its action queue runs low; "
                         f"serve checkpoints trained with n_obs_steps=1")
    return served


def _load_library(path: Path) -> Served:
    core = CorePolicy.from_pretrained(path)
    cfg = core.config
    tasks = list(cfg.extra.get("tasks") or [])
    if cfg.uses_vlm_cache or (cfg.context_dim is not None and cfg.context_dim != len(tasks)):
        raise ValueError(f"--checkpoint: {path} conditions on context tokens or VLM features "
                         f"(context_dim={cfg.context_dim}) that a LeRobot client does not send; the server serves "
                         f"policies conditioned on the state, cameras and task string")

    def prepare(obs: dict) -> dict:
        return to_core_batch(obs, tasks, cfg.state_dim, False, cfg.cameras, cfg.image_size)

    return Served(path, "library", core, cfg.state_dim, list(cfg.cameras), prepare, lambda rows: rows)


def _load_lerobot(path: Path) -> Served:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors

    from .modeling_action_decoder import ActionDecoderPolicy

    pcfg = PreTrainedConfig.from_pretrained(path)
    pcfg.device = "cpu"              # the core policy moves the batch to its own device
    policy = ActionDecoderPolicy.from_pretrained(path, config=pcfg).eval()
    pre, post = make_pre_post_processors(pcfg, pretrained_path=str(path))

    def prepare(obs: dict) -> dict:
        return to_core_batch(pre(obs), pcfg.tasks, policy.state_dim, False, policy.cameras, pcfg.image_size)

    return Served(path, "lerobot", policy.decoder, policy.state_dim, list(policy.cameras), prepare,
                  lambda rows: post(rows))


def lerobot_observation(raw: dict, features: dict, rename: dict) -> dict:
    """A robot's raw observation (named joint values, camera frames [H, W, 3] uint8, `task`) in
    LeRobot's layout for a batch of one: `observation.state` [1, S] from the names of the client's
    `lerobot_features`, `observation.images.<cam>` [1, 3, H, W] in [0, 1], `task`; keys renamed."""
    obs = {}
    for key, ft in features.items():
        if not key.startswith("observation"):
            continue
        if ft.get("dtype") in ("image", "video"):
            name = key.removeprefix(IMAGES)
            if name not in raw:
                raise ValueError(f"observation: missing camera {name!r} (lerobot_features[{key!r}]); got keys "
                                 f"{sorted(raw)}")
            frame = torch.as_tensor(np.asarray(raw[name]))
            if frame.dim() != 3 or frame.shape[-1] != 3:
                raise ValueError(f"observation[{name!r}]: expected a camera frame [H, W, 3], got {list(frame.shape)}")
            frame = frame.permute(2, 0, 1)[None]                                           # [1, 3, H, W]
            obs[key] = frame.float() / 255.0 if not frame.is_floating_point() else frame.float()
        elif len(ft.get("shape", ())) == 1:
            missing = [n for n in ft["names"] if n not in raw]
            if missing:
                raise ValueError(f"observation: missing {missing} of lerobot_features[{key!r}]; got keys {sorted(raw)}")
            obs[key] = torch.tensor([[float(raw[n]) for n in ft["names"]]], dtype=torch.float32)   # [1, S]
    obs = {rename.get(k, k): v for k, v in obs.items()}
    obs[TASK] = str(raw.get(TASK) or "")
    return obs


def check_features(served: Served, features: dict, rename: dict) -> None:
    """The client's `lerobot_features` (renamed) give the served policy its state width and cameras; one line if not."""
    if not isinstance(features, dict):
        raise ValueError(f"lerobot_features: expected a dict of LeRobot features, got {type(features).__name__}")
    renamed = {rename.get(k, k): v for k, v in features.items()}
    state = renamed.get(STATE)
    shape = tuple(state.get("shape", ())) if isinstance(state, dict) else None
    if shape != (served.state_dim,):
        raise ValueError(f"lerobot_features[{STATE!r}]: the served policy reads a state of {served.state_dim} values; "
                         f"the robot gives {'none' if shape is None else shape} (features {sorted(renamed)})")
    missing = [cam for cam in served.cameras if cam not in renamed]
    if missing:
        raise ValueError(f"lerobot_features: the served policy needs camera(s) {missing}; the robot gives "
                         f"{sorted(k for k in renamed if k.startswith(IMAGES))} (rename_map maps robot names)")


def same_checkpoint(name: str, served: Served, given: str) -> bool:
    """Whether a client's `pretrained_name_or_path` names the served checkpoint."""
    if not isinstance(name, str) or not name:
        return False
    if name == given:
        return True
    try:
        return follow_last(name).expanduser().resolve() == served.path.resolve()
    except OSError:
        return False


class PolicyServer(services_pb2_grpc.AsyncInferenceServicer):
    """LeRobot's `AsyncInference` service over one served checkpoint (module docstring)."""

    def __init__(self, cfg: ServeConfig, served: Served):
        self.cfg, self.served = cfg, served
        self.rtc = cfg.rtc and served.core.config.decoder_type != "DDPM"
        if cfg.rtc_mode == "trained" and not served.core.config.rtc_max_delay:
            raise ValueError("--rtc-mode: 'trained' needs a checkpoint trained with real-time chunking "
                             "(train --rtc-max-delay N); this one has rtc_max_delay=0: use auto or guided")
        if cfg.compile:
            check_compiled_serving(cfg, served.core, self.rtc)
        self.sample_fn: Optional[Callable] = None   # compile_sampler's, built at the first observation (--compile)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.stop_event = threading.Event()
        self.lock = threading.Lock()              # one chunk at a time, and the previous chunk below
        self.obs_lock = threading.Lock()          # the observation slot: never held while a chunk is computed
        self.slot: queue.Queue = queue.Queue(maxsize=1)
        self.compute_s: deque = deque(maxlen=10)  # recent compute times (seconds), for the delay estimate
        self.chunks = 0
        self.log_file = open(cfg.log_chunks, "a") if cfg.log_chunks else None
        self._new_client(None)

    def _new_client(self, spec: Optional[RemotePolicyConfig]) -> None:
        self.spec = spec
        self.prev: Optional[Tensor] = None        # the last chunk [H, D], policy units
        self.prev_start: Optional[int] = None
        self.prev_sent = 0
        self.warned_rate = False
        with self.obs_lock:
            self.last_queued: Optional[int] = None
            self.sent_obs: deque = deque(maxlen=30)     # (client timestamp, timestep) of the latest observations
            while not self.slot.empty():
                self.slot.get_nowait()

    # ------------------------------------------------------------------ the protocol
    def Ready(self, request, context):  # noqa: N802
        with self.lock:
            self._new_client(None)
        log.info("client %s ready", context.peer())
        return services_pb2.Empty()

    def SendPolicyInstructions(self, request, context):  # noqa: N802
        try:
            try:
                spec = pickle.loads(request.data)  # nosec
            except Exception as err:               # a payload of classes this side lacks, or no pickle at all
                raise ValueError(f"policy instructions: expected a pickled RemotePolicyConfig, could not read it "
                                 f"({type(err).__name__}: {err})") from None
            self._accept(spec)
        except ValueError as err:
            log.error("refused policy instructions: %s", err)
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"action-decoder serve: {err}")
        with self.lock:
            self._new_client(spec)
        log.info("client %s: %d actions per chunk on %s", context.peer(), spec.actions_per_chunk, spec.device)
        return services_pb2.Empty()

    def _accept(self, spec: Any) -> None:
        served, h = self.served, self.served.horizon
        if not isinstance(spec, RemotePolicyConfig):
            raise ValueError(f"policy instructions: expected LeRobot's RemotePolicyConfig, got {type(spec).__name__}")
        if spec.policy_type != POLICY_TYPE:
            raise ValueError(f"policy_type: this server serves {POLICY_TYPE!r} checkpoints; got "
                             f"{spec.policy_type!r}: start the client with --policy_type={POLICY_TYPE}")
        if not same_checkpoint(spec.pretrained_name_or_path, served, self.cfg.checkpoint):
            raise ValueError(f"pretrained_name_or_path: this server serves {self.cfg.checkpoint} (its --checkpoint); "
                             f"got {spec.pretrained_name_or_path!r}: name it, or start a server with that checkpoint")
        a = spec.actions_per_chunk
        if isinstance(a, bool) or not isinstance(a, int) or not 1 <= a <= h:
            raise ValueError(f"actions_per_chunk: expected 1..{h} (the served chunk length), got {a!r}")
        rename = spec.rename_map or {}
        check_features(served, spec.lerobot_features, rename)
        check_device(spec.device, "policy_device")
        served.core.to(spec.device)
        self.sample_fn = None                     # compiled for the device the client asks for

    def SendObservations(self, request_iterator, context):  # noqa: N802
        received = time.time()
        data = receive_bytes_in_chunks(request_iterator, None, self.stop_event, "action-decoder serve")
        if data is None:
            return services_pb2.Empty()
        obs = pickle.loads(data)  # nosec
        if not isinstance(obs, TimedObservation):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                          f"action-decoder serve: observation: expected LeRobot's TimedObservation, got "
                          f"{type(obs).__name__}")
        with self.obs_lock:                        # the client's control loop waits for this reply
            self.sent_obs.append((obs.get_timestamp(), obs.get_timestep()))
            if self.spec is None or not should_predict(obs.get_timestep(), obs.must_go, self.last_queued):
                return services_pb2.Empty()
            self.last_queued = obs.get_timestep()
            try:                                   # keep only the newest observation
                self.slot.get_nowait()
            except queue.Empty:
                pass
            self.slot.put((obs, received))
        return services_pb2.Empty()

    def GetActions(self, request, context):  # noqa: N802
        try:
            obs, received = self.slot.get(timeout=self.cfg.obs_timeout)
        except queue.Empty:
            return services_pb2.Empty()
        with self.lock:
            if self.spec is None:
                return services_pb2.Empty()
            try:
                actions, record = self.chunk(obs, received)
            except ValueError as err:
                log.error("observation #%d: %s", obs.get_timestep(), err)
                context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"action-decoder serve: {err}")
        data = pickle.dumps(actions)  # nosec
        self._report(record)
        return services_pb2.Actions(data=data)

    # ------------------------------------------------------------------ one chunk
    def chunk(self, obs: TimedObservation, received: float) -> tuple[list, dict]:
        """The timed actions for `obs` and the record of how they were made (the lock is held)."""
        cfg, served, spec = self.cfg, self.served, self.spec
        core, k = served.core, obs.get_timestep()
        picked = time.time()
        uplink, waited = received - obs.get_timestamp(), picked - received
        latency = expected_latency(uplink, waited, self.compute_s)
        delay = cfg.delay if cfg.delay is not None else delay_steps(latency, cfg.fps)
        with self.obs_lock:
            samples = list(self.sent_obs)
        client_hz = control_rate(samples)
        if len(samples) >= 10 and rate_mismatch(client_hz, cfg.fps) and not self.warned_rate:
            log.warning("the client executes about %.1f actions per second, --fps is %g: the delay in control steps "
                        "is computed with --fps; restart the server with --fps %.0f", client_hz, cfg.fps, client_hz)
            self.warned_rate = True
        plan = plan_chunk(k, self.prev_start, self.prev_sent, delay if self.rtc else 0, served.horizon)
        start = time.perf_counter()
        batch = served.prepare(lerobot_observation(obs.get_observation(), spec.lerobot_features,
                                                   spec.rename_map or {}))
        prepared = time.perf_counter()
        mode, committed = None, 0
        kwargs = {"steps": cfg.steps, "generator": self.generator, "return_logprob": False}
        if self.rtc and self.prev is not None and plan.overlap > 0:
            wanted = "trained" if cfg.compile else (None if cfg.rtc_mode == "auto" else cfg.rtc_mode)
            committed = plan.delay if wanted != "trained" else min(plan.delay, core.config.rtc_max_delay)
            mode = core.resolve_rtc_mode(wanted, committed)
            prev = self.prev[plan.prev_from: plan.prev_from + plan.overlap][None]          # [1, L, D]
            kwargs.update(prev_chunk=prev, delay=committed, rtc_mode=mode)
        compiling = cfg.compile and self.sample_fn is None
        if cfg.compile:
            chunk = self._compiled_chunk(batch, kwargs)                                    # [H, D], policy units
        else:
            chunk = core.predict_action_chunk(batch, **kwargs)[0]                          # [H, D], policy units
        sampled = time.perf_counter()
        rows = served.to_env(chunk[: spec.actions_per_chunk].detach().cpu())             # [A, D], robot units
        done = time.perf_counter()
        actions = [TimedAction(timestamp=ts, timestep=step, action=rows[i])
                   for i, (ts, step) in enumerate(chunk_timing(obs.get_timestamp(), k, plan.start, len(rows), cfg.fps))]
        self.prev, self.prev_start, self.prev_sent = chunk.detach(), plan.start, len(rows)
        if not compiling:                          # compiling is not the latency of later chunks
            self.compute_s.append(done - start)
        self.chunks += 1
        record = {"chunk": self.chunks, "obs_timestep": k, "must_go": bool(obs.must_go), "start": plan.start,
                  "rows": len(rows), "delay": delay, "overlap": plan.overlap, "committed": committed,
                  "rtc_mode": mode, "client_hz": None if client_hz is None else round(client_hz, 2),
                  "uplink_ms": round(1000 * uplink, 3), "waited_ms": round(1000 * waited, 3),
                  "prepare_ms": round(1000 * (prepared - start), 3), "sample_ms": round(1000 * (sampled - prepared), 3),
                  "compute_ms": round(1000 * (done - start), 3)}
        return actions, record

    def _compiled_chunk(self, batch: dict, kwargs: dict) -> Tensor:
        """`predict_action_chunk(batch, **kwargs)[0]` through `compile_sampler` (trained RTC), from the noise the
        eager call would draw with the server's generator; compiled at the first call."""
        core = self.served.core
        if self.sample_fn is None:
            from action_decoder.compiled import compile_sampler

            log.info("compiling the sampler for %s (one chunk's time, once)", next(core.parameters()).device)
            self.sample_fn = compile_sampler(core, steps=kwargs["steps"], rtc=self.rtc)
        cfg = core.config
        noise = randn_rows(1, (cfg.action_chunk_size, cfg.action_dim), kwargs["generator"],
                           next(core.parameters()).device)                                 # [1, H, D]
        rtc = {"prev_chunk": kwargs["prev_chunk"], "delay": kwargs["delay"]} if "prev_chunk" in kwargs else {}
        return self.sample_fn(batch, noise, **rtc)[0]

    def _report(self, record: dict) -> None:
        log.info("chunk %d for observation #%d%s: timesteps %d..%d, delay %d steps, %s, %.1f ms (sampling %.1f ms)",
                 record["chunk"], record["obs_timestep"], " (must go)" if record["must_go"] else "",
                 record["start"], record["start"] + record["rows"] - 1, record["delay"],
                 f"rtc {record['rtc_mode']} on {record['committed']} committed of {record['overlap']} overlapping rows"
                 if record["rtc_mode"] else "no previous rows", record["compute_ms"], record["sample_ms"])
        if self.log_file is not None:
            self.log_file.write(json.dumps(record) + "\n")
            self.log_file.flush()

    def stop(self) -> None:
        self.stop_event.set()
        if self.log_file is not None:
            self.log_file.close()
            self.log_file = None


def check_compiled_serving(cfg: ServeConfig, core: CorePolicy, rtc: bool) -> None:
    """One ValueError line where `--compile` cannot serve this checkpoint: the compiled sampler is
    deterministic and, with real-time chunking, runs the trained mode only."""
    from action_decoder.compiled import check_compile
    from action_decoder.export import export_refusal

    check_compile()
    refusal = export_refusal(core, None)
    if refusal:
        raise ValueError(f"--compile: {refusal}")
    if rtc and (cfg.rtc_mode == "guided" or not core.config.rtc_max_delay):
        raise ValueError("--compile: the compiled sampler runs trained real-time chunking only (a checkpoint trained "
                         f"with --rtc-max-delay; this one has rtc_max_delay={core.config.rtc_max_delay}"
                         f"{', and --rtc-mode guided was asked' if cfg.rtc_mode == 'guided' else ''}): "
                         "use --no-rtc, or drop --compile")


def serve(cfg: ServeConfig) -> None:
    """Load `cfg.checkpoint`, listen on `cfg.host:cfg.port` and serve until SIGINT or SIGTERM."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s serve: %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False
    served = load_checkpoint(cfg.checkpoint)
    servicer = PolicyServer(cfg, served)
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    services_pb2_grpc.add_AsyncInferenceServicer_to_server(servicer, server)
    try:
        port = server.add_insecure_port(f"{cfg.host}:{cfg.port}")
    except RuntimeError:
        port = 0
    if port == 0:
        raise ValueError(f"--host/--port: cannot listen on {cfg.host}:{cfg.port} (in use, or not an address of "
                         f"this machine)")
    server.start()
    c = served.core.config
    rtc = "off" if not servicer.rtc else (f"{cfg.rtc_mode}, delay "
                                          f"{cfg.delay if cfg.delay is not None else 'measured'} at {cfg.fps:g} Hz")
    print(f"action-decoder serve: {served.path} ({served.layout} layout, {c.decoder_type}, "
          f"{cfg.steps or c.num_inference_timesteps} steps, chunk {c.action_chunk_size}{', compiled' if cfg.compile else ''}) "
          f"on {cfg.host}:{port}; real-time chunking {rtc}", flush=True)
    if cfg.rtc and not servicer.rtc:
        log.info("DDPM has no real-time chunking: chunks are sampled without the previous one")
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        while not stop.wait(0.5):
            pass
    finally:
        signal.signal(signal.SIGTERM, previous)
        servicer.stop()
        server.stop(grace=1).wait()
