"""Where does an SDE sampler's exploration come from? Variance of the executed actions of a
policy's chunks, in normalised action units, for several σ(t) schedules, split by which
denoising steps' noise varies (the others' noise is held fixed):

    python -m benchmarks.sde_exploration --checkpoint runs/bc/final

PPO on chains credits chosen denoising steps; steps whose noise does not move the executed
actions carry no signal (docs/guides/rl_finetuning.md, "Trained steps").
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from action_decoder import ActionDecoderPolicy, ExploringSigma
from action_decoder.flows.samplers import _step_coefficients
from action_decoder.flows.sigma import FixedSigma

SCHEDULES = {"explore 1.0": ExploringSigma(1.0), "explore 2.0": ExploringSigma(2.0),
             "fixed 0.5": FixedSigma(0.5), "fixed 1.0": FixedSigma(1.0)}


def executed_variance(velocity, sigma, shape: tuple, steps: int, varied: set, n_exec: int, samples: int) -> float:
    """Mean variance over `samples` chains of the first `n_exec` rows of the final chunk [B, H, D]
    when only the noise of the steps in `varied` is redrawn (same start noise for every chain)."""
    grid = torch.linspace(0, 1, steps + 1)
    a, b, std = _step_coefficients(sigma, grid, 1e-2)
    fixed = torch.randn(steps + 1, 1, *shape[1:], generator=torch.Generator().manual_seed(0))
    outs = []
    for s in range(samples):
        gen = torch.Generator().manual_seed(s + 1)
        x = fixed[0].expand(shape)
        for k in range(steps):
            eps = torch.randn(shape, generator=gen) if k in varied else fixed[k + 1].expand(shape)
            x = x * a[k] + velocity(x, grid[k].expand(shape[0])) * b[k] + std[k] * eps
        outs.append(x[:, :n_exec])
    return float(torch.stack(outs).var(0).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True, help="a flow_matching or mean_flow save_pretrained directory")
    ap.add_argument("--layouts", type=int, default=8, help="start states (evaluation layouts of its task)")
    ap.add_argument("--samples", type=int, default=48, help="chains per layout and setting")
    ap.add_argument("--steps", type=int, default=10)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    from action_decoder.envs import eval_seeds, make_env

    policy = ActionDecoderPolicy.from_pretrained(args.checkpoint)
    cfg = policy.config
    env = make_env(policy.config.extra["tasks"][0], seed=0)
    states = torch.tensor(np.stack([env.reset(seed=s)[0] for s in eval_seeds(0, args.layouts)]), dtype=torch.float32)
    velocity = policy.bind({"state": states}).flow_velocity
    shape = (args.layouts, cfg.action_chunk_size, cfg.action_dim)
    K, half = args.steps, args.steps // 2
    splits = {"all steps": set(range(K)), f"first {half}": set(range(half)), f"last {K - half}": set(range(half, K)),
              "last 1": {K - 1}}
    print("| σ(t) | " + " | ".join(splits) + " |\n|---|" + "---:|" * len(splits))
    with torch.no_grad():
        for name, sigma in SCHEDULES.items():
            row = [executed_variance(velocity, sigma, shape, K, v, cfg.n_action_steps, args.samples)
                   for v in splits.values()]
            print(f"| {name} | " + " | ".join(f"{x:.4f}" for x in row) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
