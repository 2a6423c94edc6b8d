"""Closed-loop evaluation of a saved policy: batching independence, output naming, unwritable checkpoints."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.envs import evaluate
from action_decoder.evaluate import EvalConfig, make_policy_fn, run_eval


def tiny_policy(decoder_type="flow_matching", **kw) -> ActionDecoderPolicy:
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type=decoder_type, state_dim=39, action_dim=4, action_chunk_size=8, hidden_size=32,
                        num_hidden_layers=1, n_action_steps=8, num_inference_timesteps=2,
                        extra={"tasks": ["reach-v3"]}, **kw)
    return ActionDecoderPolicy(cfg).eval()


def test_policy_fn_learns_each_rows_episode_and_plan():
    calls = []

    def fn(states, task_index, **keys):         # **kwargs: given both keys
        calls.append({k: v.tolist() for k, v in keys.items()})
        return np.zeros((len(states), 4, 4))

    res = evaluate(fn, "metaworld/reach", episodes=3, seed=2, n_action_steps=4, max_steps=8, num_envs=2)
    assert calls == [{"episode_seeds": res["seeds"][:2], "plan_indices": [0, 0]},
                     {"episode_seeds": res["seeds"][:2], "plan_indices": [1, 1]},
                     {"episode_seeds": res["seeds"][2:], "plan_indices": [0]},
                     {"episode_seeds": res["seeds"][2:], "plan_indices": [1]}]


@pytest.mark.parametrize("sampler", ["ode", "sde"])
def test_episodes_do_not_depend_on_num_envs(sampler):
    """Each episode's noise comes from its own seed: 1, 3 or 10 envs in lockstep run the same episodes."""
    policy = tiny_policy()
    runs = {n: evaluate(make_policy_fn(policy, 1, sampler, 2, torch.Generator().manual_seed(7)), "metaworld/reach",
                        episodes=5, seed=3, n_action_steps=4, max_steps=12, num_envs=n, record=True)
            for n in (1, 3, 10)}
    base = runs[1]
    hands = [np.asarray(t["hand"]) for t in base["trajectories"]]     # [13, 3] per episode
    assert all(np.abs(np.diff(h, axis=0)).max() > 1e-3 for h in hands), "the hand should move"
    assert not np.allclose(hands[0][1:] - hands[0][0], hands[1][1:] - hands[1][0]), "episodes draw different noise"
    for n in (3, 10):
        assert runs[n]["successes"] == base["successes"] and runs[n]["lengths"] == base["lengths"]
        for a, b in zip(runs[n]["trajectories"], base["trajectories"]):
            # Batched matmuls round differently (~1e-7): the same path, not bit for bit.
            np.testing.assert_allclose(a["hand"], b["hand"], atol=1e-5, err_msg=f"num_envs={n}")
        np.testing.assert_allclose(runs[n]["returns"], base["returns"], rtol=1e-4)


def fake_evaluate(policy_fn, task, episodes, seed, n_action_steps, num_envs, task_index, progress, record, **kw):
    """Episodes 0, 2 succeed; they finish in reverse order, as lockstep envs can finish them."""
    successes = [i % 2 == 0 for i in range(episodes)]
    for done, ep in enumerate(reversed(range(episodes)), 1):
        progress(done, episodes, ep, successes[ep])
    extra = {"trajectories": [{"hand": [[0, 0, 0], [0.1, 0, 0]], "goal": [0.1, 0, 0]}] * episodes} if record else {}
    return {**extra, "task": "reach-v3", "success_rate": float(np.mean(successes)), "successes": successes,
            "lengths": [1] * episodes, "returns": [0.0] * episodes, "seeds": list(range(episodes)),
            "env_steps": episodes, "wall_time_s": 0.0}


@pytest.fixture
def checkpoint(tmp_path, monkeypatch):
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate)
    tiny_policy().save_pretrained(tmp_path / "final")
    monkeypatch.chdir(tmp_path)
    return tmp_path / "final"


def test_eval_keeps_one_summary_per_setting_and_numbers_lines_by_episode(checkpoint, capsys):
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=3, plot=True))          # as training's own evaluation
    lines = [ln for ln in capsys.readouterr().out.splitlines() if " episode " in ln]
    assert [ln.split(": ")[0] for ln in lines] == [f"[reach-v3] episode {i}/3" for i in (3, 2, 1)]
    assert [ln.split(": ")[1].split()[0] for ln in lines] == ["success", "failure", "success"]
    assert "1/3 done" in lines[0] and "3/3 done" in lines[2]
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=3, sampler="sde", steps=5, seed=1, n_action_steps=4))
    first, second = checkpoint / "eval_ode_k2_n8_seed0_e3.json", checkpoint / "eval_sde_k5_n4_seed1_e3.json"
    assert json.loads(first.read_text())["sampler"] == "ode" and first.with_suffix(".png").is_file()
    assert json.loads(second.read_text())["steps"] == 5
    assert sorted(p.name for p in checkpoint.glob("eval*")) == sorted([first.name, first.with_suffix(".png").name,
                                                                        second.name])


def test_eval_in_a_read_only_checkpoint_still_reports(checkpoint, capsys, monkeypatch):
    checkpoint.chmod(0o555)            # root ignores the mode: the write below raises as it would for a user
    real_write = Path.write_text

    def write_text(self, *args, **kw):
        if self.parent == checkpoint:
            raise PermissionError(13, "Permission denied", str(self))
        return real_write(self, *args, **kw)

    monkeypatch.setattr(Path, "write_text", write_text)
    summary = run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=2))
    out, err = capsys.readouterr()
    assert out.strip().splitlines()[-1] == "success_rate=0.5000" and summary["success_rate"] == 0.5
    fallback = Path.cwd() / "eval_ode_k2_n8_seed0_e2.json"
    assert json.loads(fallback.read_text())["checkpoint"] == str(checkpoint)
    assert err.strip().splitlines() == [f"action-decoder: warning: cannot write {checkpoint / fallback.name} "
                                        f"(Permission denied); wrote {fallback} instead"]

    def deny(self, *args, **kw):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "write_text", deny)         # the current directory cannot be written either
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=2))
    out, err = capsys.readouterr()
    assert out.strip().splitlines()[-1] == "success_rate=0.5000"
    assert len(err.strip().splitlines()) == 1 and "was not saved" in err and str(checkpoint) in err
    checkpoint.chmod(0o755)


# ---------------------------------------------------------------------- camera policies
def test_a_camera_rig_needs_a_policy_fn_that_takes_images():
    def fn(states, task_index):
        return np.zeros((len(states), 4, 4))

    with pytest.raises(ValueError, match=r"camera_rig: expected a policy_fn that takes an images keyword"):
        evaluate(fn, "metaworld/reach", episodes=1, camera_rig=lambda env: {})


def test_camera_images_are_channel_first_in_the_rigs_order():
    from action_decoder.envs.evaluate import camera_images

    frames = {"corner2": np.full((8, 8, 3), 1, np.uint8), "topview": np.arange(192, dtype=np.uint8).reshape(8, 8, 3)}
    out = camera_images(frames)
    assert out.shape == (2, 3, 8, 8) and out.dtype == np.uint8
    assert (out[0] == 1).all() and np.array_equal(out[1], frames["topview"].transpose(2, 0, 1))


_CAMERA_EVAL = """
import json, sys
import numpy as np, torch
from action_decoder.envs.render import check_rendering, CameraObservation
check_rendering()                              # picks MUJOCO_GL before mujoco is imported
from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.envs import evaluate
from action_decoder.evaluate import EvalConfig, run_eval

seen = []
def fn(states, task_index, images):
    seen.append(images.copy())
    return np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (len(states), 4, 1))          # the hand moves: frames change
rig = CameraObservation(["corner2", "topview"], 32)
evaluate(fn, "metaworld/reach", episodes=3, n_action_steps=4, max_steps=8, num_envs=2, camera_rig=rig)
rig.close()
assert [s.shape for s in seen] == [(2, 2, 3, 32, 32), (2, 2, 3, 32, 32), (1, 2, 3, 32, 32), (1, 2, 3, 32, 32)], \\
    [s.shape for s in seen]
assert all(s.dtype == np.uint8 for s in seen)
assert np.abs(seen[0].astype(int) - seen[1].astype(int)).sum() > 0                 # a new observation each plan
assert np.abs(seen[0][:, 0].astype(int) - seen[0][:, 1].astype(int)).mean() > 5    # two cameras, two views

torch.manual_seed(0)
cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, action_chunk_size=8, hidden_size=32,
                    num_hidden_layers=1, n_action_steps=4, num_inference_timesteps=2, state_layout="metaworld_proprio",
                    cameras=["observation.images.corner2"], image_size=32, extra={"tasks": ["reach-v3"]})
ActionDecoderPolicy(cfg).save_pretrained(sys.argv[1])
# A camera policy refuses a batch without images: finishing the episodes shows eval rendered and passed them.
summary = run_eval(EvalConfig(checkpoint=sys.argv[1], episodes=2, num_envs=2, max_steps=8))
assert summary["episodes_per_task"] == 2 and 0 <= summary["success_rate"] <= 1
print("ok")
"""


def test_eval_renders_the_cameras_of_a_camera_policy(tmp_path):
    import os
    import subprocess
    import sys

    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {**os.environ, "PYTHONPATH": src, "OMP_NUM_THREADS": "1"}
    probe = subprocess.run([sys.executable, "-c", "from action_decoder.envs.render import check_rendering as c; c()"],
                           env=env, capture_output=True, text=True, timeout=300)
    if probe.returncode != 0:
        pytest.skip(f"no offscreen renderer here: {(probe.stderr.strip().splitlines() or ['?'])[-1]}")
    run = subprocess.run([sys.executable, "-c", _CAMERA_EVAL, str(tmp_path / "ckpt")], env=env, capture_output=True,
                         text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0 and run.stdout.strip().endswith("ok"), run.stdout[-2000:] + run.stderr[-3000:]
    saved = json.loads(next((tmp_path / "ckpt").glob("eval_*.json")).read_text())
    assert saved["per_task"] == {"reach-v3": saved["success_rate"]}


def test_train_and_eval_a_camera_policy_on_metaworld_pixels_end_to_end(tmp_path):
    import os
    import subprocess
    import sys

    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {**os.environ, "PYTHONPATH": src, "OMP_NUM_THREADS": "1", "ACTION_DECODER_CACHE": str(tmp_path / "cache")}
    probe = subprocess.run([sys.executable, "-c", "from action_decoder.envs.render import check_rendering as c; c()"],
                           env=env, capture_output=True, text=True, timeout=300)
    if probe.returncode != 0:
        pytest.skip(f"no offscreen renderer here: {(probe.stderr.strip().splitlines() or ['?'])[-1]}")
    run = subprocess.run([sys.executable, "-m", "action_decoder.cli", "train", "--task", "metaworld/reach", "--demos", "2",
                          "--steps", "4", "--batch-size", "8", "--hidden-size", "32", "--num-layers", "1",
                          "--cameras", "corner2", "--image-size", "32", "--eval-episodes", "1",
                          "--output-dir", str(tmp_path / "run"), "--no-progress"],
                         env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    assert "success_rate=" in run.stdout
    saved = json.loads((tmp_path / "run" / "final" / "config.json").read_text())
    assert saved["cameras"] == ["observation.images.corner2"] and saved["image_size"] == 32
    assert saved["state_layout"] == "metaworld_proprio"


def test_summaries_of_other_episode_counts_or_tasks_do_not_replace_each_other(checkpoint):
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=2))
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=4))
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=2, task="metaworld/push"))   # a task it did not train on
    names = sorted(p.name for p in checkpoint.glob("eval_*.json"))
    assert names == ["eval_ode_k2_n8_seed0_e2.json", "eval_ode_k2_n8_seed0_e2_on-push-v3.json",
                     "eval_ode_k2_n8_seed0_e4.json"]
    assert json.loads((checkpoint / names[2]).read_text())["episodes_per_task"] == 4


def test_output_naming_a_directory_puts_the_summary_inside_it(checkpoint, tmp_path):
    (tmp_path / "evals").mkdir()
    run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=2, output=str(tmp_path / "evals")))
    assert json.loads((tmp_path / "evals" / "eval_ode_k2_n8_seed0_e2.json").read_text())["success_rate"] == 0.5


@pytest.mark.parametrize("fps", [float("inf"), 1e300, -1.0])
def test_video_fps_out_of_range_is_refused_before_any_episode(checkpoint, fps, monkeypatch):
    monkeypatch.setattr("action_decoder.envs.evaluate", lambda *a, **k: pytest.fail("ran an episode"))
    with pytest.raises(ValueError, match=r"^--video-fps: expected a number in \[0, 1000\]"):
        run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=1, video=True, video_fps=fps))


def test_device_auto_evaluates_on_what_the_machine_has(checkpoint):
    assert run_eval(EvalConfig(checkpoint=str(checkpoint), episodes=2, device="auto"))["success_rate"] == 0.5


def test_the_episode_cap_eval_checks_before_importing_the_simulator_is_meta_worlds():
    from action_decoder.envs import MAX_EPISODE_STEPS
    from action_decoder.evaluate import EPISODE_CAP

    assert EPISODE_CAP == MAX_EPISODE_STEPS


def test_a_policy_of_lerobot_layout_data_is_a_simulator_policy():
    """`record --layout lerobot` policies observe LeRobot's 4-d agent position; eval gives it to them."""
    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from action_decoder.envs.lerobot_view import AGENT_POS_DIM
    from action_decoder.evaluate import check_simulator_policy
    from action_decoder.model_card import LEROBOT_AGENT_POS_DIM

    assert LEROBOT_AGENT_POS_DIM == AGENT_POS_DIM
    extra = {"tasks": ["door-close-v3"], "observation_layout": "lerobot"}
    policy = ActionDecoderPolicy(DecoderConfig(state_dim=4, action_dim=4, hidden_size=16, num_hidden_layers=1,
                                               num_attention_heads=2, num_key_value_heads=1, extra=extra))
    check_simulator_policy(policy, "ckpt", None, "eval")                   # no refusal
    other = ActionDecoderPolicy(DecoderConfig(state_dim=4, action_dim=4, hidden_size=16, num_hidden_layers=1,
                                              num_attention_heads=2, num_key_value_heads=1,
                                              extra={"tasks": ["door-close-v3"]}))
    with pytest.raises(ValueError, match="closed-loop evaluation runs Meta-World tasks"):
        check_simulator_policy(other, "ckpt", None, "eval")
