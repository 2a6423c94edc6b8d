"""`ActionDecoderPolicy`: the core `action_decoder.ActionDecoderPolicy` as a LeRobot policy.

The batch arrives normalised by LeRobot's preprocessor and the actions leave normalised for
its postprocessor, so the core policy is built with `normalization_mode="identity"`. Keys
are converted at the boundary (`convert.to_core_batch`): `observation.state` → `state`,
`action` → `actions` (padded steps hold the last real action), `observation.images.*` →
`images` (the core's image encoder; cameras in `input_features` order, resized to
`image_size`), task strings → the one-hot task token of a multi-task policy.
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
from typing import Any, Optional

import torch
from torch import Tensor

from action_decoder import ActionDecoderPolicy as CorePolicy
from action_decoder import PolicyOutput
from lerobot.policies.pretrained import PreTrainedPolicy

from .configuration_action_decoder import ActionDecoderConfig
from .convert import (camera_keys, decoder_config, feature_dims, rtc_prefix, rtc_settings, task_list, to_core_batch,
                      unused_inputs, unused_inputs_message)


# True while `from_pretrained` builds the policy: the checkpoint brings every weight, so a pretrained
# image encoder is not read again from its source (which an offline robot may not reach).
_FROM_CHECKPOINT = contextvars.ContextVar("action_decoder_from_checkpoint", default=False)


class ActionDecoderPolicy(PreTrainedPolicy):
    """DDPM, flow matching or MeanFlow (`config.decoder_type`) over the Action Expert.

    `forward(batch) -> (loss, {"loss": float})` trains; `select_action` pops from a queue of
    `n_action_steps` actions per sampled chunk; `predict_action_chunk(batch, sampler="sde",
    return_logprob=True)` returns the core `PolicyOutput` (`actions` [B, H, D] normalised,
    `log_prob` [B], `step_log_probs` [B, K], `chain`, `grid`) and `chain_log_prob` re-scores a
    chain (PPO). `self.decoder` is the core policy itself. Real-time chunking reaches the core
    through LeRobot's hook (`supports_rtc`, `predict_action_chunk(inference_delay=...,
    prev_chunk_left_over=...)`, which `lerobot-rollout --inference.type=rtc` calls).
    """

    config_class = ActionDecoderConfig
    name = "action_decoder"

    def __init__(self, config: ActionDecoderConfig, dataset_stats: Optional[dict] = None,
                 dataset_meta: Any = None, **kwargs: Any):
        super().__init__(config)
        config.validate_features()
        data_tasks = task_list(getattr(dataset_meta, "tasks", None)) if dataset_meta is not None else []
        if not config.tasks:
            config.tasks = data_tasks
        elif len(data_tasks) > 1 and not set(data_tasks) <= set(config.tasks):
            raise ValueError(f"policy.tasks: the dataset's tasks {sorted(set(data_tasks) - set(config.tasks))} are "
                             f"not among the {len(config.tasks)} this policy conditions on {list(config.tasks)}; its "
                             f"task token is fixed when it is built: train a new policy on this dataset")
        self.state_dim, action_dim = feature_dims(config.input_features, config.output_features)
        self.action_shape = (config.chunk_size, action_dim)
        message = unused_inputs_message(unused_inputs(config.input_features))
        if message:
            logging.warning(message)
        self.cameras = camera_keys(config.input_features)
        self.decoder = CorePolicy(decoder_config(config, self.state_dim, action_dim, self.cameras),
                                  load_pretrained=not _FROM_CHECKPOINT.get())

    @classmethod
    def from_pretrained(cls, *args: Any, **kwargs: Any) -> "ActionDecoderPolicy":
        """LeRobot's `from_pretrained`, building the core policy without reading a pretrained image
        encoder's source: the checkpoint holds its weights."""
        token = _FROM_CHECKPOINT.set(True)
        try:
            return super().from_pretrained(*args, **kwargs)
        finally:
            _FROM_CHECKPOINT.reset(token)

    def _core(self, batch: dict[str, Any], with_actions: bool) -> dict:
        return to_core_batch(batch, self.config.tasks, self.state_dim, with_actions, self.cameras,
                             self.config.image_size, self.action_shape, self.config.n_obs_steps)

    def get_optim_params(self) -> list:
        return [p for p in self.parameters() if p.requires_grad]

    def reset(self) -> None:
        self.decoder.reset()

    def forward(self, batch: dict[str, Any], reduction: str = "mean") -> tuple[Tensor, dict]:
        """The decoder's training loss on a LeRobot batch (normalised, with `action` chunks)."""
        if reduction != "mean":
            raise ValueError(f"reduction: expected 'mean' (the decoders' losses are batch means; per-sample "
                             f"losses for lerobot-train --sample_weighting are not available), got {reduction!r}")
        out = self.decoder.compute_loss(self._core(batch, with_actions=True))
        return out.loss, {"loss": out.loss.item()}

    def supports_rtc(self) -> bool:
        """LeRobot's real-time chunking hook: flow matching and MeanFlow guide a chunk towards the
        previous one's left-over; DDPM does not."""
        return self.config.decoder_type != "DDPM"

    @contextlib.contextmanager
    def _rtc_guidance(self, settings: Optional[tuple[float, str, int]]):
        """The core samples with LeRobot's RTC guidance weight and schedule while a call runs."""
        core = self.decoder.config
        saved = core.rtc_guidance_weight, core.rtc_schedule
        if settings is not None:
            core.rtc_guidance_weight, core.rtc_schedule = settings[0], settings[1]
        try:
            yield
        finally:
            core.rtc_guidance_weight, core.rtc_schedule = saved

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Any], sampler: Optional[str] = None,
                             steps: Optional[int] = None, return_logprob: bool = False,
                             generator=None, noise: Optional[Tensor] = None,
                             meanflow_velocity: Optional[str] = None, inference_delay: Optional[int] = None,
                             prev_chunk_left_over: Optional[Tensor] = None):
        """A chunk [B, H, D] in normalised units (LeRobot's postprocessor un-normalises), or the
        core `PolicyOutput` when log-probs are asked for (`sampler="sde", return_logprob=True`;
        `flow_sde_return_logprob` does not change what this returns).

        `prev_chunk_left_over` [T, D] or [B, T, D] (the previous chunk's unexecuted actions, normalised)
        and `inference_delay` (control steps that run while this chunk is sampled) are LeRobot's
        real-time chunking arguments (`convert.rtc_prefix`): the chunk's first `inference_delay`
        actions are the left-over's and the rest is guided towards it. LeRobot's `RTCConfig`, where
        it sets one as `config.rtc_config`, gives the guidance weight, schedule and execution horizon
        (`convert.rtc_settings`); otherwise `rtc_guidance_weight` and `rtc_schedule` do."""
        core = self._core(batch, with_actions=False)
        if prev_chunk_left_over is not None and not self.supports_rtc():
            raise ValueError(f"prev_chunk_left_over: real-time chunking needs a flow_matching or mean_flow "
                             f"decoder, got {self.config.decoder_type}")
        settings = rtc_settings(getattr(self.config, "rtc_config", None)) if prev_chunk_left_over is not None else None
        prev, delay = rtc_prefix(prev_chunk_left_over, inference_delay, core["state"].shape[0], *self.action_shape,
                                 horizon=settings[2] if settings else None)
        with self._rtc_guidance(settings):
            return self.decoder.predict_action_chunk(core, sampler, steps, return_logprob, generator, noise,
                                                     meanflow_velocity, prev_chunk=prev, delay=delay)

    def sample(self, batch: dict[str, Any], **kwargs: Any) -> PolicyOutput:
        """The core `sample` (differentiable; same arguments as `predict_action_chunk`)."""
        return self.decoder.sample(self._core(batch, with_actions=False), **kwargs)

    def chain_log_prob(self, batch: dict[str, Any], chain: Tensor, grid: Tensor, **kwargs: Any) -> Tensor:
        """Per-step log-probs [B, K] of an SDE chain under the current weights (PPO ratio)."""
        return self.decoder.chain_log_prob(self._core(batch, with_actions=False), chain, grid, **kwargs)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Any], generator=None, **kwargs: Any) -> Tensor:
        """One normalised action [B, D]; a chunk is sampled every `n_action_steps` calls. With `n_obs_steps`
        n > 1 every call's observation joins the core policy's history (its first one repeated at an
        episode's start, as LeRobot's observation queues; `reset()` starts it anew)."""
        if kwargs.get("noise") is not None:
            raise ValueError("noise: select_action samples its own chunks; pass noise to predict_action_chunk")
        return self.decoder.select_action(self._core(batch, with_actions=False), generator=generator)
