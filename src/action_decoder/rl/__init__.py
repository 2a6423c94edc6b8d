"""RL fine-tuning of flow decoders through their SDE sampler (PPO on chains, SAC-style).

A behaviour-cloned flow-matching or MeanFlow policy explores through σ(t) while its learned
marginals stay put; these modules turn the per-step Gaussian densities of
the denoising chain into policy-gradient (PPO) or reparameterised (SAC) updates.
"""

from .finetune import FinetuneConfig, finetune

__all__ = ["FinetuneConfig", "finetune"]
