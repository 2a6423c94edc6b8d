"""ONNX export: the exported graph reproduces `predict_action_chunk` for the same noise (every decoder,
with and without context tokens, with cameras), refusals are one line, the runtime runs without
torch, and `action-decoder export` / `eval --onnx` work end to end."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.export import ChunkSampler, check_export, dpm_solver_coefficients, export_refusal
from action_decoder.runtime import OnnxPolicy, read_metadata

pytest.importorskip("onnxruntime")

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "data" / "lerobot" / "v30_toy"
DECODERS = ("flow_matching", "mean_flow", "DDPM")
TINY = {"hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2, "num_key_value_heads": 1}
TOL = 1e-4


@pytest.fixture(autouse=True)
def _seeded():
    """The same states and noise on every run: DPM-Solver's clip can turn a float-rounding difference near its
    bound into a few 1e-4, so an unseeded draw would make the tolerance a coin toss."""
    torch.manual_seed(0)


def _spread(policy, seed=0):
    """Weights of a trained network's scale, so the chunk depends on every input."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in policy.parameters():
            if p.dim() >= 2:                                  # weights; biases and norm gains keep their init
                p.copy_(torch.randn(p.shape, generator=gen) * 0.2)
    return policy.eval()


def lerobot_policy(decoder, **kw):
    """A policy over the LeRobot fixture's features (state 6, action 3) with its stats.json statistics."""
    stats = json.loads((FIXTURE / "meta" / "stats.json").read_text())
    info = json.loads((FIXTURE / "meta" / "info.json").read_text())
    cfg = DecoderConfig(decoder_type=decoder, state_dim=info["features"]["observation.state"]["shape"][0],
                        action_dim=info["features"]["action"]["shape"][0], action_chunk_size=8, **TINY, **kw)
    return _spread(ActionDecoderPolicy(cfg, {k: stats[k] for k in ("observation.state", "action")}))


def metaworld_policy(decoder, tasks=("reach-v3", "push-v3", "pick-place-v3"), **kw):
    """A Meta-World-shaped multi-task policy: 39-d state with its layout features, one-hot task tokens."""
    stats = {"state": {"mean": torch.rand(39), "std": torch.rand(39) + 0.1, "min": -torch.ones(39), "max": torch.ones(39)},
             "actions": {"mean": torch.zeros(4), "std": torch.full((4,), 0.5), "min": -torch.ones(4), "max": torch.ones(4)}}
    cfg = DecoderConfig(decoder_type=decoder, state_layout="metaworld", context_dim=3,
                        extra={"tasks": list(tasks)}, **TINY, **kw)
    return _spread(ActionDecoderPolicy(cfg, stats))


def _compare(policy, path, batch, **inputs):
    runner = OnnxPolicy(path)
    noise = torch.randn(batch["state"].shape[0], policy.config.action_chunk_size, policy.config.action_dim)
    want = policy.predict_action_chunk(batch, noise=noise)
    got = runner.predict_action_chunk(batch["state"].numpy(), noise.numpy(), **inputs)
    return float(np.abs(got - want.numpy()).max()), want


@pytest.mark.parametrize("decoder", DECODERS)
def test_lerobot_policy_export_matches_predict_action_chunk(decoder, tmp_path):
    policy = lerobot_policy(decoder)
    path = policy.export_onnx(tmp_path / "p.onnx", batch_size=0)                  # default K, any batch size
    state = policy.normalizers["state"].unnormalize(torch.randn(3, 6))
    err, want = _compare(policy, path, {"state": state})
    assert err <= TOL and want.abs().max() > 0.1
    meta = read_metadata(path)
    assert meta["steps"] == policy.config.num_inference_timesteps and meta["inputs"]["noise"] == [None, 8, 3]


@pytest.mark.parametrize("decoder", DECODERS)
def test_metaworld_policy_export_with_context_tokens(decoder, tmp_path):
    policy = metaworld_policy(decoder, action_squash=decoder == "mean_flow", num_inference_timesteps=3)
    path = policy.export_onnx(tmp_path / "p.onnx")                                # B = 1, the task token
    assert OnnxPolicy(path).input_names == ["observation.state", "noise", "context", "context_mask"]
    state = torch.rand(1, 39) * 0.4
    ctx = torch.nn.functional.one_hot(torch.tensor([2]), 3).float()[:, None]       # [1, 1, 3]
    err, _ = _compare(policy, path, {"state": state, "context": ctx}, context=ctx.numpy())
    assert err <= TOL
    # The context reaches the graph: another task token gives another chunk.
    runner, noise = OnnxPolicy(path), np.zeros((1, 16, 4), np.float32)
    other = runner.predict_action_chunk(state.numpy(), noise, context=np.roll(ctx.numpy(), 1, -1))
    assert np.abs(other - runner.predict_action_chunk(state.numpy(), noise, context=ctx.numpy())).max() > 1e-3


def test_masked_context_tokens_and_no_context(tmp_path):
    policy = metaworld_policy("flow_matching", num_inference_timesteps=2)
    path = policy.export_onnx(tmp_path / "p.onnx", batch_size=0, context_length=3)
    state, ctx = torch.rand(2, 39), torch.randn(2, 3, 3)
    mask = torch.tensor([[True, False, True], [True, True, False]])
    ctx[~mask] = 1e3                                                               # masked rows never leak
    err, _ = _compare(policy, path, {"state": state, "context": ctx, "context_mask": mask},
                      context=ctx.numpy(), context_mask=mask.numpy())
    assert err <= TOL
    single = metaworld_policy("flow_matching", tasks=("push-v3",), num_inference_timesteps=2)
    bare = single.export_onnx(tmp_path / "bare.onnx")               # context tokens are optional: no input
    assert "context" not in OnnxPolicy(bare).input_names
    assert _compare(single, bare, {"state": state[:1]})[0] <= TOL


def test_camera_policy_export(tmp_path):
    cfg = DecoderConfig(decoder_type="mean_flow", state_dim=4, action_dim=2, action_chunk_size=4, image_size=16,
                        cameras=("observation.images.top",), image_tokens_per_camera=1, num_inference_timesteps=2, **TINY)
    policy = _spread(ActionDecoderPolicy(cfg))
    path = policy.export_onnx(tmp_path / "cam.onnx", batch_size=2)
    images = torch.randint(0, 256, (2, 1, 3, 16, 16), dtype=torch.uint8)
    err, _ = _compare(policy, path, {"state": torch.randn(2, 4), "images": images}, images=images.numpy())
    assert err <= TOL


@pytest.mark.parametrize("kw", [{"prediction_type": "epsilon", "clip_sample": True, "normalization_mode": "min_max"},
                                {"prediction_type": "epsilon", "beta_schedule": "linear", "num_inference_timesteps": 3},
                                {"prediction_type": "sample", "clip_sample": True, "normalization_mode": "min_max",
                                 "num_inference_timesteps": 1}])
def test_ddpm_solver_coefficients_reproduce_diffusers(kw):
    """The constants read off diffusers' DPMSolverMultistepScheduler give `sample_ddpm`'s chunk."""
    policy = lerobot_policy("DDPM", **kw)
    state, noise = torch.randn(2, 6), torch.randn(2, 8, 3)
    with torch.no_grad():
        got = ChunkSampler(policy)(state, noise)
    assert (got - policy.predict_action_chunk({"state": state}, noise=noise)).abs().max() <= TOL
    steps = dpm_solver_coefficients(policy.config, 4)
    # 1st order, 2nd order, and 1st order again into σ = 0 (final_sigmas_type="zero"): diffusers' own choice
    assert [s.c == 0 for s in steps] == [True, False, False, True]
    assert steps[-1].t > steps[0].t                                                # noise → data


def test_euler_sampler_on_mean_flow_and_flow_prediction_sample(tmp_path):
    policy = lerobot_policy("mean_flow")
    with pytest.warns(UserWarning):
        path = policy.export_onnx(tmp_path / "e.onnx", sampler="euler", steps=3)
    assert read_metadata(path)["sampler"] == "euler" and check_export(policy, path) <= TOL
    fm = lerobot_policy("flow_matching", flow_prediction="sample")
    with torch.no_grad():
        state, noise = torch.randn(2, 6), torch.randn(2, 8, 3)
        # A clean-chunk head's velocity divides by 1 − t, floored at 0.05: rounding of the head grows up to 20×.
        assert (ChunkSampler(fm)(state, noise) - fm.predict_action_chunk({"state": state}, noise=noise)).abs().max() <= 20 * TOL


def test_refusals_are_one_line(tmp_path):
    policy = lerobot_policy("flow_matching")
    for kw, field in (({"sampler": "sde"}, "sampler: the SDE"), ({"batch_size": -1}, "batch_size:"),
                      ({"exporter": "tf"}, "exporter:"), ({"path": tmp_path / "x.pt"}, "path:")):
        kw = {"path": tmp_path / "p.onnx", **kw}
        with pytest.raises(ValueError, match=field) as err:
            policy.export_onnx(**kw)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="context_length: this policy has context_dim=None"):
        policy.export_onnx(tmp_path / "p.onnx", context_length=2)
    vlm = ActionDecoderPolicy(DecoderConfig(decoder_type="flow_matching", vlm_num_layers=2, vlm_head_dim=8,
                                            vlm_num_key_value_heads=1, **TINY))
    assert export_refusal(vlm, None).startswith("vlm_key_values:")
    mf = ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", meanflow_sde_velocity="identity", **TINY))
    assert export_refusal(mf, "euler").startswith("meanflow_sde_velocity: 'identity'")
    path = policy.export_onnx(tmp_path / "p.onnx", steps=1)
    runner = OnnxPolicy(path)
    for kw, field in (({"state": np.zeros((2, 6))}, "batch size 1"), ({"state": np.zeros((1, 5))}, r"shape \[1, 6\]"),
                      ({"state": np.full((1, 6), np.nan)}, "NaN"), ({"state": np.zeros((1, 6)), "context": np.zeros((1, 1, 3))},
                                                                    "takes no context")):
        with pytest.raises(ValueError, match=field):
            runner.predict_action_chunk(**kw)


RTC_CASES = (("flow_matching", {"num_inference_timesteps": 3}),
             ("mean_flow", {"num_inference_timesteps": 1, "action_squash": True}),
             ("mean_flow", {"num_inference_timesteps": 2, "flow_prediction": "sample"}))


@pytest.mark.parametrize("decoder,kw", RTC_CASES)
def test_trained_rtc_graph_is_sample_with_the_committed_prefix(decoder, kw, tmp_path):
    """The `rtc=True` graph with row b committing delay[b] actions is `sample(prev_chunk, delay, "trained")`
    row by row (delay 0: the plain chunk), in PyTorch and in onnxruntime; the committed rows come back exactly."""
    policy = lerobot_policy(decoder, rtc_max_delay=3, **kw)
    state = policy.normalizers["state"].unnormalize(torch.randn(4, 6))
    noise = torch.randn(4, 8, 3)
    prev = policy._env_actions(torch.randn(4, 5, 3))                  # a previous chunk's remaining actions
    delays = torch.tensor([0, 1, 3, 2])
    with torch.no_grad():
        want = torch.cat([policy.sample({"state": state[i:i + 1]}, noise=noise[i:i + 1], prev_chunk=prev[i:i + 1],
                                        delay=int(delays[i]), rtc_mode="trained").actions for i in range(4)])
        got = ChunkSampler(policy, rtc=True)(state, noise, committed=prev[:, :3], delay=delays)
    assert (got - want).abs().max() <= TOL
    free = policy.predict_action_chunk({"state": state}, noise=noise)
    assert (want[0] - free[0]).abs().max() <= TOL
    assert (want[2, 3:] - free[2, 3:]).abs().max() > 1e-3          # the prefix conditions the rows after it
    path = policy.export_onnx(tmp_path / "r.onnx", batch_size=0, rtc=True)
    assert check_export(policy, path) <= TOL
    runner = OnnxPolicy(path)
    assert runner.rtc_max_delay == 3 and runner.input_names[-2:] == ["committed_actions", "delay"]
    out = runner.predict_action_chunk(state.numpy(), noise.numpy(), committed=prev.numpy(), delay=delays.numpy())
    assert np.abs(out - want.numpy()).max() <= TOL
    for i, d in enumerate(delays.tolist()):
        assert (out[i, :d] == prev[i, :d].numpy()).all()                      # committed actions, bit for bit
    plain = runner.predict_action_chunk(state.numpy(), noise.numpy())        # no committed actions: a plain chunk
    assert np.abs(plain - policy.predict_action_chunk({"state": state}, noise=noise).numpy()).max() <= TOL
    same = runner.predict_action_chunk(state.numpy(), noise.numpy(), committed=prev[:, :2].numpy(), delay=2)
    assert np.abs(same[3] - out[3]).max() <= TOL                              # one delay for all rows; L < M is padded
    one = runner.predict_action_chunk(state[:1].numpy(), noise[:1].numpy(), committed=prev[:1, :2].numpy(),
                                      delay=np.int64(2))                 # another batch size, a numpy integer
    assert one.shape == (1, 8, 3) and np.abs(one[0] - same[0]).max() <= TOL
    with torch.no_grad():
        eager = policy.sample({"state": state[:1]}, noise=noise[:1], prev_chunk=prev[:1, :2], delay=2,
                              rtc_mode="trained").actions
    assert np.abs(one - eager.numpy()).max() <= TOL                       # against eager PyTorch


@pytest.mark.filterwarnings("ignore:sampler='euler' on a mean_flow decoder")
def test_trained_rtc_refusals_are_one_line(tmp_path):
    plain = lerobot_policy("flow_matching")
    with pytest.raises(ValueError, match="rtc: the graph feeds committed actions .* rtc_max_delay=0"):
        plain.export_onnx(tmp_path / "p.onnx", rtc=True)
    mf = lerobot_policy("mean_flow", rtc_max_delay=2)
    with pytest.raises(ValueError, match="rtc: the committed prefix is fed to the ODE sampler .* got sampler='euler'"):
        ChunkSampler(mf, sampler="euler", rtc=True)
    with pytest.raises(ValueError, match=r"committed, delay: this sampler \(rtc=True\) takes .* got no committed"):
        ChunkSampler(mf, rtc=True)(torch.zeros(1, 6), torch.zeros(1, 8, 3))
    runner = OnnxPolicy(mf.export_onnx(tmp_path / "r.onnx", rtc=True))
    state, prev = np.zeros((1, 6), np.float32), np.zeros((1, 4, 3), np.float32)
    for kw, field in (({"committed": prev, "delay": 3}, r"delay: expected values in 0..2"),
                      ({"committed": prev[:, :1], "delay": 2}, r"delay: expected values in 0..1"),
                      ({"delay": 1}, "delay: a delay of 1 commits actions, and committed is missing"),
                      ({"committed": prev, "delay": 1.5}, "delay: expected an integer"),
                      ({"committed": prev, "delay": True}, "delay: expected an integer"),
                      ({"committed": prev[0], "delay": 1}, r"committed: expected float32 values of shape \[1, L <= 8, 3\]"),
                      ({"committed": np.full((1, 4, 3), np.nan, np.float32), "delay": 1}, "committed: contains NaN")):
        with pytest.raises(ValueError, match=field) as err:
            runner.predict_action_chunk(state, **kw)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="committed: this file has no real-time chunking inputs"):
        OnnxPolicy(plain.export_onnx(tmp_path / "p.onnx")).predict_action_chunk(state, committed=prev, delay=1)


def test_runtime_runs_where_torch_cannot_be_imported(tmp_path):
    policy = lerobot_policy("mean_flow", num_inference_timesteps=1)
    path = policy.export_onnx(tmp_path / "p.onnx", batch_size=0)
    state = np.random.default_rng(0).normal(size=(2, 6)).astype(np.float32)
    noise = np.random.default_rng(1).standard_normal((2, 8, 3), dtype=np.float32)
    want = policy.predict_action_chunk({"state": torch.from_numpy(state)}, noise=torch.from_numpy(noise)).numpy()
    np.save(tmp_path / "want.npy", want)
    script = textwrap.dedent(f"""
        import sys
        class NoTorch:
            def find_spec(self, name, path=None, target=None):
                if name == "torch" or name.startswith("torch."):
                    raise ImportError("torch is blocked in this process")
        sys.meta_path.insert(0, NoTorch())
        import numpy as np
        from action_decoder.runtime import OnnxPolicy
        runner = OnnxPolicy({str(path)!r})
        state = np.random.default_rng(0).normal(size=(2, 6)).astype(np.float32)
        noise = np.random.default_rng(1).standard_normal((2, 8, 3), dtype=np.float32)
        got = runner.predict_action_chunk(state, noise)
        assert np.abs(got - np.load({str(tmp_path / 'want.npy')!r})).max() <= {TOL}
        a, b = runner.predict_action_chunk(state, seed=3), runner.predict_action_chunk(state, seed=3)
        assert (a == b).all() and a.shape == (2, 8, 3)
        assert not any(m == "torch" or m.startswith("torch.") for m in sys.modules)
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "action_decoder.cli", *args], capture_output=True, text=True,
                          timeout=300)


def test_export_cli_end_to_end(tmp_path, capsys):
    policy = metaworld_policy("DDPM", num_inference_timesteps=2)
    policy.save_pretrained(tmp_path / "ckpt")
    out = _cli("export", "--checkpoint", str(tmp_path / "ckpt"), "--output", str(tmp_path / "p.onnx"),
               "--steps", "3", "--batch-size", "0")
    assert out.returncode == 0, out.stderr
    assert "DDPM sampler=ode K=3" in out.stdout
    meta = read_metadata(tmp_path / "p.onnx")
    assert meta["steps"] == 3 and meta["batch_size"] == 0 and meta["config"]["extra"]["tasks"][0] == "reach-v3"
    assert check_export(policy, tmp_path / "p.onnx") <= TOL
    from action_decoder import cli

    assert cli.main(["export", "--checkpoint", str(tmp_path / "ckpt"), "--output", str(tmp_path / "q.onnx"),
                     "--sampler", "sde"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "sampler: the SDE" in err and not (tmp_path / "q.onnx").exists()
    assert cli.main(["export", "--checkpoint", str(tmp_path / "ckpt"), "--output", str(tmp_path / "q.onnx"), "--rtc"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "rtc: the graph feeds committed actions" in err
    metaworld_policy("flow_matching", num_inference_timesteps=2, rtc_max_delay=3).save_pretrained(tmp_path / "rtc")
    assert cli.main(["export", "--checkpoint", str(tmp_path / "rtc"), "--output", str(tmp_path / "r.onnx"), "--rtc"]) == 0
    assert "flow_matching sampler=ode K=2" in capsys.readouterr().out
    assert OnnxPolicy(tmp_path / "r.onnx").rtc_max_delay == 3


def test_eval_onnx_closed_loop_matches_checkpoint(tmp_path):
    pytest.importorskip("metaworld")
    from action_decoder.evaluate import EvalConfig, run_eval

    policy = metaworld_policy("mean_flow", num_inference_timesteps=2, rtc_max_delay=2)
    policy.save_pretrained(tmp_path / "ckpt")
    policy.export_onnx(tmp_path / "p.onnx")                                         # B = 1: eval calls it per row
    common = {"episodes": 3, "max_steps": 25, "num_envs": 2, "task": "push", "seed": 1}
    ref = run_eval(EvalConfig(checkpoint=str(tmp_path / "ckpt"), output=str(tmp_path / "ck.json"), **common))
    got = run_eval(EvalConfig(onnx=str(tmp_path / "p.onnx"), output=str(tmp_path / "ox.json"), **common))
    a, b = ref["results"][0], got["results"][0]
    assert a["seeds"] == b["seeds"] and a["successes"] == b["successes"] and a["lengths"] == b["lengths"]
    assert np.allclose(a["returns"], b["returns"], rtol=1e-4)
    assert got["success_rate"] == ref["success_rate"]
    with pytest.raises(ValueError, match="--rtc: .*p.onnx has no real-time chunking inputs"):
        run_eval(EvalConfig(onnx=str(tmp_path / "p.onnx"), rtc=True, **common))
    # Trained RTC: the graph fed the committed actions plays the checkpoint's `eval --rtc` episodes.
    policy.export_onnx(tmp_path / "r.onnx", batch_size=0, rtc=True)
    rtc = {**common, "rtc": True, "delay": 2, "n_action_steps": 4}
    ref = run_eval(EvalConfig(checkpoint=str(tmp_path / "ckpt"), output=str(tmp_path / "ckr.json"), **rtc))
    got = run_eval(EvalConfig(onnx=str(tmp_path / "r.onnx"), output=str(tmp_path / "oxr.json"), **rtc))
    a, b = ref["results"][0], got["results"][0]
    assert ref["rtc_mode"] == "trained" and a["lengths"] == b["lengths"] and a["successes"] == b["successes"]
    assert np.allclose(a["returns"], b["returns"], rtol=1e-4) and a["rtc"] and b["rtc"]
    with pytest.raises(ValueError, match="--rtc: .*delays up to 2; got --delay 3"):
        run_eval(EvalConfig(onnx=str(tmp_path / "r.onnx"), **{**rtc, "delay": 3}))
    with pytest.raises(ValueError, match="--steps: .* exported with steps=2"):
        run_eval(EvalConfig(onnx=str(tmp_path / "p.onnx"), steps=5, **common))
    with pytest.raises(ValueError, match="--checkpoint, --onnx: expected exactly one"):
        run_eval(EvalConfig(**common))


def test_dynamo_exporter_writes_the_same_graph(tmp_path):
    pytest.importorskip("onnxscript")
    policy = lerobot_policy("mean_flow", num_inference_timesteps=1)
    path = policy.export_onnx(tmp_path / "d.onnx", batch_size=0, exporter="dynamo")
    assert read_metadata(path)["exporter"] == "dynamo"
    err, _ = _compare(policy, path, {"state": torch.randn(3, 6)})                 # a batch size of its own
    assert err <= TOL
