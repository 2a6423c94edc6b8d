"""`ActionDecoderConfig`: LeRobot's config of the `action_decoder` policy type.

Defaults are those of `action-decoder train` (flow matching, 16-step chunks executed 4 at a
time, a 96-wide 3-layer Action Expert, AdamW at 1e-3 with 100 warm-up steps, cosine decay),
so `lerobot-train` and `action-decoder train` build the same network. Every field can be
set from the command line, e.g. `--policy.decoder_type=mean_flow --policy.flow_sde_use=true`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import lerobot
from lerobot.configs.policies import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamWConfig
from lerobot.optim.schedulers import DiffuserSchedulerConfig

from .convert import decoder_config, feature_dims


_LEROBOT_VERSION = getattr(lerobot, "__version__", "unknown")
_BASE_PINS_REVISION = "pretrained_revision" in PreTrainedConfig.__dataclass_fields__     # LeRobot >= 0.6


@PreTrainedConfig.register_subclass("action_decoder")
@dataclass
class ActionDecoderConfig(PreTrainedConfig):
    """The decoder (`DDPM`, `flow_matching`, `mean_flow`), its samplers and its network.

    `tasks` is filled from the dataset's task strings when the policy is built (ordered by
    task index) and saved in `config.json`: with two or more, the task string of each row
    conditions the policy (a one-hot context token). `num_inference_steps=None` is 10 steps
    for DDPM and flow matching and 1 for MeanFlow; `flow_prediction=None` is the clean-chunk
    head for MeanFlow and the velocity head otherwise. The SDE sampler (`flow_sde_*`) and its
    log-probs are reached through `ActionDecoderPolicy.predict_action_chunk(batch,
    sampler="sde", return_logprob=True)` whatever `flow_sde_use` says.
    """

    n_obs_steps: int = 1
    decoder_type: str = "flow_matching"
    chunk_size: int = 16
    n_action_steps: int = 4
    num_inference_steps: int | None = None
    flow_sde_num_steps: int = 10
    # DDPM
    num_train_timesteps: int = 1000
    prediction_type: str = "sample"
    beta_schedule: str = "squaredcos_cap_v2"
    clip_sample: bool = False
    # flow matching / MeanFlow head and SDE sampler
    flow_prediction: str | None = None
    flow_sde_use: bool = False
    flow_sde_mode: str = "churn"
    flow_sde_s_churn: float = 0.7
    flow_sde_learn_sigma: bool = False
    flow_sde_sigma_init: float = 1.0
    flow_sde_return_logprob: bool = False
    flow_sde_logprob_sigma_only: bool = True
    meanflow_sde_velocity: str = "boundary"
    # MeanFlow training recipe
    meanflow_ratio_r_neq_t: float = 0.25
    meanflow_time_dist: str = "uniform"
    meanflow_adaptive_p: float = 0.5
    meanflow_target: str | None = None     # None: "split" with rtc_max_delay > 0, else "identity" (the core's rule)
    meanflow_one_step_share: float | None = None   # None: 0.25 with rtc_max_delay > 0 and the split target, else 0
    # Action Expert
    hidden_size: int = 96
    num_hidden_layers: int = 3
    num_attention_heads: int = 4
    num_key_value_heads: int = 2
    # Cameras (`observation.images.*` input features): frames resized to image_size², encoded by the
    # core's image encoder ("conv" or "resnet18" with GroupNorm; a pretrained one from a directory or Hub id).
    image_size: int = 64
    image_encoder: str = "conv"
    image_tokens_per_camera: int = 4
    image_encoder_pretrained: str | None = None
    freeze_image_encoder: bool = False
    image_shift: int = 0
    # A noise actor steering the frozen decoder (`action-decoder finetune --algo dsrl`); 0: none, N(0, I) noise.
    noise_actor_hidden: int = 0
    noise_actor_bound: float = 2.5
    # Task strings, by task index (filled from the dataset).
    tasks: list[str] = field(default_factory=list)
    # The postprocessor clamps every action to the dataset's per-dimension [min, max] (its `action`
    # statistics), after un-normalising; saved in policy_postprocessor.json with the bounds.
    clip_actions: bool = True
    # The rest of the core's DecoderConfig, at its defaults (`action-decoder convert` carries a library
    # checkpoint's values): network, SDE and MeanFlow details, real-time chunking, control frequency.
    intermediate_size: int | None = None
    rms_norm_eps: float = 1e-6
    rope_theta: float = 10000.0
    flow_sde_eps: float = 1e-4
    flow_sde_clip_t: float = 1e-2
    flow_sde_t_min: float | None = None
    meanflow_time_mean: float = 0.4
    meanflow_time_std: float = 1.0
    meanflow_adaptive_c: float = 1e-3
    meanflow_dudt: str = "finite_difference"
    rtc_guidance_weight: float = 5.0
    rtc_schedule: str = "exp"
    rtc_horizon: str = "auto"
    rtc_max_delay: int = 0
    rtc_delay_dist: str = "exp"
    rtc_balance_rows: bool = False
    rtc_prefix_noise: float = 0.0
    default_ctrl_freq: float = 10.0

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD,
        }
    )

    # LeRobot >= 0.6 saves a Hub revision pin in every config.json; declared here where LeRobot's base
    # config lacks it (0.4.x), so checkpoints saved by 0.6+ load there too (0.4.x pins no revision).
    if not _BASE_PINS_REVISION:
        pretrained_revision: str | None = None

    optimizer_lr: float = 1e-3
    optimizer_betas: tuple[float, float] = (0.9, 0.999)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-4
    optimizer_grad_clip_norm: float = 1.0
    scheduler_warmup_steps: int = 100

    def __post_init__(self):
        super().__post_init__()
        if not _BASE_PINS_REVISION and self.pretrained_revision is not None:
            raise ValueError(f"policy.pretrained_revision: LeRobot {_LEROBOT_VERSION} loads no pinned Hub revision "
                             f"(LeRobot >= 0.6 does); got {self.pretrained_revision!r}, expected null")
        if isinstance(self.n_obs_steps, bool) or not isinstance(self.n_obs_steps, int) or self.n_obs_steps < 1:
            raise ValueError(f"policy.n_obs_steps: expected a positive integer number of observations (the current "
                             f"one and those before it), got {self.n_obs_steps!r}")
        visual = self.normalization_mapping.get("VISUAL", NormalizationMode.IDENTITY)
        if visual != NormalizationMode.IDENTITY:
            raise ValueError(f"policy.normalization_mapping: expected VISUAL: IDENTITY (the image encoder takes "
                             f"pixels in [0, 1] and normalises them itself), got VISUAL: {getattr(visual, 'value', visual)}")
        if not isinstance(self.clip_actions, bool):
            raise ValueError(f"policy.clip_actions: expected true or false, got {self.clip_actions!r}")
        decoder_config(self, state_dim=1, action_dim=1)     # raises on a bad value, naming the field

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, betas=self.optimizer_betas, eps=self.optimizer_eps,
                           weight_decay=self.optimizer_weight_decay, grad_clip_norm=self.optimizer_grad_clip_norm)

    def get_scheduler_preset(self) -> DiffuserSchedulerConfig:
        """Linear warm-up, then cosine decay to 0 over the run's steps (as `action-decoder train`)."""
        return DiffuserSchedulerConfig(name="cosine", num_warmup_steps=self.scheduler_warmup_steps)

    def validate_features(self) -> None:
        feature_dims(self.input_features, self.output_features)

    @property
    def observation_delta_indices(self) -> list[int] | None:
        if self.n_obs_steps == 1:
            return None                                     # the current frame only: state [B, S]
        return list(range(1 - self.n_obs_steps, 1))         # the last n frames: state [B, n, S], frames [B, n, 3, H, W]

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))                 # action [B, H, D] with action_is_pad [B, H]

    @property
    def reward_delta_indices(self) -> None:
        return None
