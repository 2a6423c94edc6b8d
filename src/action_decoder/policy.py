"""`ActionDecoderPolicy`: binds the Action Expert to the math of `flows/`.

It validates and normalises a batch, builds the conditioning prefix once per chunk, hands
bound callables to a loss or a sampler, un-normalises the actions and queues them. The
network knows nothing of sampling; the samplers know nothing of the network.
"""

from __future__ import annotations

import json
import math
import numbers
import re
import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

import torch
from huggingface_hub import PyTorchModelHubMixin
from torch import Tensor, nn

from . import model_card
from .config import MEANFLOW_VELOCITIES, SDE_MIN_STEPS, DecoderConfig
from .expert import ActionExpert, Prefix
from .flows import (chain_log_prob, ddpm_loss, flow_matching_loss, make_sigma, meanflow_loss,
                    sample_ddpm, sample_meanflow, sample_meanflow_prefix, sample_meanflow_rtc, sample_ode,
                    sample_ode_prefix, sample_ode_rtc, sample_sde, sample_sde_rtc, velocity_from_meanflow,
                    velocity_from_sample)
from .flows.paths import Generators, randn_rows
from .flows.rtc_trained import check_delays
from .flows.samplers import gaussian_target_std
from .history import ObservationHistory
from .noise_actor import NoiseActor
from .normalize import make_normalizers
from .state_layout import network_state

SAMPLERS = (None, "ode", "sde", "euler")
RTC_MODES = (None, "trained", "guided")
CONFIG_NAME, WEIGHTS_NAME = "config.json", "model.safetensors"


@dataclass
class PolicyOutput:
    """Training: `loss` (+ `metrics`). Sampling: `actions` [B, H, D] in environment units and,
    when asked, `log_prob` [B] / `step_log_probs` [B, K] (densities of the normalised chunk,
    float32) and the SDE `chain` [B, K+1, H, D] (normalised) with its `grid` [K+1]."""

    loss: Optional[Tensor] = None
    """Training: the scalar loss to back-propagate."""
    actions: Optional[Tensor] = None
    """Sampling: [B, H, D] actions in environment units."""
    log_prob: Optional[Tensor] = None
    """Sampling with log-probs: [B] density of the normalised chunk (the sum of `step_log_probs`)."""
    step_log_probs: Optional[Tensor] = None
    """Sampling with log-probs: [B, K] the log-density of each SDE step."""
    chain: Optional[Tensor] = None
    """SDE sampling with log-probs: [B, K+1, H, D] the chain's states, normalised, from noise to chunk."""
    grid: Optional[Tensor] = None
    """SDE sampling with log-probs: [K+1] the chain's times, from 0 (noise) to 1 (data)."""
    metrics: dict = field(default_factory=dict)
    """Training: values to log (floats)."""


@dataclass
class Bound:
    """The network bound to one batch's conditioning: the callables the math consumes."""

    velocity: Callable[[Tensor, Tensor], Tensor]
    avg_velocity: Callable[[Tensor, Tensor, Tensor], Tensor]
    model_output: Callable[[Tensor, Tensor], Tensor]
    batch_size: int
    # What the ODE/SDE samplers integrate: the FM head, or MeanFlow's u turned into a velocity
    # ("boundary" u(x, t, r=t) or "identity", `meanflow_sde_velocity`).
    flow_velocity: Optional[Callable[[Tensor, Tensor], Tensor]] = None


class ActionDecoderPolicy(nn.Module, PyTorchModelHubMixin, library_name=model_card.LIBRARY_NAME,
                          pipeline_tag="robotics", tags=["robotics", model_card.LIBRARY_NAME]):
    """A LeRobot-style policy over any of the three decoders (the API reference and the getting-started
    guide in `docs/` describe it). Checkpoints use the Hub's `PyTorchModelHubMixin` layout
    (`save_pretrained`, `from_pretrained`, `push_to_hub`)."""

    def __init__(self, config: DecoderConfig, stats: Optional[Mapping[str, Mapping]] = None, *,
                 load_pretrained: bool = True):
        """`load_pretrained=False` leaves `config.image_encoder_pretrained` unread (its architecture is
        built; the weights come from a checkpoint, as in `from_pretrained`)."""
        super().__init__()
        if not isinstance(config, DecoderConfig):
            raise ValueError(f"config: expected a DecoderConfig, got {type(config).__name__}")
        self.config = config
        """The `DecoderConfig` (saved as config.json)."""
        self.model = ActionExpert(config, load_pretrained)
        """The Action Expert network (`expert.ActionExpert`)."""
        self.normalizers = make_normalizers(config.state_dim, config.action_dim,
                                            config.normalization_mode, stats, config.action_constant_below)
        """"state" and "actions" normalisers (`normalize.Normalizer`), their statistics saved with the weights."""
        self.sigma = make_sigma(config)
        """The SDE's noise schedule σ(t), a submodule so that a learnable σ is a policy parameter."""
        self.noise_actor = NoiseActor(config.state_dim, config.context_dim, config.action_chunk_size,
                                      config.action_dim, config.noise_actor_hidden, config.noise_actor_bound) \
            if config.noise_actor_hidden else None
        """The initial-noise policy of a noise-space fine-tuned checkpoint (`finetune --algo dsrl`), or None."""
        self._queue: deque = deque()
        self.history = ObservationHistory(config.n_obs_steps)
        """The last `n_obs_steps` observations `select_action` was given (`history.ObservationHistory`)."""
        self._warned_proxy = self._warned_steps = self._warned_blend = False

    # ------------------------------------------------------------------ batch handling
    def _validate(self, batch: Mapping[str, Any], need_actions: bool) -> None:
        cfg = self.config
        if not isinstance(batch, Mapping):
            raise ValueError(f"batch: expected a dict of tensors, got {type(batch).__name__}")
        n = cfg.n_obs_steps
        want = f"[B, {cfg.state_dim}]" if n == 1 else f"[B, {n}, {cfg.state_dim}] (n_obs_steps={n} observations, oldest first)"
        state = _tensor(batch, "state", want)
        if list(state.shape[1:]) != ([cfg.state_dim] if n == 1 else [n, cfg.state_dim]):
            hint = "" if n == 1 or state.dim() != 2 else "; stack the last observations with history.ObservationHistory"
            raise ValueError(f"batch['state']: expected shape {want}, got {list(state.shape)}{hint}")
        _finite(state, "state")
        b = state.shape[0]
        if b == 0:
            raise ValueError(f"batch['state']: expected at least one row {want.replace('[B,', '[B >= 1,', 1)}, "
                             f"got {list(state.shape)}")
        if need_actions:
            shape = [b, cfg.action_chunk_size, cfg.action_dim]
            actions = _tensor(batch, "actions", str(shape))
            if list(actions.shape) != shape:
                raise ValueError(f"batch['actions']: expected shape {shape}, got {list(actions.shape)}")
            _finite(actions, "actions")
        if batch.get("ctrl_freq") is not None:
            f = batch["ctrl_freq"]
            if not isinstance(f, Tensor) or list(f.shape) != [b]:
                got = list(f.shape) if isinstance(f, Tensor) else type(f).__name__
                raise ValueError(f"batch['ctrl_freq']: expected a tensor of shape [{b}], got {got}")
            if f.dtype == torch.bool or not bool((torch.isfinite(f.double()) & (f > 0)).all()):
                raise ValueError(f"batch['ctrl_freq']: expected finite positive control frequencies in Hz, got "
                                 f"{f.tolist() if f.numel() <= 8 else f'{f.dtype} values outside (0, inf)'}")
        if batch.get("context") is not None:
            ctx = batch["context"]
            want = f"[{b}, L, {cfg.context_dim}]"
            if cfg.context_dim is None:
                raise ValueError("batch['context']: this policy has context_dim=None; set "
                                 "DecoderConfig.context_dim to condition on context tokens")
            if not isinstance(ctx, Tensor) or ctx.dim() != 3 or ctx.shape[0] != b or ctx.shape[2] != cfg.context_dim:
                got = list(ctx.shape) if isinstance(ctx, Tensor) else type(ctx).__name__
                raise ValueError(f"batch['context']: expected shape {want}, got {got}")
            mask = batch.get("context_mask")
            if mask is not None and (not isinstance(mask, Tensor) or list(mask.shape) != list(ctx.shape[:2])):
                got = list(mask.shape) if isinstance(mask, Tensor) else type(mask).__name__
                raise ValueError(f"batch['context_mask']: expected shape {list(ctx.shape[:2])}, got {got}")
            keep = ctx if mask is None else ctx[mask.to(torch.bool)]
            if not bool(torch.isfinite(keep).all()):
                raise ValueError(f"batch['context']: contains NaN or Inf at positions the context_mask keeps "
                                 f"(shape {list(ctx.shape)})")
        for key, pairs in (("context_mask", "context"), ("attention_mask", "vlm_key_values")):
            if batch.get(key) is not None and batch.get(pairs) is None:
                other = {"context_mask": "batch['attention_mask'] pairs with vlm_key_values",
                         "attention_mask": "for context tokens use batch['context_mask']"}[key]
                raise ValueError(f"batch[{key!r}]: masks batch[{pairs!r}], which is missing; {other}")
        self._validate_images(batch, b)
        tasks = cfg.extra.get("tasks")
        tasks = list(tasks) if isinstance(tasks, (list, tuple)) else []
        conditioned = cfg.context_dim is not None or cfg.uses_vlm_cache
        if len(tasks) > 1 and conditioned and batch.get("context") is None and batch.get("vlm_key_values") is None:
            shown = tasks if len(tasks) <= 10 else tasks[:10] + [f"... ({len(tasks)} in all)"]
            raise ValueError(f"batch['context']: missing; this policy was trained on {len(tasks)} tasks {shown} "
                             f"and needs its task token, else it samples unconditioned: pass "
                             f"batch['context'] = action_decoder.train.task_context(task_index [B], {len(tasks)})"
                             f"['context'] ([B, 1, {len(tasks)}] one-hot; task_index = position in "
                             f"config.extra['tasks']) or the batch's vlm_key_values")

    def _validate_images(self, batch: Mapping[str, Any], b: int) -> None:
        """`images` [B, N_cam, 3, S, S] ([B, n, N_cam, 3, S, S] with n_obs_steps n > 1): uint8 (0..255) or
        floating point in [0, 1], cameras in config order."""
        cfg = self.config
        images = batch.get("images")
        if not cfg.uses_cameras:
            if images is not None:
                raise ValueError("batch['images']: this policy has no cameras (DecoderConfig.cameras is empty); "
                                 "drop the images or train a policy with cameras")
            return
        n, s, steps = len(cfg.cameras), cfg.image_size, cfg.n_obs_steps
        lead = [b] if steps == 1 else [b, steps]
        want = f"{[*lead, n, 3, s, s]} (batch, {'' if steps == 1 else 'observation steps, '}cameras " \
               f"{list(cfg.cameras)}, RGB, image_size²), uint8 or float in [0, 1]"
        if images is None:
            raise ValueError(f"batch['images']: missing; this policy conditions on cameras; expected a tensor {want}")
        if not isinstance(images, Tensor) or list(images.shape) != [*lead, n, 3, s, s] or \
                not (images.dtype == torch.uint8 or images.is_floating_point()):
            got = f"{list(images.shape)} {images.dtype}" if isinstance(images, Tensor) else type(images).__name__
            raise ValueError(f"batch['images']: expected a tensor {want}, got {got}")
        if images.is_floating_point():
            low, high = float(images.min()), float(images.max())
            if not (0.0 <= low and high <= 1.0):     # NaN fails too
                raise ValueError(f"batch['images']: expected floating-point pixels in [0, 1] (or uint8 0..255), "
                                 f"got values in [{low:.4g}, {high:.4g}]")

    def _check_noise(self, batch: Mapping[str, Any], noise: Tensor) -> None:
        """`noise` must be one chunk per state row: a shorter chunk would come back short."""
        self._validate(batch, need_actions=False)
        cfg = self.config
        shape = [batch["state"].shape[0], cfg.action_chunk_size, cfg.action_dim]
        if not isinstance(noise, Tensor) or not noise.is_floating_point() or list(noise.shape) != shape:
            got = f"{list(noise.shape)} {noise.dtype}" if isinstance(noise, Tensor) else type(noise).__name__
            raise ValueError(f"noise: expected a floating-point tensor of shape {shape} (batch, action_chunk_size, "
                             f"action_dim), got {got}")
        if not torch.isfinite(noise).all():
            raise ValueError(f"noise: contains NaN or Inf (shape {shape})")

    def _prepare(self, batch: Mapping[str, Any]) -> dict:
        """Normalised state, ctrl_freq and the conditioning prefix (built once: camera frames are
        encoded here, once per chunk)."""
        param = next(self.model.parameters())
        raw = batch["state"].to(param.device, torch.float32)
        state = network_state(self.config.state_layout, self.normalizers["state"].normalize(raw), raw)
        ctrl = batch.get("ctrl_freq")
        prefix = self.model.build_prefix(
            context=_to(batch.get("context"), param.device), context_mask=_to(batch.get("context_mask"), param.device),
            vlm_key_values=batch.get("vlm_key_values"), attention_mask=_to(batch.get("attention_mask"), param.device),
            images=_to(batch.get("images"), param.device))
        return {"state": state, "ctrl_freq": None if ctrl is None else ctrl.to(param.device, torch.float32),
                "prefix": prefix}

    def _net(self, x: Tensor, t: Tensor, r: Tensor, state: Tensor, ctrl_freq: Optional[Tensor],
             prefix: Optional[Prefix]) -> Tensor:
        return self.model(x, t, r, state, ctrl_freq=ctrl_freq, prefix=prefix)

    def _flow_net(self, x: Tensor, t: Tensor, r: Tensor, **cond) -> Tensor:
        """The FM/MeanFlow head as a velocity, whatever `flow_prediction` the network outputs."""
        out = self._net(x, t, r, **cond)
        return out if self.config.flow_prediction == "velocity" else velocity_from_sample(x, t, out)

    def _ddpm_time(self, timestep: Tensor) -> Tensor:
        # diffusers' step 0 is data, T−1 noise; ours t = 1 is data.
        return 1.0 - timestep.float() / self.config.num_train_timesteps

    def _meanflow_velocity(self, meanflow_velocity: Optional[str]) -> str:
        mode = self.config.meanflow_sde_velocity if meanflow_velocity is None else meanflow_velocity
        if mode not in MEANFLOW_VELOCITIES:
            raise ValueError(f"meanflow_velocity: expected one of {list(MEANFLOW_VELOCITIES)} or None "
                             f"(the config's meanflow_sde_velocity), got {meanflow_velocity!r}")
        return mode

    def bind(self, batch: Mapping[str, Any], meanflow_velocity: Optional[str] = None) -> Bound:
        """Validate and normalise `batch`, build its prefix once, return the bound callables.

        `meanflow_velocity` ("boundary" | "identity", None: `config.meanflow_sde_velocity`)
        picks how a mean_flow decoder's `flow_velocity` is made from u.
        """
        mode = self._meanflow_velocity(meanflow_velocity)
        self._validate(batch, need_actions=False)
        cond = self._prepare(batch)
        state, ctrl, prefix = cond["state"], cond["ctrl_freq"], cond["prefix"]
        bound = Bound(
            velocity=lambda x, t: self._flow_net(x, t, t, **cond),
            avg_velocity=lambda x, t, r: self._flow_net(x, t, r, **cond),
            model_output=lambda x, s: self._net(x, self._ddpm_time(s), self._ddpm_time(s), state, ctrl, prefix),
            batch_size=state.shape[0])
        if self.config.decoder_type == "flow_matching":
            bound.flow_velocity = bound.velocity
        elif self.config.decoder_type == "mean_flow":
            bound.flow_velocity = velocity_from_meanflow(bound.avg_velocity, mode)
        return bound

    # ------------------------------------------------------------------ training
    def compute_loss(self, batch: Mapping[str, Any], generator: Optional[torch.Generator] = None) -> PolicyOutput:
        """The decoder's training loss on `batch` ("state", "actions" [B, H, D] in environment units, and
        its conditioning); times and noise drawn from `generator`. `PolicyOutput.loss` and `.metrics`.

        With training-time RTC (`rtc_max_delay` M > 0) an optional "rtc_delays" [B] (integers in 0..M) fixes
        how many of each chunk's first actions are its committed prefix (a relabelled dataset's
        `action.prefix_length`); 0 leaves that row's delay drawn from `rtc_delay_dist`."""
        self._validate(batch, need_actions=True)
        delays = self._rtc_delays(batch)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise ValueError(f"generator: the loss draws its times and noise from one torch.Generator (or None), "
                             f"got {type(generator).__name__} (per-row generators are for sampling)")
        cond = self._prepare(batch)
        actions = self.normalizers["actions"].normalize(batch["actions"].to(cond["state"].device, torch.float32))
        cfg = self.config
        if cfg.decoder_type == "flow_matching":
            loss = flow_matching_loss(lambda x, t, **c: self._flow_net(x, t, t, **c), actions, generator, cond,
                                      rtc_max_delay=cfg.rtc_max_delay, rtc_delay_dist=cfg.rtc_delay_dist,
                                      rtc_balance_rows=cfg.rtc_balance_rows, rtc_prefix_noise=cfg.rtc_prefix_noise,
                                      rtc_delays=delays)
        elif cfg.decoder_type == "mean_flow":
            weights = self.model.head.weight.dtype
            if (cfg.meanflow_target == "identity" and cfg.meanflow_dudt == "finite_difference"
                    and weights not in (torch.float32, torch.float64)):
                raise ValueError(f"meanflow_dudt: 'finite_difference' needs float32 or float64 weights, got "
                                 f"{weights} (set meanflow_dudt='jvp' to train in lower precision)")
            loss = meanflow_loss(self._flow_net, actions, generator, cond,
                                 ratio_r_neq_t=cfg.meanflow_ratio_r_neq_t, time_mean=cfg.meanflow_time_mean,
                                 time_std=cfg.meanflow_time_std, adaptive_p=cfg.meanflow_adaptive_p,
                                 adaptive_c=cfg.meanflow_adaptive_c, time_dist=cfg.meanflow_time_dist,
                                 dudt=cfg.meanflow_dudt, target=cfg.meanflow_target,
                                 one_step_share=cfg.meanflow_one_step_share,
                                 rtc_max_delay=cfg.rtc_max_delay, rtc_delay_dist=cfg.rtc_delay_dist,
                                 rtc_balance_rows=cfg.rtc_balance_rows, rtc_prefix_noise=cfg.rtc_prefix_noise,
                                 rtc_delays=delays)
        else:
            loss = ddpm_loss(lambda x, s, **c: self._net(x, self._ddpm_time(s), self._ddpm_time(s), **c),
                             actions, cfg, generator, cond)
        return PolicyOutput(loss=loss, metrics={"loss": loss.detach()})

    def _rtc_delays(self, batch: Mapping[str, Any]) -> Optional[Tensor]:
        """`batch["rtc_delays"]` [B] checked against `rtc_max_delay` (the loss moves it to the chunk's device);
        None without it."""
        given = batch.get("rtc_delays")
        if given is None:
            return None
        return check_delays(given, batch["state"].shape[0], self.config.rtc_max_delay, "batch['rtc_delays']")

    # ------------------------------------------------------------------ sampling
    def resolve_sampler(self, sampler: Optional[str]) -> str:
        """The runtime choice overrides the config in both directions; unsafe mixes raise."""
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler: expected one of {list(SAMPLERS)}, got {sampler!r}")
        cfg = self.config
        chosen = sampler or cfg.default_sampler
        if cfg.decoder_type == "DDPM" and chosen != "ode":
            raise ValueError(f"sampler: decoder_type='DDPM' samples with DPM-Solver (sampler='ode' or "
                             f"None); {chosen!r} needs a flow_matching or mean_flow decoder")
        if cfg.decoder_type == "mean_flow" and chosen == "euler" and not self._warned_proxy:
            warnings.warn("sampler='euler' on a mean_flow decoder integrates an instantaneous velocity made "
                          "from u (meanflow_sde_velocity: the boundary u(x, t, t) or the identity's JVP) with "
                          "Euler steps: an approximation (mixing table ⚠️); sampler='ode' is MeanFlow's native "
                          "sampler", UserWarning, stacklevel=3)
            self._warned_proxy = True
        return chosen

    def resolve_steps(self, sampler: Optional[str], steps: Optional[int] = None) -> int:
        """The step count `sample` uses: `steps`, else `flow_sde_num_steps` for the SDE and
        `num_inference_timesteps` for the others. The SDE has its own count because MeanFlow's
        K = 1 would make it one Euler–Maruyama step from noise (std 0.74 for a target of std 0.4
        at σ(0) = 0.7); below `SDE_MIN_STEPS` it warns once, as an explicit K may be a chosen
        trade-off, quoting that std for this policy's σ(t) (`flows.samplers.gaussian_target_std`)."""
        chosen = self.resolve_sampler(sampler)
        if steps is None:
            steps = self.config.flow_sde_num_steps if chosen == "sde" else self.config.num_inference_timesteps
        if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or steps < 1:
            raise ValueError(f"steps: expected a positive integer, got {steps!r}")
        if chosen == "sde" and steps < SDE_MIN_STEPS and not self._warned_steps:
            std = [gaussian_target_std(self.sigma, k, 0.4, self.config.flow_sde_clip_t,
                                       next(self.parameters()).device)
                   for k in (steps, SDE_MIN_STEPS, 10)]
            warnings.warn(f"steps: the SDE sampler with {steps} step(s) is far from the marginals it preserves in the limit: with this "
                          f"policy's σ(t) a Gaussian target of std 0.4 comes out with std {std[0]:.3f} at K = {steps} "
                          f"({std[1]:.3f} at K = {SDE_MIN_STEPS}, {std[2]:.3f} at K = 10); use at least "
                          f"{SDE_MIN_STEPS} (flow_sde_num_steps, default 10)", UserWarning, stacklevel=3)
            self._warned_steps = True
        return int(steps)

    @torch.no_grad()
    def predict_action_chunk(self, batch: Mapping[str, Any], sampler: Optional[str] = None,
                             steps: Optional[int] = None, return_logprob: Optional[bool] = None,
                             generator: Generators = None, noise: Optional[Tensor] = None,
                             meanflow_velocity: Optional[str] = None, prev_chunk: Optional[Tensor] = None,
                             delay: int = 0, rtc_mode: Optional[str] = None, n_action_steps: Optional[int] = None):
        """Sample a chunk [B, H, D] in environment units.

        Returns the tensor, or a `PolicyOutput` when log-probs are returned (asked here, or
        by `flow_sde_return_logprob` for the SDE sampler). For gradients through sampling
        (SAC), call `sample(...)` instead. `prev_chunk`, `delay`, `rtc_mode` and `n_action_steps`:
        real-time chunking, see `sample`.
        """
        out = self.sample(batch, sampler, steps, return_logprob, generator, noise, meanflow_velocity,
                          prev_chunk=prev_chunk, delay=delay, rtc_mode=rtc_mode, n_action_steps=n_action_steps)
        return out if out.log_prob is not None else out.actions

    @property
    def rtc_horizon(self) -> str:
        """The RTC horizon in effect: `config.rtc_horizon`, with "auto" resolved per decoder."""
        horizon = self.config.rtc_horizon
        if horizon == "auto":
            return "execution" if self.config.decoder_type == "mean_flow" else "overlap"
        return horizon

    def _check_prev_chunk(self, batch: Mapping[str, Any], prev_chunk: Optional[Tensor], delay: Any) -> int:
        """Validate the RTC arguments; returns the delay as an int."""
        cfg = self.config
        if isinstance(delay, bool) or not isinstance(delay, numbers.Integral) or delay < 0:
            raise ValueError(f"delay: expected a non-negative integer number of control steps, got {delay!r}")
        if prev_chunk is None:
            if delay:
                raise ValueError(f"delay: {delay} needs prev_chunk (the previous chunk's actions from the new "
                                 f"chunk's first step on, [B, L, {cfg.action_dim}]), got prev_chunk=None")
            return 0
        if cfg.decoder_type == "DDPM":
            raise ValueError("prev_chunk: real-time chunking needs a flow_matching or mean_flow decoder, got DDPM "
                             "(DPM-Solver++'s multistep updates leave no per-step velocity to guide)")
        b, h = batch["state"].shape[0], cfg.action_chunk_size
        if not isinstance(prev_chunk, Tensor) or not prev_chunk.is_floating_point() or prev_chunk.dim() != 3 \
                or prev_chunk.shape[0] != b or prev_chunk.shape[2] != cfg.action_dim or prev_chunk.shape[1] > h:
            got = f"{list(prev_chunk.shape)} {prev_chunk.dtype}" if isinstance(prev_chunk, Tensor) \
                else type(prev_chunk).__name__
            raise ValueError(f"prev_chunk: expected a floating-point tensor [{b}, L <= {h}, {cfg.action_dim}] "
                             f"(the previous chunk's actions from the new chunk's first step on), got {got}")
        if not delay <= prev_chunk.shape[1]:
            raise ValueError(f"delay: expected at most prev_chunk's length {prev_chunk.shape[1]} (the frozen actions "
                             f"come from it), got {delay}")
        _finite(prev_chunk, "prev_chunk")
        return int(delay)

    def feeds_prefix(self, sampler: str) -> bool:
        """Whether `sampler` (resolved) can be fed a committed prefix (trained RTC): "ode", or "euler" for
        flow matching."""
        return sampler == "ode" or (sampler == "euler" and self.config.decoder_type == "flow_matching")

    def resolve_rtc_mode(self, rtc_mode: Optional[str], delay: int = 0, sampler: Optional[str] = None) -> str:
        """The real-time chunking mode a chunk with a previous one uses: `rtc_mode` ("trained" |
        "guided"), or for None "trained" where the checkpoint was trained for it (`rtc_max_delay` ≥
        `delay`, a sampler that feeds a prefix: "ode", or "euler" for flow matching) and "guided"
        elsewhere. An explicit "trained" the checkpoint cannot serve is one ValueError line."""
        if rtc_mode not in RTC_MODES:
            raise ValueError(f"rtc_mode: expected one of {list(RTC_MODES)} (None: trained when the checkpoint "
                             f"has it, else guided), got {rtc_mode!r}")
        cfg = self.config
        chosen = self.resolve_sampler(sampler)
        feeds = self.feeds_prefix(chosen)
        if rtc_mode == "guided" or (rtc_mode is None and not (cfg.rtc_max_delay >= delay and cfg.rtc_max_delay
                                                               and feeds)):
            return "guided"
        if not cfg.rtc_max_delay:
            raise ValueError("rtc_mode: 'trained' needs a checkpoint trained with real-time chunking "
                             "(train --rtc-max-delay N); this one has rtc_max_delay=0: use rtc_mode='guided'")
        if delay > cfg.rtc_max_delay:
            raise ValueError(f"delay: {delay} exceeds rtc_max_delay={cfg.rtc_max_delay}, the longest prefix this "
                             f"checkpoint was trained to continue; use rtc_mode='guided' or a delay <= "
                             f"{cfg.rtc_max_delay}")
        if not feeds:
            raise ValueError(f"rtc_mode: 'trained' feeds the prefix to the ODE sampler ('ode'"
                             f"{', or euler' if cfg.decoder_type == 'flow_matching' else ''}); got sampler="
                             f"{chosen!r}: use rtc_mode='guided' with it")
        return "trained"

    def _executed_rows(self, n_action_steps: Optional[int], overlap: int) -> int:
        """The actions a new chunk executes after its delay: `n_action_steps`, else H − L (prev_chunk's
        length L = H − s implies s)."""
        h = self.config.action_chunk_size
        if n_action_steps is None:
            return h - overlap
        if isinstance(n_action_steps, bool) or not isinstance(n_action_steps, numbers.Integral) \
                or not 1 <= n_action_steps <= h:
            raise ValueError(f"n_action_steps: expected the actions executed per chunk, an integer in 1..{h}, "
                             f"got {n_action_steps!r}")
        return int(n_action_steps)

    def sample(self, batch: Mapping[str, Any], sampler: Optional[str] = None, steps: Optional[int] = None,
               return_logprob: Optional[bool] = None, generator: Generators = None,
               noise: Optional[Tensor] = None, meanflow_velocity: Optional[str] = None,
               prev_chunk: Optional[Tensor] = None, delay: int = 0, rtc_mode: Optional[str] = None,
               n_action_steps: Optional[int] = None) -> PolicyOutput:
        """Like `predict_action_chunk` but always a `PolicyOutput`, and differentiable.

        `meanflow_velocity` ("boundary" | "identity"; None: `config.meanflow_sde_velocity`)
        is the velocity a mean_flow decoder integrates with sampler "sde" or "euler"; re-score
        its chains with the same choice (`chain_log_prob(..., meanflow_velocity=...)`).
        `generator` is one torch.Generator or a list of one per row: then row b's noise (and the
        SDE's ε) come from generator[b] alone, whatever else shares the batch. A policy with a noise
        actor (`config.noise_actor_hidden`) draws its noise from the actor's Gaussian instead
        (with `generator` too); an explicit `noise` overrides either.
        Log-probs (sampler "sde") are the density of the returned chain; with
        `flow_sde_logprob_sigma_only` their gradient reaches σ only (reparameterised, SAC),
        without it the chain is data and the gradient reaches the network through the means
        (score-function / PPO form, that of `chain_log_prob`); see `flows.sample_sde`.

        Real-time chunking (flow_matching and mean_flow): `prev_chunk` [B, L, D] (env units) is what
        the previous chunk plans for this chunk's steps 0..L−1 (its actions from s on, after s executed
        ones: L = H − s), and `delay` d ≤ L is how many control steps inference takes. The returned
        chunk's first d actions are prev_chunk's, exactly. `rtc_mode` (`resolve_rtc_mode`):

        - "trained" (`flows/rtc_trained.py`; checkpoints trained with `rtc_max_delay` ≥ d, samplers
          "ode", and "euler" for flow matching): the d actions are fed in clean at t = 1 on every step,
          the same network calls as a plain chunk; the rest follows the network given them.
        - "guided" (`flows/rtc.py`, any sampler): the rest of the overlap is guided towards prev_chunk
          with weights that decay (`rtc_schedule`) under the clip `rtc_guidance_weight`; steps ≥ L are
          free (with the `rtc_horizon` "execution", MeanFlow's default, steps ≥ d + s too, s =
          `n_action_steps`, None: H − L, the executed rows prev_chunk's length implies). Flow
          matching's guidance costs each step its vector–Jacobian product; MeanFlow's needs none (a
          1-step chunk stays one network call, K steps take 2K − 1), and at K = 1 it is the output
          blend (1 − W)·x̂ + W·prev of the new plan and the previous one (warned once).
        - None: "trained" when the checkpoint has it for this delay and sampler, else "guided".

        DDPM refuses `prev_chunk`, and so do log-probs (an RTC chain has no `chain_log_prob` to
        re-score it).
        """
        cfg = self.config
        chosen = self.resolve_sampler(sampler)
        steps = self.resolve_steps(chosen, steps)
        if noise is not None:
            self._check_noise(batch, noise)
        want_lp = (cfg.flow_sde_return_logprob and chosen == "sde") if return_logprob is None \
            else bool(return_logprob)
        if want_lp and chosen != "sde":
            raise ValueError(f"return_logprob: log-probs come from the SDE sampler; got sampler={chosen!r} "
                             f"(deterministic samplers have no density)")
        if rtc_mode not in RTC_MODES:
            self.resolve_rtc_mode(rtc_mode)                                          # one line
        bound = self.bind(batch, meanflow_velocity)
        delay = self._check_prev_chunk(batch, prev_chunk, delay)
        if prev_chunk is not None and want_lp:
            raise ValueError("return_logprob: not available with prev_chunk (a guided chain has no chain_log_prob "
                             "to re-score it); pass return_logprob=False")
        param = next(self.model.parameters())
        if noise is None and self.noise_actor is not None:
            noise = self.noise_actor.sample(**self.noise_actor_inputs(batch), generator=generator)[0]   # [B, H, D]
        elif noise is None:
            noise = randn_rows(bound.batch_size, (cfg.action_chunk_size, cfg.action_dim), generator,
                               param.device)                                        # [B, H, D]
        velocity = bound.flow_velocity
        out = PolicyOutput()
        if prev_chunk is not None:
            prev = prev_chunk.to(param.device, torch.float32)                                  # [B, L, D]
            if cfg.action_squash:       # back through the squash: guidance acts on the chain's own units
                prev = torch.atanh(prev.clamp(-1 + 1e-6, 1 - 1e-6))
            prev = self.normalizers["actions"].normalize(prev)
            mode = self.resolve_rtc_mode(rtc_mode, delay, chosen)
            if mode == "trained":
                if delay == 0:                    # nothing committed: the plain chunk
                    x = sample_ode(velocity, noise, steps) if chosen == "euler" or cfg.decoder_type == "flow_matching" \
                        else sample_meanflow(bound.avg_velocity, noise, steps)
                elif chosen == "euler" or cfg.decoder_type == "flow_matching":
                    x = sample_ode_prefix(velocity, noise, prev[:, :delay], steps)
                else:
                    x = sample_meanflow_prefix(bound.avg_velocity, noise, prev[:, :delay], steps)
                out.actions = self._env_actions(x)
                out.actions[:, :delay] = prev_chunk[:, :delay].to(out.actions)      # exact, not round-tripped
                return out
            if self.rtc_horizon == "execution":
                executed = self._executed_rows(n_action_steps, prev.shape[1])
                prev = prev[:, : delay + executed]                                   # [B, min(L, d + s), D]
            rtc = {"max_guidance_weight": cfg.rtc_guidance_weight, "schedule": cfg.rtc_schedule}
            if chosen == "sde":
                res = sample_sde_rtc(velocity, noise, prev, delay, steps, self.sigma, generator=generator,
                                     clip_t=cfg.flow_sde_clip_t, **rtc)
                x, out.chain, out.grid = res.actions, res.chain, res.grid
            elif chosen == "euler" or cfg.decoder_type == "flow_matching":
                x = sample_ode_rtc(velocity, noise, prev, delay, steps, **rtc)
            else:
                if steps == 1 and not self._warned_blend:
                    warnings.warn("rtc_mode='guided' with a 1-step MeanFlow chunk returns the output blend "
                                  "(1 − W)·x̂ + W·prev_chunk of the new plan and the previous one: rows past the "
                                  "guided window ignore the committed prefix, and on multimodal chunks a blend "
                                  "can fall between the modes; a checkpoint trained with --rtc-max-delay "
                                  "(rtc_mode='trained') conditions on the prefix instead", UserWarning, stacklevel=3)
                    self._warned_blend = True
                x = sample_meanflow_rtc(bound.avg_velocity, noise, prev, delay, steps, **rtc)
            out.actions = self._env_actions(x)
            out.actions[:, :delay] = prev_chunk[:, :delay].to(out.actions)      # exact, not round-tripped
            return out
        if chosen == "sde":
            res = sample_sde(velocity, noise, steps, self.sigma, generator=generator,
                             return_logprob=want_lp, clip_t=cfg.flow_sde_clip_t,
                             logprob="eps" if cfg.flow_sde_logprob_sigma_only else "full")
            x, out.chain, out.grid = res.actions, res.chain, res.grid
            out.log_prob, out.step_log_probs = res.log_prob, res.step_log_probs
        elif chosen == "euler" or cfg.decoder_type == "flow_matching":
            x = sample_ode(velocity, noise, steps)
        elif cfg.decoder_type == "mean_flow":
            x = sample_meanflow(bound.avg_velocity, noise, steps)
        else:
            x = sample_ddpm(bound.model_output, noise, cfg, steps)
        out.actions = self._env_actions(x)
        return out

    def noise_actor_inputs(self, batch: Mapping[str, Any]) -> dict:
        """What the noise actor reads from a (validated) batch: the normalised state [B, S] and the
        context tokens with their mask, if any."""
        param = next(self.model.parameters())
        return {"state": self.normalizers["state"].normalize(batch["state"].to(param.device, torch.float32)),
                "context": _to(batch.get("context"), param.device),
                "context_mask": _to(batch.get("context_mask"), param.device)}

    def _env_actions(self, x: Tensor) -> Tensor:
        """A sampled chunk [B, H, D] in environment units: squashed into (−1, 1) with `action_squash`,
        else clamped to the action statistics' [min, max] with `clip_actions` (zero gradient outside)."""
        norm = self.normalizers["actions"]
        actions = norm.unnormalize(x)
        if self.config.action_squash:
            return torch.tanh(actions)
        return norm.clip(actions) if self.config.clip_actions else actions

    def chain_log_prob(self, batch: Mapping[str, Any], chain: Tensor, grid: Tensor, reduce: str = "sum",
                       meanflow_velocity: Optional[str] = None) -> Tensor:
        """Per-step log-probs [B, K] of a stored SDE chain under the current weights and σ (PPO);
        `meanflow_velocity` as for `sample` (use the choice that sampled the chain)."""
        if self.config.decoder_type == "DDPM":
            raise ValueError("chain_log_prob: needs a flow_matching or mean_flow decoder, got DDPM")
        cfg, b = self.config, batch["state"].shape[0] if isinstance(batch.get("state"), Tensor) else None
        want = f"[{b if b is not None else 'B'}, K+1, {cfg.action_chunk_size}, {cfg.action_dim}]"
        if not isinstance(chain, Tensor) or chain.dim() != 4 or chain.shape[0] != b or \
                tuple(chain.shape[2:]) != (cfg.action_chunk_size, cfg.action_dim):
            got = list(chain.shape) if isinstance(chain, Tensor) else type(chain).__name__
            raise ValueError(f"chain: expected a stored SDE chain of shape {want} (batch, grid points, "
                             f"action_chunk_size, action_dim), got {got}")
        if not isinstance(grid, Tensor) or list(grid.shape) != [chain.shape[1]]:
            got = list(grid.shape) if isinstance(grid, Tensor) else type(grid).__name__
            raise ValueError(f"grid: expected the chain's time grid of shape [{chain.shape[1]}] (K+1), got {got}")
        return chain_log_prob(self.bind(batch, meanflow_velocity).flow_velocity, chain, self.sigma, grid=grid,
                              clip_t=self.config.flow_sde_clip_t, reduce=reduce)

    def forward(self, batch: Mapping[str, Any], sampler: Optional[str] = None, return_logprob: Optional[bool] = None,
                steps: Optional[int] = None, generator: Optional[torch.Generator] = None) -> PolicyOutput:
        """train(): the loss of `batch` (needs "actions"); eval(): a sampled chunk.

        Sampling arguments in train() mode raise rather than being dropped for a loss."""
        if self.training:
            given = {k: v for k, v in (("sampler", sampler), ("return_logprob", return_logprob), ("steps", steps))
                     if v is not None}
            if given:
                raise ValueError(f"{', '.join(given)}: sampling arguments, got {given} while the policy is in "
                                 f"train() mode, where forward returns the loss; call policy.eval() first, or "
                                 f"policy.sample(batch, ...) to sample with gradients")
            return self.compute_loss(batch, generator)
        with torch.no_grad():
            return self.sample(batch, sampler, steps, return_logprob, generator)

    @torch.no_grad()
    def select_action(self, batch: Mapping[str, Any], generator: Optional[torch.Generator] = None) -> Tensor:
        """One action [B, D]; a new chunk is sampled when the queue of n_action_steps runs out.

        A state whose batch size differs from the queued chunk's re-plans (as after `reset()`):
        the queued rows belong to other environments and cannot be matched to the new ones, and
        a fresh chunk for the batch at hand is what a caller that changed its batch wants.

        With `n_obs_steps` n > 1, a batch of one observation (state [B, state_dim], images [B, N_cam, 3,
        S, S]) is pushed onto the policy's `history` (`history.ObservationHistory`, every call, also
        while queued actions remain) and the chunk is sampled from the last n; a batch that already
        holds n steps is used as it is."""
        batch = self._with_history(batch)
        if self._queue:
            self._validate(batch, need_actions=False)
            if self._queue[0].shape[0] != batch["state"].shape[0]:
                self._queue.clear()
        if not self._queue:
            chunk = self.sample(batch, return_logprob=False, generator=generator).actions
            self._queue.extend(chunk[:, : self.config.n_action_steps].transpose(0, 1))
        return self._queue.popleft()

    def _with_history(self, batch: Mapping[str, Any]) -> Mapping[str, Any]:
        """`batch` with its single observation stacked onto the last n − 1 (`select_action`)."""
        state = batch.get("state") if isinstance(batch, Mapping) else None
        if self.config.n_obs_steps == 1 or not isinstance(state, Tensor) or state.dim() != 2:
            return batch
        keys = ["state"] + (["images"] if isinstance(batch.get("images"), Tensor) else [])
        stacked = self.history.push({k: batch[k] for k in keys})
        return {**batch, **{k: stacked[k] for k in keys}}

    def reset(self) -> None:
        """Forget queued actions and the observation history (call at every episode start)."""
        self._queue.clear()
        self.history.reset()

    def export_onnx(self, path: str | Path, steps: Optional[int] = None, batch_size: int = 1,
                    sampler: Optional[str] = None, context_length: Optional[int] = -1,
                    exporter: str = "torchscript", rtc: bool = False) -> Path:
        """Write the deterministic sampler (normalisation, the K steps unrolled, un-normalisation, squash) as
        one ONNX graph `path` that maps `observation.state` and `noise` (+ context, camera frames; with `rtc`,
        the committed actions and the delay) to the chunk in env units; run it with
        `action_decoder.runtime.OnnxPolicy`. Arguments: `export.export_onnx`."""
        from .export import export_onnx

        return export_onnx(self, path, steps=steps, batch_size=batch_size, sampler=sampler,
                           context_length=context_length, exporter=exporter, rtc=rtc)

    # ------------------------------------------------------------------ persistence
    def save_pretrained(self, save_directory: str | Path, *, config: Any = None, repo_id: Optional[str] = None,
                        push_to_hub: bool = False, model_card_kwargs: Optional[dict] = None,
                        **push_to_hub_kwargs) -> Optional[str]:
        """`config.json` (the current format_version, every DecoderConfig field) + `model.safetensors` (weights,
        normalisation stats, learnable σ) + `README.md` (the model card, `model_card.py`): the layout
        `PyTorchModelHubMixin` reads and `push_to_hub` uploads (`push_to_hub=True` uploads to `repo_id`,
        default the directory's name; returns the commit's url). The card keeps the measured results
        of these exact weights (from the checkpoint this policy was loaded from, or already in the
        directory); results of other weights are dropped."""
        from safetensors.torch import save as tensors_to_bytes

        if config is not None and config is not self.config:
            raise ValueError(f"config: the policy saves its own DecoderConfig (policy.config); got {type(config).__name__}")
        if model_card_kwargs:
            raise ValueError(f"model_card_kwargs: the card is built from the policy's config and measured results; "
                             f"got {sorted(model_card_kwargs)}")
        path = Path(save_directory)
        path.mkdir(parents=True, exist_ok=True)
        self.config.to_json(path / CONFIG_NAME)
        tensors = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        # Serialised in memory and written by Python, so the file gets the umask's mode like the others
        # (safetensors' own save_file creates it 0600); a temporary name and a rename keep it atomic.
        tmp = path / (WEIGHTS_NAME + ".tmp")
        tmp.write_bytes(tensors_to_bytes(tensors, metadata={"format": "pt", "library": "action_decoder"}))
        tmp.replace(path / WEIGHTS_NAME)
        known = getattr(self, "_card_results", []) + model_card.read_results(path)
        digest = model_card.weights_digest(tensors)
        results = []
        for row in model_card.carried_results(known, digest):
            results = model_card.merge_result(results, row)
        model_card.write_card(path, self.config, sum(p.numel() for p in self.parameters()), results, digest)
        if push_to_hub:
            return self.push_to_hub(repo_id or path.name, **push_to_hub_kwargs)
        return None

    def push_to_hub(self, repo_id: str, **kwargs) -> str:
        """Upload `save_pretrained`'s files to the Hub repo `repo_id` (`PyTorchModelHubMixin.push_to_hub`'s
        arguments: `token`, `private`, `branch`, `commit_message`...; returns the commit's url). A Hub that
        cannot be reached or refuses the upload (offline, `HF_HUB_OFFLINE=1`, no token, no access) is
        one ValueError line."""
        try:
            return super().push_to_hub(repo_id, **kwargs)
        except TypeError:           # a wrong argument is the caller's, not the Hub's
            raise
        except Exception as err:    # offline, refused, unreachable: huggingface_hub and httpx raise many kinds
            why = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise ValueError(f"push_to_hub: could not upload to the Hub repo {repo_id!r} ({type(err).__name__}: "
                             f"{why}); check the connection, HF_HUB_OFFLINE and the token (huggingface-cli "
                             f"login), or keep the directory save_pretrained writes") from None

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: str | Path, map_location: str | torch.device = "cpu", *,
                        revision: Optional[str] = None, cache_dir: Optional[str | Path] = None,
                        force_download: bool = False, token: Optional[str | bool] = None,
                        local_files_only: bool = False) -> "ActionDecoderPolicy":
        """Load a directory written by `save_pretrained`, or a Hub repo id (`owner/name`, fetched with
        `huggingface_hub.snapshot_download`; `revision`, `cache_dir`, `token`... go to it) when no such
        local directory exists. An unreachable Hub or unknown repo is one ValueError line. The policy
        comes back in eval() mode, ready to sample (call .train() to train on)."""
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        path = _checkpoint_dir(pretrained_model_name_or_path, revision=revision, cache_dir=cache_dir,
                               force_download=force_download, token=token, local_files_only=local_files_only)
        for name in (CONFIG_NAME, WEIGHTS_NAME):
            if not (path / name).is_file():
                raise FileNotFoundError(f"checkpoint: {path} has no {name}; expected a directory written "
                                        f"by save_pretrained ({CONFIG_NAME} + {WEIGHTS_NAME})")
        policy = cls(DecoderConfig.from_json(path / CONFIG_NAME), load_pretrained=False)
        try:
            tensors = load_file(str(path / WEIGHTS_NAME), device=str(map_location))
        except (SafetensorError, OSError, json.JSONDecodeError) as err:
            raise ValueError(f"checkpoint: {path / WEIGHTS_NAME} is not a readable safetensors file ({err})") from None
        missing, unexpected = [], []
        own = policy.state_dict()
        missing = sorted(set(own) - set(tensors))
        unexpected = sorted(set(tensors) - set(own))
        wrong = sorted(k for k in set(own) & set(tensors) if own[k].shape != tensors[k].shape)
        if missing or unexpected or wrong:
            raise ValueError(f"checkpoint: {path} does not match its config.json: missing {missing[:5]}, "
                             f"unexpected {unexpected[:5]}, wrong shapes {wrong[:5]}")
        policy.load_state_dict(tensors)
        results = model_card.read_results(path)
        # The measured results of these weights, so that saving (or pushing) them again keeps them.
        policy._card_results = model_card.carried_results(results, model_card.weights_digest(tensors)) if results else []
        return policy.to(map_location).eval()   # ready to sample, as the Hub mixin returns models; .train() to train on


HUB_REPO_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")


def follow_last(name: str | Path) -> Path:
    """`name` as a path, or the `step_N` directory a run's `checkpoints/last` pointer file names."""
    path = Path(name).expanduser()
    if path.is_file() and path.name == "last":
        target = path.parent / path.read_text(errors="replace").strip()
        if target.name.startswith("step_") and target.is_dir():
            return target
    return path


def _checkpoint_dir(name: str | Path, **hub) -> Path:
    """A local checkpoint directory, or the snapshot of the Hub repo `name` names (`owner/name`). A run's
    `checkpoints/last` pointer (a file naming the newest `step_N`) is followed to that directory; another
    file is refused in one line."""
    path = follow_last(name)
    if path.is_file():
        raise ValueError(f"checkpoint: {path} is a file; expected a directory written by save_pretrained "
                         f"({CONFIG_NAME} + {WEIGHTS_NAME}), e.g. a run's final/ or checkpoints/step_N")
    if path.exists() or not HUB_REPO_ID.match(str(name)):
        return path
    from huggingface_hub import snapshot_download

    try:
        return Path(snapshot_download(str(name), allow_patterns=[CONFIG_NAME, WEIGHTS_NAME, model_card.CARD_NAME],
                                      **hub))
    except Exception as err:    # offline, unknown repo, no access: huggingface_hub raises many kinds
        why = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ValueError(f"checkpoint: {name!r} is not a local directory, and the Hub repo {name!r} could not be "
                         f"fetched ({type(err).__name__}: {why}); pass a directory written by save_pretrained, "
                         f"or check the repo id and the connection") from None


def _tensor(batch: Mapping[str, Any], key: str, shape: str) -> Tensor:
    if key not in batch or batch[key] is None:
        raise ValueError(f"batch[{key!r}]: missing; expected a tensor of shape {shape}; "
                         f"got keys {sorted(batch)}")
    value = batch[key]
    if not isinstance(value, Tensor) or not value.is_floating_point():
        got = f"dtype {value.dtype}" if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(f"batch[{key!r}]: expected a floating-point tensor of shape {shape}, got {got}")
    return value


def _finite(x: Tensor, key: str) -> None:
    # A NaN or an Inf makes the sum non-finite, so a finite sum clears x in one reduction; a non-finite sum
    # (or an overflowing one) is settled element by element.
    if not math.isfinite(x.sum().item()) and not torch.isfinite(x).all():
        raise ValueError(f"batch[{key!r}]: contains NaN or Inf (shape {list(x.shape)})")


def _to(x: Optional[Tensor], device) -> Optional[Tensor]:
    return x.to(device) if isinstance(x, Tensor) else x
