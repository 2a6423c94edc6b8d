"""Noise-space RL (`finetune --algo dsrl`): the noise actor's density and trust region against
torch.distributions, the critic and actor updates against oracle critics, the replay buffer, a
bit-exact resume, and the saved policy acting through the CLI, the core policy and the plugin's
config mapping."""

import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from torch.distributions import AffineTransform, Normal, TanhTransform, TransformedDistribution, kl_divergence

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.cli import main
from action_decoder.noise_actor import NoiseActor, kl_to_prior
from action_decoder.rl.dsrl import (KLMultiplier, alias_mode, decode, decode_pool, dsrl_policy, dsrl_update,
                                   noise_actor_fn)
from action_decoder.rl.sac import ReplayBuffer, Temperature, make_target
from action_decoder.rl.critics import QEnsemble, TwinQ, subset_min

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_rl import D, H, S, _bc  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _actor(bound=2.5, seed=0):
    torch.manual_seed(seed)
    actor = NoiseActor(S, None, H, D, hidden=16, bound=bound)
    for p in actor.head.parameters():              # away from the zero start, so mean and std vary
        p.data.normal_(0, 0.3)
    return actor


def test_untrained_actor_draws_the_decoders_own_noise():
    actor = NoiseActor(S, None, H, D, hidden=16, bound=2.5)
    mean, log_std = actor(torch.randn(5, S))
    assert mean.abs().max() == 0 and log_std.abs().max() < 1e-6
    assert actor.act(torch.randn(5, S)).abs().max() == 0
    w = torch.randn(5, H, D, generator=torch.Generator().manual_seed(2))
    drawn = actor.sample(torch.randn(5, S), generator=torch.Generator().manual_seed(2))[0]
    assert torch.allclose(drawn, actor.bounded(w), atol=1e-6)                # the BC policy's noise, bounded


@pytest.mark.parametrize("bound", [0.7, 2.5])
def test_noise_log_prob_is_the_bounded_gaussians_density(bound):
    actor = _actor(bound)
    state = torch.randn(6, S)
    noise, logp, mean, log_std = actor.sample(state, generator=torch.Generator().manual_seed(3))
    oracle = TransformedDistribution(Normal(mean.double(), log_std.double().exp()),
                                     [AffineTransform(0.0, 1 / bound), TanhTransform(), AffineTransform(0.0, bound)])
    inside = noise.double().clamp(-bound * (1 - 1e-7), bound * (1 - 1e-7))
    expected = oracle.log_prob(inside).mean((-2, -1))
    assert torch.allclose(logp.double(), expected, atol=1e-4)
    assert noise.abs().max() < bound


def test_kl_to_prior_matches_torch_distributions():
    mean, log_std = torch.randn(3, H, D), 0.5 * torch.randn(3, H, D)
    expected = kl_divergence(Normal(mean, log_std.exp()), Normal(0.0, 1.0)).mean((-2, -1))
    assert torch.allclose(kl_to_prior(mean, log_std), expected, atol=1e-6)


def test_policy_starts_from_the_actors_noise_and_reloads(tmp_path):
    policy = dsrl_policy(_bc(), hidden=16, bound=2.5, steps=None)
    for p in policy.noise_actor.head.parameters():
        p.data.normal_(0, 0.3)
    batch = {"state": torch.randn(3, S)}
    gen = lambda: [torch.Generator().manual_seed(i) for i in range(3)]            # noqa: E731
    noise = policy.noise_actor.sample(**policy.noise_actor_inputs(batch), generator=gen())[0]
    mean, log_std = policy.noise_actor(**policy.noise_actor_inputs(batch))
    eps = torch.stack([torch.randn(H, D, generator=g) for g in gen()])
    assert torch.allclose(noise, policy.noise_actor.bounded(mean + log_std.exp() * eps), atol=1e-6)
    chunk = policy.predict_action_chunk(batch, generator=gen())
    assert torch.equal(chunk, policy.predict_action_chunk(batch, noise=noise))
    assert not torch.equal(chunk, policy.predict_action_chunk(batch, noise=torch.zeros_like(noise)))
    policy.save_pretrained(tmp_path)
    again = ActionDecoderPolicy.from_pretrained(tmp_path)
    assert torch.equal(again.predict_action_chunk(batch, generator=gen()), chunk)
    assert json.loads((tmp_path / "config.json").read_text())["noise_actor_hidden"] == 16
    # the decoder is the BC decoder, frozen
    bc = _bc()
    assert all(torch.equal(a, b) for a, b in zip(policy.model.parameters(), bc.model.parameters()))
    assert not any(p.requires_grad for p in policy.model.parameters())


def test_a_format_6_config_reads_without_a_noise_actor(tmp_path):
    cfg = DecoderConfig(decoder_type="flow_matching")
    data = {**cfg.to_dict(), "format_version": 6}
    del data["noise_actor_hidden"], data["noise_actor_bound"]
    (tmp_path / "config.json").write_text(json.dumps(data))
    old = DecoderConfig.from_json(tmp_path / "config.json")
    assert old.noise_actor_hidden == 0 and ActionDecoderPolicy(old).noise_actor is None


@pytest.mark.parametrize("bad", [-1, 1.5, True])
def test_config_refuses_a_bad_noise_actor_width(bad):
    with pytest.raises(ValueError, match="^noise_actor_hidden: expected a width >= 0"):
        DecoderConfig(noise_actor_hidden=bad)


def _setup(noise_critic="noise", decoder="flow_matching", done=True, reward=None, members=2, alias="update"):
    policy = dsrl_policy(_bc(decoder), hidden=16, bound=2.5, steps=None)
    gen = torch.Generator().manual_seed(0)
    n = 16
    buffer = ReplayBuffer(64)
    state = torch.randn(n, S, generator=gen)
    rows = {"state": state, "progress": torch.rand(n, generator=gen),
            "noise": torch.randn(n, H, D, generator=gen), "actions": torch.randn(n, H, D, generator=gen),
            "reward": torch.rand(n, generator=gen) if reward is None else reward,
            "next_state": torch.randn(n, S, generator=gen), "next_progress": torch.rand(n, generator=gen),
            "done": torch.full((n,), done)}
    if alias == "iteration":        # what the rollout stores: decoded pairs, the executed one and two prior ones
        rows["actions"] = decode(policy, {"state": state}, rows["noise"])
        rows["prior_noise"] = torch.randn(n, 2, H, D, generator=gen)
        rows["prior_actions"] = decode(policy, {"state": state.repeat_interleave(2, 0)},
                                       rows["prior_noise"].flatten(0, 1)).unflatten(0, (n, 2))
    buffer.add(rows)
    q = TwinQ(S, H * D, hidden=32) if members == 2 else QEnsemble(S, H * D, members, hidden=32)
    critics = {"q": q, "q_target": make_target(q)}
    temperature = Temperature(0.01, 0.0)
    opts = {"actor": torch.optim.Adam(policy.noise_actor.parameters(), lr=3e-3),
            "q": torch.optim.Adam(q.parameters(), lr=3e-3), "alpha": torch.optim.Adam(temperature.parameters(), lr=0.0)}
    if noise_critic == "action":
        qa = TwinQ(S, H * D, hidden=32) if members == 2 else QEnsemble(S, H * D, members, hidden=32)
        critics.update(q_action=qa, q_action_target=make_target(qa))
        opts["q_action"] = torch.optim.Adam(qa.parameters(), lr=3e-3)
    cfg = SimpleNamespace(sac_batch_size=16, gamma=0.9, tau=0.5, grad_clip=10.0, kl_coef=0.0, alpha_lr=0.0,
                          noise_critic=noise_critic)
    return policy, critics, temperature, opts, buffer, cfg, gen


@pytest.mark.parametrize("noise_critic,members,alias", [("noise", 2, None), ("action", 2, "update"),
                                                         ("noise", 5, None), ("action", 5, "update"),
                                                         ("action", 2, "iteration"), ("action", 5, "iteration")])
def test_critic_learns_the_reward_of_terminal_transitions(noise_critic, members, alias):
    """done everywhere: the TD target is the reward itself, whatever the actor does."""
    policy, critics, temperature, opts, buffer, cfg, gen = _setup(noise_critic, members=members, alias=alias or "update")
    make_batch = lambda s: {"state": s}                                     # noqa: E731
    pool = decode_pool(policy, buffer, make_batch, 32, gen) if alias == "iteration" else None
    key = "q_action_loss" if noise_critic == "action" else "q_loss"
    losses = [dsrl_update(policy, critics, temperature, opts, buffer, make_batch, cfg, gen, pool)[key]
              for _ in range(100)]
    assert losses[-1] < 0.05 * losses[0]
    if noise_critic == "action":    # the noise critic follows Q_A through the decoder (aliasing)
        b = {k: v[:buffer.size] for k, v in buffer.data.items()}
        # "update" aliases fresh prior noise at every update; "iteration" the prior pairs the rollout stored
        w = torch.randn(16, H, D, generator=gen) if alias == "update" else b["prior_noise"][:, 1]
        state = policy.noise_actor_inputs({"state": b["state"]})["state"]
        qa = torch.stack(critics["q_action"](state, b["progress"], decode(policy, {"state": b["state"]}, w))).mean(0)
        qw = torch.stack(critics["q"](state, b["progress"], w)).mean(0)
        assert (qa - qw).abs().mean() < 0.5 * qa.abs().mean()


def test_decode_pool_holds_the_actors_next_noise_and_its_exact_chunk():
    policy, _, _, _, buffer, _, gen = _setup("action", alias="iteration")
    for p in policy.noise_actor.head.parameters():          # an actor away from the prior
        p.data.normal_(0, 0.3, generator=torch.Generator().manual_seed(3))
    pool = decode_pool(policy, buffer, lambda s: {"state": s}, 40, gen, chunk=16)
    assert len(pool["reward"]) == 40 and set(buffer.data) < set(pool)
    torch.testing.assert_close(pool["next_actions"], decode(policy, {"state": pool["next_state"]}, pool["next_noise"]),
                               atol=1e-6, rtol=0)
    mean, log_std = policy.noise_actor(policy.noise_actor_inputs({"state": pool["next_state"]})["state"])
    actor = policy.noise_actor
    w = actor.bound * torch.atanh(pool["next_noise"] / actor.bound)           # the draw before the bound
    logp = (Normal(mean, log_std.exp()).log_prob(w) - actor.log_det(w)).mean((-2, -1))
    torch.testing.assert_close(pool["next_logp"], logp, atol=1e-4, rtol=1e-4)


def test_rollout_acts_with_the_actors_noise_and_stores_exactly_decoded_prior_pairs():
    policy = dsrl_policy(_bc(), hidden=16, bound=2.5, steps=None)
    states = torch.randn(3, S, generator=torch.Generator().manual_seed(2)).numpy()
    progress = torch.zeros(3).numpy()
    plain = noise_actor_fn(policy, lambda s: {"state": s}, torch.Generator().manual_seed(5))
    paired = noise_actor_fn(policy, lambda s: {"state": s}, torch.Generator().manual_seed(5), prior_pairs=2)
    (chunk, rec), (chunk_p, rec_p) = plain(states, progress), paired(states, progress)
    assert torch.equal(rec["noise"], rec_p["noise"])                    # the actor's draw comes first
    torch.testing.assert_close(torch.from_numpy(chunk_p), torch.from_numpy(chunk), atol=1e-6, rtol=0)
    assert rec_p["prior_noise"].shape == (3, 2, H, D) and rec_p["prior_actions"].shape == (3, 2, H, D)
    assert rec_p["prior_noise"].abs().max() < 2.5                       # bounded as the actor's noise is
    for j in range(2):
        torch.testing.assert_close(rec_p["prior_actions"][:, j],
                                   decode(policy, {"state": torch.from_numpy(states)}, rec_p["prior_noise"][:, j]),
                                   atol=1e-6, rtol=0)


def test_alias_decodes_auto_decodes_once_an_iteration_when_a_chunk_takes_more_than_two_calls():
    two, ten = (dsrl_policy(_bc(), hidden=16, bound=2.5, steps=k) for k in (2, 10))
    assert alias_mode(two, "auto") == "update" and alias_mode(ten, "auto") == "iteration"
    assert alias_mode(two, "iteration") == "iteration" and alias_mode(ten, "update") == "update"


def test_returns_to_go_stop_at_each_episode_end():
    from action_decoder.rl.finetune import returns_to_go

    rewards = torch.tensor([1.0, 1.0, 1.0, 2.0, 0.5])
    last = torch.tensor([False, False, True, False, True])
    g = 0.9
    want = torch.tensor([1 + g + g * g, 1 + g, 1.0, 2 + g * 0.5, 0.5])
    assert torch.allclose(returns_to_go(rewards, last, g), want)


def test_subset_min_is_the_minimum_of_k_members_drawn_without_replacement():
    """Members of constant values 0..4: the minimum over all is 0; over 2 drawn without replacement it
    is 0 with probability 1 − C(4, 2)/C(5, 2) = 0.4 and 3 with probability 1/C(5, 2) = 0.1, never 4."""
    qs = tuple(torch.full((3,), float(i)) for i in range(5))
    gen = torch.Generator().manual_seed(0)
    assert torch.equal(subset_min(qs, 5, gen), torch.zeros(3))
    draws = torch.stack([subset_min(qs, 2, gen) for _ in range(4000)])
    assert (draws == draws[:, :1]).all()                       # one pair per call, the same for every row
    first = draws[:, 0]
    assert abs(float((first == 0).float().mean()) - 0.4) < 0.03
    assert abs(float((first == 3).float().mean()) - 0.1) < 0.02 and not (first == 4).any()


def test_q_ensemble_members_are_independent_and_twin_matches_twin_q():
    torch.manual_seed(0)
    ens = QEnsemble(S, H * D, 2, hidden=32)
    torch.manual_seed(0)
    twin = TwinQ(S, H * D, hidden=32, norm_every_layer=True)
    x = (torch.randn(4, S), torch.rand(4), torch.randn(4, H, D))
    for a, b in zip(ens(*x), twin(*x)):
        assert torch.equal(a, b)
    q1, q2, q3 = QEnsemble(S, H * D, 3, hidden=32)(*x)
    assert q1.shape == (4,) and not torch.equal(q1, q2) and not torch.equal(q2, q3)


def test_actor_climbs_an_oracle_critic():
    """Q(s, w) = −|w − w*|²: the actor's deterministic noise moves to w*."""
    policy, critics, temperature, opts, buffer, cfg, gen = _setup()
    target = 0.8 * torch.ones(H, D)

    class Oracle(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.unused = torch.nn.Parameter(torch.zeros(()))       # the critic step has a parameter to step

        def forward(self, state, progress, w):
            q = -(w - target).square().sum((-2, -1)) + 0 * self.unused
            return q, q

    critics = {"q": Oracle(), "q_target": Oracle()}
    opts["q"] = torch.optim.SGD(critics["q"].parameters(), lr=0.0)
    state = buffer.data["state"][:16]
    before = (policy.noise_actor.act(state) - target).abs().mean()
    for _ in range(200):
        dsrl_update(policy, critics, temperature, opts, buffer, lambda s: {"state": s}, cfg, gen)
    after = (policy.noise_actor.act(state) - target).abs().mean()
    assert before > 0.7 and after < 0.1


def test_kl_multiplier_rises_while_the_kl_is_above_its_target_and_falls_below():
    m = KLMultiplier(target=0.5, initial=1.0)
    opt = torch.optim.SGD(m.parameters(), lr=0.1)
    for kl, direction in ((torch.full((4,), 2.0), 1), (torch.full((4,), 0.1), -1)):
        before = float(m.value)
        opt.zero_grad()
        m.loss(kl).backward()
        opt.step()
        assert math.isclose(math.log(float(m.value)) - math.log(before), direction * 0.1 * abs(float(kl[0]) - 0.5),
                            rel_tol=1e-5)


@pytest.mark.parametrize("kl_target", [None, 0.5])
def test_trust_region_holds_the_actor_near_the_prior_that_an_oracle_critic_pulls_it_from(kl_target):
    """Q(s, w) = −|w − 2|²: without a trust region the actor's KL to N(0, I) heads for that of a mean at 2
    (about 2 per element); `KLMultiplier` holds it at its target."""
    policy, critics, temperature, opts, buffer, cfg, gen = _setup()

    class Oracle(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.unused = torch.nn.Parameter(torch.zeros(()))

        def forward(self, state, progress, w):
            q = -(w - 2.0).square().sum((-2, -1)) + 0 * self.unused
            return q, q

    critics = {"q": Oracle(), "q_target": Oracle()}
    opts["q"] = torch.optim.SGD(critics["q"].parameters(), lr=0.0)
    multiplier = None if kl_target is None else KLMultiplier(kl_target)
    if multiplier is not None:
        opts["kl"] = torch.optim.Adam(multiplier.parameters(), lr=0.1)
    runs = [dsrl_update(policy, critics, temperature, opts, buffer, lambda s: {"state": s}, cfg, gen,
                        multiplier=multiplier) for _ in range(400)]
    kl = sum(r["kl_prior"] for r in runs[-50:]) / 50
    if kl_target is None:
        assert kl > 1.5 and "kl_multiplier" not in runs[-1]
    else:
        assert abs(kl - kl_target) < 0.15 and runs[-1]["kl_multiplier"] > 1.0


def test_a_warm_up_update_steps_the_critics_and_leaves_the_actor_alpha_and_multiplier():
    policy, critics, temperature, opts, buffer, cfg, gen = _setup("action")
    cfg.alpha_lr = 0.1
    opts["alpha"] = torch.optim.Adam(temperature.parameters(), lr=0.1)
    multiplier = KLMultiplier(0.5)
    opts["kl"] = torch.optim.Adam(multiplier.parameters(), lr=0.1)
    snap = lambda m: [p.detach().clone() for p in m.parameters()]               # noqa: E731
    kept = [snap(m) for m in (policy.noise_actor, temperature, multiplier)]
    moved = [snap(critics[k]) for k in ("q", "q_action")]
    stats = dsrl_update(policy, critics, temperature, opts, buffer, lambda s: {"state": s}, cfg, gen,
                        multiplier=multiplier, update_actor=False)
    for m, before in zip((policy.noise_actor, temperature, multiplier), kept):
        assert all(torch.equal(a, b) for a, b in zip(m.parameters(), before))
    for k, before in zip(("q", "q_action"), moved):
        assert not all(torch.equal(a, b) for a, b in zip(critics[k].parameters(), before))
    assert {"q", "kl_prior", "entropy_per_dim", "kl_multiplier"} <= set(stats)
    dsrl_update(policy, critics, temperature, opts, buffer, lambda s: {"state": s}, cfg, gen, multiplier=multiplier)
    for m, before in zip((policy.noise_actor, temperature, multiplier), kept):
        assert not all(torch.equal(a, b) for a, b in zip(m.parameters(), before))


def test_replay_buffer_wraps_round_trips_and_checks_fields():
    buf = ReplayBuffer(5)
    rows = lambda a, b: {"state": torch.arange(a, b).float()[:, None], "noise": torch.zeros(b - a, 2)}  # noqa: E731
    buf.add(rows(0, 3))
    buf.add(rows(3, 7))
    assert buf.size == 5 and buf.pos == 2
    assert sorted(buf.data["state"][:, 0].tolist()) == [2, 3, 4, 5, 6]
    again = ReplayBuffer(1)
    again.load_state_dict(buf.state_dict())
    assert torch.equal(again.data["state"], buf.data["state"]) and again.pos == 2
    with pytest.raises(ValueError, match="rows: expected the fields"):
        buf.add({"state": torch.zeros(1, 1)})


def _run(ckpt, out, *extra):
    return main(["finetune", "--checkpoint", str(ckpt), "--output-dir", str(out), "--algo", "dsrl",
                 "--num-envs", "2", "--max-episode-steps", "12", "--eval-episodes", "0", "--sac-batch-size", "4",
                 "--checkpoint-every", "1", "--noise-hidden", "16", *extra])


@pytest.mark.parametrize("alias,trust", [("update", ()), ("iteration", ()), ("update", ("--kl-target", "0.5"))])
def test_dsrl_resumes_bit_exact_and_the_saved_policy_acts(tmp_path, capsys, alias, trust):
    ckpt = tmp_path / "bc"
    _bc().save_pretrained(ckpt)
    opt = ("--alias-decodes", alias, *trust)
    assert _run(ckpt, tmp_path / "whole", "--env-steps", "72", *opt) == 0
    assert _run(ckpt, tmp_path / "cut", "--env-steps", "48", *opt) == 0
    assert _run(ckpt, tmp_path / "cut", "--env-steps", "72", "--resume", *opt) == 0
    whole, cut = (ActionDecoderPolicy.from_pretrained(tmp_path / d / "final") for d in ("whole", "cut"))
    for a, b in zip(whole.state_dict().values(), cut.state_dict().values()):
        assert torch.equal(a, b)
    logs = [json.loads((tmp_path / d / "finetune_log.json").read_text())["history"] for d in ("whole", "cut")]
    strip = lambda hs: [{k: v for k, v in h.items() if k not in ("wall_s", "cpu_s", "rollout_cpu_s")} for h in hs]  # noqa: E731
    assert strip(logs[0]) == strip(logs[1]) and logs[0][-1]["updates"] == 2 * logs[0][-1]["decisions"]
    # DSRL's default reward: 1 at success plus k·(γ·Φ(s′) − Φ(s)), whose sum from decision t is −k·Φ(s_t) ∈ [−k, 0]
    assert -0.1 <= logs[0][-1]["return_to_go"] <= 1.1
    assert ("kl_multiplier" in logs[0][-1]) == bool(trust)
    # the decoder's weights are the BC policy's; the noise actor moved
    bc = ActionDecoderPolicy.from_pretrained(ckpt)
    assert all(torch.equal(bc.state_dict()[k], v) for k, v in whole.state_dict().items() if k in bc.state_dict())
    assert whole.noise_actor.head.weight.abs().max() > 0
    capsys.readouterr()
    assert main(["eval", "--checkpoint", str(tmp_path / "whole" / "final"), "--episodes", "1", "--num-envs", "1"]) == 0
    assert "success_rate=" in capsys.readouterr().out
    # a DSRL checkpoint is not a BC checkpoint to start from
    assert _run(tmp_path / "whole" / "final", tmp_path / "again", "--env-steps", "24") == 2
    assert "already has a noise actor" in capsys.readouterr().err


def test_dsrl_critic_warm_up_keeps_the_untrained_actor_for_its_iterations(tmp_path):
    ckpt = tmp_path / "bc"
    _bc().save_pretrained(ckpt)
    assert _run(ckpt, tmp_path / "w", "--env-steps", "24", "--critic-warmup-iters", "1") == 0
    assert _run(ckpt, tmp_path / "w2", "--env-steps", "48", "--critic-warmup-iters", "1") == 0
    start = dsrl_policy(ActionDecoderPolicy.from_pretrained(ckpt), hidden=16, bound=2.5, steps=None)
    one, two = (ActionDecoderPolicy.from_pretrained(tmp_path / d / "final") for d in ("w", "w2"))
    head = lambda p: p.noise_actor.head.weight                                   # noqa: E731
    assert torch.equal(head(one), head(start)) and not torch.equal(head(two), head(start))
    hist = json.loads((tmp_path / "w2" / "finetune_log.json").read_text())["history"]
    assert [h["updates"] for h in hist] == [2 * h["decisions"] for h in hist]     # the critics step in both


def test_dsrl_steers_a_ddpm_decoder_through_its_deterministic_solver():
    policy = dsrl_policy(_bc("DDPM"), hidden=16, bound=2.5, steps=3)
    batch = {"state": torch.randn(2, S)}
    noise = torch.randn(2, H, D)
    assert torch.equal(decode(policy, batch, noise), decode(policy, batch, noise))
    assert not torch.equal(decode(policy, batch, noise), decode(policy, batch, -noise))


def test_each_algorithm_fills_the_options_left_at_none_with_its_own_defaults():
    from action_decoder.rl.finetune import FinetuneConfig, with_defaults

    dsrl, ppo = (with_defaults(FinetuneConfig(checkpoint="-", algo=a)) for a in ("dsrl", "ppo"))
    assert (dsrl.env_steps, dsrl.num_envs, dsrl.critic_lr) == (200_000, 8, 3e-4)
    assert (ppo.env_steps, ppo.num_envs, ppo.critic_lr) == (100_000, 32, 1e-3)
    assert (dsrl.reward, ppo.reward) == ("success", "dense")
    assert with_defaults(FinetuneConfig(checkpoint="-", algo="dsrl", env_steps=4800)).env_steps == 4800


def test_dsrl_refuses_bad_options_in_one_line(tmp_path, capsys):
    ckpt = tmp_path / "bc"
    _bc().save_pretrained(ckpt)
    for args, words in ((["--noise-bound", "0"], "--noise-bound: expected a positive number"),
                        (["--group-size", "2"], "--group-size: only with --algo ppo"),
                        (["--buffer-size", "2"], "--buffer-size: expected at least --sac-batch-size"),
                        (["--target-entropy", "nan"], "--target-entropy: expected a finite number"),
                        (["--critics", "1"], "--critics: expected an ensemble of at least 2 members"),
                        (["--kl-target", "0"], "--kl-target: expected a positive finite KL per noise element"),
                        (["--kl-target", "inf"], "--kl-target: expected a positive finite KL per noise element"),
                        (["--kl-target", "1", "--kl-coef", "0.5"], "--kl-target: the trust region's weight is learnt")):
        assert _run(ckpt, tmp_path / "x", "--env-steps", "24", *args) == 2
        assert words in capsys.readouterr().err
    assert main(["finetune", "--checkpoint", str(ckpt), "--output-dir", str(tmp_path / "p"), "--algo", "ppo",
                 "--kl-target", "1"]) == 2
    assert "--kl-target: only with --algo dsrl" in capsys.readouterr().err


def test_plugin_config_carries_the_noise_actor():
    sys.path.insert(0, str(ROOT / "lerobot_policy_action_decoder" / "src"))
    from lerobot_policy_action_decoder import convert

    values = {name: getattr(DecoderConfig(), name) for name in convert.SHARED}
    values.update(decoder_type="mean_flow", chunk_size=8, n_action_steps=4, num_inference_steps=None,
                  flow_prediction=None, tasks=[], noise_actor_hidden=32, noise_actor_bound=1.5)
    core = convert.decoder_config(SimpleNamespace(**values), state_dim=6, action_dim=2)
    assert (core.noise_actor_hidden, core.noise_actor_bound) == (32, 1.5)
    policy = ActionDecoderPolicy(core)
    assert policy.noise_actor is not None and math.isclose(policy.noise_actor.bound, 1.5)


def test_export_refuses_a_noise_actor_policy_in_one_line(tmp_path):
    pytest.importorskip("onnx")
    policy = dsrl_policy(_bc(), hidden=16, bound=2.5, steps=None)
    with pytest.raises(ValueError, match="^noise_actor_hidden: a noise-space"):
        policy.export_onnx(tmp_path / "p.onnx")


def test_ctrl_c_inside_an_iteration_keeps_its_decoded_pool_and_resume_continues_exactly(tmp_path, capsys, monkeypatch):
    """--alias-decodes iteration: a checkpoint written between two updates holds the iteration's pool,
    and --resume ends with the uninterrupted run's weights."""
    import importlib
    import os
    import signal

    from action_decoder.run_dir import load_state

    F = importlib.import_module("action_decoder.rl.finetune")
    ckpt = tmp_path / "bc"
    _bc().save_pretrained(ckpt)
    opt = ("--env-steps", "48", "--alias-decodes", "iteration")
    assert _run(ckpt, tmp_path / "a", *opt) == 0
    calls, real = [], F.dsrl_update

    def interrupted(*a, **k):                   # 12 updates an iteration: the 6th of the second
        calls.append(1)
        if len(calls) == 18:
            os.kill(os.getpid(), signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(F, "dsrl_update", interrupted)
    assert _run(ckpt, tmp_path / "b", *opt) == 130
    pending = load_state(tmp_path / "b" / "checkpoints" / "step_0000001")["pending"]
    assert len(pending["runs"]) == 6 and len(pending["pool"]["next_actions"]) == 4096
    monkeypatch.setattr(F, "dsrl_update", real)
    capsys.readouterr()
    assert _run(ckpt, tmp_path / "b", *opt, "--resume") == 0
    assert "inside iteration 2, after 6 of its 12 updates" in capsys.readouterr().out
    a, b = (ActionDecoderPolicy.from_pretrained(tmp_path / r / "final").state_dict() for r in "ab")
    assert all(torch.equal(a[k], b[k]) for k in a)
