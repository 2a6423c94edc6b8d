"""Meta-World's state layout: relative positions, the shift augmentation, and the policy that reads them."""

import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.state_layout import GOAL, HAND, OBJ1, OBJ2, POSITIONS, relative_positions, shift_positions
from action_decoder.train import TrainConfig, augment_shift


def metaworld_states(b=5, second_object=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    s = torch.randn(b, 39, generator=g)                     # quaternions, gripper: anything
    for start in POSITIONS:                                 # positions on the table: y > 0.3
        s[:, start:start + 3] = torch.rand(b, 3, generator=g) * torch.tensor([0.6, 0.4, 0.3]) + torch.tensor([-0.3, 0.4, 0.0])
    if not second_object:
        s[:, OBJ2:OBJ2 + 3] = 0
        s[:, 29:32] = 0
    return s


def test_relative_positions_are_differences_in_decimetres_and_zero_for_an_absent_object():
    s = metaworld_states(second_object=False)
    rel = relative_positions(s).view(-1, 5, 3)
    torch.testing.assert_close(rel[:, 0], (s[:, OBJ1:OBJ1 + 3] - s[:, HAND:HAND + 3]) / 0.1)
    torch.testing.assert_close(rel[:, 3], (s[:, GOAL:GOAL + 3] - s[:, OBJ1:OBJ1 + 3]) / 0.1)
    assert torch.all(rel[:, 1] == 0) and torch.all(rel[:, 4] == 0), "obj2 is absent: no feature from it"


def test_shift_moves_every_present_position_in_x_and_y_only():
    s = metaworld_states(second_object=False)
    offset = torch.tensor([[0.03, -0.02]]).expand(len(s), 2)
    out = shift_positions(s, offset)
    moved = torch.zeros(39, dtype=torch.bool)
    for start in POSITIONS:
        if start in (OBJ2, 29):
            continue
        moved[start:start + 2] = True
        torch.testing.assert_close(out[:, start:start + 2], s[:, start:start + 2] + offset)
    assert torch.equal(out[:, ~moved], s[:, ~moved]), "z, quaternions, gripper and absent objects stay"
    torch.testing.assert_close(relative_positions(out), relative_positions(s), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="offset"):
        shift_positions(s, torch.zeros(len(s), 3))


def test_metaworld_policy_reads_relative_positions_and_round_trips(tmp_path):
    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, hidden_size=32, num_hidden_layers=1,
                        state_layout="metaworld")
    assert cfg.state_input_dim == 54
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(cfg).eval()
    s = metaworld_states()
    noise = torch.randn(len(s), 16, 4)
    bound = policy.bind({"state": s})
    t = torch.full((len(s),), 0.3)
    v = bound.velocity(noise, t)
    seen = []
    policy.model.state_in.register_forward_hook(lambda m, inp, out: seen.append(inp[0]))
    bound.velocity(noise, t)
    torch.testing.assert_close(seen[0], torch.cat([policy.normalizers["state"].normalize(s), relative_positions(s)], -1))
    policy.save_pretrained(tmp_path / "p")
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "p").eval()
    assert loaded.config.state_layout == "metaworld"
    torch.testing.assert_close(loaded.bind({"state": s}).velocity(noise, t), v)


def test_layout_errors_name_the_field():
    with pytest.raises(ValueError, match="state_layout"):
        DecoderConfig(state_layout="mujoco")
    with pytest.raises(ValueError, match="state_dim.*39.*got state_dim=10"):
        DecoderConfig(state_dim=10, state_layout="metaworld")
    with pytest.raises(ValueError, match="--augment-shift.*metaworld"):
        augment_shift(TrainConfig(dataset="my_robot", augment_shift=0.1))
    with pytest.raises(ValueError, match="--augment-shift.*>= 0"):
        augment_shift(TrainConfig(augment_shift=-1.0))
    assert augment_shift(TrainConfig()) == 0.05 and augment_shift(TrainConfig(dataset="my_robot")) == 0.0
