"""Closed-loop relabelling (`data.relabel`, `action-decoder relabel`): labels are the committed prefix
then the scripted expert from the state it reaches, checked by replaying the episode in a fresh env."""

import json

import numpy as np
import pytest

pytest.importorskip("metaworld")

from action_decoder.data.demos import LOOKAHEAD, expert_continuation  # noqa: E402
from action_decoder.data.relabel import relabel_episodes  # noqa: E402
from action_decoder.envs.metaworld_tasks import expert_policy, make_env  # noqa: E402

H, S, D = 8, 3, 2          # chunk length, actions executed per chunk, delay


def stand_in(states, task_index, episode_seeds=None, plan_indices=None, prev_chunks=None, delay=0):
    """A deterministic policy: chunk row j is a fixed function of the state and j."""
    rows = np.arange(H)[None, :, None]                                                   # [1, H, 1]
    return np.tanh(3 * states[:, None, :4] * np.cos(rows + np.arange(4))).astype(np.float32)   # [B, H, 4]


def test_labels_are_the_committed_prefix_then_the_expert_from_where_it_leads():
    episodes, success = relabel_episodes(stand_in, "metaworld/reach", [7, 8], delay=D, n_action_steps=S,
                                         max_steps=14, num_envs=2)
    expert = expert_policy("reach-v3")
    assert [ep["seed"] for ep in episodes] == [7, 8] and 0.0 <= success <= 1.0
    for ep in episodes:
        env = make_env("reach-v3", 0)
        obs, executed, prev = env.reset(seed=ep["seed"])[0], [], None
        assert len(ep["observation.state"]) == 5           # plans at steps 0, 3, 6, 9, 12 of 14
        assert ep["action.prefix_length"].tolist() == [0, D, D, D, D]     # the first plan has no prefix
        for k, (state, label) in enumerate(zip(ep["observation.state"], ep["action.continuation"])):
            np.testing.assert_allclose(state, obs, atol=1e-6)                         # planned from here
            chunk = stand_in(obs[None], np.zeros(1))[0]
            prefix = prev[S:S + D] if prev is not None else chunk[:0]
            np.testing.assert_allclose(label[:len(prefix)], prefix, atol=1e-6)
            # The expert's part: a fresh env replays the episode, then the prefix, then asks the expert.
            replay = make_env("reach-v3", 0)
            o = replay.reset(seed=ep["seed"])[0]
            for a in [*executed, *prefix]:
                o = replay.step(a)[0]
            for a in label[len(prefix):len(prefix) + 5]:
                np.testing.assert_allclose(a, expert(o), atol=1e-5)
                o = replay.step(a)[0]
            assert label.shape == (LOOKAHEAD, 4)
            np.testing.assert_array_equal(ep["action"][k], label[0])
            # What the harness executes until the next plan: the first chunk's rows 0..S+D−1, then
            # each new chunk's rows D..D+S−1 after the D committed ones.
            run = chunk[:S + D] if prev is None else chunk[D:D + S]
            steps = run[:S] if prev is None else [*prefix, *run][:S]
            for a in steps:
                obs = env.step(a)[0]
                executed.append(a)
            prev = chunk


def test_an_empty_prefix_needs_the_observation():
    env = make_env("reach-v3", 0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="an empty prefix needs obs"):
        expert_continuation(env, expert_policy("reach-v3"), np.zeros((0, 4), np.float32))


def test_cli_record_train_relabel_then_train_on_the_aggregate(tmp_path, monkeypatch, capsys):
    from action_decoder import cli
    from action_decoder.data import load_dataset

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))
    demos, out = tmp_path / "demos", tmp_path / "relabelled"
    assert cli.main(["record", "--task", "metaworld/reach", "--demos", "2", "--output-dir", str(demos)]) == 0
    assert cli.main(["train", "--dataset", str(demos), "--decoder", "flow_matching", "--rtc-max-delay", "2",
                     "--steps", "2", "--batch-size", "8", "--hidden-size", "32", "--num-layers", "1",
                     "--eval-episodes", "0", "--no-progress", "--state-layout", "metaworld",
                     "--output-dir", str(tmp_path / "run")]) == 0
    ckpt = str(tmp_path / "run" / "final")
    args = ["relabel", "--checkpoint", ckpt, "--dataset", str(demos), "--episodes", "1", "--max-steps", "10",
            "--num-envs", "1"]
    capsys.readouterr()
    assert cli.main(args + ["--output-dir", str(out), "--delays", "0", "2"]) == 0
    printed = capsys.readouterr().out
    assert "delay 2 (trained RTC): 1 rollouts" in printed and f"as a LeRobot v3.0 dataset in {out}" in printed
    prior, both = load_dataset(demos), load_dataset(out)
    n = len(prior.actions)
    assert both.num_episodes == 4 and len(both.actions) > n
    np.testing.assert_array_equal(both.states[:n], prior.states)
    np.testing.assert_array_equal(both.actions[:n], prior.actions)
    np.testing.assert_array_equal(both.continuations[:n, 0], prior.actions)       # a demo's own next actions
    assert both.continuations.shape[1:] == (LOOKAHEAD, 4)
    # Committed rows per label: none for the demonstrations and the delay-0 round, 2 after each first plan.
    starts = both.episode_starts
    assert both.prefix_lengths[:starts[3]].tolist() == [0] * starts[3]
    assert both.prefix_lengths[starts[3]:].tolist() == [0] + [2] * (len(both.actions) - starts[3] - 1)
    rounds = json.loads((out / "meta" / "info.json").read_text())["source"]["relabel"][0]["rounds"]
    assert [(r["delay"], r["rtc_mode"], r["layouts"]) for r in rounds] == [(0, "trained", [1000, 1000]),
                                                                           (2, "trained", [1001, 1001])]
    assert cli.main(["train", "--dataset", str(out), "--decoder", "flow_matching", "--rtc-max-delay", "2",
                     "--steps", "2", "--batch-size", "8", "--hidden-size", "32", "--num-layers", "1",
                     "--eval-episodes", "0", "--no-progress", "--state-layout", "metaworld",
                     "--output-dir", str(tmp_path / "run2")]) == 0
    # Bad input: one line naming the option; nothing written.
    for extra, words in ((["--seed", "0"], "--seed: layouts 0..1 of --seed 0 are already episodes"),
                         (["--delays", "5"], "--delays: expected at most --n-action-steps=4"),
                         (["--delays", "2", "2"], "--delays: expected distinct integers >= 0"),
                         (["--n-action-steps", "20"], "--n-action-steps: expected 1..16 (the chunk length), got 20")):
        capsys.readouterr()
        assert cli.main(args + ["--output-dir", str(tmp_path / "bad")] + extra) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, err
        assert not (tmp_path / "bad").exists()
    capsys.readouterr()
    assert cli.main(["train", "--dataset", str(out), "--rtc-max-delay", "1", "--steps", "1", "--eval-episodes", "0",
                     "--output-dir", str(tmp_path / "run4")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--rtc-max-delay: " in err and "committed prefixes of up to 2 rows" in err and \
        err.endswith("expected at least 2, got 1"), err
    assert cli.main(["train", "--dataset", str(out), "--n-obs-steps", "2", "--steps", "1", "--eval-episodes", "0",
                     "--output-dir", str(tmp_path / "run3")]) == 2
    assert "--n-obs-steps: " in capsys.readouterr().err


def test_layout_seeds_replace_the_evaluation_layouts_one_per_episode():
    from action_decoder.envs import evaluate

    res = evaluate(stand_in, "metaworld/reach", episodes=2, n_action_steps=S, max_steps=3, num_envs=2,
                   layout_seeds=[7, 8])
    assert res["seeds"] == [7, 8]
    with pytest.raises(ValueError, match=r"layout_seeds: expected 2 integers >= 0 \(one per episode\)"):
        evaluate(stand_in, "metaworld/reach", episodes=2, layout_seeds=[7])
