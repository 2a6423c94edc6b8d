"""LeRobot v3.0 writing: the files match what LeRobot 0.4.4 writes itself (the ``v30_toy`` fixture),
round-trip through the library's reader, and back ``action-decoder record`` and the demo cache."""

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from action_decoder.data import CONTINUATION, load_dataset, write_episodes

FIXTURE = Path(__file__).parent / "data" / "lerobot" / "v30_toy"
DATA = "data/chunk-000/file-000.parquet"
EPISODES = "meta/episodes/chunk-000/file-000.parquet"


def _fixture_episodes():
    """The fixture's frames as the episode dicts ``write_episodes`` takes, its tasks and names."""
    table = pq.read_table(FIXTURE / DATA)
    tasks = pq.read_table(FIXTURE / "meta" / "tasks.parquet").sort_by("task_index")["__index_level_0__"].to_pylist()
    episode = table["episode_index"].to_numpy()
    vec = lambda k, rows: np.asarray(table[k].to_pylist(), np.float32)[rows]   # [L, W]
    episodes = [{"observation.state": vec("observation.state", episode == e), "action": vec("action", episode == e),
                 "task_index": int(table["task_index"].to_numpy()[episode == e][0])} for e in np.unique(episode)]
    info = json.loads((FIXTURE / "meta" / "info.json").read_text())
    names = {k: info["features"][k]["names"] for k in ("observation.state", "action")}
    return episodes, tasks, names, info


def _hf_features(path):
    return json.loads(pq.read_schema(path).metadata[b"huggingface"])["info"]["features"]


def test_rewriting_lerobots_own_dataset_reproduces_its_files(tmp_path):
    episodes, tasks, names, info = _fixture_episodes()
    root = write_episodes(tmp_path / "ds", episodes, tasks, info["fps"], {"robot_type": "toy"}, names=names)
    assert sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()) == \
        sorted(str(p.relative_to(FIXTURE)) for p in FIXTURE.rglob("*") if p.is_file())
    assert json.loads((root / "meta" / "info.json").read_text()) == info
    assert type(json.loads((root / "meta" / "info.json").read_text())["fps"]) is int       # as LeRobot writes it
    for path in (DATA, EPISODES, "meta/tasks.parquet"):     # types with their list field names ("element")
        assert pq.read_schema(root / path).to_string(show_schema_metadata=False) == \
            pq.read_schema(FIXTURE / path).to_string(show_schema_metadata=False), path

    ours, theirs = pq.read_table(root / DATA), pq.read_table(FIXTURE / DATA)
    assert ours.equals(theirs)                                  # same columns, types, field names and values
    assert _hf_features(root / DATA) == _hf_features(FIXTURE / DATA)

    ours, theirs = pq.read_table(root / EPISODES), pq.read_table(FIXTURE / EPISODES)
    assert ours.schema.equals(theirs.schema)
    for name in theirs.column_names:
        mine, ref = ours[name].to_pylist(), theirs[name].to_pylist()
        if name.split("/")[-1] in ("q01", "q10", "q50", "q90", "q99"):
            continue            # LeRobot's are histogram estimates; ours are exact (checked below)
        if name.startswith("stats/"):
            np.testing.assert_allclose(np.asarray(mine, float), np.asarray(ref, float), rtol=1e-5, atol=1e-6, err_msg=name)
        else:
            assert mine == ref, name

    ours = pq.read_table(root / "meta" / "tasks.parquet")
    theirs = pq.read_table(FIXTURE / "meta" / "tasks.parquet")
    assert ours.equals(theirs)
    pandas_meta = [json.loads(t.schema.metadata[b"pandas"]) for t in (ours, theirs)]
    assert [{k: m[k] for k in ("index_columns", "columns", "column_indexes")} for m in pandas_meta] == \
        [{k: pandas_meta[1][k] for k in ("index_columns", "columns", "column_indexes")}] * 2

    ours, theirs = (json.loads((r / "meta" / "stats.json").read_text()) for r in (root, FIXTURE))
    assert sorted(ours) == sorted(theirs)
    for feature, stats in theirs.items():
        assert list(ours[feature]) == list(stats)
        for key in ("min", "max", "mean", "std", "count"):
            np.testing.assert_allclose(ours[feature][key], stats[key], rtol=1e-5, atol=1e-6, err_msg=f"{feature}/{key}")
    values = np.concatenate([ep["action"] for ep in episodes])                       # [N, 3]
    np.testing.assert_allclose(ours["action"]["q10"], np.quantile(values.astype(np.float64), 0.1, axis=0), rtol=1e-12)


def _episodes(rng, lengths, state=5, action=2, k=4, tasks=2):
    return [{"observation.state": rng.normal(size=(n, state)), "action": rng.uniform(-1, 1, (n, action)),
             CONTINUATION: rng.normal(size=(n, k, action)), "task_index": e % tasks,
             "next.reward": rng.random(n), "next.success": np.arange(n) >= n - 2, "seed": 100 + e}
            for e, n in enumerate(lengths)]


def test_round_trip_through_the_reader_across_several_data_files(tmp_path):
    lengths = [7, 12, 3, 9, 15]
    episodes = _episodes(np.random.default_rng(0), lengths)
    root = write_episodes(tmp_path / "ds", episodes, ["open the drawer", "push the block"], 12.5,
                          {"env": "metaworld"}, data_file_size_in_mb=1e-3)     # ~1 KB: about one episode per file
    files = sorted((root / "data").rglob("*.parquet"))
    assert len(files) > 2 and [f.name for f in files][:2] == ["file-000.parquet", "file-001.parquet"]
    rows = pq.read_table(root / EPISODES).to_pylist()
    ends = np.cumsum(lengths)
    assert [(r["dataset_from_index"], r["dataset_to_index"]) for r in rows] == list(zip(ends - lengths, ends))
    for r in rows:                  # each episode's frames are in the file its row names, at its global indices
        frames = pq.read_table(root / f"data/chunk-{r['data/chunk_index']:03d}/file-{r['data/file_index']:03d}.parquet")
        mine = frames.filter(pa.compute.equal(frames["episode_index"], r["episode_index"]))
        assert mine["index"].to_pylist() == list(range(r["dataset_from_index"], r["dataset_to_index"]))
    assert [r["seed"] for r in rows] == [100, 101, 102, 103, 104] and rows[1]["tasks"] == ["push the block"]

    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["env"] == "metaworld" and info["fps"] == 12.5
    assert info["features"][CONTINUATION] == {"dtype": "float32", "shape": [4, 2], "names": None}
    assert info["total_frames"] == sum(lengths) and info["video_path"] is None
    ds = load_dataset(root)
    assert ds.tasks == ["open the drawer", "push the block"] and ds.fps == 12.5
    assert ds.episode_lengths.tolist() == lengths and ds.task_index.tolist() == sum(([e % 2] * n for e, n in enumerate(lengths)), [])
    for key, got in (("observation.state", ds.states), ("action", ds.actions), (CONTINUATION, ds.continuations)):
        np.testing.assert_array_equal(got, np.concatenate([ep[key] for ep in episodes]).astype(np.float32))
    table = pa.concat_tables(pq.read_table(f) for f in files)
    assert np.flatnonzero(table["next.done"].to_numpy(zero_copy_only=False)).tolist() == (ends - 1).tolist()
    assert table["next.reward"].type == pa.float32() and table["next.success"].to_pylist()[5:7] == [True, True]
    assert [r["data/file_index"] for r in rows] == sorted(r["data/file_index"] for r in rows)
    stats = json.loads((root / "meta" / "stats.json").read_text())
    assert np.shape(stats[CONTINUATION]["q99"]) == (4, 2) and stats["action"]["count"] == [sum(lengths)]
    assert stats["next.success"]["mean"] == [4 * len(lengths) / 2 / sum(lengths)] * 1


@pytest.mark.parametrize("change, match", [
    (lambda eps, tasks: eps[1].update(task_index=2), r"episode 1 task_index expected an int in 0\.\.1, got 2"),
    (lambda eps, tasks: eps[0].update(action=np.zeros((7, 3))), r"same widths.*got per-frame shapes"),
    (lambda eps, tasks: eps[2].update(action=np.zeros((4, 2))), r"episode 2 expected >= 1 frame and the same length"),
    (lambda eps, tasks: eps[1].pop("seed"), r"seed expected in every episode or in none"),
    (lambda eps, tasks: tasks.append("push the block"), r"tasks expected distinct non-empty strings"),
    (lambda eps, tasks: eps.clear(), r"expected at least one episode"),
])
def test_bad_input_is_one_line_naming_the_field(tmp_path, change, match):
    episodes, tasks = _episodes(np.random.default_rng(1), [7, 5, 3]), ["open the drawer", "push the block"]
    change(episodes, tasks)
    with pytest.raises(ValueError, match=match) as err:
        write_episodes(tmp_path / "ds", episodes, tasks, 10)
    assert "\n" not in str(err.value) and not (tmp_path / "ds").exists()


def test_refuses_a_non_empty_directory_and_a_bad_fps(tmp_path):
    episodes = _episodes(np.random.default_rng(2), [4, 4])
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"expected an empty or new directory, got .*ds \(not empty"):
        write_episodes(tmp_path / "ds", episodes, ["a", "b"], 10)
    assert (tmp_path / "ds" / "notes.txt").read_text() == "mine"
    for fps in (0, -5, float("nan"), "10"):
        with pytest.raises(ValueError, match="fps expected a positive number"):
            write_episodes(tmp_path / "new", episodes, ["a", "b"], fps)


def test_overwrite_replaces_a_dataset_whole_and_nothing_else(tmp_path):
    rng = np.random.default_rng(5)
    root = write_episodes(tmp_path / "ds", _episodes(rng, [9, 9, 9]), ["a", "b"], 10, data_file_size_in_mb=1e-3)
    assert len(list((root / "data").rglob("*.parquet"))) > 1
    with pytest.raises(ValueError, match="overwrite=True replaces a dataset"):
        write_episodes(root, _episodes(rng, [4]), ["c"], 10)
    write_episodes(root, _episodes(rng, [4], tasks=1), ["c"], 10, overwrite=True)
    assert [p.name for p in (root / "data").rglob("*.parquet")] == ["file-000.parquet"]     # no stale file
    ds = load_dataset(root)
    assert ds.tasks == ["c"] and ds.episode_lengths.tolist() == [4] and not list(tmp_path.glob(".*"))
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(ValueError, match="expected an empty or new directory"):
        write_episodes(tmp_path / "mine", _episodes(rng, [4]), ["a", "b"], 10, overwrite=True)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def _write_v20_cache(root, episodes, task, fps, source):
    """A demonstration cache in the v2.0 layout this library wrote before v3.0."""
    (root / "meta").mkdir(parents=True)
    index = 0
    for e, ep in enumerate(episodes):
        n = len(ep["action"])
        flat = lambda v: pa.FixedSizeListArray.from_arrays(pa.array(v.reshape(-1).astype(np.float32)), v[0].size)
        (root / "data" / "chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table({
            "observation.state": flat(ep["observation.state"]), "action": flat(ep["action"]),
            "episode_index": np.full(n, e), "frame_index": np.arange(n), "timestamp": np.arange(n, dtype=np.float32) / fps,
            "index": np.arange(index, index + n), "task_index": np.zeros(n, np.int64),
            "next.reward": ep["next.reward"].astype(np.float32), "next.success": ep["next.success"],
            "next.done": np.arange(n) == n - 1, CONTINUATION: flat(ep[CONTINUATION])}),
            root / "data" / "chunk-000" / f"episode_{e:06d}.parquet")
        index += n
    k, d = episodes[0][CONTINUATION].shape[1:]
    info = {"codebase_version": "v2.0", "fps": fps, "total_episodes": len(episodes), "total_frames": index,
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet", "robot_type": "sawyer",
            "features": {CONTINUATION: {"dtype": "float32", "shape": [k, d], "names": None}}, "source": source}
    (root / "meta" / "tasks.jsonl").write_text(json.dumps({"task_index": 0, "task": task}) + "\n")
    (root / "meta" / "episodes.jsonl").write_text("".join(
        json.dumps({"episode_index": e, "tasks": [task], "length": len(ep["action"]), "seed": ep["seed"]}) + "\n"
        for e, ep in enumerate(episodes)))
    (root / "meta" / "info.json").write_text(json.dumps(info))


def test_a_v20_demo_cache_is_converted_without_the_simulator(tmp_path, monkeypatch, capsys):
    pytest.importorskip("metaworld")
    from action_decoder.data import demos

    episodes = [{k: v for k, v in ep.items() if k != "task_index"}
                for ep in _episodes(np.random.default_rng(3), [6, 9], state=39, action=4, k=3)]
    cache = tmp_path / "metaworld" / "reach-v3-n2-s0-dart0.1"
    source = {"env": "metaworld", "task": "reach-v3", "seed": 0, "first_layout": 0, "action_noise": 0.1}
    _write_v20_cache(cache, episodes, "reach-v3", 80.0, source)
    monkeypatch.setattr(demos, "record_episodes", lambda *a, **k: pytest.fail("conversion ran the simulator"))

    assert demos.generate_demos("metaworld/reach", 2, seed=0, cache_dir=tmp_path, action_noise=0.1) == cache
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "converting the cache" in out and "v2.0 to v3.0" in out
    info = json.loads((cache / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["source"] == source and info["env"] == "metaworld"
    assert not list(cache.rglob("episode_*.parquet")) and not list(tmp_path.glob("metaworld/.*"))
    ds = load_dataset(cache)
    assert ds.tasks == ["reach-v3"] and ds.episode_lengths.tolist() == [6, 9] and ds.fps == 80
    for key, got in (("observation.state", ds.states), ("action", ds.actions), (CONTINUATION, ds.continuations)):
        np.testing.assert_array_equal(got, np.concatenate([ep[key] for ep in episodes]).astype(np.float32))
    assert pq.read_table(cache / EPISODES)["seed"].to_pylist() == [100, 101]
    assert demos.generate_demos("metaworld/reach", 2, seed=0, cache_dir=tmp_path, action_noise=0.1) == cache
    assert capsys.readouterr().out == ""                                             # converted once


def test_a_v20_demo_cache_that_cannot_be_read_is_recorded_anew(tmp_path, monkeypatch, capsys):
    pytest.importorskip("metaworld")
    from action_decoder.data import demos

    episodes = [{k: v for k, v in ep.items() if k != "task_index"}
                for ep in _episodes(np.random.default_rng(4), [6, 9], state=39, action=4, k=3)]
    cache = tmp_path / "metaworld" / "reach-v3-n2-s0-dart0.1"
    source = {"env": "metaworld", "task": "reach-v3", "seed": 0, "first_layout": 0, "action_noise": 0.1}
    _write_v20_cache(cache, episodes, "reach-v3", 80.0, source)
    (cache / "data" / "chunk-000" / "episode_000001.parquet").write_bytes(b"PAR1 truncated")
    fresh = [{**ep, "task_index": 0, "seed": 7 + i} for i, ep in enumerate(episodes)]
    monkeypatch.setattr(demos, "record_episodes", lambda *a, **k: (fresh, 80.0, {**source, "attempts": 2}))

    assert demos.generate_demos("metaworld/reach", 2, seed=0, cache_dir=tmp_path, action_noise=0.1) == cache
    out = capsys.readouterr().out
    assert out.count("\n") == 1 and "cannot be converted" in out and "recording it anew" in out
    assert json.loads((cache / "meta" / "info.json").read_text())["source"]["attempts"] == 2
    assert pq.read_table(cache / EPISODES)["seed"].to_pylist() == [7, 8]


def test_record_cli_writes_a_lerobot_dataset(tmp_path, capsys):
    pytest.importorskip("metaworld")
    from action_decoder.cli import main

    out = tmp_path / "reach"
    assert main(["record", "--task", "metaworld/reach", "--demos", "2", "--output-dir", str(out), "--seed", "1"]) == 0
    assert f"recorded 2 demonstrations" in capsys.readouterr().out
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["env"] == "metaworld" and info["fps"] == 80
    assert info["source"]["first_layout"] == 1000 and CONTINUATION not in info["features"]
    ds = load_dataset(out)
    assert ds.tasks == ["reach-v3"] and ds.num_episodes == 2 and ds.states.shape[1] == 39
    ours, theirs = pq.read_schema(out / DATA), pq.read_schema(FIXTURE / DATA)
    assert [ours.field(f.name).type for f in theirs if f.name not in ("observation.state", "action")] == \
        [f.type for f in theirs if f.name not in ("observation.state", "action")]
    assert ours.field("action").type == pa.list_(pa.field("element", pa.float32()), 4)

    for args, match in ((["--output-dir", str(out), "--demos", "2"], "--output-dir: expected a new or empty directory"),
                        (["--output-dir", str(tmp_path / "x"), "--demos", "0"], "--demos: expected an integer >= 1")):
        assert main(["record", "--task", "metaworld/reach", *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("action-decoder: error: ") and match in err and err.count("\n") == 1


def test_a_one_dimensional_action_is_a_plain_column_as_lerobot_stores_it(tmp_path):
    rng = np.random.default_rng(1)
    episodes = [{"observation.state": rng.normal(size=(n, 3)), "action": rng.normal(size=(n, 1)), "task_index": 0}
                for n in (4, 6)]
    root = write_episodes(tmp_path / "ds", episodes, ["grip"], 10)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["features"]["action"]["shape"] == [1]
    assert pq.read_schema(root / DATA).field("action").type == pa.float32()       # LeRobot's Value("float32")
    ds = load_dataset(root)
    np.testing.assert_allclose(ds.actions, np.concatenate([ep["action"] for ep in episodes]), rtol=1e-6)
    assert ds.actions.shape == (10, 1)


def test_a_continuation_wider_or_narrower_than_the_action_is_refused(tmp_path):
    episodes = _episodes(np.random.default_rng(0), [5, 6])
    for ep in episodes:
        ep[CONTINUATION] = ep[CONTINUATION][..., :1]                                # [L, K, 1] with action [L, 2]
    with pytest.raises(ValueError, match=r"^write_episodes: expected .*action.continuation \[L, K, D\].*got "
                                         r"per-frame shapes"):
        write_episodes(tmp_path / "ds", episodes, ["a", "b"], 10)


def test_the_reader_checks_the_continuations_declared_shape(tmp_path):
    root = write_episodes(tmp_path / "ds", _episodes(np.random.default_rng(0), [5, 6]), ["a", "b"], 10)
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    info["features"][CONTINUATION]["shape"] = [2, 4]                                  # 8 values, but as [K, 4]
    path.write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"info.json: feature 'action.continuation' expected shape \[4, 2\] "
                                         r"\(8 values per frame, action width 2\), got \[2, 4\]$"):
        load_dataset(root)


def test_prefix_lengths_round_trip_beside_the_continuations_and_bad_ones_are_one_line(tmp_path):
    """``action.prefix_length`` (relabelled plans: the committed rows each continuation starts with)."""
    import dataclasses

    import torch

    from action_decoder.data import PREFIX_LENGTH, ChunkDataset
    from action_decoder.train import _batch

    episodes = _episodes(np.random.default_rng(0), [5, 6])
    for e, ep in enumerate(episodes):
        ep[PREFIX_LENGTH] = np.arange(len(ep["action"])) % (2 + e)                       # 0..1, then 0..2
    root = write_episodes(tmp_path / "ds", episodes, ["a", "b"], 10, data_file_size_in_mb=1e-3)
    ds = load_dataset(root)
    np.testing.assert_array_equal(ds.prefix_lengths, [0, 1, 0, 1, 0, 0, 1, 2, 0, 1, 2])
    assert ds.prefix_lengths.dtype == np.int64
    assert json.loads((root / "meta" / "info.json").read_text())["features"][PREFIX_LENGTH]["dtype"] == "int64"
    np.testing.assert_array_equal(ds.select([1]).prefix_lengths, [0, 1, 2, 0, 1, 2])
    items = ChunkDataset(ds, 3)
    assert [items[i]["rtc_delay"] for i in (5, 7)] == [0, 2] and _batch(items, torch.tensor([7, 4, 3]), 1, torch.device(
        "cpu"))["rtc_delays"].tolist() == [2, 0, 1]                  # what training hands `compute_loss`
    assert "rtc_delay" not in ChunkDataset(
        load_dataset(write_episodes(tmp_path / "plain", _episodes(np.random.default_rng(0), [5]), ["a", "b"], 10)), 3)[0]
    with pytest.raises(ValueError, match=r"^horizon: expected more than the 2 committed rows the dataset's "
                                         r"action.prefix_length gives a frame \(rows must remain to learn\), got 2$"):
        ChunkDataset(ds, 2)
    for change, words in (
            (lambda eps: eps[1].update({PREFIX_LENGTH: np.full(6, 4)}),
             r"episode 1 action.prefix_length expected integers \[6\] in 0\.\.3 \(rows of action.continuation\), "
             r"got int64 \[6\] in 4\.\.4$"),
            (lambda eps: eps[0].update({PREFIX_LENGTH: np.zeros(5, np.float32)}), r"got float32 \[5\] in 0\.0\.\.0\.0$"),
            (lambda eps: [ep.pop(CONTINUATION) for ep in eps],
             r"action.prefix_length counts rows of action.continuation; expected both, got no action.continuation$"),
            (lambda eps: eps[0].pop(PREFIX_LENGTH), r"action.prefix_length expected in every episode or in none")):
        bad = [dict(ep) for ep in episodes]
        change(bad)
        with pytest.raises(ValueError, match=words) as err:
            write_episodes(tmp_path / "bad", bad, ["a", "b"], 10)
        assert "\n" not in str(err.value) and not (tmp_path / "bad").exists()
    with pytest.raises(ValueError, match=r"^EpisodeDataset.prefix_lengths: expected integers \[11\] in 0\.\.K-1 beside "
                                         r"continuations \[frames, K, D\] \(none given\), got int64 \[11\] in 0\.\.2$"):
        dataclasses.replace(ds, continuations=None, stats={})
    # A file whose column is edited outside the writer is refused by the reader, naming episode and frame.
    path = sorted((root / "data").rglob("*.parquet"))[-1]
    table = pq.read_table(path)
    cells = table[PREFIX_LENGTH].to_numpy().copy()
    cells[-1] = 9
    pq.write_table(table.set_column(table.schema.get_field_index(PREFIX_LENGTH), PREFIX_LENGTH, pa.array(cells)), path)
    with pytest.raises(ValueError, match=r"column 'action.prefix_length' expected 0\.\.3 \(rows of "
                                         r"action.continuation\), got 9 in episode 1 \(frame 5\)$"):
        load_dataset(root)
