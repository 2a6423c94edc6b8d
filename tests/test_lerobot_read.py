"""Reading LeRobot datasets (v3.0, v2.1, the library's v2.0) and `train --dataset` on them.

The fixtures under tests/data/lerobot were written by LeRobot's own API (see its README): the
same 6 episodes and 2 tasks in format v3.0 (LeRobot 0.4.4) and v2.1 (LeRobot 0.3.3).
"""

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from action_decoder import ActionDecoderPolicy
from action_decoder.data import ACTION, ACTION_CONSTANT_BELOW, STATE, ChunkDataset, compute_stats, load_dataset
from action_decoder.data.lerobot_format import camera_keys, read_info
from action_decoder.train import (TrainConfig, closed_loop_env, decoder_config, held_out_count,
                                  load_training_data, validation_metrics)

DATA = Path(__file__).parent / "data" / "lerobot"
V30, V21 = DATA / "v30_toy", DATA / "v21_toy"
TASKS = ["push the block", "lift the cube"]
LENGTHS = [40, 43, 46, 49, 52, 55]


def _copy(src: Path, tmp_path: Path) -> Path:
    dst = tmp_path / src.name
    shutil.copytree(src, dst)
    return dst


def _edit_info(root: Path, **changes) -> None:
    path = root / "meta" / "info.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


# ---------------------------------------------------------------------- reading
def test_v30_and_v21_load_identically():
    a, b = load_dataset(V30), load_dataset(V21)
    assert a.tasks == b.tasks == TASKS
    assert a.fps == b.fps == 10
    assert a.episode_lengths.tolist() == b.episode_lengths.tolist() == LENGTHS
    assert a.episode_ids.tolist() == b.episode_ids.tolist() == list(range(6))
    assert np.array_equal(a.states, b.states) and a.states.shape == (285, 6)
    assert np.array_equal(a.actions, b.actions) and a.actions.shape == (285, 3)
    # Tasks alternate by episode: even episodes push, odd ones lift.
    expected = np.repeat(np.arange(6) % 2, LENGTHS)
    assert np.array_equal(a.task_index, expected) and np.array_equal(b.task_index, expected)
    for name in (STATE, ACTION):
        for key in ("mean", "std", "min", "max"):
            np.testing.assert_array_equal(a.stats[name][key], b.stats[name][key])


def test_statistics_from_frames_agree_with_lerobots_stats_json():
    ds = load_dataset(V30)
    lerobot = json.loads((V30 / "meta" / "stats.json").read_text())
    for name in (STATE, ACTION):
        for key in ("mean", "std", "min", "max"):
            np.testing.assert_allclose(ds.stats[name][key], lerobot[name][key], rtol=1e-6, atol=1e-6)


def test_stats_json_is_not_read(tmp_path):
    root = _copy(V30, tmp_path)
    (root / "meta" / "stats.json").write_text("{not json")
    np.testing.assert_array_equal(load_dataset(root).stats[ACTION]["mean"], load_dataset(V30).stats[ACTION]["mean"])


def test_v30_tasks_from_a_plain_task_column(tmp_path):
    root = _copy(V30, tmp_path)
    # Rows in another order than task_index: the index decides which string is which.
    pq.write_table(pa.table({"task": ["lift it", "push it"], "task_index": [1, 0]}), root / "meta" / "tasks.parquet")
    assert load_dataset(root).tasks == ["push it", "lift it"]


@pytest.mark.parametrize("fixture", [V30, V21])
def test_unknown_codebase_version_is_one_line(tmp_path, fixture):
    root = _copy(fixture, tmp_path)
    _edit_info(root, codebase_version="v9.9")
    with pytest.raises(ValueError, match=r"info\.json: codebase_version expected one of .*got 'v9\.9'") as err:
        load_dataset(root)
    assert "\n" not in str(err.value)


def test_v30_without_tasks_parquet_names_the_file(tmp_path):
    root = _copy(V30, tmp_path)
    (root / "meta" / "tasks.parquet").unlink()
    with pytest.raises(ValueError, match=r"meta/tasks\.parquet: expected LeRobot tasks .*missing"):
        load_dataset(root)
    pq.write_table(pa.table({"name": ["a", "b"], "task_index": [0, 1]}), root / "meta" / "tasks.parquet")
    with pytest.raises(ValueError, match=r"tasks\.parquet: expected columns task_index and task"):
        load_dataset(root)


def test_episode_metadata_that_disagrees_with_the_data_is_named(tmp_path):
    v21 = _copy(V21, tmp_path)
    path = v21 / "meta" / "episodes.jsonl"
    path.write_text(path.read_text().replace('"length": 49', '"length": 48'))
    with pytest.raises(ValueError, match=r"episodes\.jsonl: .*episode\(s\) \[3\] \(metadata \[48\] frames, data \[49\]\)"):
        load_dataset(v21)
    v30 = _copy(V30, tmp_path)
    path = next((v30 / "meta" / "episodes").rglob("*.parquet"))
    table = pq.read_table(path)
    pq.write_table(table.filter(pa.compute.not_equal(table["episode_index"], 2)), path)   # episode 2 not listed
    with pytest.raises(ValueError, match=r"meta/episodes: .*episode\(s\) \[2\]"):
        load_dataset(v30)


def test_camera_keys_from_info():
    assert camera_keys(read_info(V30)) == []
    info = {"features": {STATE: {"dtype": "float32"}, "observation.images.top": {"dtype": "video"},
                         "observation.images.wrist": {"dtype": "image"}}}
    assert camera_keys(info) == ["observation.images.top", "observation.images.wrist"]


# ---------------------------------------------------------------------- held-out validation
def test_held_out_count():
    assert [held_out_count(n, 0.1) for n in (1, 2, 6, 10, 25)] == [0, 1, 1, 1, 2]
    assert held_out_count(6, 0.0) == 0 and held_out_count(4, 0.9) == 3
    with pytest.raises(ValueError, match=r"--val-fraction: expected a share of episodes in \[0, 1\), got 1.0"):
        held_out_count(6, 1.0)


def test_training_never_sees_the_held_out_episodes():
    train, tasks, val = load_training_data(TrainConfig(dataset=str(V30), horizon=4), quiet=True)
    assert tasks == TASKS
    assert train.dataset.episode_ids.tolist() == [0, 1, 2, 3, 4] and val.dataset.episode_ids.tolist() == [5]
    full = load_dataset(V30)
    first = full.select(5)
    assert len(train) == sum(LENGTHS[:5]) and len(val) == LENGTHS[5]
    # Statistics of the training episodes only, not of all six.
    expected = compute_stats({STATE: first.states, ACTION: first.actions}, constant_below={ACTION: ACTION_CONSTANT_BELOW})
    np.testing.assert_array_equal(train.stats[ACTION]["mean"], expected[ACTION]["mean"])
    assert not np.allclose(train.stats[ACTION]["mean"], full.stats[ACTION]["mean"])


def test_a_dataset_naming_metaworld_is_not_split(tmp_path):
    root = _copy(V30, tmp_path)
    assert closed_loop_env(TrainConfig(dataset=str(root))) is None
    _edit_info(root, env="metaworld")
    cfg = TrainConfig(dataset=str(root), horizon=4)
    assert closed_loop_env(cfg) == "metaworld" and closed_loop_env(TrainConfig()) == "metaworld"
    train, _, val = load_training_data(cfg, quiet=True)
    assert val is None and train.dataset.num_episodes == 6


def _policy(decoder, ds, tasks):
    cfg = TrainConfig(dataset=str(V30), decoder=decoder, horizon=4, hidden_size=32, num_layers=1)
    torch.manual_seed(0)
    return ActionDecoderPolicy(decoder_config(cfg, 6, 3, tasks), ds.stats)


@pytest.mark.parametrize("decoder", ["DDPM", "flow_matching", "mean_flow"])
def test_validation_metrics_are_finite_and_repeatable(decoder):
    train, tasks, val = load_training_data(TrainConfig(dataset=str(V30), horizon=4), quiet=True)
    policy = _policy(decoder, train, tasks).train()
    first = validation_metrics(policy, val, len(tasks), torch.device("cpu"))
    assert policy.training                                     # its mode is restored
    again = validation_metrics(policy, val, len(tasks), torch.device("cpu"))
    assert first == again
    assert np.isfinite(first["val_loss"]) and first["val_loss"] > 0 and np.isfinite(first["val_action_mse"])
    assert first["episodes"] == [5] and first["frames"] == LENGTHS[5]


def test_validation_action_mse_is_normalised_and_skips_padding(monkeypatch):
    train, tasks, val = load_training_data(TrainConfig(dataset=str(V30), horizon=4), quiet=True)
    policy = _policy("flow_matching", train, tasks)
    norm = policy.normalizers["actions"]
    true = {}

    def sample(batch, generator=None, **_):
        # The held-out chunk shifted by 0.5 normalised units, and by 100 on padded steps.
        target = norm.normalize(batch["actions"])                              # [B, H, D]
        rows = [val[i] for i in range(true.setdefault("start", 0), true["start"] + len(target))]
        true["start"] += len(target)
        pad = torch.stack([r["action_is_pad"] for r in rows])[..., None]       # [B, H, 1]
        return type("Out", (), {"actions": norm.unnormalize(target + 0.5 + 100 * pad)})()

    monkeypatch.setattr(policy, "sample", sample)
    got = validation_metrics(policy, val, len(tasks), torch.device("cpu"))
    assert got["val_action_mse"] == pytest.approx(0.25, rel=1e-4)


# ---------------------------------------------------------------------- train --dataset end to end
def _train_args(ds, out, *more):
    return ["train", "--dataset", str(ds), "--output-dir", str(out), "--steps", "20", "--hidden-size", "32",
            "--num-layers", "1", "--batch-size", "16", "--log-every", "5", "--no-progress", *more]


@pytest.fixture
def cli_main(capsys, monkeypatch, tmp_path):
    from action_decoder import cli

    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))

    def call(args):
        capsys.readouterr()
        code = cli.main(list(args))
        out = capsys.readouterr()
        return code, out.out, out.err

    return call


def test_train_on_v30_and_v21_gives_one_loss_curve_keeps_tasks_and_exits_0(tmp_path, cli_main):
    logs = {}
    for name, root in (("v30", V30), ("v21", V21)):
        code, out, err = cli_main(_train_args(root, tmp_path / name))
        assert code == 0, err
        assert "val_loss=" in out and "val_action_mse=" in out and "held-out episodes [5]" in out
        logs[name] = json.loads((tmp_path / name / "train_log.json").read_text())
        policy = ActionDecoderPolicy.from_pretrained(tmp_path / name / "final")
        assert policy.config.extra["tasks"] == TASKS and policy.config.context_dim == 2
    assert [h["step"] for h in logs["v30"]["history"]] == [5, 10, 15, 20]
    assert logs["v30"]["history"] == logs["v21"]["history"]
    val = logs["v30"]["validation"]
    assert val == logs["v21"]["validation"] and val["episodes"] == [5] and val["frames"] == LENGTHS[5]
    assert np.isfinite(val["val_loss"]) and np.isfinite(val["val_action_mse"])


def test_closed_loop_evaluation_only_for_a_dataset_naming_its_environment(tmp_path, cli_main, monkeypatch):
    import action_decoder.evaluate as evaluate

    calls = []
    monkeypatch.setattr(evaluate, "run_eval", lambda cfg: calls.append(cfg.checkpoint))
    code, _, err = cli_main(_train_args(V21, tmp_path / "plain", "--steps", "2"))
    assert code == 0 and calls == [], err
    root = _copy(V21, tmp_path)
    _edit_info(root, env="metaworld")
    code, _, err = cli_main(_train_args(root, tmp_path / "mw", "--steps", "2"))
    assert code == 0 and calls == [str(tmp_path / "mw" / "final")], err
    assert "validation" not in json.loads((tmp_path / "mw" / "train_log.json").read_text())


def test_train_loads_the_cameras_it_is_given_and_names_them_in_one_line(tmp_path, cli_main):
    cams = DATA / "v30_cams"
    code, out, err = cli_main(_train_args(cams, tmp_path / "o", "--steps", "2", "--cameras", "observation.images.wrist",
                                          "--image-size", "16"))
    assert code == 0, err
    lines = [line for line in out.splitlines() if line.startswith("cameras:")]
    assert lines == ["cameras: observation.images.wrist (16x16 px, decoded once: 0.0 MiB)"]
    train, _, val = load_training_data(TrainConfig(dataset=str(cams), image_size=16), quiet=True)
    assert train.dataset.cameras == ["observation.images.top", "observation.images.wrist"]      # default: all
    assert train[0]["images"].shape == (2, 3, 16, 16) and val[0]["images"].shape == (2, 3, 16, 16)
    code, out, err = cli_main(_train_args(cams, tmp_path / "p", "--steps", "2", "--cameras", "top"))
    assert code == 2 and err.count("\n") == 1 and err.startswith("action-decoder: error: cameras:")
    assert "observation.images.top, observation.images.wrist" in err and "['top']" in err
    code, out, _ = cli_main(_train_args(V30, tmp_path / "q", "--steps", "2"))
    assert code == 0 and "cameras:" not in out


def test_train_dataset_with_default_evaluation_needs_no_simulator(tmp_path):
    import os
    import subprocess
    import sys

    script = tmp_path / "no_sim.py"
    script.write_text("import sys\nfor name in ('gymnasium', 'metaworld', 'mujoco'):\n    sys.modules[name] = None\n"
                      "from action_decoder.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "ACTION_DECODER_CACHE": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1] / "src"), os.environ.get("PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, str(script), *_train_args(V30, tmp_path / "o", "--steps", "2")],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "val_loss=" in res.stdout


@pytest.mark.parametrize("change, match", [
    ({"features": [1, 2]}, r"info.json: \"features\" expected an object of feature name"),
    ({"fps": "ten"}, r"info.json: \"fps\" expected a positive number of frames per second, got 'ten'$"),
    ({"fps": 0}, r"info.json: \"fps\" expected a positive number of frames per second, got 0$"),
])
def test_malformed_info_is_one_line_naming_the_field(tmp_path, change, match):
    root = _copy(V30, tmp_path)
    _edit_info(root, **change)
    with pytest.raises(ValueError, match=match):
        load_dataset(root)


@pytest.mark.parametrize("values, match", [
    ([None], r"column 'task_index' expected an integer per frame, got type int64 with \d+ nulls"),
    ([-1], r"column 'task_index' expected indices >= 0 into meta/tasks, got -1"),
])
def test_a_bad_task_index_names_the_file(tmp_path, values, match):
    root = _copy(V30, tmp_path)
    path = next((root / "data").rglob("*.parquet"))
    table = pq.read_table(path)
    column = pa.array(values * table.num_rows, pa.int64())
    table = table.set_column(table.column_names.index("task_index"), "task_index", column)
    pq.write_table(table, path)
    with pytest.raises(ValueError, match=rf"^{path}: {match}"):
        load_dataset(root)


def test_eval_of_a_dataset_policy_says_what_to_run_instead_and_its_card_shows_the_validation(tmp_path, cli_main):
    from huggingface_hub import ModelCard

    code, _, err = cli_main(_train_args(V30, tmp_path / "o", "--steps", "2"))
    assert code == 0, err
    final = tmp_path / "o" / "final"
    code, out, err = cli_main(["eval", "--checkpoint", str(final)])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert "closed-loop evaluation runs Meta-World tasks" in lines[0] and "push the block" in lines[0]
    assert "model card" in lines[0] and "unknown Meta-World task" not in lines[0]
    val = json.loads((tmp_path / "o" / "train_log.json").read_text())["validation"]
    card = (final / "README.md").read_text()
    assert "action-decoder eval --checkpoint" not in card and "Closed-loop success is not measured" in card
    assert f"| {val['val_loss']:.4f} | {val['val_action_mse']:.4f} |" in card
    metrics = {r.metric_type: r.metric_value for r in ModelCard.load(final / "README.md").data.eval_results}
    assert metrics == {"val_loss": val["val_loss"], "val_action_mse": val["val_action_mse"]}
    # Saved again it keeps them; other weights (fine-tuned, say) do not carry them.
    policy = ActionDecoderPolicy.from_pretrained(final)
    policy.save_pretrained(tmp_path / "same")
    assert f"| {val['val_loss']:.4f} |" in (tmp_path / "same" / "README.md").read_text()
    with torch.no_grad():
        policy.model.action_in.weight.add_(0.1)
    policy.save_pretrained(tmp_path / "other")
    assert "val_loss" not in (tmp_path / "other" / "README.md").read_text()
