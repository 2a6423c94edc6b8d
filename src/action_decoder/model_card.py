"""A checkpoint's model card, `README.md`: Hub front matter (`library_name`, `tags`, `pipeline_tag`,
`datasets`, and the measured success as `model-index`) over a body that says what the policy is
(decoder, sampler and K, network size), how it was trained (task(s), demonstrations or dataset,
frames, steps) and how well it did in closed loop (one table row per evaluation setting).

The measured results live in the front matter's `model-index` (the Hub shows them on the model's
page); each row records the SHA-256 of the weights it measured (`weights_digest`), so a card written for
other weights (fine-tuned, retrained) never carries them over (`carried_results`).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path
from typing import Optional

import torch
from huggingface_hub import EvalResult, ModelCard, ModelCardData

from .config import DecoderConfig

CARD_NAME = "README.md"
LIBRARY_NAME = "action-decoder"
SETTINGS = ("tasks", "sampler", "steps", "n_action_steps", "episodes", "seed", "max_steps", "delay", "rtc")
"""What makes two evaluations the same row: a new result with these settings replaces the old one."""
LATER_SETTINGS = ("max_steps", "delay", "rtc")
"""Settings that cards written before them do not hold: such a row reads them as None (not known)."""


def weights_digest(tensors: dict) -> str:
    """SHA-256 (hex) of a state dict's names, dtypes, shapes and values: which weights a result was
    measured on (not of the file, whose header order safetensors does not fix)."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        digest.update(f"{name}|{t.dtype}|{list(t.shape)}|".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def hub_dataset_id(path: Optional[str]) -> Optional[str]:
    """The Hub repo id of a dataset directory in a Hub cache (`…/datasets--owner--name/snapshots/…`
    of huggingface_hub, or `…/huggingface/lerobot/owner/name` of LeRobot), else None."""
    if not path:
        return None
    text = Path(path).as_posix()
    match = re.search(r"/datasets--([^/]+?)--([^/]+)/snapshots/", text)
    if match:
        return f"{match[1]}/{match[2]}"
    match = re.search(r"/huggingface/lerobot/([^/]+)/([^/]+?)/?$", text)
    return f"{match[1]}/{match[2]}" if match else None


def _result_row(result: EvalResult) -> Optional[dict]:
    """A row of ours from a `model-index` entry (None: an entry another tool wrote)."""
    args = result.metric_args or {}
    if result.metric_type != "success_rate" or not all(k in args for k in SETTINGS if k not in LATER_SETTINGS):
        return None
    return {**{k: args.get(k) for k in SETTINGS}, "success_rate": float(result.metric_value),
            "per_task": dict(args.get("per_task") or {}), "weights_sha256": args.get("weights_sha256")}


def _eval_result(row: dict) -> EvalResult:
    tasks = row["tasks"]
    return EvalResult(
        task_type="robotics", task_name="closed-loop control", dataset_type="metaworld",
        dataset_name=tasks[0] if len(tasks) == 1 else f"{len(tasks)} Meta-World tasks", metric_type="success_rate",
        metric_name="success rate", metric_value=row["success_rate"], metric_config=_settings_text(row),
        metric_args={**{k: row[k] for k in SETTINGS}, "per_task": row["per_task"],
                     "weights_sha256": row["weights_sha256"]})


def _settings_text(row: dict) -> str:
    return (f"{row['sampler']} K={row['steps']}, {row['n_action_steps']} actions per chunk, "
            f"{row['episodes']} episodes per task, seed {row['seed']}, {_cap_text(row)}")


def _cap_text(row: dict) -> str:
    """Episode cap, observation delay and RTC of a row ("not recorded" for a row older than them)."""
    if row.get("max_steps") is None:
        return "episode cap and delay not recorded"
    return (f"at most {row['max_steps']} steps per episode, delay {row['delay']}"
            + (" with real-time chunking" if row["rtc"] else "")
            + (f" ({row['rtc']})" if isinstance(row["rtc"], str) else ""))


def read_results(directory: Path) -> list[dict]:
    """The measured results in `directory`'s card (empty without a card or results)."""
    path = Path(directory) / CARD_NAME
    if not path.is_file():
        return []
    try:
        card = ModelCard.load(path)
    except Exception:       # a hand-written README without (valid) front matter holds no results of ours
        return []
    return [row for r in (card.data.eval_results or []) if (row := _result_row(r)) is not None]


def carried_results(results: list[dict], digest: str) -> list[dict]:
    """The results measured on the weights with this SHA-256."""
    return [r for r in results if r.get("weights_sha256") == digest]


def merge_result(results: list[dict], row: dict) -> list[dict]:
    """`results` with `row` added, replacing a row with the same settings (`SETTINGS`)."""
    key = tuple(str(row[k]) for k in SETTINGS)
    return [r for r in results if tuple(str(r[k]) for k in SETTINGS) != key] + [row]


def build_card(config: DecoderConfig, num_parameters: int, results: list[dict]) -> ModelCard:
    """The card of a policy with this config, parameter count and measured results."""
    train = config.extra.get("train") or {}
    tasks = list(config.extra.get("tasks") or [])
    dataset = hub_dataset_id(train.get("dataset"))
    tags = ["robotics", LIBRARY_NAME, config.decoder_type.lower().replace("_", "-"), "action-chunking"]
    if (train and not train.get("dataset")) or results:      # trained on, or evaluated in, Meta-World
        tags.append("metaworld")
    name = f"{LIBRARY_NAME} {config.decoder_type}" + (f" on {', '.join(tasks)}" if 0 < len(tasks) <= 3 else
                                                       f" on {len(tasks)} tasks" if tasks else "")
    data = ModelCardData(library_name=LIBRARY_NAME, pipeline_tag="robotics", tags=tags,
                         datasets=[dataset] if dataset else None, model_name=name if results else None,
                         eval_results=[_eval_result(r) for r in results] or None)
    body = "\n".join([f"# {name}", "", f"An action decoder of the `{LIBRARY_NAME}` library: it maps robot "
                      f"state (and optional context tokens or a VLM's KV cache) to a chunk of "
                      f"{config.action_chunk_size} actions.", "", "## Policy", "", *_policy_table(config, num_parameters),
                      "", "## Training", "", *_training_lines(train, tasks, config.extra.get("data") or {}),
                      "", "## Results", "", *_results_lines(results), "", "## Use", "", "```python",
                      "from action_decoder import ActionDecoderPolicy", "",
                      'policy = ActionDecoderPolicy.from_pretrained("<this repo id or directory>").eval()',
                      'chunk = policy.predict_action_chunk({"state": state})   # [B, H, D], env units', "```", ""])
    return ModelCard(f"---\n{data.to_yaml()}\n---\n\n{body}")


def _policy_table(config: DecoderConfig, num_parameters: int) -> list[str]:
    sampler = config.default_sampler
    steps = config.flow_sde_num_steps if sampler == "sde" else config.num_inference_timesteps
    head = {"DDPM": f"{config.prediction_type} prediction"}.get(config.decoder_type, f"{config.flow_prediction} head")
    native = {"DDPM": "DPM-Solver++", "flow_matching": "Euler ODE", "mean_flow": "MeanFlow steps"}[config.decoder_type]
    conditioning = [f"context tokens of width {config.context_dim}" if config.context_dim else "",
                    f"a VLM KV cache of {config.vlm_num_layers} layers" if config.vlm_num_layers else "",
                    f"cameras {', '.join(config.cameras)} ({config.image_size} px, {config.image_encoder} encoder, "
                    f"{config.image_tokens_per_camera} tokens each)" if config.cameras else ""]
    return ["| | |", "|---|---|", f"| decoder | {config.decoder_type} ({head}) |",
            f"| sampler | {sampler} ({native if sampler == 'ode' else 'SDE, ' + config.flow_sde_mode}), K = {steps} |",
            f"| action chunk | {config.action_chunk_size} steps × {config.action_dim} dims, "
            f"{config.n_action_steps} executed per plan |",
            f"| state | {config.state_dim}-d, {config.state_layout} layout, {config.normalization_mode} normalisation |",
            f"| conditioning | {' and '.join(c for c in conditioning if c) or 'state only'} |",
            f"| network | Action Expert transformer: {config.num_hidden_layers} "
            f"layer{'s' if config.num_hidden_layers != 1 else ''}, hidden size "
            f"{config.hidden_size}, {config.num_attention_heads} heads ({config.num_key_value_heads} KV), "
            f"{num_parameters:,} parameters |"]


def _training_lines(train: dict, tasks: list[str], data: dict) -> list[str]:
    if not train:
        return ["Not recorded: this checkpoint was not written by `action-decoder train`."]
    if train.get("dataset"):
        source = f"LeRobot dataset `{hub_dataset_id(train['dataset']) or train['dataset']}`"
    else:
        noise = f", recorded with action noise σ = {train['demo_noise']} (DART)" if train.get("demo_noise") else ""
        source = (f"{train.get('demos')} scripted-expert demonstrations per task (Meta-World layouts from "
                  f"seed {train.get('seed')}){noise}")
    frames = (f"{data['frames']:,} frames in {data['episodes']} episodes" if {"frames", "episodes"} <= set(data)
              else "not recorded")
    return ["| | |", "|---|---|", f"| task(s) | {', '.join(tasks) or 'not recorded'} |", f"| data | {source} |",
            f"| frames | {frames} |",
            f"| steps | {train.get('steps')} optimizer steps, batch {train.get('batch_size')}, lr {train.get('lr')}, "
            f"weight average {train.get('ema_decay')} |", f"| seed | {train.get('seed')} |"]


def _results_lines(results: list[dict]) -> list[str]:
    if not results:
        return ["Not measured yet: `action-decoder eval --checkpoint <this directory>` adds a row."]
    lines = ["Closed-loop success on layouts disjoint from the demonstrations (`action-decoder eval`):", "",
             "| sampler | K | actions per chunk | episodes per task | seed | success rate | per task | episode cap, delay |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        per_task = ", ".join(f"{t} {v:.2f}" for t, v in r["per_task"].items()) if len(r["per_task"]) > 1 else ""
        lines.append(f"| {r['sampler']} | {r['steps']} | {r['n_action_steps']} | {r['episodes']} | {r['seed']} "
                     f"| {r['success_rate']:.4f} | {per_task or ', '.join(r['tasks'])} | {_cap_text(r)} |")
    return lines


def write_card(directory: Path, config: DecoderConfig, num_parameters: int, results: list[dict]) -> Path:
    """Write `directory/README.md` atomically (a temporary file, then a rename)."""
    path, tmp = Path(directory) / CARD_NAME, Path(directory) / (CARD_NAME + ".tmp")
    tmp.write_text(str(build_card(config, num_parameters, results)), encoding="utf-8")
    os.replace(tmp, path)
    return path


def record_result(directory: Path, policy, summary: dict, tasks: list[str]) -> Path:
    """Add the result of `summary` (`evaluate.run_eval`'s) to the card in the checkpoint `directory`,
    replacing a row with the same settings; the card is (re)built from `policy` around its results.
    OSError when the directory cannot be written."""
    directory = Path(directory)
    digest = weights_digest(policy.state_dict())
    row = {"tasks": list(tasks), "sampler": summary["sampler"], "steps": summary["steps"],
           "n_action_steps": summary["n_action_steps"], "episodes": summary["episodes_per_task"],
           "seed": summary["seed"], "max_steps": summary["max_steps"], "delay": summary["delay"],
           "rtc": summary.get("rtc_mode") or bool(summary["rtc"]), "success_rate": float(summary["success_rate"]),
           "per_task": {k: float(v) for k, v in summary["per_task"].items()}, "weights_sha256": digest}
    results = merge_result(carried_results(read_results(directory), digest), row)
    return write_card(directory, policy.config, sum(p.numel() for p in policy.parameters()), results)
