"""Observation history (`n_obs_steps`): the stacking helper, the dataset reader's and the env harness's
episode-start padding, the network with n steps (n = 1 unchanged), the saved config, the CLI on
Meta-World and on a LeRobot dataset with cameras, and the refusals."""

import contextlib
import io
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.data import ChunkDataset, EpisodeDataset
from action_decoder.history import PAD_KEY, ObservationHistory

ROOT = Path(__file__).resolve().parents[1]
FORMAT7 = ROOT / "tests" / "data" / "format7_policy"
CAMS = ROOT / "tests" / "data" / "lerobot" / "v30_cams"
CAM = "observation.images.a"


def tiny(n=2, cameras=(CAM,), **over):
    return DecoderConfig(state_dim=6, action_dim=2, hidden_size=32, num_hidden_layers=1, action_chunk_size=4,
                         n_action_steps=2, n_obs_steps=n, cameras=cameras, image_size=16, **over)


def batch_of(cfg, b=3, gen=None):
    n, lead = cfg.n_obs_steps, [b] if cfg.n_obs_steps == 1 else [b, cfg.n_obs_steps]
    gen = gen or torch.Generator().manual_seed(0)
    out = {"state": torch.randn(*lead, cfg.state_dim, generator=gen),
           "actions": torch.randn(b, cfg.action_chunk_size, cfg.action_dim, generator=gen)}
    if cfg.cameras:
        out["images"] = torch.randint(0, 256, (*lead, len(cfg.cameras), 3, 16, 16), generator=gen, dtype=torch.uint8)
    return out


# ---------------------------------------------------------------------- the stacking helper
@pytest.mark.parametrize("kind", ["torch", "numpy"])
def test_history_repeats_the_first_observation_and_marks_it(kind):
    as_ = torch.tensor if kind == "torch" else np.array
    h = ObservationHistory(3)
    first = h.push({"s": as_([[0.0], [1.0]])})
    assert np.asarray(first["s"])[..., 0].tolist() == [[0, 0, 0], [1, 1, 1]]
    assert np.asarray(first[PAD_KEY]).tolist() == [[True, True, False]] * 2
    h.push({"s": as_([[10.0], [11.0]])})
    h.reset([1])                                         # env 1 starts its next episode
    third = h.push({"s": as_([[20.0], [21.0]])})
    assert np.asarray(third["s"])[..., 0].tolist() == [[0, 10, 20], [21, 21, 21]]
    assert np.asarray(third[PAD_KEY]).tolist() == [[False, False, False], [True, True, False]]
    assert type(third["s"]) is type(first["s"])
    buffer = as_([[5.0], [6.0]])                         # a caller's buffer, overwritten after the push
    h.push({"s": buffer})
    buffer[0, 0] = -1
    assert np.asarray(h.push({"s": as_([[7.0], [8.0]])})["s"])[0, :, 0].tolist() == [20, 5, 7]
    assert np.asarray(h.push({"s": as_([[1.0]])})["s"]).shape == (1, 3, 1)   # another batch: afresh
    with pytest.raises(ValueError, match=r"^n_obs_steps: expected a positive integer number of observations, got 0$"):
        ObservationHistory(0)


# ---------------------------------------------------------------------- the dataset reader
def test_chunk_dataset_stacks_observations_with_episode_start_padding():
    states = np.stack([np.arange(7), -np.arange(7)], 1).astype(np.float32)           # frame f holds f
    frames = np.arange(7, dtype=np.uint8)[:, None, None, None] * np.ones((1, 4, 4, 3), np.uint8)
    ds = EpisodeDataset(states, np.zeros((7, 1)), np.zeros(7), [3, 4], ["t"], 10.0, images={CAM: frames})
    chunks = ChunkDataset(ds, 2, n_obs_steps=3)
    T, F = True, False
    want = {0: ([0, 0, 0], [T, T, F]), 1: ([0, 0, 1], [T, F, F]), 2: ([0, 1, 2], [F, F, F]),
            3: ([3, 3, 3], [T, T, F]), 4: ([3, 3, 4], [T, F, F]), 6: ([4, 5, 6], [F, F, F])}
    for i, (frames_, pads) in want.items():
        item = chunks[i]
        assert item["state"][:, 0].tolist() == frames_                                # [n, S], oldest first
        assert item["images"].shape == (3, 1, 3, 4, 4)                                 # [n, N_cam, 3, H, W]
        assert item["images"][:, 0, 0, 0, 0].tolist() == frames_
        assert item["observation_is_pad"].tolist() == pads
    one = ChunkDataset(ds, 2)[4]                         # n = 1: the frame's own observation, no step axis
    assert one["state"].tolist() == [4.0, -4.0] and "observation_is_pad" not in one and one["images"].shape == (1, 3, 4, 4)
    with pytest.raises(ValueError, match=r"^n_obs_steps: expected an integer >= 1"):
        ChunkDataset(ds, 2, n_obs_steps=0)


# ---------------------------------------------------------------------- the network
def test_n1_reads_a_format7_config_and_samples_as_before():
    """The config.json and outputs of `tests/data/format7_policy/make.py`, written before n_obs_steps:
    the same weights (built under one seed) give the same chunk and loss, to float32 rounding (the file was written
    on another CPU, whose kernels may round the last bit differently; a changed model moves them by far more)."""
    cfg = DecoderConfig.from_json(FORMAT7 / "config.json")
    assert json.loads((FORMAT7 / "config.json").read_text())["format_version"] == 7 and cfg.n_obs_steps == 1
    ref = load_file(str(FORMAT7 / "reference.safetensors"))
    stats = {"state": {"mean": torch.zeros(6), "std": torch.full((6,), 2.0), "min": torch.full((6,), -5.0),
                       "max": torch.full((6,), 5.0)},
             "actions": {"mean": torch.full((2,), 0.1), "std": torch.ones(2), "min": torch.full((2,), -3.0),
                         "max": torch.full((2,), 3.0)}}
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(cfg, stats)
    assert not any("step_embed" in k for k in policy.state_dict())
    batch = {"state": ref["state"], "images": ref["images"]}
    with torch.no_grad():
        chunk = policy.eval().sample(batch, noise=ref["noise"]).actions
        loss = policy.train().compute_loss({**batch, "actions": ref["actions"]}, torch.Generator().manual_seed(1)).loss
    torch.testing.assert_close(chunk, ref["chunk"], rtol=0, atol=1e-5)
    torch.testing.assert_close(loss.reshape(1), ref["loss"], rtol=0, atol=1e-5)


def test_n2_reads_every_step_and_saves_its_config(tmp_path):
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(tiny(2)).eval()
    assert policy.model.obs_step_embed.shape == (2, 32) and policy.model.image_step_embed.shape == (2, 32)
    batch = batch_of(policy.config)
    noise = torch.randn(3, 4, 2)
    base = policy.sample(batch, noise=noise).actions
    for key in ("state", "images"):                      # the older step conditions the chunk too
        older = dict(batch)
        older[key] = batch[key].clone()
        older[key][:, 0] = torch.randn_like(batch["state"][:, 0]) if key == "state" else 255 - batch[key][:, 0]
        assert not torch.allclose(policy.sample(older, noise=noise).actions, base)
    policy.save_pretrained(tmp_path / "p")
    assert json.loads((tmp_path / "p" / "config.json").read_text())["n_obs_steps"] == 2
    assert "normalisation, the last 2 observations |" in (tmp_path / "p" / "README.md").read_text()
    loaded = ActionDecoderPolicy.from_pretrained(tmp_path / "p")
    assert loaded.config.n_obs_steps == 2 and torch.equal(loaded.sample(batch, noise=noise).actions, base)


def test_a_camera_policy_with_two_steps_trains_a_step():
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(tiny(2, image_shift=2)).train()
    opt = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    before = policy.model.image_step_embed.detach().clone()
    loss = policy.compute_loss(batch_of(policy.config), torch.Generator().manual_seed(0)).loss
    loss.backward()
    assert policy.model.obs_step_embed.grad.abs().sum() > 0 and policy.model.image_step_embed.grad.abs().sum() > 0
    opt.step()
    assert torch.isfinite(loss) and not torch.equal(before, policy.model.image_step_embed)


def test_batches_of_the_wrong_history_are_refused_in_one_line():
    policy = ActionDecoderPolicy(tiny(2)).eval()
    good = batch_of(policy.config)
    with pytest.raises(ValueError, match=r"^batch\['state'\]: expected shape \[B, 2, 6\] \(n_obs_steps=2 observations, "
                                         r"oldest first\), got \[3, 6\]; stack the last observations with "
                                         r"history.ObservationHistory$"):
        policy.sample({**good, "state": good["state"][:, -1]})
    with pytest.raises(ValueError, match=r"^batch\['images'\]: expected a tensor \[3, 2, 1, 3, 16, 16\] \(batch, "
                                         r"observation steps, cameras"):
        policy.sample({**good, "images": good["images"][:, -1]})
    with pytest.raises(ValueError, match=r"^n_obs_steps: expected a positive integer, got 0$"):
        tiny(0)
    with pytest.raises(ValueError, match=r"^noise_actor_hidden: the noise actor reads one state; expected 0 with "
                                         r"n_obs_steps=2, got 16$"):
        tiny(2, noise_actor_hidden=16)
    from action_decoder.export import export_refusal

    assert export_refusal(policy, None).startswith("n_obs_steps: the exported and compiled samplers take one observation")


def test_select_action_keeps_the_last_observations_per_env_and_resets():
    torch.manual_seed(0)
    policy = ActionDecoderPolicy(tiny(3, cameras=())).eval()
    seen = []
    policy.sample = lambda batch, **kw: (seen.append(batch["state"].clone()),
                                         type("Out", (), {"actions": torch.zeros(2, 4, 2)})())[1]
    for step in range(3):                                # chunks at steps 0 and 2 (n_action_steps = 2)
        policy.select_action({"state": torch.full((2, 6), float(step))})
    assert [s[0, :, 0].tolist() for s in seen] == [[0, 0, 0], [0, 1, 2]]
    policy.reset()
    policy.select_action({"state": torch.full((2, 6), 9.0)})
    assert seen[-1][0, :, 0].tolist() == [9, 9, 9]


# ---------------------------------------------------------------------- the env harness
def test_metaworld_harness_stacks_states_and_frames_with_episode_start_padding():
    pytest.importorskip("metaworld")
    from action_decoder.envs import evaluate

    calls = []

    def policy_fn(states, task_index, images=None):
        calls.append((states.copy(), images.copy()))
        return np.tile(np.array([0.5, 0.0, 0.0, 0.0]), (len(states), 8, 1))

    def rig(env):                                        # a frame that shows the env's step count
        return {"a": np.full((4, 4, 3), env.unwrapped.curr_path_length, dtype=np.uint8)}

    evaluate(policy_fn, "metaworld/reach", episodes=2, num_envs=2, n_action_steps=3, max_steps=7,
             n_obs_steps=2, camera_rig=rig)
    states, images = zip(*calls)
    assert all(s.shape == (2, 2, 39) and i.shape == (2, 2, 1, 3, 4, 4) for s, i in zip(states, images))
    assert np.array_equal(states[0][:, 0], states[0][:, 1])                  # the reset observation, twice
    assert [i[0, :, 0, 0, 0, 0].tolist() for i in images] == [[0, 0], [2, 3], [5, 6]]
    assert not np.array_equal(states[1][:, 0], states[1][:, 1])              # steps 2 and 3: the hand moved


# ---------------------------------------------------------------------- the CLI
def _cli(args, cache):
    from action_decoder import cli

    out, err = io.StringIO(), io.StringIO()
    old = os.environ.get("ACTION_DECODER_CACHE")
    os.environ["ACTION_DECODER_CACHE"] = str(cache)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli.main(list(args))
    finally:
        os.environ.pop("ACTION_DECODER_CACHE") if old is None else os.environ.__setitem__("ACTION_DECODER_CACHE", old)
    return code, out.getvalue(), err.getvalue()


SMALL = ["--batch-size", "8", "--hidden-size", "32", "--num-layers", "1", "--no-progress", "--n-obs-steps", "2"]


def test_cli_trains_and_evaluates_two_steps_on_metaworld(tmp_path):
    pytest.importorskip("metaworld")
    code, out, err = _cli(["train", "--task", "metaworld/reach", "--demos", "2", "--steps", "3", *SMALL,
                           "--output-dir", str(tmp_path / "run"), "--eval-episodes", "0"], tmp_path / "cache")
    assert code == 0, err
    final = tmp_path / "run" / "final"
    assert json.loads((final / "config.json").read_text())["n_obs_steps"] == 2
    code, out, err = _cli(["eval", "--checkpoint", str(final), "--episodes", "2", "--max-steps", "12",
                           "--num-envs", "2"], tmp_path / "cache")
    assert code == 0 and "success_rate=" in out, err
    # What takes one observation per call refuses the policy in one line.
    for args, words in ((["export", "--checkpoint", str(final), "--output", str(tmp_path / "p.onnx")],
                         "n_obs_steps: the exported and compiled samplers take one observation"),
                        (["finetune", "--checkpoint", str(final), "--output-dir", str(tmp_path / "ft")],
                         "--checkpoint: RL fine-tuning rolls out and re-scores chunks from one observation each")):
        code, out, err = _cli(args, tmp_path / "cache")
        assert code == 2 and err.count("\n") == 1 and words in err, err


def test_cli_trains_two_steps_on_a_lerobot_dataset_with_cameras(tmp_path):
    pytest.importorskip("av")
    code, out, err = _cli(["train", "--dataset", str(CAMS), "--steps", "2", *SMALL, "--image-size", "16",
                           "--output-dir", str(tmp_path / "run"), "--eval-episodes", "0"], tmp_path / "cache")
    assert code == 0, err
    policy = ActionDecoderPolicy.from_pretrained(tmp_path / "run" / "final")
    assert policy.config.n_obs_steps == 2 and len(policy.config.cameras) == 2
    assert policy.config.extra["train"]["n_obs_steps"] == 2


def test_cli_refuses_a_bad_history_in_one_line(tmp_path):
    code, out, err = _cli(["train", "--dataset", str(CAMS), "--n-obs-steps", "0", "--output-dir",
                           str(tmp_path / "run")], tmp_path / "cache")
    assert code == 2 and err.strip() == "action-decoder: error: --n-obs-steps: expected a positive integer, got 0", err


def test_the_guides_control_loop_runs_as_written():
    import re

    guide = (ROOT / "docs" / "guides" / "observation_history.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", guide, re.S)
    assert len(blocks) == 1
    scope: dict = {}
    exec(compile(blocks[0], "observation_history.md", "exec"), scope)
    assert scope["stacked"]["state"].shape == (3, 2, 6) and scope["chunk"].shape == (3, 8, 2)
    assert scope["stacked"]["observation_is_pad"].tolist() == [[False, False]] * 3    # step 7: two real steps each
