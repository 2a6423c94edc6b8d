"""Checkpoints fit for the Hub: the model card with the measured success, the `PyTorchModelHubMixin`
layout, loading by repo id, and a training state without pickles that resumes bit for bit."""

import json
import os
import random
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import safetensors.torch
import torch
from huggingface_hub import ModelCard, PyTorchModelHubMixin

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.config import CONFIG_FORMAT_VERSION
from action_decoder.evaluate import EvalConfig, run_eval
from action_decoder.model_card import hub_dataset_id, read_results
from action_decoder.run_dir import load_state, save_state

SRC = Path(__file__).resolve().parents[1] / "src"


def tiny_policy(seed=0) -> ActionDecoderPolicy:
    torch.manual_seed(seed)
    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, action_chunk_size=8, hidden_size=32,
                        num_hidden_layers=1, n_action_steps=8, num_inference_timesteps=2, extra={"tasks": ["reach-v3"]})
    return ActionDecoderPolicy(cfg).eval()


def front_matter(card: Path) -> str:
    text = card.read_text()
    assert text.startswith("---\n"), text[:200]
    return text.split("---\n")[1]


def table_rows(card: Path) -> list[list[str]]:
    """The rows of the card's results table (sampler | K | actions | episodes | seed | success | per task)."""
    body = card.read_text().split("## Results")[1].split("##")[0]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in body.splitlines() if line.startswith("| ")]
    return rows[1:]                                                   # without the header


def cli(args, env, cwd):
    return subprocess.run([sys.executable, "-m", "action_decoder.cli", *args], env=env, cwd=cwd, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture
def env(tmp_path):
    return {**os.environ, "ACTION_DECODER_CACHE": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1",
            "PYTHONPATH": os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])}


def test_trained_checkpoint_has_a_card_with_the_printed_success(tmp_path, monkeypatch, capsys):
    from action_decoder import cli as main_cli       # in this process: no interpreter start-up per call

    out = tmp_path / "run"
    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))
    code = main_cli.main(["train", "--task", "metaworld/reach", "--demos", "2", "--batch-size", "16", "--hidden-size",
                          "32", "--num-layers", "1", "--no-progress", "--steps", "20", "--eval-episodes", "2",
                          "--output-dir", str(out)])
    res = capsys.readouterr()
    assert code == 0, res.err
    printed = float(re.findall(r"^success_rate=([0-9.]+)$", res.out, re.M)[-1])
    card = out / "final" / "README.md"
    meta = front_matter(card)
    assert "library_name: action-decoder" in meta and "pipeline_tag: robotics" in meta
    assert all(f"- {tag}\n" in meta for tag in ("robotics", "action-decoder", "flow-matching", "metaworld"))
    loaded = ModelCard.load(card)
    [result] = loaded.data.eval_results
    assert result.metric_type == "success_rate" and result.metric_value == pytest.approx(printed, abs=5e-5)
    [row] = table_rows(card)
    assert row[:5] == ["ode", "10", "4", "2", "0"] and float(row[5]) == pytest.approx(printed, abs=5e-5)
    frames = ActionDecoderPolicy.from_pretrained(out / "final").config.extra["data"]["frames"]
    assert frames > 0 and f"| frames | {frames:,} frames in 2 episodes |" in loaded.text
    assert "| data | 2 scripted-expert demonstrations per task" in loaded.text and "| task(s) | reach-v3 |" in loaded.text
    assert "| steps | 20 optimizer steps, batch 16" in loaded.text
    # Each checkpoint also has a card: same policy section, no results (it was never evaluated).
    ckpt_card = out / "checkpoints" / "step_0000020" / "README.md"
    assert "Not measured yet" in ckpt_card.read_text() and read_results(ckpt_card.parent) == []


def fake_evaluate(successes):
    def evaluate(fn, task, episodes, seed, n_action_steps, num_envs, task_index=0, progress=None, record=False, **options):
        wins = successes[:episodes]
        return {"task": "reach-v3", "success_rate": float(np.mean(wins)), "successes": wins,
                "lengths": [1] * episodes, "returns": [0.0] * episodes, "seeds": list(range(episodes)),
                "env_steps": episodes, "wall_time_s": 0.0}
    return evaluate


def test_eval_adds_a_row_per_setting_and_replaces_a_row_with_the_same_settings(tmp_path, monkeypatch):
    ckpt = tmp_path / "final"
    tiny_policy().save_pretrained(ckpt)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate([True, False, True, True]))
    run_eval(EvalConfig(checkpoint=str(ckpt), episodes=4))
    run_eval(EvalConfig(checkpoint=str(ckpt), episodes=2, sampler="sde", steps=5, seed=1))
    assert [r[:6] for r in table_rows(ckpt / "README.md")] == [["ode", "2", "8", "4", "0", "0.7500"],
                                                                ["sde", "5", "8", "2", "1", "0.5000"]]
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate([True, True, True, True]))
    run_eval(EvalConfig(checkpoint=str(ckpt), episodes=4))            # the first setting again: replaced
    run_eval(EvalConfig(checkpoint=str(ckpt), episodes=3))            # other episode count: a row of its own
    rows = table_rows(ckpt / "README.md")
    assert [r[:6] for r in rows] == [["sde", "5", "8", "2", "1", "0.5000"], ["ode", "2", "8", "4", "0", "1.0000"],
                                     ["ode", "2", "8", "3", "0", "1.0000"]]
    assert [r["success_rate"] for r in read_results(ckpt)] == [0.5, 1.0, 1.0]
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate([False, False, False, False]))
    run_eval(EvalConfig(checkpoint=str(ckpt), episodes=4, max_steps=50))    # a shorter cap: its own row
    rows = table_rows(ckpt / "README.md")
    assert [r[5] for r in rows if r[:5] == ["ode", "2", "8", "4", "0"]] == ["1.0000", "0.0000"]
    assert rows[-1][7] == "at most 50 steps per episode, delay 0"


def test_results_follow_these_weights_through_save_load_and_push(tmp_path, monkeypatch):
    ckpt = tmp_path / "final"
    tiny_policy().save_pretrained(ckpt)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate([True, False]))
    run_eval(EvalConfig(checkpoint=str(ckpt), episodes=2))
    policy = ActionDecoderPolicy.from_pretrained(ckpt)
    policy.save_pretrained(tmp_path / "copy")                       # the same weights: the results come along
    assert read_results(tmp_path / "copy") == read_results(ckpt) and len(read_results(ckpt)) == 1

    uploaded = {}

    class FakeApi:                                                  # what push_to_hub uploads, without a network
        def __init__(self, token=None):
            pass

        def create_repo(self, repo_id, private=None, exist_ok=False):
            return type("Repo", (), {"repo_id": repo_id})()

        def upload_folder(self, repo_id, folder_path, **kw):
            uploaded.update({p.name: p.read_bytes() for p in Path(folder_path).iterdir()})
            return f"https://huggingface.co/{repo_id}/commit/0"

    monkeypatch.setattr("huggingface_hub.hub_mixin.HfApi", FakeApi)
    assert policy.push_to_hub("me/reach") == "https://huggingface.co/me/reach/commit/0"
    assert sorted(uploaded) == ["README.md", "config.json", "model.safetensors"]
    pushed = safetensors.torch.load(uploaded["model.safetensors"])
    assert all(torch.equal(pushed[k], v) for k, v in policy.state_dict().items())
    assert b"value: 0.5" in uploaded["README.md"]

    with torch.no_grad():                                           # other weights (fine-tuned): results dropped
        policy.model.action_in.weight.add_(0.01)
    policy.save_pretrained(tmp_path / "tuned")
    assert read_results(tmp_path / "tuned") == [] and "Not measured yet" in (tmp_path / "tuned" / "README.md").read_text()
    policy.save_pretrained(ckpt)                                    # over the evaluated directory: its rows go too
    assert read_results(ckpt) == []


def test_the_layout_is_what_pytorch_model_hub_mixin_loads(tmp_path):
    policy = tiny_policy()
    assert isinstance(policy, PyTorchModelHubMixin)
    policy.save_pretrained(tmp_path / "c")
    assert json.loads((tmp_path / "c" / "config.json").read_text())["format_version"] == CONFIG_FORMAT_VERSION
    # huggingface_hub's own safetensors loader, strict: every tensor, named as the module names it.
    fresh = PyTorchModelHubMixin._load_as_safetensor(tiny_policy(seed=1), str(tmp_path / "c" / "model.safetensors"),
                                                     "cpu", True)
    assert all(torch.equal(fresh.state_dict()[k], v) for k, v in policy.state_dict().items())


def test_from_pretrained_resolves_a_repo_id_through_snapshot_download(tmp_path, monkeypatch):
    import huggingface_hub

    policy = tiny_policy()
    policy.save_pretrained(tmp_path / "snapshot")
    calls = []

    def snapshot_download(repo_id, **kw):
        calls.append((repo_id, kw))
        return str(tmp_path / "snapshot")

    monkeypatch.setattr(huggingface_hub, "snapshot_download", snapshot_download)
    monkeypatch.chdir(tmp_path)                                     # no local directory called me/reach
    loaded = ActionDecoderPolicy.from_pretrained("me/reach", revision="v1")
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in policy.state_dict().items())
    assert calls[0][0] == "me/reach" and calls[0][1]["revision"] == "v1"
    assert set(calls[0][1]["allow_patterns"]) == {"config.json", "model.safetensors", "README.md"}
    # A local directory of that name wins over the Hub.
    policy.save_pretrained(tmp_path / "me" / "reach")
    ActionDecoderPolicy.from_pretrained("me/reach")
    assert len(calls) == 1


def test_a_repo_id_while_offline_is_one_line(tmp_path, env):
    env = {**env, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf")}
    res = cli(["eval", "--checkpoint", "someone/no-such-policy", "--episodes", "1"], env, tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("action-decoder: error: checkpoint: 'someone/no-such-policy' "
                                                   "is not a local directory"), res.stderr


def test_hub_dataset_id_from_cache_paths():
    assert hub_dataset_id("/h/hub/datasets--lerobot--pusht/snapshots/abc123") == "lerobot/pusht"
    assert hub_dataset_id("/root/.cache/huggingface/lerobot/me/toy") == "me/toy"
    assert hub_dataset_id("data/push") is None and hub_dataset_id(None) is None


# ---------------------------------------------------------------------- training state without pickles
def test_training_state_round_trips_bit_for_bit_without_pickles(tmp_path):
    net = torch.nn.Linear(3, 2)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
    net(torch.randn(4, 3)).sum().backward()
    opt.step()
    np.random.seed(3)
    random.seed(4)
    state = {"step": 7, "optimizer": opt.state_dict(), "gen": torch.Generator().manual_seed(5).get_state(),
             "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
             "history": [{"step": 7, "loss": 0.1 + 0.2, "lr": float("nan")}], "ema": None}
    save_state(state, tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["training_state.json", "training_state.safetensors"]
    json.loads((tmp_path / "training_state.json").read_text())      # plain JSON, no pickle opcodes
    back = load_state(tmp_path)
    assert back["step"] == 7 and back["ema"] is None and back["history"][0]["loss"] == 0.1 + 0.2
    assert list(back["optimizer"]["state"]) == [0, 1]               # integer keys stay integers
    assert back["optimizer"]["param_groups"][0]["betas"] == (0.9, 0.999)
    for k, v in opt.state_dict()["state"][0].items():
        assert torch.equal(back["optimizer"]["state"][0][k], v)
    assert torch.equal(back["gen"], state["gen"])
    expected = (np.random.rand(), random.random())                  # the draws that follow the saved state
    np.random.set_state(back["rng"]["numpy"])
    random.setstate(back["rng"]["python"])
    assert (np.random.rand(), random.random()) == expected
    restored = torch.optim.AdamW(net.parameters(), lr=1e-3)
    restored.load_state_dict(back["optimizer"])


def _tiny_dataset(root):
    from action_decoder.data import write_episodes

    rng = np.random.default_rng(0)
    episodes = [{"observation.state": rng.normal(size=(30, 6)), "action": rng.uniform(-1, 1, (30, 2)),
                 "task_index": 0, "next.reward": np.zeros(30), "next.success": np.zeros(30, bool)} for _ in range(2)]
    write_episodes(root, episodes, ["mine"], 10, overwrite=True)
    return str(root)


def _train(ds, out, *more):
    from action_decoder import cli

    return cli.main(["train", "--dataset", ds, "--output-dir", str(out), "--batch-size", "8", "--hidden-size", "32",
                     "--num-layers", "1", "--log-every", "1", "--eval-episodes", "0", "--no-progress", *more])


def test_resume_from_the_new_format_is_bit_exact_and_a_pickled_state_is_one_line(tmp_path, capsys, monkeypatch):
    import action_decoder.train as T

    ds = _tiny_dataset(tmp_path / "ds")
    assert _train(ds, tmp_path / "a", "--steps", "6") == 0
    real_save = T.save_checkpoint

    def save_then_stop(out, step, *args):                          # the run is interrupted after step 3's checkpoint
        real_save(out, step, *args)
        if step == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(T, "save_checkpoint", save_then_stop)
    assert _train(ds, tmp_path / "b", "--steps", "6", "--checkpoint-every", "3") == 130
    monkeypatch.setattr(T, "save_checkpoint", real_save)
    assert _train(ds, tmp_path / "b", "--steps", "6", "--checkpoint-every", "3", "--resume") == 0
    a = ActionDecoderPolicy.from_pretrained(tmp_path / "a" / "final").state_dict()
    b = ActionDecoderPolicy.from_pretrained(tmp_path / "b" / "final").state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not any(p.suffix == ".pt" for p in (tmp_path / "b").rglob("*"))
    # A checkpoint whose training state is an older pickle is never unpickled: resume falls back to an
    # intact one and says why, or, with none left, stops with one line.
    def make_legacy(step):
        for name in ("training_state.json", "training_state.safetensors"):
            (step / name).unlink()
        torch.save({"step": int(step.name[5:])}, step / "training_state.pt")

    make_legacy(tmp_path / "b" / "checkpoints" / "step_0000006")
    capsys.readouterr()
    assert _train(ds, tmp_path / "b", "--steps", "6", "--resume") == 0
    assert ("names step_0000006, which does not load (training_state.pt is a pickled training state"
            in capsys.readouterr().out)
    assert _train(ds, tmp_path / "c", "--steps", "3") == 0
    make_legacy(tmp_path / "c" / "checkpoints" / "step_0000003")
    assert _train(ds, tmp_path / "c", "--steps", "3") == 2           # still a run: never overwritten
    capsys.readouterr()
    assert _train(ds, tmp_path / "c", "--steps", "6", "--resume") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no intact checkpoint" in err[0] and "pickled training state" in err[0], err


def test_no_pickled_training_state_is_loaded_anywhere_in_the_library():
    hits = [str(p) for p in (SRC / "action_decoder").rglob("*.py") if "weights_only=False" in p.read_text()]
    assert hits == []


def test_a_camera_policys_card_names_its_cameras(tmp_path):
    from action_decoder import ActionDecoderPolicy, DecoderConfig

    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=4, action_dim=2, action_chunk_size=4, hidden_size=32,
                        num_hidden_layers=1, cameras=["observation.images.corner2"], image_size=32)
    ActionDecoderPolicy(cfg).save_pretrained(tmp_path / "c")
    card = (tmp_path / "c" / "README.md").read_text()
    line = next(l for l in card.splitlines() if l.startswith("| conditioning |"))
    assert "cameras observation.images.corner2 (32 px, conv encoder, 4 tokens each)" in line
    plain = DecoderConfig(decoder_type="flow_matching", state_dim=4, action_dim=2, action_chunk_size=4,
                          hidden_size=32, num_hidden_layers=1)
    ActionDecoderPolicy(plain).save_pretrained(tmp_path / "p")
    assert "| conditioning | state only |" in (tmp_path / "p" / "README.md").read_text()


def test_saving_final_again_keeps_the_results_and_eval_files_of_the_same_weights(tmp_path, monkeypatch):
    from action_decoder.run_dir import save_final

    policy = tiny_policy()
    final = save_final(tmp_path, policy, 100)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate([True, False, True, True]))
    run_eval(EvalConfig(checkpoint=str(final), episodes=4))
    evals = sorted(p.name for p in final.glob("eval_*"))
    assert evals and len(read_results(final)) == 1
    save_final(tmp_path, policy, 100)                           # `train --resume` of a finished run
    assert sorted(p.name for p in final.glob("eval_*")) == evals and len(read_results(final)) == 1
    with torch.no_grad():
        next(policy.parameters()).add_(1.0)                     # other weights: their results do not apply
    save_final(tmp_path, policy, 200)
    assert read_results(final) == [] and not list(final.glob("eval_*"))


def test_every_file_of_a_checkpoint_gets_the_umasks_mode(tmp_path):
    old = os.umask(0o022)
    try:
        tiny_policy().save_pretrained(tmp_path / "c")
    finally:
        os.umask(old)
    modes = {p.name: oct(p.stat().st_mode & 0o777) for p in (tmp_path / "c").iterdir()}
    assert set(modes) == {"config.json", "model.safetensors", "README.md"}
    assert set(modes.values()) == {"0o644"}, modes


@pytest.mark.parametrize("hub", [{"HF_HUB_OFFLINE": "1"}, {"HF_ENDPOINT": "http://127.0.0.1:9"}],
                         ids=["offline", "unreachable"])
def test_push_to_hub_without_a_hub_is_one_line(tmp_path, env, hub):
    """No network: offline mode, or an endpoint where nothing listens (port 9, refused at once)."""
    script = ("from action_decoder import ActionDecoderPolicy, DecoderConfig\n"
              "policy = ActionDecoderPolicy(DecoderConfig(hidden_size=32, num_hidden_layers=1))\n"
              "policy.push_to_hub('someone/policy', token='hf_not_a_token')\n")
    res = subprocess.run([sys.executable, "-c", script], env={**env, "HF_HOME": str(tmp_path / "hf"), **hub},
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert res.returncode == 1
    assert res.stderr.count('  File "') <= 2, res.stderr[-2000:]      # the caller's line and push_to_hub's raise
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("ValueError: push_to_hub: could not upload to the Hub repo 'someone/policy'"), last


def card_snippet(card: Path, checkpoint: Path) -> str:
    """The card's "Use" code block, naming `checkpoint`."""
    placeholder = "<this repo id or directory>"
    code = card.read_text().split("## Use")[1].split("```python\n")[1].split("```")[0]
    assert placeholder in code
    return code.replace(placeholder, str(checkpoint))


@pytest.mark.parametrize("kind", ["one task", "three tasks", "camera"])
def test_the_cards_use_snippet_runs_as_written(tmp_path, kind):
    torch.manual_seed(0)
    extra = {"tasks": ["reach-v3", "push-v3", "door-open-v3"] if kind == "three tasks" else ["reach-v3"]}
    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, action_chunk_size=8, hidden_size=32,
                        num_hidden_layers=1, n_action_steps=8, num_inference_timesteps=2, extra=extra,
                        context_dim=3 if kind == "three tasks" else None,
                        cameras=("observation.images.corner2",) if kind == "camera" else (), image_size=32)
    ActionDecoderPolicy(cfg).save_pretrained(tmp_path / "c")
    scope: dict = {}
    exec(card_snippet(tmp_path / "c" / "README.md", tmp_path / "c"), scope)
    assert list(scope["chunk"].shape) == [1, 8, 4]


def test_a_runs_last_pointer_is_followed_and_another_file_is_one_line(tmp_path, monkeypatch):
    root = tmp_path / "run" / "checkpoints"
    tiny_policy().save_pretrained(root / "step_0000020")
    (root / "last").write_text("step_0000020")
    loaded = ActionDecoderPolicy.from_pretrained(root / "last")
    assert all(torch.equal(loaded.state_dict()[k], v) for k, v in tiny_policy().state_dict().items())
    # eval follows it too: the summary and the card row go into the step directory.
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("action_decoder.envs.evaluate", fake_evaluate([True, False]))
    summary = run_eval(EvalConfig(checkpoint=str(root / "last"), episodes=2))
    assert summary["checkpoint"] == str(root / "step_0000020")
    assert [r["success_rate"] for r in read_results(root / "step_0000020")] == [0.5]
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ValueError, match=r"notes.txt is a file; expected a directory written by save_pretrained"):
        ActionDecoderPolicy.from_pretrained(tmp_path / "notes.txt")
