"""The image encoder (expert/image_encoder.py) and the training side of camera policies: pixel
normalisation, the random shift, the token grid, both backbones (ResNet-18 built from a config;
a "pretrained" one saved to a temporary directory: nothing is downloaded), and train.py's batches
and config for datasets with cameras."""

import numpy as np
import pytest
import torch
from torch import nn

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.expert import ImageEncoder
from action_decoder.expert.image_encoder import IMAGENET_MEAN, IMAGENET_STD, random_shift, token_grid

CAMS = ("observation.images.corner2", "observation.images.topview")


def config(**kw):
    base = dict(decoder_type="flow_matching", state_dim=5, action_dim=3, action_chunk_size=8, n_action_steps=4,
                hidden_size=32, num_hidden_layers=2, cameras=CAMS, image_size=32)
    return DecoderConfig(**{**base, **kw})


def frames(b=2, n=2, s=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (b, n, 3, s, s), dtype=torch.uint8, generator=g)


@pytest.mark.parametrize("tokens, grid", [(1, (1, 1)), (4, (2, 2)), (6, (2, 3)), (7, (1, 7)), (9, (3, 3))])
def test_token_grid_is_the_squarest_factorisation(tokens, grid):
    assert token_grid(tokens) == grid


@pytest.mark.parametrize("encoder, tokens", [("conv", 4), ("conv", 1), ("resnet18", 4)])
def test_tokens_per_camera_at_the_experts_width_with_a_camera_embedding(encoder, tokens):
    torch.manual_seed(0)
    enc = ImageEncoder(config(image_encoder=encoder, image_tokens_per_camera=tokens)).eval()
    x = frames()
    out = enc(x)
    assert out.shape == (2, 2 * tokens, 32)
    # The same frame in both cameras gives tokens that differ by exactly the camera embeddings.
    same = torch.stack([x[:, 0], x[:, 0]], dim=1)
    t = enc(same).view(2, 2, tokens, 32)
    torch.testing.assert_close(t[:, 1] - t[:, 0], (enc.camera_embed[1] - enc.camera_embed[0]).expand(2, tokens, 32))


def test_pixels_are_scaled_to_unit_range_then_imagenet_normalised():
    enc = ImageEncoder(config(image_shift=0)).eval()
    x = torch.full((1, 1, 3, 32, 32), 255, dtype=torch.uint8)
    px = enc.pixels(x)                                                       # [1, 3, 32, 32]
    want = (1 - torch.tensor(IMAGENET_MEAN)) / torch.tensor(IMAGENET_STD)
    torch.testing.assert_close(px[0, :, 5, 7], want)
    torch.testing.assert_close(enc.pixels(x.float() / 255), px)


def test_random_shift_translates_each_frame_with_edges_repeated():
    torch.manual_seed(0)
    x = torch.arange(2 * 3 * 10 * 10, dtype=torch.float32).view(2, 3, 10, 10)
    for _ in range(5):
        out = random_shift(x, 2)
        assert out.shape == x.shape
        for b in range(2):
            # Some offset (dy, dx) in [-2, 2]² maps the frame's interior onto itself.
            hits = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)
                    if torch.equal(out[b, :, 2:8, 2:8], x[b, :, 2 + dy:8 + dy, 2 + dx:8 + dx])]
            assert len(hits) == 1
    assert torch.equal(random_shift(x, 0), x)
    offsets = {tuple(random_shift(x[:1], 2)[0, 0, 5, 5:7].tolist()) for _ in range(30)}
    assert len(offsets) > 5                                                  # the offset is random


def test_random_resnet18_has_groupnorm_and_resnet18_layout():
    enc = ImageEncoder(config(image_encoder="resnet18"))
    mods = list(enc.backbone.modules())
    assert not any(isinstance(m, nn.BatchNorm2d) for m in mods)
    norms = [m for m in mods if isinstance(m, nn.GroupNorm)]
    assert len(norms) == 20 and all(m.num_channels // m.num_groups == 16 for m in norms)   # 1 stem + 16 + 3 shortcuts
    convs = [m for m in mods if isinstance(m, nn.Conv2d)]
    assert len(convs) == 20 and convs[-1].out_channels == 512
    # ResNet-18 without its classifier: 11.18 M parameters (torchvision's resnet18 less the fc layer).
    assert abs(sum(p.numel() for p in enc.backbone.parameters()) / 1e6 - 11.18) < 0.01


@pytest.fixture
def pretrained_dir(tmp_path):
    from transformers import ResNetConfig, ResNetModel

    torch.manual_seed(3)
    model = ResNetModel(ResNetConfig(layer_type="basic", depths=[2, 2, 2, 2], hidden_sizes=[64, 128, 256, 512],
                                     embedding_size=64))
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):                         # non-trivial statistics to keep
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    model.save_pretrained(tmp_path / "resnet18")
    return tmp_path / "resnet18", model


def test_pretrained_resnet18_keeps_its_weights_and_frozen_batchnorm(pretrained_dir):
    path, model = pretrained_dir
    policy = ActionDecoderPolicy(config(image_encoder="resnet18", image_encoder_pretrained=str(path)))
    backbone = policy.model.image_encoder.backbone
    for k, v in model.state_dict().items():
        torch.testing.assert_close(backbone.resnet.state_dict()[k], v)
    policy.train()
    bns = [m for m in backbone.modules() if isinstance(m, nn.BatchNorm2d)]
    assert bns and not any(m.training for m in bns)                 # running statistics used, never updated
    before = bns[0].running_mean.clone()
    policy.compute_loss({"state": torch.randn(2, 5), "actions": torch.randn(2, 8, 3), "images": frames()}).loss.backward()
    assert torch.equal(bns[0].running_mean, before)
    x = (frames()[:, 0].float() / 255 - torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)) / torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    torch.testing.assert_close(backbone(x), model.eval()(pixel_values=x).last_hidden_state)


def test_pretrained_camera_policy_reloads_without_reading_the_pretrained_source(pretrained_dir, tmp_path):
    import shutil

    path, _ = pretrained_dir
    policy = ActionDecoderPolicy(config(image_encoder="resnet18", image_encoder_pretrained=str(path))).eval()
    policy.save_pretrained(tmp_path / "ckpt")
    shutil.rmtree(path)                                             # the checkpoint alone must suffice
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "ckpt").eval()
    b, noise = {"state": torch.randn(2, 5), "images": frames()}, torch.randn(2, 8, 3)
    torch.testing.assert_close(loaded.sample(b, noise=noise).actions, policy.sample(b, noise=noise).actions)


def test_pretrained_source_that_is_not_a_resnet18_is_one_line(tmp_path):
    from transformers import ResNetConfig, ResNetModel

    ResNetModel(ResNetConfig(layer_type="basic", depths=[1, 1, 1, 1], hidden_sizes=[8, 16, 32, 64],
                             embedding_size=8)).save_pretrained(tmp_path / "small")
    with pytest.raises(ValueError, match=r"image_encoder_pretrained: expected a ResNet-18 .* got .*'depths': \[1, 1, 1, 1\]"):
        ImageEncoder(config(image_encoder="resnet18", image_encoder_pretrained=str(tmp_path / "small")))
    with pytest.raises(ValueError, match=r"image_encoder_pretrained: cannot load a ResNet from .*missing"):
        ImageEncoder(config(image_encoder="resnet18", image_encoder_pretrained=str(tmp_path / "missing")))


def test_resnet18_without_transformers_is_one_line(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "transformers", None)          # import transformers raises ImportError
    with pytest.raises(ValueError, match=r"image_encoder: 'resnet18' is built with transformers, which is not "
                                         r"installed; pip install 'action-decoder\[vlm\]'"):
        ImageEncoder(config(image_encoder="resnet18"))


# ---------------------------------------------------------------------- training batches and config
class FakeChunks:
    """What camdata's ChunkDataset gives per frame: state, actions, pad mask, task index, images."""

    def __init__(self, n=6, cams=2, size=16):
        g = torch.Generator().manual_seed(0)
        self.items = [{"state": torch.randn(39, generator=g), "actions": torch.randn(8, 4, generator=g),
                       "action_is_pad": torch.zeros(8, dtype=torch.bool), "task_index": 0,
                       "images": torch.randint(0, 256, (cams, 3, size, size), dtype=torch.uint8, generator=g)}
                      for _ in range(n)]

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        return self.items[i]


def test_training_batches_carry_the_chunks_images_to_the_policy():
    from action_decoder.train import TrainConfig, _batch, decoder_config

    ds = FakeChunks()
    b = _batch(ds, torch.tensor([0, 3]), 1, torch.device("cpu"))
    assert b["images"].shape == (2, 2, 3, 16, 16) and b["images"].dtype == torch.uint8
    assert torch.equal(b["images"][1], ds[3]["images"])
    images = {"observation.images.corner2": np.zeros((6, 16, 16, 3), np.uint8),
              "observation.images.topview": np.zeros((6, 16, 16, 3), np.uint8)}
    cfg = TrainConfig(horizon=8, n_action_steps=4, hidden_size=32, num_layers=2, image_shift=2)
    cfg.cameras = ["corner2", "topview"]                             # TrainConfig.cameras (--cameras)
    dconf = decoder_config(cfg, 39, 4, ["push-v3"], images)
    assert dconf.cameras == tuple(images) and dconf.image_size == 16 and dconf.image_shift == 2
    assert dconf.state_layout == "metaworld_proprio" and dconf.state_input_dim == 4
    policy = ActionDecoderPolicy(dconf).train()
    loss = policy(b).loss
    loss.backward()
    assert policy.model.image_encoder.proj.weight.grad.abs().sum() > 0


def test_training_config_without_cameras_refuses_image_options_and_proprio():
    from action_decoder.train import TrainConfig, decoder_config

    assert decoder_config(TrainConfig(), 39, 4, ["push-v3"]).cameras == ()
    with pytest.raises(ValueError, match=r"--image-encoder, --image-shift: set the image encoder of a camera policy"):
        decoder_config(TrainConfig(image_encoder="resnet18", image_shift=2), 39, 4, ["push-v3"])
    with pytest.raises(ValueError, match=r"--state-layout: metaworld_proprio reads only the hand and gripper"):
        decoder_config(TrainConfig(state_layout="metaworld_proprio"), 39, 4, ["push-v3"])
    images = {"observation.images.a": np.zeros((2, 16, 12, 3), np.uint8)}
    with pytest.raises(ValueError, match=r"cameras: expected square frames"):
        decoder_config(TrainConfig(state_layout="metaworld"), 39, 4, ["push-v3"], images)


def test_proprio_layout_refuses_the_position_shift_augmentation():
    from action_decoder.train import TrainConfig, augment_shift

    assert augment_shift(TrainConfig(state_layout="metaworld_proprio")) == 0.0
    with pytest.raises(ValueError, match="--augment-shift: shifting positions needs --state-layout metaworld"):
        augment_shift(TrainConfig(state_layout="metaworld_proprio", augment_shift=0.05))


def test_validation_on_held_out_chunks_passes_their_images():
    from types import SimpleNamespace

    from action_decoder.train import validation_metrics

    val = FakeChunks(n=4)
    val.dataset = SimpleNamespace(episode_ids=np.array([7]))
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4,
                                               action_chunk_size=8, n_action_steps=4, hidden_size=32,
                                               num_hidden_layers=1, cameras=CAMS, image_size=16))
    seen = []
    policy.model.image_encoder.register_forward_hook(lambda m, args, out: seen.append(args[0].shape))
    out = validation_metrics(policy, val, 1, torch.device("cpu"))
    assert np.isfinite(out["val_loss"]) and out["frames"] == 4
    assert seen and all(s == (4, 2, 3, 16, 16) for s in seen)


def test_training_on_the_lerobot_camera_fixture_uses_the_cameras():
    """On LeRobot 0.4.4's v3.0 camera fixture: a training step reaches the image encoder, and the
    sampled chunk (fixed noise) follows the frames it is shown."""
    from pathlib import Path

    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from action_decoder.data import ChunkDataset, load_dataset

    data = load_dataset(Path(__file__).parent / "data" / "lerobot" / "v30_cams", image_size=32)
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=data.states.shape[1], action_dim=data.actions.shape[1],
                        action_chunk_size=4, hidden_size=32, num_hidden_layers=1, num_inference_timesteps=2,
                        cameras=list(data.images), image_size=32)
    policy = ActionDecoderPolicy(cfg, data.stats)
    items = [ChunkDataset(data, horizon=4)[i] for i in (0, 15, 30)]                 # frames of three episodes
    batch = {k: torch.stack([it[k] for it in items]) for k in ("state", "actions", "images")}
    assert batch["images"].shape == (3, 2, 3, 32, 32) and batch["images"].dtype == torch.uint8
    policy(batch).loss.backward()
    grads = [p.grad for p in policy.model.image_encoder.parameters()]
    assert all(g is not None for g in grads) and sum(float(g.abs().sum()) for g in grads) > 0
    policy.eval()
    noise = torch.randn(3, 4, data.actions.shape[1], generator=torch.Generator().manual_seed(1))
    chunk = lambda images: policy.predict_action_chunk({"state": batch["state"], "images": images}, noise=noise)
    same = batch["images"][[0, 0, 0]]                                               # episode 0's frame in every row
    swapped = chunk(same)
    assert torch.equal(chunk(batch["images"])[0], swapped[0])                         # row 0 saw the same frame
    assert not torch.allclose(chunk(batch["images"])[1:], swapped[1:])                # rows 1, 2 saw other frames


def test_backbone_built_for_a_checkpoint_keeps_batchnorm_frozen_without_a_train_call(pretrained_dir, tmp_path):
    """Loading a checkpoint builds the ResNet from its config (load_pretrained=False), where transformers
    leaves BatchNorm in train mode: its statistics must be frozen from construction on."""
    path, _ = pretrained_dir
    built = ActionDecoderPolicy(config(image_encoder="resnet18", image_encoder_pretrained=str(path)),
                                load_pretrained=False)
    bns = [m for m in built.model.image_encoder.backbone.modules() if isinstance(m, nn.BatchNorm2d)]
    assert built.training and bns and not any(m.training for m in bns)
    before = bns[0].running_mean.clone()
    built.compute_loss({"state": torch.randn(4, 5), "actions": torch.randn(4, 8, 3), "images": frames(4)})
    assert torch.equal(bns[0].running_mean, before)
    built.save_pretrained(tmp_path / "c")
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "c")
    assert loaded.select_action({"state": torch.randn(1, 5), "images": frames(1)}).shape == (1, 3)
