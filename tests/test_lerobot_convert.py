"""`action-decoder convert`: library checkpoint ↔ LeRobot pretrained_model/, without LeRobot installed
(the plugin-side test, tests/test_lerobot_plugin.py, loads the converted directory with LeRobot itself)."""

import json

import pytest
import torch
from safetensors.torch import load_file

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.cli import main
from action_decoder.lerobot_checkpoint import CLIP_STEP, LEROBOT_EPS, PREFIX, plugin_core_config

SMALL = dict(state_dim=5, action_dim=3, action_chunk_size=8, n_action_steps=4, hidden_size=32,
             num_hidden_layers=2, num_attention_heads=4, num_key_value_heads=2, num_inference_timesteps=3)
# State dimension 4 is nearly constant (std 0.004 < the 0.01 floor): LeRobot must divide by the floor too.
STATS = {"state": {"mean": [0.1, -0.2, 0.3, 1.0, 0.5], "std": [0.5, 0.2, 1.5, 0.8, 0.004],
                   "min": [-1.0, -1.0, -3.0, -1.0, 0.49], "max": [1.0, 0.5, 3.0, 3.0, 0.51]},
         "actions": {"mean": [0.05, 0.05, 1.2], "std": [0.5, 0.1, 0.8], "min": [-0.8, -0.2, 0.0],
                     "max": [0.9, 0.3, 2.5]}}


def library_checkpoint(path, decoder_type="flow_matching", tasks=("door-close",), stats=STATS, **kw):
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type=decoder_type, **{**SMALL, **kw},
                        context_dim=len(tasks) if len(tasks) > 1 else None,
                        extra={"tasks": list(tasks), "train": {"lr": 3e-4}})
    policy = ActionDecoderPolicy(cfg, stats)
    with torch.no_grad():
        for p in policy.model.head.parameters():     # large outputs: some actions beyond the data's range
            p.mul_(20.0)
    policy.save_pretrained(path)
    return policy


def batch(seed=0, tasks=1):
    g = torch.Generator().manual_seed(seed)
    state = torch.tensor(STATS["state"]["mean"]) + torch.randn(6, 5, generator=g) * torch.tensor(STATS["state"]["std"])
    out = {"state": state}
    if tasks > 1:
        out["context"] = torch.nn.functional.one_hot(torch.arange(6) % tasks, tasks).float()[:, None]
    return out, torch.randn(6, 8, 3, generator=g)


@pytest.mark.parametrize("decoder_type, mode", [("flow_matching", "mean_std"), ("mean_flow", "mean_std"),
                                                ("DDPM", "min_max")])
def test_library_to_lerobot_and_back_is_bit_identical_and_samples_the_same_chunk(tmp_path, decoder_type, mode):
    original = library_checkpoint(tmp_path / "lib", decoder_type, normalization_mode=mode)
    assert main(["convert", "--checkpoint", str(tmp_path / "lib"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "lr")]) == 0
    assert main(["convert", "--checkpoint", str(tmp_path / "lr"), "--to", "library",
                 "--output-dir", str(tmp_path / "back")]) == 0
    back = ActionDecoderPolicy.from_pretrained(tmp_path / "back")
    before, after = load_file(str(tmp_path / "lib" / "model.safetensors")), load_file(str(tmp_path / "back" / "model.safetensors"))
    assert sorted(before) == sorted(after) and all(torch.equal(before[k], after[k]) for k in before)
    lerobot = load_file(str(tmp_path / "lr" / "model.safetensors"))
    assert sorted(lerobot) == sorted(PREFIX + k for k in before) and all(torch.equal(lerobot[PREFIX + k], v) for k, v in before.items())
    ignore = {"extra"}
    assert {k: v for k, v in back.config.to_dict().items() if k not in ignore} == \
        {k: v for k, v in original.config.to_dict().items() if k not in ignore}
    assert back.config.extra["tasks"] == ["door-close"]
    b, noise = batch()
    a, z = original.eval().predict_action_chunk(b, noise=noise), back.predict_action_chunk(b, noise=noise)
    assert torch.equal(a, z)


def lerobot_by_hand(path, state, noise, context=None):
    """What LeRobot does with the converted directory, written out: normaliser (x − mean)/(std + eps),
    the plugin's core policy (identity normalisation, no clip), un-normaliser x·std + mean, clip step."""
    cfg = json.loads((path / "config.json").read_text())
    feats = cfg["input_features"]
    policy = ActionDecoderPolicy(plugin_core_config(cfg, feats["observation.state"]["shape"][0],
                                                    cfg["output_features"]["action"]["shape"][0], (), cfg["tasks"]))
    policy.load_state_dict({k[len(PREFIX):]: v for k, v in load_file(str(path / "model.safetensors")).items()})
    pre = json.loads((path / "policy_preprocessor.json").read_text())["steps"]
    stats = load_file(str(path / pre[3]["state_file"]))
    assert [s["registry_name"] for s in pre] == ["rename_observations_processor", "to_batch_processor",
                                                 "device_processor", "normalizer_processor"]
    post = json.loads((path / "policy_postprocessor.json").read_text())["steps"]
    x = (state - stats["observation.state.mean"]) / (stats["observation.state.std"] + LEROBOT_EPS)
    out = policy.eval().predict_action_chunk({"state": x, **({"context": context} if context is not None else {})},
                                             noise=noise)
    out = out * stats["action.std"] + stats["action.mean"]
    clip = [s for s in post if s["registry_name"] == CLIP_STEP]
    if clip:
        bounds = load_file(str(path / clip[0]["state_file"]))
        out = torch.minimum(torch.maximum(out, bounds["action.min"]), bounds["action.max"])
    return out, [s["registry_name"] for s in post]


@pytest.mark.parametrize("clip", [True, False])
def test_the_converted_processors_normalise_and_clip_as_the_library_does(tmp_path, clip):
    original = library_checkpoint(tmp_path / "lib", tasks=("door-close", "drawer-open"), clip_actions=clip)
    assert main(["convert", "--checkpoint", str(tmp_path / "lib"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "lr")]) == 0
    cfg = json.loads((tmp_path / "lr" / "config.json").read_text())
    assert cfg["type"] == "action_decoder" and cfg["chunk_size"] == 8 and cfg["num_inference_steps"] == 3
    assert cfg["tasks"] == ["door-close", "drawer-open"] and cfg["clip_actions"] is clip
    assert cfg["normalization_mapping"] == {"VISUAL": "IDENTITY", "STATE": "MEAN_STD", "ACTION": "MEAN_STD"}
    assert cfg["optimizer_lr"] == 3e-4
    b, noise = batch(tasks=2)
    ours = original.eval().predict_action_chunk(b, noise=noise)
    theirs, post = lerobot_by_hand(tmp_path / "lr", b["state"], noise, b["context"])
    assert post == ["unnormalizer_processor", *([CLIP_STEP] if clip else []), "device_processor"]
    torch.testing.assert_close(theirs, ours, atol=1e-5, rtol=1e-5)
    low, high = torch.tensor(STATS["actions"]["min"]), torch.tensor(STATS["actions"]["max"])
    beyond = bool(((ours < low) | (ours > high)).any())
    assert beyond is not clip


def test_a_policy_trained_by_lerobot_takes_its_statistics_from_the_processors(tmp_path):
    library_checkpoint(tmp_path / "lib")
    main(["convert", "--checkpoint", str(tmp_path / "lib"), "--to", "lerobot", "--output-dir", str(tmp_path / "lr")])
    # What lerobot-train saves: the plugin's core policy holds no statistics (identity normalisation).
    weights = load_file(str(tmp_path / "lr" / "model.safetensors"))
    from safetensors.torch import save_file
    for key in list(weights):
        if ".normalizers." in key:
            fill = {"mean": 0.0, "std": 1.0, "min": -torch.inf, "max": torch.inf}[key.rsplit(".", 1)[1]]
            weights[key] = torch.full_like(weights[key], fill)
    save_file(weights, str(tmp_path / "lr" / "model.safetensors"))
    (tmp_path / "lr" / "policy_postprocessor.json").write_text(json.dumps({"name": "policy_postprocessor", "steps": [
        s for s in json.loads((tmp_path / "lr" / "policy_postprocessor.json").read_text())["steps"]
        if s["registry_name"] != CLIP_STEP]}))
    main(["convert", "--checkpoint", str(tmp_path / "lr"), "--to", "library", "--output-dir", str(tmp_path / "back")])
    back = ActionDecoderPolicy.from_pretrained(tmp_path / "back")
    norm = back.normalizers["actions"]
    torch.testing.assert_close(norm.mean, torch.tensor(STATS["actions"]["mean"]))
    torch.testing.assert_close(norm.max, torch.tensor(STATS["actions"]["max"]))
    assert back.config.clip_actions is False      # its postprocessor had no clip step


def test_convert_refuses_what_lerobot_cannot_run_in_one_line(tmp_path, capsys):
    library_checkpoint(tmp_path / "mw", state_dim=39, state_layout="metaworld", stats=None)
    assert main(["convert", "--checkpoint", str(tmp_path / "mw"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "o1")]) == 2
    assert "state_layout: the LeRobot plugin reads the state as it comes" in capsys.readouterr().err
    library_checkpoint(tmp_path / "rope", rope_theta=500.0)
    assert main(["convert", "--checkpoint", str(tmp_path / "rope"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "o2")]) == 0     # carried by the plugin's added fields
    assert json.loads((tmp_path / "o2" / "config.json").read_text())["rope_theta"] == 500.0
    assert main(["convert", "--checkpoint", str(tmp_path / "o2"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "o3")]) == 2
    assert "already a LeRobot checkpoint; use --to library" in capsys.readouterr().err
    assert main(["convert", "--checkpoint", str(tmp_path / "rope"), "--to", "library",
                 "--output-dir", str(tmp_path / "o4")]) == 2
    assert "is a LeRobot policy of type None; expected 'action_decoder'" in capsys.readouterr().err
    assert main(["convert", "--checkpoint", str(tmp_path / "rope"), "--to", "lerobot",
                 "--output-dir", str(tmp_path / "o2")]) == 2
    assert "--output-dir: expected a new or empty directory" in capsys.readouterr().err
