"""Perturbed committed prefixes (`data.perturbed_prefixes`): how the prefixes are drawn, that recorded labels
are the prefix then the scripted expert from where it leads (checked by replay in a fresh env), and the
options of `record` and `train` that ask for them."""

import json

import numpy as np
import pytest

from action_decoder.data.perturbed_prefixes import PerturbedPrefixes, perturbed_labels


def test_prefixes_are_the_experts_actions_shifted_then_noised_and_labelled_by_the_continuation():
    rng = np.random.default_rng(0)
    past = np.linspace(-0.5, 0.5, 6 * 2, dtype=np.float32).reshape(6, 2)           # [t = 6, D = 2]
    plan = np.linspace(0.6, 0.9, 8 * 2, dtype=np.float32).reshape(8, 2)            # [L = 8, D]
    seq = np.concatenate([past, plan])
    seen_d, seen_shift = set(), set()
    for _ in range(200):
        (label, d), = perturbed_labels(past, plan, PerturbedPrefixes(1, 3, noise=0.0, shift=2), rng,
                                       lambda prefix: np.concatenate([prefix, np.full((5, 2), 7.0)]))
        assert 1 <= d <= 3 and label.shape == (d + 5, 2) and (label[d:] == 7.0).all()
        starts = [o for o in range(-2, 3) if np.array_equal(label[:d], seq[6 + o:6 + o + d])]
        assert starts, (label[:d], d)                   # a window of the expert's actions, shifted by at most 2
        seen_d.add(d), seen_shift.update(starts)
    assert seen_d == {1, 2, 3} and seen_shift == {-2, -1, 0, 1, 2}
    # No shift, noise σ: the prefix is the plan's first rows plus N(0, σ²) (these rows stay inside [-1, 1]).
    prefixes = [p for p, _ in perturbed_labels(past, plan, PerturbedPrefixes(4000, 1, noise=0.05, shift=0), rng,
                                                lambda prefix: prefix)]
    noise = np.stack(prefixes)[:, 0] - plan[0]
    assert abs(noise.mean()) < 0.004 and abs(noise.std() - 0.05) < 0.003
    # Near the ends the shifted window takes the nearest action; noise is clipped to the action range.
    (label, d), = perturbed_labels(past[:0], plan[:1], PerturbedPrefixes(1, 4, noise=1.0, shift=3),
                                   np.random.default_rng(1), lambda prefix: prefix)
    assert np.abs(label).max() <= 1.0 and label.shape == (d, 2)


@pytest.mark.parametrize("kwargs, words", [
    ({"copies": 0}, "--perturbed-prefixes: expected an integer >= 1, got 0"),
    ({"max_delay": 0}, "--rtc-max-delay: expected an integer >= 1, got 0"),
    ({"shift": -1}, "--perturbed-prefix-shift: expected an integer >= 0, got -1"),
    ({"noise": 1.5}, "--perturbed-prefix-noise: expected a standard deviation in [0, 1]"),
    ({"noise": float("nan")}, "--perturbed-prefix-noise: expected a standard deviation in [0, 1]"),
])
def test_bad_perturbation_settings_are_refused_in_one_line(kwargs, words):
    with pytest.raises(ValueError, match=None) as err:
        PerturbedPrefixes(**{"copies": 2, "max_delay": 4, **kwargs})
    assert words in str(err.value) and "\n" not in str(err.value)


def test_recorded_copies_are_the_prefix_then_the_expert_from_where_it_leads():
    pytest.importorskip("metaworld")
    from action_decoder.data.demos import LOOKAHEAD, record_episodes
    from action_decoder.envs.metaworld_tasks import expert_policy, make_env

    spec = PerturbedPrefixes(2, 3, noise=0.3, shift=1)
    episodes, _, source = record_episodes("metaworld/reach", 1, seed=0, prefixes=spec)
    plain, _, _ = record_episodes("metaworld/reach", 1, seed=0)
    assert source["perturbed_prefixes"] == {"copies": 2, "max_delay": 3, "noise": 0.3, "shift": 1}
    base, copies = episodes[0], episodes[1:]
    assert len(copies) == 2
    # The demonstration is recorded as without them, up to the rounding that rewinding the simulator after
    # every label leaves in contacts (as DART's continuations do) ...
    for key in ("observation.state", "action"):
        np.testing.assert_allclose(base[key], plain[0][key], atol=1e-2)
    n = len(base["action"])
    # ... with its own next actions as its labels (the last one held) and no committed rows.
    np.testing.assert_array_equal(base["action.continuation"][:, 0], base["action"])
    np.testing.assert_array_equal(base["action.continuation"][-1], np.repeat(base["action"][-1:], LOOKAHEAD, 0))
    assert (base["action.prefix_length"] == 0).all()
    expert = expert_policy("reach-v3")
    for copy in copies:
        np.testing.assert_array_equal(copy["observation.state"], base["observation.state"])
        assert copy["seed"] == base["seed"] and copy["action.continuation"].shape == (n, LOOKAHEAD, 4)
        assert set(copy["action.prefix_length"].tolist()) <= {1, 2, 3}
        np.testing.assert_array_equal(copy["action"], copy["action.continuation"][:, 0])
        for t in (0, n // 2, n - 1):
            label, d = copy["action.continuation"][t], int(copy["action.prefix_length"][t])
            # A fresh env replays the demonstration to frame t, executes the prefix, then asks the expert.
            env = make_env("reach-v3", 0)
            obs = env.reset(seed=base["seed"])[0]
            for a in base["action"][:t]:
                obs = env.step(a)[0]
            np.testing.assert_allclose(obs, base["observation.state"][t], atol=1e-2)    # the rewinds' rounding
            for a in label[:d]:
                obs = env.step(a)[0]
            for a in label[d:d + 6]:
                np.testing.assert_allclose(a, expert(obs), atol=1e-4)      # reach's expert reads the hand, not the puck
                obs = env.step(a)[0]
            # The prefix is the expert's actions near frame t (within the shift), noised.
            near = np.concatenate([base["action"][max(t - 1, 0):t + 1 + d], base["action"][-1:]])
            assert np.abs(label[:d, None] - near[None]).min(axis=1).max() < 4 * 0.3 + 1e-6


def test_train_resolves_them_with_rtc_on_generated_demos_and_refuses_them_elsewhere(tmp_path):
    from action_decoder.train import PERTURBED_PREFIX_COPIES, TrainConfig, perturbed_prefixes

    assert perturbed_prefixes(TrainConfig()) is None
    assert perturbed_prefixes(TrainConfig(rtc_max_delay=4)) == PerturbedPrefixes(3, 4)          # flow matching
    assert PERTURBED_PREFIX_COPIES == {"flow_matching": 3, "mean_flow": 0}
    assert perturbed_prefixes(TrainConfig(decoder="mean_flow", rtc_max_delay=4)) is None
    assert perturbed_prefixes(TrainConfig(decoder="mean_flow", rtc_max_delay=4, perturbed_prefixes=2)) == \
        PerturbedPrefixes(2, 4)
    assert perturbed_prefixes(TrainConfig(rtc_max_delay=2, perturbed_prefixes=0)) is None
    assert perturbed_prefixes(TrainConfig(rtc_max_delay=2, perturbed_prefixes=1, perturbed_prefix_noise=0.5,
                                          perturbed_prefix_shift=0)) == PerturbedPrefixes(1, 2, 0.5, 0)
    assert perturbed_prefixes(TrainConfig(dataset=str(tmp_path), rtc_max_delay=4)) is None   # taken as it is
    for cfg, words in (
            (TrainConfig(perturbed_prefixes=2), "--perturbed-prefixes: training-time real-time chunking data, "
                                                "expected with --rtc-max-delay N > 0"),
            (TrainConfig(rtc_max_delay=4, perturbed_prefixes=-1), "--perturbed-prefixes: expected an integer >= 0"),
            (TrainConfig(dataset=str(tmp_path), rtc_max_delay=4, perturbed_prefixes=3),
             "--perturbed-prefixes 3: perturbed prefixes are recorded with the simulator's expert"),
            (TrainConfig(perturbed_prefix_shift=3), "--perturbed-prefix-shift 3: shapes perturbed prefixes, and this "
                                                    "run has none"),
            (TrainConfig(rtc_max_delay=4, perturbed_prefix_noise=2.0), "--perturbed-prefix-noise: expected a "
                                                                       "standard deviation in [0, 1]")):
        with pytest.raises(ValueError) as err:
            perturbed_prefixes(cfg)
        assert words in str(err.value) and "\n" not in str(err.value), str(err.value)


def test_cli_record_with_perturbed_prefixes_then_train_on_them(tmp_path, monkeypatch, capsys):
    pytest.importorskip("metaworld")
    from action_decoder import cli
    from action_decoder.data import load_dataset

    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))
    out = tmp_path / "demos"
    assert cli.main(["record", "--task", "metaworld/reach", "--demos", "1", "--output-dir", str(out),
                     "--perturbed-prefixes", "2", "--rtc-max-delay", "3"]) == 0
    printed = capsys.readouterr().out
    assert "recorded 1 demonstrations and 2 perturbed-prefix copies (" in printed, printed
    data = load_dataset(out)
    assert data.num_episodes == 3 and 1 <= data.prefix_lengths.max() <= 3
    source = json.loads((out / "meta" / "info.json").read_text())["source"]
    assert source["perturbed_prefixes"] == {"copies": 2, "max_delay": 3, "noise": 0.2, "shift": 2}
    train = ["train", "--dataset", str(out), "--decoder", "flow_matching", "--steps", "2", "--batch-size", "8",
             "--hidden-size", "32", "--num-layers", "1", "--eval-episodes", "0", "--no-progress",
             "--state-layout", "metaworld"]
    assert cli.main(train + ["--rtc-max-delay", "3", "--output-dir", str(tmp_path / "run")]) == 0
    # Bad input: one line naming the option; nothing written.
    for args, words in ((["--perturbed-prefix-shift", "3"], "--perturbed-prefix-shift 3: shapes perturbed prefixes, "
                                                            "which are recorded with --perturbed-prefixes N > 0"),
                        (["--perturbed-prefixes", "2", "--rtc-max-delay", "0"], "--rtc-max-delay: expected an integer "
                                                                                ">= 1, got 0")):
        capsys.readouterr()
        assert cli.main(["record", "--task", "metaworld/reach", "--demos", "1", "--output-dir",
                         str(tmp_path / "bad")] + args) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and words in err, err
        assert not (tmp_path / "bad").exists()
    capsys.readouterr()
    assert cli.main(train + ["--rtc-max-delay", "3", "--perturbed-prefixes", "1",
                             "--output-dir", str(tmp_path / "run2")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "record them into a dataset with `action-decoder record --perturbed-prefixes" in err


def test_a_run_that_predates_them_resumes_only_with_them_off():
    from dataclasses import asdict

    from action_decoder.train import TrainConfig, resume_conflicts

    old = {k: v for k, v in asdict(TrainConfig(rtc_max_delay=4)).items() if k != "perturbed_prefixes"}
    assert resume_conflicts(old, TrainConfig(rtc_max_delay=4)) == ["--perturbed-prefixes: 0 → 3"]
    assert resume_conflicts(old, TrainConfig(rtc_max_delay=4, perturbed_prefixes=0)) == []
    # A run saves them resolved, and resumes with the default that resolved them.
    saved = {**asdict(TrainConfig(rtc_max_delay=4)), "perturbed_prefixes": 3}
    assert resume_conflicts(saved, TrainConfig(rtc_max_delay=4)) == []
