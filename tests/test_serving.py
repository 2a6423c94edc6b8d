"""`action-decoder serve`'s bookkeeping (`action_decoder.serving`), without LeRobot: timesteps of a
chunk, the committed prefix it continues, the delay in control steps, and the CLI's one line
where LeRobot's async stack is missing. The server against LeRobot's own client:
tests/test_serve_lerobot.py."""

import sys

import pytest

from action_decoder.cli import main
from action_decoder.serving import (SERVER_MODULE, ChunkPlan, ServeConfig, check_serve_config, chunk_timing,
                                    control_rate, delay_steps, expected_latency, plan_chunk, rate_mismatch,
                                    should_predict)


@pytest.mark.parametrize("seconds, fps, steps", [(0.0, 30, 0), (0.010, 30, 1), (1 / 30, 30, 1), (0.034, 30, 2),
                                                  (0.1, 10, 1), (0.25, 50, 13), (2.0, 30, 60)])
def test_delay_steps_rounds_latency_up_to_whole_control_periods(seconds, fps, steps):
    assert delay_steps(seconds, fps) == steps


@pytest.mark.parametrize("seconds, fps", [(-0.1, 30), (float("nan"), 30), (0.1, 0), (0.1, -5), (0.1, float("inf"))])
def test_delay_steps_refuses_bad_latency_or_rate(seconds, fps):
    with pytest.raises(ValueError, match="seconds|fps"):
        delay_steps(seconds, fps)


def test_expected_latency_counts_the_round_trip_the_wait_and_the_slowest_recent_compute():
    assert expected_latency(0.002, 0.001, []) == pytest.approx(0.005)
    assert expected_latency(0.002, 0.001, [0.03, 0.05, 0.04]) == pytest.approx(0.055)
    # only the last `window` computes count; a clock skew that makes the uplink negative counts as 0
    assert expected_latency(-0.5, 0.0, [0.9] + [0.01] * 10, window=10) == pytest.approx(0.01)


def test_first_chunk_after_connecting_starts_at_the_observation_and_continues_nothing():
    assert plan_chunk(0, None, 0, delay=3, horizon=16) == ChunkPlan(start=0)
    assert plan_chunk(7, None, 0, delay=3, horizon=16) == ChunkPlan(start=7)


def test_next_chunk_starts_after_the_executed_action_and_commits_the_delay():
    # previous chunk: timesteps 6..17 (12 rows sent); the client executed #9 when it observed
    plan = plan_chunk(9, prev_start=6, prev_sent=12, delay=3, horizon=16)
    assert plan == ChunkPlan(start=10, prev_from=4, overlap=8, delay=3)
    # the new chunk's rows 0..2 are the previous chunk's rows 4..6: timesteps 10, 11, 12
    assert [plan.start + j for j in range(plan.delay)] == [6 + plan.prev_from + j for j in range(plan.delay)]


def test_committed_rows_are_capped_by_what_the_client_holds_and_by_the_horizon():
    # 2 rows of the previous chunk left: only they can be executed while the next is computed
    assert plan_chunk(15, prev_start=6, prev_sent=12, delay=5, horizon=16) == ChunkPlan(16, 10, 2, 2)
    # the previous chunk is used up, or the observation is older than it: nothing to continue
    assert plan_chunk(17, prev_start=6, prev_sent=12, delay=5, horizon=16) == ChunkPlan(start=18)
    assert plan_chunk(2, prev_start=6, prev_sent=12, delay=5, horizon=16) == ChunkPlan(start=3)
    # a delay as long as the chunk leaves the new chunk one row of its own
    assert plan_chunk(5, prev_start=6, prev_sent=16, delay=40, horizon=16) == ChunkPlan(6, 0, 16, 15)
    assert plan_chunk(9, prev_start=6, prev_sent=12, delay=0, horizon=16).delay == 0


@pytest.mark.parametrize("args", [(-1, None, 0, 0, 16), (1, 0, 4, -2, 16), (1, 0, 4, 1, 0), (1.5, 0, 4, 1, 16),
                                  (True, 0, 4, 1, 16)])
def test_plan_chunk_refuses_bad_integers(args):
    with pytest.raises(ValueError, match="obs_timestep|prev_sent|delay|horizon"):
        plan_chunk(*args)


def test_chunk_timing_labels_consecutive_timesteps_one_period_apart():
    timing = chunk_timing(100.0, 9, 10, 3, 20.0)
    assert [step for _, step in timing] == [10, 11, 12]
    assert [ts for ts, _ in timing] == pytest.approx([100.05, 100.10, 100.15])
    assert chunk_timing(5.0, 0, 0, 2, 10.0) == [(5.0, 0), (pytest.approx(5.1), 1)]


def test_control_rate_is_the_median_step_rate_over_observations_that_advanced():
    assert control_rate([]) is None and control_rate([(0.0, 0)]) is None
    assert control_rate([(0.0, 3), (0.5, 3)]) is None                 # the client executed nothing between them
    # one observation per control step at 20 Hz, a stall (same timestep) and a late one (2 steps in 0.1 s)
    samples = [(0.0, 0), (0.05, 1), (0.10, 2), (0.30, 2), (0.35, 3), (0.45, 5), (0.50, 6)]
    assert control_rate(samples) == pytest.approx(20.0)
    assert control_rate([(0.0, 0), (0.1, 1), (0.3, 2)]) == pytest.approx(7.5)    # median of 10 and 5


def test_rate_mismatch_flags_rates_a_quarter_away_from_fps():
    assert not rate_mismatch(None, 30) and not rate_mismatch(28.0, 30) and not rate_mismatch(37.4, 30)
    assert rate_mismatch(15.0, 30) and rate_mismatch(40.0, 30)


def test_should_predict_newer_observations_and_those_that_must_go():
    assert should_predict(0, False, None)
    assert should_predict(5, False, 4) and not should_predict(4, False, 4) and not should_predict(3, False, 4)
    assert should_predict(4, True, 4)


@pytest.mark.parametrize("over, word", [({"port": 0}, "--port"), ({"port": 70000}, "--port"), ({"fps": 0}, "--fps"),
                                        ({"delay": -1}, "--delay"), ({"steps": 0}, "--steps"),
                                        ({"obs_timeout": 0}, "--obs-timeout"),
                                        ({"checkpoint": "/nonexistent/ckpt"}, "--checkpoint")])
def test_serve_options_out_of_range_give_one_line(tmp_path, over, word):
    cfg = ServeConfig(checkpoint=str(tmp_path), **{k: v for k, v in over.items() if k != "checkpoint"})
    if "checkpoint" in over:
        cfg.checkpoint = over["checkpoint"]
    with pytest.raises(ValueError, match=word):
        check_serve_config(cfg)


def test_serve_without_lerobot_names_what_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.delitem(sys.modules, SERVER_MODULE, raising=False)
    monkeypatch.setitem(sys.modules, "grpc", None)          # as where grpcio (LeRobot's async extra) is missing
    assert main(["serve", "--checkpoint", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "serve: needs LeRobot's async inference" in err[0] and "pip install" in err[0], err
