"""Writes this directory with action-decoder at config format 7 (before `n_obs_steps`): the config.json
of a tiny camera policy, and the chunk it samples and its training loss on fixed inputs when built
under torch.manual_seed(0) (`reference.safetensors`). tests/test_obs_history.py checks that today's
code, reading the config as n_obs_steps = 1, builds the same weights and gives the same numbers."""

from pathlib import Path

import torch
from safetensors.torch import save_file

from action_decoder import ActionDecoderPolicy, DecoderConfig

HERE = Path(__file__).resolve().parent


def inputs() -> dict:
    g = torch.Generator().manual_seed(7)
    return {"state": torch.randn(3, 6, generator=g), "actions": torch.randn(3, 4, 2, generator=g),
            "images": torch.randint(0, 256, (3, 1, 3, 16, 16), generator=g, dtype=torch.uint8),
            "noise": torch.randn(3, 4, 2, generator=g)}


if __name__ == "__main__":
    torch.manual_seed(0)
    cfg = DecoderConfig(state_dim=6, action_dim=2, hidden_size=32, num_hidden_layers=2, action_chunk_size=4,
                        n_action_steps=2, cameras=("observation.images.a",), image_size=16)
    stats = {"state": {"mean": torch.zeros(6), "std": torch.full((6,), 2.0), "min": torch.full((6,), -5.0),
                       "max": torch.full((6,), 5.0)},
             "actions": {"mean": torch.full((2,), 0.1), "std": torch.ones(2), "min": torch.full((2,), -3.0),
                         "max": torch.full((2,), 3.0)}}
    policy = ActionDecoderPolicy(cfg, stats)
    cfg.to_json(HERE / "config.json")
    x = inputs()
    batch = {k: x[k] for k in ("state", "images")}
    with torch.no_grad():
        chunk = policy.eval().sample(batch, noise=x["noise"]).actions
        loss = policy.train().compute_loss({**batch, "actions": x["actions"]}, torch.Generator().manual_seed(1)).loss
    save_file({"chunk": chunk, "loss": loss.reshape(1), **x}, str(HERE / "reference.safetensors"))
