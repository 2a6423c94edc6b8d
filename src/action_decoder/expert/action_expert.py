"""The Action Expert (GO-1 style): a small transformer over [t, r, f, state, a_1..a_H] that
attends bidirectionally to its own tokens and to a conditioning prefix.

With observation history (`n_obs_steps` n > 1) the one state token becomes n, oldest first, each
with a learned step embedding, [t, r, f, s_1..s_n, a_1..a_H], and every frame's camera tokens join
the prefix with a step embedding of their own; n = 1 has neither embedding (the network as before).

The head's output is whatever the decoder trains it to be (velocity, MeanFlow average
velocity, DDPM ε or x0); the network does not know which.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import torch
from torch import Tensor, nn

from ..config import DecoderConfig
from .attention import ATTN_IMPLEMENTATIONS, RotaryTable
from .conditioning import ConditioningEncoder, Prefix
from .image_encoder import ImageEncoder
from .embeddings import FREQ_PERIODS, TIME_PERIODS, ScalarEmbedding
from .layers import ExpertBlock, RMSNorm


def default_intermediate_size(hidden_size: int) -> int:
    """SwiGLU's 8/3·hidden (same parameter count as a 4·hidden GELU MLP), rounded up to 8."""
    return 8 * math.ceil(8 * hidden_size / 3 / 8)


class ActionExpert(nn.Module):
    """forward(x, t, r, state, ctrl_freq=None, prefix=None, clean_rows=None) -> [B, H, action_dim].

    Set `attn_implementation` to "auto" (SDPA; explicit softmax under forward-mode AD),
    "sdpa" or "eager" (explicit softmax always).
    """

    def __init__(self, config: DecoderConfig, load_pretrained: bool = True) -> None:
        super().__init__()
        self.config = config
        hidden = config.hidden_size
        self.head_dim = hidden // config.num_attention_heads
        inter = config.intermediate_size or default_intermediate_size(hidden)
        self.t_embed = ScalarEmbedding(hidden, TIME_PERIODS)
        self.r_embed = ScalarEmbedding(hidden, TIME_PERIODS)
        self.freq_embed = ScalarEmbedding(hidden, FREQ_PERIODS)
        self.state_in = nn.Linear(config.state_input_dim, hidden)
        n_obs = config.n_obs_steps
        # [n, hidden]: which observation step a state token (and a frame's camera tokens) comes from.
        self.obs_step_embed = nn.Parameter(torch.randn(n_obs, hidden) * 0.02) if n_obs > 1 else None
        self.image_step_embed = nn.Parameter(torch.randn(n_obs, hidden) * 0.02) \
            if n_obs > 1 and config.uses_cameras else None
        self.action_in = nn.Linear(config.action_dim, hidden)
        self.conditioning = ConditioningEncoder(config)
        # Camera frames → tokens of the prefix (`load_pretrained`: read image_encoder_pretrained now).
        self.image_encoder = ImageEncoder(config, load_pretrained) if config.uses_cameras else None
        self.blocks = nn.ModuleList(
            ExpertBlock(hidden, config.num_attention_heads, config.num_key_value_heads, inter,
                        config.rms_norm_eps) for _ in range(config.num_hidden_layers))
        self.norm = RMSNorm(hidden, config.rms_norm_eps)
        self.head = nn.Linear(hidden, config.action_dim)
        # [t, r, f, s_1..s_n, a_1..a_H]: the rotary table of the config's own tokens (longer chunks build theirs).
        self.rotary = RotaryTable(3 + n_obs + config.action_chunk_size, self.head_dim, config.rope_theta)
        self._init_weights()

    def _init_weights(self) -> None:
        # Small normal init; residual outputs scaled by depth (GPT-2) so the residual
        # stream starts near its input; the head starts small so outputs start near 0.
        residual_std = 0.02 / math.sqrt(2 * self.config.num_hidden_layers)
        for name, module in self.named_modules():
            if isinstance(module, nn.Linear):
                std = residual_std if name.endswith(("o_proj", "down_proj")) else 0.02
                nn.init.normal_(module.weight, std=std)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

    @property
    def attn_implementation(self) -> str:
        return self.blocks[0].attn.attn_implementation

    @attn_implementation.setter
    def attn_implementation(self, value: str) -> None:
        if value not in ATTN_IMPLEMENTATIONS:
            raise ValueError(f"attn_implementation: expected one of {list(ATTN_IMPLEMENTATIONS)}, got {value!r}")
        for block in self.blocks:
            block.attn.attn_implementation = value

    def build_prefix(self, context: Optional[Tensor] = None, context_mask: Optional[Tensor] = None,
                     vlm_key_values: Any = None, attention_mask: Optional[Tensor] = None,
                     images: Optional[Tensor] = None) -> Optional[Prefix]:
        """Encode and project the conditioning once per observation; pass the result to every forward.
        `images` [B, N_cam, 3, S, S] (uint8, or float in [0, 1]) go through the image encoder; with
        `n_obs_steps` n > 1 they are [B, n, N_cam, 3, S, S], each frame encoded on its own."""
        tokens = None
        if images is not None:
            if self.image_encoder is None:
                raise ValueError("images: this expert was built without cameras; set DecoderConfig.cameras")
            if self.image_step_embed is None:
                tokens = self.image_encoder(images)                               # [B, N_cam·T, hidden]
            else:
                b, n = images.shape[:2]
                tokens = self.image_encoder(images.flatten(0, 1))                 # [B·n, N_cam·T, hidden]
                tokens = tokens.view(b, n, *tokens.shape[1:]) + self.image_step_embed[:, None]
                tokens = tokens.flatten(1, 2)                                     # [B, n·N_cam·T, hidden]
        return self.conditioning(context, context_mask, vlm_key_values, attention_mask, tokens)

    def forward(self, x: Tensor, t: Tensor, r: Tensor, state: Tensor,
                ctrl_freq: Optional[Tensor] = None, prefix: Optional[Prefix] = None,
                clean_rows: Optional[Tensor] = None) -> Tensor:
        """x [B, H, action_dim] noisy actions; t, r [B] in [0, 1] (r = t outside MeanFlow), or per
        action token [B, H] (training-time real-time chunking: the committed rows at t = r = 1);
        state [B, state_input_dim] (normalised, with the layout's features), or [B, n, state_input_dim]
        with `n_obs_steps` n > 1 (oldest first); ctrl_freq [B] Hz
        (None: config.default_ctrl_freq).

        Per-token times: the t and r tokens carry the earliest time of each sample (the rows
        still being generated), and each action token whose own time differs from it gets the
        difference of the two embeddings added; with all times of a sample equal this is the
        per-sample path exactly.

        `clean_rows` [B, H] bool, with t and r per sample: the marked action tokens are at t = r = 1
        (a committed prefix) and the others at t and r, r ≤ 1 — the per-token path for those times,
        with only three embeddings per sample (t, r and 1), which a graph with constant times folds away.
        Returns [B, H, action_dim] in x's dtype."""
        b, horizon, _ = self._check(x, state, prefix)
        dtype = self.head.weight.dtype
        t = self._time(t, b, horizon, x.device, "t")
        r = self._time(r, b, horizon, x.device, "r")
        if clean_rows is not None and (t.dim() != 1 or r.dim() != 1 or clean_rows.dtype != torch.bool
                                       or tuple(clean_rows.shape) != (b, horizon)):
            raise ValueError(f"clean_rows: expected a bool tensor [{b}, {horizon}] with t and r per sample [{b}], got "
                             f"{clean_rows.dtype} {list(clean_rows.shape)} with t {list(t.shape)}, r {list(r.shape)}")
        if ctrl_freq is None:
            ctrl_freq = torch.full((b,), self.config.default_ctrl_freq, device=x.device)
        ctrl_freq = self._per_sample(ctrl_freq, b, x.device, "ctrl_freq")
        actions = self.action_in(x.to(dtype))                                     # [B, H, hidden]
        if clean_rows is not None:   # the clean tokens' offset embed(1) − embed(earliest), as _token_times
            one = torch.ones_like(t)
            emb_t, emb_r = self.t_embed(torch.cat([t, one])), self.r_embed(torch.cat([r, one]))   # [2B, hidden] each
            t_tok, r_tok = emb_t[:b], emb_r[:b]
            shift = emb_t[b:] + emb_r[b:] - t_tok - r_tok                         # [B, hidden]
            actions = torch.where(clean_rows[..., None], actions + shift[:, None], actions)
        elif t.dim() == 1 and r.dim() == 1:
            t_tok, r_tok = self.t_embed(t), self.r_embed(r)                       # [B, hidden] each
        else:
            t_tok, r_tok, offsets = self._token_times(t, r, b, horizon)
            actions = actions + offsets
        if self.obs_step_embed is None:
            tokens = torch.cat([
                torch.stack([t_tok, r_tok, self.freq_embed(ctrl_freq),
                             self.state_in(state.to(dtype))], dim=1),             # [B, 4, hidden]
                actions,                                                          # [B, H, hidden]
            ], dim=1)                                                             # [B, N, hidden]
        else:
            states = self.state_in(state.to(dtype)) + self.obs_step_embed.to(dtype)  # [B, n, hidden]
            tokens = torch.cat([torch.stack([t_tok, r_tok, self.freq_embed(ctrl_freq)], dim=1),   # [B, 3, hidden]
                                states, actions], dim=1)                          # [B, 3 + n + H, hidden]
        n = tokens.shape[1]
        cos, sin = self.rotary.table(n, x.device, dtype)
        mask = None  # own tokens always see each other; only prefix keys may be masked
        if prefix is not None and not prefix.all_valid:
            own = torch.ones(b, n, dtype=torch.bool, device=x.device)
            mask = torch.cat([prefix.mask.to(x.device), own], dim=1)[:, None, None, :]  # [B, 1, 1, L+N]
        h = tokens
        for i, block in enumerate(self.blocks):
            pk = prefix.keys[i] if prefix is not None else None
            pv = prefix.values[i] if prefix is not None else None
            h = block(h, cos, sin, pk, pv, mask)
        return self.head(self.norm(h[:, n - horizon:])).to(x.dtype)

    def _check(self, x: Tensor, state: Tensor, prefix: Optional[Prefix]) -> tuple[int, int, int]:
        cfg = self.config
        if x.dim() != 3 or x.shape[-1] != cfg.action_dim:
            raise ValueError(f"x: expected shape [B, H, {cfg.action_dim}], got {list(x.shape)}")
        b = x.shape[0]
        want = (b, cfg.state_input_dim) if cfg.n_obs_steps == 1 else (b, cfg.n_obs_steps, cfg.state_input_dim)
        if tuple(state.shape) != want:
            raise ValueError(f"state: expected shape {list(want)}, got {list(state.shape)}")
        if prefix is not None:
            if prefix.batch_size != b:
                raise ValueError(f"prefix: expected batch size {b}, got {prefix.batch_size}")
            if len(prefix.keys) != len(self.blocks):
                raise ValueError(f"prefix: expected {len(self.blocks)} layers, got {len(prefix.keys)}")
        return x.shape[0], x.shape[1], x.shape[2]

    def _time(self, v: Tensor | float, b: int, horizon: int, device: torch.device, name: str) -> Tensor:
        """A time per sample [B] (a scalar is broadcast), or per action token [B, H] as given."""
        if isinstance(v, Tensor) and v.dim() == 2:
            if tuple(v.shape) != (b, horizon):
                raise ValueError(f"{name}: expected shape [{b}] or [{b}, {horizon}] (per action token), "
                                 f"got {list(v.shape)}")
            return v
        try:
            return self._per_sample(v, b, device, name)
        except ValueError:
            raise ValueError(f"{name}: expected shape [{b}] or [{b}, {horizon}] (per action token) or a scalar, "
                             f"got {list(v.shape)}") from None

    def _token_times(self, t: Tensor, r: Tensor, b: int, horizon: int) -> tuple[Tensor, Tensor, Tensor]:
        """(t token [B, hidden], r token [B, hidden], offsets [B, H, hidden]) of times per token ([B] or
        [B, H] each): each token embeds its sample's earliest time, and action token j is offset by
        embed_t(t_j) − embed_t(min t) + embed_r(r_j) − embed_r(min r), 0 where its times are the earliest.
        The two embeddings share their periods, so the sinusoidal features of all 2·B·(1 + H) times are
        computed once: the per-token path costs a handful of tensor operations over the per-sample one."""
        tr = torch.stack([v[:, None].expand(b, horizon) if v.dim() == 1 else v for v in (t, r)])   # [2, B, H]
        times = torch.cat([tr.amin(2, keepdim=True), tr], 2)                                # [2, B, 1 + H]
        feats = self.t_embed.features(times.reshape(-1)).view(2, b * (1 + horizon), -1)    # [2, B·(1 + H), hidden]
        emb_t = self.t_embed.project(feats[0]).view(b, 1 + horizon, -1)                    # [B, 1 + H, hidden]
        emb_r = self.r_embed.project(feats[1]).view(b, 1 + horizon, -1)
        both = emb_t + emb_r
        return emb_t[:, 0], emb_r[:, 0], both[:, 1:] - both[:, :1]

    @staticmethod
    def _per_sample(v: Tensor | float, b: int, device: torch.device, name: str) -> Tensor:
        """A float tensor [B]; a scalar is broadcast to the batch."""
        v = v if isinstance(v, Tensor) else torch.tensor(float(v), device=device)
        if v.dim() == 0:
            v = v.expand(b)
        if tuple(v.shape) != (b,):
            raise ValueError(f"{name}: expected shape [{b}] or a scalar, got {list(v.shape)}")
        return v
