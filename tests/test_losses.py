"""Losses: the MeanFlow target against the closed-form average velocity, the recipe, DDPM
training ↔ sampling consistency for both prediction types."""

import pytest
import torch
from torch import nn

from action_decoder import (ActionDecoderPolicy, DecoderConfig, ddpm_loss, flow_matching_loss, meanflow_loss, meanflow_target,
                            sample_ddpm)
from action_decoder.flows.ddpm import inference_scheduler
from action_decoder.flows import losses
from action_decoder.flows.losses import dudt_finite_difference, sample_meanflow_times
from action_decoder.oracles import Gaussian, GaussianMixture, energy_distance


@pytest.fixture(scope="module")
def gaussian():
    return Gaussian(torch.tensor([[0.7, -1.2, 0.3]], dtype=torch.float64), 0.4)


def _points(n=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(n, 1, 3, generator=g, dtype=torch.float64)
    s = torch.rand(n, 2, generator=g, dtype=torch.float64) * 0.95
    return z, s.min(1).values, s.max(1).values


def test_meanflow_target_returns_exact_u_and_is_detached(gaussian):
    z, t, r = _points()
    theta = nn.Parameter(torch.ones((), dtype=torch.float64))
    u, target = meanflow_target(lambda x, tt, rr: theta * gaussian.avg_velocity(x, tt, rr), z, t, r,
                                gaussian.velocity(z, t))
    assert torch.allclose(u, gaussian.avg_velocity(z, t, r), atol=1e-10)
    # With the exact u and the exact marginal velocity the identity holds: target == u.
    assert torch.allclose(target, u, atol=1e-8)
    assert not target.requires_grad and u.requires_grad


def test_wrong_tangent_or_sign_would_fail(gaussian):
    """The same identity with a broken ingredient is far from u: the test above has teeth."""
    z, t, r = _points()
    v = gaussian.velocity(z, t)
    u_exact = gaussian.avg_velocity(z, t, r)
    gap = (t - r).reshape(-1, 1, 1)

    def target_with(tangent, sign=-1.0):
        _, dudt = torch.func.jvp(gaussian.avg_velocity, (z, t, r), tangent)
        return v + sign * gap * dudt

    one, zero = torch.ones_like(t), torch.zeros_like(t)
    assert torch.allclose(target_with((v, one, zero)), u_exact, atol=1e-8)     # the right one
    for wrong in [target_with((v, zero, zero)),                               # no ∂/∂t
                  target_with((v, one, one)),                                 # r moving with t
                  target_with((torch.zeros_like(v), one, zero)),              # no ∂/∂z·v
                  target_with((v, one, zero), sign=+1.0)]:                    # wrong sign
        assert (wrong - u_exact).abs().max() > 1e-2


def test_meanflow_loss_gradient_has_stop_gradient_and_skips_jvp_on_r_equal_t(gaussian):
    """The loss equals an independent reference (JVP on every row, target detached)."""
    a = gaussian.sample(64, torch.Generator().manual_seed(3)).float()
    net = nn.Sequential(nn.Linear(5, 32), nn.Tanh(), nn.Linear(32, 3))

    def u(x, t, r):
        return net(torch.cat([x, t.reshape(-1, 1, 1).expand(-1, 1, 1), r.reshape(-1, 1, 1)], -1))

    loss = meanflow_loss(u, a, torch.Generator().manual_seed(7), ratio_r_neq_t=0.25)
    grads = torch.autograd.grad(loss, list(net.parameters()))

    g = torch.Generator().manual_seed(7)
    t, r, n = sample_meanflow_times(64, 0.25, 0.4, 1.0, g)
    assert n == 16 and torch.equal(t[n:], r[n:]) and torch.all(r[:n] >= t[:n])
    e = torch.randn(a.shape, generator=g)
    z = (1 - t).reshape(-1, 1, 1) * e + t.reshape(-1, 1, 1) * a
    v = a - e
    out, dudt = torch.func.jvp(u, (z, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))
    err = (out - (v - (t - r).reshape(-1, 1, 1) * dudt).detach()).square().mean((1, 2))
    ref = ((err.detach() + 1e-3).pow(-0.5) * err).mean()
    ref_grads = torch.autograd.grad(ref, list(net.parameters()), retain_graph=True)
    assert torch.allclose(loss, ref, rtol=1e-5)
    for a_, b_ in zip(grads, ref_grads):
        assert torch.allclose(a_, b_, rtol=1e-4, atol=1e-6)
    # Without the stop-gradient the gradient differs: a missing sg() would be caught.
    err_nosg = (out - (v - (t - r).reshape(-1, 1, 1) * dudt)).square().mean((1, 2))
    bad = torch.autograd.grad(((err_nosg.detach() + 1e-3).pow(-0.5) * err_nosg).mean(),
                              list(net.parameters()))
    assert max((x - y).abs().max() for x, y in zip(bad, ref_grads)) > 1e-4


@pytest.mark.parametrize("dudt", ["jvp", "finite_difference"])
def test_boundary_tangent_makes_the_exact_average_velocity_a_zero_loss(gaussian, dudt):
    """tangent="boundary" uses u(z, t, t), for the exact u the marginal velocity, in the target and
    the tangent: then the MeanFlow identity holds per row and the loss over r ≠ t rows is 0. The
    sampled tangent a − e is right only on average, so the same u leaves a clear loss."""
    a = gaussian.sample(64, torch.Generator().manual_seed(3))                     # [64, 1, 3] float64
    theta = nn.Parameter(torch.ones((), dtype=torch.float64))
    u = lambda x, t, r: theta * gaussian.avg_velocity(x, t, r)                     # noqa: E731
    kw = dict(ratio_r_neq_t=1.0, time_dist="uniform", dudt=dudt)
    boundary = meanflow_loss(u, a, torch.Generator().manual_seed(7), tangent="boundary", **kw)
    sampled = meanflow_loss(u, a, torch.Generator().manual_seed(7), **kw)
    assert boundary.item() < 1e-6 and sampled.item() > 0.1
    assert boundary.requires_grad
    # r = t rows still regress a − e: with every row at r = t the two tangents give the same loss.
    same = [meanflow_loss(u, a, torch.Generator().manual_seed(7), ratio_r_neq_t=0.0, tangent=tg)
            for tg in ("sampled", "boundary")]
    assert torch.equal(same[0], same[1]) and same[0].item() > 0.1
    with pytest.raises(ValueError, match="tangent: expected one of"):
        meanflow_loss(u, a, tangent="marginal")


def test_meanflow_adaptive_weight_uses_the_per_element_mean_of_the_chunk():
    """error = mean(Δ²) over H×D, weight (error + c)^−p, not the paper's ‖Δ‖²: the sum would make
    the loss 8× larger and c 64× smaller relative to the error (docs/benchmarks/meanflow_ablations.md)."""
    a = torch.randn(64, 16, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    seen = {}

    def u(x, t, r):                      # ratio 0: every row r = t, one plain call
        seen["z"], seen["t"] = x, t
        return 0.3 * x

    loss = meanflow_loss(u, a, torch.Generator().manual_seed(1), ratio_r_neq_t=0.0, time_dist="uniform")
    t = seen["t"].reshape(-1, 1, 1)
    e = (seen["z"] - t * a) / (1 - t)    # the noise, from z = (1 − t)·e + t·a
    err = (0.3 * seen["z"] - (a - e)).square().mean((1, 2))                            # [B]
    torch.testing.assert_close(loss, ((err + 1e-3).pow(-0.5) * err).mean(), rtol=1e-6, atol=0)
    assert loss < 4.0, "the per-element mean: ≈ 1/8 of the sum norm's loss"


def test_meanflow_times_are_logit_normal_and_ordered():
    t, r, n = sample_meanflow_times(20000, 0.5, 0.4, 1.0, torch.Generator().manual_seed(0))
    assert n == 10000 and torch.all(t <= r)
    logits = torch.logit(torch.cat([t[:n], r[:n]]))
    assert abs(float(logits.mean()) - 0.4) < 0.03   # both draws together keep the logit-normal mean
    same = torch.logit(t[n:])                       # r = t rows: one draw, not the smaller of two
    assert torch.equal(t[n:], r[n:]) and abs(float(same.mean()) - 0.4) < 0.03 and abs(float(same.std()) - 1) < 0.03
    t, r, n = sample_meanflow_times(20000, 0.5, 0.4, 1.0, torch.Generator().manual_seed(0), dist="uniform")
    both = torch.cat([t[:n], r[:n]])
    assert torch.all(t <= r) and abs(float(both.mean()) - 0.5) < 0.01 and abs(float(both.var()) - 1 / 12) < 0.003
    # The velocity rows cover t ~ U[0, 1] as flow matching does, the data end included (the min of
    # two draws would put 4 % of them above 0.8, not 20 %).
    same = t[n:]
    assert abs(float(same.mean()) - 0.5) < 0.01 and abs(float((same > 0.8).float().mean()) - 0.2) < 0.015
    # The whole interval, which 1-step sampling uses, is drawn often under "uniform" only.
    corner = lambda t, r: float(((t[:n] < 0.1) & (r[:n] > 0.9)).float().mean())   # noqa: E731
    assert corner(t, r) > 0.015
    assert corner(*sample_meanflow_times(20000, 0.5, 0.4, 1.0, torch.Generator().manual_seed(0))[:2]) < 0.002
    with pytest.raises(ValueError, match="time_dist"):
        sample_meanflow_times(4, 0.5, 0.4, 1.0, dist="beta")


def test_flow_matching_loss_minimised_by_exact_velocity():
    gm = GaussianMixture.make([[[1.5, 0.5]], [[-1.0, -1.0]]], [0.3, 0.5], dtype=torch.float64)
    a = gm.sample(4000, torch.Generator().manual_seed(0))
    exact = flow_matching_loss(gm.velocity, a, torch.Generator().manual_seed(1))
    # Same draws: loss(v + c) − loss(v) = c² + a zero-mean cross term (std ≈ 0.008 here).
    for c in (0.3, -0.3):
        shifted = flow_matching_loss(lambda x, t: gm.velocity(x, t) + c, a, torch.Generator().manual_seed(1))
        assert 0.5 * c ** 2 < shifted - exact < 1.5 * c ** 2
    # A loss whose target had the wrong sign (e − a) would be minimised by −v instead.
    assert flow_matching_loss(lambda x, t: -gm.velocity(x, t), a, torch.Generator().manual_seed(1)) > exact + 1


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_ddpm_loss_target_matches_prediction_type(prediction_type):
    gm = GaussianMixture.make([[[1.5, 0.5]], [[-1.0, -1.0]]], [0.3, 0.5], dtype=torch.float64)
    a = gm.sample(4000, torch.Generator().manual_seed(0))
    cfg = DecoderConfig(prediction_type=prediction_type)
    other = "sample" if prediction_type == "epsilon" else "epsilon"
    alphas = inference_scheduler(cfg).alphas_cumprod
    right = ddpm_loss(gm.ddpm_model(alphas, prediction_type), a, cfg, torch.Generator().manual_seed(1))
    wrong = ddpm_loss(gm.ddpm_model(alphas, other), a, cfg, torch.Generator().manual_seed(1))
    assert right < 0.5 * wrong


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_sample_ddpm_with_exact_denoiser_reproduces_mixture(prediction_type):
    gm = GaussianMixture.make([[[1.5, 0.5]], [[-1.0, -1.0]]], [0.3, 0.5], [0.4, 0.6])
    cfg = DecoderConfig(prediction_type=prediction_type)
    g = torch.Generator().manual_seed(4)
    ref = gm.sample(2000, g)
    model = gm.ddpm_model(inference_scheduler(cfg).alphas_cumprod, prediction_type)
    x = sample_ddpm(model, torch.randn(2000, 1, 2, generator=g, dtype=torch.float64), cfg, steps=25)
    floor = energy_distance(gm.sample(2000, g), gm.sample(2000, g))
    assert energy_distance(x, ref) < 3 * floor + 1e-3
    assert energy_distance(x + 0.3, ref) > 0.02


def test_one_dpm_solver_step_returns_the_x0_prediction():
    cfg = DecoderConfig(prediction_type="sample")
    x0 = torch.randn(3, 2, 2)
    out = sample_ddpm(lambda x, s: x0, torch.randn(3, 2, 2), cfg, steps=1)
    assert torch.allclose(out, x0)


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_ddpm_loss_trains_what_sample_ddpm_samples(prediction_type):
    """A small network trained with ddpm_loss samples the data through sample_ddpm."""
    torch.manual_seed(0)
    gm = GaussianMixture.make([[[1.0]], [[-1.0]]], [0.15, 0.15], dtype=torch.float32)
    cfg = DecoderConfig(prediction_type=prediction_type, num_inference_timesteps=10)
    net = nn.Sequential(nn.Linear(2, 128), nn.SiLU(), nn.Linear(128, 128), nn.SiLU(), nn.Linear(128, 1))

    def model(x, step):
        return net(torch.cat([x, (step.float() / cfg.num_train_timesteps).reshape(-1, 1, 1)], -1))

    opt = torch.optim.Adam(net.parameters(), 3e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(1500):
        loss = ddpm_loss(model, gm.sample(256, g), cfg, g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        x = sample_ddpm(model, torch.randn(1000, 1, 1, generator=g), cfg)
    # Two modes at ±1, balanced: a model trained on the other target would not get both.
    assert abs(float((x > 0).float().mean()) - 0.5) < 0.1
    assert float((x.abs() - 1).abs().median()) < 0.2
    assert energy_distance(x, gm.sample(1000, g)) < 0.05


def test_losses_reject_wrong_shapes():
    cfg = DecoderConfig()
    bad = torch.randn(4, 3)
    with pytest.raises(ValueError, match="actions"):
        flow_matching_loss(lambda x, t: x, bad)
    with pytest.raises(ValueError, match="actions"):
        meanflow_loss(lambda x, t, r: x, bad)
    with pytest.raises(ValueError, match="actions"):
        ddpm_loss(lambda x, s: x, bad, cfg)


@pytest.mark.parametrize("prediction_type", ["epsilon", "sample"])
def test_clip_sample_bounds_the_x0_prediction(prediction_type):
    cfg = DecoderConfig(prediction_type=prediction_type, clip_sample=True, normalization_mode="min_max")
    alphas = inference_scheduler(cfg).alphas_cumprod
    far = GaussianMixture.make([[[5.0, -5.0]]], [0.1], dtype=torch.float64)   # data outside [−1, 1]
    noise = torch.randn(64, 1, 2, dtype=torch.float64)
    x = sample_ddpm(far.ddpm_model(alphas, prediction_type), noise, cfg, steps=10)
    assert x.abs().max() <= 1 + 1e-6 and x.abs().min() > 0.9
    unclipped = sample_ddpm(far.ddpm_model(alphas, prediction_type), noise, DecoderConfig(prediction_type=prediction_type), 10)
    assert torch.allclose(unclipped.mean(0), far.means[0], atol=0.05)


# ------------------------------------------------------------------ du/dt: JVP or finite difference
def _gauss_target(gaussian, dtype, dudt):
    z, t, r = (x.to(dtype) for x in _points(64, seed=1))
    g = Gaussian(gaussian.mean.to(dtype), gaussian.std)
    theta = nn.Parameter(torch.ones((), dtype=dtype))
    u, target = meanflow_target(lambda x, tt, rr: theta * g.avg_velocity(x, tt, rr), z, t, r, g.velocity(z, t),
                                dudt=dudt)
    return u, target, g.avg_velocity(z, t, r).double()


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-7), (torch.float32, 2e-2)])
def test_finite_difference_target_matches_the_closed_form_average_velocity(gaussian, dtype, tol):
    """With the exact u and v the identity gives target == u. The central difference's error is
    |t − r|·(h²/6·|u'''| + rounding(u)/h); u = (z_r − z)/(r − t) rounds by eps·|z|/|r − t|, so the
    target's rounding error is about eps·|z|/h: 1.2e-7·3/3e-5 ≈ 1.2e-2 in float32 (h = 3e-5) and
    2.2e-16·3/3.7e-8 ≈ 2e-8 in float64 (h = 3.7e-8); truncation is far smaller on this smooth u."""
    u, target, exact = _gauss_target(gaussian, dtype, "finite_difference")
    _, target_jvp, _ = _gauss_target(gaussian, dtype, "jvp")
    assert u.requires_grad and not target.requires_grad
    assert (target.double() - exact).abs().max() < tol
    assert (target.double() - target_jvp.double()).abs().max() < tol
    # The du/dt term moves the target by far more than the tolerance: the test has teeth.
    z, t, r = _points(64, seed=1)
    assert (gaussian.velocity(z, t) - exact).abs().max() > 20 * tol
    assert losses.fd_step(torch.float32) == 3e-5 and 3e-8 < losses.fd_step(torch.float64) < 4e-8


def _expert_policy(dtype=torch.float32, **kw):
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type="mean_flow", hidden_size=64, num_hidden_layers=2, num_attention_heads=4,
                        num_key_value_heads=2, state_dim=7, action_dim=4, action_chunk_size=16,
                        flow_prediction="sample", **kw)
    return ActionDecoderPolicy(cfg).to(dtype)


def test_finite_difference_target_matches_jvp_on_the_network_in_float32():
    """On the Action Expert (random weights, clean-chunk head) the float32 central difference
    agrees with the float64 JVP to 1e-3 of the target's rms: the time embedding's 4e-3 period
    makes u'' and u''' large in t (|du/dt| up to ~10² here), so truncation (h·ω)²/6 ≈ 4e-4 of the
    fast part and rounding eps/h ≈ 4e-3 of |u| set the error; measured 5e-4–6e-4 over seeds 2–4
    (the CLI's network: docs/benchmarks/meanflow_cost.md). The float32 JVP is 25× closer (2e-5)."""
    policy = _expert_policy()
    g = torch.Generator().manual_seed(2)
    state, a = torch.randn(128, 7, generator=g), torch.randn(128, 16, 4, generator=g)
    t, r, _ = sample_meanflow_times(128, 1.0, 0.4, 1.0, g, dist="uniform")
    e = torch.randn(a.shape, generator=g)
    z, v = (1 - t)[:, None, None] * e + t[:, None, None] * a, a - e

    def target(pol, dtype, dudt):
        cond = pol._prepare({"state": state.to(dtype)})
        return meanflow_target(pol._flow_net, z.to(dtype), t.to(dtype), r.to(dtype), v.to(dtype), dudt=dudt,
                               cond=cond)[1].double()

    ref = target(_expert_policy(torch.float64), torch.float64, "jvp")
    fd, jvp = target(policy, torch.float32, "finite_difference"), target(policy, torch.float32, "jvp")
    rms = lambda x: x.square().mean().sqrt().item()                                      # noqa: E731
    assert rms(fd - ref) < 1e-3 * rms(ref), (rms(fd - ref), rms(ref))
    assert rms(jvp - ref) < 1e-4 * rms(ref)
    # The du/dt term moves the target by far more than the tolerance: the test has teeth.
    assert rms(v.double() - ref) > 100 * 1e-3 * rms(ref)


@pytest.mark.parametrize("t0, r0", [(0.0, 1.0), (0.0, 0.5), (0.25, 0.75), (0.9, 1.0), (0.94, 0.99), (0.99, 1.0)])
def test_finite_difference_target_matches_jvp_at_every_time_pair(t0, r0):
    """Per (t, r), including t = 0 (the difference evaluates t − h < 0) and 1 − t near the clean-chunk
    head's 0.05 floor, with the time embeddings' first layers scaled 16× (u steeper in t, as training
    sharpens it): the float32 central difference stays within 1e-3 of the float64 JVP target's rms
    (measured 4e-4–8e-4), where the du/dt term moves the target by 30–110 %."""
    policy = _expert_policy()
    with torch.no_grad():
        for embed in (policy.model.t_embed, policy.model.r_embed):
            embed.mlp[0].weight.mul_(16)
    p64 = _expert_policy(torch.float64)
    p64.load_state_dict(policy.state_dict())
    g = torch.Generator().manual_seed(2)
    state, a, e = torch.randn(32, 7, generator=g), torch.randn(32, 16, 4, generator=g), torch.randn(32, 16, 4, generator=g)
    t, r = torch.full((32,), t0), torch.full((32,), r0)
    z, v = (1 - t0) * e + t0 * a, a - e

    def target(pol, dtype, dudt):
        cond = pol._prepare({"state": state.to(dtype)})
        return meanflow_target(pol._flow_net, z.to(dtype), t.to(dtype), r.to(dtype), v.to(dtype), dudt=dudt,
                               cond=cond)[1].double()

    ref = target(p64, torch.float64, "jvp")
    rms = lambda x: x.square().mean().sqrt().item()                                      # noqa: E731
    assert rms(target(policy, torch.float32, "finite_difference") - ref) < 1e-3 * rms(ref)
    assert rms(v.double() - ref) > 0.25 * rms(ref)


def test_policy_gradient_is_the_same_with_either_dudt():
    """The whole policy step (row split, times, adaptive weight, stop-gradient, clean-chunk head) gives
    the same parameter gradient in float32 whichever way du/dt is computed: relative difference below
    1e-3 (measured 4e-5), while dropping the du/dt term (every row r = t) moves it by far more."""
    g = torch.Generator().manual_seed(4)
    batch = {"state": torch.randn(64, 7, generator=g), "actions": torch.randn(64, 16, 4, generator=g)}

    def grad(**kw):
        policy = _expert_policy(**kw)
        params = [p for p in policy.parameters() if p.requires_grad and p is not policy.sigma]
        loss = policy.compute_loss(batch, torch.Generator().manual_seed(0)).loss
        return torch.cat([x.flatten() for x in torch.autograd.grad(loss, params)])

    jvp, fd = grad(meanflow_dudt="jvp"), grad(meanflow_dudt="finite_difference")
    assert (fd - jvp).norm() < 1e-3 * jvp.norm(), ((fd - jvp).norm() / jvp.norm()).item()
    assert (grad(meanflow_ratio_r_neq_t=0.0) - jvp).norm() > 0.05 * jvp.norm()


def test_finite_difference_loss_keeps_the_stop_gradient(gaussian):
    """The loss with du/dt by central difference equals a reference with the target detached;
    it also equals the JVP loss up to the difference's error."""
    a = gaussian.sample(64, torch.Generator().manual_seed(3))
    net = nn.Sequential(nn.Linear(5, 32), nn.Tanh(), nn.Linear(32, 3)).double()

    def u(x, t, r):
        return net(torch.cat([x, t.reshape(-1, 1, 1), r.reshape(-1, 1, 1)], -1))

    params = list(net.parameters())
    loss = meanflow_loss(u, a, torch.Generator().manual_seed(7), ratio_r_neq_t=0.25, dudt="finite_difference")
    grads = torch.autograd.grad(loss, params)
    loss_jvp = meanflow_loss(u, a, torch.Generator().manual_seed(7), ratio_r_neq_t=0.25, dudt="jvp")
    grads_jvp = torch.autograd.grad(loss_jvp, params)
    torch.testing.assert_close(loss, loss_jvp, rtol=1e-9, atol=0)
    for x, y in zip(grads, grads_jvp):
        torch.testing.assert_close(x, y, rtol=1e-7, atol=1e-10)

    g = torch.Generator().manual_seed(7)
    t, r, n = sample_meanflow_times(64, 0.25, 0.4, 1.0, g)
    e = torch.randn(a.shape, generator=g, dtype=a.dtype)
    z = (1 - t).reshape(-1, 1, 1) * e + t.reshape(-1, 1, 1) * a
    v = a - e
    out = u(z, t, r)
    dudt = torch.func.jvp(u, (z, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))[1]
    target = v - (t - r).reshape(-1, 1, 1) * dudt
    err_nosg = (out - target).square().mean((1, 2))
    bad = torch.autograd.grad(((err_nosg.detach() + 1e-3).pow(-0.5) * err_nosg).mean(), params)
    assert max((x - y).abs().max() for x, y in zip(bad, grads)) > 1e-4


def test_meanflow_dudt_is_validated():
    a = torch.randn(8, 16, 4)
    with pytest.raises(ValueError, match=r"meanflow_dudt: expected one of \['jvp', 'finite_difference'\], got 'fd'"):
        meanflow_loss(lambda x, t, r: x, a, dudt="fd")
    with pytest.raises(ValueError, match=r"meanflow_dudt: expected one of .*got 'exact'"):
        DecoderConfig(decoder_type="mean_flow", meanflow_dudt="exact")
    with pytest.raises(ValueError, match="meanflow_dudt: 'finite_difference' needs float32 or float64 inputs, got torch.bfloat16"):
        meanflow_target(lambda x, t, r: x, a.bfloat16(), torch.rand(8).bfloat16(), torch.ones(8).bfloat16(),
                        a.bfloat16(), dudt="finite_difference")
    bf16 = _expert_policy(meanflow_dudt="finite_difference").to(torch.bfloat16)
    batch = {"state": torch.randn(8, 7), "actions": a}
    with pytest.raises(ValueError, match="meanflow_dudt: 'finite_difference' needs float32 or float64 weights, "
                                         "got torch.bfloat16"):
        bf16.compute_loss(batch)
    bf16.config.meanflow_dudt = "jvp"
    assert torch.isfinite(bf16.compute_loss(batch).loss)


def test_policy_trains_with_the_configured_dudt():
    """`DecoderConfig.meanflow_dudt` reaches the loss: same weights and noise, both methods give the
    same loss up to the difference's error, and the finite difference calls no JVP."""
    batch = {"state": torch.randn(32, 7), "actions": torch.randn(32, 16, 4)}
    out = {}
    for dudt in ("jvp", "finite_difference"):
        policy = _expert_policy(meanflow_dudt=dudt)
        calls = []
        real_jvp = torch.func.jvp
        torch.func.jvp = lambda *a, **k: calls.append(1) or real_jvp(*a, **k)
        try:
            out[dudt] = policy.compute_loss(batch, torch.Generator().manual_seed(0)).loss
        finally:
            torch.func.jvp = real_jvp
        assert bool(calls) == (dudt == "jvp")
    torch.testing.assert_close(out["finite_difference"], out["jvp"], rtol=1e-3, atol=0)


def test_finite_difference_under_autocast_differences_in_float32():
    """Mixed precision: the difference call runs with autocast off, so du/dt equals the float32 one."""
    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(4 + 2, 32), torch.nn.Tanh(), torch.nn.Linear(32, 4))
    u = lambda x, t, r: net(torch.cat([x, t[:, None, None].expand(-1, x.shape[1], 1),
                                       r[:, None, None].expand(-1, x.shape[1], 1)], -1))
    z, v = torch.randn(8, 16, 4), torch.randn(8, 16, 4)
    t, r = torch.rand(8) * 0.5, 0.5 + torch.rand(8) * 0.5
    plain = dudt_finite_difference(u, z, t, r, v)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = dudt_finite_difference(u, z, t, r, v)
        noisy = (u(z + 3e-5 * v, t + 3e-5, r).float() - u(z - 3e-5 * v, t - 3e-5, r).float()) / 6e-5
    torch.testing.assert_close(mixed, plain, rtol=0, atol=0)
    assert (noisy - plain).abs().max() > 10 * plain.abs().max() * 1e-3      # in bf16 it would be noise
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert torch.isfinite(meanflow_loss(u, torch.randn(8, 16, 4), dudt="finite_difference")).all()


def test_finite_difference_in_one_call_gives_the_two_call_loss_and_gradients():
    """`fd_one_call=True` puts the 2n shifted rows into u's call (one call over B + 2n rows, the
    conditioning repeated for them): same loss and gradients as two calls, which CPU takes by
    default; under autocast one call is refused (the difference must run in float32)."""
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(4 + 2 + 3, 32), nn.Tanh(), nn.Linear(32, 4)).double()
    calls = []

    def u(x, t, r, state):                                    # state: [rows, 3], batch-aligned conditioning
        calls.append(x.shape[0])
        h = x.shape[1]
        return net(torch.cat([x, t[:, None, None].expand(-1, h, 1), r[:, None, None].expand(-1, h, 1),
                              state[:, None].expand(-1, h, 3)], -1))

    a, state = torch.randn(32, 16, 4, dtype=torch.float64), torch.randn(32, 3, dtype=torch.float64)
    params, out = list(net.parameters()), {}
    for one_call in (True, False, None):
        calls.clear()
        loss = meanflow_loss(u, a, torch.Generator().manual_seed(5), {"state": state}, ratio_r_neq_t=0.25,
                             dudt="finite_difference", fd_one_call=one_call)
        out[one_call] = (loss, torch.autograd.grad(loss, params), list(calls))
    assert out[True][2] == [32 + 2 * 8] and out[False][2] == [32, 2 * 8] and out[None][2] == out[False][2]
    torch.testing.assert_close(out[True][0], out[False][0], rtol=1e-12, atol=0)
    for x, y in zip(out[True][1], out[False][1]):
        torch.testing.assert_close(x, y, rtol=1e-10, atol=1e-14)
    with torch.autocast("cpu", dtype=torch.bfloat16), pytest.raises(
            ValueError, match="fd_one_call: expected False or None under autocast .*got True"):
        meanflow_loss(u, a.float(), cond={"state": state.float()}, dudt="finite_difference", fd_one_call=True)


def test_split_target_is_exact_for_the_true_average_velocity(gaussian):
    """target="split": the exact average velocity is additive over sub-intervals, so with the
    oracle's u every r ≠ t row's target equals u (zero loss at ratio 1); the r = t rows still
    regress the sampled a − e; a wrong sub-interval weighting would not vanish."""
    a = gaussian.sample(64, torch.Generator().manual_seed(3))
    exact = gaussian.avg_velocity
    loss = meanflow_loss(exact, a, torch.Generator().manual_seed(1), ratio_r_neq_t=1.0, target="split")
    assert loss.item() < 1e-20
    assert meanflow_loss(exact, a, torch.Generator().manual_seed(1), ratio_r_neq_t=0.0, target="split") > 1e-2
    swapped = lambda x, t, r: exact(x, t, r) * (1 + 0.1 * (r - t)).reshape(-1, 1, 1)     # noqa: E731  not additive
    assert meanflow_loss(swapped, a, torch.Generator().manual_seed(1), ratio_r_neq_t=1.0, target="split") > 1e-6
    with pytest.raises(ValueError, match=r"target: expected one of \['identity', 'split'\], got 'shortcut'"):
        meanflow_loss(exact, a, target="shortcut")
    with pytest.raises(ValueError, match=r"tangent: applies to target='identity'; .*got 'boundary'"):
        meanflow_loss(exact, a, target="split", tangent="boundary")


def test_policy_trains_with_the_configured_target():
    """`DecoderConfig.meanflow_target="split"` reaches the loss: u over the batch, then two no-grad
    calls over the r ≠ t rows (no du/dt, so no difference call and no JVP); it needs no float32."""
    batch = {"state": torch.randn(32, 7), "actions": torch.randn(32, 16, 4)}
    policy = _expert_policy(meanflow_target="split")
    rows, grad = [], []
    net = policy._flow_net
    policy._flow_net = lambda x, t, r, **c: rows.append(x.shape[0]) or grad.append(torch.is_grad_enabled()) or net(x, t, r, **c)
    loss = policy.compute_loss(batch, torch.Generator().manual_seed(0)).loss
    n = round(policy.config.meanflow_ratio_r_neq_t * 32)
    assert rows == [32, n, n] and grad == [True, False, False] and torch.isfinite(loss)
    bf16 = _expert_policy(meanflow_target="split").to(torch.bfloat16)
    assert torch.isfinite(bf16.compute_loss(batch).loss)


@pytest.mark.parametrize("kw, match", [
    ({"ratio_r_neq_t": -0.25}, r"^ratio_r_neq_t: expected a fraction of the rows in \[0, 1\], got -0.25$"),
    ({"ratio_r_neq_t": 1.5}, r"^ratio_r_neq_t: expected a fraction of the rows in \[0, 1\], got 1.5$"),
    ({"ratio_r_neq_t": -0.25, "dudt": "finite_difference"}, r"^ratio_r_neq_t: "),
    ({"adaptive_c": -1.0}, r"^adaptive_c: expected a positive constant"),
    ({"adaptive_p": -0.5}, r"^adaptive_p: expected a power >= 0"),
    ({"time_std": 0.0}, r"^time_std: expected a positive std"),
])
def test_meanflow_loss_refuses_out_of_range_numbers_in_one_line(kw, match):
    u = lambda x, t, r: 0.3 * x                                                 # noqa: E731
    with pytest.raises(ValueError, match=match):
        meanflow_loss(u, torch.randn(8, 4, 2), torch.Generator().manual_seed(0), **kw)
