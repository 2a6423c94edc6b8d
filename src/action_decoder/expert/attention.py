"""Grouped-query attention over [conditioning prefix K/V | the expert's own tokens].

Two backends compute the same function: `F.scaled_dot_product_attention` (fast) and an
explicit softmax ("eager"). SDPA's fused CPU/flash kernels have no forward-mode AD rule,
so under `torch.func.jvp` (MeanFlow's du/dt) or `torch.autograd.forward_ad` the "auto"
setting switches to the eager path.
"""

from __future__ import annotations

import torch
import torch.autograd.forward_ad as fwAD
import torch.nn.functional as F
from torch import Tensor, nn

from ..normalize import Float32Buffers

ATTN_IMPLEMENTATIONS = ("auto", "sdpa", "eager")


def forward_ad_active(*tensors: Tensor | None) -> bool:
    """True when forward-mode AD is tracing this call.

    Covers `torch.autograd.forward_ad` (a tensor carries a tangent at the current dual
    level) and `torch.func.jvp`/`jacfwd`/`linearize` at any nesting depth (a Jvp transform
    on functorch's interpreter stack, seen even where inner transforms hide the tangent).
    """
    if torch.compiler.is_compiling():   # compiled graphs (`compiled.py`) never run under forward-mode AD
        return False
    if any(t is not None and fwAD.unpack_dual(t).tangent is not None for t in tensors):
        return True
    stack = torch._C._functorch.get_interpreter_stack() or ()
    return any(level.key() == torch._C._functorch.TransformType.Jvp for level in stack)


def rotary_cos_sin(n: int, head_dim: int, theta: float, device: torch.device,
                   dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """cos, sin [n, head_dim] for positions 0..n-1 (rotate-half layout), at least float32."""
    dtype = torch.promote_types(dtype, torch.float32)
    inv_freq = theta ** (-torch.arange(0, head_dim, 2, device=device, dtype=dtype) / head_dim)
    angle = torch.arange(n, device=device, dtype=dtype)[:, None] * inv_freq[None, :]
    angle = torch.cat([angle, angle], dim=-1)                                   # [n, head_dim]
    return angle.cos(), angle.sin()


class RotaryTable(Float32Buffers):
    """`rotary_cos_sin` for positions 0..length-1, built once: `table(n, device, dtype)` slices it, and builds
    longer or float64 tables per call."""

    float32_buffers = ("cos", "sin")

    def __init__(self, length: int, head_dim: int, theta: float) -> None:
        super().__init__()
        self.head_dim, self.theta = head_dim, theta
        cos, sin = rotary_cos_sin(length, head_dim, theta, torch.device("cpu"), torch.float32)   # [length, head_dim]
        self.register_buffer("cos", cos, persistent=False)
        self.register_buffer("sin", sin, persistent=False)

    def table(self, n: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """cos, sin [n, head_dim] as `rotary_cos_sin(n, head_dim, theta, device, dtype)`."""
        if n <= self.cos.shape[0] and torch.promote_types(dtype, torch.float32) == self.cos.dtype \
                and self.cos.device == device:
            return (self.cos, self.sin) if n == self.cos.shape[0] else (self.cos[:n], self.sin[:n])
        return rotary_cos_sin(n, self.head_dim, self.theta, device, dtype)


def apply_rotary(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """x [B, heads, n, head_dim] rotated by its position."""
    x1, x2 = x.chunk(2, dim=-1)
    rotated = torch.cat([-x2, x1], dim=-1)
    return (x * cos + rotated * sin).to(x.dtype)


def eager_attention(q: Tensor, k: Tensor, v: Tensor, mask: Tensor | None) -> Tensor:
    """Explicit-softmax GQA. q [B, Hq, N, d]; k, v [B, Hkv, S, d]; mask [B, 1, 1, S] bool."""
    b, hq, n, d = q.shape
    hkv = k.shape[1]
    qg = q.view(b, hkv, hq // hkv, n, d)                     # query head h uses kv head h // group
    scores = qg @ k.unsqueeze(2).transpose(-1, -2) * d ** -0.5                  # [B, Hkv, g, N, S]
    if mask is not None:
        scores = scores.masked_fill(~mask.unsqueeze(1), float("-inf"))
    probs = scores.softmax(dim=-1, dtype=torch.promote_types(scores.dtype, torch.float32)).to(v.dtype)
    return (probs @ v.unsqueeze(2)).reshape(b, hq, n, d)


class GroupedQueryAttention(nn.Module):
    """Bidirectional GQA with rotary positions on the own tokens; prefix keys keep theirs.

    `attn_implementation`: "auto" (SDPA, eager under forward-mode AD), "sdpa" or "eager".
    """

    def __init__(self, hidden_size: int, num_heads: int, num_kv_heads: int) -> None:
        super().__init__()
        self.num_heads, self.num_kv_heads = num_heads, num_kv_heads
        self.head_dim = hidden_size // num_heads
        self.q_proj = nn.Linear(hidden_size, num_heads * self.head_dim, bias=False)
        self.k_proj = nn.Linear(hidden_size, num_kv_heads * self.head_dim, bias=False)
        self.v_proj = nn.Linear(hidden_size, num_kv_heads * self.head_dim, bias=False)
        self.o_proj = nn.Linear(num_heads * self.head_dim, hidden_size, bias=False)
        self.attn_implementation = "auto"

    def forward(self, h: Tensor, cos: Tensor, sin: Tensor, prefix_k: Tensor | None = None,
                prefix_v: Tensor | None = None, mask: Tensor | None = None) -> Tensor:
        """h [B, N, hidden]; prefix_k/v [B, Hkv, L, d]; mask [B, 1, 1, L+N] bool (None: all valid)."""
        b, n, _ = h.shape
        q = self.q_proj(h).view(b, n, self.num_heads, self.head_dim).transpose(1, 2)     # [B, Hq, N, d]
        k = self.k_proj(h).view(b, n, self.num_kv_heads, self.head_dim).transpose(1, 2)  # [B, Hkv, N, d]
        v = self.v_proj(h).view(b, n, self.num_kv_heads, self.head_dim).transpose(1, 2)
        q, k = apply_rotary(q, cos, sin), apply_rotary(k, cos, sin)
        if prefix_k is not None:
            k = torch.cat([prefix_k.to(k.dtype), k], dim=2)                      # [B, Hkv, L+N, d]
            v = torch.cat([prefix_v.to(v.dtype), v], dim=2)
        if self._use_eager(q, k, v):
            out = eager_attention(q, k, v, mask)
        else:
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, enable_gqa=True)
        return self.o_proj(out.transpose(1, 2).reshape(b, n, -1))

    def _use_eager(self, q: Tensor, k: Tensor, v: Tensor) -> bool:
        impl = self.attn_implementation
        if impl not in ATTN_IMPLEMENTATIONS:
            raise ValueError(f"attn_implementation: expected one of {list(ATTN_IMPLEMENTATIONS)}, got {impl!r}")
        return impl == "eager" or (impl == "auto" and forward_ad_active(q, k, v))
