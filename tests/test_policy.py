"""ActionDecoderPolicy: training and sampling for every decoder, conditioning, runtime
sampler choice, save/load, call counts, validation."""

import dataclasses
import json
import warnings

import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig, PolicyOutput
from action_decoder.config import CONFIG_FORMAT_VERSION, SDE_MIN_STEPS
from action_decoder.expert import ActionExpert
from action_decoder.oracles import Gaussian
from action_decoder.rl.sde_policy import finetune_policy
from action_decoder.train import task_context

SMALL = dict(state_dim=5, action_dim=3, action_chunk_size=8, n_action_steps=4, hidden_size=32,
             num_hidden_layers=2, num_attention_heads=4, num_key_value_heads=2, num_inference_timesteps=4,
             flow_sde_num_steps=4)
STATS = {"state": {"mean": [1.0] * 5, "std": [2.0] * 5, "min": [-3.0] * 5, "max": [5.0] * 5},
         "actions": {"mean": [0.5, -0.5, 2.0], "std": [0.1, 0.2, 3.0], "min": [0.0, -1.5, -13.0], "max": [1.0, 0.5, 17.0]}}


def make(decoder_type="flow_matching", stats=STATS, **kw):
    torch.manual_seed(0)
    return ActionDecoderPolicy(DecoderConfig(decoder_type=decoder_type, **{**SMALL, **kw}), stats)


def batch(b=6, seed=0, actions=True):
    g = torch.Generator().manual_seed(seed)
    out = {"state": torch.randn(b, 5, generator=g)}
    if actions:
        out["actions"] = torch.randn(b, 8, 3, generator=g)
    return out


@pytest.mark.parametrize("decoder_type", ["DDPM", "flow_matching", "mean_flow"])
def test_each_decoder_trains_and_samples(decoder_type):
    policy = make(decoder_type)
    opt = torch.optim.Adam(policy.parameters(), 1e-3)
    out = policy(batch())
    assert isinstance(out, PolicyOutput) and out.loss.dim() == 0 and torch.isfinite(out.loss)
    out.loss.backward()
    trainable = [p for p in policy.model.parameters() if p.requires_grad]
    assert all(p.grad is not None for p in trainable)
    assert sum(float(p.grad.abs().sum()) > 0 for p in trainable) > 0.9 * len(trainable)
    opt.step()
    policy.eval()
    actions = policy.predict_action_chunk(batch(actions=False), generator=torch.Generator().manual_seed(0))
    assert actions.shape == (6, 8, 3) and torch.isfinite(actions).all()


def test_meanflow_training_through_attention_matches_explicit_softmax():
    policy = make("mean_flow", meanflow_ratio_r_neq_t=1.0)
    grads = []
    for impl in ("auto", "eager"):
        policy.model.attn_implementation = impl
        policy.zero_grad()
        policy(batch(), generator=torch.Generator().manual_seed(1)).loss.backward()
        grads.append([p.grad.clone() for p in policy.model.parameters()])
    for a, b in zip(*grads):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)


def test_normalisation_round_trip_and_env_units():
    policy = make("flow_matching").eval()
    noise = torch.zeros(2, 8, 3)
    # Replace the network by zero velocity: the sample is the (zero) noise in normalised units,
    # so in environment units it is the action mean.
    policy.model.forward = lambda x, *a, **k: torch.zeros_like(x)
    out = policy.sample(batch(2, actions=False), noise=noise).actions
    assert torch.allclose(out, torch.tensor([0.5, -0.5, 2.0]).expand(2, 8, 3))


def test_runtime_sampler_overrides_config_both_ways():
    policy = make("flow_matching", flow_sde_use=True, flow_sde_return_logprob=True).eval()
    b = batch(actions=False)
    default = policy(b, generator=torch.Generator().manual_seed(0))
    assert default.log_prob is not None and default.log_prob.shape == (6,)
    ode1 = policy(b, sampler="ode", generator=torch.Generator().manual_seed(3))
    ode2 = policy(b, sampler="ode", generator=torch.Generator().manual_seed(3))
    assert ode1.log_prob is None and torch.equal(ode1.actions, ode2.actions)
    assert policy(b, return_logprob=False, generator=torch.Generator().manual_seed(0)).log_prob is None
    # An ODE config asked for the SDE at run time.
    ode_policy = make("mean_flow").eval()
    sde = ode_policy(b, sampler="sde", return_logprob=True)
    assert sde.log_prob.shape == (6,) and torch.isfinite(sde.log_prob).all()
    assert sde.log_prob.dtype == torch.float32 and sde.chain.shape == (6, 5, 8, 3)
    with pytest.raises(ValueError, match="sampler"):
        make("DDPM").eval()(b, sampler="sde")
    with pytest.raises(ValueError, match="return_logprob"):
        ode_policy(b, sampler="ode", return_logprob=True)
    with pytest.raises(ValueError, match="sampler"):
        ode_policy(b, sampler="fast")


def test_euler_on_meanflow_warns():
    policy = make("mean_flow").eval()
    with pytest.warns(UserWarning, match="approximation"):
        policy(batch(actions=False), sampler="euler")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make("flow_matching").eval()(batch(actions=False), sampler="euler")


def test_learnable_sigma_is_a_policy_parameter():
    policy = make("flow_matching", flow_sde_use=True, flow_sde_learn_sigma=True, flow_sde_sigma_init=0.2)
    names = [n for n, _ in policy.named_parameters()]
    assert "sigma.log_scale" in names
    assert policy.sigma.multiplier == torch.tensor(0.2)


def test_chain_log_prob_ratio_one_and_gradient():
    policy = make("mean_flow", flow_sde_mode="explore").eval()
    b = batch(actions=False)
    out = policy(b, sampler="sde", return_logprob=True, generator=torch.Generator().manual_seed(0))
    policy.train()
    lp = policy.chain_log_prob(b, out.chain, out.grid)
    assert torch.allclose(lp, out.step_log_probs, atol=1e-3, rtol=1e-5)
    lp.sum().backward()
    assert policy.model.head.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("decoder_type", ["DDPM", "flow_matching", "mean_flow"])
def test_save_load_identical_actions(tmp_path, decoder_type):
    policy = make(decoder_type).eval()
    policy.save_pretrained(tmp_path / "ckpt")
    assert {p.name for p in (tmp_path / "ckpt").iterdir()} == {"config.json", "model.safetensors", "README.md"}
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "ckpt").eval()
    b = batch(actions=False)
    a = policy.predict_action_chunk(b, generator=torch.Generator().manual_seed(5))
    c = loaded.predict_action_chunk(b, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, c)
    assert torch.equal(loaded.normalizers["actions"].std, torch.tensor([0.1, 0.2, 3.0]))


def test_sample_head_survives_save_load(tmp_path):
    policy = make("mean_flow", flow_prediction="sample").eval()
    policy.save_pretrained(tmp_path / "new")
    b = batch(actions=False)
    a = policy.predict_action_chunk(b, generator=torch.Generator().manual_seed(5))
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "new").eval()
    assert torch.equal(a, loaded.predict_action_chunk(b, generator=torch.Generator().manual_seed(5)))


@pytest.mark.parametrize("field", ["decoder_type", "flow_prediction", "flow_sde_num_steps", "format_version"])
def test_checkpoint_missing_a_field_is_refused_not_defaulted(tmp_path, field):
    # A config.json without decoder_type loaded as DDPM, one without flow_prediction as a velocity
    # head: the same weights then act differently. Every field and the format version are required.
    make("mean_flow", flow_prediction="sample").save_pretrained(tmp_path / "c")
    path = tmp_path / "c" / "config.json"
    saved = json.loads(path.read_text())
    assert saved["format_version"] == CONFIG_FORMAT_VERSION
    assert set(saved) == {f.name for f in dataclasses.fields(DecoderConfig)} | {"format_version"}
    del saved[field]
    path.write_text(json.dumps(saved))
    with pytest.raises(ValueError, match=rf"missing field\(s\) \['{field}'\].*format_version {CONFIG_FORMAT_VERSION}"):
        ActionDecoderPolicy.from_pretrained(tmp_path / "c")
    path.write_text(json.dumps({**saved, field: None, "format_version": CONFIG_FORMAT_VERSION + 1}))
    with pytest.raises(ValueError, match=rf"expected format_version 2..{CONFIG_FORMAT_VERSION}, got {CONFIG_FORMAT_VERSION + 1}"):
        ActionDecoderPolicy.from_pretrained(tmp_path / "c")


def test_checkpoint_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json"):
        ActionDecoderPolicy.from_pretrained(tmp_path)
    make().save_pretrained(tmp_path / "a")
    (tmp_path / "a" / "model.safetensors").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="safetensors"):
        ActionDecoderPolicy.from_pretrained(tmp_path / "a")
    make().save_pretrained(tmp_path / "b")
    cfg = DecoderConfig.from_json(tmp_path / "b" / "config.json")
    cfg.hidden_size = 64
    cfg.to_json(tmp_path / "b" / "config.json")
    with pytest.raises(ValueError, match="does not match"):
        ActionDecoderPolicy.from_pretrained(tmp_path / "b")


def test_from_go1_config_builds_a_policy():
    go1 = {"decoder_type": "mean_flow", "flow_sde_use": True, "num_inference_timesteps": 2, **SMALL}
    go1.pop("num_inference_timesteps")
    policy = ActionDecoderPolicy(DecoderConfig.from_go1(go1)).eval()
    assert policy.predict_action_chunk(batch(actions=False)).shape == (6, 8, 3)


@pytest.mark.parametrize("decoder_type, sampler", [("DDPM", None), ("flow_matching", "ode"),
                                                   ("flow_matching", "sde"), ("mean_flow", "ode"),
                                                   ("mean_flow", "sde")])
def test_network_called_k_times_and_prefix_once(decoder_type, sampler):
    policy = make(decoder_type, context_dim=7).eval()
    calls = {"forward": 0, "prefix": 0}
    forward, build = ActionExpert.forward, ActionExpert.build_prefix

    def counting_forward(self, *a, **k):
        calls["forward"] += 1
        return forward(self, *a, **k)

    def counting_build(self, *a, **k):
        calls["prefix"] += 1
        return build(self, *a, **k)

    b = {**batch(actions=False), "context": torch.randn(6, 3, 7), "context_mask": torch.ones(6, 3, dtype=torch.bool)}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ActionExpert, "forward", counting_forward)
        mp.setattr(ActionExpert, "build_prefix", counting_build)
        policy(b, sampler=sampler, steps=5)
    assert calls == {"forward": 5, "prefix": 1}


@pytest.mark.parametrize("decoder_type, steps", [("flow_matching", 1), ("flow_matching", 10), ("mean_flow", 1),
                                                 ("mean_flow", 2)])
def test_sample_head_lands_on_its_prediction_whatever_the_noise(decoder_type, steps):
    # A head predicting the clean chunk c makes every step aim at c: the samples are c, with no
    # trace of the noise, at every K ≤ 20 (1 − t is floored at 0.05). A velocity head outputting c is not.
    c = torch.randn(6, 8, 3)
    for prediction, exact in (("sample", True), ("velocity", False)):
        policy = make(decoder_type, flow_prediction=prediction).eval()
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(ActionExpert, "forward", lambda self, x, *a, **k: c)
            outs = [policy.sample(batch(actions=False), steps=steps, generator=torch.Generator().manual_seed(s))
                    for s in (0, 1)]
        target = policy.normalizers["actions"].unnormalize(c)
        assert all(torch.allclose(o.actions, target, atol=1e-5) == exact for o in outs)


def test_sample_head_trains_every_parameter_through_the_jvp():
    policy = make("mean_flow", flow_prediction="sample", meanflow_ratio_r_neq_t=1.0)
    loss = policy(batch()).loss
    loss.backward()
    assert torch.isfinite(loss)
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.model.parameters() if p.requires_grad)


def test_masked_context_does_not_influence_actions():
    policy = make("flow_matching", context_dim=7).eval()
    ctx = torch.randn(6, 4, 7)
    mask = torch.tensor([[1, 1, 0, 0]] * 6, dtype=torch.bool)
    garbage = ctx.clone()
    garbage[:, 2:] = 1e4
    b = batch(actions=False)
    a = policy.predict_action_chunk({**b, "context": ctx, "context_mask": mask}, generator=torch.Generator().manual_seed(0))
    c = policy.predict_action_chunk({**b, "context": garbage, "context_mask": mask}, generator=torch.Generator().manual_seed(0))
    d = policy.predict_action_chunk({**b, "context": garbage}, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(a, c, atol=1e-5) and not torch.allclose(a, d, atol=1e-3)


def test_llama_kv_cache_conditions_training_and_sampling_without_mutation():
    transformers = pytest.importorskip("transformers")
    torch.manual_seed(0)
    llama = transformers.LlamaForCausalLM(transformers.LlamaConfig(
        vocab_size=50, hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=4,
        num_key_value_heads=2)).eval()
    ids = torch.randint(0, 50, (6, 5))
    attn = torch.ones(6, 5, dtype=torch.long)
    attn[:, -1] = 0
    with torch.no_grad():
        cache = llama(input_ids=ids, attention_mask=attn, use_cache=True).past_key_values
    before = [(k.clone(), v.clone()) for k, v in ((layer.keys, layer.values) for layer in cache.layers)]
    policy = make("mean_flow", vlm_num_layers=2, vlm_head_dim=8, vlm_num_key_value_heads=2)
    out = policy({**batch(), "vlm_key_values": cache, "attention_mask": attn})
    out.loss.backward()
    assert policy.model.conditioning.vlm_k_proj[0].weight.grad.abs().sum() > 0
    policy.eval()
    b = {**batch(actions=False), "vlm_key_values": cache, "attention_mask": attn}
    a1 = policy.predict_action_chunk(b, generator=torch.Generator().manual_seed(0))
    a2 = policy.predict_action_chunk(b, generator=torch.Generator().manual_seed(0))
    a0 = policy.predict_action_chunk(batch(actions=False), generator=torch.Generator().manual_seed(0))
    assert torch.equal(a1, a2) and not torch.allclose(a1, a0, atol=1e-4)
    after = [(layer.keys, layer.values) for layer in cache.layers]
    assert all(torch.equal(k0, k1) and torch.equal(v0, v1) for (k0, v0), (k1, v1) in zip(before, after))


def test_select_action_queue_and_reset():
    policy = make("flow_matching").eval()
    calls = []
    sample = policy.sample
    policy.sample = lambda *a, **k: calls.append(1) or sample(*a, **k)
    b = batch(2, actions=False)
    actions = [policy.select_action(b) for _ in range(5)]
    assert all(a.shape == (2, 3) for a in actions) and len(calls) == 2   # n_action_steps = 4
    policy.reset()
    policy.select_action(b)
    assert len(calls) == 3


@pytest.mark.parametrize("bad, key", [
    ({"state": torch.randn(6, 4)}, "state"),
    ({"actions": torch.randn(6, 8, 2)}, "actions"),
    ({"actions": torch.randn(6, 7, 3)}, "actions"),
    ({"state": torch.full((6, 5), float("nan"))}, "state"),
    ({"actions": torch.full((6, 8, 3), float("inf"))}, "actions"),
    ({"ctrl_freq": torch.ones(5)}, "ctrl_freq"),
    ({"context": torch.randn(6, 2, 7)}, "context"),
])
def test_bad_batches_name_the_key(bad, key):
    policy = make("flow_matching")
    with pytest.raises(ValueError, match=rf"batch\['{key}'\]: "):
        policy({**batch(), **bad})
    with pytest.raises(ValueError, match=r"batch\['actions'\]: missing"):
        policy(batch(actions=False))


def test_a_single_nan_or_opposite_infs_are_refused_and_huge_finite_inputs_are_not():
    """The finiteness check sums first: one NaN, or +Inf and −Inf (a NaN sum), must still be caught, and
    finite values whose float32 sum overflows must still pass."""
    policy = make("flow_matching")
    for value in ([float("nan")], [float("inf"), -float("inf")]):
        state = torch.zeros(6, 5)
        state[2, 1:1 + len(value)] = torch.tensor(value)
        with pytest.raises(ValueError, match=r"^batch\['state'\]: contains NaN or Inf"):
            policy.sample(batch(actions=False) | {"state": state})
    huge = torch.full((6, 5), 3e38)                      # finite; the sum is +Inf in float32
    assert policy.sample(batch(actions=False) | {"state": huge}).actions.isfinite().all()


@pytest.mark.parametrize("mode", ["churn", "explore"])
def test_meanflow_sde_takes_its_own_steps_not_the_one_step_of_meanflow(mode):
    # A MeanFlow config samples its ODE in 1 step; one Euler–Maruyama step from noise would give
    # std 0.74 for this target of std 0.4 (flows.samplers.gaussian_target_std).
    oracle = Gaussian(torch.zeros(8, 3), 0.4)
    kw = {k: v for k, v in SMALL.items() if k != "flow_sde_num_steps"}
    policy = ActionDecoderPolicy(DecoderConfig(**{**kw, "decoder_type": "mean_flow", "num_inference_timesteps": 1,
                                                  "flow_sde_mode": mode}), STATS).eval()
    assert policy.config.flow_sde_num_steps == 10 >= SDE_MIN_STEPS
    b = batch(500, actions=False)
    with pytest.MonkeyPatch.context() as mp, warnings.catch_warnings():
        warnings.simplefilter("error")
        mp.setattr(ActionExpert, "forward", lambda self, x, t, r, *a, **k: oracle.avg_velocity(x, t, r))
        sde = policy.sample(b, sampler="sde", generator=torch.Generator().manual_seed(0))
        ode = policy.sample(b, sampler="ode", generator=torch.Generator().manual_seed(0))
    std = [float(policy.normalizers["actions"].normalize(o.actions).std()) for o in (sde, ode)]
    assert sde.chain.shape == (500, 11, 8, 3) and 0.32 < std[0] < 0.42   # churn 0.34, explore 0.38 at K = 10
    assert abs(std[1] - 0.4) < 0.01                                      # MeanFlow's exact 1-step jump


def test_sde_below_the_minimum_steps_warns_once():
    policy = make("flow_matching").eval()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy.sample(batch(actions=False), sampler="sde", steps=SDE_MIN_STEPS)
        policy.sample(batch(actions=False), sampler="ode", steps=1)
    with pytest.warns(UserWarning, match=rf"steps: the SDE sampler with 1 step.*at least {SDE_MIN_STEPS}") as rec:
        policy.sample(batch(actions=False), sampler="sde", steps=1)
    # the quoted stds are this policy's σ(t)'s (closed form, checked against sampling in test_sde)
    from action_decoder.flows.samplers import gaussian_target_std
    quoted = [gaussian_target_std(policy.sigma, k, 0.4, policy.config.flow_sde_clip_t) for k in (1, SDE_MIN_STEPS, 10)]
    assert (f"std {quoted[0]:.3f} at K = 1 ({quoted[1]:.3f} at K = {SDE_MIN_STEPS}, {quoted[2]:.3f} at K = 10)"
            in str(rec[0].message)), str(rec[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy.sample(batch(actions=False), sampler="sde", steps=2)
    with pytest.raises(ValueError, match=r"steps: expected a positive integer, got 0"):
        policy.sample(batch(actions=False), steps=0)


def test_finetuned_checkpoint_samples_its_sde_with_its_k(tmp_path):
    bc = make("mean_flow", num_inference_timesteps=1, flow_sde_num_steps=10)
    finetune_policy(bc, 0.5, True, 6).save_pretrained(tmp_path / "ft")
    ft = ActionDecoderPolicy.from_pretrained(tmp_path / "ft").eval()
    assert ft.config.flow_sde_use and ft.sample(batch(actions=False)).chain.shape[1] == 7


@pytest.mark.parametrize("kwargs", [{"sampler": "sde"}, {"return_logprob": True}, {"sampler": "ode", "steps": 3}])
def test_sampling_arguments_in_train_mode_raise(kwargs):
    policy = make("flow_matching").train()
    with pytest.raises(ValueError, match=rf"{next(iter(kwargs))}.*train\(\) mode.*policy.eval\(\)"):
        policy(batch(), **kwargs)
    assert policy(batch()).loss.dim() == 0


def test_select_action_replans_when_the_batch_size_changes():
    policy = make("flow_matching").eval()
    calls = []
    sample = policy.sample
    policy.sample = lambda *a, **k: calls.append(1) or sample(*a, **k)
    assert policy.select_action(batch(4, actions=False)).shape == (4, 3)
    one = batch(1, seed=3, actions=False)
    action = policy.select_action(one, generator=torch.Generator().manual_seed(7))
    fresh = sample(one, generator=torch.Generator().manual_seed(7)).actions[:, 0]
    assert len(calls) == 2 and torch.equal(action, fresh)
    assert policy.select_action(one).shape == (1, 3) and len(calls) == 2     # the new queue is used


@pytest.mark.parametrize("shape", [(6, 4, 3), (5, 8, 3), (6, 8, 2), (8, 3)])
def test_noise_of_the_wrong_shape_is_refused(shape):
    policy = make("flow_matching").eval()
    with pytest.raises(ValueError, match=r"noise: expected a floating-point tensor of shape \[6, 8, 3\]"):
        policy.sample(batch(actions=False), noise=torch.zeros(shape))
    with pytest.raises(ValueError, match="noise: contains NaN"):
        policy.sample(batch(actions=False), noise=torch.full((6, 8, 3), float("nan")))


def test_multitask_checkpoint_refuses_to_sample_without_its_task(tmp_path):
    tasks = ["reach-v3", "push-v3", "pick-place-v3"]
    make("flow_matching", context_dim=3, extra={"tasks": tasks}).save_pretrained(tmp_path / "mt")
    policy = ActionDecoderPolicy.from_pretrained(tmp_path / "mt").eval()
    b = batch(actions=False)
    message = r"batch\['context'\]: missing; .*3 tasks \['reach-v3', 'push-v3', 'pick-place-v3'\].*task_context"
    for call, arg in ((policy.predict_action_chunk, b), (policy.select_action, b), (policy.train(), batch())):
        with pytest.raises(ValueError, match=message):
            call(arg)
    policy.eval()
    ctx = task_context(torch.full((6,), 1), 3)
    assert policy.predict_action_chunk({**b, **ctx}).shape == (6, 8, 3)
    # One task, or a policy with no conditioning path at all, has nothing to be told.
    make("flow_matching", context_dim=3, extra={"tasks": tasks[:1]}).eval().predict_action_chunk(b)
    make("flow_matching", extra={"tasks": tasks}).eval().predict_action_chunk(b)


# ---------------------------------------------------------------------- cameras
CAMS = ("observation.images.left", "observation.images.wrist")


def make_camera(decoder_type="flow_matching", **kw):
    return make(decoder_type, cameras=CAMS, image_size=16, **kw)


def camera_batch(b=3, seed=0, actions=True):
    g = torch.Generator().manual_seed(seed + 100)
    return {**batch(b, seed, actions), "images": torch.randint(0, 256, (b, 2, 3, 16, 16), dtype=torch.uint8, generator=g)}


@pytest.mark.parametrize("decoder_type", ["flow_matching", "mean_flow", "DDPM"])
def test_changing_one_camera_frame_changes_the_sampled_chunk(decoder_type):
    policy = make_camera(decoder_type).eval()
    b, noise = camera_batch(), torch.randn(3, 8, 3, generator=torch.Generator().manual_seed(1))
    same = policy.sample(b, noise=noise).actions
    assert torch.equal(same, policy.sample(b, noise=noise).actions)              # eval(): deterministic
    other = dict(b, images=b["images"].clone())
    other["images"][0, 1] = 255 - other["images"][0, 1]                          # row 0's second camera only
    moved = policy.sample(other, noise=noise).actions
    assert (moved[0] - same[0]).abs().max() > 1e-4
    torch.testing.assert_close(moved[1:], same[1:])                              # the other rows keep theirs


def test_float_frames_in_unit_range_encode_like_uint8():
    policy = make_camera().eval()
    b, noise = camera_batch(), torch.randn(3, 8, 3)
    as_float = dict(b, images=b["images"].float() / 255)
    torch.testing.assert_close(policy.sample(as_float, noise=noise).actions, policy.sample(b, noise=noise).actions)


@pytest.mark.parametrize("decoder_type", ["flow_matching", "mean_flow"])
def test_training_gradients_reach_the_image_encoder(decoder_type):
    policy = make_camera(decoder_type).train()
    policy.compute_loss(camera_batch(), torch.Generator().manual_seed(0)).loss.backward()
    enc = policy.model.image_encoder
    for name, p in [("first conv", enc.backbone.net[0].weight), ("projection", enc.proj.weight),
                    ("camera embedding", enc.camera_embed), ("image k/v", policy.model.conditioning.image_kv.weight)]:
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_frozen_image_backbone_gets_no_gradient_but_its_tokens_train():
    policy = make_camera(freeze_image_encoder=True).train()
    policy.compute_loss(camera_batch(), torch.Generator().manual_seed(0)).loss.backward()
    enc = policy.model.image_encoder
    assert all(p.grad is None and not p.requires_grad for p in enc.backbone.parameters())
    assert enc.proj.weight.grad.abs().sum() > 0


def test_camera_policy_saves_its_encoder_and_reloads_identical_chunks(tmp_path):
    policy = make_camera("mean_flow").eval()
    b, noise = camera_batch(), torch.randn(3, 8, 3)
    policy.save_pretrained(tmp_path / "ckpt")
    from safetensors.torch import load_file

    assert any(k.startswith("model.image_encoder.backbone.") for k in load_file(str(tmp_path / "ckpt" / "model.safetensors")))
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "ckpt").eval()
    assert loaded.config.cameras == CAMS and loaded.config.image_size == 16
    torch.testing.assert_close(loaded.sample(b, noise=noise).actions, policy.sample(b, noise=noise).actions,
                               rtol=0, atol=0)


def test_training_shift_changes_the_encoding_and_eval_does_not():
    policy = make_camera(image_shift=3)
    enc, images = policy.model.image_encoder, camera_batch()["images"]
    enc.eval()
    assert torch.equal(enc(images), enc(images))
    enc.train()
    torch.manual_seed(0)
    shifted = [enc(images) for _ in range(3)]
    assert any((s - enc.eval()(images)).abs().max() > 1e-4 for s in shifted)
    no_shift = make_camera(image_shift=0).model.image_encoder
    assert torch.equal(no_shift.train()(images), no_shift.eval()(images))


@pytest.mark.parametrize("images, match", [
    (None, r"batch\['images'\]: missing; this policy conditions on cameras; expected a tensor \[3, 2, 3, 16, 16\]"),
    (torch.zeros(3, 1, 3, 16, 16, dtype=torch.uint8), r"batch\['images'\]: expected a tensor \[3, 2, 3, 16, 16\].*got \[3, 1, 3, 16, 16\]"),
    (torch.zeros(3, 2, 16, 16, 3, dtype=torch.uint8), r"expected a tensor \[3, 2, 3, 16, 16\] \(batch, cameras \['observation.images.left', 'observation.images.wrist'\]"),
    (torch.zeros(3, 2, 3, 16, 16, dtype=torch.int64), r"got \[3, 2, 3, 16, 16\] torch.int64"),
    (torch.full((3, 2, 3, 16, 16), 255.0), r"expected floating-point pixels in \[0, 1\] \(or uint8 0..255\), got values in \[255, 255\]"),
    (torch.full((3, 2, 3, 16, 16), float("nan")), r"expected floating-point pixels in \[0, 1\]"),
])
def test_bad_camera_input_is_one_line_naming_the_key_and_shape(images, match):
    policy = make_camera().eval()
    b = {**camera_batch(), "images": images}
    with pytest.raises(ValueError, match=match) as err:
        policy.sample(b)
    assert "\n" not in str(err.value)


def test_images_for_a_policy_without_cameras_are_refused():
    with pytest.raises(ValueError, match=r"batch\['images'\]: this policy has no cameras"):
        make().eval().sample(camera_batch())


def test_proprio_layout_reads_the_hand_and_gripper_only():
    """With state_layout="metaworld_proprio" the network reads entries 0..3 of the 39-d state: moving an
    object or the goal leaves the chunk as it is, moving the hand does not."""
    policy = make_camera(state_dim=39, state_layout="metaworld_proprio", stats=None).eval()
    assert policy.model.state_in.in_features == 4
    g = torch.Generator().manual_seed(0)
    state, noise = torch.rand(3, 39, generator=g), torch.randn(3, 8, 3, generator=g)
    b = dict(camera_batch(), state=state)
    base = policy.sample(b, noise=noise).actions
    objects = state.clone()
    objects[:, 4:] += 0.3
    torch.testing.assert_close(policy.sample(dict(b, state=objects), noise=noise).actions, base)
    hand = state.clone()
    hand[:, :3] += 0.3
    assert (policy.sample(dict(b, state=hand), noise=noise).actions - base).abs().max() > 1e-4


@pytest.mark.parametrize("decoder_type, sampler", [("flow_matching", "ode"), ("flow_matching", "sde"),
                                                   ("mean_flow", "ode"), ("DDPM", None)])
def test_camera_frames_are_encoded_once_per_chunk(decoder_type, sampler):
    policy = make_camera(decoder_type).eval()
    calls = []
    policy.model.image_encoder.register_forward_hook(lambda *a: calls.append(1))
    policy.sample(camera_batch(), sampler=sampler, steps=4)
    assert len(calls) == 1


def test_from_pretrained_returns_a_policy_ready_to_sample(tmp_path):
    make().save_pretrained(tmp_path / "c")
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "c")
    assert not loaded.training and loaded(batch(actions=False)).actions.shape == (6, 8, 3)
    assert loaded.train()(batch()).loss.dim() == 0


def test_small_action_spreads_reach_the_network_at_unit_scale_and_constant_ones_take_the_floor():
    stats = {"state": STATS["state"],
             "actions": {"mean": [0.0, 0.0, 1.0], "std": [0.003, 0.0, 2e-7], "min": [-0.01, 0.0, 1.0],
                         "max": [0.01, 0.0, 1.0]}}
    policy = make(stats=stats)
    a = torch.tensor([[0.003, 0.0, 1.0]])
    torch.testing.assert_close(policy.normalizers["actions"].normalize(a), torch.tensor([[1.0, 0.0, 0.0]]))
    half = make(stats=stats, normalization_mode="min_max").normalizers["actions"]
    torch.testing.assert_close(half.normalize(torch.tensor([[0.01, 0.0, 1.0]])), torch.tensor([[1.0, 0.0, 0.0]]))
    assert float(policy.normalizers["state"].normalize(torch.full((1, 5), 1.02))[0, 0]) == pytest.approx(0.01)


def test_checkpoint_of_format_5_keeps_flooring_every_action_spread_at_one_hundredth(tmp_path):
    stats = {"state": STATS["state"], "actions": {**STATS["actions"], "std": [0.003, 0.2, 3.0]}}
    make(stats=stats).save_pretrained(tmp_path / "c")
    cfg = json.loads((tmp_path / "c" / "config.json").read_text())
    del cfg["action_constant_below"]
    (tmp_path / "c" / "config.json").write_text(json.dumps({**cfg, "format_version": 5}))
    old = ActionDecoderPolicy.from_pretrained(tmp_path / "c")
    assert old.config.action_constant_below == 1e-2
    torch.testing.assert_close(old.normalizers["actions"].normalize(torch.tensor([[0.503, -0.5, 2.0]])),
                               torch.tensor([[0.3, 0.0, 0.0]]))


def test_statistics_stay_float32_when_the_policy_changes_dtype(tmp_path):
    stats = {"state": {**STATS["state"], "mean": [250.3, 0.61, 1.57, 0.0, 0.0]},
             "actions": STATS["actions"]}
    policy = make(stats=stats).to(torch.bfloat16)
    norm = policy.normalizers["state"]
    assert norm.mean.dtype == torch.float32 and float(norm.mean[0]) == pytest.approx(250.3, abs=1e-4)
    assert next(policy.model.parameters()).dtype == torch.bfloat16
    policy.save_pretrained(tmp_path / "c")
    assert float(ActionDecoderPolicy.from_pretrained(tmp_path / "c").normalizers["state"].mean[0]) == pytest.approx(250.3, abs=1e-4)


@pytest.mark.parametrize("actions, match", [
    ({"std": [-1.0, 0.2, 3.0]}, r"stats\['actions'\]\['std'\]: expected non-negative values"),
    ({"min": [2.0, -1.0, -1.0]}, r"stats\['actions'\]: expected min <= max in every dimension"),
])
def test_impossible_statistics_are_refused(actions, match):
    with pytest.raises(ValueError, match=match):
        make(stats={"state": STATS["state"], "actions": {**STATS["actions"], **actions}})


@pytest.mark.parametrize("bad, match", [
    ({"context": "nan"}, r"batch\['context'\]: contains NaN or Inf at positions the context_mask keeps"),
    ({"ctrl_freq": torch.tensor([10.0, float("nan"), 10, 10, 10, 10])}, r"batch\['ctrl_freq'\]: expected finite positive"),
    ({"ctrl_freq": torch.tensor([10.0, -5.0, 10, 10, 10, 10])}, r"batch\['ctrl_freq'\]: expected finite positive"),
    ({"attention_mask": torch.ones(6, 3, dtype=torch.bool)}, r"batch\['attention_mask'\]: masks batch\['vlm_key_values'\], which is missing; for context tokens use batch\['context_mask'\]"),
    ({"context_mask": torch.ones(6, 3, dtype=torch.bool)}, r"batch\['context_mask'\]: masks batch\['context'\], which is missing"),
    ({"state": torch.randn(0, 5), "actions": torch.randn(0, 8, 3)}, r"batch\['state'\]: expected at least one row"),
])
def test_conditioning_inputs_that_would_give_nan_or_be_ignored_are_refused(bad, match):
    policy = make(context_dim=7)
    ctx = torch.randn(6, 3, 7)
    if bad.get("context") == "nan":
        bad = {"context": ctx.clone()}
        bad["context"][0, 1, 2] = float("nan")
    with pytest.raises(ValueError, match=match):
        policy({**batch(), **bad})
    masked = ctx.clone()
    masked[0, 2] = float("nan")               # a padded position may hold anything
    mask = torch.ones(6, 3, dtype=torch.bool)
    mask[0, 2] = False
    assert torch.isfinite(policy({**batch(), "context": masked, "context_mask": mask}).loss)
    assert torch.isfinite(policy({**batch(), "ctrl_freq": torch.full((6,), 20, dtype=torch.long)}).loss)


def test_nan_in_a_used_vlm_layer_is_refused_but_not_under_the_mask():
    policy = make(vlm_num_layers=2, vlm_head_dim=8, vlm_num_key_value_heads=2)
    kv = [(torch.randn(6, 2, 5, 8), torch.randn(6, 2, 5, 8)) for _ in range(2)]
    kv[1][0][0, 0, 3, 0] = float("nan")
    with pytest.raises(ValueError, match=r"vlm_key_values: layer 1's K contains NaN or Inf at positions attention_mask keeps"):
        policy({**batch(), "vlm_key_values": kv})
    mask = torch.ones(6, 5, dtype=torch.bool)
    mask[0, 3] = False
    assert torch.isfinite(policy({**batch(), "vlm_key_values": kv, "attention_mask": mask}).loss)


def test_chain_log_prob_refuses_a_chain_of_another_shape():
    policy = make().eval()
    b = batch(2, actions=False)
    out = policy.sample(b, sampler="sde", return_logprob=True)
    with pytest.raises(ValueError, match=r"chain: expected a stored SDE chain of shape \[2, K\+1, 8, 3\] .* got \[2, 5, 3, 3\]"):
        policy.chain_log_prob(b, out.chain[:, :, :3], out.grid)
    with pytest.raises(ValueError, match=r"chain: expected .* got \[1, 5, 8, 3\]"):
        policy.chain_log_prob(b, out.chain[:1], out.grid)
    with pytest.raises(ValueError, match=r"grid: expected the chain's time grid of shape \[5\]"):
        policy.chain_log_prob(b, out.chain, out.grid[:-1])
    torch.testing.assert_close(policy.chain_log_prob(b, out.chain, out.grid).sum(1), out.log_prob)


def test_a_list_of_generators_for_the_loss_is_one_line():
    with pytest.raises(ValueError, match=r"generator: the loss draws its times and noise from one torch.Generator"):
        make()(batch(), generator=[torch.Generator()] * 6)
