"""Real-time chunking: guidance math on analytic flows, the policy's contract, asynchronous evaluation."""

import importlib
import json
import math

import numpy as np
import pytest
import torch

from action_decoder import (ActionDecoderPolicy, DecoderConfig, rtc_weights, sample_meanflow, sample_meanflow_rtc,
                            sample_ode, sample_ode_rtc, sample_sde, sample_sde_rtc)
from action_decoder.envs import evaluate
from action_decoder.envs.evaluate import jerk_stats
from action_decoder.flows import guidance_weight, meanflow_guidance, rtc_guided_velocity
from action_decoder.oracles import Gaussian, GaussianMixture

H, D = 8, 2


def two_modes():
    """Chunks at +1 or −1 everywhere (std 0.1): a naive next chunk picks either mode."""
    return GaussianMixture.make(torch.stack([torch.ones(H, D), -torch.ones(H, D)]), [0.1, 0.1])


def noise(b=16, seed=0, dtype=torch.float64):
    return torch.randn(b, H, D, generator=torch.Generator().manual_seed(seed), dtype=dtype)


# ---------------------------------------------------------------------------- weights
def test_weights_follow_the_papers_exponential_decay():
    w = rtc_weights(2, 6, H)                                                   # d = 2, overlap L = H − s = 6
    c = torch.tensor([(6 - j) / (6 - 2 + 1) for j in range(2, 6)])
    expected = torch.cat([torch.ones(2), c * (torch.exp(c) - 1) / (math.e - 1), torch.zeros(2)])
    torch.testing.assert_close(w, expected)
    assert (w[2:6].diff() < 0).all() and 0 < w[5] < w[2] < 1
    assert torch.equal(rtc_weights(2, 6, H, "zeros"), torch.tensor([1., 1, 0, 0, 0, 0, 0, 0]))
    assert torch.equal(rtc_weights(2, 6, H, "ones"), torch.tensor([1., 1, 1, 1, 1, 1, 0, 0]))
    with pytest.raises(ValueError, match="delay, overlap"):
        rtc_weights(4, 3, H)


def test_guidance_weight_is_the_papers_clipped_form():
    t = torch.tensor([0.0, 0.1, 0.5, 0.9], dtype=torch.float64)
    r2 = (1 - t) ** 2 / (t ** 2 + (1 - t) ** 2)
    raw = (1 - t) / (t * r2)                                                   # inf at t = 0
    torch.testing.assert_close(guidance_weight(t, 5.0), raw.clamp(max=5.0))
    assert guidance_weight(t, 5.0)[0] == 5.0 and guidance_weight(t, 100.0)[2] == 2.0


# ---------------------------------------------------------------------------- the three checks of the issue
def test_zero_delay_and_zero_guidance_equals_the_plain_sampler():
    gm, g = two_modes(), Gaussian(torch.linspace(-1, 1, H * D, dtype=torch.float64).reshape(H, D), 0.3)
    e, prev = noise(), torch.randn(16, 5, D, dtype=torch.float64)
    kw = {"max_guidance_weight": 0.0}
    assert torch.equal(sample_ode_rtc(gm.velocity, e, prev, 0, 10, **kw), sample_ode(gm.velocity, e, 10))
    for k in (1, 2):
        assert torch.equal(sample_meanflow_rtc(g.avg_velocity, e, prev, 0, k, **kw), sample_meanflow(g.avg_velocity, e, k))
    a = sample_sde_rtc(gm.velocity, e, prev, 0, 5, sigma=0.5, generator=torch.Generator().manual_seed(1), **kw)
    b = sample_sde(gm.velocity, e, 5, sigma=0.5, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a.actions, b.actions) and torch.equal(a.chain, b.chain)
    # With guidance on, the result differs (the test above would pass for a sampler that ignores prev).
    assert not torch.allclose(sample_ode_rtc(gm.velocity, e, prev, 0, 10), sample_ode(gm.velocity, e, 10))


@pytest.mark.parametrize("which", ["ode", "sde", "mf1", "mf2"])
def test_frozen_actions_are_reproduced_exactly(which):
    gm, g = two_modes(), Gaussian(torch.zeros(H, D, dtype=torch.float64), 0.5)
    e, prev = noise(dtype=torch.float32), torch.randn(16, 6, D) * 0.3
    out = {"ode": lambda: sample_ode_rtc(gm.velocity, e, prev, 3, 4),
           "sde": lambda: sample_sde_rtc(gm.velocity, e, prev, 3, 4, sigma=0.5).actions,
           "mf1": lambda: sample_meanflow_rtc(g.avg_velocity, e, prev, 3, 1),
           "mf2": lambda: sample_meanflow_rtc(g.avg_velocity, e, prev, 3, 2)}[which]()
    assert out.shape == e.shape and torch.equal(out[:, :3], prev[:, :3])
    assert not torch.equal(out[:, 3:6], prev[:, 3:6])


def _fd_grad(phi, x, h=1e-6):
    grad = torch.zeros_like(x)
    for idx in np.ndindex(*x.shape):
        step = torch.zeros_like(x)
        step[idx] = h
        grad[idx] = (phi(x + step) - phi(x - step)) / (2 * h)
    return grad


def test_guidance_matches_finite_differences_on_analytic_flows():
    """FM: v_guided − v = w(t)·∇_x[−½ Σ_j W_j |Y_j − Â_j(x)|²] with Â = x + (1 − t)·v."""
    gm = two_modes()
    x, y = noise(2, seed=3), torch.randn(2, H, D, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    w = rtc_weights(2, 6, H, dtype=torch.float64)
    t = torch.full((2,), 0.3, dtype=torch.float64)
    phi = lambda x_: -0.5 * (w[:, None] * (y - (x_ + 0.7 * gm.velocity(x_, t))).square()).sum()
    expected = guidance_weight(t, 5.0)[:, None, None] * _fd_grad(phi, x)
    torch.testing.assert_close(rtc_guided_velocity(gm.velocity, y, w, 5.0)(x, t) - gm.velocity(x, t), expected,
                               rtol=1e-6, atol=1e-8)


def test_meanflow_guidance_pulls_the_clean_estimate_by_the_weights():
    """MF: the term is min(β, 1/(1 − t))·W ⊙ (Y − Â), Â = x + (1 − t)·u(x, t, 1); a step to 1 lands on Â + W ⊙ (Y − Â)."""
    g = Gaussian(torch.linspace(-1, 1, H * D, dtype=torch.float64).reshape(H, D), 0.4)
    x, y = noise(2, seed=3), torch.randn(2, H, D, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    w = rtc_weights(2, 6, H, dtype=torch.float64)
    t = torch.tensor([0.0, 0.6], dtype=torch.float64)
    a_hat = x + (1 - t)[:, None, None] * g.avg_velocity(x, t, torch.ones_like(t))
    pull, u1 = meanflow_guidance(g.avg_velocity, x, t, y, w, 2.0)
    torch.testing.assert_close(u1, g.avg_velocity(x, t, torch.ones_like(t)))
    gain = torch.tensor([1.0, 2.0], dtype=torch.float64)                          # 1/(1 − t) = 1, 2.5 → clipped at 2
    torch.testing.assert_close(pull, gain[:, None, None] * w[:, None] * (y - a_hat))
    # One step from 0: the chunk is the guided clean estimate; K = 2 pulls at both steps (2K − 1 = 3 calls).
    e, prev = noise(4, seed=6), torch.randn(4, 6, D, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    y6, w6 = torch.cat([prev, torch.zeros(4, H - 6, D, dtype=torch.float64)], 1), rtc_weights(2, 6, H, dtype=torch.float64)
    plain = sample_meanflow(g.avg_velocity, e, 1)
    torch.testing.assert_close(sample_meanflow_rtc(g.avg_velocity, e, prev, 2, 1),
                               plain + w6[:, None] * (y6 - plain))
    calls = []
    counted = lambda x_, t_, r_: calls.append(float(r_[0])) or g.avg_velocity(x_, t_, r_)
    two = sample_meanflow_rtc(counted, e, prev, 2, 2)
    assert sorted(calls) == [0.5, 1.0, 1.0]
    half = e + 0.5 * g.avg_velocity(e, torch.zeros(4, dtype=e.dtype), torch.full((4,), 0.5, dtype=e.dtype)) \
        + 0.5 * w6[:, None] * (y6 - plain)
    t_half = torch.full((4,), 0.5, dtype=e.dtype)
    a_half = half + 0.5 * g.avg_velocity(half, t_half, torch.ones_like(t_half))
    expected = a_half + w6[:, None] * (y6 - a_half)
    expected[:, :2] = prev[:, :2]
    torch.testing.assert_close(two, expected)


def test_guidance_keeps_the_next_chunk_in_the_previous_chunks_mode():
    """Two modes: a naive chunk picks either; with RTC the overlap follows the previous chunk's mode."""
    gm, g = two_modes(), Gaussian(torch.zeros(H, D, dtype=torch.float64), 1.0)
    e = noise(64, seed=5)
    prev = torch.ones(64, 5, D, dtype=torch.float64)                              # mode +1, d = 2, L = 5
    naive, rtc = sample_ode(gm.velocity, e, 10), sample_ode_rtc(gm.velocity, e, prev, 2, 10)
    assert (naive[:, 4].mean(-1) < 0).float().mean() > 0.3                        # about half go to −1
    assert (rtc[:, 4].mean(-1) > 0).all()                                         # all stay at +1
    # MeanFlow at 1 step: W = 1 over the overlap puts it on Y there; beyond the overlap it is the plain chunk.
    x = sample_meanflow_rtc(g.avg_velocity, e, prev, 2, 1, schedule="ones")
    plain = sample_meanflow(g.avg_velocity, e, 1)
    torch.testing.assert_close(x[:, 2:5], prev[:, 2:5].expand_as(x[:, 2:5]), rtol=0, atol=1e-9)
    assert torch.equal(x[:, 5:], plain[:, 5:])


# ---------------------------------------------------------------------------- the policy
def tiny(decoder_type="flow_matching", **kw):
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type=decoder_type, state_dim=6, action_dim=3, action_chunk_size=8, hidden_size=32,
                        num_hidden_layers=1, num_inference_timesteps=2, **kw)
    stats = {"state": {"mean": torch.zeros(6), "std": torch.ones(6), "min": -torch.ones(6), "max": torch.ones(6)},
             "actions": {"mean": torch.full((3,), 0.5), "std": torch.full((3,), 2.0), "min": -torch.ones(3),
                         "max": torch.ones(3)}}
    return ActionDecoderPolicy(cfg, stats).eval()


@pytest.mark.parametrize("decoder,sampler", [("flow_matching", None), ("flow_matching", "sde"),
                                             ("mean_flow", None), ("mean_flow", "euler")])
def test_policy_freezes_the_prefix_in_env_units_and_guides_the_rest(decoder, sampler):
    policy = tiny(decoder)
    batch = {"state": torch.randn(3, 6)}
    prev = torch.randn(3, 5, 3)
    gen = lambda: torch.Generator().manual_seed(0)
    with pytest.warns(UserWarning) if sampler == "euler" else _nothing():
        plain = policy.predict_action_chunk(batch, sampler=sampler, generator=gen())
    out = policy.predict_action_chunk(batch, sampler=sampler, generator=gen(), prev_chunk=prev, delay=2)
    assert out.shape == (3, 8, 3) and torch.equal(out[:, :2], prev[:, :2])
    assert (out[:, 2:5] - prev[:, 2:5]).norm() < (plain[:, 2:5] - prev[:, 2:5]).norm()
    zero = tiny(decoder, rtc_guidance_weight=0.0)
    same = zero.predict_action_chunk(batch, sampler=sampler, generator=gen(), prev_chunk=prev, delay=0)
    torch.testing.assert_close(same, plain, rtol=0, atol=1e-6)


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


@pytest.mark.parametrize("kwargs,words", [
    ({"prev_chunk": None, "delay": 2}, ["delay", "needs prev_chunk"]),
    ({"prev_chunk": torch.zeros(2, 5, 3), "delay": -1}, ["delay", "non-negative integer", "-1"]),
    ({"prev_chunk": torch.zeros(2, 5, 3), "delay": 6}, ["delay", "at most", "5", "6"]),
    ({"prev_chunk": torch.zeros(2, 9, 3), "delay": 1}, ["prev_chunk", "[2, L <= 8, 3]", "[2, 9, 3]"]),
    ({"prev_chunk": torch.full((2, 5, 3), float("nan")), "delay": 1}, ["prev_chunk", "NaN"]),
    ({"prev_chunk": torch.zeros(2, 5, 3), "delay": 1, "sampler": "sde", "return_logprob": True},
     ["return_logprob", "prev_chunk"]),
])
def test_bad_rtc_arguments_give_one_line(kwargs, words):
    with pytest.raises(ValueError) as err:
        tiny().predict_action_chunk({"state": torch.zeros(2, 6)}, **kwargs)
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_ddpm_refuses_a_previous_chunk_in_one_line():
    with pytest.raises(ValueError, match="prev_chunk: real-time chunking needs a flow_matching or mean_flow"):
        tiny("DDPM").predict_action_chunk({"state": torch.zeros(2, 6)}, prev_chunk=torch.zeros(2, 5, 3), delay=1)


def test_config_validates_the_rtc_fields():
    with pytest.raises(ValueError, match="rtc_guidance_weight: expected a non-negative finite number"):
        DecoderConfig(rtc_guidance_weight=float("inf"))
    with pytest.raises(ValueError, match="rtc_schedule: expected one of"):
        DecoderConfig(rtc_schedule="cosine")
    with pytest.raises(ValueError, match="rtc_horizon: expected one of"):
        DecoderConfig(rtc_horizon="chunk")


@pytest.mark.parametrize("decoder", ["flow_matching", "mean_flow"])
def test_execution_horizon_guides_only_the_rows_the_new_chunk_executes(decoder):
    """rtc_horizon="execution": the same chunk as passing prev_chunk's first d + s rows, not the whole overlap."""
    policy = tiny(decoder, n_action_steps=2)
    batch = {"state": torch.randn(3, 6, generator=torch.Generator().manual_seed(2))}
    prev = torch.randn(3, 6, 3, generator=torch.Generator().manual_seed(3))                 # L = 6 > d + s = 3
    gen = lambda: torch.Generator().manual_seed(0)
    chunk = lambda horizon, p: (setattr(policy.config, "rtc_horizon", horizon),
                                policy.predict_action_chunk(batch, generator=gen(), prev_chunk=p, delay=1))[1]
    whole, short = chunk("overlap", prev), chunk("overlap", prev[:, :3])
    executed = chunk("execution", prev)
    torch.testing.assert_close(executed, short, rtol=0, atol=0)
    assert not torch.allclose(executed, whole)
    # "auto" (the default): the whole overlap for flow matching, the execution horizon for MeanFlow.
    assert DecoderConfig().rtc_horizon == "auto"
    expected = executed if decoder == "mean_flow" else whole
    torch.testing.assert_close(chunk("auto", prev), expected, rtol=0, atol=0)


# ---------------------------------------------------------------------------- asynchronous evaluation
def test_delayed_execution_runs_the_old_chunk_while_the_new_one_is_computed(monkeypatch):
    """Chunks encode (plan index, step): the executed sequence shows which chunk ran when."""
    calls, executed = [], []

    def fn(states, task_index, plan_indices, episode_seeds, prev_chunks=None, delay=0):
        calls.append((plan_indices.tolist(), None if prev_chunks is None else prev_chunks.copy(), delay))
        p = plan_indices[:, None, None].astype(float)
        return np.broadcast_to(np.concatenate([p / 10 + np.arange(8)[None, :, None] / 100] * 1, 1),
                               (len(states), 8, 4)).copy()

    ev = importlib.import_module("action_decoder.envs.evaluate")     # the module, not the function
    real_step = ev.SeededLayoutEnv.step

    def step(self, action):
        executed.append(np.asarray(action).copy())
        return real_step(self, action)

    monkeypatch.setattr(ev.SeededLayoutEnv, "step", step)
    res = evaluate(fn, "metaworld/reach", episodes=1, seed=0, n_action_steps=4, max_steps=14, num_envs=1,
                   delay=2, rtc=True)
    codes = [round(a[0] * 100) for a in executed]            # plan·10 + step
    # plan 0 runs its steps 0..5 (s + d), then each later plan its steps 2..5.
    assert codes == [0, 1, 2, 3, 4, 5, 12, 13, 14, 15, 22, 23, 24, 25]
    assert calls[0][1] is None and [c[0] for c in calls] == [[0], [1], [2], [3]]
    np.testing.assert_allclose(calls[1][1][0, :, 0], (0 + np.arange(4, 8)) / 100)   # old chunk's steps s..H−1
    assert calls[1][2] == 2 and res["delay"] == 2 and res["rtc"] is True
    assert res["boundaries"] == 4 and res["boundary_jerk"] > 0
    assert res["episode_boundary_jerk"] == [pytest.approx(res["boundary_jerk"])]      # one episode


def test_jerk_stats_count_the_stencils_around_each_switch():
    a = np.zeros((8, 4))
    a[4:] = 1.0                                              # a jump where the new chunk starts (k = 4)
    b, nb, total, n = jerk_stats(list(a), [4])
    assert (nb, n) == (2, 6) and b == total == 8.0           # (1 − 0)²·4 dims at both stencils


def test_eval_delay_rtc_runs_end_to_end_and_records_it(tmp_path, monkeypatch, capsys):
    """`action-decoder eval --delay 2 --rtc` on a tiny checkpoint (episodes cut at 24 steps to stay fast)."""
    from action_decoder import cli

    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type="mean_flow", state_dim=39, action_dim=4, action_chunk_size=8, hidden_size=32,
                        num_hidden_layers=1, n_action_steps=4, num_inference_timesteps=1,
                        state_layout="metaworld", extra={"tasks": ["reach-v3"]})
    ActionDecoderPolicy(cfg).save_pretrained(tmp_path / "ckpt")
    monkeypatch.chdir(tmp_path)
    args = ["eval", "--checkpoint", str(tmp_path / "ckpt"), "--episodes", "2", "--num-envs", "2", "--max-steps", "24"]
    assert cli.main(args + ["--delay", "2", "--rtc"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("success_rate=")
    summary = json.loads((tmp_path / "ckpt" / "eval_ode_k1_n4_d2_rtc_seed0_e2_t24.json").read_text())
    assert summary["delay"] == 2 and summary["rtc"] is True and summary["boundary_jerk"] > 0
    assert summary["results"][0]["boundaries"] == 2 * 10    # switches at 6, 10, .., 22: stencils centred k − 1, k
    assert cli.main(args + ["--delay", "5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("action-decoder: error: --delay: expected 0..4") and "got 5" in err


def test_benchmark_table_pools_seeds_by_episode_and_jerk_by_stencil(tmp_path):
    from argparse import Namespace

    from benchmarks.rtc import write_page

    def row(seed, rtc, successes, jerk, boundaries, per_episode, ms):
        return {"task": "push-v3", "decoder": "mean_flow", "steps": 1, "delay": 2, "rtc": rtc, "episodes": 4,
                "seed": seed, "successes": successes, "success_rate": successes / 4, "boundary_jerk": jerk,
                "boundaries": boundaries, "episode_boundary_jerk": per_episode, "latency_ms": ms, "command": "c",
                "date": "2026-01-0" + str(1 + seed)}

    rows = [row(0, False, 4, 0.2, 10, [0.2] * 4, 10.0), row(1, False, 2, 0.1, 30, [0.1] * 4, 10.0),
            row(0, True, 3, 0.1, 10, [0.1] * 4, 20.0), row(1, True, 3, 0.1, 10, [0.0, 0.2, 0.1, 0.1], 30.0),
            {**row(0, True, 1, 0.05, 20, [0.05] * 4, 10.0), "rtc_horizon": "execution"}]
    page = tmp_path / "rtc.md"
    write_page(rows, page, Namespace(seed=0, latency_reps=5), "c")
    lines = {l.split("|")[3].strip(): [c.strip() for c in l.strip("|").split("|")]
             for l in page.read_text().splitlines() if l.startswith("| MF K=1 | 2 |") and "/" not in l}
    overlap, execution = lines["overlap"], lines["execution (default)"]    # MeanFlow's default: execution
    assert overlap[3:7] == ["1", "75.0", "75.0", "+0.0"]                   # rows without a horizon: the overlap
    assert overlap[7].startswith("0.1250 ± ") and overlap[8].startswith("0.1000 ± ")   # (0.2·10 + 0.1·30)/40
    assert overlap[9] == "0.80" and overlap[12] == "2.50×"                # 0.1/0.125; 25 ms / 10 ms
    # The execution arm ran at seed 0 only: naive switching is pooled over the same (task, seed) cells.
    assert execution[4:7] == ["100.0", "25.0", "-75.0"] and execution[7].startswith("0.2000 ± ")
    assert execution[9] == "0.25" and execution[12] == "1.00×"
    per_task = next(l for l in page.read_text().splitlines() if l.startswith("| MF K=1 | 2 |") and "/" in l)
    assert per_task.split("|")[3].strip() == "75 / 75 / 25"
    assert "Generated by `c` on 2026-01-01, 2026-01-02 (" in page.read_text()   # the rows' dates, not the rebuild's


def test_flow_matching_guidance_under_inference_mode_is_one_line_and_meanflows_works():
    gm, g = two_modes(), Gaussian(torch.linspace(-1, 1, H * D, dtype=torch.float64).reshape(H, D), 0.3)
    e, prev = noise(), torch.randn(16, 5, D, dtype=torch.float64)
    with torch.no_grad():
        expected = sample_ode_rtc(gm.velocity, e, prev, 2, 4)
    with torch.inference_mode():
        assert sample_meanflow_rtc(g.avg_velocity, e, prev, 2, 1).shape == e.shape
        with pytest.raises(RuntimeError, match=r"^prev_chunk: .*vector-Jacobian product.*torch.no_grad\(\), not "
                                               r"torch.inference_mode\(\)"):
            sample_ode_rtc(gm.velocity, e, prev, 2, 4)
    assert torch.isfinite(expected).all()


def test_benchmark_page_states_the_noise_of_each_cells_episode_count(tmp_path):
    from argparse import Namespace

    from benchmarks.rtc import write_page

    def row(task, rtc, horizon=None):
        return {"task": task, "decoder": "mean_flow", "steps": 1, "delay": 2, "rtc": rtc, "episodes": 20, "seed": 0,
                "successes": 10, "success_rate": 0.5, "boundary_jerk": 0.1, "boundaries": 10,
                "episode_boundary_jerk": [0.1] * 20, "latency_ms": 10.0, "command": "c", "rtc_horizon": horizon,
                "date": "2026-01-01"}

    rows = [row(t, False) for t in "abcde"] + [row(t, True, "execution") for t in "abcde"] + \
        [row(t, True, "overlap") for t in "ab"]
    write_page(rows, tmp_path / "rtc.md", Namespace(seed=0, latency_reps=5), "c")
    text = (tmp_path / "rtc.md").read_text()
    assert "±5.0 points over 100 episodes (beyond noise: more than 14 points)" in text
    assert "±7.9 points over 40 episodes (beyond noise: more than 22 points)" in text
