"""SDE samplers against the closed-form mixture velocity and score: marginals, log-probs,
gradient routing, stability."""

import math

import pytest
import torch
from torch import nn

from action_decoder import (ChurnSigma, DecoderConfig, ExploringSigma, FixedSigma, LearnableSigma,
                            chain_log_prob, make_sigma, sample_sde, velocity_from_meanflow)
from action_decoder.oracles import Gaussian, GaussianMixture, energy_distance

N = 2000


@pytest.fixture(scope="module")
def mixture():
    return GaussianMixture.make([[[1.5, 0.5]], [[-1.0, -1.0]]], [0.3, 0.5], [0.4, 0.6])


def reference_em(mixture, noise, eps, sigma, steps, sign=+1.0):
    """Independent Euler–Maruyama with the oracle's own score (not derived from v)."""
    x, states = noise.clone(), [noise]
    grid = torch.linspace(0, 1, steps + 1, dtype=torch.float64)
    for k in range(steps):
        t = grid[k].expand(len(x))
        dt = float(grid[k + 1] - grid[k])
        s = float(sigma(grid[k:k + 1]))
        drift = mixture.velocity(x, t) + sign * 0.5 * s ** 2 * mixture.score(x, t)
        x = x + drift * dt + s * math.sqrt(dt) * eps[:, k]
        states.append(x)
    return torch.stack(states, 1)


def _floor(mixture, t=1.0, seed=50):
    g = torch.Generator().manual_seed(seed)
    draw = mixture.sample if t == 1.0 else (lambda n, g: mixture.marginal_sample(n, t, g))
    return 3 * max(energy_distance(draw(N, g), draw(N, g)) for _ in range(3))


SCHEDULES = {
    "fixed-0.8": lambda: FixedSigma(0.8),
    "fixed-1.5": lambda: FixedSigma(1.5),
    "churn": lambda: ChurnSigma(0.7, 1e-4),
    "explore": lambda: ExploringSigma(0.7),
    "learnable": lambda: LearnableSigma(ExploringSigma(0.7), init=0.5),
}


@pytest.mark.parametrize("name", list(SCHEDULES))
def test_sde_preserves_marginals(mixture, name):
    sigma = SCHEDULES[name]()
    g = torch.Generator().manual_seed(1)
    noise = torch.randn(N, 1, 2, generator=g, dtype=torch.float64)
    res = sample_sde(mixture.velocity, noise, steps=200, sigma=sigma, generator=g, clip_t=1e-3)
    assert energy_distance(res.actions, mixture.sample(N, g)) < _floor(mixture)
    # Not only the endpoint: the state at t = 0.5 has the exact marginal p_0.5.
    assert energy_distance(res.chain[:, 100], mixture.marginal_sample(N, 0.5, g)) < _floor(mixture, 0.5)


@pytest.mark.parametrize("name", ["fixed-0.8", "fixed-1.5"])
def test_sample_sde_equals_independent_em_and_wrong_sign_fails(mixture, name):
    sigma = SCHEDULES[name]()
    g = torch.Generator().manual_seed(2)
    noise = torch.randn(N, 1, 2, generator=g, dtype=torch.float64)
    res = sample_sde(mixture.velocity, noise, steps=100, sigma=sigma, generator=g, clip_t=1e-3)
    ref = reference_em(mixture, noise, res.eps, sigma, 100)
    assert torch.allclose(res.chain, ref, atol=1e-6)
    wrong = reference_em(mixture, noise, res.eps, sigma, 100, sign=-1.0)
    floor = _floor(mixture, 0.5)
    assert energy_distance(wrong[:, 50], mixture.marginal_sample(N, 0.5, g)) > 5 * floor


def test_log_probs_match_torch_normal_and_forms_agree(mixture):
    g = torch.Generator().manual_seed(3)
    noise = torch.randn(64, 4, 2, dtype=torch.float64, generator=g)
    sigma = ExploringSigma(0.7)
    full = sample_sde(mixture.velocity, noise, 10, sigma, generator=torch.Generator().manual_seed(9),
                      return_logprob=True, logprob="full")
    eps = sample_sde(mixture.velocity, noise, 10, sigma, generator=torch.Generator().manual_seed(9),
                     return_logprob=True, logprob="eps")
    ref = torch.distributions.Normal(full.means, full.stds[..., None, None]).log_prob(full.chain[:, 1:]).sum((-2, -1))
    assert torch.allclose(full.step_log_probs, ref, atol=1e-9)
    assert torch.allclose(eps.step_log_probs, ref, atol=1e-9)
    assert torch.allclose(full.log_prob, ref.sum(1))
    # The means are those of the marginal-preserving drift, computed from the oracle's score.
    grid = full.grid
    x, t = full.chain[:, 3], grid[3].expand(64)
    s = sigma(grid[3:4])
    mean = x + (mixture.velocity(x, t) + 0.5 * s ** 2 * mixture.score(x, t)) * (grid[4] - grid[3])
    assert torch.allclose(full.means[:, 3], mean, atol=1e-9)
    # The recorded chain re-scored under the same velocity: PPO ratio exactly 1.
    again = chain_log_prob(mixture.velocity, full.chain, sigma, grid=full.grid)
    assert torch.allclose(again, full.step_log_probs, atol=1e-9)
    mean_form = sample_sde(mixture.velocity, noise, 10, sigma, generator=torch.Generator().manual_seed(9),
                           return_logprob=True, reduce="mean")
    assert torch.allclose(mean_form.step_log_probs, ref / 8)


def test_float32_ratio_is_one_with_a_network():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(3, 64), nn.Tanh(), nn.Linear(64, 2))

    def velocity(x, t):
        return net(torch.cat([x, t.reshape(-1, 1, 1).expand(-1, x.shape[1], 1)], -1))

    sigma = ExploringSigma(0.7)
    with torch.no_grad():
        res = sample_sde(velocity, torch.randn(32, 8, 2), 10, sigma, return_logprob=True)
        again = chain_log_prob(velocity, res.chain, sigma, grid=res.grid)
    assert res.step_log_probs.dtype == torch.float32
    assert torch.allclose((again - res.step_log_probs).exp(), torch.ones(32, 10), atol=1e-4)


def test_gradient_routing():
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(3, 32), nn.Tanh(), nn.Linear(32, 2))

    def velocity(x, t):
        return net(torch.cat([x, t.reshape(-1, 1, 1).expand(-1, x.shape[1], 1)], -1))

    sigma = LearnableSigma(ExploringSigma(0.7), init=0.3)
    params = list(net.parameters()) + [sigma.log_scale]
    res = sample_sde(velocity, torch.randn(16, 4, 2), 5, sigma, return_logprob=True, logprob="eps")
    grads = torch.autograd.grad(res.log_prob.sum(), params, allow_unused=True, retain_graph=True)
    assert all(g is None or torch.all(g == 0) for g in grads[:-1])     # entropy: not the network
    assert grads[-1] is not None and grads[-1].abs() > 0               # only σ
    # The reparameterised actions do reach the network (the Q-term path).
    assert torch.autograd.grad(res.actions.sum(), net[0].weight, retain_graph=True)[0].abs().sum() > 0
    # A stored (detached) chain re-scored: gradient reaches the network (PPO).
    lp = chain_log_prob(velocity, res.chain.detach(), sigma, grid=res.grid)
    g_net = torch.autograd.grad(lp.sum(), net[0].weight)[0]
    assert g_net.abs().sum() > 0


@pytest.mark.parametrize("name", list(SCHEDULES))
def test_no_nan_or_inf_for_any_step_count(mixture, name):
    sigma = SCHEDULES[name]()
    noise = torch.randn(8, 2, 2, generator=torch.Generator().manual_seed(0))

    def bf16_velocity(x, t):
        return mixture.velocity(x.double(), t.double()).to(torch.bfloat16)

    for steps in range(1, 101):
        res = sample_sde(bf16_velocity, noise.bfloat16(), steps, sigma, return_logprob=True,
                         generator=torch.Generator().manual_seed(steps))
        assert res.actions.dtype == torch.bfloat16 and res.log_prob.dtype == torch.float32
        for x in (res.chain, res.step_log_probs, res.log_prob):
            assert torch.isfinite(x).all(), (name, steps)


def test_mf_sde_boundary_keeps_gaussian_mean_and_std():
    gauss = Gaussian(torch.tensor([[0.5, -1.0]], dtype=torch.float64), 0.3)
    g = torch.Generator().manual_seed(4)
    noise = torch.randn(8000, 1, 2, dtype=torch.float64, generator=g)
    v = velocity_from_meanflow(gauss.avg_velocity, "boundary")
    out = sample_sde(v, noise, 200, FixedSigma(0.8), generator=g, clip_t=1e-3).actions
    assert torch.allclose(out.mean(0), gauss.mean, atol=0.02)
    assert torch.allclose(out.std(0), torch.full_like(gauss.mean, 0.3), atol=0.02)


def test_squash_once_matches_transformed_distribution():
    mean_fn = lambda x, t: torch.full_like(x, 0.4)   # noqa: E731
    noise = torch.randn(16, 3, 2, dtype=torch.float64)
    res = sample_sde(mean_fn, noise, 1, FixedSigma(0.9), return_logprob=True, squash=True,
                     generator=torch.Generator().manual_seed(0))
    base = torch.distributions.Normal(res.means[:, 0], res.stds[:, 0, None, None])
    dist = torch.distributions.TransformedDistribution(base, [torch.distributions.TanhTransform()])
    assert torch.allclose(res.actions, torch.tanh(res.chain[:, -1]))
    assert torch.allclose(res.log_prob, dist.log_prob(res.actions).sum((-2, -1)), atol=1e-6)
    assert torch.allclose(res.step_log_probs.sum(1) - res.squash_log_det, res.log_prob)


def test_generator_reproducibility(mixture):
    noise = torch.randn(4, 2, 2, dtype=torch.float64)
    a = sample_sde(mixture.velocity, noise, 5, 0.5, generator=torch.Generator().manual_seed(3))
    b = sample_sde(mixture.velocity, noise, 5, 0.5, generator=torch.Generator().manual_seed(3))
    c = sample_sde(mixture.velocity, noise, 5, 0.5, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a.chain, b.chain) and not torch.equal(a.chain, c.chain)


def test_schedules():
    t = torch.tensor([0.0, 0.1, 0.5, 1.0], dtype=torch.float64)
    churn = ChurnSigma(0.7, 1e-4)(t)
    assert torch.allclose(churn, 0.7 * torch.sqrt(1 - t / (t + 1e-4)))
    assert churn[1] < 0.05 * churn[0]   # documented: churn stops exploring after t ≈ 0.1
    explore = ExploringSigma(0.7)(t)
    assert explore[2] > 0.5 and explore[3] == 0 and torch.isfinite(explore).all()
    learn = LearnableSigma(ChurnSigma(0.7, 1e-4), init=0.1)
    assert learn.multiplier == torch.tensor(0.1)   # exactly init (GO-1 started at softplus(0.1))
    assert torch.equal(learn(t), ChurnSigma(0.7, 1e-4)(t) * 0.1)
    assert isinstance(make_sigma(DecoderConfig(flow_sde_mode="fixed", flow_sde_s_churn=0.3)), FixedSigma)
    assert isinstance(make_sigma(DecoderConfig(flow_sde_mode="explore")), ExploringSigma)
    made = make_sigma(DecoderConfig(flow_sde_learn_sigma=True, flow_sde_sigma_init=0.25))
    assert isinstance(made, LearnableSigma) and made.multiplier == torch.tensor(0.25)
    assert isinstance(made.base, ChurnSigma)


def test_bad_arguments():
    f = lambda x, t: x   # noqa: E731
    noise = torch.randn(2, 3, 1)
    for kwargs, field in [({"logprob": "exact"}, "logprob"), ({"reduce": "max"}, "reduce"),
                          ({"clip_t": 0.0}, "clip_t"), ({"steps": 0}, "steps"),
                          ({"sigma": "big"}, "sigma")]:
        with pytest.raises(ValueError, match=field):
            sample_sde(f, noise, **kwargs)
    res = sample_sde(f, noise, 4, 0.5)
    with pytest.raises(ValueError, match="grid"):
        chain_log_prob(f, res.chain, 0.5, grid=torch.linspace(0, 1, 4))
    with pytest.raises(ValueError, match="chain"):
        chain_log_prob(f, res.chain[:, 0], 0.5)


# ---------------------------------------------------------------- grid cache, log-prob contract
def _net_velocity(seed=0, width=32):
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(3, width), nn.Tanh(), nn.Linear(width, 2))

    def velocity(x, t):
        return net(torch.cat([x, t.reshape(-1, 1, 1).expand(-1, x.shape[1], 1)], -1))
    return net, velocity


def test_grid_built_under_inference_mode_serves_differentiable_calls():
    from action_decoder.flows import paths
    paths._uniform_steps.cache_clear()
    net, velocity = _net_velocity()
    noise = torch.randn(5, 4, 2)
    with torch.inference_mode():
        sample_sde(velocity, noise, 7, 0.5, return_logprob=True)
        sample_sde(velocity, noise, 7, 0.5)
    sigma = LearnableSigma(ExploringSigma(0.7), init=0.5)
    res = sample_sde(velocity, noise, 7, sigma, return_logprob=True, logprob="full")
    res.log_prob.sum().backward()
    assert sigma.log_scale.grad is not None and net[0].weight.grad is not None
    lp = chain_log_prob(velocity, res.chain.detach(), sigma, grid=None)
    lp.sum().backward()


def test_returned_grid_is_a_copy():
    seen = []

    def velocity(x, t):
        seen.append(float(t[0]))
        return -x

    noise = torch.randn(3, 2, 2)
    res = sample_sde(velocity, noise, 6, 0.5)
    res.grid.mul_(0.5)
    seen.clear()
    again = sample_sde(velocity, noise, 6, 0.5)
    assert torch.allclose(torch.tensor(seen), torch.linspace(0, 1, 7)[:-1])
    assert torch.allclose(again.grid, torch.linspace(0, 1, 7))


SDE_MODES = ["churn", "explore", "fixed"]


@pytest.mark.parametrize("mode", SDE_MODES)
@pytest.mark.parametrize("decoder_type", ["flow_matching", "mean_flow"])
def test_default_config_log_probs_rescore_to_ratio_one(mode, decoder_type):
    from test_policy import batch, make
    policy = make(decoder_type, flow_sde_mode=mode, num_inference_timesteps=10).eval()
    assert policy.config.flow_sde_logprob_sigma_only          # the default: the ε form's gradient
    b = batch(b=16, actions=False)
    out = policy(b, sampler="sde", return_logprob=True, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        again = policy.chain_log_prob(b, out.chain, out.grid)
    assert out.step_log_probs.dtype == torch.float32
    assert (again - out.step_log_probs).exp().sub(1).abs().max() < 1e-4
    assert torch.allclose(out.log_prob, out.step_log_probs.sum(1))


@pytest.mark.parametrize("name", ["churn", "explore", "fixed-0.8"])
def test_returned_log_probs_are_the_chain_density_in_both_forms(name):
    _, velocity = _net_velocity()
    sigma = SCHEDULES[name]()
    with torch.no_grad():
        for form in ("full", "eps"):
            res = sample_sde(velocity, torch.randn(32, 8, 2), 10, sigma, return_logprob=True, logprob=form,
                             generator=torch.Generator().manual_seed(1))
            again = chain_log_prob(velocity, res.chain, sigma, grid=res.grid)
            assert (again - res.step_log_probs).exp().sub(1).abs().max() < 1e-4, form


def test_gradient_contract_of_the_two_forms():
    net, velocity = _net_velocity()
    sigma = LearnableSigma(ExploringSigma(0.7), init=0.3)
    params = list(net.parameters()) + [sigma.log_scale]
    noise = torch.randn(16, 4, 2)

    def run(form):
        return sample_sde(velocity, noise, 5, sigma, return_logprob=True, logprob=form,
                          generator=torch.Generator().manual_seed(0))

    # "full": the chain is data, the gradient is that of re-scoring it (score function / PPO).
    full = run("full")
    g_full = torch.autograd.grad(full.log_prob.sum(), params)
    rescored = chain_log_prob(velocity, full.chain.detach(), sigma, grid=full.grid).sum()
    g_ref = torch.autograd.grad(rescored, params)
    assert g_full[0].abs().sum() > 0
    for a, b in zip(g_full, g_ref):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    # "eps": the same value, the ε form's gradient: σ only, −Σ ∂log std/∂θ_σ = −K·H·D·B per unit log-scale.
    eps = run("eps")
    assert torch.allclose(eps.log_prob, full.log_prob)
    g_eps = torch.autograd.grad(eps.log_prob.sum(), params, allow_unused=True)
    assert all(g is None or torch.all(g == 0) for g in g_eps[:-1])
    assert torch.allclose(g_eps[-1], torch.tensor(-16.0 * 5 * 4 * 2))


@pytest.mark.parametrize("sigma_only", [True, False])
def test_policy_logprob_sigma_only_routes_the_gradient(sigma_only):
    from test_policy import batch, make
    policy = make("flow_matching", flow_sde_learn_sigma=True, flow_sde_logprob_sigma_only=sigma_only)
    b = batch(actions=False)
    out = policy.sample(b, sampler="sde", return_logprob=True, generator=torch.Generator().manual_seed(0))
    out.log_prob.sum().backward()
    net_grad = sum(float(p.grad.abs().sum()) for p in policy.model.parameters() if p.grad is not None)
    assert float(policy.sigma.log_scale.grad.abs()) > 0
    assert (net_grad == 0) == sigma_only
    if not sigma_only:       # the score-function gradient is that of re-scoring the chain
        policy.zero_grad()
        policy.chain_log_prob(b, out.chain.detach(), out.grid).sum().backward()
        again = sum(float(p.grad.abs().sum()) for p in policy.model.parameters() if p.grad is not None)
        assert again == pytest.approx(net_grad, rel=1e-4)


def test_nonpositive_or_nonfinite_sigma_with_log_probs_raises():
    f = lambda x, t: -x   # noqa: E731
    noise = torch.randn(2, 3, 1)

    def nan_late(t):
        return torch.where(t > 0.6, torch.full_like(t, float("nan")), torch.full_like(t, 0.5))

    for sigma, value in [(0.0, "0 "), (-0.3, "-0.3 "), (nan_late, "nan ")]:
        with pytest.raises(ValueError, match=rf"sigma: expected σ\(t\) > 0 .*got σ\(.*\) = {value}"):
            sample_sde(f, noise, 5, sigma, return_logprob=True)
        res = sample_sde(f, noise, 5, sigma if sigma != nan_late else 0.5)   # sampling alone is fine
        with pytest.raises(ValueError, match="sigma"):
            chain_log_prob(f, res.chain, sigma, grid=res.grid)
    with pytest.raises(ValueError, match=r"σ\(0.8\)"):
        sample_sde(f, noise, 5, nan_late, return_logprob=True)
    assert torch.allclose(sample_sde(f, noise, 5, 0.0).actions, noise * 0.8 ** 5)   # σ = 0: the ODE


@pytest.mark.parametrize("steps", [4, 20])
def test_exploring_sigma_clamps_at_the_first_interior_grid_point(steps):
    from test_policy import make
    a = 0.7
    res = sample_sde(lambda x, t: -x, torch.randn(2, 1, 1), steps, ExploringSigma(a))
    # σ(0) = a·√((1 − 0)/(1/K)): std_0 = σ(0)·√(1/K) = a for any K.
    assert res.stds[0, 0] == pytest.approx(a, rel=1e-5)
    t = torch.linspace(0, 1, steps + 1)[:-1]
    sig = ExploringSigma(a)(t)
    assert sig[0] == pytest.approx(a * math.sqrt(steps), rel=1e-5)
    assert sig[1] == pytest.approx(a * math.sqrt(steps - 1), rel=1e-5)
    assert ExploringSigma(a, t_min=0.1)(t)[0] == pytest.approx(a * math.sqrt(10), rel=1e-5)
    assert ExploringSigma(a)(torch.zeros(1)) == pytest.approx(a)       # one step: clamp at 1
    assert make_sigma(DecoderConfig(flow_sde_mode="explore", flow_sde_t_min=0.25)).t_min == 0.25
    # The RL fine-tuning policy ("explore", config built by dataclasses.replace) follows the grid.
    from action_decoder.rl.sde_policy import finetune_policy
    policy = finetune_policy(make("flow_matching"), sigma=a, learn_sigma=False, steps=steps)
    assert policy.sigma(t)[0] == pytest.approx(a * math.sqrt(steps), rel=1e-5)


def test_bad_t_min_names_the_field():
    for bad in (0.0, -0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="flow_sde_t_min"):
            DecoderConfig(flow_sde_t_min=bad)
        with pytest.raises(ValueError, match="t_min"):
            ExploringSigma(0.7, t_min=bad)
    with pytest.raises(ValueError, match="meanflow_sde_velocity"):
        DecoderConfig(meanflow_sde_velocity="jvp")


def test_meanflow_identity_velocity_from_config_and_at_run_time():
    from test_policy import batch, make
    b = batch(b=4, actions=False)
    noise = torch.randn(4, 8, 3, generator=torch.Generator().manual_seed(0))
    ident = make("mean_flow", meanflow_sde_velocity="identity").eval()
    bound = make("mean_flow").eval()

    def run(policy, **kw):
        return policy.sample(b, sampler="sde", return_logprob=True, noise=noise,
                             generator=torch.Generator().manual_seed(1), **kw)

    with torch.no_grad():
        out = run(ident)
        v = velocity_from_meanflow(ident.bind(b).avg_velocity, "identity")
        ref = sample_sde(v, noise, 4, ident.sigma, generator=torch.Generator().manual_seed(1),
                         clip_t=ident.config.flow_sde_clip_t)
        assert torch.allclose(out.chain, ref.chain, atol=1e-5)
        assert not torch.allclose(out.chain, run(bound).chain, atol=1e-3)     # a different velocity
        # The run-time choice overrides the config both ways; re-scoring with it gives ratio 1.
        assert torch.allclose(run(ident, meanflow_velocity="boundary").chain, run(bound).chain)
        over = run(bound, meanflow_velocity="identity")
        assert torch.allclose(over.chain, out.chain)
        again = bound.chain_log_prob(b, over.chain, over.grid, meanflow_velocity="identity")
        assert (again - over.step_log_probs).exp().sub(1).abs().max() < 1e-4
    with torch.inference_mode():            # evaluation rollouts: the JVP runs there too
        acts = ident.predict_action_chunk(b, sampler="sde", generator=torch.Generator().manual_seed(1))
        assert torch.isfinite(acts).all()
    with pytest.raises(ValueError, match="meanflow_velocity"):
        bound.sample(b, sampler="sde", meanflow_velocity="jvp")


def test_per_row_generators_make_each_row_independent_of_its_batch():
    """One generator per row: a row's SDE sample (noise and every step's ε) is the one it gets alone."""
    from action_decoder.flows.paths import randn_rows

    velocity = lambda x, t: -x                                                   # noqa: E731
    gens = lambda seeds: [torch.Generator().manual_seed(s) for s in seeds]      # noqa: E731
    noise = randn_rows(3, (4, 2), gens([1, 2, 3]))
    batched = sample_sde(velocity, noise, 5, sigma=0.5, generator=gens([11, 12, 13]), return_logprob=True)
    for b, (ns, es) in enumerate(zip([1, 2, 3], [11, 12, 13])):
        alone = sample_sde(velocity, randn_rows(1, (4, 2), gens([ns])), 5, sigma=0.5, generator=gens([es]),
                           return_logprob=True)
        torch.testing.assert_close(batched.chain[b:b + 1], alone.chain, rtol=0, atol=1e-6)
        torch.testing.assert_close(batched.step_log_probs[b:b + 1], alone.step_log_probs, rtol=0, atol=1e-4)
    with pytest.raises(ValueError, match="generator: expected a torch.Generator or a list of 3"):
        sample_sde(velocity, noise, 5, sigma=0.5, generator=gens([1, 2]))


def test_editing_the_returned_actions_in_place_leaves_the_chain_and_its_log_probs():
    velocity = lambda x, t: -x                                                  # noqa: E731
    res = sample_sde(velocity, torch.randn(2, 3, 1), 4, 0.5, return_logprob=True,
                     generator=torch.Generator().manual_seed(0))
    chain = res.chain.clone()
    res.actions.clamp_(-0.05, 0.05)                        # what a rollout does before stepping an environment
    assert torch.equal(res.chain, chain)
    again = chain_log_prob(velocity, res.chain, 0.5, grid=res.grid)
    torch.testing.assert_close(again, res.step_log_probs)


def test_squashed_eps_log_prob_keeps_its_gradient_on_sigma_only():
    """squash=True with the ε form: the tanh log-det enters log_prob's value, not its gradient, so the
    network gets none and σ's log-scale gets exactly −B·K·H·D (the ε form's −Σ ∂log std_k)."""
    net, velocity = _net_velocity()
    sigma = LearnableSigma(ExploringSigma(0.7), init=0.3)
    params = list(net.parameters()) + [sigma.log_scale]
    noise = torch.randn(16, 4, 2, generator=torch.Generator().manual_seed(1)) * 2
    kw = dict(return_logprob=True, squash=True, generator=torch.Generator().manual_seed(0))
    eps = sample_sde(velocity, noise, 5, sigma, logprob="eps", **kw)
    full = sample_sde(velocity, noise, 5, sigma, logprob="full", generator=torch.Generator().manual_seed(0),
                      return_logprob=True, squash=True)
    assert torch.allclose(eps.log_prob, full.log_prob)                      # the same value
    g = torch.autograd.grad(eps.log_prob.sum(), params, allow_unused=True)
    assert all(x is None or torch.all(x == 0) for x in g[:-1])
    assert torch.allclose(g[-1], torch.tensor(-16.0 * 5 * 4 * 2))
    # the log-det field itself is the pathwise one (the actions reach the network)
    grad_det = torch.autograd.grad(eps.squash_log_det.sum(), net[0].weight)[0]
    assert grad_det.abs().sum() > 0


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nonfinite_sigma_without_log_probs_is_refused_in_one_line(bad):
    f = lambda x, t: -x   # noqa: E731
    with pytest.raises(ValueError, match=rf"^sigma: expected σ\(t\) finite on every step, got σ\(0\) = {bad}"):
        sample_sde(f, torch.randn(2, 3, 1), 5, bad)
    late = lambda t: torch.where(t > 0.6, torch.full_like(t, bad), torch.full_like(t, 0.5))   # noqa: E731
    with pytest.raises(ValueError, match=r"σ\(0.8\)"):
        sample_sde(f, torch.randn(2, 3, 1), 5, late)


@pytest.mark.parametrize("name", ["churn", "explore", "fixed"])
@pytest.mark.parametrize("steps", [1, 2, 3])
def test_gaussian_target_std_is_what_sampling_gives(name, steps):
    """The closed-form std of `sample_sde` on N(0, 0.4²) with its exact velocity, against sampling:
    explore at σ(0) = 0.7 gives 0.742 at K = 1 and 0.507 at K = 2."""
    from action_decoder.flows.samplers import gaussian_target_std

    sigma = {"churn": ChurnSigma(0.7), "explore": ExploringSigma(0.7), "fixed": FixedSigma(0.7)}[name]
    oracle = Gaussian(torch.zeros(8, 3, dtype=torch.float64), 0.4)
    noise = torch.randn(4000, 8, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = sample_sde(oracle.velocity, noise, steps, sigma, generator=torch.Generator().manual_seed(1)).actions
    assert float(out.std()) == pytest.approx(gaussian_target_std(sigma, steps), rel=0.02)
    if name == "explore" and steps < 3:
        assert round(gaussian_target_std(sigma, steps), 3) == {1: 0.742, 2: 0.507}[steps]
