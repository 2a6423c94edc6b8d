"""Training-time real-time chunking: per-token times, the prefix-masked losses, prefix-fed sampling,
the policy's modes and the CLI (train --rtc-max-delay, eval --rtc-mode)."""

import json
import re

import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.config import CONFIG_FORMAT_VERSION
from action_decoder.expert import ActionExpert
from action_decoder.flows import (flow_matching_loss, meanflow_loss, sample_meanflow, sample_meanflow_prefix,
                                  sample_ode, sample_ode_prefix)
from action_decoder.flows.losses import sample_meanflow_times
from action_decoder.flows.rtc_trained import delay_probs, prefix_mask, sample_delays, with_clean_prefix

H, D = 8, 3


def tiny(decoder_type="flow_matching", **kw):
    torch.manual_seed(0)
    kw = {"num_inference_timesteps": 2, **kw}
    cfg = DecoderConfig(decoder_type=decoder_type, state_dim=6, action_dim=D, action_chunk_size=H, hidden_size=32,
                        num_hidden_layers=1, **kw)
    stats = {"state": {"mean": torch.zeros(6), "std": torch.ones(6), "min": -torch.ones(6), "max": torch.ones(6)},
             "actions": {"mean": torch.full((D,), 0.5), "std": torch.full((D,), 2.0), "min": -torch.ones(D),
                         "max": torch.ones(D)}}
    return ActionDecoderPolicy(cfg, stats).eval()


# ---------------------------------------------------------------------------- per-token times
def test_per_token_times_equal_the_per_sample_path_when_all_times_are_equal():
    torch.manual_seed(0)
    net = ActionExpert(DecoderConfig(decoder_type="mean_flow", state_dim=5, action_dim=D, action_chunk_size=H,
                                     hidden_size=32, num_hidden_layers=2)).double()
    x, state = torch.randn(4, H, D, dtype=torch.float64), torch.randn(4, 5, dtype=torch.float64)
    t, r = torch.rand(4, dtype=torch.float64), torch.rand(4, dtype=torch.float64)
    scalar = net(x, t, r, state)
    tokens = net(x, t[:, None].expand(4, H), r[:, None].expand(4, H), state)
    torch.testing.assert_close(tokens, scalar, rtol=0, atol=1e-12)
    # A clean prefix (t = r = 1 on the first two rows) changes the output: the tokens see their own time.
    keep = prefix_mask(torch.full((4,), 2), H)
    t2, r2 = torch.where(keep, 1.0, t[:, None]), torch.where(keep, 1.0, r[:, None])
    assert (net(x, t2, r2, state) - scalar).abs().max() > 1e-3
    with pytest.raises(ValueError, match=r"t: expected shape \[4\] or \[4, 8\] \(per action token\)"):
        net(x, torch.rand(4, H + 1), r, state)


def test_clean_rows_are_the_per_token_path_with_those_rows_at_one():
    """`clean_rows` with per-sample t, r (the exported graph's form, its time embeddings constants) gives the
    network of per-token times 1 on the marked rows and t, r elsewhere; a bad mask is one line."""
    torch.manual_seed(2)
    net = ActionExpert(DecoderConfig(decoder_type="mean_flow", state_dim=5, action_dim=D, action_chunk_size=H,
                                     hidden_size=32, num_hidden_layers=2)).double()
    x, state = torch.randn(4, H, D, dtype=torch.float64), torch.randn(4, 5, dtype=torch.float64)
    t = torch.rand(4, dtype=torch.float64)
    r = t + (1 - t) * torch.rand(4, dtype=torch.float64)                        # t ≤ r ≤ 1
    keep = prefix_mask(torch.tensor([0, 1, 3, 7]), H)
    want = net(x, torch.where(keep, 1.0, t[:, None]), torch.where(keep, 1.0, r[:, None]), state)
    torch.testing.assert_close(net(x, t, r, state, clean_rows=keep), want, rtol=0, atol=1e-10)
    assert (want[1:] - net(x, t, r, state)[1:]).abs().max() > 1e-3            # the marked rows change the output
    for bad in (keep.double(), keep[:, :-1]):
        with pytest.raises(ValueError, match=r"clean_rows: expected a bool tensor \[4, 8\] with t and r per sample"):
            net(x, t, r, state, clean_rows=bad)
    with pytest.raises(ValueError, match="clean_rows: .* t \\[4, 8\\]"):
        net(x, t[:, None].expand(4, H), r, state, clean_rows=keep)


def test_per_token_offsets_are_each_tokens_own_embedding_less_the_earliest():
    """Any times per token (not only a prefix at 1): token j gets embed_t(t_j) − embed_t(min t) +
    embed_r(r_j) − embed_r(min r), the t and r tokens the earliest times' embeddings; the sinusoidal
    features of all those times are computed in one call (the second embedding reuses them)."""
    from unittest import mock

    from action_decoder.expert import embeddings

    torch.manual_seed(1)
    net = ActionExpert(DecoderConfig(decoder_type="mean_flow", state_dim=5, action_dim=D, action_chunk_size=H,
                                     hidden_size=32, num_hidden_layers=1)).double()
    t, r = torch.rand(3, H, dtype=torch.float64), torch.rand(3, H, dtype=torch.float64)
    calls = []
    real = embeddings.sinusoidal_features
    with mock.patch.object(embeddings, "sinusoidal_features", lambda *a: (calls.append(1), real(*a))[1]):
        t_tok, r_tok, off = net._token_times(t, r, 3, H)
    assert len(calls) == 1
    e_t = lambda v: net.t_embed(v.reshape(-1)).view(*v.shape, -1)         # noqa: E731
    e_r = lambda v: net.r_embed(v.reshape(-1)).view(*v.shape, -1)         # noqa: E731
    t0, r0 = t.amin(1), r.amin(1)
    torch.testing.assert_close(t_tok, e_t(t0), rtol=0, atol=1e-12)
    torch.testing.assert_close(r_tok, e_r(r0), rtol=0, atol=1e-12)
    want = e_t(t) - e_t(t0)[:, None] + e_r(r) - e_r(r0)[:, None]
    torch.testing.assert_close(off, want, rtol=0, atol=1e-12)


# ---------------------------------------------------------------------------- the losses
def test_flow_matching_loss_scores_only_the_rows_after_the_clean_prefix():
    """Oracle: the velocity returns 0 on the live rows and 1e6 on the prefix; the loss is then the
    closed-form mean of |a − e|² over the live rows, from the same draws."""
    a = torch.randn(64, H, D, dtype=torch.float64)
    seen = []

    def velocity(x, t):
        keep = t == 1.0                                                     # [B, H] per-token times
        seen.append(bool(torch.equal(x[keep], a[keep])))                   # prefix rows given clean
        return torch.where(keep[..., None], torch.full_like(x, 1e6), torch.zeros_like(x))

    loss = flow_matching_loss(velocity, a, torch.Generator().manual_seed(3), rtc_max_delay=3)
    g = torch.Generator().manual_seed(3)
    t = torch.rand(64, generator=g, dtype=torch.float64)
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    d = sample_delays(64, 3, g)
    live = ~prefix_mask(d, H)
    want = torch.stack([(a - e)[b][live[b]].square().mean() for b in range(64)]).mean()
    torch.testing.assert_close(loss, want, rtol=1e-12, atol=0)
    assert seen == [True] and set(d.tolist()) == {0, 1, 2, 3}
    assert (t < 1).all()
    # rtc_max_delay = 0 is the plain loss, with the same draws.
    plain = flow_matching_loss(lambda x, t: torch.zeros_like(x), a, torch.Generator().manual_seed(3))
    torch.testing.assert_close(plain, (a - e).square().mean(), rtol=1e-12, atol=0)


def test_delay_distributions_uniform_and_exp():
    """P(d) on 0..max: uniform keeps torch.randint's draws; exp ∝ e^(−d) puts row 0 of a chunk in the loss of
    1/Σe^(−d) = 64 % of the chunks at max_delay = 4 (uniform: 20 %)."""
    g = lambda: torch.Generator().manual_seed(7)                              # noqa: E731
    assert torch.equal(sample_delays(1000, 4, g()), torch.randint(0, 5, (1000,), generator=g()))
    p = delay_probs(4, "exp")
    torch.testing.assert_close(p, torch.exp(-torch.arange(5.0, dtype=torch.float64)) / sum(
        torch.exp(torch.tensor(-k, dtype=torch.float64)) for k in range(5)))
    assert abs(float(p[0]) - 0.6364) < 1e-4 and float(delay_probs(4)[0]) == 0.2
    d = sample_delays(200_000, 4, g(), dist="exp")
    freq = torch.bincount(d, minlength=5).double() / d.numel()
    torch.testing.assert_close(freq, p, rtol=0, atol=4e-3)
    assert int(d.min()) == 0 and int(d.max()) == 4
    torch.testing.assert_close(delay_probs(4, "half_zero"), torch.tensor([0.5, 0.125, 0.125, 0.125, 0.125],
                                                                       dtype=torch.float64))
    half = torch.bincount(sample_delays(200_000, 4, g(), dist="half_zero"), minlength=5).double() / 200_000
    torch.testing.assert_close(half, delay_probs(4, "half_zero"), rtol=0, atol=4e-3)
    assert delay_probs(0, "half_zero").tolist() == [1.0]
    # The share of chunks whose row j is in the loss, P(d <= j): exp keeps the first rows trained.
    live = (~prefix_mask(d, H)).double().mean(0)                            # [H]
    torch.testing.assert_close(live[:5], p.cumsum(0), rtol=0, atol=4e-3)
    with pytest.raises(ValueError, match=r"rtc_delay_dist: expected one of \['uniform', 'exp', 'half_zero'\], got 'normal'"):
        delay_probs(4, "normal")
    with pytest.raises(ValueError, match=r"rtc_delay_dist: expected one of \['uniform', 'exp', 'half_zero'\], got 'normal'"):
        flow_matching_loss(lambda x, t: x, torch.zeros(2, H, D), rtc_max_delay=2, rtc_delay_dist="normal")


def test_flow_matching_loss_draws_its_delays_from_the_delay_distribution():
    a = torch.randn(256, H, D, dtype=torch.float64)
    oracle = lambda x, t: torch.zeros_like(x)                                # noqa: E731
    loss = flow_matching_loss(oracle, a, torch.Generator().manual_seed(3), rtc_max_delay=4, rtc_delay_dist="exp")
    g = torch.Generator().manual_seed(3)
    torch.rand(256, generator=g, dtype=torch.float64)
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    live = ~prefix_mask(sample_delays(256, 4, g, dist="exp"), H)
    want = torch.stack([(a - e)[b][live[b]].square().mean() for b in range(256)]).mean()
    torch.testing.assert_close(loss, want, rtol=1e-12, atol=0)


def test_given_delays_fix_those_rows_prefixes_and_leave_the_others_drawn():
    """A relabelled frame's committed rows (`rtc_delays` > 0) are its prefix; rows with 0 keep the same draws
    as without `rtc_delays`, so a dataset without committed prefixes trains exactly as before."""
    a = torch.randn(256, H, D, dtype=torch.float64)
    oracle = lambda x, t: torch.zeros_like(x)                                # noqa: E731
    given = torch.tensor([0, 3, 1, 0] * 64)
    for decoder in ("flow_matching", "mean_flow"):
        seen = []

        def velocity(x, t, r=None):
            seen.append((t == 1.0).sum(1))                                        # [B] clean rows per chunk
            return torch.zeros_like(x)

        g = torch.Generator().manual_seed(5)
        if decoder == "flow_matching":
            flow_matching_loss(velocity, a, g, rtc_max_delay=4, rtc_delay_dist="exp", rtc_delays=given)
        else:
            meanflow_loss(velocity, a, g, target="split", rtc_max_delay=4, rtc_delay_dist="exp", rtc_delays=given)
        g = torch.Generator().manual_seed(5)
        if decoder == "flow_matching":
            torch.rand(256, generator=g, dtype=torch.float64)
        else:
            sample_meanflow_times(256, 0.5, 0.4, 1.0, g, None, torch.float64, "logit_normal")
        torch.randn(a.shape, generator=g, dtype=torch.float64)
        drawn = sample_delays(256, 4, g, dist="exp")
        assert torch.equal(seen[0], torch.where(given > 0, given, drawn)), decoder
    loss = flow_matching_loss(oracle, a, torch.Generator().manual_seed(3), rtc_max_delay=4, rtc_delay_dist="exp",
                              rtc_delays=torch.full((256,), 4))
    g = torch.Generator().manual_seed(3)
    torch.rand(256, generator=g, dtype=torch.float64)
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    torch.testing.assert_close(loss, (a - e)[:, 4:].square().mean(), rtol=1e-12, atol=0)
    zeros = flow_matching_loss(oracle, a, torch.Generator().manual_seed(3), rtc_max_delay=4, rtc_delay_dist="exp",
                               rtc_delays=torch.zeros(256, dtype=torch.int64))
    assert torch.equal(zeros, flow_matching_loss(oracle, a, torch.Generator().manual_seed(3), rtc_max_delay=4,
                                                 rtc_delay_dist="exp"))
    for bad, words in ((torch.full((256,), 5), r"^rtc_delays: expected integers \[256\] in 0\.\.4 \(committed rows per "
                                               r"chunk; rtc_max_delay=4\), got torch.int64 \[256\] in 5\.\.5$"),
                       (torch.zeros(256), r"got torch.float32 \[256\]$"),
                       (torch.zeros(3, dtype=torch.int64), r"got torch.int64 \[3\] in 0\.\.0$")):
        with pytest.raises(ValueError, match=words):
            flow_matching_loss(oracle, a, rtc_max_delay=4, rtc_delays=bad)


def test_the_policy_trains_given_delays_and_refuses_bad_ones_in_one_line():
    policy = tiny(rtc_max_delay=2).train()
    batch = {"state": torch.randn(8, 6), "actions": torch.randn(8, H, D)}
    loss = lambda **kw: float(policy.compute_loss({**batch, **kw}, torch.Generator().manual_seed(0)).loss.detach())  # noqa: E731
    assert loss(rtc_delays=torch.zeros(8, dtype=torch.int64)) == loss()
    assert loss(rtc_delays=torch.full((8,), 2)) != loss()
    for value, words in ((torch.full((8,), 3), r"got torch.int64 \[8\] in 3\.\.3$"),
                         (torch.ones(8), r"got torch.float32 \[8\]$"), ([1] * 8, "got list$")):
        with pytest.raises(ValueError, match=r"^batch\['rtc_delays'\]: expected integers \[8\] in 0\.\.2 "
                                             r"\(committed rows per chunk; rtc_max_delay=2\), " + words):
            loss(rtc_delays=value)
    with pytest.raises(ValueError, match=r"rtc_max_delay=0, so training-time RTC is off\), got torch.int64"):
        tiny().train().compute_loss({**batch, "rtc_delays": torch.ones(8, dtype=torch.int64)})


def test_balanced_rows_weight_each_row_by_the_inverse_share_of_chunks_that_train_it():
    """Row j is in the loss when d ≤ j: weights 1/P(d ≤ j) (uniform on 0..4: 5, 2.5, 5/3, 1.25, then 1) make
    each row's expected weight over the delays the plain loss's, 1/(H·D) per entry."""
    from action_decoder.flows.rtc_trained import row_weights

    w = row_weights(4, H, "uniform")
    torch.testing.assert_close(w, torch.tensor([5, 2.5, 5 / 3, 1.25, 1, 1, 1, 1], dtype=torch.float64))
    torch.testing.assert_close(row_weights(4, H, "exp")[0], 1 / delay_probs(4, "exp")[0])
    a = torch.randn(4096, H, D, dtype=torch.float64)
    oracle = lambda x, t: torch.zeros_like(x)                                # noqa: E731
    loss = flow_matching_loss(oracle, a, torch.Generator().manual_seed(3), rtc_max_delay=4, rtc_balance_rows=True)
    g = torch.Generator().manual_seed(3)
    torch.rand(4096, generator=g, dtype=torch.float64)
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    live = ~prefix_mask(sample_delays(4096, 4, g), H)
    sq = (a - e).square()
    want = (sq * (live * w)[..., None]).mean((1, 2)).mean()
    torch.testing.assert_close(loss, want, rtol=1e-12, atol=0)
    # In expectation over the delays, every row weighs as in the plain loss.
    torch.testing.assert_close((live * w).mean(0), torch.ones(H, dtype=torch.float64), rtol=0, atol=0.12)
    # MeanFlow: the adaptive weight reads the balanced error; without a prefix it is the plain loss.
    mf = dict(ratio_r_neq_t=0.0, adaptive_p=0.0, time_dist="uniform", rtc_max_delay=4)
    u = lambda x, t, r: torch.zeros_like(x)                                  # noqa: E731
    balanced = meanflow_loss(u, a, torch.Generator().manual_seed(3), rtc_balance_rows=True, **mf)
    g = torch.Generator().manual_seed(3)
    sample_meanflow_times(4096, 0.0, 0.4, 1.0, g, dtype=torch.float64, dist="uniform")
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    live = ~prefix_mask(sample_delays(4096, 4, g), H)
    torch.testing.assert_close(balanced, ((a - e).square() * (live * w)[..., None]).mean((1, 2)).mean(),
                               rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="rtc_balance_rows: expected true or false, got 'yes'"):
        DecoderConfig(decoder_type="mean_flow", rtc_max_delay=2, rtc_balance_rows="yes")


def test_prefix_noise_perturbs_only_the_prefix_fed_in_and_keeps_the_targets():
    """With rtc_prefix_noise σ the kept rows are fed a + σ·ε (ε drawn after the delays) at t = 1, the other rows
    the usual z_t, and the loss still regresses a − e on the other rows; σ = 0 draws nothing more."""
    B, a = 512, torch.randn(512, H, D, dtype=torch.float64)
    seen = {}

    def oracle(x, t):
        seen["x"], seen["t"] = x, t
        return torch.zeros_like(x)

    loss = flow_matching_loss(oracle, a, torch.Generator().manual_seed(5), rtc_max_delay=4, rtc_prefix_noise=0.3)
    g = torch.Generator().manual_seed(5)
    t = torch.rand(B, generator=g, dtype=torch.float64)
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    keep = prefix_mask(sample_delays(B, 4, g), H)
    eps = torch.randn(a.shape, generator=g, dtype=torch.float64)
    z = (1 - t[:, None, None]) * e + t[:, None, None] * a
    want_x = torch.where(keep[..., None], a + 0.3 * eps, z)
    torch.testing.assert_close(seen["x"], want_x, rtol=1e-12, atol=0)
    torch.testing.assert_close(seen["t"], torch.where(keep, 1.0, t[:, None].expand(B, H)), rtol=0, atol=0)
    want = torch.stack([(a - e)[b][~keep[b]].square().mean() for b in range(B)]).mean()
    torch.testing.assert_close(loss, want, rtol=1e-12, atol=0)            # targets: the clean actions
    assert 0.28 < (seen["x"] - a)[keep].std() < 0.32
    plain = flow_matching_loss(oracle, a, torch.Generator().manual_seed(5), rtc_max_delay=4)
    torch.testing.assert_close(seen["x"][keep], a[keep], rtol=0, atol=0)
    torch.testing.assert_close(plain, want, rtol=1e-12, atol=0)
    # MeanFlow: the same prefix input in every call.
    u_seen = []
    u = lambda x, t, r: (u_seen.append(x), torch.zeros_like(x))[1]        # noqa: E731
    meanflow_loss(u, a, torch.Generator().manual_seed(5), ratio_r_neq_t=0.0, adaptive_p=0.0, time_dist="uniform",
                  rtc_max_delay=4, rtc_prefix_noise=0.3)
    g = torch.Generator().manual_seed(5)
    sample_meanflow_times(B, 0.0, 0.4, 1.0, g, dtype=torch.float64, dist="uniform")
    torch.randn(a.shape, generator=g, dtype=torch.float64)
    keep = prefix_mask(sample_delays(B, 4, g), H)
    eps = torch.randn(a.shape, generator=g, dtype=torch.float64)
    torch.testing.assert_close(u_seen[0][keep], (a + 0.3 * eps)[keep], rtol=1e-12, atol=0)
    for bad in (-0.1, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match=r"rtc_prefix_noise: expected a non-negative finite std in normalised "
                                             rf"action units, got {bad!r}"):
            flow_matching_loss(oracle, a, rtc_max_delay=2, rtc_prefix_noise=bad)
    with pytest.raises(ValueError, match="rtc_prefix_noise: expected a non-negative finite number, got -1"):
        DecoderConfig(decoder_type="flow_matching", rtc_max_delay=2, rtc_prefix_noise=-1)


@pytest.mark.parametrize("dudt", ["jvp", "finite_difference"])
def test_meanflow_loss_holds_the_prefix_fixed_along_the_tangent(dudt):
    """u(x, t, r) = x[:, 0] + t[:, 0] broadcast over the chunk: with row 0 in the prefix (x = a, t = 1
    fixed) du/dt = 0 and every target is v; with no prefix du/dt = v₀ + 1. Closed form from the same draws."""
    B, a = 48, torch.randn(48, H, D, dtype=torch.float64)

    def u(x, t, r):
        assert t.shape == r.shape == (x.shape[0], H) and bool(((t == 1) <= (r == 1)).all())   # prefix: t = r = 1
        return (x[:, :1] + t[:, :1, None]).expand_as(x)

    kw = dict(ratio_r_neq_t=1.0, adaptive_p=0.0, time_dist="uniform", dudt=dudt, rtc_max_delay=2)
    loss = meanflow_loss(u, a, torch.Generator().manual_seed(5), fd_one_call=False, **kw)
    g = torch.Generator().manual_seed(5)
    t, r, _ = sample_meanflow_times(B, 1.0, 0.4, 1.0, g, dtype=torch.float64, dist="uniform")
    e = torch.randn(a.shape, generator=g, dtype=torch.float64)
    d = sample_delays(B, 2, g)
    keep = prefix_mask(d, H)
    v = a - e
    z = (1 - t[:, None, None]) * e + t[:, None, None] * a
    x0 = torch.where(keep[:, :1, None], a[:, :1], z[:, :1])
    out = (x0 + torch.where(keep[:, :1], 1.0, t[:, None])[..., None]).expand_as(a)
    dudt_ = torch.where(keep[:, :1, None], torch.zeros_like(v[:, :1]), v[:, :1] + 1).expand_as(a)
    target = v - (t - r)[:, None, None] * dudt_
    live = ~keep
    want = torch.stack([(out - target)[b][live[b]].square().mean() for b in range(B)]).mean()
    tol = 1e-12 if dudt == "jvp" else 1e-6
    torch.testing.assert_close(loss, want, rtol=tol, atol=0)
    assert set(d.tolist()) == {0, 1, 2}


def test_meanflow_loss_with_a_prefix_trains_every_target_and_tangent():
    policy = tiny("mean_flow", rtc_max_delay=3).train()
    batch = {"state": torch.randn(6, 6), "actions": torch.randn(6, H, D)}
    for target, tangent in [("identity", "sampled"), ("identity", "boundary"), ("split", "sampled")]:
        for dudt in ("jvp", "finite_difference"):
            loss = meanflow_loss(policy._flow_net, policy.normalizers["actions"].normalize(batch["actions"]),
                                 torch.Generator().manual_seed(0), policy._prepare(batch), ratio_r_neq_t=0.5,
                                 dudt=dudt, target=target, tangent=tangent, rtc_max_delay=3)
            assert torch.isfinite(loss)
            loss.backward()
    with pytest.raises(ValueError, match=r"rtc_max_delay: expected an integer number of control steps in \[0, 7\]"):
        flow_matching_loss(lambda x, t: x, torch.zeros(2, H, D), rtc_max_delay=H)


def test_meanflow_jvp_through_the_expert_holds_the_prefix_fixed():
    """The policy's MeanFlow head (clean-chunk output, per-token times through the expert's earliest-time
    token and offsets) with a clean prefix: its JVP along (v, 1, 0), as the loss takes it, equals a central
    difference of the network called directly on (clean prefix at t = r = 1 | the shifted live rows)."""
    policy = tiny("mean_flow", rtc_max_delay=3, flow_prediction="sample").double()
    B = 4
    cond = {"state": torch.randn(B, 6, dtype=torch.float64), "ctrl_freq": None, "prefix": None}
    keep = prefix_mask(torch.tensor([0, 1, 2, 3]), H)                      # one row per delay
    a, e, v = (torch.randn(B, H, D, dtype=torch.float64) for _ in range(3))
    t = torch.tensor([0.2, 0.0, 0.5, 0.1], dtype=torch.float64)
    r = torch.tensor([0.7, 1.0, 0.5, 0.9], dtype=torch.float64)
    z = (1 - t[:, None, None]) * e + t[:, None, None] * a
    wrapped = with_clean_prefix(policy._flow_net)
    u, dudt = torch.func.jvp(lambda x, tt, rr: wrapped(x, tt, rr, rtc_keep=keep, rtc_clean=a, **cond),
                             (z, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))

    def direct(x, tt):                                                      # the prefix written in by hand
        x = torch.where(keep[..., None], a, x)
        return policy._flow_net(x, torch.where(keep, 1.0, tt[:, None].expand(B, H)),
                                torch.where(keep, 1.0, r[:, None].expand(B, H)), **cond)

    h = 1e-6
    torch.testing.assert_close(u, direct(z, t), rtol=0, atol=1e-12)
    fd = (direct(z + h * v, t + h) - direct(z - h * v, t - h)) / (2 * h)
    live = ~keep
    torch.testing.assert_close(dudt[live], fd[live], rtol=1e-5, atol=1e-6)
    # The row without a prefix is the per-sample path (times [B]) exactly.
    torch.testing.assert_close(u[0], policy._flow_net(z[:1], t[:1], r[:1], **{**cond, "state": cond["state"][:1]})[0],
                               rtol=0, atol=1e-12)


@pytest.mark.parametrize("decoder,steps", [("flow_matching", 2), ("mean_flow", 1)])
def test_training_and_sampling_feed_the_network_the_same_prefix(decoder, steps):
    """What the network sees on the committed rows: the normalised clean actions at t = r = 1, in training
    (the chunk's own first d actions) and in sampling (prev_chunk's first d), and on the other rows the
    sampler's times; MeanFlow's 1-step chunk runs at (t, r) = (0, 1) on the live rows."""
    policy = tiny(decoder, rtc_max_delay=3)
    seen = []
    forward = policy.model.forward
    policy.model.forward = lambda x, t, r, *a, **k: (seen.append((x.detach(), t.detach(), r.detach())),
                                                     forward(x, t, r, *a, **k))[1]
    state, prev = torch.randn(3, 6), torch.rand(3, H - 2, D) * 2 - 1
    policy.predict_action_chunk({"state": state}, steps=steps, prev_chunk=prev, delay=2, rtc_mode="trained",
                                generator=torch.Generator().manual_seed(0))
    assert len(seen) == steps
    clean = policy.normalizers["actions"].normalize(prev[:, :2])
    for k, (x, t, r) in enumerate(seen):
        torch.testing.assert_close(x[:, :2], clean)
        assert bool((t[:, :2] == 1).all() and (r[:, :2] == 1).all()) and bool((t[:, 2:] == k / steps).all())
        if decoder == "mean_flow":
            assert bool((r[:, 2:] == (k + 1) / steps).all())
    seen.clear()
    actions = torch.rand(64, H, D) * 2 - 1
    policy.train().compute_loss({"state": torch.randn(64, 6), "actions": actions}, torch.Generator().manual_seed(1))
    normed = policy.normalizers["actions"].normalize(actions)
    delays = set()
    for x, t, r in seen:
        if t.dim() == 1 or x.shape[0] != 64:
            continue
        keep = t == 1
        d = keep.sum(1)                                                     # [B] the prefix is the first d rows
        assert torch.equal(keep, prefix_mask(d, H)) and bool((r[keep] == 1).all())
        torch.testing.assert_close(x[keep], normed[keep])
        delays |= set(d.tolist())
    assert delays == {0, 1, 2, 3}


# ---------------------------------------------------------------------------- sampling
@pytest.mark.parametrize("which", ["ode", "meanflow"])
def test_prefix_samplers_feed_the_clean_prefix_on_every_step_and_keep_it(which):
    noise = torch.randn(5, H, D, dtype=torch.float64)
    prefix = torch.randn(5, 2, D, dtype=torch.float64)
    calls = []

    def net(x, t, *r):
        calls.append(1)
        assert torch.equal(x[:, :2], prefix) and bool((t[:, :2] == 1).all()) and bool((t[:, 2:] < 1).all())
        return torch.sin(x) + t[..., None]

    steps = 3
    if which == "ode":
        out, plain = sample_ode_prefix(net, noise, prefix, steps), None
    else:
        out = sample_meanflow_prefix(net, noise, prefix, steps)
    assert torch.equal(out[:, :2], prefix) and len(calls) == steps
    # No prefix: the plain sampler exactly.
    empty = prefix[:, :0]
    f = lambda x, t, *r: torch.sin(x) + (t[..., None] if t.dim() == 2 else t[:, None, None])    # noqa: E731
    plain = sample_ode(f, noise, steps) if which == "ode" else sample_meanflow(f, noise, steps)
    got = sample_ode_prefix(f, noise, empty, steps) if which == "ode" else sample_meanflow_prefix(f, noise, empty, steps)
    torch.testing.assert_close(got, plain, rtol=0, atol=1e-15)


def test_prefix_step_times_are_built_once_and_rebuilt_if_a_callable_edits_them():
    from action_decoder.flows.rtc_trained import prefix_steps

    st = prefix_steps(3, 2, H, 2, "cpu", torch.float32)
    assert prefix_steps(3, 2, H, 2, "cpu", torch.float32) is st                     # a chunk builds no times
    want = torch.tensor([0.0, 1 / 3, 2 / 3])
    for k, (t, r) in enumerate(zip(st.starts, st.ends)):
        assert t.shape == r.shape == (2, H) and bool((t[:, :2] == 1).all() and (r[:, :2] == 1).all())
        torch.testing.assert_close(t[:, 2:], want[k].expand(2, H - 2))
        torch.testing.assert_close(r[:, 2:], (want[k] + 1 / 3).expand(2, H - 2))
    assert st.live.flatten().tolist() == [0.0] * 2 + [1.0] * (H - 2)

    def rude(x, t):
        t.add_(0.5)                                                             # writes into its times
        return torch.zeros_like(x)

    sample_ode_prefix(rude, torch.zeros(2, H, D), torch.zeros(2, 2, D), 3)
    fresh = prefix_steps(3, 2, H, 2, "cpu", torch.float32)
    assert fresh is not st and float(fresh.starts[0][0, 2]) == 0.0


@pytest.mark.parametrize("decoder,steps", [("flow_matching", 10), ("mean_flow", 1), ("mean_flow", 2)])
def test_trained_mode_keeps_the_prefix_exactly_with_the_plain_chunks_network_calls(decoder, steps):
    policy = tiny(decoder, rtc_max_delay=3)
    calls = []
    forward = policy.model.forward
    policy.model.forward = lambda *a, **k: (calls.append(1), forward(*a, **k))[1]
    batch, prev = {"state": torch.randn(3, 6)}, torch.randn(3, H - 2, D)
    gen = lambda: torch.Generator().manual_seed(0)                          # noqa: E731
    plain = policy.predict_action_chunk(batch, steps=steps, generator=gen())
    n_plain, calls[:] = len(calls), []
    out = policy.predict_action_chunk(batch, steps=steps, generator=gen(), prev_chunk=prev, delay=3)
    assert len(calls) == n_plain == steps
    assert torch.equal(out[:, :3], prev[:, :3]) and not torch.allclose(out[:, 3:], plain[:, 3:])
    # rtc_mode=None on this checkpoint is trained; delay 0 is the plain chunk.
    assert policy.resolve_rtc_mode(None, 3) == "trained" and policy.resolve_rtc_mode(None, 4) == "guided"
    same = policy.predict_action_chunk(batch, steps=steps, generator=gen(), prev_chunk=prev, delay=0)
    assert torch.equal(same, plain)


@pytest.mark.parametrize("kwargs,words", [
    ({"decoder": "flow_matching", "rtc_mode": "trained"}, ["rtc_mode", "'trained' needs", "--rtc-max-delay",
                                                           "rtc_max_delay=0"]),
    ({"decoder": "flow_matching", "rtc_mode": "always"}, ["rtc_mode", "expected one of", "'always'"]),
    ({"decoder": "mean_flow", "rtc_mode": "trained", "max_delay": 1}, ["delay", "2 exceeds rtc_max_delay=1"]),
    ({"decoder": "flow_matching", "rtc_mode": "trained", "max_delay": 2, "sampler": "sde"},
     ["rtc_mode", "'trained' feeds", "sampler='sde'"]),
])
def test_bad_rtc_modes_give_one_line(kwargs, words):
    policy = tiny(kwargs["decoder"], rtc_max_delay=kwargs.get("max_delay", 0))
    with pytest.raises(ValueError) as err:
        policy.predict_action_chunk({"state": torch.zeros(2, 6)}, prev_chunk=torch.zeros(2, 5, D), delay=2,
                                    rtc_mode=kwargs["rtc_mode"], sampler=kwargs.get("sampler"))
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_guided_one_step_meanflow_warns_once_that_it_is_an_output_blend():
    policy = tiny("mean_flow", num_inference_timesteps=1)
    batch, prev = {"state": torch.zeros(2, 6)}, torch.zeros(2, 5, D)
    with pytest.warns(UserWarning, match=r"output blend \(1 − W\)·x̂ \+ W·prev_chunk"):
        policy.predict_action_chunk(batch, prev_chunk=prev, delay=2)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy.predict_action_chunk(batch, prev_chunk=prev, delay=2)       # once
        policy.predict_action_chunk(batch, prev_chunk=prev, delay=2, steps=2)


@pytest.mark.parametrize("mode", ["guided", "trained"])
def test_rtc_covers_every_row_eval_executes_beyond_config_n_action_steps(mode):
    """eval --n-action-steps 3 on a checkpoint with n_action_steps = 1: prev_chunks = old[3:] (L = 5), d = 1,
    executed rows 1..3. Guided (execution horizon, weights 1, 1-step MeanFlow) lands exactly on the previous
    chunk over rows 0..3 and leaves row 4 free; before, rows ≥ d + 1 = 2 were executed unguided."""
    import numpy as np

    from action_decoder.evaluate import make_policy_fn

    policy = tiny("mean_flow", n_action_steps=1, num_inference_timesteps=1, rtc_schedule="ones",
                  rtc_horizon="execution", rtc_max_delay=2 if mode == "trained" else 0,
                  clip_actions=False)       # the previous chunk is N(0, 1), beyond the statistics' range
    fn = make_policy_fn(policy, 1, None, None, torch.Generator().manual_seed(0), rtc_mode=mode)
    prev = np.random.default_rng(0).normal(size=(2, H - 3, D)).astype(np.float32)
    with pytest.warns(UserWarning, match="output blend") if mode == "guided" else _nothing():
        out = fn(np.zeros((2, 6), np.float32), np.zeros(2, np.int64), prev_chunks=prev, delay=1)
    np.testing.assert_array_equal(out[:, :1], prev[:, :1])
    if mode == "guided":
        np.testing.assert_allclose(out[:, :4], prev[:, :4], atol=1e-5)       # every executed row
        assert np.abs(out[:, 4] - prev[:, 4]).max() > 1e-3                    # the first row past them: free
        explicit = policy.predict_action_chunk({"state": torch.zeros(2, 6)}, prev_chunk=torch.from_numpy(prev),
                                               delay=1, n_action_steps=1, generator=torch.Generator().manual_seed(0))
        assert (explicit[:, 2] - torch.from_numpy(prev[:, 2])).abs().max() > 1e-3     # s = 1: row 2 free


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *a):
        return False


# ---------------------------------------------------------------------------- config and CLI
def test_config_saves_rtc_delay_dist_and_format_7_reads_uniform(tmp_path):
    cfg = DecoderConfig(decoder_type="flow_matching", rtc_max_delay=4, rtc_delay_dist="exp")
    cfg.to_json(tmp_path / "c.json")
    saved = json.loads((tmp_path / "c.json").read_text())
    assert saved["rtc_delay_dist"] == "exp" and DecoderConfig.from_json(tmp_path / "c.json").rtc_delay_dist == "exp"
    old = {k: v for k, v in saved.items() if k not in ("rtc_delay_dist", "rtc_balance_rows")}
    (tmp_path / "old.json").write_text(json.dumps({**old, "format_version": 7}))
    assert DecoderConfig.from_json(tmp_path / "old.json").rtc_delay_dist == "uniform"
    assert saved["rtc_balance_rows"] is False and DecoderConfig.from_json(tmp_path / "old.json").rtc_balance_rows is False
    assert saved["rtc_prefix_noise"] == 0.0
    old = {k: v for k, v in saved.items() if k != "rtc_prefix_noise"}
    (tmp_path / "old8.json").write_text(json.dumps({**old, "format_version": 8}))
    assert DecoderConfig.from_json(tmp_path / "old8.json").rtc_prefix_noise == 0.0
    with pytest.raises(ValueError, match=r"rtc_delay_dist: expected one of \['uniform', 'exp', 'half_zero'\], got 'zipf'"):
        DecoderConfig(decoder_type="mean_flow", rtc_max_delay=2, rtc_delay_dist="zipf")


def test_config_saves_rtc_max_delay_and_older_formats_read_zero(tmp_path):
    cfg = DecoderConfig(decoder_type="mean_flow", rtc_max_delay=4)
    cfg.to_json(tmp_path / "c.json")
    saved = json.loads((tmp_path / "c.json").read_text())
    assert CONFIG_FORMAT_VERSION == 10 and saved["rtc_max_delay"] == 4
    assert DecoderConfig.from_json(tmp_path / "c.json").rtc_max_delay == 4
    old = {k: v for k, v in saved.items() if k != "rtc_max_delay"}
    (tmp_path / "old.json").write_text(json.dumps({**old, "format_version": 6}))
    assert DecoderConfig.from_json(tmp_path / "old.json").rtc_max_delay == 0
    with pytest.raises(ValueError, match="rtc_max_delay: training-time real-time chunking needs a flow_matching or "
                                         "mean_flow decoder"):
        DecoderConfig(decoder_type="DDPM", rtc_max_delay=2)
    with pytest.raises(ValueError, match="rtc_max_delay: expected fewer control steps than action_chunk_size=16"):
        DecoderConfig(decoder_type="mean_flow", rtc_max_delay=16)
    with pytest.raises(ValueError, match="rtc_max_delay: expected a non-negative integer"):
        DecoderConfig(decoder_type="mean_flow", rtc_max_delay=1.5)


def test_train_rtc_max_delay_refuses_ddpm_in_one_line(capsys):
    from action_decoder import cli

    assert cli.main(["train", "--decoder", "DDPM", "--rtc-max-delay", "2", "--steps", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("action-decoder: error: --rtc-max-delay: training-time real-time "
                                              "chunking needs --decoder flow_matching or mean_flow")


def test_cli_round_trip_train_rtc_max_delay_then_eval_rtc_mode(tmp_path, monkeypatch, capsys):
    """train --rtc-max-delay 2 saves it in config.json; eval --rtc --rtc-mode trained|guided runs and records it."""
    from action_decoder import cli

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "run"
    assert cli.main(["train", "--task", "metaworld/reach", "--decoder", "mean_flow", "--rtc-max-delay", "2",
                     "--rtc-delay-dist", "exp", "--rtc-balance-rows", "--rtc-prefix-noise", "0.2",
                     "--steps", "2", "--demos", "1", "--batch-size", "8", "--hidden-size", "32", "--num-layers", "1",
                     "--eval-episodes", "0", "--no-progress", "--checkpoint-every", "2", "--log-every", "1",
                     "--output-dir", str(out)]) == 0
    ckpt = out / "final"
    saved = json.loads((ckpt / "config.json").read_text())
    assert saved["rtc_max_delay"] == 2 and saved["rtc_delay_dist"] == "exp" and saved["rtc_balance_rows"] is True
    assert saved["rtc_prefix_noise"] == 0.2
    args = ["eval", "--checkpoint", str(ckpt), "--episodes", "1", "--num-envs", "1", "--max-steps", "12",
            "--delay", "2", "--rtc"]
    for mode in ("trained", "guided"):
        assert cli.main(args + ["--rtc-mode", mode]) == 0
        summary = json.loads((ckpt / f"eval_ode_k1_n4_d2_rtc-{mode}_seed0_e1_t12.json").read_text())
        assert summary["rtc"] is True and summary["rtc_mode"] == mode
    assert cli.main(args) == 0                                               # default: trained on this checkpoint
    assert json.loads((ckpt / "eval_ode_k1_n4_d2_rtc_seed0_e1_t12.json").read_text())["rtc_mode"] == "trained"
    capsys.readouterr()
    assert cli.main(args[:-3] + ["--rtc-mode", "trained"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--rtc-mode: chooses how --rtc conditions" in err


# ---------------------------------------------------------------------------- the benchmark's measures
class _RoutePolicy:
    """A stand-in policy: with a previous chunk it continues it; without one it takes route +1."""

    config = DecoderConfig(decoder_type="flow_matching", state_dim=4, action_dim=4)

    def sample(self, batch, steps=None, generator=None, prev_chunk=None, delay=0, rtc_mode=None):
        from types import SimpleNamespace

        from benchmarks.multimodal import routes
        if prev_chunk is None:
            return SimpleNamespace(actions=routes(batch["state"])[:, 0])
        pad = prev_chunk[:, -1:].expand(-1, 16 - prev_chunk.shape[1], -1)
        return SimpleNamespace(actions=torch.cat([prev_chunk, pad], 1))


def test_synthetic_route_consistency_counts_re_plans_that_keep_the_committed_route():
    from benchmarks.rtc_modes import run_synthetic

    fake = _RoutePolicy()
    rows = run_synthetic({"flow_matching": {"plain": fake, "rtc": fake}}, states=64, samples=2, seed=0)
    by = {(r["delay"], r["arm"]): r for r in rows}
    assert by[(2, "trained")]["route_consistency"] == 1.0 and by[(2, "trained")]["off_route"] == 0.0
    assert 0.3 < by[(2, "naive")]["route_consistency"] < 0.7          # route +1 against a 50/50 committed route
    assert by[(2, "trained")]["switch_jerk"] < by[(2, "naive")]["switch_jerk"]
    assert "mode_metrics" in by[(0, "naive")] and "mode_metrics" not in by[(2, "naive")]


def test_obstacle_episode_with_delay_runs_the_scripted_expert_to_the_goal_on_one_route():
    """The scripted expert (above) as the policy: every re-plan keeps the route, and the delayed
    loop executes the old chunk's actions while the new one is planned."""
    import numpy as np

    from action_decoder.envs.obstacle_routes import SPEED, expert_action
    from benchmarks.rtc_modes import obstacle_episode

    class Expert:
        config = DecoderConfig(decoder_type="flow_matching", state_dim=6, action_dim=2)

        def sample(self, batch, **kw):
            from types import SimpleNamespace
            obs, out = batch["state"][0].numpy().copy(), []
            for _ in range(16):
                a = expert_action(obs, 1)
                out.append(a)
                obs[:2] = obs[:2] + SPEED * np.clip(a, -1, 1)
            return SimpleNamespace(actions=torch.from_numpy(np.stack(out))[None])

    for d in (0, 2, 4):
        res = obstacle_episode(Expert(), 1, "trained", d, layout=1_000_000, noise_seed=0)
        assert res["success"] and not res["collided"] and res["checks"] and all(res["checks"])


def test_benchmark_cost_part_times_plain_and_trained_chunks_side_by_side(tmp_path):
    from benchmarks.rtc import main

    out = tmp_path / "cost.json"
    pytest.importorskip("onnxruntime")
    from benchmarks.rtc_modes import cost_section

    main(["--part", "cost", "--settings", "mean_flow:1", "flow_matching:10", "--latency-reps", "2",
          "--cost-runtimes", "eager", "onnxruntime", "--cost-json", str(out)])
    rows = json.loads(out.read_text())
    assert [(r["decoder"], r["steps"], r["runtime"]) for r in rows] == [
        ("mean_flow", 1, "eager"), ("mean_flow", 1, "onnxruntime"),
        ("flow_matching", 10, "eager"), ("flow_matching", 10, "onnxruntime")]
    assert all(r["plain_ms"] > 0 and r["trained_ms"] > 0 and r["delay"] == 4 and r["clock"] == "CPU time"
               for r in rows)
    table = [line for line in cost_section(rows) if line.startswith("| FM K=10") or line.startswith("| MF K=1")]
    assert [line.split(" | ")[2] for line in table] == ["eager", "eager", "onnxruntime", "onnxruntime"]


def test_benchmark_names_the_rtc_weights_by_their_delay_distribution():
    from benchmarks.rtc_modes import _dists, rtc_suffix

    assert rtc_suffix(0, "exp") == "" and rtc_suffix(4, "uniform") == "-rtc4" and rtc_suffix(4, "exp") == "-rtc4exp"
    rows = [{"arm": "trained", "rtc_delay_dist": "exp"}, {"arm": "trained"}, {"arm": "naive"}]
    assert _dists(rows) == "delays drawn exp and uniform on 0..4" and _dists(rows[:1]) == "delays drawn exp on 0..4"


def test_benchmark_names_the_multimodal_weights_by_their_budget():
    """Weights of another training budget or network size live in their own directory, never reused."""
    from benchmarks.multimodal import Budget
    from benchmarks.rtc_modes import budget_suffix

    assert budget_suffix(Budget()) == "" and budget_suffix(Budget(steps=5000)) == "-5000steps"
    assert budget_suffix(Budget(hidden=96, layers=3)) == "-h96x3"
    assert budget_suffix(Budget(steps=5000, layers=3)) == "-5000steps-h64x3"
    assert budget_suffix(Budget(recipe={"target": "split", "one_step_share": 0.25})) == \
        "-one_step_share0.25-targetsplit"


def test_benchmark_mm_recipe_reaches_the_trained_weights_and_refuses_bad_keys_in_one_line(tmp_path, monkeypatch):
    """`--mm-recipe KEY=VALUE` is the multimodal benchmark's `--recipe`: parsed alike, handed to training."""
    import benchmarks.multimodal as mm
    from benchmarks.rtc import main

    assert mm.parse_recipe(["one_step_share=0.25", "target=split"]) == {"one_step_share": 0.25, "target": "split"}
    for bad, match in ((["ratio"], "--mm-recipe: expected KEY=VALUE"), (["nope=1"], "--mm-recipe: expected KEY=VALUE"),
                       (["one_step_share=a"], "--mm-recipe: expected a number for one_step_share, got 'a'")):
        with pytest.raises(ValueError, match=match):
            main(["--part", "multimodal", "--multimodal", "synthetic", "--mm-recipe", *bad, "--runs", str(tmp_path)])
    seen = []

    def fake_train(decoder, draw, state_dim, action_dim, b, seed):
        seen.append(dict(b.recipe))
        raise SystemExit(0)

    monkeypatch.setattr(mm, "train", fake_train)
    with pytest.raises(SystemExit):
        main(["--part", "multimodal", "--multimodal", "synthetic", "--settings", "mean_flow:1", "--arms", "trained",
              "--mm-recipe", "one_step_share=0.25", "--rtc-meanflow-target", "split", "--runs", str(tmp_path),
              "--multimodal-json", str(tmp_path / "mm.json"), "--table", str(tmp_path / "rtc.md")])
    assert seen == [{"one_step_share": 0.25, "target": "split"}]


def test_benchmark_trains_again_for_another_budget_and_reuses_its_own(tmp_path, monkeypatch):
    """`trained_policies` trains once per (budget, network): the same budget loads, another one trains."""
    import benchmarks.multimodal as mm
    from benchmarks.rtc_modes import trained_policies

    calls = []

    def fake_train(decoder, draw, state_dim, action_dim, b, seed):
        calls.append((b.steps, b.hidden, b.layers))
        cfg = DecoderConfig(decoder_type=decoder, state_dim=state_dim, action_dim=action_dim, action_chunk_size=16,
                            hidden_size=b.hidden, num_hidden_layers=b.layers, num_attention_heads=4,
                            num_key_value_heads=2)
        return ActionDecoderPolicy(cfg).eval(), 0.0

    monkeypatch.setattr(mm, "train", fake_train)
    for budget in (mm.Budget(), mm.Budget(), mm.Budget(steps=5000), mm.Budget(hidden=32, layers=1)):
        pols = trained_policies("synthetic", "flow_matching", budget, 0, tmp_path, None, 4, 4, ["naive"])
        assert (pols["plain"].config.hidden_size, pols["plain"].config.num_hidden_layers) == (budget.hidden, budget.layers)
    assert calls == [(1500, 64, 2), (5000, 64, 2), (1500, 32, 1)]


def _mw_row(task, arm, delay, successes, train_steps=None, train_seed=None, episodes=50):
    r = {"task": task, "decoder": "mean_flow", "steps": 1, "delay": delay, "arm": arm, "episodes": episodes,
         "seed": 0, "successes": successes, "success_rate": successes / episodes, "boundary_jerk": 0.1,
         "boundaries": 10, "episode_boundary_jerk": [0.1, 0.1], "latency_plain_ms": 2.0, "latency_ms": 2.0,
         "date": "2026-11-27", "machine": "x86_64", "command": "c",
         "rtc_delay_dist": "exp" if arm == "trained" else None}
    r.update({} if train_steps is None else {"train_steps": train_steps})
    r.update({} if train_seed is None else {"train_seed": train_seed})
    return r


def test_meta_world_page_gives_one_table_per_training_budget_and_the_spread_over_training_seeds():
    from benchmarks.rtc_modes import metaworld_section, row_key, run_suffix, seed_spread

    assert run_suffix(1500, 0) == "" and run_suffix(5000, 2) == "-5000steps-seed2"
    old = _mw_row("push-v3", "naive", 0, 40)                      # a row from before budgets and seeds were recorded
    assert row_key(old) == row_key(_mw_row("push-v3", "naive", 0, 10, 1500, 0))
    assert row_key(old) != row_key(_mw_row("push-v3", "naive", 0, 10, 5000, 0))
    # two training seeds on two tasks: per seed 60 % and 40 % pooled over tasks -> SD 14.1
    seeds = [_mw_row("push-v3", "trained", 2, 40, 5000, 0), _mw_row("hammer-v3", "trained", 2, 20, 5000, 0),
             _mw_row("push-v3", "trained", 2, 30, 5000, 1), _mw_row("hammer-v3", "trained", 2, 10, 5000, 1)]
    assert seed_spread(seeds) == "14.1" and seed_spread(seeds[:3]) == "–" and seed_spread(seeds[:2]) == "–"
    page = "\n".join(metaworld_section([old, *seeds], ["metaworld/push", "metaworld/hammer"]))
    assert "### Trained 1500 steps" in page and "### Trained 5000 steps" in page
    assert "| MF K=1 | 2 | trained | 2 | 0, 1 | 50.0 | 14.1 |" in page
    assert "| MF K=1 | 0 | naive | 1 | 0 | 80.0 | – |" in page
    assert "the mean over 2 training seeds" in page and "| MF K=1 | trained | 30 | 70 |" in page


def test_meta_world_training_runs_the_cli_with_the_budget_and_seed_under_their_own_directory(tmp_path, monkeypatch):
    import subprocess

    from benchmarks.rtc_modes import train_metaworld

    calls = []
    monkeypatch.setattr(subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    out = train_metaworld("metaworld/push", "mean_flow", tmp_path, 4, "exp", False, 5000, 2)
    assert out == tmp_path / "push-mean_flow-rtc4expsplitos0.25-5000steps-seed2" / "final"    # the defaults
    cmd = calls[0]
    assert cmd[cmd.index("--steps") + 1] == "5000" and cmd[cmd.index("--seed") + 1] == "2"
    assert cmd[cmd.index("--rtc-max-delay") + 1] == "4" and cmd[cmd.index("--rtc-delay-dist") + 1] == "exp"
    assert cmd[cmd.index("--perturbed-prefixes") + 1] == "0"          # MeanFlow's default: none
    assert cmd[cmd.index("--meanflow-target") + 1] == "split" and cmd[cmd.index("--meanflow-one-step-share") + 1] == "0.25"
    assert "--resume" not in cmd
    # An interrupted run (checkpoints, no final weights) continues from its newest checkpoint.
    (out.parent / "checkpoints" / "step_0001000").mkdir(parents=True)
    train_metaworld("metaworld/push", "mean_flow", tmp_path, 4, "exp", False, 5000, 2)
    assert "--resume" in calls[-1] and [a for a in calls[-1] if a != "--resume"] == cmd
    assert train_metaworld("metaworld/push", "mean_flow", tmp_path, 0) == tmp_path / "push-mean_flow" / "final"
    assert "--perturbed-prefixes" not in calls[-1]
    # Weights trained on the demonstrations alone live apart from the default's.
    out = train_metaworld("metaworld/push", "flow_matching", tmp_path, 4, "exp", False, 5000, 0, None, 0)
    assert out.parent.name == "push-flow_matching-rtc4exp-5000steps"
    assert calls[-1][calls[-1].index("--perturbed-prefixes") + 1] == "0"


def test_meta_world_split_target_weights_get_their_own_directory_command_and_rows(tmp_path, monkeypatch):
    import subprocess

    from benchmarks.rtc_modes import arm_label, arm_labels, metaworld_section, row_key, rtc_suffix, train_metaworld

    calls = []
    monkeypatch.setattr(subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    out = train_metaworld("metaworld/push", "mean_flow", tmp_path, 4, "exp", False, 5000, 0, "split")
    assert out == tmp_path / "push-mean_flow-rtc4expsplitos0.25-5000steps" / "final"
    assert calls[0][calls[0].index("--meanflow-target") + 1] == "split"
    # the plain weights and flow matching take no MeanFlow target
    assert train_metaworld("metaworld/push", "mean_flow", tmp_path, 0, "exp", False, 5000, 0, "split").parent.name \
        == "push-mean_flow-5000steps" and "--meanflow-target" not in calls[-1]
    assert train_metaworld("metaworld/push", "flow_matching", tmp_path, 4, "exp", False, 5000, 0, "split").parent.name \
        == "push-flow_matching-rtc4exppp3-5000steps" and "--meanflow-target" not in calls[-1]
    assert rtc_suffix(4, "exp", False, "identity") == "-rtc4exp" and rtc_suffix(0, "exp", False, "split") == ""
    assert rtc_suffix(4, "exp", False, "split", 0.25) == "-rtc4expsplitos0.25" and rtc_suffix(0, "exp", False, "split", 0.25) == ""
    assert train_metaworld("metaworld/push", "mean_flow", tmp_path, 4, "exp", False, 5000, 0, "identity").parent.name \
        == "push-mean_flow-rtc4exp-5000steps" and calls[-1][calls[-1].index("--meanflow-target") + 1] == "identity"
    identity = _mw_row("push-v3", "trained", 2, 40, 5000, 0)
    split = {**_mw_row("push-v3", "trained", 2, 10, 5000, 0), "rtc_meanflow_target": "split"}
    naive = _mw_row("push-v3", "naive", 2, 30, 5000, 0)
    assert row_key(identity) != row_key(split) and arm_label(split) == "trained, split target"
    assert arm_labels([split, identity, naive]) == ["naive", "trained", "trained, split target"]
    one_step = {**split, "rtc_meanflow_one_step_share": 0.25}
    assert arm_label(one_step) == "trained, split target, one-step rows 0.25" and row_key(one_step) != row_key(split)
    perturbed = {**one_step, "rtc_perturbed_prefixes": 3}
    assert arm_label(perturbed) == "trained, split target, one-step rows 0.25, perturbed prefixes 3"
    assert row_key(perturbed) != row_key(one_step) and rtc_suffix(4, "exp", False, "split", 0.25, 3) == "-rtc4expsplitos0.25pp3"
    page = "\n".join(metaworld_section([identity, split, naive], ["metaworld/push"]))
    assert "| MF K=1 | 2 | trained | 1 | 0 | 80.0 |" in page and "| MF K=1 | 2 | trained, split target | 1 | 0 | 20.0 |" in page
    assert "| MF K=1 | trained, split target | 20 |" in page and "interval-consistency" in page


def _prefix_policy(seed=0):
    torch.manual_seed(seed)
    cfg = DecoderConfig(decoder_type="mean_flow", state_dim=3, action_dim=2, action_chunk_size=16, n_action_steps=4,
                        hidden_size=32, num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1,
                        rtc_max_delay=4, flow_prediction="sample")
    return ActionDecoderPolicy(cfg).eval()


def test_prefix_fit_scores_the_executed_rows_of_the_prefix_fed_chunk_against_the_demonstration():
    from benchmarks.rtc_prefix_fit import NOISE_SEED, prefix_errors

    policy, state = _prefix_policy(), torch.randn(6, 3)
    noise = torch.randn(6, 16, 2, generator=torch.Generator().manual_seed(NOISE_SEED))
    own = policy.sample({"state": state}, steps=1, noise=noise).actions              # [6, 16, 2]
    errs = prefix_errors(policy, state, own, 1, [0, 2, 4])
    assert errs[0] == 0.0                                  # d = 0: the plain chunk from the same noise, exactly
    fed = policy.sample({"state": state}, steps=1, noise=noise, prev_chunk=own[:, :12], delay=4,
                        rtc_mode="trained").actions
    # a demonstration that is the prefix-fed chunk itself (its first 4 rows are own's, exactly) fits it at d = 4
    assert prefix_errors(policy, state, fed, 1, [4])[4] == 0.0
    assert errs[2] > 0 and errs[4] > 0                      # the prefix changes what an untrained network plans


def test_prefix_fit_page_gives_each_weight_and_seed_its_row_and_the_worst_delays_ratio():
    from benchmarks.rtc_prefix_fit import prefix_section, row_key

    def row(delay, err, target="identity", seed=0):
        return {"task": "stick-pull-v3", "decoder": "mean_flow", "steps": 1, "delay": delay, "train_steps": 5000,
                "train_seed": seed, "chunks": 100, "mean_abs_error": err, "rtc_delay_dist": "exp",
                "rtc_meanflow_target": target, "date": "2026-11-27", "machine": "x86_64", "command": "c"}

    rows = [row(0, 0.03), row(2, 0.12), row(4, 0.24), row(0, 0.03, "split"), row(2, 0.03, "split"),
            row(4, 0.03, "split")]
    page = "\n".join(prefix_section(rows))
    assert "| stick-pull-v3 | MF K=1 | exp delays, identity target | 5000 | 0 | 100 | 0.030 | 0.120 | 0.240 | 8.0× |" in page
    assert "| stick-pull-v3 | MF K=1 | exp delays, split target | 5000 | 0 | 100 | 0.030 | 0.030 | 0.030 | 1.0× |" in page
    assert row_key(rows[0]) != row_key(rows[3]) and row_key(rows[0]) != row_key(row(0, 0.03, seed=1))
    assert prefix_section([]) == []


def test_meanflow_trained_with_rtc_defaults_to_the_split_target_and_saves_it_resolved(tmp_path):
    assert DecoderConfig(decoder_type="mean_flow").meanflow_target == "identity"
    assert DecoderConfig(decoder_type="mean_flow", rtc_max_delay=4).meanflow_target == "split"
    assert DecoderConfig(decoder_type="flow_matching", rtc_max_delay=4).meanflow_target == "identity"
    assert DecoderConfig(decoder_type="mean_flow", rtc_max_delay=4, meanflow_target="identity").meanflow_target \
        == "identity"
    path = tmp_path / "config.json"
    DecoderConfig(decoder_type="mean_flow", rtc_max_delay=4).to_json(path)
    assert json.loads(path.read_text())["meanflow_target"] == "split"
    assert DecoderConfig.from_json(path).meanflow_target == "split"


def test_multimodal_rtc_weights_are_named_and_labelled_by_their_meanflow_target():
    from benchmarks.rtc_modes import multimodal_section, rtc_target

    assert rtc_target("mean_flow", 4) == "split" and rtc_target("mean_flow", 4, "identity") == "identity"
    assert rtc_target("mean_flow", 0, "split") == "identity" and rtc_target("flow_matching", 4, "split") == "identity"

    def row(arm, kept, target=None):
        return {"task": "synthetic", "decoder": "mean_flow", "steps": 1, "delay": 2, "arm": arm, "samples": 1024,
                "route_consistency": kept, "off_route": 0.0, "switch_jerk": 0.1, "train_steps": 5000,
                "rtc_delay_dist": "exp" if arm == "trained" else None, "rtc_meanflow_target": target,
                "date": "2026-11-27", "machine": "x86_64", "command": "c"}

    page = "\n".join(multimodal_section([row("naive", 0.4), row("trained", 0.87), row("trained", 0.63, "split")]))
    assert "| MF K=1 | 2 | trained | 87 % |" in page and "| MF K=1 | 2 | trained, split target | 63 % |" in page


def test_benchmark_prefix_part_writes_its_rows_and_its_page_section(tmp_path, monkeypatch):
    import benchmarks.rtc_prefix_fit as fit
    from benchmarks.rtc import main

    policy = _prefix_policy()
    policy.config.extra["train"] = {"demos": 2, "seed": 0, "demo_noise": 0.0}
    policy.save_pretrained(tmp_path / "w" / "final")
    asked = []
    monkeypatch.setattr(fit, "train_metaworld", lambda *a: asked.append(a) or tmp_path / "w" / "final")
    monkeypatch.setattr(fit, "demo_chunks", lambda task, demos, seed, noise, horizon: (torch.randn(5, 3),
                                                                                       torch.randn(5, horizon, 2)))
    out, page = tmp_path / "prefix.json", tmp_path / "rtc.md"
    main(["--part", "prefix", "--tasks", "metaworld/push", "--settings", "mean_flow:1", "--train-steps", "5000",
          "--rtc-delay-dist", "exp", "--runs", str(tmp_path), "--prefix-json", str(out), "--table", str(page),
          "--json", str(tmp_path / "h.json"), "--modes-json", str(tmp_path / "m.json"),
          "--multimodal-json", str(tmp_path / "mm.json")])
    rows = json.loads(out.read_text())
    assert [r["delay"] for r in rows] == [0, 1, 2, 4] and rows[0]["mean_abs_error"] > 0
    assert {r["rtc_meanflow_target"] for r in rows} == {"split"} and rows[0]["task"] == "push-v3"
    assert asked[0][:4] == ("metaworld/push", "mean_flow", tmp_path, 4) and asked[0][6] == 5000
    assert "## Trained RTC on its own training chunks" in page.read_text()
    assert "| push-v3 | MF K=1 | exp delays, split target | 5000 | 0 | 5 |" in page.read_text()


def test_meanflow_one_step_share_resolves_by_decoder_rtc_and_target_and_reaches_the_loss(tmp_path, monkeypatch):
    """None resolves to 0.25 only for MeanFlow trained with RTC and the split target; it is saved resolved,
    format-9 files read 0, bad values are one line, and the policy's loss draws that share of rows at (0, 1)."""
    import action_decoder.policy as policy_mod

    resolved = lambda **kw: DecoderConfig(**kw).meanflow_one_step_share                  # noqa: E731
    assert resolved(decoder_type="mean_flow", rtc_max_delay=4) == 0.25                    # split by default there
    assert resolved(decoder_type="mean_flow", rtc_max_delay=4, meanflow_target="identity") == 0.0
    assert resolved(decoder_type="mean_flow") == 0.0 and resolved(decoder_type="flow_matching", rtc_max_delay=4) == 0.0
    assert resolved(decoder_type="mean_flow", meanflow_one_step_share=0.5) == 0.5
    cfg = DecoderConfig(decoder_type="mean_flow", rtc_max_delay=4)
    cfg.to_json(tmp_path / "c.json")
    saved = json.loads((tmp_path / "c.json").read_text())
    assert saved["meanflow_one_step_share"] == 0.25 and saved["format_version"] == CONFIG_FORMAT_VERSION
    old = {k: v for k, v in saved.items() if k != "meanflow_one_step_share"}
    (tmp_path / "old9.json").write_text(json.dumps({**old, "format_version": 9}))
    assert DecoderConfig.from_json(tmp_path / "old9.json").meanflow_one_step_share == 0.0
    for bad in (1.5, -0.1, True, "a"):
        with pytest.raises(ValueError, match=r"^meanflow_one_step_share: expected a fraction of the r != t rows in "
                                             rf"\[0, 1\] \(None: the resolved default\), got {re.escape(repr(bad))}$"):
            DecoderConfig(decoder_type="mean_flow", meanflow_one_step_share=bad)
    seen = []
    real = policy_mod.meanflow_loss
    monkeypatch.setattr(policy_mod, "meanflow_loss", lambda *a, **kw: seen.append(kw["one_step_share"]) or real(*a, **kw))
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", state_dim=3, action_dim=2, action_chunk_size=8,
                                               hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
                                               num_key_value_heads=1, rtc_max_delay=2))
    loss = policy.compute_loss({"state": torch.randn(4, 3), "actions": torch.randn(4, 8, 2)},
                               torch.Generator().manual_seed(0)).loss
    assert seen == [0.25] and torch.isfinite(loss)
