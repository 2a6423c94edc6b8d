"""Camera observations in the data path: LeRobot video (v3.0 written by LeRobot 0.4.4 with AV1,
v2.1's one file per episode) and image columns decode to the right episode and frame; the writer's
H.264 videos round-trip; `ChunkDataset` gives the chunk's first frame; `record --cameras` renders
Meta-World at every observation."""

import importlib.util
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

pytest.importorskip("av")
from PIL import Image  # noqa: E402

from action_decoder.data import ChunkDataset, EpisodeDataset, concat_datasets, load_dataset, write_episodes  # noqa: E402
from action_decoder.data.video import write_video  # noqa: E402

DATA = Path(__file__).parent / "data" / "lerobot"
CAMS = DATA / "v30_cams"
TOP, WRIST = "observation.images.top", "observation.images.wrist"
SRC = str(Path(__file__).parents[1] / "src")
_spec = importlib.util.spec_from_file_location("make_v30_cams", DATA / "make_v30_cams.py")
fixture = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fixture)            # its generator, `frame_image(camera, episode, frame)`


def _read_square(image: np.ndarray, camera: str) -> tuple[int, int]:
    """(episode, frame) a fixture image [H, W, 3] shows: the bright cell's column, the background level."""
    grey = np.asarray(Image.fromarray(image).resize((32, 32), Image.NEAREST))[..., 0].astype(float)
    cells = grey.reshape(4, 8, 4, 8).mean((1, 3))                             # [4, 4]
    col = int(cells[1].argmax())
    level = np.median(grey)
    frame = round((180 - level) / 12) if camera == WRIST else round((level - 10) / 12)
    return (3 - col if camera == WRIST else col), int(frame)


# ---------------------------------------------------------------------- reading LeRobot's own dataset
def test_lerobot_v30_av1_frames_come_back_with_their_episode_and_frame():
    ds = load_dataset(CAMS)
    assert ds.cameras == [TOP, WRIST] and ds.episode_lengths.tolist() == list(fixture.LENGTHS)
    assert json.loads((CAMS / "meta" / "info.json").read_text())["features"][TOP]["info"]["video.codec"] == "av1"
    for key in ds.cameras:
        frames = ds.images[key]
        assert frames.shape == (35, 32, 32, 3) and frames.dtype == np.uint8
        for i in range(ds.num_frames):
            episode, frame = ds.states[i, :2].astype(int)
            assert _read_square(frames[i], key) == (episode, frame), (key, i)
            want = fixture.frame_image(key, episode, frame).astype(int)
            assert np.abs(frames[i] - want).mean() < 3, (key, i)


def test_camera_selection_and_its_errors(tmp_path):
    only = load_dataset(CAMS, cameras=[WRIST])
    assert only.cameras == [WRIST]
    np.testing.assert_array_equal(only.images[WRIST], load_dataset(CAMS).images[WRIST])
    assert load_dataset(CAMS, cameras=[WRIST, TOP]).cameras == [WRIST, TOP]          # the order asked for
    none = load_dataset(CAMS, cameras=[])
    assert none.images is None and none.cameras == []
    with pytest.raises(ValueError, match=r"^cameras: .*available: observation.images.top, observation.images.wrist"
                                         r"\), got \['top'\]$"):
        load_dataset(CAMS, cameras=["top"])
    with pytest.raises(ValueError, match="^cameras: expected a list"):
        load_dataset(CAMS, cameras=TOP)
    with pytest.raises(ValueError, match=r"available: none\), got \['observation.images.top'\]"):
        load_dataset(DATA / "v30_toy", cameras=[TOP])


def test_resize_keeps_content_and_size_errors_name_the_field():
    small = load_dataset(CAMS, image_size=16).images[TOP]                          # [N, 16, 16, 3]
    wide = load_dataset(CAMS, image_size=(16, 24)).images[WRIST]
    assert small.shape == (35, 16, 16, 3) and wide.shape == (35, 16, 24, 3)
    native, ds_states = load_dataset(CAMS).images[TOP], load_dataset(CAMS, cameras=[]).states[:, :2].astype(int)
    for i in (0, 7, 20):
        want = np.asarray(Image.fromarray(native[i]).resize((16, 16), Image.BILINEAR))
        np.testing.assert_allclose(small[i], want, atol=1)
        assert _read_square(small[i], TOP) == _read_square(native[i], TOP) == tuple(ds_states[i])
    for bad in (0, -4, "64", (16,), (16, 0), 2.5):
        with pytest.raises(ValueError, match="^image_size: expected a positive int or"):
            load_dataset(CAMS, image_size=bad)


def test_a_row_without_a_frame_names_the_file_and_the_timestamp(tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(CAMS, root)
    path = next((root / "meta" / "episodes").rglob("*.parquet"))
    table = pq.read_table(path)
    column = f"videos/{TOP}/from_timestamp"
    shifted = pa.array([v + (10.0 if e == 2 else 0.0) for e, v in zip(table["episode_index"].to_pylist(),
                                                                          table[column].to_pylist())], pa.float64())
    pq.write_table(table.set_column(table.column_names.index(column), column, shifted), path)
    with pytest.raises(ValueError, match=r"file-000\.mp4: expected a frame within 0\.05 s .* of timestamp 12\.1000 s, "
                                         r"the nearest is at 3\.4000 s"):
        load_dataset(root, cameras=[TOP])
    assert load_dataset(root, cameras=[WRIST]).cameras == [WRIST]                  # the other camera is intact


# ---------------------------------------------------------------------- image columns and v2.1 videos
def _png_cell(image: np.ndarray) -> dict:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return {"bytes": buffer.getvalue(), "path": None}


def _toy_episodes(lengths, cameras=(), size=32):
    return [{"observation.state": np.stack([np.full(n, e), np.arange(n)], 1).astype(np.float32),
             "action": np.zeros((n, 2), np.float32), "task_index": 0,
             **({"images": {c: np.stack([fixture.frame_image(c, e, f) for f in range(n)])[:, :size, :size]
                            for c in cameras}} if cameras else {})}
            for e, n in enumerate(lengths)]


def test_image_columns_decode_png_cells_losslessly_in_row_order(tmp_path):
    root = write_episodes(tmp_path / "ds", _toy_episodes([5, 4]), ["t"], 10)
    path = root / "data" / "chunk-000" / "file-000.parquet"
    table = pq.read_table(path)
    rows = list(zip(table["episode_index"].to_pylist(), table["frame_index"].to_pylist()))
    cells = pa.array([_png_cell(fixture.frame_image(TOP, e, f)) for e, f in rows],
                     pa.struct([("bytes", pa.binary()), ("path", pa.string())]))
    order = np.random.default_rng(0).permutation(len(rows))                     # rows need not be sorted
    pq.write_table(table.append_column(TOP, cells).take(order), path)
    info = json.loads((root / "meta" / "info.json").read_text())
    info["features"][TOP] = {"dtype": "image", "shape": [32, 32, 3], "names": ["height", "width", "channels"]}
    (root / "meta" / "info.json").write_text(json.dumps(info))

    ds = load_dataset(root)
    assert ds.cameras == [TOP]
    for i in range(ds.num_frames):
        episode, frame = ds.states[i].astype(int)
        np.testing.assert_array_equal(ds.images[TOP][i], fixture.frame_image(TOP, episode, frame))
    assert load_dataset(root, image_size=8).images[TOP].shape == (9, 8, 8, 3)


def test_v21_video_layout_one_file_per_episode_and_camera(tmp_path):
    """LeRobot 0.3.3's layout: data/chunk-000/episode_00000e.parquet, meta/*.jsonl, and
    videos/chunk-000/<key>/episode_00000e.mp4 named by info.json's video_path."""
    root, lengths, fps = tmp_path / "v21", [6, 8], 10
    info = {"codebase_version": "v2.1", "fps": fps, "chunks_size": 1000,
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
            "features": {"observation.state": {"dtype": "float32", "shape": [2]},
                         "action": {"dtype": "float32", "shape": [2]},
                         **{k: {"dtype": "video", "shape": [32, 32, 3]} for k in (TOP, WRIST)}}}
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps(info))
    (root / "meta" / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": "look"}) + "\n")
    (root / "meta" / "episodes.jsonl").write_text("".join(
        json.dumps({"episode_index": e, "tasks": ["look"], "length": n}) + "\n" for e, n in enumerate(lengths)))
    start = 0
    for e, n in enumerate(lengths):
        vec = pa.list_(pa.float32(), 2)
        table = pa.table({"observation.state": pa.array([[e, f] for f in range(n)], vec),
                          "action": pa.array([[0, 0]] * n, vec),
                          "timestamp": pa.array(np.arange(n) / fps, pa.float32()),
                          "frame_index": np.arange(n), "episode_index": np.full(n, e), "index": start + np.arange(n),
                          "task_index": np.zeros(n, np.int64)})
        (root / "data" / "chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(table, root / "data" / "chunk-000" / f"episode_{e:06d}.parquet")
        for key in (TOP, WRIST):
            write_video(root / "videos" / "chunk-000" / key / f"episode_{e:06d}.mp4",
                        np.stack([fixture.frame_image(key, e, f) for f in range(n)]), fps)
        start += n

    ds = load_dataset(root)
    assert ds.cameras == [TOP, WRIST] and ds.episode_lengths.tolist() == lengths
    for key in ds.cameras:
        for i in range(ds.num_frames):
            episode, frame = ds.states[i].astype(int)
            assert _read_square(ds.images[key][i], key) == (episode, frame), (key, i)
    (root / "videos" / "chunk-000" / WRIST / "episode_000001.mp4").unlink()
    with pytest.raises(ValueError, match=r"episode_000001\.mp4: expected the video file of this camera, the file is missing"):
        load_dataset(root)


# ---------------------------------------------------------------------- writing video features
def _smooth(episode: int, frame: int) -> np.ndarray:
    """[32, 48, 3] uint8: smooth gradients whose phase moves with the frame and the episode."""
    y, x = np.mgrid[:32, :48] / 32.0
    phase = 0.35 * frame + 1.7 * episode
    planes = [np.sin(x * 2 + phase), np.cos(y * 2 - phase), np.sin((x + y) + 0.5 * phase)]
    return np.clip(127.5 + 100 * np.stack(planes, -1), 0, 255).astype(np.uint8)


def test_written_video_features_round_trip_within_codec_tolerance_in_order(tmp_path):
    lengths, fps = [7, 5, 9], 15
    episodes = _toy_episodes(lengths)
    for e, ep in enumerate(episodes):
        frames = np.stack([_smooth(e, f) for f in range(lengths[e])])
        ep["images"] = {"observation.images.front": frames, "observation.images.side": 255 - frames}
    root = write_episodes(tmp_path / "ds", episodes, ["t"], fps)

    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    feature = info["features"]["observation.images.front"]
    assert {k: feature[k] for k in ("dtype", "shape", "names")} == \
        {"dtype": "video", "shape": [32, 48, 3], "names": ["height", "width", "channels"]}
    assert feature["info"]["video.codec"] == "h264" and feature["info"]["video.pix_fmt"] == "yuv420p"
    assert list(info["features"])[:4] == ["observation.state", "action", "observation.images.front",
                                          "observation.images.side"]
    assert "observation.images.front" not in pq.read_schema(root / "data" / "chunk-000" / "file-000.parquet").names
    rows = pq.read_table(next((root / "meta" / "episodes").rglob("*.parquet"))).to_pylist()
    starts = np.cumsum([0] + lengths) / fps
    for e, row in enumerate(rows):
        assert row["videos/observation.images.side/from_timestamp"] == pytest.approx(starts[e])
        assert row["videos/observation.images.side/to_timestamp"] == pytest.approx(starts[e + 1])
        assert np.shape(row["stats/observation.images.front/mean"]) == (3, 1, 1)

    ds = load_dataset(root)
    for key in ("observation.images.front", "observation.images.side"):
        want = np.concatenate([ep["images"][key] for ep in episodes]).astype(int)     # [N, H, W, 3]
        errors = np.abs(ds.images[key] - want).mean(axis=(1, 2, 3))
        assert errors.max() < 3, (key, errors)
        # each frame is nearer its own original than the frame before or after it
        shifted = np.abs(ds.images[key][1:] - want[:-1]).mean(axis=(1, 2, 3))
        assert (shifted > 3 * errors[1:]).all()

    stats = json.loads((root / "meta" / "stats.json").read_text())["observation.images.side"]
    pixels = 255 - np.concatenate([ep["images"]["observation.images.front"] for ep in episodes])
    values = pixels.reshape(-1, 3).astype(np.float64) / 255
    np.testing.assert_allclose(np.asarray(stats["mean"]).reshape(3), values.mean(0), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(stats["std"]).reshape(3), values.std(0), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(stats["min"]).reshape(3), values.min(0))
    np.testing.assert_allclose(np.asarray(stats["q10"]).reshape(3), np.quantile(values, 0.1, axis=0), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(stats["q99"]).reshape(3), np.quantile(values, 0.99, axis=0), rtol=1e-9)
    assert stats["count"] == [sum(lengths)]


@pytest.mark.parametrize("change, match", [
    (lambda eps: eps[1].pop("images"), "images expected in every episode or in none"),
    (lambda eps: eps[1]["images"].update({TOP: eps[1]["images"][TOP][:-1]}), r"episode 1 images\['observation.images.top'\] expected uint8 \[4, H, W, 3\]"),
    (lambda eps: eps[0]["images"].update({TOP: eps[0]["images"][TOP].astype(np.float32)}), "expected uint8"),
    (lambda eps: [ep["images"].update({TOP: ep["images"][TOP][:, :31, :31]}) for ep in eps], "expected an even height and width"),
    (lambda eps: eps[1].update(images={WRIST: eps[1]["images"][TOP]}), r"episode 1 images expected the cameras \['observation.images.top'\]"),
])
def test_bad_images_are_one_line_naming_the_field(tmp_path, change, match):
    episodes = _toy_episodes([3, 4], cameras=[TOP])
    change(episodes)
    with pytest.raises(ValueError, match=match):
        write_episodes(tmp_path / "ds", episodes, ["t"], 10)


# ---------------------------------------------------------------------- EpisodeDataset and ChunkDataset
def test_chunk_dataset_gives_the_first_frame_of_each_chunk_channel_first():
    ds = load_dataset(CAMS)
    chunks = ChunkDataset(ds, horizon=5)
    for i in (0, 11, 12, 20, 34):
        item = chunks[i]
        assert item["images"].shape == (2, 3, 32, 32) and item["images"].dtype == torch.uint8
        for c, key in enumerate(ds.cameras):
            image = item["images"][c].permute(1, 2, 0).numpy()                    # [H, W, 3]
            np.testing.assert_array_equal(image, ds.images[key][i])
            assert _read_square(image, key) == tuple(item["state"][:2].int().tolist())
    assert "images" not in ChunkDataset(load_dataset(CAMS, cameras=[]), horizon=5)[0]
    picked = ChunkDataset(ds, horizon=5, episodes=[2])                            # subsets keep the frames
    assert _read_square(picked[3]["images"][0].permute(1, 2, 0).numpy(), TOP) == (2, 3)
    batch = torch.utils.data.default_collate([chunks[0], chunks[1]])
    assert batch["images"].shape == (2, 2, 3, 32, 32)


def test_select_and_concat_keep_the_cameras_and_refuse_mismatches():
    ds = load_dataset(CAMS)
    sub = ds.select([2, 0])
    assert sub.cameras == ds.cameras and sub.images[TOP].shape == (26, 32, 32, 3)
    assert _read_square(sub.images[TOP][0], TOP) == (2, 0) and _read_square(sub.images[TOP][14], TOP) == (0, 0)
    both = concat_datasets([ds, sub])
    assert both.images[WRIST].shape == (61, 32, 32, 3)
    np.testing.assert_array_equal(both.images[WRIST][35:], sub.images[WRIST])
    with pytest.raises(ValueError, match="^concat_datasets: expected the same cameras at one image size"):
        concat_datasets([ds, load_dataset(CAMS, cameras=[TOP])])
    with pytest.raises(ValueError, match="^concat_datasets: expected the same cameras at one image size"):
        concat_datasets([ds, load_dataset(CAMS, image_size=16)])
    with pytest.raises(ValueError, match=r"^EpisodeDataset.images\['observation.images.top'\]: expected uint8 \[35, H, W, 3\]"):
        EpisodeDataset(ds.states, ds.actions, ds.task_index, ds.episode_lengths, ds.tasks, ds.fps,
                       images={TOP: ds.images[TOP][:-1]})


# ---------------------------------------------------------------------- Meta-World pixels
@pytest.fixture(scope="module")
def rendering():
    """Probe once, in a child process (MUJOCO_GL binds at mujoco's import): the reason it fails, or None."""
    probe = subprocess.run([sys.executable, "-c", "from action_decoder.envs.render import check_rendering as c; c()"],
                           env={**os.environ, "PYTHONPATH": SRC}, capture_output=True, text=True, timeout=300)
    return None if probe.returncode == 0 else (probe.stderr.strip().splitlines() or ["no output"])[-1]


REPLAY = """
import json, sys, numpy as np
from action_decoder.data import load_demos
from action_decoder.data.demos import record_episodes
from action_decoder.envs.metaworld_tasks import make_env
from action_decoder.envs.render import CameraObservation

episodes, fps, source = record_episodes("reach", 1, cameras=["corner2"], image_size=32)
ep = episodes[0]
frames = ep["images"]["observation.images.corner2"]                      # [L, 32, 32, 3], as rendered
env, rig = make_env("reach-v3", 0), CameraObservation(["corner2"], 32)
env.reset(seed=int(ep["seed"]))
replay = [rig(env)["corner2"]]
for action in ep["action"][:5]:
    env.step(action.astype(np.float32))
    replay.append(rig(env)["corner2"])
rig.close()
same = [bool((frames[k] == replay[k]).all()) for k in range(6)]
shifted = [float(np.abs(frames[k + 1].astype(int) - replay[k]).mean()) for k in range(5)]
ds = load_demos("metaworld/reach", 1, cameras=["corner2"], image_size=32)
again = load_demos("metaworld/reach", 1, cameras=["corner2"], image_size=32)
plain = load_demos("metaworld/reach", 1)
print(json.dumps({"same": same, "shifted": shifted, "states": len(ep["observation.state"]), "frames": len(frames),
                  "cameras": ds.cameras, "shape": list(ds.images["observation.images.corner2"].shape),
                  "num_frames": ds.num_frames, "plain": plain.cameras, "again": bool(
                      (again.images["observation.images.corner2"] == ds.images["observation.images.corner2"]).all()),
                  "source": source}))
"""


def test_meta_world_frames_are_rendered_at_every_observation_and_cached_by_camera_and_size(rendering, tmp_path):
    if rendering is not None:
        pytest.skip(f"offscreen rendering is unavailable here: {rendering}")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": SRC, "ACTION_DECODER_CACHE": str(tmp_path / "cache")}
    res = subprocess.run([sys.executable, "-c", REPLAY], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["frames"] == out["states"]
    assert out["same"] == [True] * 6, "frame k is the scene after reset and k actions, as state k is"
    assert min(out["shifted"]) > 0, "consecutive frames differ, so an off-by-one would show"
    assert out["cameras"] == ["observation.images.corner2"] and out["shape"] == [out["num_frames"], 32, 32, 3]
    assert out["plain"] == [] and out["again"]
    assert out["source"]["cameras"] == ["corner2"] and out["source"]["image_size"] == 32
    cached = sorted(p.name for p in (tmp_path / "cache" / "metaworld").iterdir())
    assert cached == ["reach-v3-n1-s0", "reach-v3-n1-s0-camcorner2-px32"]


def test_record_cameras_cli_writes_a_video_dataset_that_loads(rendering, tmp_path):
    if rendering is not None:
        pytest.skip(f"offscreen rendering is unavailable here: {rendering}")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": SRC}
    out = tmp_path / "rec"
    res = subprocess.run([sys.executable, "-m", "action_decoder.cli", "record", "--task", "metaworld/reach",
                          "--demos", "1", "--output-dir", str(out), "--cameras", "corner2,corner", "--image-size", "32"],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "cameras observation.images.corner2, observation.images.corner at 32x32 px" in res.stdout
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["features"]["observation.images.corner2"]["shape"] == [32, 32, 3]
    assert (out / "videos" / "observation.images.corner" / "chunk-000" / "file-000.mp4").is_file()
    ds = load_dataset(out)
    assert ds.cameras == ["observation.images.corner2", "observation.images.corner"]
    frames = ds.images["observation.images.corner2"]
    assert frames.shape == (ds.num_frames, 32, 32, 3) and frames.std() > 10, "a rendered scene, not a blank frame"
    assert np.abs(frames.astype(int) - ds.images["observation.images.corner"]).mean() > 10, "two viewpoints"
    res = subprocess.run([sys.executable, "-m", "action_decoder.cli", "record", "--task", "metaworld/reach",
                          "--demos", "1", "--output-dir", str(tmp_path / "bad"), "--cameras", "nadir",
                          "--image-size", "32"], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert res.stderr.startswith("action-decoder: error: --cameras: expected one of") and "corner2" in res.stderr


def test_a_datasets_single_camera_observation_image_trains_and_loads(tmp_path, monkeypatch, capsys):
    from action_decoder import ActionDecoderPolicy, cli
    from action_decoder.evaluate import policy_camera_rig

    episodes = _toy_episodes([12, 12, 12])
    for e, ep in enumerate(episodes):                 # LeRobot's pusht / xarm name their one camera so
        ep["images"] = {"observation.image": np.stack([_smooth(e, f) for f in range(12)])[:, :32, :32]}
    root = write_episodes(tmp_path / "ds", episodes, ["t"], 10)
    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))
    assert cli.main(["train", "--dataset", str(root), "--output-dir", str(tmp_path / "run"), "--steps", "2",
                     "--hidden-size", "32", "--num-layers", "1", "--batch-size", "4", "--image-size", "16",
                     "--no-progress"]) == 0
    assert "cameras: observation.image (16x16 px" in capsys.readouterr().out
    policy = ActionDecoderPolicy.from_pretrained(tmp_path / "run" / "final")
    assert policy.config.cameras == ("observation.image",)
    with pytest.raises(ValueError, match=r"^checkpoint cameras: expected keys 'observation.images.<simulator "
                                         r"camera>' to render, got \['observation.image'\]"):
        policy_camera_rig(policy)
