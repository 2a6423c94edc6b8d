"""Training you can watch: TensorBoard events and train_log.jsonl written as a run goes, kept once per
step across a kill and --resume; finetune's RL scalars; evaluation success in the run's events;
W&B only on request, and a one-line error without the wandb package."""

import json
import os
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from action_decoder import ActionDecoderPolicy, DecoderConfig
from action_decoder.cli import main
from action_decoder.tracking import RunLogger, checkpoint_run, log_evaluation, read_jsonl
from action_decoder.train import ema_decay_at


def scalars(run_dir) -> dict:
    """tag -> [(step, value)] as TensorBoard reads the run directory (orphaned events purged)."""
    acc = EventAccumulator(str(run_dir))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def _dataset(root: Path) -> str:
    from action_decoder.data import write_episodes

    rng = np.random.default_rng(0)
    episodes = [{"observation.state": rng.normal(size=(30, 6)), "action": rng.uniform(-1, 1, (30, 2)),
                 "task_index": 0, "next.reward": np.zeros(30), "next.success": np.zeros(30, bool)} for _ in range(2)]
    write_episodes(root, episodes, ["mine"], 10, overwrite=True)
    return str(root)


def _env(tmp_path) -> dict:
    return {**os.environ, "ACTION_DECODER_CACHE": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1"}


def test_train_events_and_jsonl_are_written_as_it_goes_and_a_resume_keeps_each_step_once(tmp_path, monkeypatch, capsys):
    ds, out = _dataset(tmp_path / "ds"), tmp_path / "run"
    args = [sys.executable, "-m", "action_decoder.cli", "train", "--dataset", ds, "--output-dir", str(out),
            "--batch-size", "8", "--hidden-size", "32", "--num-layers", "1", "--eval-episodes", "0", "--no-progress",
            "--log-every", "1", "--checkpoint-every", "50"]
    proc = subprocess.Popen([*args, "--steps", "100000"], env=_env(tmp_path), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while proc.poll() is None and time.time() < deadline and len(read_jsonl(out / "train_log.jsonl")) < 53:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    # Killed mid-run: the curve so far is on disk, one line and one event per log step.
    rows = read_jsonl(out / "train_log.jsonl")
    checkpoint = int((out / "checkpoints" / "last").read_text().removeprefix("step_"))
    assert [r["step"] for r in rows] == list(range(1, len(rows) + 1)) and len(rows) > checkpoint, (len(rows), checkpoint)
    loss = scalars(out)["train/loss"]
    assert [s for s, _ in loss[:len(rows)]] == [r["step"] for r in rows] and len(loss) - len(rows) in (0, 1)

    from action_decoder import cli                 # the resume in this process: no second interpreter start-up

    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))
    assert cli.main([*args[3:], "--steps", str(checkpoint + 3), "--resume"]) == 0, capsys.readouterr().err[-2000:]
    # Steps past the checkpoint were trained again: each is in the log once, and TensorBoard drops the orphans.
    final = read_jsonl(out / "train_log.jsonl")
    steps = list(range(1, checkpoint + 4))
    assert [r["step"] for r in final] == steps
    assert final[:checkpoint] == rows[:checkpoint]
    history = json.loads((out / "train_log.json").read_text())["history"]    # what was trained: no timings
    assert [{k: v for k, v in r.items() if k != "samples_per_s"} for r in final] == history
    events = scalars(out)
    for key in ("loss", "lr", "grad_norm", "samples_per_s", "ema_decay"):
        assert [s for s, _ in events[f"train/{key}"]] == steps, key
        assert np.allclose([v for _, v in events[f"train/{key}"]], [r[key] for r in final], rtol=1e-6), key
    assert all(r["grad_norm"] > 0 and r["samples_per_s"] > 0 for r in final)
    assert [r["ema_decay"] for r in final] == [ema_decay_at(0.999, s - 1) for s in steps]
    assert [s for s, _ in events["val/loss"]] == [checkpoint + 3]   # held-out validation at the last step


def test_logger_resume_drops_rows_and_events_past_the_start_step(tmp_path):
    with RunLogger(tmp_path, "train_log.jsonl") as log:
        for step in range(1, 11):
            log.log(step, {"loss": float(step)}, "train")
    with open(tmp_path / "train_log.jsonl", "a") as f:
        f.write('{"step": 11, "lo')                                   # a line cut short by a kill
    with RunLogger(tmp_path, "train_log.jsonl", start_step=6) as log:
        for step in (7, 8):
            log.log(step, {"loss": -float(step)}, "train")
    assert read_jsonl(tmp_path / "train_log.jsonl") == [{"step": s, "loss": float(s)} for s in range(1, 7)] + \
        [{"step": s, "loss": -float(s)} for s in (7, 8)]
    assert scalars(tmp_path)["train/loss"] == [(s, float(s)) for s in range(1, 7)] + [(7, -7.0), (8, -8.0)]
    # An evaluation adds to a finished run without cutting its curve.
    with RunLogger(tmp_path, start_step=None) as log:
        log.log(8, {"success_rate": 0.5}, "eval/x", record=False)
    assert len(scalars(tmp_path)["train/loss"]) == 8 and len(read_jsonl(tmp_path / "train_log.jsonl")) == 8


def _bc(task="reach-v3"):
    torch.manual_seed(0)
    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, action_chunk_size=4,
                        n_action_steps=4, hidden_size=16, num_hidden_layers=1, num_attention_heads=2,
                        num_key_value_heads=1, num_inference_timesteps=2, extra={"tasks": [task]})
    stats = {k: {"mean": torch.zeros(d), "std": torch.ones(d), "min": -torch.ones(d), "max": torch.ones(d)}
             for k, d in (("state", 39), ("actions", 4))}
    return ActionDecoderPolicy(cfg, stats)


def test_finetune_writes_its_rl_scalars_per_iteration(tmp_path):
    ckpt, out = tmp_path / "bc", tmp_path / "ft"
    _bc().save_pretrained(ckpt)
    assert main(["finetune", "--checkpoint", str(ckpt), "--output-dir", str(out), "--env-steps", "30",
                 "--num-envs", "2", "--max-episode-steps", "12", "--sde-steps", "3", "--trained-steps", "2",
                 "--eval-episodes", "1", "--minibatch-size", "4", "--group-size", "2",
                 "--checkpoint-every", "1"]) == 0
    log = json.loads((out / "finetune_log.json").read_text())
    history = log["history"]
    assert read_jsonl(out / "finetune_log.jsonl") == [{"step": h["env_steps"], **h} for h in history]
    events = scalars(out)
    for key in ("return", "success", "sigma_mult", "sigma_scale", "kl_bc", "approx_kl", "ratio_mean", "ratio_min",
                "ratio_max", "clipfrac"):
        assert events[f"rl/{key}"] == [(h["env_steps"], pytest.approx(h[key], rel=1e-6)) for h in history], key
    assert [s for s, _ in events["eval/success_sde"]] == [e["env_steps"] for e in log["evals"]]
    assert checkpoint_run(out / "checkpoints" / "step_0000001") == (out, history[0]["env_steps"])
    assert checkpoint_run(out / "final") == (out, history[-1]["env_steps"])


def test_eval_writes_success_into_the_run_of_its_checkpoint(tmp_path):
    run = tmp_path / "run"
    _bc().save_pretrained(run / "final")
    (run / "train_log.jsonl").write_text("".join(json.dumps({"step": s, "loss": 1.0}) + "\n" for s in (10, 20)))
    assert main(["eval", "--checkpoint", str(run / "final"), "--episodes", "1", "--num-envs", "1"]) == 0
    summary = json.loads((run / "final" / "eval_ode_k2_n4_seed0_e1.json").read_text())
    events = scalars(run)
    assert events["eval/ode_k2_n4_seed0_e1/success_rate"] == [(20, summary["success_rate"])]
    assert events["eval/ode_k2_n4_seed0_e1/success/reach-v3"] == [(20, summary["per_task"]["reach-v3"])]


def test_log_evaluation_places_scores_at_the_checkpoints_step(tmp_path):
    summary = {"sampler": "sde", "steps": 3, "n_action_steps": 4, "seed": 1, "success_rate": 0.75,
               "per_task": {"a-v3": 1.0, "b-v3": 0.5}, "results": []}
    run = tmp_path / "run"
    (run / "checkpoints" / "step_0000040").mkdir(parents=True)
    (run / "train_log.jsonl").write_text("".join(json.dumps({"step": s}) + "\n" for s in (20, 40, 60)))
    ckpt = run / "checkpoints" / "step_0000040"
    assert log_evaluation(summary, ckpt, ckpt / "eval_sde_k3_n4_seed1.json") == run
    events = scalars(run)
    assert events["eval/sde_k3_n4_seed1/success_rate"] == [(40, 0.75)]
    assert events["eval/sde_k3_n4_seed1/success/b-v3"] == [(40, 0.5)]
    # A checkpoint outside a run directory: the events go next to the summary, at step 0.
    loose = tmp_path / "downloaded"
    assert checkpoint_run(loose) == (None, 0)
    assert log_evaluation(summary, loose, tmp_path / "out" / "mine.json") == tmp_path / "out"
    assert scalars(tmp_path / "out")["eval/mine/success/a-v3"] == [(0, 1.0)]


class _FakeWandb(types.ModuleType):
    """Records what the library asks of wandb (the real one needs an account or a service process)."""

    def __init__(self):
        super().__init__("wandb")
        self.inits, self.logged, self.finished = [], [], 0

    def init(self, **kw):
        self.inits.append(kw)
        fake = self
        return types.SimpleNamespace(log=fake.logged.append, define_metric=lambda *a, **k: None,
                                     finish=lambda: setattr(fake, "finished", fake.finished + 1))


def test_wandb_gets_the_same_scalars_and_a_resume_continues_its_run(tmp_path, monkeypatch):
    fake = _FakeWandb()
    monkeypatch.setitem(sys.modules, "wandb", fake)
    for start in (0, 2, 0):                                   # a run, its resume, a new run in the same directory
        with RunLogger(tmp_path, "train_log.jsonl", start, wandb_project="proj", config={"lr": 0.1}) as log:
            log.log(start + 1, {"loss": 0.5, "lr": 0.1}, "train")
    first, second, third = fake.inits
    assert first["project"] == second["project"] == "proj" and first["config"] == {"lr": 0.1}
    assert first["id"] == second["id"] != third["id"] and second["resume"] == "allow" and first["dir"] == str(tmp_path)
    assert fake.logged == [{"train/step": 1, "train/loss": 0.5, "train/lr": 0.1},
                           {"train/step": 3, "train/loss": 0.5, "train/lr": 0.1},
                           {"train/step": 1, "train/loss": 0.5, "train/lr": 0.1}]
    assert fake.finished == 3
    with RunLogger(tmp_path, start_step=None, wandb_project="proj", job_type="eval") as log:
        log.log(1, {"success_rate": 1.0}, "eval/x", record=False)
    assert "id" not in fake.inits[-1] and fake.inits[-1]["job_type"] == "eval"


def test_wandb_without_the_package_is_one_line_before_any_work(tmp_path):
    script = tmp_path / "no_wandb.py"
    script.write_text("import json, sys\nsys.modules['wandb'] = None\nfrom action_decoder.cli import main\n"
                      "print([main(args) for args in json.loads(sys.argv[1])])\n")
    commands = [["train", "--output-dir", str(tmp_path / "t"), "--wandb"],
                ["finetune", "--checkpoint", str(tmp_path / "missing"), "--output-dir", str(tmp_path / "f"), "--wandb"],
                ["eval", "--checkpoint", str(tmp_path / "missing"), "--wandb", "--wandb-project", "p"]]
    res = subprocess.run([sys.executable, str(script), json.dumps(commands)], env=_env(tmp_path), capture_output=True,
                         text=True, timeout=120)
    assert res.stdout.strip() == "[2, 2, 2]", res.stdout + res.stderr
    assert res.stderr.strip().splitlines() == 3 * ['action-decoder: error: --wandb: needs the wandb package '
                                                   '(pip install "action-decoder[wandb]"), which is not installed']
    assert not (tmp_path / "t").exists() and not (tmp_path / "f").exists()


def test_a_missing_tensorboard_is_one_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "tensorboard", None)
    with pytest.raises(ValueError, match=r'^tensorboard: .*pip install "tensorboard>=2.18"'):
        RunLogger(tmp_path, "train_log.jsonl")


def test_final_is_logged_at_the_step_of_its_weights_not_the_runs_last_row(tmp_path):
    from action_decoder.run_dir import save_final
    from action_decoder.tracking import checkpoint_run

    run = tmp_path / "run"
    save_final(run, _bc(), 4)                                   # a finished 4-step run ...
    (run / "train_log.jsonl").write_text("".join(json.dumps({"step": s}) + "\n" for s in (4, 1300)))  # ... resumed, stopped
    assert checkpoint_run(run / "final") == (run, 4)
    lone = tmp_path / "copied" / "final"                        # a final/ outside any run: events beside the summary
    _bc().save_pretrained(lone)
    assert checkpoint_run(lone) == (None, 0)


def test_a_resume_in_the_same_second_writes_an_event_file_read_after_the_earlier_one(tmp_path):
    """TensorBoard reads event files in name order (second, host, pid): a resume's file must sort after the
    killed run's, or the killed run's events past the restart would survive its purge marker."""
    import time

    later = int(time.time()) + 1
    (tmp_path / f"events.out.tfevents.{later}.host.99999999.0").write_bytes(b"")   # a file of this second or later
    with RunLogger(tmp_path, start_step=3) as log:
        log.log(4, {"loss": 1.0}, "train")
    ours = [f.name for f in tmp_path.glob("events.out.tfevents.*") if ".99999999." not in f.name]
    assert len(ours) == 1 and int(ours[0].split(".")[3]) > later
    assert sorted(f.name for f in tmp_path.glob("events.out.tfevents.*"))[-1] == ours[0]
