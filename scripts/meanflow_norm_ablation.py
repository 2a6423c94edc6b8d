"""MeanFlow adaptive weight: error ‖Δ‖² (sum over the chunk, the paper's) vs mean(Δ²) over H×D.

With N = H·D and e = ‖Δ‖², the mean-norm loss mean(w·e/N), w = 1/(e/N + c)^p, equals exactly
N^(p−1) × the sum-norm loss with c·N (weights are detached, so gradients match too). Each
variant is therefore the library's `meanflow_loss` with c and a constant scale changed; the
library's own norm runs as is.

    # synthetic two-route task (state -> one of two routes, 50/50); prints one JSON line
    python scripts/meanflow_norm_ablation.py synthetic --norm sum --seed 0
    # a CLI command (e.g. Meta-World training) with the chosen norm
    python scripts/meanflow_norm_ablation.py cli --norm mean -- train --task metaworld/push ...
    # a CLI training with MeanFlow's du/dt chosen (`DecoderConfig.meanflow_dudt`; the CLI has no flag)
    python scripts/meanflow_norm_ablation.py cli --dudt jvp -- train --task metaworld/push --decoder mean_flow ...
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

import action_decoder.policy as policy_mod
from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.flows import losses

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))       # the repository root: `benchmarks`
from benchmarks.multimodal import optimizer_step, routes, synthetic_batch  # noqa: E402

def library_norm() -> str:
    """Which norm `meanflow_loss` computes: with p = 0, u ≡ 0 and zero actions its loss is the
    row error of the target −noise: ≈ H·D = 64 for the sum, ≈ 1 for the mean."""
    loss = losses.meanflow_loss(lambda x, t, r: 0 * x, torch.zeros(256, 16, 4), torch.Generator().manual_seed(0),
                                adaptive_p=0.0)
    return "sum" if loss.item() > 8 else "mean"


def use_norm(norm: str) -> None:
    """Make the policy's MeanFlow loss use `norm` ("sum" or "mean") for the adaptive weight."""
    if norm == library_norm():
        return
    lib = losses.meanflow_loss

    def variant(avg_velocity, actions, *args, adaptive_c=1e-3, adaptive_p=0.5, **kw):
        n = actions.shape[1] * actions.shape[2]                  # H·D
        c, scale = (adaptive_c * n, n ** (adaptive_p - 1)) if norm == "mean" else (adaptive_c / n, n ** (1 - adaptive_p))
        return scale * lib(avg_velocity, actions, *args, adaptive_c=c, adaptive_p=adaptive_p, **kw)

    policy_mod.meanflow_loss = variant


def use_dudt(dudt: str) -> None:
    """Make `action-decoder train` build its DecoderConfig with `meanflow_dudt=dudt`."""
    import action_decoder.train as train_mod
    build = train_mod.decoder_config

    def with_dudt(*args, **kw) -> DecoderConfig:
        cfg = build(*args, **kw)
        cfg.meanflow_dudt = dudt
        cfg.validate()
        return cfg
    train_mod.decoder_config = with_dudt


def synthetic(seed: int, steps: int, batch: int, eval_states: int = 256, samples: int = 8, dudt=None) -> dict:
    torch.manual_seed(seed)
    cfg = DecoderConfig(decoder_type="mean_flow", state_dim=4, action_dim=4, action_chunk_size=16,
                        hidden_size=64, num_hidden_layers=2, num_attention_heads=4, num_key_value_heads=2,
                        normalization_mode="identity", num_inference_timesteps=1,
                        **({"meanflow_dudt": dudt} if dudt else {}))
    policy = ActionDecoderPolicy(cfg)
    params = [p for p in policy.parameters() if p.requires_grad and p is not policy.sigma]
    opt = torch.optim.AdamW(params, lr=1e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.LambdaLR(   # train.py's warmup + cosine
        opt, lambda s: min(1.0, (s + 1) / 100) * 0.5 * (1 + math.cos(math.pi * min(s, steps) / steps)))
    data, noise = torch.Generator().manual_seed(seed * 1000), torch.Generator().manual_seed(seed * 1000 + 500)
    t0 = time.time()
    for _ in range(steps):
        state, actions = synthetic_batch(data, batch)                                    # [B, 4], [B, H, 4]
        loss = optimizer_step(policy, {"state": state, "actions": actions}, noise, opt, sched, params)
    policy.eval()
    state = torch.randn(eval_states, 4, generator=torch.Generator().manual_seed(12345)).repeat_interleave(samples, 0)
    with torch.no_grad():
        chunk = policy.sample({"state": state}, sampler="ode", steps=1,
                              generator=torch.Generator().manual_seed(777)).actions                  # [B, H, 4]
    rms = (chunk[:, None] - routes(state)).square().mean((2, 3)).sqrt()                   # [B, 2]
    dist, which = rms.min(1)
    return {"seed": seed, "steps": steps, "on_route": (dist < 0.1).float().mean().item(),
            "rms_to_nearest": dist.mean().item(), "route_a_share": (which == 0).float().mean().item(),
            "final_loss": loss.item(), "train_s": round(time.time() - t0, 1)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=["synthetic", "cli"])
    p.add_argument("--norm", choices=["sum", "mean"], default=None, help="default: the library's (mean)")
    p.add_argument("--dudt", choices=["jvp", "finite_difference"], default=None,
                   help="MeanFlow's du/dt in training (default: DecoderConfig's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, default=1500)
    p.add_argument("--batch", type=int, default=128)
    argv = sys.argv[1:] if argv is None else argv
    cut = argv.index("--") if "--" in argv else len(argv)          # after "--": the CLI's own arguments
    a, rest = p.parse_args(argv[:cut]), argv[cut + 1:]
    torch.set_num_threads(1)
    use_norm(a.norm or library_norm())
    if a.dudt:
        use_dudt(a.dudt)
    if a.what == "synthetic":
        res = synthetic(a.seed, a.steps, a.batch, dudt=a.dudt)
        print(json.dumps({"norm": a.norm or library_norm(), "dudt": a.dudt, **res}), flush=True)
        return 0
    from action_decoder.cli import main as cli_main
    return cli_main(rest)


if __name__ == "__main__":
    sys.exit(main())
