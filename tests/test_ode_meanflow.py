"""Oracle tests for the deterministic samplers and the MeanFlow target."""

import pytest
import torch

from action_decoder import (FixedSigma, sample_meanflow, sample_ode, sample_sde, time_grid,
                            velocity_from_meanflow, velocity_from_sample)
from action_decoder.oracles import Gaussian, GaussianMixture, energy_distance

N = 2000


@pytest.fixture(scope="module")
def mixture():
    return GaussianMixture.make([[[1.5, 0.5]], [[-1.0, -1.0]]], [0.3, 0.5], [0.4, 0.6])


@pytest.fixture(scope="module")
def gaussian():
    return Gaussian(torch.tensor([[0.7, -1.2, 0.3]], dtype=torch.float64), 0.4)


def tolerance(mixture, seed=100):
    """Energy distance between exact draws of the same size: the noise floor of the test."""
    g = torch.Generator().manual_seed(seed)
    floors = [energy_distance(mixture.sample(N, g), mixture.sample(N, g)) for _ in range(3)]
    return 3 * max(floors)


def test_time_grid():
    g = time_grid(4)
    assert torch.allclose(g, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0]))
    assert g.dtype == torch.float32
    with pytest.raises(ValueError, match="steps"):
        time_grid(0)


def test_sample_ode_reproduces_mixture(mixture):
    g = torch.Generator().manual_seed(1)
    ref = mixture.sample(N, g)
    x = sample_ode(mixture.velocity, torch.randn(N, 1, 2, generator=g, dtype=torch.float64), steps=200)
    tol = tolerance(mixture)
    assert energy_distance(x, ref) < tol
    # The statistic does see a 0.3 shift at this size: the test has teeth.
    assert energy_distance(x + 0.3, ref) > 5 * tol


def test_sample_ode_first_order(mixture):
    g = torch.Generator().manual_seed(2)
    noise = torch.randn(500, 1, 2, generator=g, dtype=torch.float64)
    exact = sample_ode(mixture.velocity, noise, steps=4096)
    errs = [(sample_ode(mixture.velocity, noise, steps=k) - exact).abs().mean() for k in (16, 32, 64, 128)]
    ratios = [float(errs[i] / errs[i + 1]) for i in range(3)]
    assert all(1.7 < r < 2.3 for r in ratios), ratios   # halving the step halves the error


def test_sample_ode_exact_flow_map(gaussian):
    noise = torch.randn(64, 1, 3, dtype=torch.float64)
    target = gaussian.flow_map(noise, torch.zeros(64, dtype=torch.float64), torch.ones(64, dtype=torch.float64))
    err = (sample_ode(gaussian.velocity, noise, steps=1000) - target).abs().max()
    assert err < 5e-3


def test_custom_grid_matches_and_is_validated(gaussian):
    noise = torch.randn(8, 1, 3, dtype=torch.float64)
    a = sample_ode(gaussian.velocity, noise, grid=time_grid(7, dtype=torch.float64))
    b = sample_ode(gaussian.velocity, noise, steps=7)
    assert torch.allclose(a, b)
    with pytest.raises(ValueError, match="grid"):
        sample_ode(gaussian.velocity, noise, grid=torch.tensor([0.0, 0.6, 0.5, 1.0]))


@pytest.mark.parametrize("steps", [1, 4])
def test_sample_meanflow_exact(gaussian, steps):
    noise = torch.randn(64, 1, 3, dtype=torch.float64)
    ones = torch.ones(64, dtype=torch.float64)
    target = gaussian.flow_map(noise, 0 * ones, ones)
    out = sample_meanflow(gaussian.avg_velocity, noise, steps=steps)
    assert torch.allclose(out, target, atol=1e-10)
    assert not torch.allclose(sample_ode(gaussian.velocity, noise, steps=steps), target, atol=1e-3)


@pytest.mark.parametrize("mode", ["boundary", "identity"])
def test_velocity_from_meanflow_recovers_velocity(gaussian, mode):
    z = torch.randn(32, 1, 3, dtype=torch.float64)
    t = torch.rand(32, dtype=torch.float64) * 0.98
    v_hat = velocity_from_meanflow(gaussian.avg_velocity, mode=mode)(z, t)
    assert torch.allclose(v_hat, gaussian.velocity(z, t), atol=1e-5)
    if mode == "identity":
        # Without the (t − r)·du/dt correction u(x, t, t + δ) is off at first order in δ.
        u = gaussian.avg_velocity(z, t, t + 1e-3)
        assert (v_hat - gaussian.velocity(z, t)).abs().max() < 0.01 * (u - gaussian.velocity(z, t)).abs().max()


def test_velocity_from_sample_is_the_mixture_velocity(mixture):
    # On z_t = (1 − t)·e + t·a, z_t / s with s = √(t² + (1 − t)²) is DDPM's √ᾱ·a + √(1 − ᾱ)·ε at
    # ᾱ = t²/s², so E[a | z_t] comes from the mixture's denoiser, independently of its velocity.
    g = torch.Generator().manual_seed(3)
    z = torch.randn(64, 1, 2, generator=g, dtype=torch.float64)
    t = torch.rand(64, generator=g, dtype=torch.float64) * 0.94
    s = (t.square() + (1 - t).square()).sqrt()
    clean = mixture.denoiser(z / s.reshape(-1, 1, 1), (t / s).square())
    assert torch.allclose(velocity_from_sample(z, t, clean), mixture.velocity(z, t), atol=1e-10)
    # Past the floor the step shrinks: 1 − t = 0.01 divides by 0.05.
    late = torch.full((64,), 0.99, dtype=torch.float64)
    assert torch.allclose(velocity_from_sample(z, late, clean), (clean - z) / 0.05)


def test_bf16_velocity_does_not_drag_integration_into_bf16():
    # bf16 spacing at 8.0 is 0.0625: adding 100 increments of 0.005 in bf16 would stay at 8.0.
    noise = torch.full((2, 1, 1), 8.0, dtype=torch.bfloat16)
    seen = []

    def velocity(x, t):
        seen.append((x.dtype, t.dtype))
        return torch.full_like(x, 0.5, dtype=torch.bfloat16)

    out = sample_ode(velocity, noise, steps=100)
    assert out.dtype == torch.bfloat16 and torch.all(out == 8.5)
    assert set(seen) == {(torch.float32, torch.float32)}
    out = sample_meanflow(lambda x, t, r: velocity(x, t), noise, steps=100)
    assert torch.all(out == 8.5)


def test_float64_noise_integrates_in_float64(gaussian):
    noise = torch.randn(4, 1, 3, dtype=torch.float64)
    assert sample_ode(lambda x, t: (x.dtype == torch.float64) * torch.ones_like(x), noise, 2).dtype == torch.float64


@pytest.mark.parametrize("bad", [torch.randn(4, 3), torch.randn(2, 4, 3, 1)])
def test_wrong_noise_shape_names_the_argument(bad, gaussian):
    with pytest.raises(ValueError, match=r"noise: expected a tensor of shape \[B, H, D\]"):
        sample_ode(gaussian.velocity, bad)


def test_negative_steps_and_wrong_output_shape(gaussian):
    noise = torch.randn(4, 1, 3, dtype=torch.float64)
    for fn in (sample_ode, sample_meanflow):
        with pytest.raises(ValueError, match="steps"):
            fn(gaussian.velocity, noise, steps=-1)
    with pytest.raises(ValueError, match="velocity: expected an output"):
        sample_ode(lambda x, t: x[:, :, :1], noise)


def test_identity_velocity_error_is_second_order_in_delta(gaussian):
    z = torch.randn(32, 1, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    t = torch.rand(32, dtype=torch.float64, generator=torch.Generator().manual_seed(6)) * 0.9
    v = gaussian.velocity(z, t)
    errs = [(velocity_from_meanflow(gaussian.avg_velocity, "identity", delta=d)(z, t) - v).abs().max()
            for d in (0.04, 0.02, 0.01)]
    ratios = [float(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(3.5 < r < 4.5 for r in ratios), ratios   # halving delta quarters the error


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_identity_velocity_runs_in_the_samplers(gaussian, dtype):
    g = torch.Generator().manual_seed(7)
    noise = torch.randn(4000, 1, 3, dtype=torch.float64, generator=g).to(dtype)
    v_id = velocity_from_meanflow(gaussian.avg_velocity, "identity")
    # ODE: the same Euler path as the exact velocity's, up to the O(delta²) velocity error.
    exact = sample_ode(gaussian.velocity, noise, steps=50)
    assert torch.allclose(sample_ode(v_id, noise, steps=50), exact, atol=1e-4)
    # SDE (the design's MF-SDE option 2): the Gaussian's mean and std, with finite log-probs.
    res = sample_sde(v_id, noise, 100, FixedSigma(0.8), generator=g, clip_t=1e-3, return_logprob=True)
    out = res.actions.double()
    assert torch.allclose(out.mean(0), gaussian.mean, atol=0.03)
    assert torch.allclose(out.std(0), torch.full_like(gaussian.mean, gaussian.std), atol=0.03)
    assert torch.isfinite(res.log_prob).all()


@pytest.mark.parametrize("batch", [1, 3])
def test_a_callable_that_writes_into_its_t_changes_no_later_call(batch):
    seen = []

    def observe(x, t):
        seen.append(t.clone())
        return torch.zeros_like(x)

    def scale_t_in_place(x, t):
        t.mul_(2.0)
        return torch.zeros_like(x)

    noise = torch.randn(batch, 4, 2)
    sample_ode(observe, noise, 4)
    before = torch.stack(seen)
    sample_ode(scale_t_in_place, noise, 4)
    seen.clear()
    sample_ode(observe, noise, 4)
    torch.testing.assert_close(torch.stack(seen), before)
    torch.testing.assert_close(before[:, 0], time_grid(4)[:-1])
