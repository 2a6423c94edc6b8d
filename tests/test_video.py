"""`eval --video`: offscreen rendering set-up, mp4s a player reads back, the outcome border, the plot's legend."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.envs import render
from action_decoder.envs.render import EpisodeCamera, choose_backend, framed, tile
from action_decoder.evaluate import EvalConfig, plot_trajectories, run_eval

SRC = str(Path(render.__file__).parents[2])


def cli(args, env, cwd):
    return subprocess.run([sys.executable, "-m", "action_decoder.cli", *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def rendering():
    """Probe once, in a child process (MUJOCO_GL binds at mujoco's import): the reason it fails, or None."""
    probe = subprocess.run([sys.executable, "-c", "from action_decoder.envs.render import check_rendering as c; c()"],
                           env={**os.environ, "PYTHONPATH": SRC}, capture_output=True, text=True, timeout=300)
    return None if probe.returncode == 0 else (probe.stderr.strip().splitlines() or ["no output"])[-1]


@pytest.fixture
def checkpoint(tmp_path):
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, action_chunk_size=8, hidden_size=32,
                        num_hidden_layers=1, n_action_steps=8, num_inference_timesteps=2, extra={"tasks": ["reach-v3"]})
    ActionDecoderPolicy(cfg).eval().save_pretrained(tmp_path / "final")
    return tmp_path / "final"


def border_color(frames: np.ndarray) -> np.ndarray:
    """Mean RGB of the outer 2 px of frames [T, H, W, 3] (H.264 blurs colours a little)."""
    ring = np.concatenate([frames[:, :2].reshape(-1, 3), frames[:, -2:].reshape(-1, 3),
                           frames[:, :, :2].reshape(-1, 3), frames[:, :, -2:].reshape(-1, 3)])
    return ring.astype(float).mean(0)


def test_eval_video_writes_a_grid_mp4_with_one_frame_per_observation(rendering, checkpoint, tmp_path):
    if rendering is not None:
        pytest.skip(f"offscreen rendering is unavailable here: {rendering}")
    import imageio.v3 as iio

    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": SRC}
    res = cli(["eval", "--checkpoint", str(checkpoint), "--episodes", "3", "--num-envs", "2", "--max-steps", "12",
               "--video", "--video-episodes", "2", "--video-size", "48", "--video-fps", "20", "--plot",
               "--sampler", "sde", "--steps", "3"], env, tmp_path)
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr and "Exception ignored" not in res.stderr, "renderers are closed"
    stem = checkpoint / "eval_sde_k3_n8_seed0_e3_t12"
    video = stem.parent / f"{stem.name}_reach-v3.mp4"
    lines = res.stdout.strip().splitlines()
    assert f"video: {video}" in lines and lines[-1].startswith("success_rate=")
    summary = json.loads(stem.with_suffix(".json").read_text())
    lengths, successes = summary["results"][0]["lengths"], summary["results"][0]["successes"]
    assert summary["max_steps"] == 12 and max(lengths) <= 12
    frames = iio.imread(video, plugin="FFMPEG")                       # [T, H, W, 3]
    meta = iio.immeta(video, plugin="FFMPEG")
    assert meta["codec"] == "h264" and meta["fps"] == 20
    # Episodes 1 and 2 side by side; the grid lasts as long as the longer one, reset frame included.
    assert frames.shape == (max(lengths[:2]) + 1, 48, 96, 3)
    assert frames[0].std() > 10, "a rendered scene, not a blank frame"
    for tile_frames, ok in zip((frames[:, :, :48], frames[:, :, 48:]), successes):
        r, g, _ = border_color(tile_frames)
        assert (g > 150 > r) if ok else (r > 150 > g), (ok, r, g)
    assert stem.with_suffix(".png").is_file()


def test_eval_video_without_a_renderer_is_one_line(checkpoint, tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.update(MUJOCO_GL="glfw", PYTHONPATH=SRC, OMP_NUM_THREADS="1")        # glfw needs a display
    res = cli(["eval", "--checkpoint", str(checkpoint), "--video"], env, tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("action-decoder: error: --video: offscreen rendering is unavailable with MUJOCO_GL=glfw")
    assert "libegl1" in lines[0] and "libosmesa6" in lines[0]
    assert not list(checkpoint.glob("eval*")), "no episode ran"


def test_backend_is_the_users_else_egl_else_osmesa(monkeypatch):
    monkeypatch.delitem(sys.modules, "mujoco", raising=False)

    def only(*names):
        return lambda library: f"lib{library}.so" if library in names else None

    environ = {}
    assert choose_backend(environ, only("EGL", "OSMesa")) == "egl" and environ == {"MUJOCO_GL": "egl"}
    environ = {}
    assert choose_backend(environ, only("OSMesa")) == "osmesa" and environ == {"MUJOCO_GL": "osmesa"}
    environ = {"MUJOCO_GL": "OSMesa"}
    assert choose_backend(environ, only("EGL")) == "osmesa" and environ == {"MUJOCO_GL": "OSMesa"}
    with pytest.raises(ValueError, match=r"^--video: .*neither is installed.*libegl1.*libosmesa6") as err:
        choose_backend({}, only())
    assert "\n" not in str(err.value)
    monkeypatch.setitem(sys.modules, "mujoco", object())             # imported already: MUJOCO_GL is bound
    with pytest.raises(ValueError, match="imported before MUJOCO_GL was set"):
        choose_backend({}, only("EGL"))


def test_frames_are_framed_by_outcome_and_tiled_with_ended_episodes_held():
    size = 32
    episodes = [np.full((n, size, size, 3), 100 + n, dtype=np.uint8) for n in (5, 3, 4)]   # [T_i, S, S, 3]
    marked = [framed(e, ok) for e, ok in zip(episodes, (True, False, True))]
    width = 2                                                          # S/32, at least 2 px
    assert (marked[0][:, 0, 0] == render.GREEN).all() and (marked[1][:, -1, size // 2] == render.RED).all()
    assert (marked[0][:, width:-width, width:-width] == 105).all(), "the picture inside the border is kept"
    assert (marked[0][:, width - 1, size // 2] == render.GREEN).all() and (marked[0][:, width, size // 2] == 105).all()
    grid = tile(marked)                                                # 3 episodes: 2 columns, 2 rows
    assert grid.shape == (5, 2 * size, 2 * size, 3)
    np.testing.assert_array_equal(grid[:, :size, :size], marked[0])
    np.testing.assert_array_equal(grid[:3, :size, size:], marked[1])
    np.testing.assert_array_equal(grid[3:, :size, size:], marked[1][[-1, -1]])   # ended: its last frame, held
    np.testing.assert_array_equal(grid[4, size:, :size], marked[2][-1])
    assert (grid[:, size:, size:] == 0).all(), "the empty cell stays black"


def test_per_episode_videos_play_back_with_their_frame_counts(tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason="writing mp4 needs imageio-ffmpeg")
    import imageio.v3 as iio

    camera = EpisodeCamera(episodes=2, size=32, camera="corner2")
    rng = np.random.default_rng(0)
    camera.frames = {0: list(rng.integers(0, 255, (7, 32, 32, 3), dtype=np.uint8)),
                     1: list(rng.integers(0, 255, (4, 32, 32, 3), dtype=np.uint8))}
    camera.control_dt = 0.0125                                         # Meta-World: 80 steps a second
    paths = camera.write([False, True], "episodes", 0, tmp_path, "eval_x_push-v3")
    assert [p.name for p in paths] == ["eval_x_push-v3_episode1.mp4", "eval_x_push-v3_episode2.mp4"]
    for path, n, ok in zip(paths, (7, 4), (False, True)):
        frames = iio.imread(path, plugin="FFMPEG")
        assert frames.shape == (n, 32, 32, 3) and iio.immeta(path, plugin="FFMPEG")["fps"] == 80
        r, g, _ = border_color(frames)
        assert (g > 150 > r) if ok else (r > 150 > g)


def test_an_unknown_camera_names_the_cameras_there_are():
    from action_decoder.envs import make_env

    env = make_env("metaworld/reach", seed=0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^--video-camera: expected one of topview, corner, corner2, .*got 'front'$"):
        EpisodeCamera(episodes=1, size=32, camera="front")(0, env)
    env.close()


@pytest.mark.parametrize("options, message", [
    ({"video_size": 64}, "--video-size: take effect only with --video"),
    ({"video": True, "video_size": 100}, "--video-size: expected a multiple of 16"),
    ({"video": True, "video_episodes": 0}, "--video-episodes: expected an integer >= 1"),
    ({"video": True, "video_fps": -1.0}, "--video-fps: expected a number in \\[0, 1000\\]"),
    ({"max_steps": 0}, "--max-steps: expected 1..500"),
])
def test_video_options_are_checked_before_any_episode(options, message):
    with pytest.raises(ValueError, match=f"^{message}"):
        run_eval(EvalConfig(checkpoint="/nonexistent", **options))


def test_trajectory_plot_has_a_legend_and_names_sampler_and_k():
    hand = [[0.0, 0.6, 0.2], [0.05, 0.7, 0.2]]
    res = {"task": "reach-v3", "success_rate": 0.5, "successes": [True, False],
           "trajectories": [{"hand": hand, "goal": [0.05, 0.7, 0.2]}, {"hand": hand[::-1], "goal": [0.1, 0.8, 0.2]}]}
    fig = plot_trajectories([res, {**res, "task": "push-v3", "successes": [False, False], "success_rate": 0.0}], None,
                            {"decoder_type": "mean_flow", "sampler": "sde", "steps": 10, "n_action_steps": 4})
    title = fig._suptitle.get_text()
    assert "reach-v3, push-v3" in title and "sampler sde" in title and "K = 10" in title and "mean_flow" in title
    legends = [[t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes]
    assert legends == [["success (1)", "failure (1)", "start", "goal"], ["success (0)", "failure (2)", "start", "goal"]]
    starts = [c for c in fig.axes[0].collections if c.get_offsets().tolist() == [[0.0, 0.6]]]
    assert starts, "each path's start is marked"


_OBSERVE = """
import numpy as np
from action_decoder.envs.render import check_rendering
check_rendering()                              # picks MUJOCO_GL before mujoco is imported
from action_decoder.envs import make_env
from action_decoder.envs.render import CameraObservation
env = make_env("metaworld/push", seed=0)
env.reset(seed=0)
rig = CameraObservation(["corner2", "topview"], 32)
first = rig(env)
for _ in range(15):
    env.step(np.array([1.0, 0.0, 0.0, 0.0]))
moved = rig(env)
rig.close()
for name in ("corner2", "topview"):
    assert first[name].shape == (32, 32, 3) and first[name].dtype == np.uint8, first[name].shape
    assert np.abs(first[name].astype(int) - moved[name].astype(int)).sum() > 0, name   # the arm moved
assert np.abs(first["corner2"].astype(int) - first["topview"].astype(int)).mean() > 5   # two views
print("ok")
"""


def test_camera_observation_renders_each_named_camera_of_the_current_state(rendering):
    if rendering:
        pytest.skip(f"no offscreen renderer here: {rendering}")
    run = subprocess.run([sys.executable, "-c", _OBSERVE], env={**os.environ, "PYTHONPATH": SRC},
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-2000:]


def test_camera_observation_refuses_a_camera_list_it_cannot_render():
    from action_decoder.envs.render import CameraObservation

    with pytest.raises(ValueError, match=r"^cameras: expected a non-empty list of camera names, got 'corner2'$"):
        CameraObservation("corner2", 32)
    with pytest.raises(ValueError, match=r"^--cameras: expected an image size of at least 8 pixels, got 4$"):
        CameraObservation(["corner2"], 4, field="--cameras")
