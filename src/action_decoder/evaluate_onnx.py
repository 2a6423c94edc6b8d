"""`action-decoder eval --onnx FILE`: closed-loop evaluation of an exported policy with onnxruntime.

The episodes, their layouts and each chunk's initial noise are those of the checkpoint's own
evaluation (`evaluate.run_eval` with the same --seed): the noise of row b is drawn from the
generator seeded by (seed, episode seed, plan index), here with torch, and handed to the graph.
With --rtc, a file exported with `--rtc` is handed each new chunk's committed actions and the delay
(trained real-time chunking, as `eval --rtc` runs it on the checkpoint).
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from .config import DecoderConfig
from .evaluate import EvalConfig, eval_tasks, policy_camera_rig, row_generators, write_summary
from .flows.paths import randn_rows
from .runtime import CONTEXT, OnnxPolicy

# Options of a checkpoint evaluation an exported graph cannot honour (its sampler and K are fixed in the file).
_REFUSED = {"video": "filming is not wired to --onnx",
            "wandb": "--onnx results go to the JSON summary only", "compile": "the file is already compiled by onnxruntime"}


def make_onnx_policy_fn(runner: OnnxPolicy, num_tasks: int, seed: int):
    """states [B, S] (numpy) → chunks [B, H, D] (numpy) through `runner`, with `make_policy_fn`'s noise:
    row b from the generator seeded by (seed, episode_seeds[b], plan_indices[b]). A file exported for a
    fixed batch size is called on slices of that size (the last one padded with copies of its first row)."""
    h, d = runner.chunk_shape
    shared = torch.Generator().manual_seed(seed)

    def policy_fn(states: np.ndarray, task_index: np.ndarray, episode_seeds=None, plan_indices=None,
                  images=None, prev_chunks=None, delay: int = 0) -> np.ndarray:
        b = len(states)
        gens = shared if episode_seeds is None else row_generators(seed, episode_seeds, plan_indices, "cpu")
        noise = randn_rows(b, (h, d), gens).numpy()                                        # [B, H, D]
        feeds = {"state": np.asarray(states, dtype=np.float32), "noise": noise}
        if CONTEXT in runner.input_names:
            length = runner.metadata["inputs"][CONTEXT][1]
            onehot = np.eye(num_tasks, dtype=np.float32)[np.asarray(task_index)]          # [B, num_tasks]
            feeds["context"] = np.repeat(onehot[:, None, :], length, axis=1)              # [B, L, num_tasks]
        if images is not None:
            feeds["images"] = np.ascontiguousarray(images)
        if prev_chunks is not None:                          # trained RTC: the graph's committed actions
            feeds["committed"] = np.asarray(prev_chunks, dtype=np.float32)                # [B, L, D]
        size = runner.batch_size or b
        out = []
        for start in range(0, b, size):
            part = {k: v[start:start + size] for k, v in feeds.items()}
            n = len(part["state"])
            if n < size:
                part = {k: np.concatenate([v, np.repeat(v[:1], size - n, axis=0)]) for k, v in part.items()}
            out.append(runner.predict_action_chunk(**part, delay=delay if prev_chunks is not None else 0)[:n])
        return np.concatenate(out)

    return policy_fn


def run_eval_onnx(cfg: EvalConfig) -> dict:
    from .envs import MAX_EPISODE_STEPS, canonical_task, evaluate

    for name, why in _REFUSED.items():
        if getattr(cfg, name):
            raise ValueError(f"--{name}: not available with --onnx ({why})")
    if cfg.episodes < 1 or cfg.steps < 0:
        raise ValueError(f"--episodes/--steps: expected episodes >= 1 and steps >= 0, got {cfg.episodes}, {cfg.steps}")
    if not 1 <= cfg.max_steps <= MAX_EPISODE_STEPS:
        raise ValueError(f"--max-steps: expected 1..{MAX_EPISODE_STEPS} (Meta-World's episode cap), got {cfg.max_steps}")
    runner = OnnxPolicy(cfg.onnx, threads=1)
    meta = runner.metadata
    if cfg.rtc and not runner.rtc_max_delay:
        raise ValueError(f"--rtc: {cfg.onnx} has no real-time chunking inputs; export a checkpoint trained with "
                         f"--rtc-max-delay with --rtc")
    if cfg.rtc and (cfg.rtc_mode == "guided" or cfg.delay > runner.rtc_max_delay):
        raise ValueError(f"--rtc: {cfg.onnx} runs trained real-time chunking for delays up to "
                         f"{runner.rtc_max_delay}; got --delay {cfg.delay}{' with --rtc-mode guided' if cfg.rtc_mode == 'guided' else ''}")
    if cfg.rtc_mode is not None and not cfg.rtc:
        raise ValueError(f"--rtc-mode: chooses how --rtc conditions each new chunk; got --rtc-mode {cfg.rtc_mode} "
                         f"without --rtc")
    for name, value in (("sampler", cfg.sampler), ("steps", cfg.steps or None)):
        if value is not None and value != meta[name]:
            raise ValueError(f"--{name}: {cfg.onnx} was exported with {name}={meta[name]!r}, got {value!r}; "
                             f"export again with --{name} {value}")
    config = DecoderConfig.from_dict(meta["config"])
    h = config.action_chunk_size
    n_exec = cfg.n_action_steps or config.n_action_steps
    if not 1 <= n_exec <= h or not 0 <= cfg.delay <= n_exec or n_exec + cfg.delay > h:
        raise ValueError(f"--n-action-steps/--delay: expected 1 <= n_action_steps <= {h} and 0 <= delay <= "
                         f"min(n_action_steps, {h} - n_action_steps), got {cfg.n_action_steps} and {cfg.delay}")
    trained = list(config.extra.get("tasks") or [])
    tasks = eval_tasks(cfg.task, trained, cfg.onnx)
    if config.uses_cameras:
        from .envs.render import check_rendering

        check_rendering()
    fn = make_onnx_policy_fn(runner, len(trained), cfg.seed)
    results = []
    for task in tasks:
        index = trained.index(canonical_task(task)) if len(trained) > 1 else 0
        rig = policy_camera_rig(SimpleNamespace(config=config))
        try:
            res = evaluate(fn, task, episodes=cfg.episodes, seed=cfg.seed, n_action_steps=n_exec,
                           max_steps=cfg.max_steps, num_envs=cfg.num_envs, task_index=index, record=cfg.plot,
                           delay=cfg.delay, rtc=cfg.rtc, camera_rig=rig)
        finally:
            if rig is not None:
                rig.close()
        results.append(res)
        print(f"[{task}] success_rate={res['success_rate']:.3f}", flush=True)
    summary = {
        "onnx": str(cfg.onnx), "decoder_type": meta["decoder_type"], "sampler": meta["sampler"],
        "steps": meta["steps"], "episodes_per_task": cfg.episodes, "seed": cfg.seed, "n_action_steps": n_exec,
        "max_steps": cfg.max_steps, "delay": cfg.delay, "rtc": cfg.rtc, "rtc_mode": "trained" if cfg.rtc else None,
        "success_rate": float(np.mean([r["success_rate"] for r in results])),
        "per_task": {r["task"]: r["success_rate"] for r in results},
        "results": [{k: v for k, v in r.items() if k != "trajectories"} for r in results],
    }
    cap = f"_t{cfg.max_steps}" if cfg.max_steps < MAX_EPISODE_STEPS else ""
    name = (f"eval_onnx_{meta['sampler']}_k{meta['steps']}_n{n_exec}{f'_d{cfg.delay}' if cfg.delay else ''}"
            f"{'_rtc' if cfg.rtc else ''}"
            f"_seed{cfg.seed}_e{cfg.episodes}{cap}.json")
    out = Path(cfg.output) if cfg.output else Path(cfg.onnx).parent / name
    if cfg.output and out.is_dir():
        out = out / name
    write_summary(summary, results if cfg.plot else None, out)
    print(f"success_rate={summary['success_rate']:.4f}", flush=True)
    return summary
