"""`action-decoder serve` against LeRobot's own `RobotClient`, unmodified, on loopback.

Tiny checkpoints are trained here in seconds on the LeRobot-written fixture (6-d state, 3-d
action, two tasks): MF-1 (mean_flow, 1 step, trained for real-time chunking) served from the
library layout, FM-10 (flow_matching, 10 Euler steps, guided real-time chunking) converted to
the plugin's LeRobot layout. The server runs as a subprocess (`python -m action_decoder.cli
serve`) on a free port; the client drives a simulated robot registered below, bounded in
actions and seconds. Runs where LeRobot's async stack is installed (scripts/lerobot_integration.sh
runs it in its venv); skipped elsewhere.
"""

import json
import math
import os
import pickle
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

pytest.importorskip("grpc")
pytest.importorskip("lerobot.async_inference.robot_client")

from lerobot.robots.config import RobotConfig  # noqa: E402
from lerobot.robots.robot import Robot  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "data" / "lerobot" / "v30_toy"
TASK = "push the block"
ACTIONS_PER_CHUNK, EXECUTED, SECONDS = 12, 45, 60
CHUNK = 16


@RobotConfig.register_subclass("action_decoder_test_sim")
@dataclass
class SimRobotConfig(RobotConfig):
    """A simulated 6-joint robot with a 3-d action (the fixture's shapes)."""


class SimRobot(Robot):
    """State: three positions moved by the action and three oscillators; it records what it is sent."""

    config_class = SimRobotConfig
    name = "action_decoder_test_sim"

    def __init__(self, config: SimRobotConfig):
        super().__init__(config)
        self.state = [0.1, -0.2, 0.3, 0.0, 0.0, 0.0]
        self.sent: list = []
        self.connected = False

    @property
    def observation_features(self) -> dict:
        return {f"s{i}": float for i in range(6)}

    @property
    def action_features(self) -> dict:
        return {"dx": float, "dy": float, "grip": float}

    @property
    def is_connected(self) -> bool:
        return self.connected

    def connect(self, calibrate: bool = True) -> None:
        self.connected = True

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict:
        return {f"s{i}": v for i, v in enumerate(self.state)}

    def send_action(self, action: dict) -> dict:
        for i, key in enumerate(("dx", "dy", "grip")):
            self.state[i] += 0.1 * float(action[key])
        self.state[3:] = [math.sin(len(self.sent) / 10 + j) for j in range(3)]
        self.sent.append(dict(action))
        return action

    def disconnect(self) -> None:
        self.connected = False


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """{"MF-1": library checkpoint, "FM-10": LeRobot-layout checkpoint}, trained on the fixture."""
    from action_decoder.lerobot_checkpoint import to_lerobot
    from action_decoder.train import TrainConfig, train

    root = tmp_path_factory.mktemp("serve_ckpts")
    tiny = dict(dataset=str(FIXTURE), steps=20, batch_size=16, hidden_size=32, num_layers=1, num_heads=2,
                num_kv_heads=1, horizon=CHUNK, eval_episodes=0, progress=False, seed=0)
    mf = train(TrainConfig(decoder="mean_flow", rtc_max_delay=4, output_dir=str(root / "mf"), **tiny))
    fm = train(TrainConfig(decoder="flow_matching", output_dir=str(root / "fm"), **tiny))
    return {"MF-1": mf, "FM-10": to_lerobot(fm, root / "fm_lerobot")}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serving(checkpoint: Path, log: Path, *extra: str):
    """`action-decoder serve` in a subprocess on a free loopback port; yields the port, stops it with SIGTERM."""
    port = free_port()
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "lerobot_policy_action_decoder" / "src"),
                                          os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "action_decoder.cli", "serve", "--checkpoint", str(checkpoint),
                             "--port", str(port), "--log-chunks", str(log), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    lines: list = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    deadline = time.time() + SECONDS
    while not any("action-decoder serve:" in line for line in lines):
        if proc.poll() is not None or time.time() > deadline:
            proc.kill()
            pytest.fail(f"serve did not start (exit {proc.returncode}): {proc.stderr.read()[-2000:]}")
        time.sleep(0.1)
    try:
        yield port
    finally:
        proc.terminate()
        try:
            code = proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            code = "killed"
        err = proc.stderr.read()
        assert code == 0, f"serve exited with {code} after SIGTERM: {err[-2000:]}"


def run_client(port: int, checkpoint: Path, tmp_path: Path, monkeypatch, **over):
    """LeRobot's RobotClient with the simulated robot until it executed EXECUTED actions (or SECONDS
    passed); returns (robot, received chunks as lists of TimedAction)."""
    monkeypatch.chdir(tmp_path)                       # LeRobot's loggers write ./logs/
    from lerobot.async_inference.configs import RobotClientConfig
    from lerobot.async_inference.robot_client import RobotClient

    cfg = RobotClientConfig(policy_type="action_decoder", pretrained_name_or_path=str(checkpoint),
                            robot=SimRobotConfig(), actions_per_chunk=ACTIONS_PER_CHUNK, task=TASK,
                            server_address=f"127.0.0.1:{port}", fps=30, aggregate_fn_name="latest_only", **over)
    client = RobotClient(cfg)
    received: list = []
    aggregate = client._aggregate_action_queues

    def watched(incoming, fn=None):                   # observe what arrives; the client's own code merges it
        received.append(list(incoming))
        return aggregate(incoming, fn)

    client._aggregate_action_queues = watched
    assert client.start(), "RobotClient could not start against the server"
    receiver = threading.Thread(target=client.receive_actions, daemon=True)
    control = threading.Thread(target=client.control_loop, kwargs={"task": TASK}, daemon=True)
    receiver.start()
    control.start()
    deadline = time.time() + SECONDS
    while len(client.robot.sent) < EXECUTED and time.time() < deadline:
        time.sleep(0.02)
    client.stop()
    control.join(timeout=5)
    receiver.join(timeout=5)
    return client.robot, received


def instructions_error(port: int, **spec_over) -> str:
    """The server's answer to policy instructions, through LeRobot's protocol stub and payload class."""
    import grpc
    from lerobot.async_inference.helpers import RemotePolicyConfig
    from lerobot.transport import services_pb2, services_pb2_grpc

    spec = dict(policy_type="action_decoder", pretrained_name_or_path="", actions_per_chunk=ACTIONS_PER_CHUNK,
                lerobot_features={"observation.state": {"dtype": "float32", "shape": (6,),
                                                        "names": [f"s{i}" for i in range(6)]}}, device="cpu")
    spec.update(spec_over)
    with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
        stub = services_pb2_grpc.AsyncInferenceStub(channel)
        stub.Ready(services_pb2.Empty())
        try:
            stub.SendPolicyInstructions(services_pb2.PolicySetup(data=pickle.dumps(RemotePolicyConfig(**spec))))
        except grpc.RpcError as err:
            assert err.code() == grpc.StatusCode.INVALID_ARGUMENT
            return err.details()
    return ""


@pytest.mark.parametrize("name, rtc_mode", [("MF-1", "trained"), ("FM-10", "guided")])
def test_robot_client_receives_timed_chunks_with_real_time_chunking(checkpoints, name, rtc_mode, tmp_path, monkeypatch):
    ckpt = checkpoints[name]
    log = tmp_path / "chunks.jsonl"
    with serving(ckpt, log) as port:
        if name == "MF-1":       # instructions the server cannot follow: one line each, the client learns why
            assert "policy_type" in instructions_error(port, policy_type="act", pretrained_name_or_path=str(ckpt))
            assert "pretrained_name_or_path" in instructions_error(port, pretrained_name_or_path="/elsewhere")
            assert "actions_per_chunk: expected 1..16" in instructions_error(
                port, pretrained_name_or_path=str(ckpt), actions_per_chunk=50)
            assert "reads a state of 6 values" in instructions_error(
                port, pretrained_name_or_path=str(ckpt),
                lerobot_features={"observation.state": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}})
        robot, received = run_client(port, ckpt, tmp_path, monkeypatch)
    records = [json.loads(line) for line in log.read_text().splitlines()]
    print(f"{name}: {len(records)} chunks served, {len(robot.sent)} actions executed; compute ms",
          [r["compute_ms"] for r in records])

    assert len(robot.sent) >= EXECUTED, f"the robot executed {len(robot.sent)} actions in {SECONDS} s"
    assert all(set(a) == {"dx", "dy", "grip"} and all(math.isfinite(v) for v in a.values()) for a in robot.sent)
    assert len(received) >= 3 and len(records) >= len(received)
    for chunk in received:                # actions_per_chunk rows on consecutive timesteps, tensors [3]
        steps = [a.get_timestep() for a in chunk]
        assert len(chunk) == ACTIONS_PER_CHUNK and steps == list(range(steps[0], steps[0] + ACTIONS_PER_CHUNK))
        assert all(a.get_action().shape == (3,) for a in chunk)
        assert all(b.get_timestamp() > a.get_timestamp() for a, b in zip(chunk, chunk[1:]))
    # the first chunk starts at the first observation; every later one after the action observed
    assert records[0]["start"] == records[0]["obs_timestep"] == 0 and records[0]["rtc_mode"] is None
    assert all(r["start"] == r["obs_timestep"] + 1 for r in records[1:])
    assert [c[0].get_timestep() for c in received] == [r["start"] for r in records[: len(received)]]
    # real-time chunking: the committed rows are the previous chunk's actions at those timesteps, exactly
    conditioned = [(i, r) for i, r in enumerate(records[: len(received)]) if r["committed"] > 0]
    assert conditioned, f"no chunk continued a committed prefix: {records}"
    for i, r in conditioned:
        assert r["rtc_mode"] == rtc_mode and r["committed"] <= r["delay"]
        before = {a.get_timestep(): a.get_action() for a in received[i - 1]}
        for a in received[i][: r["committed"]]:
            assert torch.allclose(a.get_action(), before[a.get_timestep()], atol=1e-6), (i, a.get_timestep())
