"""`action-decoder serve` against LeRobot's own `RobotClient`, unmodified, on loopback.

Tiny checkpoints are trained here in seconds on the LeRobot-written fixture (6-d state, 3-d
action, two tasks): MF-1 (mean_flow, 1 step, trained for real-time chunking) served from the
library layout, FM-10 (flow_matching, 10 Euler steps, guided real-time chunking) converted to
the plugin's LeRobot layout. The server runs as a subprocess (`python -m action_decoder.cli
serve`) on a free port; the client drives the plugin's simulated robot (`sim_robot`), bounded in
actions and seconds (the harness of `python -m benchmarks serve`, which reads the client's queue at
each arrival and leaves its merge unchanged). Runs where LeRobot's async stack is installed (scripts/lerobot_integration.sh
runs it in its venv); skipped elsewhere.
"""

import json
import math
import pickle
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("grpc")
pytest.importorskip("lerobot.async_inference.helpers")   # robot_client opens ./logs/ on import: drive_client imports it

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "lerobot_policy_action_decoder" / "src")]
from benchmarks.serve import drive_client, serve_subprocess  # noqa: E402   the harness `python -m benchmarks serve` uses

FIXTURE = ROOT / "tests" / "data" / "lerobot" / "v30_toy"
ACTIONS_PER_CHUNK, EXECUTED, SECONDS = 12, 45, 60
CHUNK = 16


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


@pytest.mark.parametrize("name, rtc_mode, extra", [("MF-1", "trained", ()), ("FM-10", "guided", ()),
                                                   ("MF-1", "trained", ("--compile",))],
                         ids=["MF-1", "FM-10", "MF-1-compiled"])
def test_robot_client_receives_timed_chunks_with_real_time_chunking(checkpoints, name, rtc_mode, extra, tmp_path):
    ckpt = checkpoints[name]
    log = tmp_path / "chunks.jsonl"
    with serve_subprocess(ckpt, log, *extra, timeout=SECONDS) as (port, server):
        if name == "MF-1" and not extra:   # instructions the server cannot follow: one line each, the client learns why
            assert "policy_type" in instructions_error(port, policy_type="act", pretrained_name_or_path=str(ckpt))
            assert "pretrained_name_or_path" in instructions_error(port, pretrained_name_or_path="/elsewhere")
            assert "actions_per_chunk: expected 1..16" in instructions_error(
                port, pretrained_name_or_path=str(ckpt), actions_per_chunk=50)
            assert "reads a state of 6 values" in instructions_error(
                port, pretrained_name_or_path=str(ckpt),
                lerobot_features={"observation.state": {"dtype": "float32", "shape": (2,), "names": ["a", "b"]}})
        robot, arrivals = drive_client(port, ckpt, tmp_path, actions=EXECUTED, seconds=SECONDS,
                                       actions_per_chunk=ACTIONS_PER_CHUNK)
        assert server.poll() is None, "the server died while serving"
    assert server.returncode == 0, f"serve exited with {server.returncode} after SIGTERM"
    received = [incoming for _, _, incoming in arrivals]
    records = [json.loads(line) for line in log.read_text().splitlines()]
    print(f"{name}: {len(records)} chunks served, {len(robot.executed)} actions executed; compute ms",
          [r["compute_ms"] for r in records])

    assert len(robot.executed) >= EXECUTED, f"the robot executed {len(robot.executed)} actions in {SECONDS} s"
    assert all(set(a) == {"a0", "a1", "a2"} and all(math.isfinite(v) for v in a.values()) for a in robot.executed)
    assert len(received) >= 3 and len(records) >= len(received)
    for chunk in received:                # actions_per_chunk rows on consecutive timesteps, tensors [3]
        steps = [a.get_timestep() for a in chunk]
        assert len(chunk) == ACTIONS_PER_CHUNK and steps == list(range(steps[0], steps[0] + ACTIONS_PER_CHUNK))
        assert all(a.get_action().shape == (3,) for a in chunk)
        assert all(b.get_timestamp() > a.get_timestamp() for a, b in zip(chunk, chunk[1:]))
    # the first chunk starts at the first observation; every later one after the action observed
    assert records[0]["start"] == records[0]["obs_timestep"] == 0 and records[0]["rtc_mode"] is None
    assert all(r["start"] == r["obs_timestep"] + 1 for r in records[1:])
    assert all(r["client_hz"] > 0 for r in records[1:] if r["client_hz"] is not None)
    assert [c[0].get_timestep() for c in received] == [r["start"] for r in records[: len(received)]]
    # real-time chunking: the committed rows are the previous chunk's actions at those timesteps, exactly
    conditioned = [(i, r) for i, r in enumerate(records[: len(received)]) if r["committed"] > 0]
    assert conditioned, f"no chunk continued a committed prefix: {records}"
    for i, r in conditioned:
        assert r["rtc_mode"] == rtc_mode and r["committed"] <= r["delay"]
        before = {a.get_timestep(): a.get_action() for a in received[i - 1]}
        for a in received[i][: r["committed"]]:
            assert torch.allclose(a.get_action(), before[a.get_timestep()], atol=1e-6), (i, a.get_timestep())


def test_compiled_server_chunks_are_the_eager_ones(checkpoints):
    """`serve --compile` samples the chunk the eager server would, from the same generator's noise, with and
    without a committed prefix; what it cannot compile is refused in one line."""
    from action_decoder.serving import ServeConfig
    from lerobot_policy_action_decoder.serve import PolicyServer, load_checkpoint

    served = load_checkpoint(str(checkpoints["MF-1"]))
    server = PolicyServer(ServeConfig(checkpoint=str(checkpoints["MF-1"]), compile=True), served)
    batch = {"state": torch.randn(1, 6), "context": torch.tensor([[[0.0, 1.0]]])}     # the fixture's second task
    prev = served.core.predict_action_chunk(batch)[0, 4:][None]                       # [1, 12, 3]
    for rtc in ({}, {"prev_chunk": prev, "delay": 3, "rtc_mode": "trained"}):
        kwargs = {"steps": None, "generator": torch.Generator().manual_seed(5), "return_logprob": False, **rtc}
        want = served.core.predict_action_chunk(batch, **kwargs)[0]
        got = server._compiled_chunk(batch, {**kwargs, "generator": torch.Generator().manual_seed(5)})
        assert (got - want).abs().max() <= 1e-5
    server.stop()
    fm = load_checkpoint(str(checkpoints["FM-10"]))
    with pytest.raises(ValueError, match="--compile: the compiled sampler runs trained real-time chunking only") as err:
        PolicyServer(ServeConfig(checkpoint=str(checkpoints["FM-10"]), compile=True), fm)
    assert "\n" not in str(err.value)
    PolicyServer(ServeConfig(checkpoint=str(checkpoints["FM-10"]), compile=True, rtc=False), fm).stop()


def test_camera_frames_and_task_reach_a_multi_task_camera_policy(tmp_path):
    """A robot's raw frames [H, W, 3] uint8 and its task string, through the server's observation
    layout and the checkpoint's own preparation, condition a camera policy (no server needed)."""
    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from lerobot_policy_action_decoder.serve import check_features, lerobot_observation, load_checkpoint

    cfg = DecoderConfig(decoder_type="mean_flow", state_dim=6, action_dim=3, action_chunk_size=8, n_action_steps=4,
                        hidden_size=32, num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1,
                        normalization_mode="identity", cameras=("observation.images.front",), image_size=32,
                        context_dim=2, extra={"tasks": ["push the block", "lift the cube"]})
    ActionDecoderPolicy(cfg).save_pretrained(tmp_path / "cam")
    served = load_checkpoint(str(tmp_path / "cam"))
    features = {"observation.state": {"dtype": "float32", "shape": (6,), "names": [f"s{i}" for i in range(6)]},
                "observation.images.wrist": {"dtype": "image", "shape": (48, 64, 3),
                                             "names": ["height", "width", "channels"]}}
    rename = {"observation.images.wrist": "observation.images.front"}
    check_features(served, features, rename)
    with pytest.raises(ValueError, match=r"needs camera\(s\) \['observation.images.front'\]"):
        check_features(served, features, {})
    frame = torch.randint(0, 256, (48, 64, 3), dtype=torch.uint8).numpy()
    raw = {**{f"s{i}": 0.1 * i for i in range(6)}, "wrist": frame, "task": "lift the cube"}
    batch = served.prepare(lerobot_observation(raw, features, rename))
    assert batch["images"].shape == (1, 1, 3, 32, 32) and batch["context"].tolist() == [[[0.0, 1.0]]]
    assert torch.equal(batch["state"], torch.tensor([[0.1 * i for i in range(6)]]))
    chunk = served.core.predict_action_chunk(batch)
    assert chunk.shape == (1, 8, 3) and torch.isfinite(chunk).all()
    with pytest.raises(ValueError, match=r"missing camera 'wrist'"):
        lerobot_observation({f"s{i}": 0.0 for i in range(6)}, features, rename)


def test_checkpoints_of_other_policies_are_refused_in_one_line(tmp_path):
    from lerobot_policy_action_decoder.serve import load_checkpoint

    (tmp_path / "act").mkdir()
    (tmp_path / "act" / "config.json").write_text(json.dumps({"type": "act"}))
    with pytest.raises(ValueError, match="policy type 'act'; this server serves 'action_decoder'"):
        load_checkpoint(str(tmp_path / "act"))
    with pytest.raises(ValueError, match="has no config.json"):
        load_checkpoint(str(tmp_path))


def test_checkpoints_with_observation_history_are_refused_in_one_line(tmp_path):
    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from lerobot_policy_action_decoder.serve import load_checkpoint

    ActionDecoderPolicy(DecoderConfig(state_dim=6, action_dim=2, hidden_size=32, num_hidden_layers=1,
                                      n_obs_steps=2)).save_pretrained(tmp_path / "hist")
    with pytest.raises(ValueError, match="conditions on n_obs_steps=2 consecutive observations"):
        load_checkpoint(str(tmp_path / "hist"))
