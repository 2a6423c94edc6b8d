"""The multimodal benchmark: its metrics on known inputs, the obstacle task's expert, a tiny run,
and the MeanFlow recipe option it measures (rows at (t, r) = (0, 1))."""

import json

import numpy as np
import pytest
import torch

from action_decoder.envs.obstacle_routes import (MAX_STEPS, N_ACTION_STEPS, SPEED, ObstacleRoutesEnv,
                                                  expert_action, expert_dataset, expert_episode, rollout)
from action_decoder.flows.losses import meanflow_loss, sample_meanflow_times
from benchmarks import multimodal as mm


@pytest.fixture(scope="module")
def modes():
    state = torch.randn(64, 4, generator=torch.Generator().manual_seed(0))
    return mm.routes(state)                                                   # [N, 2, H, 4]


def test_separation_and_tolerance():
    # bend sin(πh)·c with RMS(c) ≈ 0.73: the routes are ≈ 1.0 apart, the midpoint 0.5 from each.
    assert 0.95 < mm.separation() < 1.05


def test_exact_balanced_samples_score_perfectly(modes):
    samples = modes.repeat_interleave(4, 1)                                    # [N, 8, H, 4]: 4 on each
    m = mm.mode_metrics(samples, modes, 0.1)
    assert m["on_mode"] == 1.0 and m["coverage"] == 1.0 and m["majority_share"] == 0.5
    assert m["energy"] < 1e-6 and m["rms_to_nearest"] < 1e-6


def test_midpoint_is_off_mode_and_far_in_energy(modes):
    mid = modes.mean(1, keepdim=True).expand(-1, 8, -1, -1)                    # the average of the routes
    m = mm.mode_metrics(mid, modes, 0.1)
    assert m["on_mode"] == 0.0 and m["coverage"] == 0.0
    # E|X−Y| = d/2, E|X−X'| = 0, E|Y−Y'| = d/2: energy = d/2 with d the separation.
    assert m["energy"] == pytest.approx(mm.separation() / 2, rel=1e-4)


def test_unbalanced_split_shows_in_balance_coverage_and_energy(modes):
    # 6 of 8 samples on route A in every state; then all on A.
    skew = torch.cat([modes[:, :1].expand(-1, 6, -1, -1), modes[:, 1:].expand(-1, 2, -1, -1)], 1)
    m = mm.mode_metrics(skew, modes, 0.1)
    assert m["on_mode"] == 1.0 and m["majority_share"] == pytest.approx(0.75) and m["coverage"] == 1.0
    one = mm.mode_metrics(modes[:, :1].expand(-1, 8, -1, -1), modes, 0.1)
    assert one["majority_share"] == 1.0 and one["coverage"] == 0.0
    # the energy distance grows with the imbalance (q = 3/4 on A, then q = 1)
    assert 1e-3 < m["energy"] < one["energy"]
    # Half the states collapsed to A, half to B: pooled balance is perfect, coverage is not.
    per_state = torch.where(torch.arange(64)[:, None, None, None] % 2 == 0, modes[:, :1], modes[:, 1:])
    ps = mm.mode_metrics(per_state.expand(-1, 8, -1, -1), modes, 0.1)
    assert ps["majority_share"] == 0.5 and ps["coverage"] == 0.0 and ps["energy"] > 0.2


def test_tolerance_is_a_strict_radius(modes):
    off = modes[:, :1] + 0.2                                                   # RMS 0.2 from route A
    assert mm.mode_metrics(off.expand(-1, 2, -1, -1), modes, 0.1)["on_mode"] == 0.0
    assert mm.mode_metrics(off.expand(-1, 2, -1, -1), modes, 0.25)["on_mode"] == 1.0


@pytest.mark.parametrize("side", [1, -1])
def test_expert_succeeds_by_both_routes(side):
    for seed in range(20):
        obs, chunks, ok = expert_episode(seed, side)
        assert ok and obs.shape[1:] == (6,) and chunks.shape == (len(obs), 16, 2) and len(obs) < MAX_STEPS
        res = rollout(lambda o: np.stack([expert_action(o, side)] * 16), seed, n_action_steps=1)
        assert res == {"success": True, "collided": False, "route": side}
        # closed loop as the benchmark runs it: a 16-action chunk from each frame, N_ACTION_STEPS executed
        chunk = lambda o: expert_episode_from(o, side)                          # noqa: E731
        assert rollout(chunk, seed) == {"success": True, "collided": False, "route": side}


def expert_episode_from(obs, side, horizon=16):
    """The expert's next `horizon` actions from observation `obs`, simulated open loop."""
    obs, out = obs.copy(), []
    for _ in range(horizon):
        a = expert_action(obs, side)
        out.append(a)
        obs[:2] = obs[:2] + SPEED * np.clip(a, -1, 1)
    return np.stack(out)


def test_layout_is_symmetric_so_both_routes_start_from_the_same_state():
    for seed in range(10):
        up, up_chunks, _ = expert_episode(seed, 1)
        down, down_chunks, _ = expert_episode(seed, -1)
        assert np.array_equal(up[0], down[0]) and np.all(up[0][1::2] == 0)    # every y on the axis
        # the two first chunks are mirror images: same x, opposite y, clearly apart
        assert np.allclose(up_chunks[0, :, 0], down_chunks[0, :, 0])
        assert np.allclose(up_chunks[0, :, 1], -down_chunks[0, :, 1]) and up_chunks[0, :4, 1].min() > 0.4


def test_averaging_the_routes_collides_within_the_first_chunk():
    avg = lambda o: np.stack([(expert_action(o, 1) + expert_action(o, -1)) / 2] * 16)   # noqa: E731
    for seed in range(20):
        env = ObstacleRoutesEnv()
        obs, _ = env.reset(seed=seed)
        for step in range(1, N_ACTION_STEPS + 1):
            obs, _, done, _, info = env.step(avg(obs)[0])
            if done:
                break
        assert info["collided"] and step <= N_ACTION_STEPS
        assert rollout(avg, seed) == {"success": False, "collided": True, "route": None}


def test_expert_dataset_is_balanced_and_bimodal_at_the_start():
    states, chunks = expert_dataset(40, seed=0)
    start = (states[:, 1] == 0) & (states[:, 0] < -0.5)                        # first frame of each episode
    assert int(start.sum()) == 40
    up = chunks[start][:, :8, 1].mean(1) > 0                                   # heading above the obstacle
    assert 10 <= int(up.sum()) <= 30
    assert torch.all(chunks[start][:, :8, 1].abs().mean(1) > 0.4)             # every demo commits at once


def test_one_step_rows_take_the_whole_interval():
    t, r, n = sample_meanflow_times(128, 0.25, 0.4, 1.0, torch.Generator().manual_seed(0), dist="uniform",
                                    one_step_share=0.5)
    assert n == 32 and torch.all(t[:16] == 0) and torch.all(r[:16] == 1)
    assert torch.all((t[16:n] > 0) & (r[16:n] < 1) & (t[16:n] <= r[16:n])) and torch.equal(t[n:], r[n:])
    base = sample_meanflow_times(128, 0.25, 0.4, 1.0, torch.Generator().manual_seed(0), dist="uniform")
    assert torch.equal(base[0][16:], t[16:]) and torch.equal(base[1][16:], r[16:])   # the rest unchanged
    with pytest.raises(ValueError, match="one_step_share"):
        sample_meanflow_times(8, 0.25, 0.4, 1.0, one_step_share=1.5)


def test_one_step_rows_regress_the_one_step_map():
    # A point mass at a: u(z, t, r) = (a − z)/(1 − t) for every r; with every row at (0, 1) it has
    # loss 0 (its total derivative vanishes there), and a u that depends on r − t does not.
    a = torch.full((16, 4, 2), 0.7)
    exact = lambda z, t, r: (a[: z.shape[0]] - z) / (1 - t).reshape(-1, 1, 1)   # noqa: E731
    assert meanflow_loss(exact, a, torch.Generator().manual_seed(0), ratio_r_neq_t=1.0,
                         one_step_share=1.0).item() < 1e-9
    wrong = lambda z, t, r: exact(z, t, r) * (1 + (r - t) * 0.5).reshape(-1, 1, 1)   # noqa: E731
    assert meanflow_loss(wrong, a, torch.Generator().manual_seed(0), ratio_r_neq_t=1.0, one_step_share=1.0) > 0.1


def test_tiny_benchmark_runs(tmp_path, capsys):
    from benchmarks.__main__ import main                                       # python -m benchmarks multimodal
    assert main(["multimodal", "--tiny", "--decoders", "mean_flow", "--out", str(tmp_path),
                 "--recipe", "one_step_share=0.5", "--log-every", "1"]) == 0
    printed = capsys.readouterr()
    progress = [json.loads(line) for line in printed.err.splitlines() if line.startswith("{")]
    assert [(p["step"], p["of"]) for p in progress] == [(1, 3), (2, 3), (3, 3)] * 2     # synthetic, obstacle
    assert all(p["decoder"] == "mean_flow" and p["loss"] > 0 for p in progress)
    data = json.loads((tmp_path / "multimodal_run.json").read_text())
    assert set(data["results"]) == {"synthetic", "obstacle"}
    assert set(data["results"]["synthetic"]) == {"MF K=1", "MF K=2"}
    assert data["meta"]["budget"]["recipe"] == {"one_step_share": 0.5}
    assert mm.policy_mod.meanflow_loss is meanflow_loss          # the loss option ends with the run
    assert "| on a mode" in printed.out
    with pytest.raises(ValueError, match="--recipe"):
        mm.main(["--tiny", "--recipe", "ratio"])


def test_distillation_term_fits_the_student_one_step_map_to_the_teacher_chunk_from_the_same_noise():
    """Trained on the term alone, the student's 1-step chunk approaches the teacher's 10-step ODE
    chunk of the same noise (a map of the noise, not just its mean: the teacher's chunks spread far
    more than the final gap), and no gradient reaches the teacher."""
    b = mm.Budget(hidden=32, layers=1)
    torch.manual_seed(0)
    teacher = mm.make_policy("flow_matching", 4, 4, b).eval()
    teacher.requires_grad_(False)
    student = mm.make_policy("mean_flow", 4, 4, b)
    opt = torch.optim.Adam([p for p in student.parameters() if p.requires_grad], lr=3e-3)
    state = torch.randn(64, 4, generator=torch.Generator().manual_seed(1))
    for step in range(100):           # far below the bound by then; untrained, the term is about the spread
        loss = mm.distillation_term(student, teacher, state, torch.Generator().manual_seed(step % 8))
        opt.zero_grad()
        loss.backward()
        opt.step()
    z = torch.randn(64, 16, 4, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        target = teacher.sample({"state": state}, sampler="ode", steps=mm.TEACHER_STEPS, noise=z).actions
    spread = (target - target.mean(0)).square().mean().item()            # what a noise-blind map would leave
    gen = torch.Generator().manual_seed(3)
    assert mm.distillation_term(student, teacher, state, gen).item() < 0.1 * spread
    assert all(p.grad is None for p in teacher.parameters())


def test_distill_recipe_trains_a_teacher_and_counts_its_time(tmp_path):
    assert mm.main(["--tiny", "--only", "synthetic", "--decoders", "mean_flow", "--out", str(tmp_path),
                    "--recipe", "distill=1"]) == 0
    data = json.loads((tmp_path / "multimodal_run.json").read_text())
    assert data["meta"]["budget"]["recipe"] == {"distill": 1.0}
    assert set(data["results"]["synthetic"]) == {"MF K=1", "MF K=2"}


def test_device_option_names_the_field_and_what_was_given(monkeypatch):
    with pytest.raises(ValueError, match=r"--log-every: expected a number of steps ≥ 0, got -1"):
        mm.main(["--tiny", "--log-every", "-1"])
    with pytest.raises(ValueError, match=r"--device: expected auto, cpu, cuda, cuda:N .*got 'gpu'"):
        mm.main(["--tiny", "--device", "gpu"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"--device: 'cuda' is not available on this machine"):
        mm.main(["--tiny", "--device", "cuda"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match=r"--device: 'cuda:1' names device 1, but this machine has 1 cuda"):
        mm.main(["--tiny", "--device", "cuda:1"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_tiny_benchmark_runs_on_cuda(tmp_path):
    assert mm.main(["--tiny", "--decoders", "flow_matching", "mean_flow", "--out", str(tmp_path),
                    "--device", "cuda"]) == 0
    data = json.loads((tmp_path / "multimodal_run.json").read_text())
    assert data["meta"]["device"] != "cpu"
    assert set(data["results"]["obstacle"]) >= {"FM K=10", "MF K=1"}
