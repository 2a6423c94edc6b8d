"""The LeRobot policy plugin (`lerobot_policy_action_decoder/`).

Its pure part (`convert`: config mapping, batch keys, padding, task tokens) is tested without
LeRobot, on the LeRobot-written fixture `tests/data/lerobot/v30_toy`. The LeRobot part (config
registration, factory, processors, `from_pretrained`) runs where `lerobot` is installed
(`scripts/lerobot_integration.sh` runs this file in its virtual environment) and is skipped
elsewhere.
"""

import importlib.util
import json
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "lerobot_policy_action_decoder" / "src"))

from action_decoder import ActionDecoderPolicy as CorePolicy, DecoderConfig  # noqa: E402
from lerobot_policy_action_decoder import convert  # noqa: E402

FIXTURE = ROOT / "tests" / "data" / "lerobot" / "v30_toy"
TASKS = ["push the block", "lift the cube"]
HAS_LEROBOT = importlib.util.find_spec("lerobot") is not None


def plugin_cfg(**over):
    """The plugin config's fields (what `ActionDecoderConfig` holds), as a plain namespace."""
    core = DecoderConfig()
    values = {name: getattr(core, name) for name in convert.SHARED}
    values.update(decoder_type="flow_matching", chunk_size=16, n_action_steps=4, num_inference_steps=None,
                  flow_prediction=None, hidden_size=32, num_hidden_layers=2, tasks=[])
    values.update(over)
    return SimpleNamespace(**values)


# ---------------------------------------------------------------------- without LeRobot
@pytest.mark.parametrize("decoder, steps, head", [("DDPM", 10, "velocity"), ("flow_matching", 10, "velocity"),
                                                   ("mean_flow", 1, "sample")])
def test_decoder_config_maps_lerobot_names_and_defaults(decoder, steps, head):
    cfg = convert.decoder_config(plugin_cfg(decoder_type=decoder, chunk_size=8, n_action_steps=2), 6, 3)
    assert (cfg.decoder_type, cfg.action_chunk_size, cfg.n_action_steps) == (decoder, 8, 2)
    assert (cfg.num_inference_timesteps, cfg.flow_prediction) == (steps, head)
    assert (cfg.state_dim, cfg.action_dim, cfg.hidden_size, cfg.num_hidden_layers) == (6, 3, 32, 2)
    assert cfg.normalization_mode == "identity"          # LeRobot's processors normalise
    assert cfg.context_dim is None and cfg.extra["tasks"] == []
    explicit = convert.decoder_config(plugin_cfg(decoder_type=decoder, num_inference_steps=4,
                                                 flow_prediction="velocity"), 6, 3)
    assert (explicit.num_inference_timesteps, explicit.flow_prediction) == (4, "velocity")


def test_decoder_config_tasks_become_a_context_token_width():
    assert convert.decoder_config(plugin_cfg(tasks=TASKS), 6, 3).context_dim == 2
    assert convert.decoder_config(plugin_cfg(tasks=TASKS[:1]), 6, 3).context_dim is None


@pytest.mark.parametrize("over, field", [({"chunk_size": 0}, "policy.chunk_size"),
                                         ({"num_inference_steps": -1}, "policy.num_inference_steps"),
                                         ({"decoder_type": "flow"}, "policy.decoder_type"),
                                         ({"n_action_steps": 20}, "policy.n_action_steps")])
def test_decoder_config_errors_name_the_plugin_field(over, field):
    with pytest.raises(ValueError) as err:
        convert.decoder_config(plugin_cfg(**over), 6, 3)
    assert str(err.value).startswith(field + ":"), str(err.value)


def test_feature_dims_need_state_and_action():
    ft = lambda *shape: SimpleNamespace(shape=shape)  # noqa: E731
    feats = {"observation.state": ft(6), "observation.images.top": ft(3, 64, 64), "observation.environment_state": ft(9)}
    assert convert.feature_dims(feats, {"action": ft(3)}) == (6, 3)
    assert convert.unused_inputs(feats) == ["observation.environment_state"]     # cameras are read
    line = convert.unused_inputs_message(convert.unused_inputs(feats))
    assert "observation.environment_state" in line and "\n" not in line
    assert convert.unused_inputs_message([]) is None
    with pytest.raises(ValueError, match=r"input_features\['observation.state'\]"):
        convert.feature_dims({"observation.images.top": ft(3, 64, 64)}, {"action": ft(3)})
    with pytest.raises(ValueError, match=r"output_features\['action'\].*\(2, 3\)"):
        convert.feature_dims(feats, {"action": ft(2, 3)})


def test_hold_last_action_fills_padding_with_the_last_real_action():
    actions = torch.arange(8.0).reshape(2, 4, 1)                          # [B=2, H=4, D=1]
    pad = torch.tensor([[False, False, True, True], [False, False, False, False]])
    held = convert.hold_last_action(actions, pad)
    assert held[:, :, 0].tolist() == [[0, 1, 1, 1], [4, 5, 6, 7]]
    assert convert.hold_last_action(actions, None) is actions
    with pytest.raises(ValueError, match="action_is_pad.*\\[2, 4\\]"):
        convert.hold_last_action(actions, pad[:, :3])


def test_to_core_batch_converts_keys_and_task_strings():
    state, action = torch.randn(3, 6), torch.randn(3, 4, 2)
    pad = torch.tensor([[False] * 3 + [True]] * 3)
    out = convert.to_core_batch({"observation.state": state, "action": action, "action_is_pad": pad,
                                 "task": ["lift the cube", "push the block", "lift the cube"]}, TASKS, 6, True)
    assert torch.equal(out["state"], state)
    assert torch.equal(out["actions"][:, 3], action[:, 2]) and torch.equal(out["actions"][:, :3], action[:, :3])
    assert out["context"].shape == (3, 1, 2) and out["context"][:, 0].argmax(-1).tolist() == [1, 0, 1]
    single = convert.to_core_batch({"observation.state": state[:1, None], "task": "push the block"}, TASKS, 6, False)
    assert single["state"].shape == (1, 6) and single["context"][0, 0].tolist() == [1.0, 0.0]
    assert "context" not in convert.to_core_batch({"observation.state": state}, TASKS[:1], 6, False)


@pytest.mark.parametrize("batch, match", [
    ({"task": ["push the block"]}, r"batch\['observation.state'\]: missing"),
    ({"observation.state": torch.randn(1, 5), "task": ["push the block"]}, r"\[B, 6\], got \[1, 5\]"),
    ({"observation.state": torch.randn(1, 6)}, r"batch\['task'\]: missing"),
    ({"observation.state": torch.randn(1, 6), "task": ["open the door"]}, r"unknown task\(s\) \['open the door'\]"),
    ({"observation.state": torch.randn(2, 6), "task": ["push the block"]}, r"expected 2 task strings"),
])
def test_to_core_batch_rejects_bad_input_in_one_line(batch, match):
    with pytest.raises(ValueError, match=match) as err:
        convert.to_core_batch(batch, TASKS, 6, False)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("over, match", [
    ({"observation.state": torch.full((2, 6), float("nan"))}, r"^batch\['observation.state'\]: contains NaN or Inf"),
    ({"observation.state": torch.zeros(2, 6, dtype=torch.long)}, r"^batch\['observation.state'\]: expected a floating-point"),
    ({"action": torch.randn(2, 8, 4)}, r"^batch\['action'\]: expected shape \[2, 8, 3\] \(batch, chunk_size, action dim\), got \[2, 8, 4\]"),
    ({"action": torch.randn(2, 5, 3)}, r"^batch\['action'\]: expected shape \[2, 8, 3\]"),
    ({"action": torch.full((2, 8, 3), float("inf"))}, r"^batch\['action'\]: contains NaN or Inf"),
])
def test_bad_training_batches_name_lerobots_keys(over, match):
    batch = {"observation.state": torch.randn(2, 6), "action": torch.randn(2, 8, 3), **over}
    with pytest.raises(ValueError, match=match):
        convert.to_core_batch(batch, [], 6, True, action_shape=(8, 3))


def test_meanflow_target_reaches_the_core_config():
    assert convert.decoder_config(plugin_cfg(decoder_type="mean_flow", meanflow_target="split"), 6, 3).meanflow_target == "split"


CAM_KEYS = ["observation.images.wrist", "observation.images.top"]


def test_camera_keys_keep_the_feature_order_and_reach_the_core_config():
    ft = lambda *shape: SimpleNamespace(shape=shape)  # noqa: E731
    feats = {"observation.images.wrist": ft(3, 48, 64), "observation.state": ft(6), "observation.images.top": ft(3, 32, 32)}
    assert convert.camera_keys(feats) == CAM_KEYS
    single = {"observation.state": ft(6), "observation.image": ft(3, 96, 96)}              # pusht, xarm
    assert convert.camera_keys(single) == ["observation.image"] and convert.unused_inputs(single) == []
    cfg = convert.decoder_config(plugin_cfg(image_size=24, image_encoder="resnet18", image_tokens_per_camera=2,
                                            freeze_image_encoder=True, image_shift=2), 6, 3, convert.camera_keys(feats))
    assert cfg.cameras == tuple(CAM_KEYS) and (cfg.image_size, cfg.image_encoder) == (24, "resnet18")
    assert (cfg.image_tokens_per_camera, cfg.freeze_image_encoder, cfg.image_shift) == (2, True, 2)
    with pytest.raises(ValueError, match=r"^policy.image_size: expected at least 16 pixels, got 4$"):
        convert.decoder_config(plugin_cfg(image_size=4), 6, 3, CAM_KEYS)


def test_camera_frames_are_stacked_in_config_order_and_resized():
    g = torch.Generator().manual_seed(0)
    wrist, top = torch.rand(2, 3, 48, 64, generator=g), torch.rand(2, 1, 3, 16, 16, generator=g)
    out = convert.to_core_batch({"observation.state": torch.randn(2, 6), "observation.images.wrist": wrist,
                                 "observation.images.top": top}, [], 6, False, CAM_KEYS, 16)
    images = out["images"]                                                      # [B, N_cam, 3, S, S]
    assert images.shape == (2, 2, 3, 16, 16) and images.dtype == torch.float32
    assert torch.equal(images[:, 1], top[:, 0])                                  # already 16²: untouched
    torch.testing.assert_close(images[:, 0].mean((-1, -2)), wrist.mean((-1, -2)), atol=0.02, rtol=0)
    assert 0 <= float(images.min()) and float(images.max()) <= 1
    assert "images" not in convert.to_core_batch({"observation.state": torch.randn(2, 6)}, [], 6, False)


def test_camera_frames_outside_unit_range_are_refused_before_resizing_hides_them():
    batch = {"observation.state": torch.randn(2, 6), "observation.images.wrist": torch.rand(2, 3, 16, 16),
             "observation.images.top": torch.randn(2, 3, 32, 32) * 3}         # mean-std normalised frames
    with pytest.raises(ValueError, match=r"^batch\['observation.images.top'\]: expected pixels in \[0, 1\]"):
        convert.to_core_batch(batch, [], 6, False, CAM_KEYS, 16)


@pytest.mark.parametrize("frames, match", [
    (None, r"batch\['observation.images.top'\]: expected camera frames of shape \[2, 3, H, W\] \(float in \[0, 1\]\), got nothing"),
    (torch.rand(2, 16, 16, 3), r"got \[2, 16, 16, 3\]"),
    (torch.rand(3, 3, 16, 16), r"expected camera frames of shape \[2, 3, H, W\].*got \[3, 3, 16, 16\]"),
])
def test_bad_camera_frames_are_one_line(frames, match):
    batch = {"observation.state": torch.randn(2, 6), "observation.images.wrist": torch.rand(2, 3, 16, 16)}
    if frames is not None:
        batch["observation.images.top"] = frames
    with pytest.raises(ValueError, match=match) as err:
        convert.to_core_batch(batch, [], 6, False, CAM_KEYS, 16)
    assert "\n" not in str(err.value)


def test_core_camera_policy_trains_and_samples_on_converted_lerobot_batches():
    torch.manual_seed(0)
    cfg = convert.decoder_config(plugin_cfg(chunk_size=8, image_size=16), 6, 3, CAM_KEYS)
    policy = CorePolicy(cfg)
    g = torch.Generator().manual_seed(1)
    lerobot = {"observation.state": torch.randn(4, 6, generator=g), "action": torch.randn(4, 8, 3, generator=g),
               "observation.images.wrist": torch.rand(4, 3, 32, 32, generator=g),
               "observation.images.top": torch.rand(4, 3, 16, 16, generator=g)}
    core = convert.to_core_batch(lerobot, [], 6, True, CAM_KEYS, 16)
    policy.compute_loss(core).loss.backward()
    assert policy.model.image_encoder.backbone.net[0].weight.grad.abs().sum() > 0
    policy.eval()
    noise = torch.randn(4, 8, 3, generator=g)
    first = policy.sample(core, noise=noise).actions
    dark = dict(core, images=core["images"] * 0.1)
    assert (policy.sample(dark, noise=noise).actions - first).abs().max() > 1e-4


def test_task_list_orders_by_task_index():
    assert convert.task_list({1: "b", 0: "a"}) == ["a", "b"]
    assert convert.task_list(None) == []
    pq = pytest.importorskip("pyarrow.parquet")
    rows = pq.read_table(FIXTURE / "meta" / "tasks.parquet").to_pylist()
    assert convert.task_list({r["task_index"]: r["__index_level_0__"] for r in rows}) == TASKS


def _fixture_batches(horizon: int, batch_size: int, gen: torch.Generator):
    """LeRobot-style normalised batches from the v30 fixture: chunks of `horizon` actions that
    LeRobot's `action_delta_indices` would give, padded past each episode's end."""
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(FIXTURE / "data" / "chunk-000" / "file-000.parquet").to_pydict()
    stats = json.loads((FIXTURE / "meta" / "stats.json").read_text())
    norm = lambda x, k: (x - torch.tensor(stats[k]["mean"])) / torch.tensor(stats[k]["std"])  # noqa: E731
    state = norm(torch.tensor(table["observation.state"]), "observation.state")      # [N, 6]
    action = norm(torch.tensor(table["action"]), "action")                           # [N, 3]
    episode = torch.tensor(table["episode_index"])                                    # [N]
    last = torch.tensor([int((episode == e).nonzero().max()) for e in episode.tolist()])
    rows = torch.randperm(len(state), generator=gen)[:batch_size]                    # [B]
    want = rows[:, None] + torch.arange(horizon)                                      # [B, H]
    pad = want > last[rows, None]
    idx = torch.minimum(want, last[rows, None])
    return {"observation.state": state[rows], "action": action[idx], "action_is_pad": pad,
            "task": [TASKS[i] for i in torch.tensor(table["task_index"])[rows].tolist()]}


@pytest.mark.parametrize("decoder", ["DDPM", "flow_matching", "mean_flow"])
def test_core_policy_learns_from_converted_fixture_batches(decoder, gen):
    torch.manual_seed(0)
    cfg = convert.decoder_config(plugin_cfg(decoder_type=decoder, chunk_size=8, tasks=TASKS), 6, 3)
    policy = CorePolicy(cfg)
    batch = _fixture_batches(8, 32, gen)
    assert batch["action_is_pad"].any()                     # the batch reaches past episode ends
    core = convert.to_core_batch(batch, TASKS, 6, True)
    policy.compute_loss(core).loss.backward()
    assert all(p.grad is not None for n, p in policy.named_parameters() if n.startswith("model."))
    if decoder == "flow_matching":                          # the same noise before and after: a fair comparison
        fixed = lambda: policy.compute_loss(core, torch.Generator().manual_seed(1)).loss.item()  # noqa: E731
        before, opt = fixed(), torch.optim.Adam(policy.parameters(), lr=3e-3)
        for _ in range(20):
            opt.zero_grad()
            policy.compute_loss(core).loss.backward()
            opt.step()
        assert fixed() < 0.8 * before
    policy.eval()
    chunk = policy.predict_action_chunk(convert.to_core_batch(batch, TASKS, 6, False), steps=2)
    assert chunk.shape == (32, 8, 3) and torch.isfinite(chunk).all()


@pytest.mark.skipif(HAS_LEROBOT, reason="checks the package without LeRobot")
def test_plugin_imports_without_lerobot_and_names_what_is_missing():
    import lerobot_policy_action_decoder as plugin

    with pytest.raises(ImportError, match=r"lerobot>=0\.4\.3,<0\.7"):
        plugin.ActionDecoderPolicy


# ---------------------------------------------------------------------- with LeRobot
lerobot_only = pytest.mark.skipif(not HAS_LEROBOT, reason="LeRobot is not installed (scripts/lerobot_integration.sh)")


@pytest.fixture
def toy_root(tmp_path):
    root = tmp_path / "v30_toy"
    shutil.copytree(FIXTURE, root)
    return root


def _lerobot_policy(root, **over):
    from lerobot.configs.types import FeatureType
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy, make_policy_config, make_pre_post_processors

    meta = LeRobotDatasetMetadata("local/v30_toy", root=root)
    cfg = make_policy_config("action_decoder", device="cpu", hidden_size=32, num_hidden_layers=2, chunk_size=8,
                             push_to_hub=False, **over)
    policy = make_policy(cfg, ds_meta=meta)
    pre, post = make_pre_post_processors(cfg, dataset_stats=meta.stats)
    assert all(ft.type in (FeatureType.STATE, FeatureType.ACTION) for ft in
               {**cfg.input_features, **cfg.output_features}.values())
    return policy, pre, post, meta


@lerobot_only
def test_lerobot_resolves_the_plugin_type():
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    from lerobot_policy_action_decoder import ActionDecoderConfig, ActionDecoderPolicy

    assert PreTrainedConfig.get_choice_class("action_decoder") is ActionDecoderConfig
    assert get_policy_class("action_decoder") is ActionDecoderPolicy
    cfg = ActionDecoderConfig(device="cpu")
    assert cfg.action_delta_indices == list(range(16)) and cfg.observation_delta_indices is None
    assert cfg.get_optimizer_preset().lr == 1e-3 and cfg.get_optimizer_preset().grad_clip_norm == 1.0
    with pytest.raises(ValueError, match=r"^policy.chunk_size:"):
        ActionDecoderConfig(device="cpu", chunk_size=0)


@lerobot_only
@pytest.mark.parametrize("decoder", ["DDPM", "flow_matching", "mean_flow"])
def test_lerobot_dataset_batch_trains_and_reloads(decoder, toy_root, tmp_path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_policy_action_decoder import ActionDecoderPolicy

    torch.manual_seed(0)
    policy, pre, post, meta = _lerobot_policy(toy_root, decoder_type=decoder)
    assert policy.config.tasks == TASKS and policy.decoder.config.context_dim == 2
    ds = LeRobotDataset("local/v30_toy", root=toy_root, delta_timestamps=resolve_delta_timestamps(policy.config, meta))
    batch = pre(next(iter(torch.utils.data.DataLoader(ds, batch_size=16, shuffle=True))))
    assert batch["action"].shape == (16, 8, 3) and batch["action_is_pad"].shape == (16, 8)
    loss, info = policy.forward(batch)
    loss.backward()
    assert torch.isfinite(loss) and info["loss"] == pytest.approx(loss.item())

    policy.save_pretrained(tmp_path / "ckpt")
    pre.save_pretrained(tmp_path / "ckpt")
    post.save_pretrained(tmp_path / "ckpt")
    assert json.loads((tmp_path / "ckpt" / "config.json").read_text())["type"] == "action_decoder"
    again = ActionDecoderPolicy.from_pretrained(tmp_path / "ckpt")
    assert again.config.tasks == TASKS
    for k, v in policy.state_dict().items():
        assert torch.equal(v, again.state_dict()[k]), k
    pre2, post2 = make_pre_post_processors(again.config, pretrained_path=str(tmp_path / "ckpt"))
    frame = ds[0]
    obs = pre2({"observation.state": frame["observation.state"], "task": frame["task"]})
    action = post2(again.select_action(obs))
    assert action.shape == (1, 3) and torch.isfinite(action).all()
    noise = torch.randn(1, 8, 3)
    assert torch.equal(policy.eval().predict_action_chunk(obs, noise=noise), again.predict_action_chunk(obs, noise=noise))


@lerobot_only
def test_lerobot_policy_reaches_the_sde_and_its_log_probs(toy_root):
    policy, pre, _, _ = _lerobot_policy(toy_root, decoder_type="mean_flow")
    obs = pre({"observation.state": torch.randn(6), "task": "lift the cube"})
    out = policy.eval().predict_action_chunk(obs, sampler="sde", return_logprob=True, steps=4)
    assert out.actions.shape == (1, 8, 3) and out.step_log_probs.shape == (1, 4)
    rescored = policy.chain_log_prob(obs, out.chain, out.grid)
    torch.testing.assert_close(rescored, out.step_log_probs)
    with pytest.raises(ValueError, match=r"unknown task\(s\) \['open the door'\]"):
        policy.select_action(pre({"observation.state": torch.randn(6), "task": "open the door"}))


@lerobot_only
def test_lerobot_policy_encodes_its_cameras_and_names_inputs_it_does_not_use(caplog):
    from lerobot.configs.types import FeatureType, PolicyFeature

    from lerobot_policy_action_decoder import ActionDecoderConfig, ActionDecoderPolicy

    cfg = ActionDecoderConfig(device="cpu", hidden_size=32, num_hidden_layers=2, image_size=16, input_features={
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
        "observation.images.top": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 32, 32)),
        "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(9,))},
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(3,))})
    with caplog.at_level("WARNING"):
        policy = ActionDecoderPolicy(cfg)
    assert policy.decoder.config.cameras == ("observation.images.top",)
    lines = [r.getMessage() for r in caplog.records if "observation.environment_state" in r.getMessage()]
    assert len(lines) == 1 and "\n" not in lines[0] and "observation.images.top" not in lines[0]
    batch = {"observation.state": torch.randn(2, 6), "observation.images.top": torch.rand(2, 3, 32, 32),
             "action": torch.randn(2, 16, 3), "action_is_pad": torch.zeros(2, 16, dtype=torch.bool)}
    loss, _ = policy.forward(batch)
    loss.backward()
    assert policy.decoder.model.image_encoder.proj.weight.grad.abs().sum() > 0


@lerobot_only
def test_lerobot_predict_action_chunk_returns_a_chunk_whatever_flow_sde_return_logprob_says(toy_root):
    policy, pre, _, _ = _lerobot_policy(toy_root, flow_sde_use=True, flow_sde_return_logprob=True)
    obs = pre({"observation.state": torch.randn(6), "task": "lift the cube"})
    chunk = policy.eval().predict_action_chunk(obs)
    assert isinstance(chunk, torch.Tensor) and chunk.shape == (1, 8, 3)


@lerobot_only
def test_lerobot_config_refuses_normalised_camera_frames():
    from lerobot.configs.types import NormalizationMode

    from lerobot_policy_action_decoder import ActionDecoderConfig

    mapping = {"VISUAL": NormalizationMode.MEAN_STD, "STATE": NormalizationMode.MEAN_STD,
               "ACTION": NormalizationMode.MEAN_STD}
    with pytest.raises(ValueError, match=r"^policy.normalization_mapping: expected VISUAL: IDENTITY"):
        ActionDecoderConfig(device="cpu", normalization_mapping=mapping)


@lerobot_only
def test_lerobot_single_task_policy_refuses_a_dataset_of_other_tasks(toy_root):
    with pytest.raises(ValueError, match=r"^policy.tasks: the dataset's tasks \['lift the cube'\] are not among"):
        _lerobot_policy(toy_root, tasks=["push the block"])


@lerobot_only
def test_lerobot_reload_builds_the_core_policy_without_its_pretrained_encoder_source(toy_root, tmp_path, monkeypatch):
    from lerobot_policy_action_decoder import ActionDecoderPolicy, modeling_action_decoder

    policy, _, _, _ = _lerobot_policy(toy_root)
    policy.save_pretrained(tmp_path / "ckpt")
    seen = []
    real = modeling_action_decoder.CorePolicy

    def recording(config, load_pretrained=True):
        seen.append(load_pretrained)
        return real(config, load_pretrained=load_pretrained)

    monkeypatch.setattr(modeling_action_decoder, "CorePolicy", recording)
    ActionDecoderPolicy.from_pretrained(tmp_path / "ckpt")
    ActionDecoderPolicy(policy.config)
    assert seen == [False, True]


@lerobot_only
@pytest.mark.parametrize("decoder", ["DDPM", "flow_matching", "mean_flow"])
def test_a_converted_library_checkpoint_runs_in_lerobot_as_in_the_library(decoder, tmp_path):
    """`action-decoder convert --to lerobot`, loaded by LeRobot's own from_pretrained and processors:
    the same chunk for the same noise (to LeRobot's eps), actions clamped by the postprocessor; and back."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    from action_decoder.cli import main

    torch.manual_seed(0)
    stats = {"state": {"mean": [0.1, -0.2, 0.3, 1.0], "std": [0.5, 0.2, 1.5, 0.004],
                       "min": [-1.0, -1.0, -3.0, 0.99], "max": [1.0, 0.5, 3.0, 1.01]},
             "actions": {"mean": [0.05, 0.05, 1.2], "std": [0.5, 0.1, 0.8], "min": [-0.8, -0.2, 0.0],
                         "max": [0.9, 0.3, 2.5]}}
    cfg = DecoderConfig(decoder_type=decoder, state_dim=4, action_dim=3, action_chunk_size=8, n_action_steps=4,
                        hidden_size=32, num_hidden_layers=2, num_inference_timesteps=3, extra={"tasks": ["reach"]})
    lib = CorePolicy(cfg, stats)
    with torch.no_grad():
        for p in lib.model.head.parameters():
            p.mul_(20.0)                               # chunks far beyond the data's range
    lib.save_pretrained(tmp_path / "lib")
    assert main(["convert", "--checkpoint", str(tmp_path / "lib"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "lr")]) == 0
    path = str(tmp_path / "lr")
    pcfg = PreTrainedConfig.from_pretrained(path)
    policy = get_policy_class(pcfg.type).from_pretrained(path, config=pcfg).eval()
    pre, post = make_pre_post_processors(pcfg, pretrained_path=path)
    state = torch.tensor(stats["state"]["mean"]) + 0.3 * torch.randn(5, 4) * torch.tensor(stats["state"]["std"])
    noise = torch.randn(5, 8, 3)
    theirs = post(policy.predict_action_chunk(pre({"observation.state": state, "task": ["reach"] * 5}), noise=noise))
    ours = lib.eval().predict_action_chunk({"state": state}, noise=noise)
    torch.testing.assert_close(theirs, ours, atol=1e-5, rtol=1e-5)
    low, high = torch.tensor(stats["actions"]["min"]), torch.tensor(stats["actions"]["max"])
    assert bool(((theirs >= low) & (theirs <= high)).all())
    free = CorePolicy.from_pretrained(tmp_path / "lib")
    free.config.clip_actions = False
    assert bool(((free.predict_action_chunk({"state": state}, noise=noise) > high)).any())
    # LeRobot's own save of the loaded policy and processors converts back to the same library weights.
    policy.save_pretrained(tmp_path / "resaved")
    pre.save_pretrained(tmp_path / "resaved")
    post.save_pretrained(tmp_path / "resaved")
    assert main(["convert", "--checkpoint", str(tmp_path / "resaved"), "--to", "library",
                 "--output-dir", str(tmp_path / "back")]) == 0
    back = CorePolicy.from_pretrained(tmp_path / "back")
    for k, v in lib.state_dict().items():
        assert torch.equal(v, back.state_dict()[k]), k
    assert torch.equal(back.predict_action_chunk({"state": state}, noise=noise), ours)


@lerobot_only
def test_lerobot_postprocessor_clamps_to_the_dataset_range_unless_clip_actions_is_off(toy_root, tmp_path):
    from lerobot.policies.factory import make_pre_post_processors

    from action_decoder.cli import main

    policy, pre, post, meta = _lerobot_policy(toy_root)
    low, high = (torch.as_tensor(meta.stats["action"][k], dtype=torch.float32) for k in ("min", "max"))
    assert torch.equal(post(torch.full((3, 3), 50.0)), high.expand(3, -1))     # normalised actions 50 std out
    policy.save_pretrained(tmp_path / "ckpt")
    pre.save_pretrained(tmp_path / "ckpt")
    post.save_pretrained(tmp_path / "ckpt")
    _, post2 = make_pre_post_processors(policy.config, pretrained_path=str(tmp_path / "ckpt"))
    assert torch.equal(post2(torch.full((2, 3), -50.0)), low.expand(2, -1))
    _, _, free, _ = _lerobot_policy(toy_root, clip_actions=False)
    assert bool((free(torch.full((2, 3), 50.0)) > high).all())
    # A policy trained by lerobot-train converts to a library checkpoint that clamps alike.
    assert main(["convert", "--checkpoint", str(tmp_path / "ckpt"), "--to", "library",
                 "--output-dir", str(tmp_path / "lib")]) == 0
    lib = CorePolicy.from_pretrained(tmp_path / "lib")
    assert lib.config.clip_actions and lib.config.extra["tasks"] == TASKS
    torch.testing.assert_close(lib.normalizers["actions"].max, high)
    frame = {"observation.state": torch.zeros(2, 6), "task": TASKS}
    noise = torch.randn(2, 8, 3)
    theirs = post2(policy.eval().predict_action_chunk(pre(frame), noise=noise))
    context = torch.nn.functional.one_hot(torch.arange(2), 2).float()[:, None]
    ours = lib.predict_action_chunk({"state": frame["observation.state"], "context": context}, noise=noise)
    torch.testing.assert_close(theirs, ours, atol=1e-4, rtol=1e-4)


@lerobot_only
def test_a_checkpoint_config_with_a_revision_pin_field_loads(toy_root, tmp_path):
    """LeRobot >= 0.6 writes `pretrained_revision` into config.json; such a checkpoint loads on 0.4.x too."""
    from lerobot.configs.policies import PreTrainedConfig

    policy, _, _, _ = _lerobot_policy(toy_root)
    policy.save_pretrained(tmp_path / "ckpt")
    config = json.loads((tmp_path / "ckpt" / "config.json").read_text())
    config["pretrained_revision"] = None
    (tmp_path / "ckpt" / "config.json").write_text(json.dumps(config))
    cfg = PreTrainedConfig.from_pretrained(tmp_path / "ckpt")
    assert cfg.type == "action_decoder" and cfg.pretrained_revision is None and cfg.tasks == TASKS


@lerobot_only
def test_lerobot_rtc_rollout_engine_drives_the_plugin_through_its_queue(toy_root):
    """LeRobot 0.6's RTC rollout path without a robot: its acceptance test, its action queue's left-over
    (zero-padded to the execution horizon as its engine pads it) and the merge after the delay."""
    engine = pytest.importorskip("lerobot.rollout.inference.rtc", reason="LeRobot < 0.6 has no RTC rollout engine")
    from lerobot.configs.types import RTCAttentionSchedule
    from lerobot.policies.rtc import ActionQueue, RTCConfig

    torch.manual_seed(0)
    policy, pre, post, _ = _lerobot_policy(toy_root, decoder_type="flow_matching")
    assert engine.supports_rtc_inference(policy.eval())
    assert not engine.supports_rtc_inference(_lerobot_policy(toy_root, decoder_type="DDPM")[0])
    rtc = RTCConfig(execution_horizon=6, prefix_attention_schedule=RTCAttentionSchedule.EXP, max_guidance_weight=5.0)
    policy.config.rtc_config = rtc                                   # what lerobot-rollout sets
    queue = ActionQueue(rtc)
    obs = pre({"observation.state": torch.randn(6), "task": "lift the cube"})
    first = policy.predict_action_chunk(obs, inference_delay=0, prev_chunk_left_over=queue.get_left_over())
    queue.merge(first.squeeze(0), post(first).squeeze(0), 0, 0)
    executed = [queue.get() for _ in range(5)]                       # the robot runs 5 of the 8 actions
    assert all(a.shape == (3,) for a in executed)
    left = queue.get_left_over()                                     # [3, D], normalised
    prev = engine._normalize_prev_actions_length(left, target_steps=rtc.execution_horizon)        # [6, D]
    chunk = policy.predict_action_chunk(obs, inference_delay=2, prev_chunk_left_over=prev)
    during = [queue.get() for _ in range(2)]                          # the robot goes on while it samples
    assert chunk.shape == (1, 8, 3) and torch.equal(chunk[0, :2], left[:2])
    torch.testing.assert_close(torch.stack(during), post(chunk)[0, :2])   # the committed actions, unchanged
    queue.merge(chunk.squeeze(0), post(chunk).squeeze(0), 2, 5)
    assert queue.qsize() == 6 and torch.equal(queue.get_left_over(), chunk[0, 2:])


LEROBOT_VIEW = """
import json, numpy as np
from action_decoder.envs.render import check_rendering
check_rendering()
from lerobot.envs.metaworld import MetaworldEnv
from action_decoder.envs.lerobot_view import LeRobotCamera, agent_pos
env = MetaworldEnv("door-close-v3", obs_type="pixels_agent_pos")
obs, _ = env.reset(seed=0)
for _ in range(3):
    obs, *_ = env.step(np.array([0.3, -0.2, 0.1, 0.5], np.float32))
rig = LeRobotCamera()
ours = rig(env._env)["observation.image"]
print(json.dumps({"pixels": bool(np.array_equal(ours, obs["pixels"])),
                  "state": bool(np.array_equal(agent_pos(env._env._get_obs()), obs["agent_pos"].astype(np.float32)))}))
rig.close()
"""


@lerobot_only
def test_record_layout_lerobot_observes_exactly_what_lerobots_metaworld_env_does():
    """`envs.lerobot_view` against LeRobot's own MetaworldEnv, in the same simulator state: the same pixels
    (corner2 moved, 480 px, turned 180°) and the same agent position."""
    import os
    import subprocess

    pytest.importorskip("metaworld")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = subprocess.run([sys.executable, "-c", LEROBOT_VIEW], env=env, capture_output=True, text=True, timeout=600)
    if res.returncode != 0 and "rendering" in res.stderr.lower():
        pytest.skip(f"offscreen rendering is unavailable here: {res.stderr.strip().splitlines()[-1]}")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.strip().splitlines()[-1]) == {"pixels": True, "state": True}


# ---------------------------------------------------------------------- observation history (n_obs_steps)
def test_history_batches_keep_their_step_axis_and_train_a_camera_policy():
    """A dataset batch of `observation_delta_indices` = [-1, 0] keeps its steps ([B, 2, S], frames [B, 2, 3,
    H, W] → images [B, 2, N_cam, 3, S, S]); an environment's single observation stays one for select_action."""
    torch.manual_seed(0)
    cfg = convert.decoder_config(plugin_cfg(chunk_size=8, image_size=16, n_obs_steps=2), 6, 3, CAM_KEYS)
    assert cfg.n_obs_steps == 2
    policy = CorePolicy(cfg)
    g = torch.Generator().manual_seed(1)
    lerobot = {"observation.state": torch.randn(4, 2, 6, generator=g), "action": torch.randn(4, 8, 3, generator=g),
               "observation.images.wrist": torch.rand(4, 2, 3, 32, 32, generator=g),
               "observation.images.top": torch.rand(4, 2, 3, 16, 16, generator=g)}
    core = convert.to_core_batch(lerobot, [], 6, True, CAM_KEYS, 16, (8, 3), n_obs_steps=2)
    assert core["state"].shape == (4, 2, 6) and core["images"].shape == (4, 2, 2, 3, 16, 16)
    assert torch.equal(core["images"][:, 1, 1], lerobot["observation.images.top"][:, 1])
    policy.compute_loss(core).loss.backward()
    assert policy.model.image_step_embed.grad.abs().sum() > 0
    single = {"observation.state": lerobot["observation.state"][:, -1],
              **{k: lerobot[k][:, -1] for k in CAM_KEYS}}
    one = convert.to_core_batch(single, [], 6, False, CAM_KEYS, 16, n_obs_steps=2)
    assert one["state"].shape == (4, 6) and one["images"].shape == (4, 2, 3, 16, 16)
    steps_of_one = {k: v[:, None] for k, v in single.items()}                  # [B, 1, ...]: one observation too
    assert convert.to_core_batch(steps_of_one, [], 6, False, CAM_KEYS, 16, n_obs_steps=2)["state"].shape == (4, 6)
    assert policy.eval().select_action(one).shape == (4, 3)
    assert policy.history.push({"state": one["state"]})["observation_is_pad"].tolist() == [[False, False]] * 4
    with pytest.raises(ValueError, match=r"^batch\['observation.state'\]: expected shape \[B, 6\] or \[B, 2, 6\] "
                                         r"\(n_obs_steps=2\), got \[4, 3, 6\]$"):
        convert.to_core_batch({**lerobot, "observation.state": torch.randn(4, 3, 6)}, [], 6, True, CAM_KEYS, 16,
                              n_obs_steps=2)


@lerobot_only
def test_lerobot_history_comes_from_delta_indices_and_select_action_pads_with_the_first_observation(toy_root):
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from lerobot_policy_action_decoder import ActionDecoderConfig

    assert ActionDecoderConfig(device="cpu", n_obs_steps=2).observation_delta_indices == [-1, 0]
    assert ActionDecoderConfig(device="cpu", n_obs_steps=3).observation_delta_indices == [-2, -1, 0]
    with pytest.raises(ValueError, match=r"^policy.n_obs_steps: expected a positive integer"):
        ActionDecoderConfig(device="cpu", n_obs_steps=0)
    torch.manual_seed(0)
    policy, pre, post, meta = _lerobot_policy(toy_root, n_obs_steps=2)
    assert policy.decoder.config.n_obs_steps == 2
    ds = LeRobotDataset("local/v30_toy", root=toy_root, delta_timestamps=resolve_delta_timestamps(policy.config, meta))
    first = ds[0]                                        # an episode's first frame: itself twice, marked as padding
    assert first["observation.state"].shape == (2, 6) and first["observation.state_is_pad"].tolist() == [True, False]
    assert torch.equal(first["observation.state"][0], first["observation.state"][1])
    batch = pre(next(iter(torch.utils.data.DataLoader(ds, batch_size=8, shuffle=True))))
    assert batch["observation.state"].shape == (8, 2, 6)
    loss, _ = policy.forward(batch)
    loss.backward()
    assert torch.isfinite(loss)
    policy.eval().reset()
    seen = []
    sample = policy.decoder.sample
    policy.decoder.sample = lambda b, **kw: (seen.append(b["state"].clone()), sample(b, **kw))[1]
    for i in range(5):                                   # a chunk at calls 0 and 4 (n_action_steps = 4)
        frame = ds[i]
        obs = pre({"observation.state": frame["observation.state"][-1], "task": frame["task"]})
        assert post(policy.select_action(obs)).shape == (1, 3)
    assert seen[0].shape == (1, 2, 6) and torch.equal(seen[0][0, 0], seen[0][0, 1])
    assert not torch.equal(seen[1][0, 0], seen[1][0, 1])
