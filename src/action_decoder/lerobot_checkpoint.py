"""Library checkpoints ↔ LeRobot `pretrained_model/` directories of the `action_decoder` plugin.

A library checkpoint (`save_pretrained`: config.json, model.safetensors) normalises inside the
policy; a LeRobot one holds the same network under the prefix `decoder.` and normalises in its
processors (`policy_preprocessor.json`, `policy_postprocessor.json` and their safetensors
states). `to_lerobot` writes the second from the first and `to_library` the first from the
second, without LeRobot installed:

- weights: the tensors are copied as stored (bit-identical), the statistics buffers included;
- config: the plugin's fields (`PLUGIN_FIELDS`, LeRobot's `chunk_size` and `num_inference_steps`
  for the library's `action_chunk_size` and `num_inference_timesteps`), the features (state,
  cameras, action) and the normalisation mode (`mean_std`, `min_max`, `identity` ↔ LeRobot's
  MEAN_STD, MIN_MAX, IDENTITY);
- statistics: the processors get the spread the library divides by (a spread below the floor
  taken as `normalize.SPREAD_FLOOR`), so LeRobot normalises as the library does; the
  postprocessor clamps actions to the data's [min, max] (the step `CLIP_STEP`) when the policy
  has `clip_actions`.

Back in the library, the statistics buffers of the weights are kept when the processors'
statistics are theirs (a round trip is bit-identical); otherwise (a policy trained by
`lerobot-train`) they come from the processors.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any, Literal, Mapping, Optional, Sequence

import torch
from torch import Tensor

from .config import DecoderConfig, is_camera_key

LEROBOT_TYPE = "action_decoder"
PREFIX = "decoder."                              # the plugin holds the core policy as `self.decoder`
STATE, ACTION = "observation.state", "action"
PREPROCESSOR, POSTPROCESSOR = "policy_preprocessor", "policy_postprocessor"
NORMALIZER, UNNORMALIZER = "normalizer_processor", "unnormalizer_processor"
CLIP_STEP = "action_decoder_clip_actions"        # registered by the plugin (processor_action_decoder.py)
MODES = {"mean_std": "MEAN_STD", "min_max": "MIN_MAX", "identity": "IDENTITY"}
LEROBOT_EPS = 1e-8                               # LeRobot's normaliser: (x − mean)/(std + eps)
# Plugin field -> DecoderConfig field where the names differ (LeRobot's names on the left).
RENAMED = {"chunk_size": "action_chunk_size", "num_inference_steps": "num_inference_timesteps"}
# DecoderConfig fields the plugin carries under the same name. The first group is the plugin's
# original set (a LeRobot config.json always has them); the second has the core's defaults there.
PLUGIN_FIELDS = (
    "decoder_type", "n_action_steps", "flow_sde_num_steps", "num_train_timesteps", "prediction_type",
    "beta_schedule", "clip_sample", "flow_sde_use", "flow_sde_mode", "flow_sde_s_churn",
    "flow_sde_learn_sigma", "flow_sde_sigma_init", "flow_sde_return_logprob", "flow_sde_logprob_sigma_only",
    "meanflow_sde_velocity", "meanflow_ratio_r_neq_t", "meanflow_time_dist", "meanflow_adaptive_p",
    "meanflow_target", "hidden_size", "num_hidden_layers", "num_attention_heads", "num_key_value_heads",
    "image_size", "image_encoder", "image_tokens_per_camera", "image_encoder_pretrained",
    "freeze_image_encoder", "image_shift")
PLUGIN_FIELDS_ADDED = (
    "intermediate_size", "rms_norm_eps", "rope_theta", "flow_sde_eps", "flow_sde_clip_t", "flow_sde_t_min",
    "meanflow_time_mean", "meanflow_time_std", "meanflow_adaptive_c", "meanflow_dudt", "rtc_guidance_weight",
    "rtc_schedule", "rtc_horizon", "rtc_max_delay", "rtc_delay_dist", "rtc_balance_rows", "rtc_prefix_noise",
    "default_ctrl_freq", "noise_actor_hidden", "noise_actor_bound", "n_obs_steps", "meanflow_one_step_share")
# Fields each side sets itself: from the features, the tasks and the processors.
DERIVED = ("state_dim", "action_dim", "cameras", "context_dim", "normalization_mode", "clip_actions",
           "action_constant_below", "extra")


def plugin_core_config(values: Mapping[str, Any], state_dim: int, action_dim: int, cameras: Sequence[str] = (),
                       tasks: Sequence[str] = (), **core: Any) -> DecoderConfig:
    """The core `DecoderConfig` of plugin fields `values` (LeRobot's names; a missing added field takes
    the core's default). `num_inference_steps=None` and `flow_prediction=None` take what `action-decoder
    train` takes (MeanFlow: 1 step and the clean-chunk head; DDPM and flow matching: 10 steps and the
    velocity head). Two or more `tasks` make a one-hot task token of width len(tasks). `core` sets
    the derived fields (normalisation, clipping, extra); the plugin's own policy normalises nothing.
    A bad value raises the core's ValueError with the plugin's field name (`policy.<name>`)."""
    from .train import DEFAULT_STEPS      # sampling steps when num_inference_steps is None

    fields = {name: values[name] for name in PLUGIN_FIELDS}
    fields.update({name: values[name] for name in PLUGIN_FIELDS_ADDED if name in values})
    steps = values.get("num_inference_steps")
    fields["num_inference_timesteps"] = DEFAULT_STEPS.get(fields["decoder_type"], 10) if steps is None else steps
    fields["action_chunk_size"] = values["chunk_size"]
    fields["flow_prediction"] = values.get("flow_prediction") or (
        "sample" if fields["decoder_type"] == "mean_flow" else "velocity")
    tasks = [str(t) for t in tasks]
    core = {"normalization_mode": "identity", "clip_actions": False,
            "extra": {"tasks": tasks, "lerobot_policy": LEROBOT_TYPE}, **core}
    try:
        return DecoderConfig(**fields, state_dim=state_dim, action_dim=action_dim, cameras=tuple(cameras),
                             context_dim=len(tasks) if len(tasks) > 1 else None, **core)
    except ValueError as err:
        msg = str(err)
        for ours, name in RENAMED.items():
            msg = msg.replace(name, ours)
        raise ValueError(f"policy.{msg}") from None


# ---------------------------------------------------------------------------------------- statistics
def _effective(norm) -> dict[str, Tensor]:
    """What LeRobot's normaliser needs to normalise as the library's `Normalizer` does: mean/std
    (mean_std: the spread after the floor), min/max (min_max: centre ∓ the floored half range), and the
    data's own min/max otherwise."""
    scale, shift = norm._scale_shift()
    if norm.mode == "mean_std":
        return {"mean": shift.clone(), "std": scale.clone(), "min": norm.min.clone(), "max": norm.max.clone()}
    if norm.mode == "min_max":
        return {"mean": norm.mean.clone(), "std": norm.std.clone(), "min": shift - scale, "max": shift + scale}
    return {k: getattr(norm, k).clone() for k in ("mean", "std", "min", "max")}


def _features(cfg: DecoderConfig) -> tuple[dict, dict]:
    inputs = {STATE: {"type": "STATE", "shape": [cfg.state_dim]}}
    inputs.update({cam: {"type": "VISUAL", "shape": [3, cfg.image_size, cfg.image_size]} for cam in cfg.cameras})
    return inputs, {ACTION: {"type": "ACTION", "shape": [cfg.action_dim]}}


def _norm_map(mode: str) -> dict:
    return {"VISUAL": "IDENTITY", "STATE": MODES[mode], "ACTION": MODES[mode]}


# ---------------------------------------------------------------------------------------- library → LeRobot
def _convertible(cfg: DecoderConfig) -> list[str]:
    """Tasks of `cfg` after checking that the plugin can run it; raises naming the field otherwise."""
    if cfg.state_layout != "flat":
        raise ValueError(f"state_layout: the LeRobot plugin reads the state as it comes (LeRobot normalises it "
                         f"before the policy, so the raw positions that state_layout={cfg.state_layout!r} derives "
                         f"features from never reach it); expected 'flat', e.g. a policy trained with --dataset on "
                         f"`record --layout lerobot` demonstrations")
    if cfg.uses_vlm_cache:
        raise ValueError("vlm_num_layers: a policy conditioned on a VLM's KV cache has no LeRobot counterpart")
    if cfg.action_squash:
        raise ValueError("action_squash: a SAC-fine-tuned policy squashes environment units, which LeRobot's "
                         "postprocessor reaches only after the policy; it has no LeRobot counterpart")
    tasks = [str(t) for t in (cfg.extra.get("tasks") or [])]
    want = len(tasks) if len(tasks) > 1 else None
    if cfg.context_dim != want:
        raise ValueError(f"context_dim: the plugin conditions on a one-hot token of the {len(tasks)} task(s) "
                         f"(context_dim {want}); this policy has context_dim {cfg.context_dim}")
    return tasks


def plugin_values(cfg: DecoderConfig) -> dict:
    """The plugin's config fields (LeRobot's names) of a library config."""
    values = {name: getattr(cfg, name) for name in PLUGIN_FIELDS + PLUGIN_FIELDS_ADDED}
    values.update({ours: getattr(cfg, core) for ours, core in RENAMED.items()})
    values["flow_prediction"] = cfg.flow_prediction
    values["clip_actions"] = cfg.clip_actions
    values["tasks"] = [str(t) for t in (cfg.extra.get("tasks") or [])]
    return values


def to_lerobot(checkpoint: str | Path, output_dir: str | Path) -> Path:
    """Write the LeRobot `pretrained_model/` directory of a library checkpoint into `output_dir`
    (new or empty); returns it. Loads with LeRobot's `from_pretrained` and `make_pre_post_processors`
    once the plugin is installed (`lerobot-eval --policy.path=DIR`)."""
    from safetensors.torch import load_file, save_file

    from .policy import CONFIG_NAME, WEIGHTS_NAME, ActionDecoderPolicy

    src = Path(checkpoint).expanduser()
    if (src / "config.json").is_file() and json.loads((src / "config.json").read_text()).get("type") == LEROBOT_TYPE:
        raise ValueError(f"--checkpoint: {src} is already a LeRobot checkpoint; use --to library")
    policy = ActionDecoderPolicy.from_pretrained(src)
    cfg = policy.config
    tasks = _convertible(cfg)
    values = plugin_values(cfg)
    # Every field the plugin does not carry must be what the plugin builds, or the policy would change.
    rebuilt = plugin_core_config(values, cfg.state_dim, cfg.action_dim, cfg.cameras, tasks)
    lost = [f.name for f in dataclasses.fields(cfg) if f.name not in DERIVED
            and getattr(cfg, f.name) != getattr(rebuilt, f.name)]
    if lost:
        raise ValueError(f"{', '.join(lost)}: {[getattr(cfg, n) for n in lost]} has no field in the LeRobot plugin "
                         f"(which would build {[getattr(rebuilt, n) for n in lost]})")
    out = _new_dir(output_dir)
    inputs, outputs = _features(cfg)
    norm_map = _norm_map(cfg.normalization_mode)
    config = {"type": LEROBOT_TYPE, "n_obs_steps": 1, "input_features": inputs, "output_features": outputs,
              "device": "cpu", "use_amp": False, "push_to_hub": False, **values, "normalization_mapping": norm_map}
    train = cfg.extra.get("train") or {}
    for ours, theirs in (("optimizer_lr", "lr"), ("optimizer_weight_decay", "weight_decay"),
                         ("optimizer_grad_clip_norm", "grad_clip"), ("scheduler_warmup_steps", "warmup_steps")):
        if theirs in train:
            config[ours] = train[theirs]
    (out / CONFIG_NAME).write_text(json.dumps(config, indent=4) + "\n")
    tensors = load_file(str(src / WEIGHTS_NAME))              # as stored: bit-identical
    save_file({PREFIX + k: v for k, v in tensors.items()}, str(out / WEIGHTS_NAME), metadata={"format": "pt"})
    stats = {STATE: _effective(policy.normalizers["state"]), ACTION: _effective(policy.normalizers["actions"])}
    flat = {f"{key}.{name}": value.contiguous() for key, d in stats.items() for name, value in d.items()}
    pre_state = f"{PREPROCESSOR}_step_3_{NORMALIZER}.safetensors"
    save_file(flat, str(out / pre_state))
    device = {"device": "cpu", "float_dtype": None}
    pre = {"name": PREPROCESSOR, "steps": [
        {"registry_name": "rename_observations_processor", "config": {"rename_map": {}}},
        {"registry_name": "to_batch_processor", "config": {}},
        {"registry_name": "device_processor", "config": device},
        {"registry_name": NORMALIZER, "config": {"eps": LEROBOT_EPS, "features": {**inputs, **outputs},
                                                "norm_map": norm_map}, "state_file": pre_state}]}
    post_state = f"{POSTPROCESSOR}_step_0_{UNNORMALIZER}.safetensors"
    save_file(flat, str(out / post_state))
    steps = [{"registry_name": UNNORMALIZER, "config": {"eps": LEROBOT_EPS, "features": outputs, "norm_map": norm_map},
              "state_file": post_state}]
    if cfg.clip_actions:
        clip_state = f"{POSTPROCESSOR}_step_1_{CLIP_STEP}.safetensors"
        norm = policy.normalizers["actions"]
        save_file({f"{ACTION}.min": norm.min.clone(), f"{ACTION}.max": norm.max.clone()}, str(out / clip_state))
        steps.append({"registry_name": CLIP_STEP, "config": {}, "state_file": clip_state})
    steps.append({"registry_name": "device_processor", "config": device})
    (out / f"{PREPROCESSOR}.json").write_text(json.dumps(pre, indent=2) + "\n")
    (out / f"{POSTPROCESSOR}.json").write_text(json.dumps({"name": POSTPROCESSOR, "steps": steps}, indent=2) + "\n")
    return out


# ---------------------------------------------------------------------------------------- LeRobot → library
def _pipeline_state(path: Path, name: str, registry_name: str) -> Optional[dict[str, Tensor]]:
    """The safetensors state of the first step `registry_name` of the pipeline `name`.json (None: no such step)."""
    from safetensors.torch import load_file

    file = path / f"{name}.json"
    if not file.is_file():
        raise ValueError(f"--checkpoint: {path} has no {file.name}; expected a LeRobot pretrained_model/ directory "
                         f"saved with its processors (lerobot-train writes them)")
    for step in json.loads(file.read_text()).get("steps", []):
        if step.get("registry_name") == registry_name:
            return load_file(str(path / step["state_file"])) if step.get("state_file") else {}
    return None


def _lerobot_dir(path: str | Path) -> Path:
    """`path`, or its `pretrained_model/` (a LeRobot checkpoint directory such as checkpoints/last)."""
    path = Path(path).expanduser()
    if not (path / "config.json").is_file() and (path / "pretrained_model" / "config.json").is_file():
        path = path / "pretrained_model"
    if not (path / "config.json").is_file():
        raise ValueError(f"--checkpoint: expected a LeRobot pretrained_model/ directory with a config.json, got {path}")
    return path


def to_library(checkpoint: str | Path, output_dir: str | Path) -> Path:
    """Write the library checkpoint of a LeRobot `action_decoder` `pretrained_model/` directory into
    `output_dir` (new or empty); returns it. Actions are clamped when the postprocessor clamps them."""
    from safetensors.torch import load_file

    from .policy import WEIGHTS_NAME, ActionDecoderPolicy

    src = _lerobot_dir(checkpoint)
    data = json.loads((src / "config.json").read_text())
    if data.get("type") != LEROBOT_TYPE:
        raise ValueError(f"--checkpoint: {src}/config.json is a LeRobot policy of type {data.get('type')!r}; "
                         f"expected {LEROBOT_TYPE!r} (the action-decoder plugin)")
    missing = [k for k in PLUGIN_FIELDS + ("chunk_size", "input_features", "output_features") if k not in data]
    if missing:
        raise ValueError(f"--checkpoint: {src}/config.json lacks the field(s) {missing} of the plugin's config")
    inputs, outputs = data["input_features"] or {}, data["output_features"] or {}
    dims = []
    for where, feats, key in (("input_features", inputs, STATE), ("output_features", outputs, ACTION)):
        shape = (feats.get(key) or {}).get("shape")
        if not isinstance(shape, list) or len(shape) != 1:
            raise ValueError(f"--checkpoint: config.json {where}[{key!r}]: expected a 1-d feature, got {shape}")
        dims.append(int(shape[0]))
    cameras = [k for k in inputs if is_camera_key(k)]
    norm_map = data.get("normalization_mapping") or {}
    modes = {MODES[m]: m for m in MODES}
    state_mode, action_mode = norm_map.get("STATE", "MEAN_STD"), norm_map.get("ACTION", "MEAN_STD")
    if state_mode != action_mode or state_mode not in modes:
        raise ValueError(f"normalization_mapping: the library normalises state and action alike, with one of "
                         f"{list(modes)}; got STATE {state_mode} and ACTION {action_mode}")
    stats = _pipeline_state(src, PREPROCESSOR, NORMALIZER)
    if stats is None:
        raise ValueError(f"--checkpoint: {src}/{PREPROCESSOR}.json has no {NORMALIZER} step (the statistics)")
    clip = _pipeline_state(src, POSTPROCESSOR, CLIP_STEP)
    cfg = plugin_core_config(data, dims[0], dims[1], cameras, data.get("tasks") or [],
                             normalization_mode=modes[state_mode], clip_actions=clip is not None,
                             extra={"tasks": [str(t) for t in data.get("tasks") or []]})
    weights = load_file(str(src / WEIGHTS_NAME))
    foreign = sorted(k for k in weights if not k.startswith(PREFIX))
    if foreign:
        raise ValueError(f"--checkpoint: {src / WEIGHTS_NAME} holds tensors outside the plugin's decoder: {foreign[:5]}")
    tensors = {k[len(PREFIX):]: v for k, v in weights.items()}
    policy = ActionDecoderPolicy(cfg, load_pretrained=False)
    own = policy.state_dict()
    if set(own) != set(tensors) or any(own[k].shape != tensors[k].shape for k in own):
        raise ValueError(f"--checkpoint: {src / WEIGHTS_NAME} does not match its config.json (missing "
                         f"{sorted(set(own) - set(tensors))[:5]}, unexpected {sorted(set(tensors) - set(own))[:5]})")
    policy.load_state_dict(tensors)
    for key, name in ((STATE, "state"), (ACTION, "actions")):
        norm, theirs = policy.normalizers[name], {s: stats[f"{key}.{s}"] for s in ("mean", "std", "min", "max")
                                                  if f"{key}.{s}" in stats}
        ours = _effective(norm)
        if not all(torch.equal(ours[s], v.to(torch.float32)) for s, v in theirs.items()):
            # Not the buffers' own statistics (a policy trained by lerobot-train): the processors' are.
            for s in ("mean", "std"):
                getattr(norm, s).copy_(theirs.get(s, getattr(norm, s)))
            for s, fill in (("min", -torch.inf), ("max", torch.inf)):
                getattr(norm, s).copy_(theirs[s] if s in theirs else torch.full_like(getattr(norm, s), fill))
        if name == "actions" and clip:
            norm.min.copy_(clip[f"{ACTION}.min"])
            norm.max.copy_(clip[f"{ACTION}.max"])
    out = _new_dir(output_dir)
    policy.save_pretrained(out)
    return out


def _new_dir(path: str | Path) -> Path:
    out = Path(path).expanduser()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"--output-dir: expected a new or empty directory, got {out} (not empty)")
    out.mkdir(parents=True, exist_ok=True)
    return out


def convert(checkpoint: str | Path, to: str, output_dir: str | Path) -> Path:
    """`to_lerobot` or `to_library` by `to` ("lerobot" | "library")."""
    if to == "lerobot":
        return to_lerobot(checkpoint, output_dir)
    if to == "library":
        return to_library(checkpoint, output_dir)
    raise ValueError(f"--to: expected 'lerobot' or 'library', got {to!r}")


@dataclasses.dataclass
class ConvertConfig:
    """Convert a checkpoint between the library's layout (a `final/` directory) and a LeRobot
    `pretrained_model/` of the action_decoder plugin (weights copied bit-identical)."""

    checkpoint: str
    """The checkpoint: a library directory (--to lerobot), or a LeRobot pretrained_model/ or the checkpoint directory holding it (--to library)."""
    to: Literal["lerobot", "library"]
    """lerobot: a pretrained_model/ for lerobot-eval --policy.path (plugin installed); library: a directory for action-decoder eval."""
    output_dir: str
    """A new or empty directory for the converted checkpoint."""


def run_convert(cfg: ConvertConfig) -> Path:
    out = convert(cfg.checkpoint, cfg.to, cfg.output_dir)
    print(f"converted {cfg.checkpoint} to a {'LeRobot pretrained_model' if cfg.to == 'lerobot' else 'library checkpoint'} "
          f"in {out}", flush=True)
    return out
