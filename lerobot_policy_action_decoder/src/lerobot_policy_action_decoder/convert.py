"""The LeRobot ↔ action_decoder boundary, in plain torch (no LeRobot import, testable without it).

LeRobot names a batch `observation.state` [B, S], `action` [B, H, D] with `action_is_pad`
[B, H], `task` (one string per row) and camera frames `observation.images.<name>` [B, 3, H, W]
(float in [0, 1]); the core policy reads `state`, `actions`, `images` [B, N_cam, 3, S, S] (the
cameras stacked in the config's order, resized to `image_size`) and, when it was trained on
several tasks, a one-hot task token `context` [B, 1, T]. `decoder_config` maps the plugin's
config (any object with its attribute names) to a core `DecoderConfig`. `rtc_prefix` and
`rtc_settings` turn LeRobot's real-time chunking arguments (`inference_delay`,
`prev_chunk_left_over`, its `RTCConfig`) into the core's (`delay`, `prev_chunk`, guidance weight
and schedule).
"""

from __future__ import annotations

import numbers
from typing import Any, Mapping, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from action_decoder import DecoderConfig
from action_decoder.config import RTC_SCHEDULES, is_camera_key
# The plugin's config fields and their core names: one table, shared with `action-decoder convert`.
from action_decoder.lerobot_checkpoint import PLUGIN_FIELDS, PLUGIN_FIELDS_ADDED, RENAMED, plugin_core_config  # noqa: F401

STATE, ACTION, PAD, TASK = "observation.state", "action", "action_is_pad", "task"
SHARED = PLUGIN_FIELDS + PLUGIN_FIELDS_ADDED


def feature_dims(input_features: Mapping[str, Any], output_features: Mapping[str, Any]) -> tuple[int, int]:
    """(state_dim, action_dim) from LeRobot's features (`.shape` each): a 1-d `observation.state`
    and a 1-d `action` are required."""
    dims = []
    for where, feats, key in (("input_features", input_features, STATE), ("output_features", output_features, ACTION)):
        ft = (feats or {}).get(key)
        shape = tuple(getattr(ft, "shape", ())) if ft is not None else None
        if shape is None or len(shape) != 1 or int(shape[0]) < 1:
            raise ValueError(f"policy.{where}[{key!r}]: expected a 1-d feature of shape (dim,), got "
                             f"{'nothing' if ft is None else shape} (features: {sorted(feats or {})})")
        dims.append(int(shape[0]))
    return dims[0], dims[1]


def camera_keys(input_features: Mapping[str, Any]) -> list[str]:
    """The camera inputs (`observation.images.<name>`, or LeRobot's single `observation.image`), in the
    order of `input_features`: the order in which the policy stacks them."""
    return [k for k in (input_features or {}) if is_camera_key(k)]


def unused_inputs(input_features: Mapping[str, Any]) -> list[str]:
    """Input keys the decoder does not read (environment state, ...): all but the state and the cameras."""
    return sorted(k for k in (input_features or {}) if k != STATE and not is_camera_key(k))


def unused_inputs_message(keys: Sequence[str]) -> Optional[str]:
    """One line naming the inputs that do not condition the policy, and how they could; None if none."""
    if not keys:
        return None
    return (f"action_decoder: not using input(s) {list(keys)}; the policy conditions on {STATE!r} and the task "
            f"string and cameras only. To condition on them, encode them into context tokens of the core policy "
            f"(action_decoder.DecoderConfig.context_dim, batch['context'] [B, L, C])")


def decoder_config(cfg: Any, state_dim: int, action_dim: int, cameras: Sequence[str] = ()) -> DecoderConfig:
    """The core `DecoderConfig` of a plugin config (any object with its attribute names).

    Normalisation is `identity`: LeRobot's processors normalise before the policy and
    un-normalise after it, and the postprocessor clamps actions to the data's range
    (`clip_actions`), so the core policy neither normalises nor clips. `num_inference_steps=None`
    and `flow_prediction=None` take what `action-decoder train` takes (MeanFlow: 1 step and
    the clean-chunk head; DDPM and flow matching: 10 steps and GO-1's velocity head). With
    two or more `tasks` the task is a one-hot context token of width len(tasks).
    `cameras` (`camera_keys` of the input features) go through the core's image encoder.
    A bad value raises the core's ValueError with the plugin's field name (`policy.<name>`).
    """
    names = SHARED + ("chunk_size", "num_inference_steps", "flow_prediction")
    values = {name: getattr(cfg, name) for name in names if hasattr(cfg, name)}
    return plugin_core_config(values, state_dim, action_dim, cameras, getattr(cfg, "tasks", None) or [])


def task_list(tasks: Any) -> list[str]:
    """Task strings ordered by task index, from LeRobot metadata's `tasks` (a pandas DataFrame
    indexed by the string with a `task_index` column), a {index: string} dict or a list."""
    if tasks is None:
        return []
    if hasattr(tasks, "index") and hasattr(tasks, "columns") and "task_index" in tasks.columns:
        pairs = sorted((int(i), str(s)) for s, i in zip(tasks.index, tasks["task_index"]))
        return [s for _, s in pairs]
    if isinstance(tasks, Mapping):
        return [str(tasks[k]) for k in sorted(tasks)]
    return [str(t) for t in tasks]


def task_token(task: Any, tasks: Sequence[str], batch_size: int, device=None) -> Optional[Tensor]:
    """One-hot task token [B, 1, T] from the batch's task strings; None for a single-task policy."""
    if len(tasks) <= 1:
        return None
    if task is None:
        raise ValueError(f"batch[{TASK!r}]: missing; this policy was trained on {len(tasks)} tasks {list(tasks)} "
                         f"and needs one task string per row")
    names = [task] * batch_size if isinstance(task, str) else list(task)
    if len(names) != batch_size:
        raise ValueError(f"batch[{TASK!r}]: expected {batch_size} task strings (one per row), got {len(names)}")
    known = {t: i for i, t in enumerate(tasks)}
    unknown = sorted({n for n in names if n not in known})
    if unknown:
        raise ValueError(f"batch[{TASK!r}]: unknown task(s) {unknown}; this policy knows {list(tasks)}")
    index = torch.tensor([known[n] for n in names], device=device)                     # [B]
    return torch.nn.functional.one_hot(index, len(tasks)).float()[:, None, :]           # [B, 1, T]


def hold_last_action(actions: Tensor, is_pad: Optional[Tensor]) -> Tensor:
    """Padded steps [B, H, D] replaced by the row's last real action (the core trainer's convention
    near an episode's end, so `lerobot-train` and `action-decoder train` learn the same targets:
    hold the final action). A row that is all padding is left as it is."""
    if is_pad is None:
        return actions
    if is_pad.shape != actions.shape[:2]:
        raise ValueError(f"batch[{PAD!r}]: expected shape {list(actions.shape[:2])} (batch, chunk), "
                         f"got {list(is_pad.shape)}")
    real = ~is_pad.bool()                                                                 # [B, H]
    steps = torch.arange(actions.shape[1], device=actions.device)                         # [H]
    last = torch.where(real, steps, -1).cummax(dim=1).values.clamp_min(0)                 # [B, H] last real step so far
    held = actions.gather(1, last[..., None].expand_as(actions))                          # [B, H, D]
    return torch.where(real[..., None], actions, held)


def camera_batch(batch: Mapping[str, Any], cameras: Sequence[str], image_size: int, batch_size: int,
                 n_obs_steps: Optional[int] = None) -> Tensor:
    """LeRobot camera frames `batch[key]` [B, 3, H, W] (or [B, 1, 3, H, W]) float in [0, 1] → `images`
    [B, N_cam, 3, S, S], stacked in `cameras` order, resized (bilinear, antialiased) to S = `image_size`.
    `n_obs_steps` n (observation history, `observation_delta_indices`): frames [B, n, 3, H, W] → images
    [B, n, N_cam, 3, S, S]."""
    frames = []
    for key in cameras:
        x = batch.get(key)
        if isinstance(x, Tensor) and x.dim() == 5 and x.shape[1] == 1 and n_obs_steps is None:
            x = x[:, 0]                                                                   # [B, 1, 3, H, W] -> [B, 3, H, W]
        lead = [batch_size] if n_obs_steps is None else [batch_size, n_obs_steps]
        if not isinstance(x, Tensor) or list(x.shape[:len(lead)]) != lead or x.dim() != len(lead) + 3 \
                or x.shape[len(lead)] != 3:
            got = list(x.shape) if isinstance(x, Tensor) else ("nothing" if x is None else type(x).__name__)
            raise ValueError(f"batch[{key!r}]: expected camera frames of shape [{', '.join(map(str, lead))}, 3, H, W] "
                             f"(float in [0, 1]), got {got}")
        if n_obs_steps is not None:
            x = x.flatten(0, 1)                                                           # [B·n, 3, H, W]
        x = x.float() / 255.0 if not x.is_floating_point() else x.float()
        low, high = float(x.min()), float(x.max())
        if not (0.0 <= low and high <= 1.0):              # NaN fails too
            raise ValueError(f"batch[{key!r}]: expected pixels in [0, 1] (uint8 0..255, or float with the VISUAL "
                             f"normalisation IDENTITY), got values in [{low:.4g}, {high:.4g}]")
        if tuple(x.shape[-2:]) != (image_size, image_size):
            x = F.interpolate(x, size=(image_size, image_size), mode="bilinear", antialias=True,
                              align_corners=False).clamp(0.0, 1.0)
        frames.append(x if n_obs_steps is None else x.view(*lead, *x.shape[1:]))
    return torch.stack(frames, dim=len(lead))                                             # [B, (n,) N_cam, 3, S, S]


def _finite_float(x: Tensor, key: str) -> None:
    """Checked here, where LeRobot's key is known (the core would name its own key)."""
    if not x.is_floating_point():
        raise ValueError(f"batch[{key!r}]: expected a floating-point tensor, got {x.dtype}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"batch[{key!r}]: contains NaN or Inf (shape {list(x.shape)})")


def to_core_batch(batch: Mapping[str, Any], tasks: Sequence[str], state_dim: int,
                  with_actions: bool, cameras: Sequence[str] = (), image_size: int = 64,
                  action_shape: Optional[tuple[int, int]] = None, n_obs_steps: int = 1) -> dict:
    """LeRobot batch → core batch: `state` [B, S], `actions` [B, H, D] (padding held at the last
    real action) when `with_actions`, `images` [B, N_cam, 3, S, S] for a camera policy
    (`camera_batch`), and the task token `context` [B, 1, T] for multi-task. `action_shape` (H, D)
    checks the chunk's shape here, naming LeRobot's key. With `n_obs_steps` n > 1 a batch of the
    dataset's observation history (`observation.state` [B, n, S], frames [B, n, 3, H, W]) keeps its
    step axis (`state` [B, n, S], `images` [B, n, N_cam, 3, S, S]); a batch of one observation (the
    environment's, in `select_action`) stays one, for the core policy's history to stack."""
    state = batch.get(STATE)
    if not isinstance(state, Tensor):
        raise ValueError(f"batch[{STATE!r}]: missing; expected a tensor of shape [B, {state_dim}], got "
                         f"{type(state).__name__} (keys {sorted(batch)})")
    stacked = n_obs_steps > 1 and state.dim() == 3 and state.shape[1] != 1
    if stacked:
        if list(state.shape[1:]) != [n_obs_steps, state_dim]:
            raise ValueError(f"batch[{STATE!r}]: expected shape [B, {state_dim}] or [B, {n_obs_steps}, {state_dim}] "
                             f"(n_obs_steps={n_obs_steps}), got {list(state.shape)}")
    elif state.dim() == 3 and state.shape[1] == 1:
        state = state[:, 0]                                                               # [B, 1, S] -> [B, S]
    if not stacked and (state.dim() != 2 or state.shape[1] != state_dim):
        raise ValueError(f"batch[{STATE!r}]: expected shape [B, {state_dim}], got {list(state.shape)}")
    _finite_float(state, STATE)
    out = {"state": state}
    if with_actions:
        actions = batch.get(ACTION)
        if not isinstance(actions, Tensor) or actions.dim() != 3:
            got = list(actions.shape) if isinstance(actions, Tensor) else type(actions).__name__
            raise ValueError(f"batch[{ACTION!r}]: expected an action chunk of shape [B, H, D] (action_delta_indices "
                             f"give H steps), got {got}")
        want = [state.shape[0], *(action_shape or actions.shape[1:])]
        if list(actions.shape) != want:
            raise ValueError(f"batch[{ACTION!r}]: expected shape {want} (batch, chunk_size, action dim), "
                             f"got {list(actions.shape)}")
        _finite_float(actions, ACTION)
        out["actions"] = hold_last_action(actions, batch.get(PAD))
    if cameras:
        out["images"] = camera_batch(batch, cameras, image_size, state.shape[0], n_obs_steps if stacked else None)
    context = task_token(batch.get(TASK), tasks, state.shape[0], state.device)
    if context is not None:
        out["context"] = context
    return out


def rtc_settings(rtc_config: Any) -> Optional[tuple[float, str, int]]:
    """(guidance weight, schedule, execution horizon) of LeRobot's `RTCConfig` (`max_guidance_weight`,
    `prefix_attention_schedule` ZEROS | ONES | LINEAR | EXP, `execution_horizon`), which
    `lerobot-rollout --inference.type=rtc` sets as `policy.config.rtc_config`; None when there is
    none or it is disabled (the plugin's own `rtc_guidance_weight` and `rtc_schedule` apply)."""
    if rtc_config is None or not getattr(rtc_config, "enabled", True):
        return None
    raw = getattr(rtc_config, "prefix_attention_schedule", None)
    schedule = str(getattr(raw, "value", raw)).lower()
    if schedule not in RTC_SCHEDULES:
        raise ValueError(f"rtc_config.prefix_attention_schedule: expected one of "
                         f"{[s.upper() for s in RTC_SCHEDULES]}, got {raw!r}")
    weight, horizon = getattr(rtc_config, "max_guidance_weight", None), getattr(rtc_config, "execution_horizon", None)
    if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not weight >= 0:
        raise ValueError(f"rtc_config.max_guidance_weight: expected a number >= 0, got {weight!r}")
    if isinstance(horizon, bool) or not isinstance(horizon, int) or horizon < 1:
        raise ValueError(f"rtc_config.execution_horizon: expected a positive number of steps, got {horizon!r}")
    return float(weight), schedule, horizon


def rtc_prefix(prev_chunk_left_over: Any, inference_delay: Any, batch_size: int, chunk_size: int,
               action_dim: int, horizon: Optional[int] = None) -> tuple[Optional[Tensor], int]:
    """LeRobot's RTC arguments → the core's (`prev_chunk` [B, L, D], `delay`).

    `prev_chunk_left_over` [T, D] or [B, T, D] is what the previous chunk has not executed yet, in the
    policy's normalised units, from the new chunk's first step on; its first L = min(T, chunk_size,
    `horizon`) steps guide the new chunk. `inference_delay` is how many control steps run while the
    chunk is sampled; the actions committed in that time come from the left-over, so the delay is
    at most L. Without a left-over (the first chunk) nothing is committed: (None, 0)."""
    if isinstance(inference_delay, bool) or not isinstance(inference_delay, (numbers.Integral, type(None))) \
            or (inference_delay or 0) < 0:
        raise ValueError(f"inference_delay: expected a non-negative integer number of control steps, "
                         f"got {inference_delay!r}")
    if prev_chunk_left_over is None:
        return None, 0
    prev = prev_chunk_left_over
    if isinstance(prev, Tensor) and prev.dim() == 2:
        prev = prev[None].expand(batch_size, -1, -1)                                      # [T, D] -> [B, T, D]
    if not isinstance(prev, Tensor) or not prev.is_floating_point() or prev.dim() != 3 \
            or prev.shape[0] != batch_size or prev.shape[2] != action_dim:
        got = list(prev_chunk_left_over.shape) if isinstance(prev_chunk_left_over, Tensor) \
            else type(prev_chunk_left_over).__name__
        raise ValueError(f"prev_chunk_left_over: expected a float tensor [T, {action_dim}] or [{batch_size}, T, "
                         f"{action_dim}] (the previous chunk's unexecuted actions, normalised), got {got}")
    length = min(prev.shape[1], chunk_size, horizon or chunk_size)
    return prev[:, :length], min(int(inference_delay or 0), length)                       # [B, L, D], d <= L
