"""`ActionDecoderPolicy`: binds the Action Expert to the math of `flows/`.

It validates and normalises a batch, builds the conditioning prefix once per chunk, hands
bound callables to a loss or a sampler, un-normalises the actions and queues them. The
network knows nothing of sampling; the samplers know nothing of the network.
"""

from __future__ import annotations

import json
import numbers
import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

import torch
from torch import Tensor, nn

from .config import MEANFLOW_VELOCITIES, SDE_MIN_STEPS, DecoderConfig
from .expert import ActionExpert, Prefix
from .flows import (chain_log_prob, ddpm_loss, flow_matching_loss, make_sigma, meanflow_loss,
                    sample_ddpm, sample_meanflow, sample_ode, sample_sde, velocity_from_meanflow,
                    velocity_from_sample)
from .flows.paths import Generators, randn_rows
from .normalize import make_normalizers
from .state_layout import relative_positions

SAMPLERS = (None, "ode", "sde", "euler")
CONFIG_NAME, WEIGHTS_NAME = "config.json", "model.safetensors"


@dataclass
class PolicyOutput:
    """Training: `loss` (+ `metrics`). Sampling: `actions` [B, H, D] in environment units and,
    when asked, `log_prob` [B] / `step_log_probs` [B, K] (densities of the normalised chunk,
    float32) and the SDE `chain` [B, K+1, H, D] (normalised) with its `grid` [K+1]."""

    loss: Optional[Tensor] = None
    actions: Optional[Tensor] = None
    log_prob: Optional[Tensor] = None
    step_log_probs: Optional[Tensor] = None
    chain: Optional[Tensor] = None
    grid: Optional[Tensor] = None
    metrics: dict = field(default_factory=dict)


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


class ActionDecoderPolicy(nn.Module):
    """A LeRobot-style policy over any of the three decoders (see API.md)."""

    def __init__(self, config: DecoderConfig, stats: Optional[Mapping[str, Mapping]] = None):
        super().__init__()
        if not isinstance(config, DecoderConfig):
            raise ValueError(f"config: expected a DecoderConfig, got {type(config).__name__}")
        self.config = config
        self.model = ActionExpert(config)
        self.normalizers = make_normalizers(config.state_dim, config.action_dim,
                                            config.normalization_mode, stats)
        # The noise schedule is a submodule so that a learnable σ is a policy parameter.
        self.sigma = make_sigma(config)
        self._queue: deque = deque()
        self._warned_proxy = self._warned_steps = False

    # ------------------------------------------------------------------ batch handling
    def _validate(self, batch: Mapping[str, Any], need_actions: bool) -> None:
        cfg = self.config
        if not isinstance(batch, Mapping):
            raise ValueError(f"batch: expected a dict of tensors, got {type(batch).__name__}")
        state = _tensor(batch, "state", f"[B, {cfg.state_dim}]")
        if state.dim() != 2 or state.shape[1] != cfg.state_dim:
            raise ValueError(f"batch['state']: expected shape [B, {cfg.state_dim}], got {list(state.shape)}")
        _finite(state, "state")
        b = state.shape[0]
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
        """Normalised state, ctrl_freq and the conditioning prefix (built once)."""
        param = next(self.model.parameters())
        raw = batch["state"].to(param.device, torch.float32)
        state = self.normalizers["state"].normalize(raw)                      # [B, state_dim]
        if self.config.state_layout == "metaworld":
            state = torch.cat([state, relative_positions(raw)], dim=-1)      # [B, state_input_dim]
        ctrl = batch.get("ctrl_freq")
        prefix = self.model.build_prefix(
            context=_to(batch.get("context"), param.device), context_mask=_to(batch.get("context_mask"), param.device),
            vlm_key_values=batch.get("vlm_key_values"), attention_mask=_to(batch.get("attention_mask"), param.device))
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
        self._validate(batch, need_actions=True)
        cond = self._prepare(batch)
        actions = self.normalizers["actions"].normalize(batch["actions"].to(cond["state"].device, torch.float32))
        cfg = self.config
        if cfg.decoder_type == "flow_matching":
            loss = flow_matching_loss(lambda x, t, **c: self._flow_net(x, t, t, **c), actions, generator, cond)
        elif cfg.decoder_type == "mean_flow":
            weights = self.model.head.weight.dtype
            if cfg.meanflow_dudt == "finite_difference" and weights not in (torch.float32, torch.float64):
                raise ValueError(f"meanflow_dudt: 'finite_difference' needs float32 or float64 weights, got "
                                 f"{weights} (set meanflow_dudt='jvp' to train in lower precision)")
            loss = meanflow_loss(self._flow_net, actions, generator, cond,
                                 ratio_r_neq_t=cfg.meanflow_ratio_r_neq_t, time_mean=cfg.meanflow_time_mean,
                                 time_std=cfg.meanflow_time_std, adaptive_p=cfg.meanflow_adaptive_p,
                                 adaptive_c=cfg.meanflow_adaptive_c, time_dist=cfg.meanflow_time_dist,
                                 dudt=cfg.meanflow_dudt)
        else:
            loss = ddpm_loss(lambda x, s, **c: self._net(x, self._ddpm_time(s), self._ddpm_time(s), **c),
                             actions, cfg, generator, cond)
        return PolicyOutput(loss=loss, metrics={"loss": loss.detach()})

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
        K = 1 would make it one Euler–Maruyama step from noise (std 0.74 or 3.3 for a target of
        std 0.4); below `SDE_MIN_STEPS` it warns once, as an explicit K may be a chosen trade-off."""
        chosen = self.resolve_sampler(sampler)
        if steps is None:
            steps = self.config.flow_sde_num_steps if chosen == "sde" else self.config.num_inference_timesteps
        if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) or steps < 1:
            raise ValueError(f"steps: expected a positive integer, got {steps!r}")
        if chosen == "sde" and steps < SDE_MIN_STEPS and not self._warned_steps:
            warnings.warn(f"steps: the SDE sampler with {steps} step(s) leaves noise it injects unremoved (a Gaussian "
                          f"of std 0.4 comes out with std 0.74 (churn) or 3.3 (explore) at K = 1, 0.55 (explore) "
                          f"at K = 2); use at least {SDE_MIN_STEPS} (flow_sde_num_steps, default 10)",
                          UserWarning, stacklevel=3)
            self._warned_steps = True
        return int(steps)

    @torch.no_grad()
    def predict_action_chunk(self, batch: Mapping[str, Any], sampler: Optional[str] = None,
                             steps: Optional[int] = None, return_logprob: Optional[bool] = None,
                             generator: Generators = None, noise: Optional[Tensor] = None,
                             meanflow_velocity: Optional[str] = None):
        """Sample a chunk [B, H, D] in environment units.

        Returns the tensor, or a `PolicyOutput` when log-probs are returned (asked here, or
        by `flow_sde_return_logprob` for the SDE sampler). For gradients through sampling
        (SAC), call `sample(...)` instead.
        """
        out = self.sample(batch, sampler, steps, return_logprob, generator, noise, meanflow_velocity)
        return out if out.log_prob is not None else out.actions

    def sample(self, batch: Mapping[str, Any], sampler: Optional[str] = None, steps: Optional[int] = None,
               return_logprob: Optional[bool] = None, generator: Generators = None,
               noise: Optional[Tensor] = None, meanflow_velocity: Optional[str] = None) -> PolicyOutput:
        """Like `predict_action_chunk` but always a `PolicyOutput`, and differentiable.

        `meanflow_velocity` ("boundary" | "identity"; None: `config.meanflow_sde_velocity`)
        is the velocity a mean_flow decoder integrates with sampler "sde" or "euler"; re-score
        its chains with the same choice (`chain_log_prob(..., meanflow_velocity=...)`).
        `generator` is one torch.Generator or a list of one per row: then row b's noise (and the
        SDE's ε) come from generator[b] alone, whatever else shares the batch.
        Log-probs (sampler "sde") are the density of the returned chain; with
        `flow_sde_logprob_sigma_only` their gradient reaches σ only (reparameterised, SAC),
        without it the chain is data and the gradient reaches the network through the means
        (score-function / PPO form, that of `chain_log_prob`); see `flows.sample_sde`.
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
        bound = self.bind(batch, meanflow_velocity)
        param = next(self.model.parameters())
        if noise is None:
            noise = randn_rows(bound.batch_size, (cfg.action_chunk_size, cfg.action_dim), generator,
                               param.device)                                        # [B, H, D]
        velocity = bound.flow_velocity
        out = PolicyOutput()
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
        out.actions = self.normalizers["actions"].unnormalize(x)
        return out

    def chain_log_prob(self, batch: Mapping[str, Any], chain: Tensor, grid: Tensor, reduce: str = "sum",
                       meanflow_velocity: Optional[str] = None) -> Tensor:
        """Per-step log-probs [B, K] of a stored SDE chain under the current weights and σ (PPO);
        `meanflow_velocity` as for `sample` (use the choice that sampled the chain)."""
        if self.config.decoder_type == "DDPM":
            raise ValueError("chain_log_prob: needs a flow_matching or mean_flow decoder, got DDPM")
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
        a fresh chunk for the batch at hand is what a caller that changed its batch wants."""
        if self._queue:
            self._validate(batch, need_actions=False)
            if self._queue[0].shape[0] != batch["state"].shape[0]:
                self._queue.clear()
        if not self._queue:
            chunk = self.sample(batch, return_logprob=False, generator=generator).actions
            self._queue.extend(chunk[:, : self.config.n_action_steps].transpose(0, 1))
        return self._queue.popleft()

    def reset(self) -> None:
        """Forget queued actions (call at every episode start)."""
        self._queue.clear()

    # ------------------------------------------------------------------ persistence
    def save_pretrained(self, path: str | Path) -> None:
        """`config.json` + `model.safetensors` (weights, normalisation stats, learnable σ)."""
        from safetensors.torch import save_file

        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        self.config.to_json(path / CONFIG_NAME)
        tensors = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        tmp = path / (WEIGHTS_NAME + ".tmp")
        save_file(tensors, str(tmp), metadata={"format": "pt", "library": "action_decoder"})
        tmp.replace(path / WEIGHTS_NAME)

    @classmethod
    def from_pretrained(cls, path: str | Path, map_location: str | torch.device = "cpu") -> "ActionDecoderPolicy":
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        path = Path(path)
        for name in (CONFIG_NAME, WEIGHTS_NAME):
            if not (path / name).is_file():
                raise FileNotFoundError(f"checkpoint: {path} has no {name}; expected a directory written "
                                        f"by save_pretrained ({CONFIG_NAME} + {WEIGHTS_NAME})")
        policy = cls(DecoderConfig.from_json(path / CONFIG_NAME))
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
        return policy.to(map_location)


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
    if not torch.isfinite(x).all():
        raise ValueError(f"batch[{key!r}]: contains NaN or Inf (shape {list(x.shape)})")


def _to(x: Optional[Tensor], device) -> Optional[Tensor]:
    return x.to(device) if isinstance(x, Tensor) else x
