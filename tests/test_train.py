"""Training pieces below the CLI: the weight average that `final/` holds."""

import math

import pytest
import torch

from action_decoder.train import TrainConfig, _check, decoder_config, weight_average


def test_weight_average_starts_at_the_weights_warms_up_then_caps():
    net = torch.nn.Linear(1, 1, bias=False)
    ema, ceiling = weight_average(net, 0.8), 0.8
    ref = None
    for n, w in enumerate([1.0, 5.0, -2.0, 3.0, 7.0, 0.5, 4.0, 2.0, 9.0, 1.0, 6.0, 3.0]):
        net.weight.data.fill_(w)
        ema.update_parameters(net)
        d = min(ceiling, 1 - (1 + n) ** -0.75)
        ref = w if ref is None else d * ref + (1 - d) * w
        assert float(ema.module.weight) == pytest.approx(ref, rel=1e-6)
    assert 1 - (1 + 11) ** -0.75 > ceiling, "the ceiling was never reached: the test would not check it"


def test_weight_average_off():
    assert weight_average(torch.nn.Linear(1, 1), 0.0) is None


@pytest.mark.parametrize("decoder, chosen, head", [("mean_flow", None, "sample"), ("flow_matching", None, "velocity"),
                                                  ("mean_flow", "velocity", "velocity")])
def test_train_picks_the_head_per_decoder(decoder, chosen, head):
    cfg = TrainConfig(decoder=decoder, flow_prediction=chosen)
    assert decoder_config(cfg, 39, 4, ["push-v3"]).flow_prediction == head


def test_flow_head_given_to_ddpm_is_refused_not_ignored():
    with pytest.raises(ValueError, match="--flow-prediction.*--decoder DDPM"):
        _check(TrainConfig(decoder="DDPM", flow_prediction="sample"))
    _check(TrainConfig(decoder="DDPM"))


@pytest.mark.parametrize("kw, match", [
    ({"grad_clip": -1.0}, r"^--grad-clip: expected a positive finite gradient norm, got -1.0$"),
    ({"grad_clip": 0.0}, r"^--grad-clip: "),
    ({"lr": float("inf")}, r"^--lr: expected a positive finite learning rate, got inf$"),
    ({"lr": float("nan")}, r"^--lr: "),
    ({"weight_decay": -5.0}, r"^--weight-decay: expected a finite decay >= 0, got -5.0$"),
    ({"warmup_steps": -10}, r"^--warmup-steps: expected a number of steps >= 0, got -10$"),
    ({"prediction_type": "epsilon"}, r"^--prediction-type: sets DDPM's target; flow_matching takes --flow-prediction"),
    ({"dataset": "some/dir", "task": "metaworld/reach"}, r"^--task metaworld/reach: choose generated Meta-World"),
    ({"dataset": "some/dir", "demos": 50}, r"^--demos 50: choose generated Meta-World demonstrations"),
])
def test_options_that_would_be_ignored_or_break_training_are_refused_in_one_line(kw, match):
    with pytest.raises(ValueError, match=match):
        _check(TrainConfig(**kw))
    _check(TrainConfig(decoder="DDPM", prediction_type="epsilon"))


def test_an_image_size_without_cameras_is_refused():
    from action_decoder.train import camera_fields

    with pytest.raises(ValueError, match=r"^--image-size: set the image encoder of a camera policy; this run has no "
                                         r"cameras"):
        camera_fields(TrainConfig(image_size=128), None)
    assert camera_fields(TrainConfig(), None) == {}


def test_learning_rate_warms_up_to_lr_then_follows_a_cosine_over_the_remaining_steps():
    from action_decoder.train import lr_factor

    assert [lr_factor(s, 3, 10) for s in range(3)] == pytest.approx([1 / 3, 2 / 3, 1.0])
    assert lr_factor(3, 3, 10) == 1.0                                       # the cosine starts at the peak
    assert lr_factor(3 + 7 / 2, 3, 10) == pytest.approx(0.5)                # half-way through the cosine
    assert 0 < lr_factor(9, 3, 10) < 0.06 and lr_factor(10, 3, 10) == pytest.approx(0.0)
    assert max(lr_factor(s, 100, 100) for s in range(100)) == 1.0          # a run as long as its warm-up
    assert lr_factor(0, 0, 10) == 1.0 and lr_factor(5, 0, 10) == pytest.approx(0.5 * (1 + math.cos(math.pi * 4 / 9)))
