"""Pre- and post-processors of the `action_decoder` policy: LeRobot's own steps.

Before the policy: rename (none), add a batch dimension, move to the policy's device, and
normalise `observation.state` and `action` with the dataset's statistics
(`config.normalization_mapping`, mean/std by default). After it: un-normalise the action, clamp
it to the dataset's per-dimension [min, max] (`ClipActionsProcessorStep`, with
`config.clip_actions`) and move it to the CPU. The policy itself holds no statistics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import torch
from action_decoder.lerobot_checkpoint import CLIP_STEP
from lerobot.processor import (AddBatchDimensionProcessorStep, DeviceProcessorStep, NormalizerProcessorStep,
                               PolicyAction, PolicyProcessorPipeline, ProcessorStepRegistry,
                               RenameObservationsProcessorStep, UnnormalizerProcessorStep)
from lerobot.processor.pipeline import PolicyActionProcessorStep
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action
from lerobot.utils.constants import POLICY_POSTPROCESSOR_DEFAULT_NAME, POLICY_PREPROCESSOR_DEFAULT_NAME

from .configuration_action_decoder import ActionDecoderConfig


@ProcessorStepRegistry.register(CLIP_STEP)
@dataclass
class ClipActionsProcessorStep(PolicyActionProcessorStep):
    """Clamp actions [..., D] (environment units) to `min` and `max` [D], the dataset's action range.
    The bounds are the step's state (`policy_postprocessor_step_<i>_action_decoder_clip_actions.safetensors`);
    without them the step passes actions through."""

    min: Optional[torch.Tensor] = None
    max: Optional[torch.Tensor] = None

    @classmethod
    def from_stats(cls, stats: Optional[dict]) -> "ClipActionsProcessorStep":
        """The step of a dataset's `action` statistics (their `min` and `max`); no statistics: no bounds."""
        action = (stats or {}).get("action") or {}
        if action.get("min") is None or action.get("max") is None:
            return cls()
        low, high = (torch.as_tensor(action[k], dtype=torch.float32).flatten() for k in ("min", "max"))
        if low.shape != high.shape or not bool((low <= high).all()):
            raise ValueError(f"dataset_stats['action']: expected min <= max of one shape, got min {low.tolist()} "
                             f"and max {high.tolist()}")
        return cls(min=low, max=high)

    def action(self, action: PolicyAction) -> PolicyAction:
        if self.min is None or self.max is None:
            return action
        low, high = self.min.to(action.device, action.dtype), self.max.to(action.device, action.dtype)
        return torch.minimum(torch.maximum(action, low), high)

    def state_dict(self) -> dict[str, torch.Tensor]:
        if self.min is None or self.max is None:
            return {}
        return {"action.min": self.min.clone(), "action.max": self.max.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.min, self.max = state.get("action.min"), state.get("action.max")

    def transform_features(self, features):
        return features


def make_action_decoder_pre_post_processors(
    config: ActionDecoderConfig, dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None
) -> tuple[PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]]:
    features = {**config.input_features, **config.output_features}
    pre = [
        RenameObservationsProcessorStep(rename_map={}),
        AddBatchDimensionProcessorStep(),
        DeviceProcessorStep(device=config.device),
        NormalizerProcessorStep(features=features, norm_map=config.normalization_mapping, stats=dataset_stats),
    ]
    post = [
        UnnormalizerProcessorStep(features=config.output_features, norm_map=config.normalization_mapping,
                                  stats=dataset_stats),
        *([ClipActionsProcessorStep.from_stats(dataset_stats)] if config.clip_actions else []),
        DeviceProcessorStep(device="cpu"),
    ]
    return (
        PolicyProcessorPipeline[dict[str, Any], dict[str, Any]](steps=pre, name=POLICY_PREPROCESSOR_DEFAULT_NAME),
        PolicyProcessorPipeline[PolicyAction, PolicyAction](
            steps=post, name=POLICY_POSTPROCESSOR_DEFAULT_NAME,
            to_transition=policy_action_to_transition, to_output=transition_to_policy_action),
    )
