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
import json
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


METAWORLD_TASK = re.compile(r"^[a-z][a-z0-9-]*-v3$")
"""A Meta-World v3 task name, as generated demonstrations and `action-decoder record`'s datasets carry them."""


LEROBOT_AGENT_POS_DIM = 4
"""The state LeRobot's Meta-World env observes (`envs.lerobot_view.AGENT_POS_DIM`, here without the simulator)."""


def simulator_policy(config: DecoderConfig) -> bool:
    """Whether `action-decoder eval` and `finetune` can run this policy closed loop: Meta-World's state
    and action widths (39, 4; a policy of `record --layout lerobot` data observes LeRobot's 4-d agent
    position instead), and Meta-World task names, if it names any (a LeRobot dataset's task strings,
    "push the block", name none)."""
    from .state_layout import METAWORLD_STATE_DIM

    lerobot_view = config.extra.get("observation_layout") == "lerobot"
    state_dim = LEROBOT_AGENT_POS_DIM if lerobot_view else METAWORLD_STATE_DIM
    tasks = list(config.extra.get("tasks") or [])
    return (config.state_dim, config.action_dim) == (state_dim, 4) and \
        all(isinstance(t, str) and METAWORLD_TASK.match(t) for t in tasks)


def trained_on(config: DecoderConfig) -> str:
    """What the policy was trained on, in a few words: the dataset (and its tasks), for messages."""
    train, tasks = config.extra.get("train") or {}, list(config.extra.get("tasks") or [])
    shown = tasks if len(tasks) <= 3 else tasks[:3] + [f"... ({len(tasks)} in all)"]
    source = f"the dataset {hub_dataset_id(train['dataset']) or train['dataset']}" if train.get("dataset") else \
        "data of its own"
    return (f"{source} (tasks {shown}, {config.state_dim}-d state, {config.action_dim}-d actions)" if tasks else
            f"{source} ({config.state_dim}-d state, {config.action_dim}-d actions)")


def validation_of(config: DecoderConfig, digest: Optional[str]) -> Optional[dict]:
    """The held-out validation `action-decoder train --dataset` measured on the weights with this SHA-256
    (`config.extra["validation"]`), or None (none measured, or measured on other weights)."""
    val = config.extra.get("validation")
    if not isinstance(val, dict) or digest is None or val.get("weights_sha256") != digest:
        return None
    return val


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


def build_card(config: DecoderConfig, num_parameters: int, results: list[dict],
               digest: Optional[str] = None) -> ModelCard:
    """The card of a policy with this config, parameter count and measured results; `digest`, the
    weights' SHA-256, shows the held-out validation measured on them (`validation_of`). With
    `config.extra["finetune_weights"]`, a "Fine-tuning" section says which weights of an RL run these are."""
    train = config.extra.get("train") or {}
    tasks = list(config.extra.get("tasks") or [])
    dataset = hub_dataset_id(train.get("dataset"))
    val = validation_of(config, digest)
    tags = ["robotics", LIBRARY_NAME, config.decoder_type.lower().replace("_", "-"), "action-chunking"]
    if (train and not train.get("dataset")) or results:      # trained on, or evaluated in, Meta-World
        tags.append("metaworld")
    name = f"{LIBRARY_NAME} {config.decoder_type}" + (f" on {', '.join(tasks)}" if 0 < len(tasks) <= 3 else
                                                       f" on {len(tasks)} tasks" if tasks else "")
    evals = [_eval_result(r) for r in results] + (_validation_results(val, train) if val else [])
    data = ModelCardData(library_name=LIBRARY_NAME, pipeline_tag="robotics", tags=tags,
                         datasets=[dataset] if dataset else None, model_name=name if evals else None,
                         eval_results=evals or None)
    body = "\n".join([f"# {name}", "", f"An action decoder of the `{LIBRARY_NAME}` library: it maps robot "
                      f"state (and optional context tokens or a VLM's KV cache) to a chunk of "
                      f"{config.action_chunk_size} actions.", "", "## Policy", "", *_policy_table(config, num_parameters),
                      "", "## Training", "", *_training_lines(train, tasks, config.extra.get("data") or {}),
                      *(["", "## Fine-tuning", "", config.extra["finetune_weights"]]
                        if config.extra.get("finetune_weights") else []),
                      "", "## Results", "", *_results_lines(results, config, val), "", "## Use", "", "```python",
                      *use_snippet(config), "```", ""])
    return ModelCard(f"---\n{data.to_yaml()}\n---\n\n{body}")


REPO_PLACEHOLDER = "<this repo id or directory>"


def use_snippet(config: DecoderConfig) -> list[str]:
    """The card's "Use" code, lines that run as written once `REPO_PLACEHOLDER` names the checkpoint: a
    batch of one zero state (and the inputs this policy needs: the task's one-hot token of a multi-task
    policy, context tokens, camera frames) → one chunk."""
    tasks = list(config.extra.get("tasks") or [])
    multi = len(tasks) > 1 and config.context_dim == len(tasks)
    lines = ["import torch", "", "from action_decoder import ActionDecoderPolicy"]
    lines += ["from action_decoder.train import task_context"] if multi else []
    lines += ["", f'policy = ActionDecoderPolicy.from_pretrained("{REPO_PLACEHOLDER}").eval()',
              f'batch = {{"state": torch.zeros(1, {config.state_dim})}}   # [B, {config.state_dim}]: '
              f'the robot state, env units']
    if multi:
        lines += [f"task = policy.config.extra[\"tasks\"].index({json.dumps(tasks[0])})   # one of the {len(tasks)} "
                  f"trained tasks",
                  f"batch.update(task_context(torch.tensor([task]), {len(tasks)}))   # its one-hot token, "
                  f"context [B, 1, {len(tasks)}]"]
    elif config.context_dim:
        lines += [f'batch["context"] = torch.zeros(1, 1, {config.context_dim})   # [B, L, {config.context_dim}]: '
                  f'your context tokens']
    if config.cameras:
        n, size = len(config.cameras), config.image_size
        lines += [f'batch["images"] = torch.zeros(1, {n}, 3, {size}, {size}, dtype=torch.uint8)   # [B, {n}, 3, '
                  f'{size}, {size}]: {", ".join(config.cameras)}']
    if config.uses_vlm_cache:
        lines += [f'# batch["vlm_key_values"] = the VLM\'s KV cache ({config.vlm_num_layers} layers) and '
                  f'batch["attention_mask"]']
    return lines + ['chunk = policy.predict_action_chunk(batch)   # [B, H, D], env units']


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
            f"| state | {config.state_dim}-d, {config.state_layout} layout, {config.normalization_mode} normalisation"
            f"{f', the last {config.n_obs_steps} observations' if config.n_obs_steps > 1 else ''} |",
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


def _validation_results(val: dict, train: dict) -> list[EvalResult]:
    """`model-index` entries of the held-out validation (the Hub shows them with the success rates)."""
    name = hub_dataset_id(train.get("dataset")) or Path(str(train.get("dataset"))).name
    where = f"held-out episodes {val.get('episodes')} ({val.get('frames')} frames)"
    return [EvalResult(task_type="robotics", task_name="action chunk prediction", dataset_type="lerobot",
                       dataset_name=name, metric_type=key, metric_name=label, metric_value=float(val[key]),
                       metric_config=where)
            for key, label in (("val_loss", "validation loss"), ("val_action_mse", "validation action MSE"))]


def _validation_lines(val: dict) -> list[str]:
    return ["Held-out validation (`action-decoder train --dataset`: the last episodes of the dataset, never "
            "trained on):", "", "| held-out episodes | frames | val_loss | val_action_mse |", "|---|---|---|---|",
            f"| {', '.join(map(str, val.get('episodes') or []))} | {val.get('frames')} | {val['val_loss']:.4f} "
            f"| {val['val_action_mse']:.4f} |", "",
            f"`val_loss`: the decoder's training loss on the held-out chunks ({val.get('noise_draws')} noise draws, "
            f"seed {val.get('seed')}); `val_action_mse`: sampled chunks against the held-out actions, normalised "
            f"units, padding excluded."]


def _results_lines(results: list[dict], config: DecoderConfig, val: Optional[dict] = None) -> list[str]:
    from .state_layout import METAWORLD_STATE_DIM

    if not results:
        lines = [*_validation_lines(val), ""] if val else []
        if simulator_policy(config):
            return lines + ["Not measured yet: `action-decoder eval --checkpoint <this directory>` adds a row."]
        return lines + [f"Closed-loop success is not measured: `action-decoder eval` runs Meta-World tasks "
                        f"({METAWORLD_STATE_DIM}-d state, 4-d actions), and this policy was trained on "
                        f"{trained_on(config)}. Run it in its own environment (see Use)."]
    lines = ["Closed-loop success on layouts disjoint from the demonstrations (`action-decoder eval`):", "",
             "| sampler | K | actions per chunk | episodes per task | seed | success rate | per task | episode cap, delay |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        per_task = ", ".join(f"{t} {v:.2f}" for t, v in r["per_task"].items()) if len(r["per_task"]) > 1 else ""
        lines.append(f"| {r['sampler']} | {r['steps']} | {r['n_action_steps']} | {r['episodes']} | {r['seed']} "
                     f"| {r['success_rate']:.4f} | {per_task or ', '.join(r['tasks'])} | {_cap_text(r)} |")
    return lines


def write_card(directory: Path, config: DecoderConfig, num_parameters: int, results: list[dict],
               digest: Optional[str] = None) -> Path:
    """Write `directory/README.md` atomically (a temporary file, then a rename)."""
    path, tmp = Path(directory) / CARD_NAME, Path(directory) / (CARD_NAME + ".tmp")
    tmp.write_text(str(build_card(config, num_parameters, results, digest)), encoding="utf-8")
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
    return write_card(directory, policy.config, sum(p.numel() for p in policy.parameters()), results, digest)
