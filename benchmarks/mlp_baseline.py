"""The reference the MP1 benchmark is judged against: a plain ~190k-parameter MLP velocity
trained with our `flow_matching_loss` and sampled with our `sample_ode` (chunk 16, execute 8),
on the same demonstrations, normalisation, state inputs (relative positions), shift
augmentation and evaluation layouts as the Action Expert runs. Only the network differs, so
the gap between the two columns is the network's. `--state-layout flat` is the plain MLP that
NOTES.md measured (≈ 80 % on 17 tasks).

    python -m benchmarks.mlp_baseline --task metaworld/pick-place --seed 0

`--output-dir` writes one `eval_ode_k{K}.json` per K in the schema of `action-decoder eval`,
so `benchmarks.metaworld_bc` tabulates it as a column beside the decoders.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch
from torch import Tensor, nn

from action_decoder.data import ChunkDataset, load_demos
from action_decoder.envs import evaluate
from action_decoder.flows import flow_matching_loss, sample_ode
from action_decoder.normalize import make_normalizers
from action_decoder.state_layout import feature_dim, relative_positions, shift_positions
from action_decoder.train import DEFAULT_SHIFT, TrainConfig

N_ACTION_STEPS = 8   # the reference as NOTES.md defines it: chunk 16, execute 8


class MLPVelocity(nn.Module):
    """v(x_t, t | state): the flattened chunk, the state and a sinusoidal time code through a
    4-layer SiLU MLP (hidden 256: 190k parameters for Meta-World's 39-d state and 16×4 chunk)."""

    def __init__(self, state_dim: int, horizon: int, action_dim: int, hidden: int = 256, time_dim: int = 32):
        super().__init__()
        self.shape, self.time_dim = (horizon, action_dim), time_dim
        self.net = nn.Sequential(
            nn.Linear(horizon * action_dim + state_dim + time_dim, hidden), nn.SiLU(),
            nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
            nn.Linear(hidden, horizon * action_dim))

    def forward(self, x: Tensor, t: Tensor, state: Tensor) -> Tensor:
        freqs = torch.exp(torch.linspace(0.0, math.log(1000.0), self.time_dim // 2, dtype=x.dtype))
        angle = t[:, None] * freqs[None]                                                 # [B, time_dim/2]
        h = torch.cat([x.flatten(1), state, angle.sin(), angle.cos()], dim=-1)
        return self.net(h).view(-1, *self.shape)                                          # [B, H, D]


def run(task: str, seed: int, demos: int = 10, steps: int = 5000, batch_size: int = 256, episodes: int = 50,
        ks: tuple[int, ...] = (10, 1), horizon: int = 16, n_action_steps: int = N_ACTION_STEPS, norm: str = "mean_std",
        layout: str = "metaworld", shift: float = DEFAULT_SHIFT, demo_noise: float = 0.0) -> dict:
    """Train on `demos` demonstrations of `task` (demo subset = `seed`, recorded with `demo_noise`),
    evaluate at each K. `layout` and `shift` are the policy's state layout and the training's shift
    augmentation."""
    torch.manual_seed(seed)
    ds = ChunkDataset(load_demos(task, demos, seed, demo_noise), horizon)
    norms = make_normalizers(ds.states.shape[1], ds.actions.shape[1], norm, ds.stats)
    frames = [ds[i] for i in range(len(ds))]
    states = torch.stack([f["state"] for f in frames])                                  # [N, S]
    actions = norms["actions"].normalize(torch.stack([f["actions"] for f in frames]))   # [N, H, D]

    def inputs(raw: Tensor) -> Tensor:        # what the Action Expert reads, see ActionDecoderPolicy
        x = norms["state"].normalize(raw)
        return torch.cat([x, relative_positions(raw)], -1) if layout == "metaworld" else x

    net = MLPVelocity(states.shape[1] + feature_dim(layout), horizon, actions.shape[2])
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    for _ in range(steps):
        idx = torch.randint(len(states), (batch_size,), generator=gen)
        raw = states[idx]
        if shift > 0:
            raw = shift_positions(raw, (2 * torch.rand(batch_size, 2, generator=gen) - 1) * shift)
        loss = flow_matching_loss(net, actions[idx], generator=gen, cond={"state": inputs(raw)})
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
    train_s = time.perf_counter() - t0
    net.eval()
    out = {"task": task, "seed": seed, "params": sum(p.numel() for p in net.parameters()), "train_s": train_s,
           "n_action_steps": n_action_steps,
           "recipe": {"demos": demos, "demo_noise": demo_noise, "state_layout": layout, "augment_shift": shift}}
    for k in ks:
        sample_gen = torch.Generator().manual_seed(seed)

        @torch.no_grad()
        def policy_fn(s, _task_index, k=k, sample_gen=sample_gen):
            st = inputs(torch.as_tensor(s, dtype=torch.float32))
            noise = torch.randn((len(st), horizon, actions.shape[2]), generator=sample_gen)
            x = sample_ode(lambda z, t: net(z, t, st), noise, k)
            return norms["actions"].unnormalize(x).numpy()

        res = evaluate(policy_fn, task, episodes=episodes, seed=seed, n_action_steps=n_action_steps)
        out[f"success_k{k}"], out[f"result_k{k}"] = res["success_rate"], res
    return out


def write_evals(res: dict, out_dir: Path, ks: tuple[int, ...]) -> None:
    """One `eval_ode_k{K}.json` per K, shaped like `action-decoder eval`'s summary."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for k in ks:
        r = res[f"result_k{k}"]
        (out_dir / f"eval_ode_k{k}.json").write_text(json.dumps({
            "checkpoint": None, "decoder_type": "mlp_baseline", "sampler": "ode", "steps": k,
            "episodes_per_task": len(r["successes"]), "seed": res["seed"], "success_rate": r["success_rate"],
            "per_task": {r["task"]: r["success_rate"]}, "results": [r], "params": res["params"], "recipe": res["recipe"],
            "n_action_steps": res["n_action_steps"],
            "train_s": res["train_s"]}, indent=1))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="metaworld/pick-place")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--demos", type=int, default=10)
    p.add_argument("--demo-noise", type=float, default=TrainConfig.demo_noise,
                   help="std of the noise on the expert's executed actions (default: as `action-decoder train`)")
    p.add_argument("--steps", type=int, default=5000)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--n-action-steps", type=int, default=N_ACTION_STEPS)
    p.add_argument("--norm", default="mean_std", choices=["mean_std", "min_max"])
    p.add_argument("--state-layout", default="metaworld", choices=["metaworld", "flat"],
                   help="flat: the plain MLP of NOTES.md (normalised state only, no shift augmentation)")
    p.add_argument("--augment-shift", type=float, default=None, help="metres (default: as `action-decoder train`)")
    p.add_argument("--output-dir", default=None, help="directory for eval_ode_k{K}.json files")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    res = run(args.task, args.seed, demos=args.demos, steps=args.steps, episodes=args.episodes, horizon=args.horizon,
              n_action_steps=args.n_action_steps, norm=args.norm, layout=args.state_layout,
              shift=(DEFAULT_SHIFT if args.state_layout == "metaworld" else 0.0) if args.augment_shift is None
              else args.augment_shift, demo_noise=args.demo_noise)
    print(json.dumps({k: v for k, v in res.items() if not k.startswith("result_")}))
    if args.output_dir:
        write_evals(res, Path(args.output_dir), (10, 1))


if __name__ == "__main__":
    main()
