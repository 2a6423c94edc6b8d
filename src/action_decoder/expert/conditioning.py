"""Conditioning prefix: context tokens, camera tokens and/or a VLM's per-layer KV cache, projected once
per observation into every expert layer's keys and values and reused at each denoising step.

VLM layer mapping: expert layer i reads VLM layer round(i·(V−1)/(E−1)) (halves up) for E
expert and V VLM layers, so the first and last layers line up and the rest spread evenly
(identity when E = V; with E = 1 the last VLM layer). The cache is only read, never
updated: denoising steps must all see the same prefix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import torch
from torch import Tensor, nn

from ..config import DecoderConfig
from .layers import RMSNorm


@dataclass
class Prefix:
    """Per-expert-layer keys/values [B, Hkv, L, head_dim] and key mask [B, L] (True = valid)."""

    keys: tuple[Tensor, ...]
    values: tuple[Tensor, ...]
    mask: Tensor
    all_valid: bool = field(init=False)  # decided once here, so forward never syncs on it

    def __post_init__(self) -> None:
        self.mask = self.mask.bool()
        self.all_valid = bool(self.mask.all())

    @property
    def batch_size(self) -> int:
        return self.mask.shape[0]

    @property
    def length(self) -> int:
        return self.mask.shape[1]


def vlm_layer_for(i: int, expert_layers: int, vlm_layers: int) -> int:
    """The VLM layer whose cache feeds expert layer i (see module docstring)."""
    if expert_layers == 1:
        return vlm_layers - 1
    return math.floor(i * (vlm_layers - 1) / (expert_layers - 1) + 0.5)


def read_kv_layers(vlm_key_values: Any) -> list[tuple[Tensor, Tensor]]:
    """Per-layer (K, V) from a transformers `Cache` (its `layers[i].keys/.values`) or a
    sequence of (K, V) pairs, without touching the cache."""
    layers = getattr(vlm_key_values, "layers", None)
    if layers is not None:
        return [(layer.keys, layer.values) for layer in layers]
    if hasattr(vlm_key_values, "key_cache"):      # transformers < 4.54 keeps key_cache lists, no .layers
        raise ValueError("vlm_key_values: this transformers Cache has no .layers (transformers < 4.54); "
                         "install action-decoder[vlm] (transformers>=4.54) or pass a sequence of (K, V) pairs")
    if isinstance(vlm_key_values, Sequence) and not isinstance(vlm_key_values, Tensor):
        return [(pair[0], pair[1]) for pair in vlm_key_values]
    raise ValueError(f"vlm_key_values: expected a transformers Cache or a sequence of per-layer "
                     f"(K, V) pairs, got {type(vlm_key_values).__name__}")


def _key_mask(mask: Optional[Tensor], name: str, batch: int, length: int, device) -> Tensor:
    if mask is None:
        return torch.ones(batch, length, dtype=torch.bool, device=device)
    if tuple(mask.shape) != (batch, length):
        raise ValueError(f"{name}: expected shape [B, L] = [{batch}, {length}], got {list(mask.shape)}")
    return mask.to(device).bool()


class ConditioningEncoder(nn.Module):
    """Builds a `Prefix` from `context` [B, L, C], camera tokens [B, L_img, hidden_size] (from
    `ImageEncoder`) and/or `vlm_key_values` (per-layer K, V [B, vlm_num_key_value_heads, L,
    vlm_head_dim]) with GO-1-style per-layer k/v projections; the prefix's order is
    [context | cameras | VLM]."""

    def __init__(self, config: DecoderConfig) -> None:
        super().__init__()
        self.num_layers = config.num_hidden_layers
        self.num_kv_heads = config.num_key_value_heads
        self.head_dim = config.hidden_size // config.num_attention_heads
        self.context_dim = config.context_dim
        self.vlm_shape = (config.vlm_num_layers, config.vlm_num_key_value_heads, config.vlm_head_dim)
        kv_width = self.num_kv_heads * self.head_dim
        if config.context_dim is not None:
            # Context comes from arbitrary encoders at arbitrary scale: normalise first.
            self.context_norm = RMSNorm(config.context_dim, config.rms_norm_eps)
            self.context_kv = nn.Linear(config.context_dim, self.num_layers * 2 * kv_width, bias=False)
        if config.uses_cameras:
            self.image_norm = RMSNorm(config.hidden_size, config.rms_norm_eps)
            self.image_kv = nn.Linear(config.hidden_size, self.num_layers * 2 * kv_width, bias=False)
        if config.uses_vlm_cache:
            vlm_width = config.vlm_num_key_value_heads * config.vlm_head_dim
            self.vlm_k_proj = nn.ModuleList(nn.Linear(vlm_width, kv_width, bias=False)
                                            for _ in range(self.num_layers))
            self.vlm_v_proj = nn.ModuleList(nn.Linear(vlm_width, kv_width, bias=False)
                                            for _ in range(self.num_layers))
            self.vlm_layer_index = tuple(vlm_layer_for(i, self.num_layers, config.vlm_num_layers)
                                         for i in range(self.num_layers))

    def forward(self, context: Optional[Tensor] = None, context_mask: Optional[Tensor] = None,
                vlm_key_values: Any = None, attention_mask: Optional[Tensor] = None,
                image_tokens: Optional[Tensor] = None) -> Optional[Prefix]:
        """Prefix over [context tokens | camera tokens | VLM tokens], or None when none is given."""
        parts = []
        if context is not None:
            parts.append(self._from_context(context, context_mask))
        if image_tokens is not None:
            parts.append(self._tokens_kv(self.image_kv, self.image_norm(image_tokens),
                                         torch.ones(image_tokens.shape[:2], dtype=torch.bool, device=image_tokens.device)))
        if vlm_key_values is not None:
            parts.append(self._from_vlm(vlm_key_values, attention_mask))
        if not parts:
            return None
        if len({mask.shape[0] for _, _, mask in parts}) > 1:
            raise ValueError(f"context, images, vlm_key_values: batch sizes differ "
                             f"({[mask.shape[0] for _, _, mask in parts]})")
        keys = tuple(torch.cat([p[0][i] for p in parts], dim=2) for i in range(self.num_layers))
        values = tuple(torch.cat([p[1][i] for p in parts], dim=2) for i in range(self.num_layers))
        return Prefix(keys, values, torch.cat([p[2] for p in parts], dim=1))

    def _from_context(self, context: Tensor, context_mask: Optional[Tensor]):
        if self.context_dim is None:
            raise ValueError("context: this expert was built with context_dim=None; set "
                             "DecoderConfig.context_dim to condition on context tokens")
        if context.dim() != 3 or context.shape[-1] != self.context_dim:
            raise ValueError(f"context: expected shape [B, L, {self.context_dim}], got {list(context.shape)}")
        b, length, _ = context.shape
        mask = _key_mask(context_mask, "context_mask", b, length, context.device)   # [B, L]
        # Zero masked rows so that nothing (not even inf/NaN) leaks from them.
        context = torch.where(mask[..., None], context.to(self.context_kv.weight.dtype), 0.0)
        return self._tokens_kv(self.context_kv, self.context_norm(context), mask)

    def _tokens_kv(self, proj: nn.Linear, tokens: Tensor, mask: Tensor):
        """Tokens [B, L, W] → every layer's keys and values [B, Hkv, L, d] through one projection."""
        b, length, _ = tokens.shape
        kv = proj(tokens.to(proj.weight.dtype))                                   # [B, L, E·2·Hkv·d]
        kv = kv.view(b, length, self.num_layers, 2, self.num_kv_heads, self.head_dim)
        kv = kv.permute(2, 3, 0, 4, 1, 5)                                         # [E, 2, B, Hkv, L, d]
        return tuple(kv[:, 0]), tuple(kv[:, 1]), mask

    def _from_vlm(self, vlm_key_values: Any, attention_mask: Optional[Tensor]):
        if self.vlm_shape[0] is None:
            raise ValueError("vlm_key_values: this expert was built without vlm_num_layers, "
                             "vlm_head_dim, vlm_num_key_value_heads; set them in DecoderConfig")
        layers = read_kv_layers(vlm_key_values)
        n_layers, n_heads, head_dim = self.vlm_shape
        if len(layers) != n_layers:
            raise ValueError(f"vlm_key_values: expected {n_layers} layers (vlm_num_layers), got {len(layers)}")
        k0 = layers[0][0]
        if k0 is None or k0.dim() != 4 or tuple(k0.shape[1::2]) != (n_heads, head_dim):
            got = None if k0 is None else list(k0.shape)
            raise ValueError(f"vlm_key_values: expected per-layer K, V of shape "
                             f"[B, {n_heads}, L, {head_dim}], got {got}")
        b, _, length, _ = k0.shape
        mask = _key_mask(attention_mask, "attention_mask", b, length, k0.device)  # [B, L]
        keys, values = [], []
        for i, j in enumerate(self.vlm_layer_index):
            k, v = layers[j]
            if k.shape != k0.shape or v.shape != k0.shape:
                raise ValueError(f"vlm_key_values: layer {j} has K {list(k.shape)}, V {list(v.shape)}; "
                                 f"expected {list(k0.shape)} like layer 0")
            for name, x in (("K", k), ("V", v)):
                if not bool(torch.isfinite(x[mask[:, None, :, None].expand_as(x)]).all()):
                    raise ValueError(f"vlm_key_values: layer {j}'s {name} contains NaN or Inf at positions "
                                     f"attention_mask keeps (shape {list(x.shape)})")
            keys.append(self._project(self.vlm_k_proj[i], k, mask))
            values.append(self._project(self.vlm_v_proj[i], v, mask))
        return tuple(keys), tuple(values), mask

    def _project(self, proj: nn.Linear, x: Tensor, mask: Tensor) -> Tensor:
        """[B, Hv, L, dv] -> [B, Hkv, L, d]; masked positions zeroed first (new tensors: the cache is untouched)."""
        b, _, length, _ = x.shape
        x = torch.where(mask[:, None, :, None], x.to(proj.weight.dtype), 0.0)
        x = proj(x.transpose(1, 2).reshape(b, length, -1))                        # [B, L, Hkv·d]
        return x.view(b, length, self.num_kv_heads, self.head_dim).transpose(1, 2)
