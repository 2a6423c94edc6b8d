"""Action bounds: sampled chunks are clamped to the action statistics' [min, max] (`clip_actions`),
saved with the checkpoint; older checkpoints keep sampling unclamped."""

import json

import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig

SMALL = dict(state_dim=5, action_dim=3, action_chunk_size=8, n_action_steps=4, hidden_size=32,
             num_hidden_layers=2, num_attention_heads=4, num_key_value_heads=2, num_inference_timesteps=4)
LOW, HIGH = [-0.8, -0.2, 0.0], [0.9, 0.3, 2.5]
STATS = {"state": {"mean": [0.0] * 5, "std": [1.0] * 5, "min": [-3.0] * 5, "max": [3.0] * 5},
         "actions": {"mean": [0.05, 0.05, 1.2], "std": [0.5, 0.1, 0.8], "min": LOW, "max": HIGH}}


def wild(decoder_type="flow_matching", stats=STATS, **kw):
    """An untrained policy whose output layer is scaled ×50: its chunks land far outside the data's range."""
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type=decoder_type, **{**SMALL, **kw}), stats).eval()
    with torch.no_grad():
        for p in policy.model.head.parameters():
            p.mul_(50.0)
    return policy


def chunk(policy, seed=0):
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(16, 5, generator=g)
    return policy.predict_action_chunk({"state": state}, generator=g)                # [16, 8, 3]


def outside(actions):
    low, high = torch.tensor(LOW), torch.tensor(HIGH)
    return float(((actions < low) | (actions > high)).float().mean())


@pytest.mark.parametrize("decoder_type", ["DDPM", "flow_matching", "mean_flow"])
def test_no_action_leaves_the_data_range_by_default_and_turning_the_clip_off_lets_them(decoder_type):
    clipped = chunk(wild(decoder_type))
    free = chunk(wild(decoder_type, clip_actions=False))
    assert outside(free) > 0.3, "the scaled head must produce out-of-range chunks for this test to mean anything"
    assert outside(clipped) == 0.0
    # Clamping is all the clip does: inside the range the two chunks agree, outside they sit on the bound.
    low, high = torch.tensor(LOW), torch.tensor(HIGH)
    torch.testing.assert_close(clipped, torch.minimum(torch.maximum(free, low), high))
    assert bool((clipped == high).any() and (clipped == low).any())


def test_the_clip_setting_is_saved_with_the_checkpoint(tmp_path):
    for clip in (True, False):
        wild(clip_actions=clip).save_pretrained(tmp_path / str(clip))
        assert json.loads((tmp_path / str(clip) / "config.json").read_text())["clip_actions"] is clip
        loaded = ActionDecoderPolicy.from_pretrained(tmp_path / str(clip))
        assert loaded.config.clip_actions is clip
        assert (outside(chunk(loaded)) == 0.0) is clip
        torch.testing.assert_close(loaded.normalizers["actions"].max, torch.tensor(HIGH))


def test_a_checkpoint_older_than_the_clip_samples_unclamped_as_it_did(tmp_path):
    wild().save_pretrained(tmp_path / "c")
    cfg = json.loads((tmp_path / "c" / "config.json").read_text())
    del cfg["clip_actions"]
    (tmp_path / "c" / "config.json").write_text(json.dumps({**cfg, "format_version": 6}))
    old = ActionDecoderPolicy.from_pretrained(tmp_path / "c")
    assert old.config.clip_actions is False and outside(chunk(old)) > 0.3


def test_without_statistics_nothing_is_clipped_and_min_max_leaves_the_actions_as_they_are():
    free = chunk(wild(stats=None, clip_actions=False))
    torch.testing.assert_close(chunk(wild(stats=None)), free)
    assert float(free.abs().max()) > 3.0
    norm = wild(stats=None, normalization_mode="min_max").normalizers["actions"]
    x = torch.tensor([[5.0, -7.0, 0.25]])
    assert torch.equal(norm.normalize(x), x) and torch.equal(norm.unnormalize(x), x) and torch.equal(norm.clip(x), x)


def test_the_squash_bounds_a_sac_policy_to_the_box_instead_of_the_data_range():
    squashed = chunk(wild(action_squash=True))
    assert float(squashed.abs().max()) <= 1.0      # tanh, which rounds to ±1 in float32 far out
    assert float(squashed[..., 0].max()) > HIGH[0] and float(squashed[..., 1].min()) < LOW[1]


def test_clip_actions_must_be_a_bool():
    with pytest.raises(ValueError, match=r"clip_actions: expected True or False, got 'yes'"):
        DecoderConfig(clip_actions="yes")
