"""Camera frames → context tokens the Action Expert attends to.

Pixels, stated once: uint8 frames are divided by 255 (floating-point frames are taken as [0, 1]),
then normalised with ImageNet's per-channel mean and std, for both backbones (the statistics the
pretrained ResNet-18 checkpoints were trained with).

Backbones: "conv", four stride-2 3×3 convolutions with GroupNorm (cheap on a CPU), or "resnet18",
transformers' `ResNetModel` with ResNet-18's layout. A randomly initialised ResNet-18 has every
BatchNorm replaced by GroupNorm (16 channels a group), as Diffusion Policy does; a pretrained one
(`image_encoder_pretrained`) keeps its BatchNorm layers with their running statistics frozen (always
in eval mode), so the features are those it was trained to give. `freeze_image_encoder` keeps the
backbone's weights fixed.

Tokens: the feature map [C, h, w] of each camera is average-pooled to a grid of
`image_tokens_per_camera` cells (rows × cols, rows the largest divisor ≤ √T), each cell projected
to the expert's width, plus a learned embedding per cell and per camera.

Augmentation (train() mode only; eval() is deterministic): each frame is shifted by a random
integer offset in [−k, k]² pixels (k = `image_shift`): padded by k with its edge pixels and
cropped back (DrQ, Diffusion Policy). The default k is 0: where an object moves by fewer pixels
across layouts than k, the shift hides where it is.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..config import DecoderConfig

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CONV_WIDTHS = (32, 64, 128, 128)
GROUP_CHANNELS = 16        # GroupNorm: channels per group (Diffusion Policy's features // 16 groups)
RESNET18 = {"layer_type": "basic", "depths": [2, 2, 2, 2], "hidden_sizes": [64, 128, 256, 512],
            "embedding_size": 64}


def token_grid(tokens: int) -> tuple[int, int]:
    """(rows, cols) of the pooled grid of `tokens` cells: rows the largest divisor ≤ √tokens."""
    rows = max(d for d in range(1, math.isqrt(tokens) + 1) if tokens % d == 0)
    return rows, tokens // rows


def random_shift(images: Tensor, pad: int, generator: Optional[torch.Generator] = None) -> Tensor:
    """[B, C, H, W] frames each moved by its own integer offset in [−pad, pad]² (edge pixels repeated)."""
    if pad == 0:
        return images
    b, _, h, w = images.shape
    padded = F.pad(images, (pad, pad, pad, pad), mode="replicate")                 # [B, C, H+2p, W+2p]
    dy, dx = (torch.randint(0, 2 * pad + 1, (2, b), generator=generator)).to(images.device)   # [B] each
    rows = dy[:, None] + torch.arange(h, device=images.device)                     # [B, H]
    cols = dx[:, None] + torch.arange(w, device=images.device)                     # [B, W]
    out = padded[torch.arange(b, device=images.device)[:, None, None], :, rows[:, :, None], cols[:, None, :]]
    return out.permute(0, 3, 1, 2)                                                 # [B, H, W, C] -> [B, C, H, W]


def _group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(max(1, channels // GROUP_CHANNELS), channels)


def _swap_batch_norm(module: nn.Module) -> None:
    """Every BatchNorm2d of `module` replaced, in place, by a GroupNorm of as many channels."""
    for name, child in module.named_children():
        if isinstance(child, nn.BatchNorm2d):
            setattr(module, name, _group_norm(child.num_features))
        else:
            _swap_batch_norm(child)


class ConvBackbone(nn.Module):
    """[B, 3, S, S] → [B, 128, S/16, S/16]: four stride-2 3×3 convolutions, GroupNorm, SiLU."""

    def __init__(self) -> None:
        super().__init__()
        layers, width = [], 3
        for out in CONV_WIDTHS:
            layers += [nn.Conv2d(width, out, 3, stride=2, padding=1), _group_norm(out), nn.SiLU()]
            width = out
        self.net = nn.Sequential(*layers)
        self.out_channels = width

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class ResNet18Backbone(nn.Module):
    """[B, 3, S, S] → [B, 512, S/32, S/32] from transformers' `ResNetModel` (see the module docstring)."""

    def __init__(self, pretrained: Optional[str], load: bool) -> None:
        super().__init__()
        try:
            from transformers import ResNetConfig, ResNetModel
        except ImportError:
            raise ValueError("image_encoder: 'resnet18' is built with transformers, which is not installed; "
                             "pip install 'action-decoder[vlm]' (or use image_encoder='conv')") from None
        if pretrained is not None and load:
            try:
                self.resnet = ResNetModel.from_pretrained(pretrained)
            except Exception as err:    # not found, offline, not a ResNet: transformers raises many kinds
                why = (str(err).strip().splitlines() or [type(err).__name__])[0]
                raise ValueError(f"image_encoder_pretrained: cannot load a ResNet from {pretrained!r} "
                                 f"({type(err).__name__}: {why})") from None
            got = {k: getattr(self.resnet.config, k) for k in RESNET18}
            if {k: list(v) if isinstance(v, (list, tuple)) else v for k, v in got.items()} != RESNET18:
                raise ValueError(f"image_encoder_pretrained: expected a ResNet-18 ({RESNET18}), got {got} "
                                 f"from {pretrained!r}")
        else:
            self.resnet = ResNetModel(ResNetConfig(**RESNET18))
        self.frozen_batch_norm = pretrained is not None
        if not self.frozen_batch_norm:
            _swap_batch_norm(self.resnet)
        self.out_channels = RESNET18["hidden_sizes"][-1]
        self.train(self.training)       # a ResNet built from its config starts with BatchNorm in train mode

    def train(self, mode: bool = True) -> "ResNet18Backbone":
        super().train(mode)
        if self.frozen_batch_norm:          # pretrained running statistics are used, never updated
            for m in self.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self

    def forward(self, x: Tensor) -> Tensor:
        return self.resnet(pixel_values=x).last_hidden_state


class ImageEncoder(nn.Module):
    """forward(images [B, N_cam, 3, S, S] uint8 or float in [0, 1]) → tokens [B, N_cam·T, hidden_size].

    `load_pretrained=False` builds `image_encoder_pretrained`'s architecture without reading it (the
    weights then come from a policy checkpoint)."""

    def __init__(self, config: DecoderConfig, load_pretrained: bool = True) -> None:
        super().__init__()
        self.num_cameras, self.shift = len(config.cameras), config.image_shift
        self.backbone = ConvBackbone() if config.image_encoder == "conv" else \
            ResNet18Backbone(config.image_encoder_pretrained, load_pretrained)
        """The CNN: frames [B·N, 3, S, S] → feature maps [B·N, C, h, w] (conv or ResNet-18, GroupNorm)."""
        if config.freeze_image_encoder:
            self.backbone.requires_grad_(False)
        self.grid = token_grid(config.image_tokens_per_camera)
        """(rows, columns) of the pooled feature map: one token per cell (`token_grid`)."""
        hidden = config.hidden_size
        self.proj = nn.Linear(self.backbone.out_channels, hidden)
        """Projection of each cell's C features to the expert's hidden size."""
        self.cell_embed = nn.Parameter(torch.randn(config.image_tokens_per_camera, hidden) * 0.02)
        """[T, hidden]: learned embedding of each cell's position."""
        self.camera_embed = nn.Parameter(torch.randn(self.num_cameras, hidden) * 0.02)
        """[N_cam, hidden]: learned embedding of each camera."""
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def pixels(self, images: Tensor) -> Tensor:
        """[B, N, 3, S, S] → [B·N, 3, S, S] normalised (and shifted in train() mode), in the weights' dtype."""
        b, n = images.shape[:2]
        x = images.reshape(b * n, *images.shape[2:]).to(self.proj.weight.device)
        x = x.float() / 255.0 if not x.is_floating_point() else x.float()
        if self.training:
            x = random_shift(x, self.shift)
        return ((x - self.mean) / self.std).to(self.proj.weight.dtype)

    def forward(self, images: Tensor) -> Tensor:
        """[B, N_cam, 3, S, S] frames (uint8, or float in [0, 1]) → [B, N_cam·T, hidden] context tokens."""
        b, n = images.shape[:2]
        feats = self.backbone(self.pixels(images))                                   # [B·N, C, h, w]
        cells = F.adaptive_avg_pool2d(feats, self.grid).flatten(2).transpose(1, 2)   # [B·N, T, C]
        tokens = self.proj(cells) + self.cell_embed                                  # [B·N, T, hidden]
        tokens = tokens.view(b, n, *tokens.shape[1:]) + self.camera_embed[:, None]  # [B, N, T, hidden]
        return tokens.flatten(1, 2)                                                  # [B, N·T, hidden]
