"""DecoderConfig: GO-1 names and defaults, validation naming the field, GO-1 import, JSON."""

import json
import types

import pytest

from action_decoder import DecoderConfig
from action_decoder.config import ADDED_FIELDS, CONFIG_FORMAT_VERSION, OLDEST_FORMAT_VERSION


def test_go1_defaults():
    c = DecoderConfig()
    assert (c.decoder_type, c.num_train_timesteps, c.beta_schedule, c.prediction_type) == (
        "flow_matching", 1000, "squaredcos_cap_v2", "sample")
    assert c.flow_sde_use is False and c.default_sampler == "ode"
    assert (c.num_inference_timesteps, c.flow_sde_num_steps) == (10, 10)
    assert DecoderConfig(decoder_type="flow_matching", flow_sde_use=True).default_sampler == "sde"


@pytest.mark.parametrize("kwargs, field", [
    ({"decoder_type": "unknown"}, "decoder_type"),
    ({"prediction_type": "v"}, "prediction_type"),
    ({"num_inference_timesteps": -1}, "num_inference_timesteps"),
    ({"flow_sde_num_steps": 0}, "flow_sde_num_steps"),
    ({"num_train_timesteps": 0}, "num_train_timesteps"),
    ({"beta_schedule": "cosine"}, "beta_schedule"),
    ({"flow_sde_mode": "wild"}, "flow_sde_mode"),
    ({"meanflow_time_dist": "beta"}, "meanflow_time_dist"),
    ({"flow_prediction": "x0"}, "flow_prediction"),
    ({"flow_sde_sigma_init": 0.0}, "flow_sde_sigma_init"),
    ({"flow_sde_clip_t": 1.5}, "flow_sde_clip_t"),
    ({"meanflow_ratio_r_neq_t": 1.2}, "meanflow_ratio_r_neq_t"),
    ({"num_attention_heads": 3}, "hidden_size"),
    ({"num_key_value_heads": 3}, "num_key_value_heads"),
    ({"n_action_steps": 32}, "n_action_steps"),
    ({"vlm_num_layers": 2}, "vlm_num_layers"),
    ({"decoder_type": "DDPM", "flow_sde_use": True}, "flow_sde_use"),
    ({"action_dim": 2.5}, "action_dim"),
])
def test_invalid_values_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        DecoderConfig(**kwargs)


def test_error_lists_allowed_values():
    with pytest.raises(ValueError, match=r"expected one of \['DDPM', 'flow_matching', 'mean_flow'\], got 'unknown'"):
        DecoderConfig(decoder_type="unknown")


def test_from_go1_object_and_dict():
    go1 = types.SimpleNamespace(decoder_type="mean_flow", num_inference_timesteps=2, flow_sde_use=True,
                                flow_sde_s_churn=0.5, action_chunk_size=30, state_token_num=3,
                                ctrl_freqs=30, some_vlm_option="ignored")
    c = DecoderConfig.from_go1(go1, action_dim=7)
    assert (c.decoder_type, c.num_inference_timesteps, c.flow_sde_use, c.flow_sde_s_churn,
            c.action_chunk_size, c.action_dim) == ("mean_flow", 2, True, 0.5, 30, 7)
    assert DecoderConfig.from_go1({"decoder_type": "flow_matching"}).decoder_type == "flow_matching"
    with pytest.raises(ValueError, match="decoder_type"):
        DecoderConfig.from_go1({"decoder_type": "GAN"})


def test_json_round_trip(tmp_path):
    c = DecoderConfig(decoder_type="mean_flow", context_dim=12, extra={"task": "push-v3"})
    path = tmp_path / "config.json"
    c.to_json(path)
    assert DecoderConfig.from_json(path) == c
    with pytest.raises(ValueError, match="unknown field"):
        DecoderConfig.from_dict({**c.to_dict(), "bogus": 1})


def test_json_carries_every_field_and_a_format_version(tmp_path):
    path = tmp_path / "config.json"
    DecoderConfig(decoder_type="mean_flow", flow_prediction="sample").to_json(path)
    saved = json.loads(path.read_text())
    assert saved["format_version"] == CONFIG_FORMAT_VERSION and set(DecoderConfig().to_dict()) < set(saved)
    for field in ("decoder_type", "flow_prediction", "format_version"):
        path.write_text(json.dumps({k: v for k, v in saved.items() if k != field}))
        with pytest.raises(ValueError, match=rf"config: .*missing field\(s\) \['{field}'\]; expected every field"):
            DecoderConfig.from_json(path)
    # User code keeps the defaults of DecoderConfig(...): from_dict reads partial dicts.
    partial = {"decoder_type": "mean_flow", "format_version": CONFIG_FORMAT_VERSION}
    assert DecoderConfig.from_dict(partial) == DecoderConfig(decoder_type="mean_flow")
    with pytest.raises(ValueError, match=rf"expected format_version 2..{CONFIG_FORMAT_VERSION}, got 1"):
        DecoderConfig.from_dict({**partial, "format_version": 1})
    with pytest.raises(ValueError, match=rf"expected format_version 2..{CONFIG_FORMAT_VERSION}, got {CONFIG_FORMAT_VERSION + 1}"):
        DecoderConfig.from_dict({**partial, "format_version": CONFIG_FORMAT_VERSION + 1})


def test_an_older_format_version_reads_with_the_fields_it_lacked_set_to_their_old_behaviour(tmp_path):
    """A format-2 config.json (every field of its version) loads; the fields later versions added take
    the values of ADDED_FIELDS, and a field missing within its own version still raises."""
    from action_decoder.config import ADDED_FIELDS

    later = {k for version, added in ADDED_FIELDS.items() if version > 2 for k in added}
    assert later, "ADDED_FIELDS names the fields added after format 2"
    cfg = DecoderConfig(decoder_type="mean_flow", hidden_size=48)
    old = {k: v for k, v in cfg.to_dict().items() if k not in later}
    path = tmp_path / "config.json"
    path.write_text(json.dumps({**old, "format_version": 2}))
    loaded = DecoderConfig.from_json(path)
    assert loaded.hidden_size == 48 and loaded.decoder_type == "mean_flow"
    for version, added in ADDED_FIELDS.items():
        for key, value in added.items():
            assert getattr(loaded, key) == value
    path.write_text(json.dumps({**{k: v for k, v in old.items() if k != "hidden_size"}, "format_version": 2}))
    with pytest.raises(ValueError, match=r"missing field\(s\) \['hidden_size'\]"):
        DecoderConfig.from_json(path)


def test_camera_fields_round_trip_and_a_format_3_checkpoint_reads_without_cameras(tmp_path):
    from action_decoder.config import ADDED_FIELDS

    cams = ["observation.images.corner2", "observation.images.topview"]
    cfg = DecoderConfig(cameras=cams, image_size=48, image_encoder="resnet18", image_tokens_per_camera=6,
                        freeze_image_encoder=True, image_shift=3)
    assert cfg.cameras == tuple(cams) and cfg.uses_cameras
    cfg.to_json(tmp_path / "c.json")
    assert DecoderConfig.from_json(tmp_path / "c.json") == cfg
    v3 = {k: v for k, v in DecoderConfig().to_dict().items() if k not in ADDED_FIELDS[4]}
    (tmp_path / "v3.json").write_text(json.dumps({**v3, "format_version": 3}))
    old = DecoderConfig.from_json(tmp_path / "v3.json")
    assert old.cameras == () and not old.uses_cameras and old == DecoderConfig(rtc_horizon="overlap")
    assert DecoderConfig().rtc_horizon == "auto" and old.rtc_horizon == "overlap"   # RTC as format 3 sampled it


@pytest.mark.parametrize("over, match", [
    ({"cameras": "observation.images.a"}, r"cameras: expected a list of LeRobot camera keys 'observation.images.<name>'"),
    ({"cameras": ["corner2"]}, r"cameras: expected a list of LeRobot camera keys .* got \['corner2'\]"),
    ({"cameras": ["observation.images.a", "observation.images.a"]}, r"cameras: expected distinct camera keys"),
    ({"image_encoder": "vit"}, r"image_encoder: expected one of \['conv', 'resnet18'\], got 'vit'"),
    ({"image_size": 8}, r"image_size: expected at least 16 pixels, got 8"),
    ({"image_size": 32.0}, r"image_size: expected a positive integer, got 32.0"),
    ({"image_tokens_per_camera": 0}, r"image_tokens_per_camera: expected a positive integer, got 0"),
    ({"image_shift": 32}, r"image_shift: expected an integer number of pixels in \[0, image_size/2 = 32\), got 32"),
    ({"image_shift": -1}, r"image_shift: .* got -1"),
    ({"freeze_image_encoder": "yes"}, r"freeze_image_encoder: expected True or False, got 'yes'"),
    ({"image_encoder_pretrained": "microsoft/resnet-18"}, r"image_encoder_pretrained: loads a ResNet-18; expected "
                                                          r"image_encoder='resnet18', got image_encoder='conv'"),
    ({"image_encoder_pretrained": "", "image_encoder": "resnet18"}, r"image_encoder_pretrained: expected None or"),
    ({"state_layout": "metaworld_proprio", "state_dim": 10}, r"state_dim: state_layout='metaworld_proprio' expects"),
])
def test_bad_camera_fields_are_one_line_each(over, match):
    with pytest.raises(ValueError, match=match) as err:
        DecoderConfig(**over)
    assert "\n" not in str(err.value)


def test_new_configs_take_the_finite_difference_while_saved_ones_keep_their_dudt(tmp_path):
    """The default du/dt of a new config is the central difference; a checkpoint's config.json reads
    back with the method its weights trained with: format 3 stores it, format 2 (older than the field)
    reads as the JVP, its behaviour when it was written."""
    from action_decoder.config import ADDED_FIELDS

    assert DecoderConfig().meanflow_dudt == "finite_difference"
    assert ADDED_FIELDS[3]["meanflow_dudt"] == "jvp"
    path = tmp_path / "config.json"
    DecoderConfig(decoder_type="mean_flow", meanflow_dudt="jvp").to_json(path)
    saved = json.loads(path.read_text())
    assert DecoderConfig.from_json(path).meanflow_dudt == "jvp"
    path.write_text(json.dumps({**{k: v for k, v in saved.items() if k != "meanflow_dudt"}, "format_version": 3}))
    with pytest.raises(ValueError, match=r"missing field\(s\) \['meanflow_dudt'\]"):
        DecoderConfig.from_json(path)                       # never completed with today's default
    later = {k for version, added in ADDED_FIELDS.items() if version > 2 for k in added}
    path.write_text(json.dumps({**{k: v for k, v in saved.items() if k not in later}, "format_version": 2}))
    assert DecoderConfig.from_json(path).meanflow_dudt == "jvp"


def test_meanflow_target_is_validated_and_a_format_4_checkpoint_reads_as_the_identity(tmp_path):
    from action_decoder.config import ADDED_FIELDS

    with pytest.raises(ValueError, match=r"meanflow_target: expected one of \['identity', 'split'\], got 'half'"):
        DecoderConfig(meanflow_target="half")
    cfg = DecoderConfig(decoder_type="mean_flow", meanflow_target="split")
    cfg.to_json(tmp_path / "c.json")
    assert DecoderConfig.from_json(tmp_path / "c.json").meanflow_target == "split"
    v4 = {k: v for k, v in cfg.to_dict().items() if k not in ADDED_FIELDS[5]}
    (tmp_path / "v4.json").write_text(json.dumps({**v4, "format_version": 4}))
    assert DecoderConfig.from_json(tmp_path / "v4.json").meanflow_target == "identity"


@pytest.mark.parametrize("field", ["clip_sample", "flow_sde_use", "flow_sde_learn_sigma", "flow_sde_return_logprob",
                                   "flow_sde_logprob_sigma_only"])
def test_boolean_fields_refuse_strings(field):
    with pytest.raises(ValueError, match=rf"^{field}: expected True or False, got 'false'$"):
        DecoderConfig(**{field: "false"})


def test_clip_sample_with_mean_std_normalisation_is_refused():
    with pytest.raises(ValueError, match=r"clip_sample: clips DDPM's predicted chunk to \[-1, 1\].*mean_std"):
        DecoderConfig(decoder_type="DDPM", clip_sample=True)
    assert DecoderConfig(decoder_type="DDPM", clip_sample=True, normalization_mode="min_max").clip_sample


def test_extra_that_json_cannot_hold_is_refused_at_construction():
    import numpy as np

    with pytest.raises(ValueError, match=r"extra: expected JSON data .*ndarray"):
        DecoderConfig(extra={"tasks": np.array(["a", "b"])})


def test_the_default_decoder_is_the_clis_and_saved_or_go1_configs_keep_theirs(tmp_path):
    from action_decoder.train import TrainConfig

    assert DecoderConfig().decoder_type == TrainConfig().decoder == "flow_matching"
    assert DecoderConfig.from_go1({"action_dim": 7}).decoder_type == "DDPM"          # GO-1's Base default
    saved = DecoderConfig(decoder_type="DDPM")
    saved.to_json(tmp_path / "config.json")
    assert DecoderConfig.from_json(tmp_path / "config.json").decoder_type == "DDPM"
    for version in range(OLDEST_FORMAT_VERSION, CONFIG_FORMAT_VERSION):      # every readable format stores it
        assert "decoder_type" not in ADDED_FIELDS.get(version + 1, {})
