"""RL fine-tuning: on-policy ratio 1, SAC's σ-only entropy gradient, the tanh correction,
σ → 0 reducing to the deterministic policy, and `finetune` → `eval` through the CLI."""

import copy
import json
import math
from types import SimpleNamespace

import pytest
import torch
from torch.distributions import AffineTransform, Normal, TanhTransform, TransformedDistribution

from action_decoder import (ActionDecoderPolicy, DecoderConfig, ExploringSigma, sample_ode, sample_sde,
                            velocity_from_meanflow)
from action_decoder.envs import make_env
from action_decoder.cli import main
from action_decoder.rl.critics import TwinQ, ValueNet
from action_decoder.rl.finetune import FinetuneConfig, chain_actor, shaping
from action_decoder.rl import ppo
from action_decoder.rl.ppo import gae, group_advantages, ppo_update
from action_decoder.rl.rollout import collect
from action_decoder.rl.sac import ReplayBuffer, Temperature, actor_sample, make_target, sac_update
from action_decoder.rl.sde_policy import finetune_policy, rescore_chain, sample_chain, squash_to_box

S, D, H = 39, 4, 4


def _stats(gen):
    def one(dim):
        return {"mean": torch.randn(dim, generator=gen) * 0.1, "std": 0.5 + torch.rand(dim, generator=gen),
                "min": -torch.ones(dim), "max": torch.ones(dim)}
    return {"state": one(S), "actions": one(D)}


def _bc(decoder="flow_matching", task="reach-v3"):
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type=decoder, state_dim=S, action_dim=D, action_chunk_size=H, n_action_steps=H,
                        hidden_size=16, num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1,
                        num_inference_timesteps=2, extra={"tasks": [task]})
    return ActionDecoderPolicy(cfg, _stats(gen))


def _batch(n=6):
    return {"state": torch.randn(n, S, generator=torch.Generator().manual_seed(1))}


@pytest.mark.parametrize("decoder", ["flow_matching", "mean_flow"])
def test_ratio_is_one_on_policy_and_checked(decoder):
    policy = finetune_policy(_bc(decoder), sigma=0.5, learn_sigma=True, steps=5)
    batch, gen = _batch(), torch.Generator().manual_seed(0)
    for reduce in ("sum", "mean"):
        with torch.no_grad():
            res = sample_chain(policy, batch, 5, torch.Generator().manual_seed(0), reduce=reduce)
        lp = rescore_chain(policy, batch, res.chain, res.grid, reduce)
        assert torch.allclose((lp - res.step_log_probs).exp(), torch.ones_like(lp), atol=1e-5)
    # through ppo_update: the run-time check passes on-policy and fails once the weights moved
    value = ValueNet(S)
    data = {"states": batch["state"], "state_norm": batch["state"], "progress": torch.zeros(6),
            "chain": res.chain, "grid": res.grid, "logp_old": res.step_log_probs, "logp_ref": res.step_log_probs,
            "adv": torch.randn(6, generator=gen), "ret": torch.zeros(6)}
    cfg = SimpleNamespace(trained_steps=2, ppo_epochs=1, minibatch_size=6, logprob_reduce="mean", ratio_tol=1e-4,
                          clip_eps=0.2, kl_coef=0.1, target_kl=1.0, vf_coef=0.5, grad_clip=1.0, lr_schedule="fixed",
                          lr_warmup_updates=0)
    opt = torch.optim.Adam(list(policy.parameters()) + list(value.parameters()), lr=1e-2)
    stats = ppo_update(policy, value, opt, lambda s: {"state": s}, data, cfg, gen)
    assert stats["ratio_dev_before_update"] < 1e-5
    with pytest.raises(RuntimeError, match="ratio is not 1"):
        ppo_update(policy, value, opt, lambda s: {"state": s}, data, cfg, gen)


def test_gae_terminal_truncation_and_episode_boundaries():
    r = torch.tensor([0.0, 1.0, 0.0, 0.0])
    v = torch.tensor([0.5, 0.5, 0.2, 0.2])
    nv = torch.tensor([9.0, 9.0, 9.0, 3.0])           # only the truncated row's next value is used
    last, term = torch.tensor([False, True, False, True]), torch.tensor([False, True, False, False])
    adv, ret = gae(r, v, nv, term, last, gamma=0.5, lam=1.0)
    assert torch.allclose(ret, torch.tensor([0.5, 1.0, 0.75, 1.5]))


def test_critics_bootstrap_nothing_at_success_or_the_training_cap():
    """The heads see progress, so the cap ends their MDP: GAE uses no next value there; an episode that
    ends before the cap without success (an env's own limit) still bootstraps."""
    from action_decoder.rl.finetune import episode_ends

    ro = SimpleNamespace(terminal=torch.tensor([False, False, True, False]),
                         next_progress=torch.tensor([0.5, 1.0, 0.7, 0.9]))
    ends = episode_ends(ro)
    assert ends.tolist() == [False, True, True, False]
    last = torch.tensor([False, True, True, True])
    rewards, values = torch.tensor([1.0, 2.0, 3.0, 4.0]), torch.zeros(4)
    adv, _ = gae(rewards, values, torch.full((4,), 100.0), ends, last, 0.5, 1.0)
    assert adv.tolist() == pytest.approx([1.0 + 0.5 * 2.0, 2.0, 3.0, 4.0 + 0.5 * 100.0])


def test_sac_entropy_gradient_reaches_sigma_only():
    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=4)
    cfg = SimpleNamespace(sde_steps=4)
    actions, logp, _ = actor_sample(policy, _batch(), cfg, torch.Generator().manual_seed(0))
    logp.sum().backward(retain_graph=True)
    assert policy.sigma.log_scale.grad is not None and policy.sigma.log_scale.grad.abs() > 0
    assert all(p.grad is None or not p.grad.any() for p in policy.model.parameters())
    policy.zero_grad()
    actions.square().sum().backward()                  # a Q-like term moves the velocity network
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.model.parameters())


def test_temperature_holds_the_entropy_at_its_target():
    temp = Temperature(alpha=0.1)
    opt = torch.optim.SGD(temp.parameters(), lr=0.5)
    logp = torch.full((8,), -1.0)                       # entropy 1 per dimension: becomes the target
    temp.loss(logp).backward()
    assert temp.target == 1.0 and temp.log_alpha.grad == 0
    for entropy, direction in ((2.0, -1), (0.5, +1)):   # too much entropy: α falls; too little: α rises
        before = float(temp.alpha)
        opt.zero_grad()
        temp.loss(torch.full((8,), -entropy, requires_grad=True)).backward()
        opt.step()
        assert (float(temp.alpha) - before) * direction > 0
    fixed = Temperature(alpha=0.1, target=-3.0)
    assert fixed.target == -3.0 and abs(float(fixed.alpha) - 0.1) < 1e-7


def test_squash_correction_matches_transformed_distribution():
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn(5, H, D, generator=gen, dtype=torch.float64)   # float64: atanh near ±1
    velocity = lambda x, t: 0.3 - 0.5 * x               # noqa: E731
    sigma = ExploringSigma(0.3)
    res = sample_sde(velocity, noise, steps=1, sigma=sigma, generator=gen, return_logprob=True, squash=True)
    base = Normal(res.means[:, 0], res.stds[:, 0, None, None].expand_as(res.means[:, 0]))
    ref = TransformedDistribution(base, [TanhTransform()]).log_prob(res.actions).sum((-2, -1))
    assert torch.allclose(res.log_prob, ref, atol=1e-6)
    # squashing into the env box after un-normalising: Normal -> affine -> tanh
    norm = _bc().normalizers["actions"]
    env_actions, log_det = squash_to_box(res.chain[:, -1], norm)
    ref = TransformedDistribution(base, [AffineTransform(norm.mean.double(), norm.std.double()), TanhTransform()])
    assert torch.allclose(res.step_log_probs.sum(1) - log_det, ref.log_prob(env_actions).sum((-2, -1)),
                          atol=1e-6)


@pytest.mark.parametrize("decoder", ["flow_matching", "mean_flow"])
def test_sigma_to_zero_is_the_deterministic_policy(decoder):
    bc = _bc(decoder)
    policy = finetune_policy(bc, sigma=1e-7, learn_sigma=True, steps=3)
    batch = _batch()
    noise = torch.randn(6, H, D, generator=torch.Generator().manual_seed(2))
    res = sample_chain(policy, batch, 3, torch.Generator().manual_seed(3), noise=noise)
    bound = policy.bind(batch)
    v = bound.velocity if decoder == "flow_matching" else velocity_from_meanflow(bound.avg_velocity)
    assert torch.allclose(res.chain[:, -1], sample_ode(v, noise, 3), atol=1e-5)
    if decoder == "flow_matching":                      # = the policy's own ODE sampler
        ode = policy.sample(batch, sampler="ode", steps=3, noise=noise).actions
        norm = policy.normalizers["actions"]
        assert torch.allclose(norm.clip(norm.unnormalize(res.chain[:, -1])), ode, atol=1e-5)
    # the PPO rollout executes exactly the deterministic chunk of its chain's start noise
    act = chain_actor(policy, lambda s: {"state": s}, 3, torch.Generator().manual_seed(0), "sum", squash=False)
    ro = collect([make_env("reach-v3", seed=0)], [7], act, H, max_steps=12)
    with torch.no_grad():
        bound = policy.bind({"state": ro.states})
        v = bound.velocity if decoder == "flow_matching" else velocity_from_meanflow(bound.avg_velocity)
        norm = policy.normalizers["actions"]
        det = norm.clip(norm.unnormalize(sample_ode(v, ro.records["chain"][:, 0], 3)))   # as BC executes it
    assert ro.records["actions"].shape == (3, H, D)
    assert torch.allclose(ro.records["actions"], det, atol=1e-4)


def test_finetune_cli_end_to_end_resume_and_eval(tmp_path, capsys):
    ckpt, out = tmp_path / "bc", tmp_path / "ft"
    _bc().save_pretrained(ckpt)
    args = ["finetune", "--checkpoint", str(ckpt), "--output-dir", str(out), "--env-steps", "30", "--num-envs", "2",
            "--max-episode-steps", "12", "--sde-steps", "3", "--trained-steps", "2", "--eval-episodes", "1",
            "--minibatch-size", "4", "--group-size", "2",
            "--checkpoint-every", "1", "--kl-coef", "0.01"]
    assert main(args) == 0
    log = json.loads((out / "finetune_log.json").read_text())
    assert log["history"][-1]["env_steps"] >= 30 and "ratio_min" in log["history"][-1]
    # one kl_bc: what each iteration prints is what the log (and its plot) holds; the update's own term is apart
    printed = [line.split(" kl_bc ")[1].split()[0] for line in capsys.readouterr().out.splitlines()
               if line.startswith("iter ")]
    assert printed == [f"{h['kl_bc']:.4f}" for h in log["history"]] and len(printed) == len(log["history"])
    assert all("kl_bc_update" in h for h in log["history"])
    assert (out / "finetune.png").is_file()
    assert main(args) == 2                                  # refuses to overwrite a run
    assert "already holds a fine-tuning run" in capsys.readouterr().err
    assert main([*args, "--resume", "--lr", "3e-4"]) == 2    # another recipe does not continue this run
    err = capsys.readouterr().err
    assert "--resume: " in err and "started with lr=0.0001; this call sets lr=0.0003" in err
    assert main([*args[:5], "--env-steps", "54", *args[7:], "--resume"]) == 0
    log2 = json.loads((out / "finetune_log.json").read_text())
    assert log2["history"][: len(log["history"])] == log["history"] and len(log2["history"]) > len(log["history"])
    assert main(["eval", "--checkpoint", str(out / "final"), "--episodes", "1", "--num-envs", "1"]) == 0
    assert "success_rate=" in capsys.readouterr().out
    cfg = json.loads((out / "final" / "config.json").read_text())
    assert cfg["flow_sde_use"] and cfg["flow_sde_learn_sigma"]
    assert cfg["flow_sde_mode"] == FinetuneConfig.sigma_schedule
    # SAC path, one short run, stopped by the CPU budget after its first iteration
    at = args.index("--group-size")
    no_group = args[5:at] + args[at + 2:]
    assert main([*args[:4], str(tmp_path / "sac"), "--algo", "sac", *no_group, "--sac-batch-size", "4",
                 "--env-steps", "100000", "--max-cpu-minutes", "1e-4"]) == 0
    sac = json.loads((tmp_path / "sac" / "finetune_log.json").read_text())
    assert len(sac["history"]) == 1 and sac["history"][0]["cpu_s"] > 0


def test_finetune_rejects_ddpm_and_bad_arguments(tmp_path, capsys):
    ddpm = tmp_path / "ddpm"
    _bc("DDPM").save_pretrained(ddpm)
    assert main(["finetune", "--checkpoint", str(ddpm), "--output-dir", str(tmp_path / "o")]) == 2
    assert "flow_matching or mean_flow" in capsys.readouterr().err
    ok = tmp_path / "fm"
    _bc().save_pretrained(ok)
    assert main(["finetune", "--checkpoint", str(ok), "--output-dir", str(tmp_path / "o"), "--trained-steps",
                 "11"]) == 2
    assert "--trained-steps" in capsys.readouterr().err
    # the critic's warm-up acts only with the critic: refused with group advantages instead of ignored
    assert main(["finetune", "--checkpoint", str(ok), "--output-dir", str(tmp_path / "o"), "--critic-warmup-iters",
                 "3"]) == 2
    err = capsys.readouterr().err
    assert "--critic-warmup-iters: only with PPO's critic (--group-size 1) or --algo dsrl" in err and "got 3" in err
    assert main(["finetune", "--checkpoint", str(ok), "--output-dir", str(tmp_path / "o"), "--algo", "sac",
                 "--critic-warmup-iters", "3"]) == 2
    assert "SAC (--algo sac, --group-size 1) have no critic-only phase" in capsys.readouterr().err
    assert main(["finetune", "--checkpoint", str(ok), "--output-dir", str(tmp_path / "o"), "--group-size", "1",
                 "--critic-warmup-iters", "-1"]) == 2
    assert "--critic-warmup-iters: expected >= 0, got -1" in capsys.readouterr().err
    assert main(["finetune", "--checkpoint", str(ok), "--output-dir", str(tmp_path / "o"), "--lr-warmup-updates", "10",
                 "--lr-schedule", "adaptive"]) == 2
    assert "--lr-warmup-updates: only with --algo ppo and --lr-schedule fixed, got 10" in capsys.readouterr().err
    for bad, expected in ((["--algo", "sac", "--group-size", "4"], "--group-size: only with --algo ppo"),
                          (["--algo", "sac", "--sac-updates-per-decision", "0"],
                           "--sac-updates-per-decision: expected a positive number, got 0"),
                          (["--gamma", "0"], "--gamma: expected a number in (0, 1], got 0"),
                          (["--gae-lambda", "1.5"], "--gae-lambda: expected a number in [0, 1], got 1.5")):
        assert main(["finetune", "--checkpoint", str(ok), "--output-dir", str(tmp_path / "o"), *bad]) == 2
        err = capsys.readouterr().err
        assert expected in err and len(err.strip().splitlines()) == 1, err


def test_shaping_is_potential_based_and_telescopes():
    """On a real rollout, the discounted shaping of each episode sums to 0, whether it ends in success
    or at the training cap, where the critics bootstrap nothing (Φ(s₀) = 0, independent of the first
    action, and Φ = 0 at the cap): it cannot change which policy is best."""
    envs = [make_env("reach-v3") for _ in range(2)]
    gen = torch.Generator().manual_seed(0)

    def act(states, progress):
        return torch.rand((len(states), 8, 4), generator=gen).numpy() * 2 - 1, {}

    ro = collect(envs, [3, 4], act, n_action_steps=4, max_steps=40)
    gamma, f = 0.9, shaping(ro, 0.9)
    assert torch.equal(ro.reward_before[1:][~ro.last[:-1]], ro.reward_after[:-1][~ro.last[:-1]])
    ends = torch.nonzero(ro.last).flatten().tolist()
    for start, end in zip([0] + [e + 1 for e in ends[:-1]], ends):
        n = end - start + 1
        total = sum(gamma ** i * float(f[start + i]) for i in range(n))
        assert float(ro.reward_before[start]) == 0.0
        assert total == pytest.approx(0.0, abs=1e-5)


def test_shaped_return_equals_the_unshaped_one_at_the_cap_in_closed_form():
    """Two hand-made episodes of three decisions (env rewards 10·Φ), one ending at the training cap
    and one in success: the shaping per decision is γΦ₁ − 0, γΦ₂ − Φ₁, γ·0 − Φ₂ in both, and the
    discounted shaped return equals the success reward's, whatever Φ the episode ends near. An
    episode cut before the cap (an env's own limit) keeps γΦ₃, which the critic's bootstrap balances."""
    from action_decoder.rl.finetune import decision_rewards

    phi = [0.3, 0.7, 0.95]
    ro = SimpleNamespace(reward_before=torch.tensor([0.0, 3.0, 7.0] * 3), reward_after=torch.tensor([3.0, 7.0, 9.5] * 3),
                         terminal=torch.tensor([False, False, False, False, False, True, False, False, False]),
                         next_progress=torch.tensor([0.3, 0.6, 1.0, 0.3, 0.6, 0.9, 0.3, 0.6, 0.9]))
    gamma = 0.9
    expected = torch.tensor([gamma * phi[0], gamma * phi[1] - phi[0], -phi[1]] * 2
                            + [gamma * phi[0], gamma * phi[1] - phi[0], gamma * phi[2] - phi[1]])
    assert torch.allclose(shaping(ro, gamma), expected)
    cfg = SimpleNamespace(reward="success", success_reward=1.0, shaping_scale=0.5, gamma=gamma)
    r = decision_rewards(ro, cfg, n_exec=4)
    ret = [sum(gamma ** i * float(r[3 * e + i]) for i in range(3)) for e in range(3)]
    assert ret[0] == pytest.approx(0.0, abs=1e-6)                        # capped: no k·γ³·Φ(s₃) left
    assert ret[1] == pytest.approx(gamma ** 2 * 1.0, abs=1e-6)           # success: the success reward alone
    assert ret[2] == pytest.approx(0.5 * gamma ** 3 * phi[2], abs=1e-6)  # cut early: the bootstrap's share


def test_group_advantages_compare_episodes_of_one_layout():
    # Four episodes (rows stored episode by episode), two layouts of two episodes each.
    rewards = torch.tensor([0.0, 1.0, 0.2, 0.0, -0.1, 2.0, 0.5, 1.0])
    last = torch.tensor([0, 1, 0, 0, 1, 1, 0, 1], dtype=torch.bool)
    # discounted rewards-to-go (γ = 0.5) per episode and decision, 0 after an episode's end
    to_go = [[0.5, 1.0, 0.0], [0.175, -0.05, -0.1], [2.0, 0.0, 0.0], [1.0, 1.0, 0.0]]
    other = {0: 1, 1: 0, 2: 3, 3: 2}                     # leave-one-out mean of a group of two
    rows = [(0, 0), (0, 1), (1, 0), (1, 1), (1, 2), (2, 0), (3, 0), (3, 1)]
    expected = torch.tensor([to_go[e][t] - to_go[other[e]][t] for e, t in rows])
    assert torch.allclose(group_advantages(rewards, last, 0.5, 2), expected)
    # the baseline ignores the episode's own rewards: changing them moves only its own advantages
    bumped = rewards.clone()
    bumped[5] += 1.0
    diff = group_advantages(bumped, last, 0.5, 2) - expected
    assert torch.allclose(diff, torch.tensor([0, 0, 0, 0, 0, 1.0, -1.0, 0]))
    for bad in (1, 3):
        with pytest.raises(ValueError, match="group_size"):
            group_advantages(rewards, last, 0.5, bad)


def test_ppo_on_chains_learns_a_contextual_bandit():
    """The whole PPO path (SDE chains, re-scoring, clipped per-step ratios) on a one-decision task
    whose best chunk is all ones: the mean action must move towards 1 and the reward rise."""

    torch.manual_seed(0)
    cfg_d = DecoderConfig(decoder_type="flow_matching", state_dim=8, action_dim=2, action_chunk_size=4,
                          n_action_steps=4, hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
                          num_key_value_heads=1)
    cfg = FinetuneConfig(checkpoint="unused", lr=3e-5, trained_steps=5, minibatch_size=256, sigma=1.0)
    policy = finetune_policy(ActionDecoderPolicy(cfg_d), cfg.sigma, True, cfg.sde_steps)
    critic = ValueNet(8)
    opt = torch.optim.Adam([{"params": list(policy.model.parameters()), "lr": cfg.lr},
                            {"params": list(critic.parameters()), "lr": 1e-3}])
    gen = torch.Generator().manual_seed(0)
    means, rewards = [], []
    for _ in range(11):
        s = torch.randn(512, 8, generator=gen)
        with torch.no_grad():
            res = sample_chain(policy, {"state": s}, cfg.sde_steps, gen)
        a = res.chain[:, -1]
        r = -(a - 1.0).square().mean((1, 2))
        means.append(float(a.mean()))
        rewards.append(float(r.mean()))
        data = {"states": s, "state_norm": s, "progress": torch.zeros(512), "chain": res.chain, "grid": res.grid,
                "logp_old": res.step_log_probs, "logp_ref": res.step_log_probs, "adv": r - r.mean(), "ret": r}
        stats = ppo_update(policy, critic, opt, lambda st: {"state": st}, data, cfg, gen)
        assert stats["ratio_dev_before_update"] <= cfg.ratio_tol
    assert means[-1] > means[0] + 0.12 and rewards[-1] > rewards[0] + 0.2, (means, rewards)
    # the critic's warm-up (update_policy=False): the value head moves, the velocity network and σ do not
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    head = [p.clone() for p in critic.parameters()]
    stats = ppo_update(policy, critic, opt, lambda st: {"state": st}, data, cfg, gen, update_policy=False)
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())
    assert any(not torch.equal(a, b) for a, b in zip(head, critic.parameters())) and "v_loss" in stats
    assert "approx_kl" not in stats


def test_rollout_runs_past_success_for_the_dense_reward():
    """With stop_on_success=False an episode that succeeds keeps going to the time limit, nothing
    is terminal (the critic bootstraps), and its success is still counted; with True it ends there."""
    from action_decoder.envs import expert_policy

    expert = expert_policy("reach-v3")

    def act(states, progress):
        return expert(states)[:, None].repeat(4, 1), {}

    for stop in (True, False):
        ro = collect([make_env("reach-v3", seed=0)], [5], act, n_action_steps=4, max_steps=200, stop_on_success=stop)
        assert ro.episode_success == [True]
        assert bool(ro.terminal.any()) is stop and bool(ro.success[-1])
        assert (ro.env_steps < 200) is stop
        assert torch.equal(torch.nonzero(ro.last).flatten(), torch.tensor([len(ro.last) - 1]))
        cut = int(ro.env_steps - 4 * (len(ro.last) - 1))        # actions of the last decision that ran
        assert ro.executed[:-1].tolist() == [4] * (len(ro.last) - 1) and int(ro.executed[-1]) == cut
        assert (cut < 4) is (stop and ro.env_steps % 4 != 0)


@pytest.mark.parametrize("reduce", ["sum", "mean"])
def test_last_step_log_prob_keeps_only_executed_rows(reduce):
    """The last step's density counts only the executed rows (nothing depends on the others), every
    earlier step counts the whole chunk, and sampling and re-scoring agree (PPO ratio 1)."""
    from action_decoder.rl.sde_policy import reduce_step_log_probs

    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=3)
    batch = _batch()
    with torch.no_grad():
        res = sample_chain(policy, batch, 3, torch.Generator().manual_seed(0), reduce=reduce, executed=2)
        full = policy.chain_log_prob(batch, res.chain, res.grid, reduce="none")            # [B, K, H, D]
    agg = (lambda x: x.sum((-2, -1))) if reduce == "sum" else (lambda x: x.mean((-2, -1)))
    assert torch.allclose(res.step_log_probs[:, :-1], agg(full[:, :-1]), atol=1e-5)
    assert torch.allclose(res.step_log_probs[:, -1], agg(full[:, -1, :2]), atol=1e-5)
    assert torch.allclose(reduce_step_log_probs(full, reduce), agg(full), atol=1e-6)
    moved = res.chain.clone()
    moved[:, -1, 2:] += 3.0                                    # unexecuted rows of the final chunk
    lp = rescore_chain(policy, batch, moved, res.grid, reduce, executed=2)
    assert torch.allclose(lp, res.step_log_probs, atol=1e-5)
    moved[:, -1, :2] += 0.1                                    # executed rows do count
    assert not torch.allclose(rescore_chain(policy, batch, moved, res.grid, reduce, executed=2)[:, -1],
                              res.step_log_probs[:, -1], atol=1e-3)


@pytest.fixture(scope="module")
def demo_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.mark.parametrize("decoder", ["mean_flow", "flow_matching"])
def test_default_path_train_then_finetune(tmp_path, monkeypatch, demo_cache, decoder):
    """What a user runs first: `train` with its defaults for the decoder (MeanFlow: the clean-chunk
    head), then `finetune`. Its first PPO update must stay a bounded step: finite logged KLs and an
    approximate KL to the rollout policy of a few nats at most (the clean-chunk head's last
    denoising step once made it overflow to inf and stopped the run at iteration 1)."""
    monkeypatch.setenv("ACTION_DECODER_CACHE", str(demo_cache))
    bc, out = tmp_path / "bc", tmp_path / "ft"
    assert main(["train", "--task", "metaworld/drawer-close", "--demos", "3", "--decoder", decoder, "--steps", "100",
                 "--output-dir", str(bc), "--eval-episodes", "0", "--no-progress"]) == 0
    assert main(["finetune", "--checkpoint", str(bc / "final"), "--output-dir", str(out), "--env-steps", "1",
                 "--num-envs", "4", "--group-size", "2", "--max-episode-steps", "60", "--eval-episodes", "0"]) == 0
    row = json.loads((out / "finetune_log.json").read_text())["history"][0]
    assert all(math.isfinite(v) for v in row.values() if isinstance(v, float)), row
    assert row["approx_kl"] < 3.0 and row["kl_bc"] < 3.0, row


def _ppo_data(policy, n=12, steps=5):
    batch, gen = _batch(n), torch.Generator().manual_seed(0)
    with torch.no_grad():
        res = sample_chain(policy, batch, steps, torch.Generator().manual_seed(0), executed=policy.config.n_action_steps)
    return {"states": batch["state"], "state_norm": batch["state"], "progress": torch.zeros(n), "chain": res.chain,
            "grid": res.grid, "logp_old": res.step_log_probs.clone(), "logp_ref": res.step_log_probs.clone(),
            "adv": torch.randn(n, generator=gen), "ret": torch.zeros(n)}


def test_ppo_update_rescores_in_micro_batches(monkeypatch):
    """The minibatch's gradient is accumulated over micro-batches: the network never sees more than
    MICROBATCH_ROW_CALLS // trained_steps rows with a live graph, and the update is the unsplit one."""
    base = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    data = _ppo_data(base)
    cfg = SimpleNamespace(trained_steps=3, ppo_epochs=2, minibatch_size=12, logprob_reduce="sum", ratio_tol=1e-4,
                          clip_eps=0.2, kl_coef=0.1, target_kl=100.0, vf_coef=0.5, grad_clip=1.0, lr_schedule="fixed",
                          lr_warmup_updates=0)
    results = []
    for budget in (10**6, 6):                                    # one micro-batch; then 6 // 3 = 2 rows each
        monkeypatch.setattr(ppo, "MICROBATCH_ROW_CALLS", budget)
        policy, value = copy.deepcopy(base), ValueNet(S)
        torch.manual_seed(0)
        value.load_state_dict(ValueNet(S).state_dict())
        rows, forward = [], policy.model.forward
        monkeypatch.setattr(policy.model, "forward",
                            lambda x, *a, **k: rows.append(x.shape[0] * torch.is_grad_enabled()) or forward(x, *a, **k))
        opt = torch.optim.SGD(list(policy.parameters()) + list(value.parameters()), lr=1e-2)
        stats = ppo_update(policy, value, opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))
        results.append((stats, policy.state_dict(), max(rows)))
    (s1, w1, rows1), (s2, w2, rows2) = results
    assert rows1 == 12 and rows2 == 2
    assert all(torch.allclose(w1[k], w2[k], atol=1e-6) for k in w1)
    assert s1.keys() == s2.keys() and all(s1[k] == pytest.approx(s2[k], rel=1e-4, abs=1e-5) for k in s1)


def test_approx_kl_stays_finite_where_a_step_density_collapses():
    """approx_kl estimates KL(π_old ‖ π_θ) on π_old's chains as mean(ratio − 1 − log ratio): a stored
    step that the updated policy finds e^200 times less likely adds ≈ 200/numel, not inf."""
    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    data = _ppo_data(policy)
    data["logp_old"][3, 4] += 200.0
    cfg = SimpleNamespace(trained_steps=5, ppo_epochs=1, minibatch_size=12, logprob_reduce="sum",
                          ratio_tol=float("inf"), clip_eps=0.2, kl_coef=0.0, target_kl=100.0, vf_coef=0.5,
                          grad_clip=1.0, lr_schedule="fixed", lr_warmup_updates=0)
    opt = torch.optim.SGD(policy.parameters(), lr=0.0)
    stats = ppo_update(policy, ValueNet(S), opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))
    assert stats["approx_kl"] == pytest.approx(199.0 / (12 * 5), rel=1e-3)
    assert stats["ratio_min"] == 0.0 and "kl_bc_update" not in stats


def _sac_setup():
    """A SAC update's parts on the tiny BC policy: policy, reference, twin Q, temperature, optimizers,
    a filled replay buffer of 16 chunk transitions, config and generator."""
    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=4)
    reference = finetune_policy(_bc(), sigma=0.5, learn_sigma=False, steps=4).requires_grad_(False)
    gen = torch.Generator().manual_seed(0)
    buffer = ReplayBuffer(16)
    buffer.add({"state": torch.randn(16, S, generator=gen), "progress": torch.rand(16, generator=gen),
                "actions": torch.rand(16, H, D, generator=gen) * 2 - 1, "reward": torch.rand(16, generator=gen),
                "next_state": torch.randn(16, S, generator=gen), "next_progress": torch.rand(16, generator=gen),
                "done": torch.zeros(16, dtype=torch.bool)})
    q, temperature = TwinQ(S, H * D), Temperature(0.01)
    optimizers = {"q": torch.optim.Adam(q.parameters(), lr=1e-3), "alpha": torch.optim.Adam(temperature.parameters()),
                  "actor": torch.optim.Adam(policy.parameters(), lr=1e-3)}
    cfg = SimpleNamespace(sac_batch_size=6, sde_steps=4, gamma=0.99, grad_clip=1.0, kl_coef=0.1, trained_steps=4,
                          alpha_lr=1e-2, tau=0.005)
    return policy, reference, q, temperature, optimizers, buffer, cfg, gen


def test_sac_actor_back_propagates_per_micro_batch(monkeypatch):
    """SAC's actor loss (K network calls per row) is back-propagated per micro-batch of
    MICROBATCH_ROW_CALLS // sde_steps rows; the update still uses the whole batch."""
    monkeypatch.setattr(ppo, "MICROBATCH_ROW_CALLS", 8)                 # 8 // 4 steps = 2 rows
    policy, reference, q, temperature, optimizers, buffer, cfg, gen = _sac_setup()
    rows, forward = [], policy.model.forward
    monkeypatch.setattr(policy.model, "forward",
                        lambda x, *a, **k: rows.append(x.shape[0] * torch.is_grad_enabled()) or forward(x, *a, **k))
    before = [p.detach().clone() for p in policy.model.parameters()]
    stats = sac_update(policy, reference, q, make_target(q), temperature, optimizers, buffer, lambda st: {"state": st},
                       cfg, gen)
    assert max(rows) == 2 and rows.count(2) == 3 * 2 * 4              # 3 micro-batches × (sample + re-score) × K
    assert all(math.isfinite(v) for v in stats.values()) and {"kl_bc_update", "actor_loss", "q"} <= stats.keys()
    assert any(not torch.equal(p, b) for p, b in zip(policy.model.parameters(), before))


def test_finetune_refuses_an_output_dir_in_use(tmp_path):
    """Two fine-tuning runs on one directory: the second stops at once, before loading anything."""
    from action_decoder.rl.finetune import finetune
    from action_decoder.run_dir import run_dir_lock

    out = tmp_path / "ft"
    with run_dir_lock(out):
        with pytest.raises(ValueError, match=r"--output-dir: .* is in use by another run"):
            finetune(FinetuneConfig(checkpoint=str(tmp_path / "missing"), output_dir=str(out)))
    with pytest.raises(FileNotFoundError):      # lock released: the run gets as far as the checkpoint
        finetune(FinetuneConfig(checkpoint=str(tmp_path / "missing"), output_dir=str(out)))


def test_adapt_lr_follows_the_kl_band_within_bounds():
    assert ppo.adapt_lr(1e-4, 0.5, 0.05, 1e-6, 1e-3) == pytest.approx(1e-4 / 1.5)       # beyond 2 × target
    assert ppo.adapt_lr(1e-4, 0.01, 0.05, 1e-6, 1e-3) == pytest.approx(1.5e-4)          # below target / 2
    assert ppo.adapt_lr(1e-4, 0.05, 0.05, 1e-6, 1e-3) == 1e-4                           # inside the band
    assert ppo.adapt_lr(1.1e-6, 9.0, 0.05, 1e-6, 1e-3) == 1e-6                          # floor
    assert ppo.adapt_lr(9e-4, 0.0, 0.05, 1e-6, 1e-3) == 1e-3                            # ceiling


@pytest.mark.parametrize("target_kl, moves", [(1e-9, "down"), (1e9, "up")])
def test_adaptive_lr_is_set_by_the_kl_after_each_update(target_kl, moves):
    """With the adaptive schedule, only minibatches measured after an update move the velocity
    network's learning rate (group 0), by 1.5 per minibatch, and the other groups keep theirs; the
    fixed schedule leaves every group alone. The rate stays in the optimizer's state."""
    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    data = _ppo_data(policy)
    value = ValueNet(S)
    lrs = {}
    for schedule in ("fixed", "adaptive"):
        p, v = copy.deepcopy(policy), copy.deepcopy(value)
        opt = torch.optim.Adam([{"params": list(p.model.parameters()), "lr": 1e-4},
                                {"params": list(v.parameters()), "lr": 1e-3}])
        cfg = SimpleNamespace(trained_steps=5, ppo_epochs=1, minibatch_size=3, logprob_reduce="sum",
                              ratio_tol=1e-4, clip_eps=0.2, kl_coef=0.0, target_kl=target_kl, vf_coef=0.5,
                              grad_clip=1.0, lr=1e-4, lr_schedule=schedule, lr_warmup_updates=0)
        stats = ppo_update(p, v, opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))
        lrs[schedule] = (stats["lr"], opt.param_groups[0]["lr"], opt.param_groups[1]["lr"], stats["epochs"])
    assert lrs["fixed"][:3] == (1e-4, 1e-4, 1e-3)
    lr, group_lr, critic_lr, _ = lrs["adaptive"]
    assert lr == group_lr and critic_lr == 1e-3
    if moves == "up":      # 4 minibatches of 3 rows, the first before any update: 3 × 1.5
        assert lr == pytest.approx(1e-4 * 1.5 ** 3)
    else:                  # the second minibatch is past 1.5 × target: one cut, then the early stop
        assert lr == pytest.approx(1e-4 / 1.5) and lrs["adaptive"][3] == 1


def test_warmup_lr_rises_linearly_to_lr():
    assert [ppo.warmup_lr(1e-4, n, 4) for n in range(6)] == pytest.approx([2.5e-5, 5e-5, 7.5e-5, 1e-4, 1e-4, 1e-4])
    assert ppo.warmup_lr(1e-4, 0, 0) == 1e-4                                            # no warm-up


def test_lr_warmup_sizes_the_first_updates_and_resumes_with_the_optimizer():
    """Adam's first step moves each weight by lr·sign(g) (up to ε): with a warm-up of N updates the
    first one moves the velocity network by at most lr / N, and the count lives in Adam's state, so
    a second call (the next iteration, or a resumed run) continues the ramp."""
    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    data = _ppo_data(policy)
    value = ValueNet(S)
    opt = torch.optim.Adam([{"params": list(policy.model.parameters()), "lr": 1e-3},
                            {"params": list(value.parameters()), "lr": 1e-3}])
    cfg = SimpleNamespace(trained_steps=5, ppo_epochs=1, minibatch_size=12, logprob_reduce="sum", ratio_tol=1e-4,
                          clip_eps=0.2, kl_coef=0.0, target_kl=1e9, vf_coef=0.5, grad_clip=1.0, lr=1e-3,
                          lr_schedule="fixed", lr_warmup_updates=8)
    before = [p.detach().clone() for p in policy.model.parameters()]
    stats = ppo_update(policy, value, opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))
    moved = max(float((p.detach() - b).abs().max()) for p, b in zip(policy.model.parameters(), before))
    assert stats["lr"] == pytest.approx(1e-3 / 8) and moved == pytest.approx(1e-3 / 8, rel=1e-3)
    for _ in range(8):                                       # one update per call (fresh chains): updates 2 … 9
        stats = ppo_update(policy, value, opt, lambda s: {"state": s}, _ppo_data(policy), cfg,
                           torch.Generator().manual_seed(0))
    assert stats["lr"] == 1e-3 and opt.param_groups[1]["lr"] == 1e-3      # ramp done; the critic's rate untouched


def test_ppo_logs_the_kl_of_the_first_update():
    """`approx_kl_first_update` is k3 of log(π_θ/π_old) on the stored chains after exactly one update:
    the same statistic recomputed on a copy of the policy that made only that update."""
    base = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    data = _ppo_data(base)
    cfg = SimpleNamespace(trained_steps=5, ppo_epochs=2, minibatch_size=12, logprob_reduce="sum", ratio_tol=1e-4,
                          clip_eps=0.2, kl_coef=0.0, target_kl=1e9, vf_coef=0.5, grad_clip=1.0, lr=1e-3,
                          lr_schedule="fixed", lr_warmup_updates=0)
    out = {}
    for epochs in (2, 1):
        policy, value = copy.deepcopy(base), ValueNet(S)
        opt = torch.optim.Adam([{"params": list(policy.model.parameters()), "lr": 1e-3},
                                {"params": list(value.parameters()), "lr": 1e-3}])
        out[epochs] = ppo_update(policy, value, opt, lambda s: {"state": s}, data, SimpleNamespace(**{**vars(cfg),
                                 "ppo_epochs": epochs}), torch.Generator().manual_seed(0))
    with torch.no_grad():
        lp = rescore_chain(policy, {"state": data["states"]}, data["chain"], data["grid"], "sum",
                           policy.config.n_action_steps)                                    # after one update
    expected = float(ppo.k3_kl(lp - data["logp_old"]).mean())
    assert expected > 1e-4 and out[2]["approx_kl_first_update"] == pytest.approx(expected, rel=1e-4)
    assert "approx_kl_first_update" not in out[1]                # one minibatch, one update: nothing measured after it
    assert out[2]["updates"] == 2 and out[1]["updates"] == 1
    # stopped by the KL at epoch 2's first minibatch: two epochs begun, one update taken
    policy, value = copy.deepcopy(base), ValueNet(S)
    opt = torch.optim.Adam(list(policy.model.parameters()) + list(value.parameters()), lr=1e-3)
    stop = ppo_update(policy, value, opt, lambda s: {"state": s}, data, SimpleNamespace(**{**vars(cfg),
                      "target_kl": 1e-6}), torch.Generator().manual_seed(0))
    assert stop["epochs"] == 2 and stop["updates"] == 1


def test_kl_penalty_gradient_is_that_of_kl_to_the_reference():
    """On samples of π_θ = N(μ, s²) the penalty's mean gradient is ∇ KL(π_θ ‖ π_ref), π_ref = N(0, 1):
    (μ, s − 1/s) in closed form; k3's gradient is that of the reverse KL, (μ/s², 1/s − (1 + μ²)/s³)."""
    mu, s = torch.tensor(0.5, requires_grad=True), torch.tensor(1.5, requires_grad=True)
    x = (mu + s * torch.randn(400_000, generator=torch.Generator().manual_seed(0))).detach()
    logp, logp_ref = Normal(mu, s).log_prob(x), Normal(0.0, 1.0).log_prob(x)
    grad = torch.autograd.grad(ppo.kl_penalty(logp, logp_ref).mean(), (mu, s), retain_graph=True)
    assert [float(g) for g in grad] == pytest.approx([0.5, 1.5 - 1 / 1.5], abs=0.02)
    reverse = torch.autograd.grad(ppo.k3_kl(logp_ref - logp).mean(), (mu, s))
    assert [float(g) for g in reverse] == pytest.approx([0.5 / 1.5 ** 2, 1 / 1.5 - 1.25 / 1.5 ** 3], abs=0.02)


def test_training_layouts_of_different_seeds_do_not_overlap():
    """Each iteration plays num_envs / group layouts, `group` envs each; a seed's layouts are distinct over a
    run, lie in the training range, and the first 16 seeds share none over 200 iterations of the defaults."""
    from action_decoder.rl.finetune import TRAIN_LAYOUT_BASE, TRAIN_LAYOUT_SPAN, train_layout_seeds

    it = train_layout_seeds(3, 7, 32, 4)
    assert it == [x for x in dict.fromkeys(it) for _ in range(4)] and len(set(it)) == 8
    runs = [[x for i in range(200) for x in train_layout_seeds(seed, i, 32, 4)[::4]] for seed in range(16)]
    assert all(len(set(r)) == 1600 and TRAIN_LAYOUT_BASE <= min(r) and max(r) < TRAIN_LAYOUT_BASE + TRAIN_LAYOUT_SPAN
               for r in runs)
    assert len(set().union(*map(set, runs))) == 16 * 1600


@pytest.mark.parametrize("reduce", ["sum", "mean"])
def test_chunks_cut_short_drop_the_rows_they_did_not_execute(reduce):
    """Per-row counts: a chunk whose episode ended after one action keeps one row of its last step."""
    from action_decoder.rl.sde_policy import reduce_step_log_probs

    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=3)
    batch = _batch()
    with torch.no_grad():
        res = sample_chain(policy, batch, 3, torch.Generator().manual_seed(0), reduce=reduce)
        full = policy.chain_log_prob(batch, res.chain, res.grid, reduce="none")            # [B, K, H, D]
    counts = torch.tensor([1, 3] + [4] * (len(res.chain) - 2))
    per_row = reduce_step_log_probs(full, reduce, counts)
    for i, n in enumerate(counts.tolist()):
        torch.testing.assert_close(per_row[i], reduce_step_log_probs(full[i:i + 1], reduce, n)[0])
    assert not torch.allclose(per_row[0, -1], per_row[1, -1])
    torch.testing.assert_close(rescore_chain(policy, batch, res.chain, res.grid, reduce, counts), per_row)


def test_finetune_with_chunks_cut_by_the_episode_cap_stays_on_policy(tmp_path):
    """A cap of 10 steps with 4 actions per decision cuts each episode's last chunk after 2 actions:
    those chunks are re-scored without their unexecuted rows, and PPO's first ratio is still 1."""
    ckpt, out = tmp_path / "bc", tmp_path / "ft"
    _bc().save_pretrained(ckpt)
    assert main(["finetune", "--checkpoint", str(ckpt), "--output-dir", str(out), "--env-steps", "40",
                 "--num-envs", "2", "--max-episode-steps", "10", "--sde-steps", "3", "--trained-steps", "2",
                 "--eval-episodes", "1", "--minibatch-size", "4", "--group-size", "2", "--reward", "success"]) == 0
    history = json.loads((out / "finetune_log.json").read_text())["history"]
    assert history and all(h["ratio_dev_before_update"] <= 1e-4 for h in history)


def test_adaptive_rate_comes_down_when_the_kl_stop_ends_an_iteration():
    """An approximate KL between 1.5 and 2 × target stops the epochs; the rate that got there must not rise."""
    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    data = _ppo_data(policy)
    kl = {"value": 0.0}
    cfg = SimpleNamespace(trained_steps=5, ppo_epochs=4, minibatch_size=4, logprob_reduce="sum", ratio_tol=1e-4,
                          clip_eps=0.2, kl_coef=0.0, target_kl=0.05, vf_coef=0.5, grad_clip=1.0,
                          lr_schedule="adaptive", lr_warmup_updates=0, lr=1e-4)
    opt = torch.optim.Adam([{"params": list(policy.model.parameters()), "lr": 1e-4}])
    real = ppo.k3_kl
    calls = []

    def kl_after_the_first(x, numel=1.0):           # 1.8 × target from the second minibatch on
        calls.append(1)
        return real(x, numel) if len(calls) == 1 else torch.full_like(real(x), 0.09)

    ppo.k3_kl = kl_after_the_first
    try:
        stats = ppo_update(policy, ValueNet(S), opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))
    finally:
        ppo.k3_kl = real
    assert stats["updates"] == 1 and opt.param_groups[0]["lr"] == pytest.approx(1e-4 / ppo.LR_STEP)


def test_sac_kl_penalty_uses_the_k2_term_whose_gradient_is_kl_from_the_policy(monkeypatch):
    """SAC's penalty, like PPO's, back-propagates `ppo.kl_penalty` (k2: ∇KL(π_θ ‖ π_BC) on π_θ's chains,
    tested in closed form above); k3 would give the reverse KL's gradient."""
    used = []
    real = ppo.kl_penalty
    monkeypatch.setattr(ppo, "kl_penalty", lambda lp, ref: used.append(lp.requires_grad) or real(lp, ref))
    policy, reference, q, temperature, optimizers, buffer, cfg, gen = _sac_setup()
    stats = sac_update(policy, reference, q, make_target(q), temperature, optimizers, buffer, lambda st: {"state": st},
                       cfg, gen)
    assert used and all(used) and stats["kl_bc_update"] >= 0


def test_a_sac_fine_tuned_policy_samples_the_squashed_actions_it_trained_on():
    from action_decoder.rl.sde_policy import squash_to_box

    policy = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=3, squash=True).eval()
    batch, noise = _batch(), torch.randn(6, 4, 4)
    out = policy.sample(batch, sampler="sde", noise=noise, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(out.actions, squash_to_box(out.chain[:, -1], policy.normalizers["actions"])[0])
    assert out.actions.abs().max() < 1
    plain = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=3).eval()
    assert not plain.config.action_squash


@pytest.mark.parametrize("args, words", [
    (["--reward", "success", "--success-reward", "nan"], "--success-reward: expected a finite number"),
    (["--success-reward", "-1"], "--success-reward: expected a positive reward"),
    (["--shaping-scale", "nan"], "--shaping-scale: expected >= 0"),
    (["--kl-coef", "nan"], "--kl-coef: expected >= 0"),
    (["--sigma", "1e6"], "--sigma: expected a noise scale in [0.001, 10]"),
    (["--sigma", "1e-30"], "--sigma: expected a noise scale"),
    (["--algo", "sac", "--buffer-size", "4", "--sac-batch-size", "8"], "--buffer-size: expected at least --sac-batch-size (8)"),
])
def test_finetune_refuses_nan_and_out_of_range_numbers_in_one_line(tmp_path, capsys, args, words):
    ckpt = tmp_path / "bc"
    _bc().save_pretrained(ckpt)
    assert main(["finetune", "--checkpoint", str(ckpt), "--output-dir", str(tmp_path / "ft"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


def test_finetune_resume_refuses_another_bc_checkpoint(tmp_path, capsys):
    ckpt, other, out = tmp_path / "bc", tmp_path / "bc2", tmp_path / "ft"
    _bc().save_pretrained(ckpt)
    torch.manual_seed(1)
    moved = _bc()
    with torch.no_grad():
        next(moved.parameters()).add_(0.1)
    moved.save_pretrained(other)
    args = ["finetune", "--output-dir", str(out), "--env-steps", "24", "--num-envs", "2", "--max-episode-steps", "12",
            "--sde-steps", "3", "--trained-steps", "2", "--eval-episodes", "1", "--minibatch-size", "4",
            "--group-size", "2"]
    assert main([*args, "--checkpoint", str(ckpt)]) == 0
    capsys.readouterr()
    assert main([*args, "--checkpoint", str(other), "--env-steps", "48", "--resume"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--checkpoint: " in err[0] and "other BC weights" in err[0], err
    assert main([*args, "--checkpoint", str(ckpt), "--env-steps", "48", "--resume"]) == 0


def test_mean_reduced_log_probs_give_kl_per_element_from_the_summed_ratio():
    """With `--logprob-reduce mean` the KLs are the chunk's KL / (H·D): in closed form for Gaussians
    (N(μ, 1) against N(0, 1) on n elements: KL = n·μ²/2), and through `ppo_update`, whose approx_kl,
    kl_bc_update and penalty gradient with averaged log-probs are the summed ones / n."""
    n, mu = 16, 0.5
    x = mu + torch.randn(200_000, n, generator=torch.Generator().manual_seed(0))
    log_ratio_ref = (Normal(0.0, 1.0).log_prob(x) - Normal(mu, 1.0).log_prob(x))          # [S, n]
    per_element = float(ppo.k3_kl(log_ratio_ref.mean(-1, keepdim=True), n).mean())
    assert per_element == pytest.approx(mu ** 2 / 2, rel=0.03)
    assert float(ppo.k3_kl(log_ratio_ref.mean(-1)).mean()) < 0.25 * mu ** 2 / 2         # k3 of the mean: not it
    lp = torch.tensor([[0.3]], requires_grad=True)
    g = torch.autograd.grad(ppo.kl_penalty(lp, torch.zeros(1, 1), n).sum(), lp)[0]
    assert float(g) == pytest.approx(n * 0.3)          # ∇ of ½(n·Δ)²/n: the summed one's gradient / n per unit sum

    base = finetune_policy(_bc(), sigma=0.5, learn_sigma=True, steps=5)
    batch = _batch(12)
    with torch.no_grad():
        full = base.chain_log_prob(batch, _ppo_data(base)["chain"], _ppo_data(base)["grid"], reduce="none")
    data = _ppo_data(base)
    shift = torch.linspace(-0.4, 0.6, 12)[:, None].expand(12, 5)                         # per-chain log-ratios
    stats, grads = {}, {}
    for reduce in ("sum", "mean"):
        numel = 1.0 if reduce == "sum" else H * D
        lp = full.sum((-2, -1)) / numel                                                   # [12, 5]
        d = {**data, "logp_old": lp + shift / numel, "logp_ref": lp - 2 * shift / numel, "adv": torch.zeros(12)}
        policy = copy.deepcopy(base)
        cfg = SimpleNamespace(trained_steps=5, ppo_epochs=1, minibatch_size=12, logprob_reduce=reduce,
                              ratio_tol=float("inf"), clip_eps=0.2, kl_coef=1.0, target_kl=100.0, vf_coef=0.5,
                              grad_clip=1e9, lr_schedule="fixed", lr_warmup_updates=0)
        opt = torch.optim.SGD(policy.model.parameters(), lr=0.0)
        stats[reduce] = ppo_update(policy, ValueNet(S), opt, lambda s: {"state": s}, d, cfg,
                                   torch.Generator().manual_seed(0))
        grads[reduce] = torch.cat([p.grad.flatten() for p in policy.model.parameters() if p.grad is not None])
    for key in ("approx_kl", "kl_bc_update"):
        assert stats["mean"][key] == pytest.approx(stats["sum"][key] / (H * D), rel=1e-4), key
    assert torch.allclose(grads["mean"], grads["sum"] / (H * D), rtol=1e-3, atol=1e-7)


@pytest.mark.parametrize("schedule", ["explore", "fixed"])
def test_on_policy_check_passes_chains_sampled_in_small_batches_and_rescored_in_micro_batches(schedule):
    """The rollout samples on the envs still running (1–3 rows), PPO re-scores in micro-batches of 25:
    float32 rounds the network's products differently, by more than --ratio-tol at a small σ. The
    check allows that rounding (`ppo.rescore_rounding`) and still catches a re-scoring with another σ."""
    torch.manual_seed(0)
    cfg_d = DecoderConfig(decoder_type="flow_matching", state_dim=S, action_dim=D, action_chunk_size=8,
                          n_action_steps=4, hidden_size=32, num_hidden_layers=2, num_attention_heads=2,
                          num_key_value_heads=1, extra={"tasks": ["reach-v3"]})
    bc = ActionDecoderPolicy(cfg_d, _stats(torch.Generator().manual_seed(0)))
    with torch.no_grad():
        for p in bc.model.parameters():
            p.mul_(2.0 if p.dim() == 2 else 1.0)          # larger velocities, as trained networks have
    policy = finetune_policy(bc, sigma=0.003, learn_sigma=True, steps=10, schedule=schedule)
    states = torch.randn(45, S, generator=torch.Generator().manual_seed(1))
    gen, parts, i = torch.Generator().manual_seed(0), [], 0
    with torch.no_grad():
        while i < len(states):
            b = 1 + i % 3
            parts.append(sample_chain(policy, {"state": states[i:i + b]}, 10, gen, executed=4))
            i += b
    data = {"states": states, "state_norm": states, "progress": torch.zeros(45),
            "chain": torch.cat([r.chain for r in parts]), "grid": parts[0].grid,
            "logp_old": torch.cat([r.step_log_probs for r in parts]), "adv": torch.randn(45, generator=gen),
            "ret": torch.zeros(45)}
    data["logp_ref"] = data["logp_old"]
    cfg = SimpleNamespace(trained_steps=10, ppo_epochs=1, minibatch_size=45, logprob_reduce="sum", ratio_tol=1e-4,
                          clip_eps=0.2, kl_coef=0.0, target_kl=1e9, vf_coef=0.5, grad_clip=1.0, lr_schedule="fixed",
                          lr_warmup_updates=0)
    opt = torch.optim.SGD(policy.model.parameters(), lr=0.0)
    stats = ppo_update(policy, ValueNet(S), opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))
    assert stats["ratio_dev_before_update"] > cfg.ratio_tol           # rounding alone exceeds --ratio-tol here
    with torch.no_grad():
        policy.sigma.log_scale.fill_(0.05)                              # σ re-scored 5 % off
    with pytest.raises(RuntimeError, match="ratio is not 1"):
        ppo_update(policy, ValueNet(S), opt, lambda s: {"state": s}, data, cfg, torch.Generator().manual_seed(0))


def _tiny_finetune_args(ckpt, out, *more):
    return ["finetune", "--checkpoint", str(ckpt), "--output-dir", str(out), "--num-envs", "2",
            "--max-episode-steps", "12", "--sde-steps", "3", "--trained-steps", "2", "--eval-episodes", "0", *more]


@pytest.mark.parametrize("algo", ["sac", "ppo"])
def test_cpu_budget_holds_within_one_update(tmp_path, monkeypatch, algo):
    """Each update costs 100 s of (simulated) CPU: with a budget of 250 s the run stops after the update
    that spends it (the third), inside the first iteration, not after that iteration's 12 updates; the
    iteration logs the updates it took and is checkpointed, and final/ is written."""
    import importlib
    import time

    F = importlib.import_module("action_decoder.rl.finetune")              # the module, not the function
    clock, real = {"extra": 0.0}, time.process_time
    monkeypatch.setattr(time, "process_time", lambda: real() + clock["extra"])

    def costly(fn):
        def update(*a, **k):
            clock["extra"] += 100.0
            return fn(*a, **k)
        return update

    if algo == "sac":                      # 2 envs × 3 decisions × 2 updates per decision = 12 SAC updates
        monkeypatch.setattr(F, "sac_update", costly(F.sac_update))
        more = ["--sac-batch-size", "4", "--sac-updates-per-decision", "2"]
    else:                                  # 6 decisions in minibatches of 2, 4 epochs: 12 minibatch updates
        monkeypatch.setattr(ppo, "rescore_chain", costly(ppo.rescore_chain))
        more = ["--group-size", "2", "--minibatch-size", "2", "--target-kl", "1e9"]
    ckpt, out = tmp_path / "bc", tmp_path / "ft"
    _bc().save_pretrained(ckpt)
    assert main(_tiny_finetune_args(ckpt, out, "--algo", algo, "--env-steps", "100000",
                                    "--max-cpu-minutes", str(250 / 60), *more)) == 0
    history = json.loads((out / "finetune_log.json").read_text())["history"]
    assert len(history) == 1 and history[0]["updates"] == 3, history
    assert 250 <= history[0]["cpu_s"] < 250 + 100 + 30                      # within one update's cost
    assert (out / "checkpoints" / "step_0000001").is_dir() and (out / "final").is_dir()


def test_ctrl_c_inside_a_sac_iteration_checkpoints_it_and_resume_continues_exactly(tmp_path, capsys, monkeypatch):
    """Ctrl-C during the 5th SAC update of the second iteration: the update finishes, a checkpoint holding
    the iteration's progress is written and named by the interrupt line, and --resume continues inside
    the iteration: the run ends with the uninterrupted run's weights and log."""
    import importlib
    import os
    import signal

    F = importlib.import_module("action_decoder.rl.finetune")
    ckpt = tmp_path / "bc"
    _bc().save_pretrained(ckpt)
    args = ["--algo", "sac", "--env-steps", "40", "--sac-batch-size", "4", "--sac-updates-per-decision", "2"]
    assert main(_tiny_finetune_args(ckpt, tmp_path / "a", *args)) == 0
    calls, real = [], F.sac_update

    def interrupted_at_17(*a, **k):                # 12 updates per iteration: the 5th of iteration 2
        calls.append(1)
        if len(calls) == 17:
            os.kill(os.getpid(), signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(F, "sac_update", interrupted_at_17)
    capsys.readouterr()
    assert main(_tiny_finetune_args(ckpt, tmp_path / "b", *args)) == 130
    err = capsys.readouterr().err
    step = tmp_path / "b" / "checkpoints" / "step_0000001"
    assert f"continue from {step} with --resume" in err and step.is_dir(), err
    assert len(calls) == 17 and not (tmp_path / "b" / "final").exists()
    from action_decoder.run_dir import load_state
    pending = load_state(step)["pending"]
    assert len(pending["runs"]) == 5 and pending["n_updates"] == 12
    monkeypatch.setattr(F, "sac_update", real)
    assert main(_tiny_finetune_args(ckpt, tmp_path / "b", *args, "--resume")) == 0
    assert "inside iteration 2, after 5 of its 12 updates" in capsys.readouterr().out
    logs = [json.loads((tmp_path / r / "finetune_log.json").read_text())["history"] for r in "ab"]
    clock = ("wall_s", "cpu_s", "rollout_cpu_s")
    assert [{k: v for k, v in h.items() if k not in clock} for h in logs[0]] == \
           [{k: v for k, v in h.items() if k not in clock} for h in logs[1]]
    a, b = (ActionDecoderPolicy.from_pretrained(tmp_path / r / "final").state_dict() for r in "ab")
    assert all(torch.equal(a[k], b[k]) for k in a)
    # A long iteration checkpoints inside itself (--checkpoint-minutes): updates cost 100 s of simulated CPU,
    # so a checkpoint is due before the 4th; a crash at the 6th loses only the updates after it.
    import time
    clock, process_time, calls = {"extra": 0.0}, time.process_time, []
    monkeypatch.setattr(time, "process_time", lambda: process_time() + clock["extra"])

    def crash_at_6(*a, **k):
        calls.append(1)
        if len(calls) == 6:
            raise RuntimeError("simulated crash")
        clock["extra"] += 100.0
        return real(*a, **k)

    monkeypatch.setattr(F, "sac_update", crash_at_6)
    c = _tiny_finetune_args(ckpt, tmp_path / "c", *args, "--checkpoint-minutes", str(250 / 60))
    with pytest.raises(RuntimeError, match="simulated crash"):
        main(c)
    assert len(load_state(tmp_path / "c" / "checkpoints" / "step_0000000")["pending"]["runs"]) == 3
    monkeypatch.setattr(F, "sac_update", real)
    assert main([*c, "--resume"]) == 0
    assert "inside iteration 1, after 3 of its 12 updates" in capsys.readouterr().out
    c_final = ActionDecoderPolicy.from_pretrained(tmp_path / "c" / "final").state_dict()
    assert all(torch.equal(a[k], c_final[k]) for k in a)


def test_an_interrupt_before_the_first_checkpoint_names_no_checkpoint(tmp_path, capsys, monkeypatch):
    def interrupted(cfg):
        raise KeyboardInterrupt

    monkeypatch.setattr("action_decoder.rl.finetune", interrupted)
    assert main(["finetune", "--checkpoint", str(tmp_path / "bc"), "--output-dir", str(tmp_path / "ft")]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"action-decoder: interrupted before the first checkpoint in {tmp_path / 'ft'}: nothing to "
                   f"resume, run it again"]


def test_best_by_evaluation_is_kept_beside_the_last_weights(tmp_path, monkeypatch, capsys):
    """Evaluations 0.50 (start), 0.75 (iteration 1), 0.60 (iteration 2, the last): final/ keeps the last
    weights and says so, best/ keeps iteration 1's with its evaluation, and the run output names both."""
    import importlib

    from action_decoder.model_card import CARD_NAME

    F = importlib.import_module("action_decoder.rl.finetune")
    scores = iter([0.5, 0.5, 0.75, 0.7, 0.6, 0.8])                    # (sde, ode) per evaluation
    monkeypatch.setattr("action_decoder.envs.evaluate", lambda *a, **k: {"success_rate": next(scores)})
    ckpt, out = tmp_path / "bc", tmp_path / "ft"
    _bc().save_pretrained(ckpt)
    assert main(_tiny_finetune_args(ckpt, out, "--env-steps", "48", "--group-size", "2", "--minibatch-size", "4",
                                    "--eval-episodes", "3", "--eval-every", "1", "--checkpoint-every", "1")) == 0
    best = json.loads((out / F.BEST / F.BEST_EVAL).read_text())
    assert (best["iteration"], best["success_sde"], best["success_ode"], best["episodes"]) == (1, 0.75, 0.7, 3)
    assert json.loads((out / "finetune_log.json").read_text())["best"]["iteration"] == 1
    weights = {d: ActionDecoderPolicy.from_pretrained(d).state_dict()
               for d in (out / F.BEST, out / "checkpoints" / "step_0000001", out / "final", out / "checkpoints" / "step_0000002")}
    same = lambda a, b: all(torch.equal(weights[a][k], weights[b][k]) for k in weights[a])   # noqa: E731
    assert same(out / F.BEST, out / "checkpoints" / "step_0000001")
    assert same(out / "final", out / "checkpoints" / "step_0000002") and not same(out / "final", out / F.BEST)
    assert "best weights by closed-loop evaluation" in (out / F.BEST / CARD_NAME).read_text()
    card = (out / "final" / CARD_NAME).read_text()
    assert "These are the last weights" in card and "holds the best by evaluation (iteration 1" in card
    printed = capsys.readouterr().out
    assert f"saved {out / 'final'}: the last weights" in printed
    assert f"best by evaluation: {out / F.BEST}, iteration 1, success sde=0.750 ode=0.700" in printed
    assert "finetune_weights" not in json.loads((out / "checkpoints" / "step_0000002" / "config.json").read_text())["extra"]
