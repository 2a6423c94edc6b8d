"""Meta-World tasks, seeded layouts, demonstrations, datasets and closed-loop evaluation."""

import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch

pytest.importorskip("metaworld")

from action_decoder.data import (  # noqa: E402
    CONTINUATION,
    ChunkDataset,
    EpisodeDataset,
    compute_stats,
    concat_datasets,
    generate_demos,
    load_dataset,
    load_demos,
    write_episodes,
)
from action_decoder.envs import (  # noqa: E402
    MAX_EPISODE_STEPS,
    demo_seeds,
    eval_seeds,
    evaluate,
    expert_policy,
    make_env,
    resolve_tasks,
    restore_state,
    save_state,
)
from action_decoder.data.demos import LOOKAHEAD  # noqa: E402


@pytest.fixture(scope="module")
def reach_demos(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("ACTION_DECODER_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield generate_demos("metaworld/reach", 2, seed=0)
    mp.undo()


def test_resolve_tasks():
    assert resolve_tasks("metaworld/push-v3") == resolve_tasks("metaworld/push") == ["push-v3"]
    assert resolve_tasks("metaworld/push, metaworld/reach,metaworld/push") == ["push-v3", "reach-v3"]
    assert len(resolve_tasks("metaworld/MT10")) == 10
    groups = resolve_tasks("metaworld/medium,metaworld/hard,metaworld/very_hard")
    assert len(groups) == 22 and len(set(groups)) == 22
    assert "stick-pull-v3" in resolve_tasks("metaworld/very_hard")
    for bad in ("metaworld/pushh", "metaworld/push,nope", ""):
        with pytest.raises(ValueError, match="metaworld/<task>"):
            resolve_tasks(bad)


def _layout(env, seed):
    obs = env.reset(seed=seed)[0]
    return np.concatenate([obs[:18], obs[36:]])  # hand, objects and goal


def test_layouts_reproducible_and_disjoint():
    env, other = make_env("push", seed=123), make_env("push", seed=7)
    np.testing.assert_array_equal(_layout(env, 5), _layout(other, 5))
    assert not np.allclose(_layout(env, 5), _layout(env, 6))
    assert set(demo_seeds(0, 50)).isdisjoint(eval_seeds(0, 50))
    demo = np.stack([_layout(env, s) for s in demo_seeds(0, 10)])
    evals = np.stack([_layout(env, s) for s in eval_seeds(0, 10)])
    goals_differ = np.abs(demo[:, None, -3:] - evals[None, :, -3:]).max(-1) > 1e-6
    assert goals_differ.all()
    with pytest.raises(ValueError, match="seed"):
        demo_seeds(500, 20)             # would reach RL's training layouts
    with pytest.raises(ValueError, match="at most 1000 demonstration attempts"):
        demo_seeds(0, 1001)             # would take seed 1's demonstrations
    with pytest.raises(ValueError, match="num_episodes: expected at most 333 demonstrations"):
        generate_demos("metaworld/reach", 334)


def test_seeds_draw_disjoint_demonstrations_and_evaluations():
    assert demo_seeds(0, 30) == list(range(30)) and eval_seeds(0, 3) == [1_000_000, 1_000_001, 1_000_002]
    demos = [set(demo_seeds(s, 1000)) for s in (0, 1, 2, 499)]
    evals = [set(eval_seeds(s, 1000)) for s in (0, 1, 2, 499)]
    for i, a in enumerate(demos + evals):
        for b in (demos + evals)[i + 1:]:
            assert a.isdisjoint(b)


def test_episode_cap_raises():
    env = make_env("reach", seed=0)
    env.reset(seed=0)
    for _ in range(MAX_EPISODE_STEPS):
        env.step(np.zeros(4))
    with pytest.raises(ValueError):
        env.step(np.zeros(4))


def test_demos_layout_and_dataset(reach_demos):
    root = reach_demos
    assert root.name == "reach-v3-n2-s0" and root.parent.name == "metaworld"
    assert sorted(p.name for p in (root / "data" / "chunk-000").iterdir()) == ["file-000.parquet"]
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 2 and info["features"]["observation.state"]["shape"] == [39]
    assert info["features"]["action"]["shape"] == [4] and info["fps"] == 80.0
    assert info["codebase_version"] == "v3.0" and info["env"] == "metaworld"
    assert pq.read_table(root / "meta" / "tasks.parquet")["__index_level_0__"].to_pylist() == ["reach-v3"]
    table = pq.read_table(root / "data" / "chunk-000" / "file-000.parquet")
    for column in ("observation.state", "action", "episode_index", "frame_index", "timestamp", "task_index", "next.success", "next.reward"):
        assert column in table.column_names
    assert table["next.success"].to_pylist()[-1]
    assert generate_demos("metaworld/reach", 2, seed=0) == root  # cached
    assert info["source"]["first_layout"] == 0

    ds = load_dataset(root)
    assert ds.num_episodes == 2 and ds.states.shape == (info["total_frames"], 39) and ds.actions.shape[1] == 4
    assert np.abs(ds.actions).max() <= 1.0
    for stats, dim in ((ds.stats["observation.state"], 39), (ds.stats["action"], 4)):
        assert all(stats[k].shape == (dim,) for k in ("mean", "std", "min", "max"))
    state_std = ds.stats["observation.state"]["std"]
    assert state_std.min() == pytest.approx(1e-2)  # constant dims (e.g. unused object slots) floored


def test_demo_cache_from_before_the_seed_stride_is_regenerated(tmp_path):
    old = generate_demos("metaworld/reach", 2, seed=1, cache_dir=tmp_path)
    info_path = old / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    assert info["source"]["first_layout"] == 1000
    first = pq.read_table(old / "data" / "chunk-000" / "file-000.parquet")["observation.state"].to_pylist()[0]
    del info["source"]["first_layout"]                  # as written when seed 1 began at layout 1
    info_path.write_text(json.dumps(info))
    fresh = generate_demos("metaworld/reach", 2, seed=1, cache_dir=tmp_path)
    assert json.loads((fresh / "meta" / "info.json").read_text())["source"]["first_layout"] == 1000
    again = pq.read_table(fresh / "data" / "chunk-000" / "file-000.parquet")["observation.state"].to_pylist()[0]
    assert again == first
    np.testing.assert_allclose(first, make_env("reach", seed=0).reset(seed=1000)[0], atol=1e-5)
    # seed 0's caches began at layout 0 under both rules: kept
    zero = generate_demos("metaworld/reach", 2, seed=0, cache_dir=tmp_path)
    info0 = json.loads((zero / "meta" / "info.json").read_text())
    del info0["source"]["first_layout"]
    (zero / "meta" / "info.json").write_text(json.dumps(info0))
    episode = zero / "data" / "chunk-000" / "file-000.parquet"
    mtime = episode.stat().st_mtime_ns
    assert generate_demos("metaworld/reach", 2, seed=0, cache_dir=tmp_path) == zero
    assert episode.stat().st_mtime_ns == mtime


def test_noisy_demos_record_the_clean_expert_action(reach_demos):
    """DART: the env executes perturbed actions, so the states leave the clean rollout's path,
    while every recorded action is the expert's own action at the recorded state."""
    noisy_root = generate_demos("metaworld/reach", 2, seed=0, cache_dir=reach_demos.parents[1], action_noise=0.2)
    assert noisy_root.name == "reach-v3-n2-s0-dart0.2" and noisy_root.parent == reach_demos.parent
    info = json.loads((noisy_root / "meta" / "info.json").read_text())
    assert info["source"]["action_noise"] == 0.2 and info["features"][CONTINUATION]["shape"] == [LOOKAHEAD, 4]
    noisy, clean = load_dataset(noisy_root), load_dataset(reach_demos)
    expert = expert_policy("reach")
    np.testing.assert_allclose(expert(noisy.states), noisy.actions, atol=1e-6)
    np.testing.assert_allclose(expert(clean.states), clean.actions, atol=1e-6)
    n = 5
    np.testing.assert_array_equal(noisy.states[0], clean.states[0])      # the same layout ...
    assert np.abs(noisy.states[1:n, :3] - clean.states[1:n, :3]).max() > 1e-4   # ... a perturbed hand path
    assert clean.continuations is None
    for bad in (-0.1, 2.0, float("nan")):
        with pytest.raises(ValueError, match="action_noise"):
            generate_demos("metaworld/reach", 2, seed=0, action_noise=bad)


def test_noisy_demos_store_the_clean_continuation_as_chunk_targets(reach_demos):
    """Frame 0 of a noisy episode has seen no noise yet, so its continuation is the clean
    episode of the same layout; later frames' continuations are not the (noisy) frames that
    follow them; chunks are cut from the continuations."""
    noisy = load_dataset(generate_demos("metaworld/reach", 2, seed=0, cache_dir=reach_demos.parents[1],
                                        action_noise=0.2))
    clean = load_dataset(reach_demos)
    assert noisy.continuations.shape == (noisy.num_frames, LOOKAHEAD, 4)
    np.testing.assert_array_equal(noisy.continuations[:, 0], noisy.actions)
    k = min(LOOKAHEAD, int(clean.episode_lengths[0]))
    np.testing.assert_allclose(noisy.continuations[0, :k], clean.actions[:k], atol=1e-5)
    following = noisy.actions[1:16]
    assert np.abs(noisy.continuations[:15, 1] - following).max() > 1e-3
    chunks = ChunkDataset(noisy, horizon=8)
    item = chunks[5]
    assert torch.equal(item["actions"], torch.from_numpy(noisy.continuations[5, :8])) and not item["action_is_pad"].any()
    assert ChunkDataset(noisy.select([1]), 8)[0]["actions"].shape == (8, 4)
    with pytest.raises(ValueError, match="horizon"):
        ChunkDataset(noisy, horizon=LOOKAHEAD + 1)
    with pytest.raises(ValueError, match="continuation"):
        concat_datasets([noisy, clean])


def test_demos_recorded_with_executed_labels_keep_the_noisy_action_that_moved_the_env(reach_demos, tmp_path):
    """action_label="executed": the same noise stream as DART's (the same states), but each recorded action is
    the executed one, the expert's plus the noise, and no continuation is stored."""
    from action_decoder.data.demos import record_demos

    dart = load_dataset(generate_demos("metaworld/reach", 2, seed=0, cache_dir=reach_demos.parents[1],
                                       action_noise=0.2))
    root = record_demos("metaworld/reach", 2, tmp_path / "exec", seed=0, action_noise=0.2, action_label="executed")
    executed = load_dataset(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["source"]["action_label"] == "executed" and executed.continuations is None
    np.testing.assert_allclose(executed.states, dart.states, atol=1e-2)    # DART's continuations rewind the env
    noise = executed.actions - dart.actions                                  # clipped to [-1, 1] where it went past
    inside = np.abs(dart.actions + noise) < 1 - 1e-6
    assert 0.17 < noise[inside].std() < 0.23 and np.abs(executed.actions).max() <= 1.0
    # The next state follows the recorded action: replaying it from the same state reproduces the episode.
    env = make_env("reach", seed=0)
    env.reset(seed=int(info["source"]["first_layout"]))
    n = int(executed.episode_lengths[0])
    replay = [env.step(a.astype(np.float32))[0] for a in executed.actions[:n - 1]]
    np.testing.assert_allclose(np.stack(replay), executed.states[1:n], atol=1e-5)
    env.reset(seed=int(info["source"]["first_layout"]))                    # DART's clean labels do not replay
    replay = [env.step(a.astype(np.float32))[0] for a in dart.actions[:n - 1]]
    assert np.abs(np.stack(replay) - dart.states[1:n]).max() > 1e-2
    env.close()
    for label, noise_std, want in (("executed", 0.0, "needs --action-noise > 0, got --action-noise 0.0"),
                                   ("clean", 0.2, "expected one of ['expert', 'executed'], got 'clean'")):
        with pytest.raises(ValueError, match=re.escape(f"--action-label: ") + ".*" + re.escape(want)):
            record_demos("metaworld/reach", 1, tmp_path / label, action_noise=noise_std, action_label=label)
        assert not (tmp_path / label).exists()


def test_saved_state_rewinds_the_env_exactly():
    env, expert = make_env("pick-place", seed=0), expert_policy("pick-place")
    obs = env.reset(seed=4)[0]
    for _ in range(20):
        obs = env.step(expert(obs))[0]
    saved = save_state(env)
    ahead = [env.step(expert(obs))[0]]
    for _ in range(10):                                   # a detour the rewind must undo
        ahead.append(env.step(np.ones(4, np.float32))[0])
    restore_state(env, saved)
    again = env.step(expert(obs))[0]
    np.testing.assert_allclose(again, ahead[0], atol=1e-9)
    assert env.unwrapped.curr_path_length == 21


def test_chunk_padding_at_episode_end(reach_demos):
    ds = load_dataset(reach_demos)
    chunks = ChunkDataset(ds, horizon=8)
    length = int(ds.episode_lengths[0])
    last = chunks[length - 3]
    expected = torch.from_numpy(ds.actions[[length - 3, length - 2, length - 1] + [length - 1] * 5])
    assert torch.equal(last["actions"], expected)
    assert last["action_is_pad"].tolist() == [False] * 3 + [True] * 5
    first_of_next = chunks[length]
    assert torch.equal(first_of_next["state"], torch.from_numpy(ds.states[length]))
    assert not first_of_next["action_is_pad"].any() and first_of_next["task_index"] == 0
    batch = next(iter(torch.utils.data.DataLoader(chunks, batch_size=4)))
    assert batch["state"].shape == (4, 39) and batch["actions"].shape == (4, 8, 4) and batch["action_is_pad"].dtype == torch.bool
    assert len(ChunkDataset(ds, 8, episodes=1)) == length


def test_multitask_concat(reach_demos):
    ds = load_dataset(reach_demos)
    other = EpisodeDataset(ds.states, ds.actions, ds.task_index, ds.episode_lengths, ["push-v3"], ds.fps)
    both = concat_datasets([ds, other, ds.select(1)])
    assert both.tasks == ["reach-v3", "push-v3"] and both.num_episodes == 5
    chunks = ChunkDataset(both, horizon=4)
    assert chunks[ds.num_frames]["task_index"] == 1 and chunks[-1]["task_index"] == 0


def test_load_demos_multitask(reach_demos, monkeypatch):
    monkeypatch.setenv("ACTION_DECODER_CACHE", str(reach_demos.parents[1]))
    ds = load_demos("metaworld/reach,metaworld/push", 2, seed=0)
    assert ds.tasks == ["reach-v3", "push-v3"] and ds.num_episodes == 4
    assert ds.task_index[: ds.episode_lengths[:2].sum()].max() == 0 and ds.task_index[-1] == 1


def test_stats_floor():
    stats = compute_stats({"x": np.array([[1.0, 0.0], [1.0, 2.0]])})["x"]
    np.testing.assert_allclose(stats["std"], [1e-2, 1.0])
    np.testing.assert_allclose(stats["min"], [1.0, 0.0])


def _write_tiny(root, actions):
    episode = {"observation.state": np.zeros((len(actions), 3)), "action": actions, "task_index": 0,
               "next.reward": np.zeros(len(actions)), "next.success": np.zeros(len(actions), bool)}
    write_episodes(root, [episode, episode], ["t"], fps=10)


def test_load_dataset_rejects_nan_and_missing(tmp_path):
    bad = np.ones((5, 2))
    bad[3, 1] = np.nan
    _write_tiny(tmp_path / "nan", bad)
    with pytest.raises(ValueError, match=r"'action'.*episode 0"):
        load_dataset(tmp_path / "nan")
    with pytest.raises(ValueError, match="parquet"):
        load_dataset(tmp_path / "empty")
    _write_tiny(tmp_path / "ok", np.ones((5, 2)))
    path = tmp_path / "ok" / "data" / "chunk-000" / "file-000.parquet"
    pq.write_table(pq.read_table(path).drop(["action"]), path)
    with pytest.raises(ValueError, match="missing column.*'action'"):
        load_dataset(tmp_path / "ok")


def test_empty_episode_file_is_named(tmp_path):
    _write_tiny(tmp_path / "ds", np.ones((5, 2)))
    path = tmp_path / "ds" / "data" / "chunk-000" / "file-000.parquet"
    pq.write_table(pq.read_table(path).slice(0, 0), path)        # the columns, no frames
    with pytest.raises(ValueError, match=r"file-000\.parquet: expected an episode with at least one frame"):
        load_dataset(tmp_path / "ds")


@pytest.mark.parametrize("name, content", [("info.json", "\x00garbage"), ("info.json", "[1, 2]"),
                                           ("tasks.parquet", "not parquet\n"),
                                           ("episodes/chunk-000/file-000.parquet", "not parquet\n")])
def test_garbage_metadata_names_the_file(tmp_path, name, content):
    _write_tiny(tmp_path / "ds", np.ones((5, 2)))
    (tmp_path / "ds" / "meta" / name).write_text(content)
    with pytest.raises(ValueError, match=rf"meta/{name}: expected") as err:
        load_dataset(tmp_path / "ds")
    assert "\n" not in str(err.value)


def test_evaluate_expert_and_zero_policy():
    expert = expert_policy("metaworld/reach")
    done = []
    result = evaluate(lambda s, t: expert(s)[:, None], "metaworld/reach", episodes=2, seed=0,
                      n_action_steps=1, progress=lambda i, n, ep, ok: done.append(i))
    assert result["success_rate"] == 1.0 and done == [1, 2]
    assert result["seeds"] == eval_seeds(0, 2) and max(result["lengths"]) < 500
    zero = evaluate(lambda s, t: np.zeros((len(s), 8, 4)), "metaworld/reach", episodes=2, n_action_steps=8, max_steps=100)
    assert zero["success_rate"] == 0.0 and zero["lengths"] == [100, 100]
    again = evaluate(lambda s, t: expert(s)[:, None], "metaworld/reach", episodes=3, n_action_steps=1, num_envs=2)
    assert again["lengths"][:2] == result["lengths"] and again["returns"][:2] == result["returns"]  # env reuse, num_envs
    with pytest.raises(ValueError, match="policy_fn output"):
        evaluate(lambda s, t: np.zeros((len(s), 2, 4)), "metaworld/reach", episodes=1, n_action_steps=4)


def test_actions_in_metres_reach_the_decoder_at_unit_scale_and_constant_ones_stay_finite():
    from action_decoder.data import EpisodeDataset

    rng = np.random.default_rng(0)
    actions = rng.normal(0, [0.003, 0.005, 0.5, 0.0], (400, 4)).astype(np.float32)      # last dim constant
    states = np.column_stack([rng.normal(0, 1, 400), np.full(400, 0.7)]).astype(np.float32)
    ds = EpisodeDataset(states, actions, np.zeros(400, np.int64), np.array([200, 200]), ["t"], 10)
    std = ds.stats["action"]["std"]
    np.testing.assert_allclose((actions[:, :3] - ds.stats["action"]["mean"][:3]).std(0) / std[:3], 1.0, rtol=1e-4)
    assert std[3] == pytest.approx(1e-2)                          # a constant dimension takes STD_FLOOR
    assert ds.stats["observation.state"]["std"][1] == pytest.approx(1e-2)     # states keep STD_FLOOR
