"""Tests of the Action Expert: shapes, forward-mode AD, backends, masking, VLM caches."""

from __future__ import annotations

import math
from unittest import mock

import pytest
import torch
import torch.autograd.forward_ad as fwAD
from torch.nn.attention import SDPBackend, sdpa_kernel

from action_decoder.config import DecoderConfig
from action_decoder.expert import ActionExpert, Prefix, forward_ad_active
from action_decoder.expert.conditioning import vlm_layer_for
from action_decoder.expert.embeddings import TIME_PERIODS, sinusoidal_features

B, H, S, A, C = 3, 4, 5, 3, 6


def make_config(**kw) -> DecoderConfig:
    base = dict(state_dim=S, action_dim=A, hidden_size=32, num_hidden_layers=2,
                num_attention_heads=4, num_key_value_heads=2, context_dim=C, action_chunk_size=H,
                n_action_steps=H)
    base.update(kw)
    return DecoderConfig(**base)


def make_expert(seed: int = 0, dtype=torch.float32, **kw) -> ActionExpert:
    torch.manual_seed(seed)
    expert = ActionExpert(make_config(**kw)).to(dtype)
    # Give every layer (head included) weights large enough that every path shows in the output.
    with torch.no_grad():
        for p in expert.parameters():
            if p.dim() > 1:
                p.normal_(0.0, 0.3)
    return expert


def inputs(seed: int = 1, dtype=torch.float32, b: int = B, h: int = H):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(b, h, A, generator=g, dtype=dtype)
    t = torch.rand(b, generator=g, dtype=dtype)
    r = (t + 0.3 * torch.rand(b, generator=g, dtype=dtype)).clamp(max=1.0)
    state = torch.randn(b, S, generator=g, dtype=dtype)
    freq = torch.tensor([10.0, 30.0, 50.0][:b], dtype=dtype) if b <= 3 else None
    return x, t, r, state, freq


def context_inputs(seed: int = 2, dtype=torch.float32, b: int = B, length: int = 5):
    g = torch.Generator().manual_seed(seed)
    context = torch.randn(b, length, C, generator=g, dtype=dtype)
    mask = torch.ones(b, length, dtype=torch.bool)
    mask[0, 3:] = False
    mask[1, 1:] = False
    return context, mask


def tiny_llama(seed: int = 0):
    transformers = pytest.importorskip("transformers")
    torch.manual_seed(seed)
    cfg = transformers.LlamaConfig(hidden_size=32, num_hidden_layers=2, num_attention_heads=4,
                                   num_key_value_heads=2, vocab_size=50, intermediate_size=64)
    return transformers.LlamaForCausalLM(cfg).eval()


def llama_cache(b: int = B, length: int = 6):
    model = tiny_llama()
    ids = torch.randint(0, 50, (b, length), generator=torch.Generator().manual_seed(3))
    attention_mask = torch.ones(b, length, dtype=torch.long)
    attention_mask[0, :2] = 0  # left padding
    with torch.no_grad():
        out = model(input_ids=ids, attention_mask=attention_mask, use_cache=True)
    return out.past_key_values, attention_mask


VLM = dict(vlm_num_layers=2, vlm_head_dim=8, vlm_num_key_value_heads=2)


# ------------------------------------------------------------------ 1. shapes, dtype, gradients
def test_shape_dtype_and_gradients_reach_every_parameter():
    expert = make_expert(**VLM)
    x, t, r, state, freq = inputs()
    context, mask = context_inputs()
    cache, am = llama_cache()
    prefix = expert.build_prefix(context=context, context_mask=mask, vlm_key_values=cache,
                                 attention_mask=am)
    out = expert(x, t, r, state, freq, prefix=prefix)
    assert out.shape == (B, H, A) and out.dtype == torch.float32
    out.pow(2).mean().backward()
    for name, p in expert.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert expert(x.double(), t, r, state).dtype == torch.float64
    assert expert.to(torch.bfloat16)(x, t, r, state).dtype == torch.float32


def test_default_init_starts_small_and_ctrl_freq_default():
    torch.manual_seed(0)
    cfg = make_config()
    expert = ActionExpert(cfg)
    x, t, r, state, _ = inputs()
    out = expert(x, t, r, state)
    assert out.abs().max() < 1.0
    default = torch.full((B,), cfg.default_ctrl_freq)
    torch.testing.assert_close(out, expert(x, t, r, state, default), rtol=0, atol=0)
    assert not torch.allclose(out, expert(x, t, r, state, default * 3))


def test_time_features_vary_over_unit_interval():
    feats = sinusoidal_features(torch.tensor([0.0, 0.05, 0.5, 1.0]), 64, *TIME_PERIODS)
    cos = torch.nn.functional.cosine_similarity(feats[:, None], feats[None], dim=-1)
    assert cos[0, 1] < 0.9 and cos[0, 3] < 0.5 and cos[2, 3] < 0.5


def test_time_embedding_frequencies_are_built_once_and_stay_float32():
    """The cached frequencies give the same features as building them per call, bit for bit; they stay
    float32 on `.half()` / `.to(bfloat16)` and out of the state dict; float64 times get float64 ones."""
    from action_decoder.expert.embeddings import ScalarEmbedding

    emb = ScalarEmbedding(32, TIME_PERIODS)
    x = torch.rand(7)
    fresh = sinusoidal_features(x, 32, *TIME_PERIODS)                      # built on this call
    torch.testing.assert_close(emb.features(x), fresh, rtol=0, atol=0)
    assert "freqs" not in emb.state_dict()
    for dtype in (torch.float16, torch.bfloat16):
        moved = ScalarEmbedding(32, TIME_PERIODS).to(dtype)
        assert moved.freqs.dtype == torch.float32 and moved.mlp[0].weight.dtype == dtype
        torch.testing.assert_close(moved.features(x.to(dtype)), sinusoidal_features(x.to(dtype), 32, *TIME_PERIODS),
                                   rtol=0, atol=0)
    x64 = torch.rand(5, dtype=torch.float64)
    period = TIME_PERIODS[0] * (TIME_PERIODS[1] / TIME_PERIODS[0]) ** (torch.arange(16, dtype=torch.float64) / 15)
    angle = x64[:, None] * 2 * math.pi / period                           # independent float64 oracle
    torch.testing.assert_close(emb.double().features(x64), torch.cat([angle.sin(), angle.cos()], -1),
                               rtol=1e-12, atol=1e-12)


def test_rotary_table_is_the_per_call_table_and_longer_chunks_build_their_own():
    """The expert's stored rotary table gives the outputs of the table built per call, bit for bit, for its
    own length and for a longer chunk; it stays float32 under `.to(bfloat16)` and out of the state dict."""
    from action_decoder.expert.attention import rotary_cos_sin

    expert = make_expert()
    x, t, r, state, _ = inputs()
    assert not any(k.startswith("rotary") for k in expert.state_dict())
    cos, sin = rotary_cos_sin(expert.rotary.cos.shape[0], expert.head_dim, expert.config.rope_theta,
                              torch.device("cpu"), torch.float32)
    torch.testing.assert_close((expert.rotary.cos, expert.rotary.sin), (cos, sin), rtol=0, atol=0)
    for chunk in (x, torch.cat([x, x], 1)):              # a longer chunk than the config's: built per call
        want = expert(chunk, t, r, state)
        with mock.patch.object(expert.rotary, "table", lambda n, device, dtype:
                               rotary_cos_sin(n, expert.head_dim, expert.config.rope_theta, device, dtype)):
            torch.testing.assert_close(expert(chunk, t, r, state), want, rtol=0, atol=0)
    assert expert.to(torch.bfloat16).rotary.cos.dtype == torch.float32


# ------------------------------------------------------------------ 2. forward-mode AD
@pytest.mark.skipif(tuple(int(x) for x in torch.__version__.split(".")[:2]) < (2, 6),
                    reason="torch 2.5's SDPA runs under forward AD on CPU; the detection is then a safety net")
def test_sdpa_really_lacks_forward_ad_so_detection_matters():
    expert = make_expert()
    x, t, r, state, _ = inputs()
    expert.attn_implementation = "sdpa"
    with pytest.raises(NotImplementedError):
        torch.func.jvp(lambda x: expert(x, t, r, state), (x,), (torch.ones_like(x),))


def test_forward_ad_detection():
    x = torch.randn(3)
    assert not forward_ad_active(x)
    seen = []
    torch.func.jvp(lambda y: seen.append(forward_ad_active(y * 1)) or y, (x,), (x,))
    torch.func.grad(lambda y: torch.func.jvp(lambda z: seen.append(forward_ad_active(z)) or z.sum(),
                                             (y,), (y,))[1])(x)
    with fwAD.dual_level():
        seen.append(forward_ad_active(fwAD.make_dual(x, x)))
        assert not forward_ad_active(x)
    torch.func.jvp(torch.func.grad(lambda y: seen.append(forward_ad_active(y)) or y.sum()), (x,), (x,))
    torch.func.vmap(lambda y: seen.append(not forward_ad_active(y)) or y)(x[None])
    assert seen == [True] * 5


def test_forward_over_reverse_through_expert():
    """Hessian-vector products (jvp of a grad) hide the tangent inside the grad level."""
    expert = make_expert()
    x, t, r, state, _ = inputs()
    grad_x = torch.func.grad(lambda x: expert(x, t, r, state).pow(2).sum())
    tx = torch.randn_like(x)
    _, hvp = torch.func.jvp(grad_x, (x,), (tx,))
    eps = 1e-3
    fd = (grad_x(x + eps * tx) - grad_x(x - eps * tx)) / (2 * eps)
    torch.testing.assert_close(hvp, fd, rtol=1e-2, atol=1e-3)


def test_jvp_matches_finite_difference_and_eager_path():
    expert = make_expert(dtype=torch.float64)
    x, t, r, state, freq = inputs(dtype=torch.float64)
    context, mask = context_inputs(dtype=torch.float64)
    prefix = expert.build_prefix(context=context, context_mask=mask)
    tx, tt = torch.randn_like(x), torch.ones_like(t)
    f = lambda x, t: expert(x, t, r, state, freq, prefix)
    with torch.no_grad():
        out, jvp = torch.func.jvp(f, (x, t), (tx, tt))
        eps = 1e-7  # the time features are high-frequency: keep FD truncation error small
        fd = (f(x + eps * tx, t + eps * tt) - f(x - eps * tx, t - eps * tt)) / (2 * eps)
        torch.testing.assert_close(out, f(x, t), rtol=0, atol=1e-12)
        torch.testing.assert_close(jvp, fd, rtol=1e-5, atol=1e-6)
        expert.attn_implementation = "eager"
        out_e, jvp_e = torch.func.jvp(f, (x, t), (tx, tt))
    torch.testing.assert_close(out_e, out, rtol=0, atol=1e-12)
    torch.testing.assert_close(jvp_e, jvp, rtol=0, atol=1e-12)
    assert jvp.abs().max() > 1e-3


def test_autograd_forward_ad_matches_func_jvp():
    expert = make_expert(**VLM)
    x, t, r, state, freq = inputs()
    cache, am = llama_cache()
    prefix = expert.build_prefix(vlm_key_values=cache, attention_mask=am)
    tx, tt = torch.randn_like(x), torch.ones_like(t)
    with torch.no_grad():
        _, ref = torch.func.jvp(lambda x, t: expert(x, t, r, state, freq, prefix), (x, t), (tx, tt))
        with fwAD.dual_level():
            out = expert(fwAD.make_dual(x, tx), fwAD.make_dual(t, tt), r, state, freq, prefix)
            tangent = fwAD.unpack_dual(out).tangent
    torch.testing.assert_close(tangent, ref, rtol=1e-5, atol=1e-6)


def _meanflow_grads(expert, x, t, r, state, prefix_fn, primal_from_plain_forward=False):
    expert.zero_grad()
    prefix = prefix_fn()
    v = torch.randn_like(x)
    f = lambda z, t, r: expert(z, t, r, state, None, prefix)
    u, dudt = torch.func.jvp(f, (x, t, r), (v, torch.ones_like(t), torch.zeros_like(r)))
    target = (v - (t - r)[:, None, None] * dudt).detach()
    if primal_from_plain_forward:
        u = f(x, t, r)
    ((u - target) ** 2).mean().backward()
    return {n: p.grad.clone() for n, p in expert.named_parameters() if p.grad is not None}


def test_meanflow_loss_gradients_match_explicit_reference():
    expert = make_expert(dtype=torch.float64)  # float64: backends agree to rounding, so tolerances can be tight
    x, t, r, state, _ = inputs(dtype=torch.float64)
    context, mask = context_inputs(dtype=torch.float64)
    prefix_fn = lambda: expert.build_prefix(context=context, context_mask=mask)
    torch.manual_seed(5)
    auto = _meanflow_grads(expert, x, t, r, state, prefix_fn)
    expert.attn_implementation = "eager"
    torch.manual_seed(5)
    eager = _meanflow_grads(expert, x, t, r, state, prefix_fn)
    expert.attn_implementation = "auto"
    torch.manual_seed(5)  # u from the fast SDPA forward: same gradients, target is detached
    fast = _meanflow_grads(expert, x, t, r, state, prefix_fn, primal_from_plain_forward=True)
    assert auto.keys() == eager.keys() == fast.keys()
    assert len(auto) == len(list(expert.parameters()))
    for name in auto:
        torch.testing.assert_close(auto[name], eager[name], rtol=1e-10, atol=1e-12, msg=name)
        torch.testing.assert_close(fast[name], eager[name], rtol=1e-10, atol=1e-12, msg=name)


# ------------------------------------------------------------------ 3. backends agree
@pytest.mark.parametrize("masked", [False, True])
def test_sdpa_and_eager_agree(masked):
    expert = make_expert()
    x, t, r, state, freq = inputs()
    context, mask = context_inputs()
    prefix = expert.build_prefix(context=context, context_mask=mask if masked else None)
    assert prefix.all_valid is (not masked)
    outs = {}
    for impl in ("sdpa", "eager"):
        expert.attn_implementation = impl
        with torch.no_grad():
            outs[impl] = (expert(x, t, r, state, freq), expert(x, t, r, state, freq, prefix))
    for a, b in zip(outs["sdpa"], outs["eager"]):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
    with sdpa_kernel(SDPBackend.MATH), torch.no_grad():
        expert.attn_implementation = "sdpa"
        torch.testing.assert_close(expert(x, t, r, state, freq, prefix), outs["eager"][1],
                                   rtol=0, atol=1e-5)


def test_unknown_attn_implementation_rejected():
    with pytest.raises(ValueError, match="attn_implementation"):
        make_expert().attn_implementation = "flash"


# ------------------------------------------------------------------ 4. masked positions are inert
@pytest.mark.parametrize("impl", ["sdpa", "eager"])
def test_masked_context_and_cache_positions_do_not_influence_output(impl):
    expert = make_expert(**VLM)
    expert.attn_implementation = impl
    x, t, r, state, freq = inputs()
    context, mask = context_inputs()
    cache, am = llama_cache()
    kv = [(layer.keys.clone(), layer.values.clone()) for layer in cache.layers]
    garbage_ctx = torch.where(mask[..., None], context, torch.full_like(context, 1e4))
    garbage_ctx[1, -1] = float("nan")  # even non-finite garbage must not leak
    garbage_kv = [(torch.where(am[:, None, :, None].bool(), k, 1e4),
                   torch.where(am[:, None, :, None].bool(), v, -1e4)) for k, v in kv]
    garbage_kv[1][1][0, :, 0] = float("inf")
    with torch.no_grad():
        clean = expert(x, t, r, state, freq, expert.build_prefix(
            context=context, context_mask=mask, vlm_key_values=kv, attention_mask=am))
        dirty = expert(x, t, r, state, freq, expert.build_prefix(
            context=garbage_ctx, context_mask=mask, vlm_key_values=garbage_kv, attention_mask=am))
        moved = context.clone()
        moved[2, 0] += 1.0  # a valid position does matter
        valid = expert(x, t, r, state, freq, expert.build_prefix(
            context=moved, context_mask=mask, vlm_key_values=kv, attention_mask=am))
    assert torch.isfinite(dirty).all()
    torch.testing.assert_close(dirty, clean, rtol=0, atol=1e-6)
    assert (valid[2] - clean[2]).abs().max() > 1e-4
    torch.testing.assert_close(valid[:2], clean[:2], rtol=0, atol=1e-6)


def test_fully_masked_context_row_is_finite():
    expert = make_expert()
    x, t, r, state, freq = inputs()
    context, mask = context_inputs()
    mask[0] = False
    for impl in ("sdpa", "eager"):
        expert.attn_implementation = impl
        out = expert(x, t, r, state, freq, expert.build_prefix(context=context, context_mask=mask))
        assert torch.isfinite(out).all()
        with torch.no_grad():
            alone = expert(x[:1], t[:1], r[:1], state[:1], freq[:1])
        torch.testing.assert_close(out[:1], alone, rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------ 5. real transformers cache
def _snapshot(cache):
    return [(layer.keys.clone(), layer.values.clone()) for layer in cache.layers], cache.get_seq_length()


@pytest.mark.parametrize("layers", [2, 3])
def test_llama_cache_conditions_expert_and_is_never_mutated(layers):
    expert = make_expert(num_hidden_layers=layers, **VLM)
    x, t, r, state, freq = inputs()
    cache, am = llama_cache()
    before, seq_len = _snapshot(cache)
    prefix = expert.build_prefix(vlm_key_values=cache, attention_mask=am)
    assert isinstance(prefix, Prefix) and prefix.length == 6 and len(prefix.keys) == layers
    assert prefix.keys[0].shape == (B, 2, 6, 8)
    with torch.no_grad():
        outs = [expert(x, t, r, state, freq, prefix) for _ in range(3)]
        plain = expert(x, t, r, state, freq)
        from_tuple = expert(x, t, r, state, freq, expert.build_prefix(
            vlm_key_values=tuple((k, v) for k, v in before), attention_mask=am))
    torch.testing.assert_close(outs[0], outs[2], rtol=0, atol=0)
    assert (outs[0] - plain).abs().max() > 1e-3
    torch.testing.assert_close(from_tuple, outs[0], rtol=0, atol=0)
    for j in range(2):  # every VLM layer feeds some expert layer
        edited = [(k + (i == j), v) for i, (k, v) in enumerate(before)]
        with torch.no_grad():
            moved = expert(x, t, r, state, freq, expert.build_prefix(vlm_key_values=edited, attention_mask=am))
        assert (moved - outs[0]).abs().max() > 1e-4, f"VLM layer {j} unused"
    after, seq_len_after = _snapshot(cache)
    assert seq_len_after == seq_len == 6
    for (k0, v0), (k1, v1) in zip(before, after):
        assert torch.equal(k0, k1) and torch.equal(v0, v1)


def test_vlm_layer_mapping():
    assert [vlm_layer_for(i, 3, 2) for i in range(3)] == [0, 1, 1]
    assert [vlm_layer_for(i, 4, 4) for i in range(4)] == [0, 1, 2, 3]
    assert [vlm_layer_for(i, 3, 9) for i in range(3)] == [0, 4, 8]
    assert vlm_layer_for(0, 1, 5) == 4


def test_conditioning_errors_and_empty_prefix():
    expert = make_expert(context_dim=None)
    assert expert.build_prefix() is None
    with pytest.raises(ValueError, match="context_dim"):
        expert.build_prefix(context=torch.zeros(B, 2, C))
    with pytest.raises(ValueError, match="vlm_key_values"):
        expert.build_prefix(vlm_key_values=[(torch.zeros(B, 2, 3, 8),) * 2])
    expert = make_expert(**VLM)
    with pytest.raises(ValueError, match="expected 2 layers"):
        expert.build_prefix(vlm_key_values=[(torch.zeros(B, 2, 3, 8),) * 2])
    with pytest.raises(ValueError, match="attention_mask"):
        expert.build_prefix(vlm_key_values=[(torch.zeros(B, 2, 3, 8),) * 2] * 2,
                            attention_mask=torch.ones(B, 4))
    with pytest.raises(ValueError, match="context_mask"):
        expert.build_prefix(context=torch.zeros(B, 2, C), context_mask=torch.ones(B, 3))


# ------------------------------------------------------------------ 6. own-token attention
def test_state_reaches_every_action_token_and_the_time_tokens():
    expert = make_expert()
    x, t, r, state, freq = inputs()
    state.requires_grad_(True)
    hidden = {}
    expert.norm.register_forward_hook(lambda m, args, out: hidden.update(h=args[0]))
    out = expert(x, t, r, state, freq)
    for k in range(H):
        (g,) = torch.autograd.grad(out[:, k].sum(), state, retain_graph=True)
        assert g.abs().min() > 0, f"action token {k} does not see the state"
    for k in range(3):  # t, r, f tokens see the state (and each other) too
        (g,) = torch.autograd.grad(hidden["h"][:, k].sum(), state, retain_graph=True)
        assert g.abs().min() > 0, f"prefix token {k} does not see the state"
    x.requires_grad_(True)
    out = expert(x, t, r, state, freq)
    (g,) = torch.autograd.grad(out[:, 0].sum(), x)
    assert (g[:, -1].abs().sum(-1) > 0).all(), "action tokens must see each other"


@pytest.mark.parametrize("h,length", [(1, 1), (4, 2), (9, 7)])
def test_any_chunk_and_prefix_length(h, length):
    expert = make_expert()
    x, t, r, state, freq = inputs(h=h)
    context, mask = context_inputs(length=length)
    mask[:, 0] = True
    for impl in ("sdpa", "eager"):
        expert.attn_implementation = impl
        out = expert(x, t, r, state, freq, expert.build_prefix(context=context, context_mask=mask))
        assert out.shape == (B, h, A) and torch.isfinite(out).all()


# ------------------------------------------------------------------ 7. no cross-batch leakage
def test_batch_permutation_equivariance():
    expert = make_expert(**VLM)
    x, t, r, state, freq = inputs()
    context, mask = context_inputs()
    cache, am = llama_cache()
    kv = [(layer.keys, layer.values) for layer in cache.layers]
    perm = torch.tensor([2, 0, 1])
    with torch.no_grad():
        out = expert(x, t, r, state, freq, expert.build_prefix(
            context=context, context_mask=mask, vlm_key_values=kv, attention_mask=am))
        out_p = expert(x[perm], t[perm], r[perm], state[perm], freq[perm], expert.build_prefix(
            context=context[perm], context_mask=mask[perm],
            vlm_key_values=[(k[perm], v[perm]) for k, v in kv], attention_mask=am[perm]))
    # float32 kernels may sum in a batch-position-dependent order (~1e-6); mixing rows errs by ~1e-1.
    torch.testing.assert_close(out_p, out[perm], rtol=0, atol=1e-5)


def test_input_validation():
    expert = make_expert()
    x, t, r, state, _ = inputs()
    with pytest.raises(ValueError, match="x:"):
        expert(x[..., :2], t, r, state)
    with pytest.raises(ValueError, match="state:"):
        expert(x, t, r, state[:, :2])
    with pytest.raises(ValueError, match="t:"):
        expert(x, t[:2], r, state)
    scalar = expert(x, torch.tensor(0.3), 0.3, state)
    torch.testing.assert_close(scalar, expert(x, torch.full((B,), 0.3), torch.full((B,), 0.3), state))
