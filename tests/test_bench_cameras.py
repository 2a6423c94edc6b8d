"""benchmarks/cameras.py: the table built from result rows, the merge of rows, and the training
commands it runs (no training here)."""

import argparse
import json
from dataclasses import fields

import pytest

from benchmarks import cameras


def row(task, diff, decoder, condition, success, seed=0, latency=10.0, encoder=None, train_s=100.0):
    r = {"task": task, "difficulty": diff, "seed": seed, "decoder": decoder, "condition": condition,
         "success": success, "latency_ms": latency, "train_s": train_s}
    if encoder is not None:
        r["encoder_ms"] = encoder
    return r


FAKE = [row("drawer-open-v3", "easy", "flow_matching", "state", 1.0),
        row("drawer-open-v3", "easy", "flow_matching", "image", 0.9, encoder=2.0, latency=12.0, train_s=300.0),
        row("drawer-open-v3", "easy", "flow_matching", "state", 0.8, seed=1),
        row("drawer-open-v3", "easy", "flow_matching", "image", 0.5, seed=1, encoder=4.0, latency=14.0, train_s=500.0),
        row("basketball-v3", "medium", "mean_flow", "state", 0.6),
        row("basketball-v3", "medium", "mean_flow", "image", 0.1, encoder=3.0),
        row("door-open-v3", "easy", "mean_flow", "state", 0.9)]                  # image half not run yet


def test_table_means_seeds_and_states_the_gap_per_task_and_difficulty():
    table = cameras.build_table(FAKE)
    lines = table.splitlines()
    drawer = next(line for line in lines if line.startswith("| drawer-open-v3"))
    # state (100 + 80)/2 = 90, image (90 + 50)/2 = 70: gap −20; latency 13.00 ms with encoder 3.00; train 100 / 400 s
    assert drawer == "| drawer-open-v3 | easy | FM | 90.0 | 70.0 | -20.0 | 10.00 | 13.00 (3.00) | 100 | 400 | 2 |"
    assert "| door-open-v3 | easy | MF | 90.0 | — | — | 10.00 | — | 100 | — | 1 |" in lines
    assert lines.index(drawer) < lines.index(next(x for x in lines if x.startswith("| basketball-v3")))  # easy first
    assert "| easy | FM | 1 | -20.0 |" in lines and "| medium | MF | 1 | -50.0 |" in lines
    assert lines[-1] == ("Target: image-conditioned success on the easy tasks within 15 points of state-conditioned, "
                         "mean over tasks: FM misses it (-20.0).")
    close = [dict(r, success=0.95) if r["condition"] == "image" else r for r in FAKE[:2]]
    assert cameras.build_table(close).splitlines()[-1].endswith("FM meets it (-5.0).")


def test_merge_keeps_one_row_per_run_the_newest(tmp_path):
    path = tmp_path / "cameras.json"
    cameras.merge(path, FAKE[:2])
    out = cameras.merge(path, [dict(FAKE[1], success=0.2)])
    assert len(out) == 2 and json.loads(path.read_text()) == out
    assert next(r for r in out if r["condition"] == "image")["success"] == 0.2


def test_write_table_keeps_the_notes_below_the_marker(tmp_path):
    page = tmp_path / "cameras.md"
    page.write_text(f"old table\n{cameras.NOTES}\n## Notes\nkept text\n")
    cameras.write_table(page, FAKE, "# Cameras\n")
    text = page.read_text()
    assert text.startswith("# Cameras\n") and "old table" not in text and text.endswith("## Notes\nkept text\n")
    assert "| drawer-open-v3 |" in text


def test_difficulty_follows_the_task_groups():
    assert cameras.difficulty("metaworld/basketball") == "medium"
    assert cameras.difficulty("drawer-open-v3") == "easy"


def _args(**kw):
    base = dict(demos=10, steps=1500, batch_size=128, episodes=50, camera="corner2", image_size=64,
                image_encoder="conv", image_shift=2)
    return argparse.Namespace(**{**base, **kw})


def test_image_runs_differ_from_state_runs_only_in_what_the_policy_sees(tmp_path):
    state = cameras.train_command("metaworld/drawer-open", 0, "mean_flow", "state", _args(), tmp_path)
    image = cameras.train_command("metaworld/drawer-open", 0, "mean_flow", "image", _args(), tmp_path)
    assert state[state.index("--state-layout") + 1] == "metaworld"
    assert image[image.index("--state-layout") + 1] == "metaworld_proprio"
    assert image[image.index("--cameras") + 1] == "corner2" and image[image.index("--image-size") + 1] == "64"
    assert image[image.index("--image-shift") + 1] == "2" and "--image-shift" not in state
    common = [a for a in state if a not in ("--state-layout", "metaworld")]
    assert all(a in image for a in common)
    from action_decoder.train import TrainConfig

    known = {f"--{f.name.replace('_', '-')}" for f in fields(TrainConfig)} | {"--no-progress"}
    flags = {a for a in image if a.startswith("--")}
    # --cameras and --image-size are TrainConfig fields of the data side (camera datasets, Meta-World renders).
    pending = {"--cameras", "--image-size"} - known
    assert flags - pending <= known, flags - known


def test_the_command_refuses_unknown_conditions(capsys):
    with pytest.raises(SystemExit):
        cameras.main(["--conditions", "state,depth"])
    assert "--conditions: expected a comma-separated subset of ['state', 'image']" in capsys.readouterr().err


def test_a_finished_run_is_reused_whichever_way_the_task_is_spelled(tmp_path, monkeypatch):
    """`metaworld/drawer-open` and `metaworld/drawer-open-v3` name one run directory: a complete run
    is read back (its eval summary, training time and a latency of its checkpoint), never retrained."""
    from action_decoder import ActionDecoderPolicy, DecoderConfig

    final = tmp_path / "drawer-open_s0_flow_matching_state" / "final"
    ActionDecoderPolicy(DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, hidden_size=32,
                                      num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1,
                                      num_inference_timesteps=2)).save_pretrained(final)
    (final / "eval_ode_k2_n4_seed0.json").write_text(json.dumps({
        "success_rate": 0.7, "episodes_per_task": 50, "sampler": "ode", "steps": 2,
        "results": [{"task": "drawer-open-v3"}]}))
    (final.parent / "log.txt").write_text("saved final (123 s of training)\n")
    monkeypatch.setattr(cameras.subprocess, "run", lambda *a, **k: pytest.fail(f"retrained: {a}"))
    args = _args(runs=str(tmp_path), latency_reps=2)
    for task in ("metaworld/drawer-open", "metaworld/drawer-open-v3"):
        r = cameras.run_one(task, 0, "flow_matching", "state", args)
        assert (r["task"], r["success"], r["train_s"], r["steps"]) == ("drawer-open-v3", 0.7, 123.0, 2)
        assert r["latency_ms"] > 0 and "encoder_ms" not in r
    (final.parent / "log.txt").write_text("saved final (125 s of training, 98 s CPU)\n")   # the trainer's line now
    assert cameras.run_one("metaworld/drawer-open", 0, "flow_matching", "state", args)["train_s"] == 125.0
