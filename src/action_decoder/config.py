"""`DecoderConfig`: GO-1's Base config field names, validation, GO-1 import and JSON round-trip.

One time convention for the whole library: t = 0 is the Gaussian prior, t = 1 is data.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping, Optional

from .normalize import ACTION_CONSTANT_BELOW, SPREAD_FLOOR
from .state_layout import METAWORLD_LAYOUTS, METAWORLD_STATE_DIM, STATE_LAYOUTS, input_dim

DECODER_TYPES = ("DDPM", "flow_matching", "mean_flow")
PREDICTION_TYPES = ("epsilon", "sample")
FLOW_PREDICTIONS = ("velocity", "sample")
# The DDPM schedules diffusers' DDPMScheduler and DPMSolverMultistepScheduler both accept.
BETA_SCHEDULES = ("linear", "scaled_linear", "squaredcos_cap_v2")
SDE_MODES = ("churn", "fixed", "explore")
MEANFLOW_VELOCITIES = ("boundary", "identity")
MEANFLOW_DUDT = ("jvp", "finite_difference")
MEANFLOW_TARGETS = ("identity", "split")
NORMALIZATION_MODES = ("mean_std", "min_max", "identity")
RTC_SCHEDULES = ("exp", "linear", "ones", "zeros")     # flows.rtc.rtc_weights
RTC_HORIZONS = ("auto", "overlap", "execution")        # which rows of prev_chunk RTC guides
RTC_DELAY_DISTS = ("uniform", "exp", "half_zero")      # flows.rtc_trained.delay_probs
IMAGE_ENCODERS = ("conv", "resnet18")                   # expert/image_encoder.py
CAMERA_PREFIX = "observation.images."                   # LeRobot's camera feature keys
SINGLE_CAMERA_KEY = "observation.image"                 # LeRobot's key for a dataset's only camera (pusht, xarm)


def is_camera_key(key) -> bool:
    """`observation.images.<name>` or `observation.image`: a LeRobot camera feature."""
    return isinstance(key, str) and (key == SINGLE_CAMERA_KEY or
                                     key.startswith(CAMERA_PREFIX) and len(key) > len(CAMERA_PREFIX))
# Version of the config.json layout that `to_json` writes and `from_json` reads. Versions 2 and
# up carry every field of their version: a checkpoint is read back as it was trained, never
# completed with today's defaults (files without a version are version 1, no longer read).
CONFIG_FORMAT_VERSION = 10
# The fields each format version added, with the values that keep an older checkpoint's behaviour:
# a config.json of an older (still readable) version gets them filled in when it is read.
ADDED_FIELDS: dict[int, dict[str, Any]] = {
    3: {"rtc_guidance_weight": 5.0, "rtc_schedule": "exp", "meanflow_dudt": "jvp"},
    4: {"cameras": (), "image_size": 64, "image_encoder": "conv", "image_tokens_per_camera": 4,
        "image_encoder_pretrained": None, "freeze_image_encoder": False, "image_shift": 0,
        "rtc_horizon": "overlap"},
    5: {"meanflow_target": "identity"},
    6: {"action_constant_below": SPREAD_FLOOR, "action_squash": False},
    7: {"noise_actor_hidden": 0, "noise_actor_bound": 2.5, "clip_actions": False, "rtc_max_delay": 0},
    8: {"n_obs_steps": 1, "rtc_delay_dist": "uniform", "rtc_balance_rows": False},
    9: {"rtc_prefix_noise": 0.0},
    10: {"meanflow_one_step_share": 0.0},
}
OLDEST_FORMAT_VERSION = 2
# The fewest SDE steps that sample the trained marginals about as well as the Euler ODE at
# the same K. On N(0, 0.4²) chunks the SDE's std at K = 1, 2, 3, 10 is 0.74, 0.17, 0.23, 0.34
# (churn; the ODE: 0.00, 0.14, 0.22, 0.34) and 3.30, 0.55, 0.37, 0.38 (explore); on two modes at
# ±1 the energy distance at K = 3 is 0.060 (churn) and 0.022 (explore) against the ODE's 0.067.
SDE_MIN_STEPS = 3
GO1_DEFAULT_DECODER = "DDPM"
"""The decoder of a GO-1 Base config that names none (`DecoderConfig.from_go1`)."""


@dataclass
class DecoderConfig:
    """Everything that defines an action decoder: which decoder, its sampler, and the network.

    Field names of the first block follow GO-1's Base config so that GO-1 configs load as-is
    (`from_go1`); the defaults are this library's (flow matching, as `action-decoder train`), GO-1's
    Base config defaults to DDPM. `flow_sde_s_churn` is the noise level `s` of every SDE mode: churn
    `s·√(ε/(t+ε))`, fixed `s`, explore `s·√((1−t)/t)`.
    """

    # --- decoder (GO-1 Base config names) ---
    decoder_type: str = "flow_matching"
    """Which decoder: "DDPM", "flow_matching" or "mean_flow". The default is the CLI's (`train --decoder`);
    a checkpoint keeps the type it was trained with (config.json stores every field), and `from_go1`
    keeps GO-1's default, DDPM, for a GO-1 config that names none."""
    num_train_timesteps: int = 1000
    """DDPM: diffusion steps of the training noise schedule."""
    num_inference_timesteps: int = 10
    """Sampling steps K of the native sampler: the Euler ODE (flow matching), MeanFlow's steps, or DPM-Solver++ (DDPM)."""
    flow_sde_num_steps: int = 10
    """Steps of the SDE sampler (its own: MeanFlow's K = 1 is too few for an SDE)."""
    prediction_type: str = "sample"
    """DDPM: what the network predicts, "epsilon" (the noise) or "sample" (the clean chunk)."""
    clip_sample: bool = False
    """DDPM: clip the predicted clean chunk to [-1, 1] (only with min_max normalisation)."""
    beta_schedule: str = "squaredcos_cap_v2"
    """DDPM: the noise schedule, "linear", "scaled_linear" or "squaredcos_cap_v2" (diffusers' names)."""
    action_chunk_size: int = 16
    """H: actions per sampled chunk."""
    # --- SDE sampling for flow matching and MeanFlow ---
    flow_sde_use: bool = False
    """Sample with the marginal-preserving SDE by default instead of the ODE (flow_matching and mean_flow)."""
    flow_sde_mode: str = "churn"
    """The SDE's noise schedule σ(t) with level s = `flow_sde_s_churn`: "churn" s·√(ε/(t+ε)), "fixed" s,
    "explore" s·√((1−t)/t)."""
    flow_sde_s_churn: float = 0.7
    """s: the noise level of every SDE mode."""
    flow_sde_eps: float = 1e-4
    """ε of the churn schedule (how fast its noise fades as t grows)."""
    flow_sde_learn_sigma: bool = False
    """Learn a multiplier of σ(t) (a policy parameter, starting at `flow_sde_sigma_init`)."""
    flow_sde_sigma_init: float = 1.0
    """Initial value of the learnable σ multiplier."""
    flow_sde_clip_t: float = 1e-2
    """The SDE's times are clipped to [clip_t, 1 − clip_t] where σ(t) or the score would divide by t or 1 − t."""
    flow_sde_return_logprob: bool = False
    """Return each SDE chunk's log-probability (and per-step log-probs) by default."""
    flow_sde_logprob_sigma_only: bool = True
    """Log-probs pass gradients to σ only (the velocity network's output is detached in them)."""
    flow_sde_t_min: Optional[float] = None
    """"explore" clamps t at this time near the noise end; None: the first interior grid point."""
    meanflow_sde_velocity: str = "boundary"
    """The velocity a mean_flow decoder's ODE/SDE samplers integrate: "boundary" u(x, t, t), or
    "identity" u + (t − r)·du/dt by JVP (`flows.velocity_from_meanflow`)."""
    # --- MeanFlow training recipe (NOTES §2); times in our convention (t = 0 noise) ---
    meanflow_ratio_r_neq_t: float = 0.25
    """MeanFlow: fraction of training (t, r) pairs with r ≠ t."""
    meanflow_time_dist: str = "uniform"
    """MeanFlow: distribution of (t, r), "uniform" or "logit_normal" (the paper's)."""
    meanflow_time_mean: float = 0.4
    """MeanFlow, logit_normal: mean of the normal before the logistic."""
    meanflow_time_std: float = 1.0
    """MeanFlow, logit_normal: standard deviation of the normal before the logistic."""
    meanflow_adaptive_p: float = 0.5
    """MeanFlow: power p of the adaptive loss weight 1/(error + c)^p (0: plain MSE)."""
    meanflow_adaptive_c: float = 1e-3
    """MeanFlow: c of the adaptive loss weight 1/(error + c)^p."""
    meanflow_dudt: str = "finite_difference"
    """How MeanFlow training gets du/dt for the r ≠ t rows: "finite_difference" (a central difference
    over 2n shifted rows, in a no-grad second call on a CPU or under autocast, which then runs in
    float32, inside u's call on CUDA; float32/float64 weights only) or "jvp" (exact, forward-mode AD;
    any dtype). The two train alike; their cost is measured in docs/benchmarks/meanflow_cost.md.
    Format-2 files, older than the field, read as "jvp"."""
    meanflow_target: Optional[str] = None
    """The r ≠ t rows' regression target (`flows.losses.meanflow_loss`): "identity", the MeanFlow
    identity v − (t − r)·du/dt (`meanflow_dudt` applies); "split", interval consistency λ·u(z, t, s)
    + (1 − λ)·u(z_s, s, r) from two no-grad calls, no du/dt (docs/benchmarks/meanflow_ablations.md).
    None (resolved on construction and saved resolved): "split" for a mean_flow decoder trained with
    real-time chunking (`rtc_max_delay` > 0), whose one-step chunk under a committed prefix the identity
    does not learn on every task (docs/benchmarks/rtc.md), "identity" otherwise.
    Format-4 files, older than the field, read as "identity"."""
    meanflow_one_step_share: Optional[float] = None
    """MeanFlow: the share of the r ≠ t training rows set to the whole interval (t, r) = (0, 1), the jump a
    1-step chunk makes (`flows.losses.sample_meanflow_times`); ordered uniform pairs land near it rarely.
    None (resolved on construction and saved resolved): 0.25 for a mean_flow decoder trained with real-time
    chunking and the split target, whose one-step chunk then follows a weakly informative committed prefix
    (docs/benchmarks/rtc.md), 0 otherwise (without a prefix the identity target collapses to one mode with
    such rows; docs/benchmarks/meanflow_ablations.md). Format-9 files read 0."""
    flow_prediction: str = "velocity"
    """What the flow matching / MeanFlow head outputs: "velocity" itself, or "sample", the clean chunk x̂
    from which v = (x̂ − x)/(1 − t) (`velocity_from_sample`), so that no step has to carry the noise."""
    # --- real-time chunking (`flows/rtc.py`; used when a previous chunk is passed to sampling) ---
    rtc_guidance_weight: float = 5.0
    """RTC β: the clip of the guidance weight (the paper's 5; 0: no guidance, only the frozen prefix):
    flow matching's min(β, (1 − t)/(t·r_t²), 1/Δt), MeanFlow's min(β, 1/(1 − t))."""
    rtc_schedule: str = "exp"
    """How RTC's guidance weights decay over the overlap after the frozen prefix: "exp" (the paper),
    "linear", "ones" (the whole overlap as strongly as the prefix), "zeros" (only the prefix)."""
    rtc_horizon: str = "auto"
    """The rows RTC guides after the d frozen ones: "overlap" (the paper: every row prev_chunk covers,
    H − s) or "execution" (only those the new chunk executes before the next plan: rows < d + s,
    s = n_action_steps; later rows are re-planned anyway and stay free). "auto": overlap for flow
    matching, whose Jᵀ-guidance is re-projected by the later steps, and execution for MeanFlow,
    whose guidance pulls the chunk itself (docs/benchmarks/rtc.md measures both)."""
    rtc_max_delay: int = 0
    """Training-time RTC (`flows/rtc_trained.py`): the largest delay d, in control steps, whose committed
    prefix the network was trained to continue (each training chunk's first d actions, d on 0..max from
    `rtc_delay_dist`, given clean at t = 1, the loss on the rest); 0: not trained so. Sampling with a previous chunk then feeds
    the prefix in (`rtc_mode="trained"`) instead of guiding. Below action_chunk_size; not for DDPM.
    Format-6 files, older than the field, read as 0."""
    rtc_delay_dist: str = "exp"
    """How training-time RTC draws each chunk's delay d on 0..rtc_max_delay (`flows.rtc_trained.delay_probs`):
    "exp" (P(d) ∝ e^(−d): short prefixes more often, so the first rows, which a chunk without a prefix
    executes, stay in the loss of most chunks) or "uniform" (docs/benchmarks/rtc.md compares them).
    Format-7 files, older than the field, read as "uniform"."""
    rtc_balance_rows: bool = False
    """Training-time RTC: weight row j of the prefix-masked loss by 1/P(d ≤ j), so that each row's expected
    weight is the plain loss's (row j is in the loss only when d ≤ j). Format-7 files read False."""
    rtc_prefix_noise: float = 0.0
    """Training-time RTC: std of Gaussian noise added to the committed prefix the network is fed, in normalised
    action units (the loss targets stay the clean actions), so that it learns to continue a prefix that an older
    plan made and the current observation may contradict (docs/benchmarks/rtc.md screens it); 0: the clean
    prefix. Format-8 files read 0."""
    # --- the Action Expert network ---
    state_dim: int = 39
    """Width of `batch["state"]` (Meta-World's 39 by default)."""
    action_dim: int = 4
    """D: width of each action."""
    hidden_size: int = 128
    """Width of the Action Expert transformer."""
    num_hidden_layers: int = 4
    """Transformer layers."""
    num_attention_heads: int = 4
    """Attention heads (hidden_size / heads must be even, for rotary positions)."""
    num_key_value_heads: int = 2
    """Key/value heads (grouped-query attention; a divisor of num_attention_heads)."""
    intermediate_size: Optional[int] = None
    """Width of the SwiGLU feed-forward (None: 8/3·hidden_size, rounded to a multiple of 8)."""
    rms_norm_eps: float = 1e-6
    """ε of the RMS norms."""
    rope_theta: float = 10000.0
    """Base of the rotary position embedding."""
    # --- conditioning (None: not used) ---
    context_dim: Optional[int] = None
    """Width C of `batch["context"]` tokens [B, L, C] (None: no context tokens; a multi-task policy's one-hot
    task token has C = the number of tasks)."""
    vlm_num_layers: Optional[int] = None
    """Layers of the VLM whose KV cache (`batch["vlm_key_values"]`) conditions the expert (None: none)."""
    vlm_head_dim: Optional[int] = None
    """Head dim of that VLM's keys and values (projected per layer to the expert's)."""
    vlm_num_key_value_heads: Optional[int] = None
    """Key/value heads of that VLM's cache."""
    # --- cameras (expert/image_encoder.py; none: no image encoder) ---
    cameras: tuple = ()
    """LeRobot camera feature keys, e.g. "observation.images.corner2" (or a dataset's single
    "observation.image"); `batch["images"]` [B, N_cam, 3, S, S] stacks them in this order (empty: no cameras)."""
    image_size: int = 64
    """S: side of the square camera frames, in pixels."""
    image_encoder: str = "conv"
    """The camera backbone: "conv" (small, GroupNorm) or "resnet18" (transformers, GroupNorm)."""
    image_tokens_per_camera: int = 4
    """Context tokens per camera: pooled cells of the feature map."""
    image_encoder_pretrained: Optional[str] = None
    """resnet18 only: a local directory or Hub id of a ResNet-18 (`ResNetModel.from_pretrained`), read when
    the policy is built for training; its BatchNorm statistics stay frozen."""
    freeze_image_encoder: bool = False
    """Keep the backbone's weights fixed (the tokens' projection trains)."""
    image_shift: int = 0
    """Training-time random shift of camera frames: pad by this many pixels, crop back (0: none;
    measured in docs/benchmarks/cameras.md)."""
    # --- policy ---
    n_obs_steps: int = 1
    """Observations the policy conditions on: the current one and the n − 1 before it (LeRobot's
    `n_obs_steps`). With n > 1 `batch["state"]` is [B, n, state_dim] (oldest first) and `batch["images"]`
    [B, n, N_cam, 3, S, S]; each step is a state token (and camera tokens) with a learned step embedding.
    At an episode's start the first observation stands in for the missing ones (`history.ObservationHistory`).
    1: the current observation only, the network of format-7 files, which read as 1."""
    n_action_steps: int = 4
    """Actions executed from each chunk before re-planning (at most action_chunk_size; re-planning rates
    are compared in docs/benchmarks/metaworld_bc_n8.md)."""
    normalization_mode: str = "mean_std"
    """How states and actions reach the network: "mean_std", "min_max" (to [-1, 1]) or "identity"
    (normalised outside, e.g. by LeRobot's processors)."""
    action_constant_below: float = ACTION_CONSTANT_BELOW
    """An action dimension whose spread (std for mean_std, half range for min_max) is below this is
    constant and is divided by the floor `normalize.SPREAD_FLOOR` (0.01) instead; any other keeps its
    own spread, so an end-effector delta of std 0.003 reaches the network at unit scale. State
    dimensions take the floor below 0.01. Format-5 files, older than the field, read as 0.01 (every
    action spread floored at 0.01)."""
    action_squash: bool = False
    """tanh on every sampled chunk in environment units, into (−1, 1): what a policy fine-tuned with
    SAC executes (`rl.sde_policy.squash_to_box`), so that evaluating it samples what was trained.
    Format-5 files, older than the field, read as False."""
    clip_actions: bool = True
    """Clamp every sampled chunk, in environment units, to the per-dimension [min, max] of the action
    statistics the policy was built with (the training data's range; no statistics: no clamp), so a
    robot with hard limits never receives an action its demonstrations never reached. With
    `action_squash` the tanh bounds the chunk instead (to (−1, 1), the env's box). Format-6 files,
    older than the field, read as False."""
    noise_actor_hidden: int = 0
    """Width of a noise actor (`noise_actor.NoiseActor`, trained by `finetune --algo dsrl`): an MLP that maps
    the state (and pooled context tokens) to a Gaussian over the sampler's initial noise chunk, which the
    decoder's deterministic sampler turns into the chunk. 0: none; the noise is N(0, I). Format-6 files read 0."""
    noise_actor_bound: float = 2.5
    """The noise actor's noise lies in (−b, b) per element (b·tanh(w/b), close to w inside ±b/2)."""
    state_layout: str = "flat"
    """What the state is: "flat" (as given), "metaworld" (relative positions appended) or
    "metaworld_proprio" (the hand and gripper only, for camera policies; state_layout.py)."""
    default_ctrl_freq: float = 10.0
    """Control frequency in Hz the network is told when `batch["ctrl_freq"]` is not given."""
    extra: dict = field(default_factory=dict)
    """Free-form JSON data carried through save/load: the trained task names ("tasks"), the training
    options ("train"), the data's size ("data"), a dataset run's held-out validation ("validation")."""

    def __post_init__(self) -> None:
        if self.meanflow_target is None:
            self.meanflow_target = "split" if self.decoder_type == "mean_flow" and self.rtc_max_delay else "identity"
        if self.meanflow_one_step_share is None:
            self.meanflow_one_step_share = 0.25 if (self.decoder_type == "mean_flow" and self.rtc_max_delay
                                                    and self.meanflow_target == "split") else 0.0
        self.validate()

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        """Raise ValueError naming the first field with a value outside its allowed ones (run on construction)."""
        _choice("decoder_type", self.decoder_type, DECODER_TYPES)
        _choice("prediction_type", self.prediction_type, PREDICTION_TYPES)
        _choice("beta_schedule", self.beta_schedule, BETA_SCHEDULES)
        _choice("flow_sde_mode", self.flow_sde_mode, SDE_MODES)
        _choice("normalization_mode", self.normalization_mode, NORMALIZATION_MODES)
        _choice("state_layout", self.state_layout, STATE_LAYOUTS)
        _choice("meanflow_time_dist", self.meanflow_time_dist, ("logit_normal", "uniform"))
        _choice("flow_prediction", self.flow_prediction, FLOW_PREDICTIONS)
        _choice("meanflow_sde_velocity", self.meanflow_sde_velocity, MEANFLOW_VELOCITIES)
        _choice("rtc_schedule", self.rtc_schedule, RTC_SCHEDULES)
        _choice("rtc_horizon", self.rtc_horizon, RTC_HORIZONS)
        _choice("rtc_delay_dist", self.rtc_delay_dist, RTC_DELAY_DISTS)
        if not isinstance(self.rtc_balance_rows, bool):
            raise ValueError(f"rtc_balance_rows: expected true or false, got {self.rtc_balance_rows!r}")
        _positive_float("rtc_guidance_weight", self.rtc_guidance_weight, allow_zero=True)
        _positive_float("rtc_prefix_noise", self.rtc_prefix_noise, allow_zero=True)
        if isinstance(self.rtc_max_delay, bool) or not isinstance(self.rtc_max_delay, int) or self.rtc_max_delay < 0:
            raise ValueError(f"rtc_max_delay: expected a non-negative integer number of control steps (0: no "
                             f"training-time RTC), got {self.rtc_max_delay!r}")
        if self.rtc_max_delay and self.decoder_type == "DDPM":
            raise ValueError(f"rtc_max_delay: training-time real-time chunking needs a flow_matching or mean_flow "
                             f"decoder (DPM-Solver++ samples one time per chunk), got decoder_type='DDPM' with "
                             f"rtc_max_delay={self.rtc_max_delay}")
        _choice("meanflow_dudt", self.meanflow_dudt, MEANFLOW_DUDT)
        _choice("meanflow_target", self.meanflow_target, MEANFLOW_TARGETS)
        share = self.meanflow_one_step_share
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share <= 1.0:
            raise ValueError(f"meanflow_one_step_share: expected a fraction of the r != t rows in [0, 1] (None: the "
                             f"resolved default), got {share!r}")
        if self.flow_sde_t_min is not None:
            _finite("flow_sde_t_min", self.flow_sde_t_min)
            if not 0.0 < self.flow_sde_t_min <= 1.0:
                raise ValueError(f"flow_sde_t_min: expected None (the first interior grid point) or a "
                                 f"time in (0, 1], got {self.flow_sde_t_min!r}")
        for name in ("num_train_timesteps", "num_inference_timesteps", "flow_sde_num_steps", "action_chunk_size",
                     "state_dim", "action_dim", "hidden_size", "num_hidden_layers",
                     "num_attention_heads", "num_key_value_heads", "n_obs_steps", "n_action_steps"):
            _positive_int(name, getattr(self, name))
        for name in ("intermediate_size", "context_dim", "vlm_num_layers", "vlm_head_dim",
                     "vlm_num_key_value_heads"):
            if getattr(self, name) is not None:
                _positive_int(name, getattr(self, name))
        for name in ("flow_sde_s_churn", "flow_sde_eps", "flow_sde_sigma_init", "flow_sde_clip_t",
                     "meanflow_time_std", "meanflow_adaptive_c", "rms_norm_eps", "rope_theta",
                     "default_ctrl_freq"):
            _positive_float(name, getattr(self, name))
        _positive_float("meanflow_adaptive_p", self.meanflow_adaptive_p, allow_zero=True)
        _positive_float("action_constant_below", self.action_constant_below, allow_zero=True)
        if isinstance(self.noise_actor_hidden, bool) or not isinstance(self.noise_actor_hidden, int) or \
                self.noise_actor_hidden < 0:
            raise ValueError(f"noise_actor_hidden: expected a width >= 0 (0: no noise actor), "
                             f"got {self.noise_actor_hidden!r}")
        _positive_float("noise_actor_bound", self.noise_actor_bound)
        if self.n_obs_steps > 1 and self.noise_actor_hidden:
            raise ValueError(f"noise_actor_hidden: the noise actor reads one state; expected 0 with n_obs_steps="
                             f"{self.n_obs_steps}, got {self.noise_actor_hidden}")
        _finite("meanflow_time_mean", self.meanflow_time_mean)
        if not 0.0 <= self.meanflow_ratio_r_neq_t <= 1.0:
            raise ValueError(f"meanflow_ratio_r_neq_t: expected a fraction in [0, 1], "
                             f"got {self.meanflow_ratio_r_neq_t!r}")
        if self.flow_sde_clip_t >= 1.0:
            raise ValueError(f"flow_sde_clip_t: expected a value in (0, 1), got {self.flow_sde_clip_t!r}")
        if self.rtc_max_delay >= self.action_chunk_size:
            raise ValueError(f"rtc_max_delay: expected fewer control steps than action_chunk_size="
                             f"{self.action_chunk_size} (rows must remain to generate), got {self.rtc_max_delay}")
        if self.n_action_steps > self.action_chunk_size:
            raise ValueError(f"n_action_steps: expected at most action_chunk_size="
                             f"{self.action_chunk_size}, got {self.n_action_steps}")
        if self.hidden_size % self.num_attention_heads:
            raise ValueError(f"hidden_size: expected a multiple of num_attention_heads="
                             f"{self.num_attention_heads}, got {self.hidden_size}")
        if (self.hidden_size // self.num_attention_heads) % 2:
            raise ValueError(f"hidden_size: head dim hidden_size/num_attention_heads must be even "
                             f"for rotary positions, got {self.hidden_size}/{self.num_attention_heads}")
        if self.num_attention_heads % self.num_key_value_heads:
            raise ValueError(f"num_key_value_heads: expected a divisor of num_attention_heads="
                             f"{self.num_attention_heads}, got {self.num_key_value_heads}")
        vlm = (self.vlm_num_layers, self.vlm_head_dim, self.vlm_num_key_value_heads)
        if any(v is not None for v in vlm) and any(v is None for v in vlm):
            raise ValueError("vlm_num_layers, vlm_head_dim, vlm_num_key_value_heads: expected all "
                             f"three set or all None, got {vlm}")
        for name in ("clip_sample", "flow_sde_use", "flow_sde_learn_sigma", "flow_sde_return_logprob",
                     "flow_sde_logprob_sigma_only", "action_squash", "clip_actions"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        if self.clip_sample and self.normalization_mode == "mean_std":
            raise ValueError("clip_sample: clips DDPM's predicted chunk to [-1, 1], the range of "
                             "normalization_mode='min_max' (or of an outside min-max normaliser with 'identity'); "
                             "with normalization_mode='mean_std' it would cut every action beyond one std "
                             "(set clip_sample=False or normalization_mode='min_max')")
        if self.flow_sde_use and self.decoder_type == "DDPM":
            raise ValueError("flow_sde_use: the SDE sampler serves flow_matching and mean_flow; "
                             "decoder_type='DDPM' samples with DPM-Solver (set flow_sde_use=False)")
        if self.state_layout in METAWORLD_LAYOUTS and self.state_dim != METAWORLD_STATE_DIM:
            raise ValueError(f"state_dim: state_layout={self.state_layout!r} expects Meta-World's "
                             f"{METAWORLD_STATE_DIM}-d state, got state_dim={self.state_dim}")
        if not isinstance(self.extra, dict):
            raise ValueError(f"extra: expected a dict, got {type(self.extra).__name__}")
        try:
            json.dumps(self.extra, sort_keys=True)
        except (TypeError, ValueError) as err:
            raise ValueError(f"extra: expected JSON data (string keys; lists, numbers, strings, bools, None), "
                             f"saved in config.json; got {err}") from None
        self._validate_cameras()

    def _validate_cameras(self) -> None:
        cams = self.cameras
        if isinstance(cams, str) or not isinstance(cams, (list, tuple)) or \
                not all(is_camera_key(c) for c in cams):
            raise ValueError(f"cameras: expected a list of LeRobot camera keys '{CAMERA_PREFIX}<name>' or "
                             f"'{SINGLE_CAMERA_KEY}' (empty: no cameras), got {cams!r}")
        if len(set(cams)) != len(cams):
            raise ValueError(f"cameras: expected distinct camera keys, got {list(cams)}")
        self.cameras = tuple(cams)
        _choice("image_encoder", self.image_encoder, IMAGE_ENCODERS)
        for name in ("image_size", "image_tokens_per_camera"):
            _positive_int(name, getattr(self, name))
        if self.image_size < 16:
            raise ValueError(f"image_size: expected at least 16 pixels, got {self.image_size}")
        if isinstance(self.image_shift, bool) or not isinstance(self.image_shift, int) or \
                not 0 <= self.image_shift < self.image_size // 2:
            raise ValueError(f"image_shift: expected an integer number of pixels in [0, image_size/2 = "
                             f"{self.image_size // 2}), got {self.image_shift!r}")
        if not isinstance(self.freeze_image_encoder, bool):
            raise ValueError(f"freeze_image_encoder: expected True or False, got {self.freeze_image_encoder!r}")
        pre = self.image_encoder_pretrained
        if pre is not None and (not isinstance(pre, str) or not pre):
            raise ValueError(f"image_encoder_pretrained: expected None or a local directory or Hub id, got {pre!r}")
        if pre is not None and self.image_encoder != "resnet18":
            raise ValueError(f"image_encoder_pretrained: loads a ResNet-18; expected image_encoder='resnet18', "
                             f"got image_encoder={self.image_encoder!r}")

    # ------------------------------------------------------------------ derived
    @property
    def default_sampler(self) -> str:
        """"sde" when flow_sde_use, else "ode": what `sample` uses when no sampler is named."""
        return "sde" if self.flow_sde_use else "ode"

    @property
    def state_input_dim(self) -> int:
        """Width of what the network reads: the normalised state and the layout's features."""
        return input_dim(self.state_layout, self.state_dim)

    @property
    def uses_vlm_cache(self) -> bool:
        """Whether a VLM's KV cache conditions the expert (vlm_num_layers is set)."""
        return self.vlm_num_layers is not None

    @property
    def uses_cameras(self) -> bool:
        """Whether camera frames condition the expert (cameras is not empty)."""
        return len(self.cameras) > 0

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict:
        """Every field by name (`extra` included), as `to_json` writes them."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], complete: bool = False) -> "DecoderConfig":
        """Build from a dict of fields. In user code (`complete=False`) a missing field takes
        its default, as in `DecoderConfig(...)`. `complete=True` (checkpoints, `from_json`)
        asks for every field and the current `format_version`: a field missing from a saved
        config would otherwise silently change the behaviour of the weights it was saved with."""
        data = dict(data)
        version = data.pop("format_version", None)
        readable = range(OLDEST_FORMAT_VERSION, CONFIG_FORMAT_VERSION + 1)
        if version is not None and (isinstance(version, bool) or version not in readable):
            raise ValueError(f"DecoderConfig: expected format_version {OLDEST_FORMAT_VERSION}..{CONFIG_FORMAT_VERSION}, "
                             f"got {version!r} (written by another version of action-decoder)")
        for added in range(version or CONFIG_FORMAT_VERSION, CONFIG_FORMAT_VERSION):
            for key, value in ADDED_FIELDS.get(added + 1, {}).items():
                data.setdefault(key, value)
        known = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(known))
        if unknown:
            raise ValueError(f"DecoderConfig: unknown field(s) {unknown}; known fields are "
                             f"{sorted(known)}")
        missing = [k for k in known if k not in data] + (["format_version"] if version is None else [])
        if complete and missing:
            raise ValueError(f"DecoderConfig: missing field(s) {missing}; expected every field of format_version "
                             f"{CONFIG_FORMAT_VERSION}, got format_version {version}: write them in with the "
                             f"values its weights were trained with")
        return cls(**data)

    def to_json(self, path: str | Path) -> None:
        """Every field and the `format_version`, so that `from_json` needs no default."""
        data = {"format_version": CONFIG_FORMAT_VERSION, **self.to_dict()}
        Path(path).write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")

    @classmethod
    def from_json(cls, path: str | Path) -> "DecoderConfig":
        """Read a config written by `to_json`; a missing field or another format_version raises."""
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as err:
            raise ValueError(f"config: cannot read a DecoderConfig JSON from {path}: {err}") from None
        if not isinstance(data, dict):
            raise ValueError(f"config: expected a JSON object in {path}, got {type(data).__name__}")
        try:
            return cls.from_dict(data, complete=True)
        except ValueError as err:
            raise ValueError(f"config: {path}: {err}") from None

    @classmethod
    def from_go1(cls, args: Any, **overrides: Any) -> "DecoderConfig":
        """Read a GO-1 model-arguments object (any attribute holder) or dict.

        Fields of ours found on `args` are taken; GO-1's other fields are ignored. GO-1's
        `state_token_num` and `ctrl_freqs` describe the old prefix and are not needed here.
        """
        src = dict(args) if isinstance(args, Mapping) else dict(vars(args))
        known = {f.name for f in fields(cls)} - {"extra"}
        values = {k: src[k] for k in known if k in src}
        # GO-1 names the action dimension and chunk length differently in places.
        aliases = {"action_dim": ("action_dims",), "action_chunk_size": ("action_chunk", "chunk_size"),
                   "state_dim": ("state_dims",)}
        for ours, theirs in aliases.items():
            for name in theirs:
                if ours not in values and name in src:
                    values[ours] = src[name]
        values.setdefault("decoder_type", GO1_DEFAULT_DECODER)
        values.update(overrides)
        return cls(**values)


def _choice(name: str, value: Any, allowed: tuple) -> None:
    if value not in allowed:
        raise ValueError(f"{name}: expected one of {list(allowed)}, got {value!r}")


def _positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")


def _positive_float(name: str, value: Any, allow_zero: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        kind = "a non-negative" if allow_zero else "a positive"
        raise ValueError(f"{name}: expected {kind} finite number, got {value!r}")


def _finite(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
