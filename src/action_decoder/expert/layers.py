"""Pre-norm transformer block of the Action Expert: RMSNorm, SwiGLU MLP, GQA attention."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .attention import GroupedQueryAttention


class RMSNorm(nn.Module):
    """RMSNorm computed in float32 (stable under bf16), written out so forward-mode AD applies."""

    def __init__(self, dim: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(dim))

    def forward(self, x: Tensor) -> Tensor:
        x32 = x.to(torch.promote_types(x.dtype, torch.float32))
        x32 = x32 * torch.rsqrt(x32.pow(2).mean(-1, keepdim=True) + self.eps)
        return self.weight * x32.to(x.dtype)


class SwiGLU(nn.Module):
    """down(silu(gate(x)) * up(x))."""

    def __init__(self, hidden_size: int, intermediate_size: int) -> None:
        super().__init__()
        self.gate_proj = nn.Linear(hidden_size, intermediate_size, bias=False)
        self.up_proj = nn.Linear(hidden_size, intermediate_size, bias=False)
        self.down_proj = nn.Linear(intermediate_size, hidden_size, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.down_proj(F.silu(self.gate_proj(x)) * self.up_proj(x))


class ExpertBlock(nn.Module):
    """h + attn(norm(h)), then h + mlp(norm(h))."""

    def __init__(self, hidden_size: int, num_heads: int, num_kv_heads: int,
                 intermediate_size: int, eps: float) -> None:
        super().__init__()
        self.input_norm = RMSNorm(hidden_size, eps)
        self.attn = GroupedQueryAttention(hidden_size, num_heads, num_kv_heads)
        self.post_attn_norm = RMSNorm(hidden_size, eps)
        self.mlp = SwiGLU(hidden_size, intermediate_size)

    def forward(self, h: Tensor, cos: Tensor, sin: Tensor, prefix_k: Tensor | None,
                prefix_v: Tensor | None, mask: Tensor | None) -> Tensor:
        """h [B, N, hidden] -> [B, N, hidden]."""
        h = h + self.attn(self.input_norm(h), cos, sin, prefix_k, prefix_v, mask)
        return h + self.mlp(self.post_attn_norm(h))
