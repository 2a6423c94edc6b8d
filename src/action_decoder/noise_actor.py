"""`NoiseActor`: a policy over the decoder's initial noise (diffusion steering, DSRL).

A behaviour-cloned decoder maps a noise chunk w [H, D] to an action chunk through its
deterministic sampler (flow-matching ODE, MeanFlow, DPM-Solver). Choosing w per state steers
the frozen decoder: every chunk it can emit stays one it learnt from the demonstrations, and
the noise actor, a small MLP, is all that RL trains (`rl/dsrl.py`).

The actor is a Gaussian over w, soft-bounded per element by b·tanh(w/b) (`bound`), which is
close to the identity inside ±b/2. Its output layer starts at zero mean and unit std, so the
untrained actor draws (nearly) the N(0, I) noise the decoder was trained on: it starts as the
BC policy. The policy is the stochastic actor (as DSRL evaluates it); `act` gives its bounded
mean, a deterministic alternative.

It reads the normalised state and, when the policy has context tokens, their masked mean; it
does not read a VLM cache or camera frames.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .flows.paths import Generators, randn_rows

LOG_STD_RANGE = (-5.0, 1.0)
"""Bounds of the actor's log std (tanh-scaled into the range, SAC's convention)."""


class NoiseActor(nn.Module):
    """π(w | state[, context]): Gaussian mean and log std of the noise chunk [B, H, D]."""

    def __init__(self, state_dim: int, context_dim: Optional[int], horizon: int, action_dim: int, hidden: int,
                 bound: float):
        super().__init__()
        self.horizon, self.action_dim, self.bound = horizon, action_dim, float(bound)
        inp = state_dim + (context_dim or 0)
        self.body = nn.Sequential(nn.Linear(inp, hidden), nn.LayerNorm(hidden), nn.SiLU(),
                                  nn.Linear(hidden, hidden), nn.SiLU())
        self.head = nn.Linear(hidden, 2 * horizon * action_dim)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        # log std = 0 at the start: the tanh-scaled pre-activation that gives it
        lo, hi = LOG_STD_RANGE
        with torch.no_grad():
            self.head.bias[horizon * action_dim:] = math.atanh(2 * (0.0 - lo) / (hi - lo) - 1)

    def forward(self, state: Tensor, context: Optional[Tensor] = None,
                context_mask: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        """state [B, S] (normalised), context [B, L, C] with mask [B, L] (True: kept) ->
        mean [B, H, D], log std [B, H, D]."""
        x = state
        if context is not None:
            keep = torch.ones(context.shape[:2], dtype=context.dtype, device=context.device) if context_mask is None \
                else context_mask.to(context.dtype)                                       # [B, L]
            pooled = (context * keep[..., None]).sum(1) / keep.sum(1, keepdim=True).clamp_min(1.0)   # [B, C]
            x = torch.cat([x, pooled], -1)
        out = self.head(self.body(x)).view(-1, 2, self.horizon, self.action_dim)
        lo, hi = LOG_STD_RANGE
        return out[:, 0], lo + 0.5 * (hi - lo) * (torch.tanh(out[:, 1]) + 1)

    def bounded(self, w: Tensor) -> Tensor:
        """b·tanh(w/b): the noise handed to the sampler, in (−b, b)."""
        return self.bound * torch.tanh(w / self.bound)

    def log_det(self, w: Tensor) -> Tensor:
        """log |d bounded / dw| per element [..., H, D] (stable for large |w|)."""
        u = w / self.bound
        return 2 * (math.log(2) - u - F.softplus(-2 * u))

    def sample(self, state: Tensor, context: Optional[Tensor] = None, context_mask: Optional[Tensor] = None,
               generator: Generators = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Reparameterised draw: (noise [B, H, D] in (−b, b), log-prob per element [B] (the mean over
        H·D of the bounded density's log), mean [B, H, D], log std [B, H, D]). `generator`: one
        torch.Generator or one per row, as for the policy's own noise."""
        mean, log_std = self(state, context, context_mask)
        eps = randn_rows(mean.shape[0], tuple(mean.shape[1:]), generator, mean.device, mean.dtype)
        w = mean + log_std.exp() * eps
        logp = -0.5 * eps.square() - log_std - 0.5 * math.log(2 * math.pi) - self.log_det(w)
        return self.bounded(w), logp.mean((-2, -1)), mean, log_std

    def act(self, state: Tensor, context: Optional[Tensor] = None, context_mask: Optional[Tensor] = None) -> Tensor:
        """The deterministic noise chunk [B, H, D]: the bounded mean."""
        return self.bounded(self(state, context, context_mask)[0])


def kl_to_prior(mean: Tensor, log_std: Tensor) -> Tensor:
    """KL(N(mean, std²) ‖ N(0, 1)) per element, averaged over H·D -> [B]: how far the actor's
    (unbounded) Gaussian has moved from the noise the decoder was trained on."""
    return (0.5 * (mean.square() + (2 * log_std).exp() - 1) - log_std).mean((-2, -1))
