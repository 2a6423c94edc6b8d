"""torch.compile paths: the compiled sampler and the compiled network give eager's results.

The agreement test captures whole graphs with TorchDynamo and AOTAutograd ("aot_eager": the same
graphs inductor lowers, without building C kernels); one inductor run checks the kernels on the
smallest sampler (it compiles C code: tens of seconds)."""

import shutil

import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.compiled import compile_network, compile_sampler

TINY = {"hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2, "num_key_value_heads": 1,
        "action_chunk_size": 4, "state_dim": 5, "action_dim": 2}
NO_CC = shutil.which("gcc") is None and shutil.which("cc") is None


def test_compiled_sampler_and_training_step_match_eager():
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type="flow_matching", num_inference_timesteps=2,
                                               context_dim=3, **TINY)).eval()
    state, noise, ctx = torch.randn(2, 5), torch.randn(2, 4, 2), torch.randn(2, 1, 3)
    sample = compile_sampler(policy, backend="aot_eager")
    want = policy.predict_action_chunk({"state": state, "context": ctx}, noise=noise)
    assert (sample({"state": state, "context": ctx}, noise) - want).abs().max() <= 1e-5
    assert sample.steps == 2 and sample.sampler == "ode"

    policy.train()
    batch = {"state": state, "actions": torch.randn(2, 4, 2), "context": ctx}
    eager = policy.compute_loss(batch, torch.Generator().manual_seed(1)).loss
    eager.backward()
    grads = [p.grad.clone() for p in policy.model.parameters()]
    policy.zero_grad()
    keys = list(policy.state_dict())
    compile_network(policy, backend="aot_eager")
    loss = policy.compute_loss(batch, torch.Generator().manual_seed(1)).loss
    loss.backward()
    assert abs(float(loss) - float(eager)) <= 1e-5
    assert max(float((p.grad - g).abs().max()) for p, g in zip(policy.model.parameters(), grads)) <= 1e-5
    assert list(policy.state_dict()) == keys                                   # checkpoints are unchanged


@pytest.mark.skipif(NO_CC, reason="inductor builds CPU kernels with a C compiler; none (gcc, cc) on PATH")
def test_inductor_sampler_matches_eager():
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", num_inference_timesteps=1, **TINY)).eval()
    state, noise = torch.randn(1, 5), torch.randn(1, 4, 2)
    sample = compile_sampler(policy)
    assert (sample({"state": state}, noise) - policy.predict_action_chunk({"state": state}, noise=noise)).abs().max() <= 1e-5


def test_compile_refusals_are_one_line():
    mf = ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", meanflow_dudt="jvp", **TINY))
    with pytest.raises(ValueError, match="--compile: MeanFlow's meanflow_dudt='jvp'"):
        compile_network(mf)
    with pytest.raises(ValueError, match="sampler: the SDE sampler"):
        compile_sampler(mf, sampler="sde")


def test_eval_policy_fn_with_the_compiled_sampler_draws_the_checkpoints_noise():
    """`eval --compile`'s policy_fn gives the chunks of the plain one: same per-row noise, same sampler."""
    import numpy as np

    from action_decoder.evaluate import make_policy_fn

    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", num_inference_timesteps=2, **TINY)).eval()
    states = np.random.default_rng(0).normal(size=(3, 5)).astype(np.float32)
    keys = {"episode_seeds": np.array([5, 6, 7]), "plan_indices": np.array([0, 2, 1])}
    plain = make_policy_fn(policy, 1, None, None, torch.Generator().manual_seed(4))
    compiled = make_policy_fn(policy, 1, None, None, torch.Generator().manual_seed(4),
                              compile_sampler(policy, backend="aot_eager"))
    want = plain(states, np.zeros(3, np.int64), **keys)
    assert np.abs(compiled(states, np.zeros(3, np.int64), **keys) - want).max() <= 1e-5
    other = plain(states, np.zeros(3, np.int64), episode_seeds=keys["episode_seeds"], plan_indices=np.array([1, 2, 1]))
    assert np.abs(other[0] - want[0]).max() > 1e-3 and np.abs(other[1:] - want[1:]).max() <= 1e-6


def test_compiled_trained_rtc_sampler_matches_eager_at_every_delay():
    """One `compile_sampler(rtc=True)` graph serves delays 0..M: each is `sample(prev_chunk, delay, "trained")`;
    `eval --compile --rtc`'s policy_fn hands it the previous chunks."""
    import numpy as np

    from action_decoder.evaluate import make_policy_fn

    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", num_inference_timesteps=1, rtc_max_delay=2,
                                               **TINY)).eval()
    state, noise, prev = torch.randn(2, 5), torch.randn(2, 4, 2), torch.randn(2, 3, 2).tanh()
    sample = compile_sampler(policy, backend="aot_eager", rtc=True)
    for delay in (0, 1, 2):
        want = policy.sample({"state": state}, noise=noise, prev_chunk=prev, delay=delay, rtc_mode="trained").actions
        got = sample({"state": state}, noise, prev_chunk=prev, delay=delay)
        assert (got - want).abs().max() <= 1e-5 and (got[:, :delay] == prev[:, :delay]).all()
    assert (sample({"state": state}, noise) - policy.predict_action_chunk({"state": state}, noise=noise)).abs().max() <= 1e-5
    short = prev[:, :1]                                      # fewer rows than rtc_max_delay: padded for the graph
    want = policy.sample({"state": state}, noise=noise, prev_chunk=short, delay=1, rtc_mode="trained").actions
    assert (sample({"state": state}, noise, prev_chunk=short, delay=1) - want).abs().max() <= 1e-5
    with pytest.raises(ValueError, match="delay: 3 exceeds rtc_max_delay=2"):
        sample({"state": state}, noise, prev_chunk=prev, delay=3)
    with pytest.raises(ValueError, match="prev_chunk: this compiled sampler has no real-time chunking"):
        compile_sampler(policy, backend="aot_eager")({"state": state}, noise, prev_chunk=prev, delay=1)
    with pytest.raises(ValueError, match="rtc: the graph feeds committed actions"):
        compile_sampler(ActionDecoderPolicy(DecoderConfig(decoder_type="mean_flow", **TINY)), rtc=True)

    states = np.random.default_rng(0).normal(size=(2, 5)).astype(np.float32)
    keys = {"episode_seeds": np.array([5, 6]), "plan_indices": np.array([1, 2]), "prev_chunks": prev.numpy(), "delay": 2}
    eager = make_policy_fn(policy, 1, None, None, torch.Generator().manual_seed(4), rtc_mode="trained")
    compiled = make_policy_fn(policy, 1, None, None, torch.Generator().manual_seed(4), sample)
    assert np.abs(compiled(states, np.zeros(2, np.int64), **keys) - eager(states, np.zeros(2, np.int64), **keys)).max() <= 1e-5
