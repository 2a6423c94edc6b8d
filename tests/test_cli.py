"""The CLI as a user runs it: train → save → load → eval, errors, kill and resume, torchrun."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from action_decoder import ActionDecoderPolicy

TINY = ["--task", "metaworld/reach", "--demos", "2", "--batch-size", "16", "--hidden-size", "32",
        "--num-layers", "1", "--no-progress", "--log-every", "5"]


def run(args, env, cwd=None):
    """The CLI as a user runs it (`cli.main`, its exit status and output), from the test's own directory
    (default outputs land there) with `env`'s cache. In this process: a new interpreter costs seconds of
    imports per call; the tests that need one (a kill, torchrun, no simulator, stderr not a terminal)
    start their own."""
    import contextlib
    import io

    from action_decoder import cli

    out, err = io.StringIO(), io.StringIO()
    saved_env, saved_cwd = {k: os.environ.get(k) for k in ("ACTION_DECODER_CACHE", "OMP_NUM_THREADS")}, os.getcwd()
    os.environ.update({k: env[k] for k in saved_env})
    os.chdir(cwd or Path(env["ACTION_DECODER_CACHE"]).parent)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli.main(list(args))
    finally:
        os.chdir(saved_cwd)
        for k, v in saved_env.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


@pytest.fixture
def env(tmp_path):
    return {**os.environ, "ACTION_DECODER_CACHE": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1"}


def test_train_save_load_eval_cycle(tmp_path, env, cli_main):
    out = tmp_path / "run"
    res = run(["train", *TINY, "--decoder", "flow_matching", "--steps", "20", "--output-dir", str(out),
               "--eval-episodes", "0"], env)
    assert res.returncode == 0, res.stderr
    assert (out / "final" / "config.json").is_file() and (out / "loss.png").is_file()
    # Wall and CPU time, both named (the README quotes the CPU time).
    assert re.search(r"^saved \S+final \(\d+ s of training, \d+ s CPU\)$", res.stdout, re.M), res.stdout[-500:]
    policy = ActionDecoderPolicy.from_pretrained(out / "final")
    averaged, raw = policy.state_dict(), ActionDecoderPolicy.from_pretrained(out / "checkpoints" / "step_0000020").state_dict()
    assert not torch.equal(averaged["model.action_in.weight"], raw["model.action_in.weight"]), \
        "final/ should hold the weight average, not the raw weights"
    assert policy.config.decoder_type == "flow_matching" and policy.config.extra["tasks"] == ["reach-v3"]
    assert policy.config.state_layout == "metaworld", "Meta-World tasks train with relative positions"
    res = cli_main(["eval", "--checkpoint", str(out / "final"), "--episodes", "2", "--num-envs", "2", "--plot",
                    "--sampler", "sde", "--steps", "3"])
    assert res.returncode == 0, res.stderr
    last = res.stdout.strip().splitlines()[-1]
    assert last.startswith("success_rate=") and 0.0 <= float(last.split("=")[1]) <= 1.0
    assert "episode 2/2" in res.stdout
    name = out / "final" / f"eval_sde_k3_n{policy.config.n_action_steps}_seed0_e2"     # named by its settings
    summary = json.loads(name.with_suffix(".json").read_text())
    assert summary["sampler"] == "sde" and summary["steps"] == 3 and len(summary["results"][0]["successes"]) == 2
    assert name.with_suffix(".png").is_file()


def test_train_on_demonstrations_recorded_with_noise(tmp_path, env):
    out = tmp_path / "run"
    res = run(["train", *TINY, "--decoder", "mean_flow", "--steps", "3", "--demo-noise", "0.2",
               "--output-dir", str(out), "--eval-episodes", "0"], env)
    assert res.returncode == 0, res.stderr
    assert [p.name for p in (tmp_path / "cache" / "metaworld").iterdir()] == ["reach-v3-n2-s0-dart0.2"]
    assert ActionDecoderPolicy.from_pretrained(out / "final").config.extra["train"]["demo_noise"] == 0.2


@pytest.mark.parametrize("args, message", [
    (["train", "--task", "metaworld/fly-to-moon"], "fly-to-moon"),
    (["eval", "--checkpoint", "/nonexistent/ckpt"], "config.json"),
    (["train", "--steps", "0"], "--steps"),
    (["train", "--dataset", "/nonexistent/ds", "--augment-shift", "0.1"], "--augment-shift"),
    (["train", "--demo-noise", "1.5"], "--demo-noise"),
    (["train", "--dataset", "/nonexistent/ds", "--demo-noise", "0.2"], "--demo-noise"),
    (["eval", "--checkpoint", "CKPT", "--sampler", "sde"], "sampler"),
    (["train", "--dataset", "/nonexistent/ds"], "--dataset: /nonexistent/ds does not exist; expected a LeRobot dataset"),
    (["train", "--dataset", "FILE"], "is a file; expected a LeRobot dataset directory"),
])
def test_bad_input_gives_one_clear_line(tmp_path, cli_main, args, message):
    if "CKPT" in args:   # a DDPM checkpoint cannot be sampled with the SDE
        from action_decoder import DecoderConfig
        ActionDecoderPolicy(DecoderConfig(decoder_type="DDPM", state_dim=39, extra={"tasks": ["reach-v3"]})) \
            .save_pretrained(tmp_path / "c")
        args = [str(tmp_path / "c") if a == "CKPT" else a for a in args]
    if "FILE" in args:
        (tmp_path / "data.parquet").write_bytes(b"PAR1")
        args = [str(tmp_path / "data.parquet") if a == "FILE" else a for a in args]
    if args[0] == "train":
        args = [*args, "--output-dir", str(tmp_path / "out")]
    res = cli_main(args)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("action-decoder: error:") and message in lines[0], res.stderr


def test_corrupted_checkpoint_and_nan_dataset(tmp_path, env):
    from action_decoder import DecoderConfig
    from action_decoder.data import write_episodes

    ActionDecoderPolicy(DecoderConfig(state_dim=39)).save_pretrained(tmp_path / "c")
    (tmp_path / "c" / "model.safetensors").write_bytes(b"\x00" * 10)
    res = run(["eval", "--checkpoint", str(tmp_path / "c")], env)
    assert res.returncode == 2 and "safetensors" in res.stderr and "Traceback" not in res.stderr
    states = np.zeros((20, 39), np.float32)
    states[3, 5] = np.nan
    episodes = [{"observation.state": states, "action": np.zeros((20, 4), np.float32), "task_index": 0,
                 "next.reward": np.zeros(20), "next.success": np.zeros(20, bool)}]
    write_episodes(tmp_path / "ds", episodes, ["mine"], 10)
    res = run(["train", "--dataset", str(tmp_path / "ds"), "--output-dir", str(tmp_path / "o")], env)
    assert res.returncode == 2 and "observation.state" in res.stderr and "Traceback" not in res.stderr


def test_kill_and_resume_continues_from_last_checkpoint(tmp_path, env):
    common = ["train", *TINY, "--decoder", "mean_flow", "--steps", "40", "--checkpoint-every", "10",
              "--log-every", "4", "--eval-episodes", "0", "--hidden-size", "64", "--num-layers", "2",
              "--batch-size", "64"]
    straight = run([*common, "--output-dir", str(tmp_path / "a")], env)
    assert straight.returncode == 0, straight.stderr
    out = tmp_path / "b"
    proc = subprocess.Popen([sys.executable, "-m", "action_decoder.cli", *common, "--output-dir", str(out)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 240
    while not (out / "checkpoints" / "last").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "final").exists(), "the run finished before it could be killed"
    killed_at = (out / "checkpoints" / "last").read_text()
    assert killed_at != "step_0000040"
    # Without --resume the directory is protected; with it the run continues and ends where the
    # uninterrupted run ended, bit for bit (same optimizer, data order and noise).
    assert run([*common, "--output-dir", str(out)], env).returncode == 2
    resumed = run([*common, "--output-dir", str(out), "--resume"], env)
    assert resumed.returncode == 0, resumed.stderr
    assert f"continuing from {out / 'checkpoints' / killed_at}" in resumed.stdout
    a = ActionDecoderPolicy.from_pretrained(tmp_path / "a" / "final").state_dict()
    b = ActionDecoderPolicy.from_pretrained(out / "final").state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    log = json.loads((out / "train_log.json").read_text())["history"]
    assert [h["step"] for h in log] == list(range(4, 41, 4))
    # A log row whose window spans the checkpoint the run resumed from is the uninterrupted run's row.
    assert log == json.loads((tmp_path / "a" / "train_log.json").read_text())["history"]
    from action_decoder.train import lr_factor
    assert [h["lr"] for h in log[:2]] == pytest.approx([1e-3 * lr_factor(3, 100, 40), 1e-3 * lr_factor(7, 100, 40)])


@pytest.mark.parametrize("decoder", ["flow_matching", "mean_flow"])
def test_torchrun_two_processes_stay_in_sync(tmp_path, env, decoder):
    script = tmp_path / "ddp_check.py"
    script.write_text(textwrap.dedent(f"""
        import os, sys, torch, torch.distributed as dist
        from action_decoder.train import TrainConfig, train
        import action_decoder.train as T
        seen = {{}}
        orig = T.ActionDecoderPolicy.__init__
        def keep(self, *a, **k):
            orig(self, *a, **k)
            seen["policy"] = self
        T.ActionDecoderPolicy.__init__ = keep
        cfg = TrainConfig(task="metaworld/reach", demos=2, batch_size=16, hidden_size=32, num_layers=1,
                          steps=3, decoder="{decoder}", output_dir=sys.argv[1], eval_episodes=0,
                          progress=False, device="cpu")
        train(cfg)
        flat = torch.cat([p.detach().flatten() for p in seen["policy"].parameters()])
        gathered = [torch.zeros_like(flat) for _ in range(dist.get_world_size())]
        dist.all_gather(gathered, flat)
        dist_rank = dist.get_rank()
        if dist_rank == 0:
            print("MAXDIFF", float((gathered[0] - gathered[1]).abs().max()), flush=True)
        dist.barrier()          # no rank tears gloo down while the other still talks to it
        dist.destroy_process_group()
        print("DONE", dist_rank, flush=True)
        # Skip interpreter teardown: there, gloo's threads sometimes abort the process ("terminate
        # called without an active exception"), after the work is done.
        os._exit(0)
    """))
    # Generate the demos once, outside the two ranks.
    from action_decoder.data import generate_demos
    os.environ["ACTION_DECODER_CACHE"] = env["ACTION_DECODER_CACHE"]
    generate_demos("reach-v3", 2, 0)
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                          "--master_port", str(29500 + os.getpid() % 1000 + (decoder == "mean_flow")),
                          str(script), str(tmp_path / "out")], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert res.stdout.count("DONE") == 2, res.stdout
    maxdiff = float(res.stdout.split("MAXDIFF")[1].split()[0])
    assert maxdiff == 0.0   # each rank drew different rows and noise: equal only if gradients were all-reduced
    assert (tmp_path / "out" / "final" / "model.safetensors").is_file()


def test_torchrun_cli_as_the_readme_writes_it(tmp_path, env, monkeypatch):
    from action_decoder.data import generate_demos
    monkeypatch.setenv("ACTION_DECODER_CACHE", env["ACTION_DECODER_CACHE"])
    monkeypatch.chdir(Path(env["ACTION_DECODER_CACHE"]).parent)
    generate_demos("reach-v3", 2, 0)
    out = tmp_path / "ddp"
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                          "--master_port", str(29600 + os.getpid() % 1000), "-m", "action_decoder.cli", "train",
                          *TINY, "--decoder", "flow_matching", "--steps", "3", "--device", "cpu",
                          "--eval-episodes", "0", "--output-dir", str(out)],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert res.stdout.count("saved ") == 1, res.stdout      # rank 0 writes, rank 1 does not
    assert ActionDecoderPolicy.from_pretrained(out / "final").config.decoder_type == "flow_matching"


# ---------------------------------------------------------------------- run directories, resume, errors
def _tiny_dataset(root, seed=0, scale=1.0):
    """Two 30-frame episodes of a made-up 6-d state / 2-d action task: trains in a second."""
    from action_decoder.data import write_episodes

    rng = np.random.default_rng(seed)
    episodes = [{"observation.state": rng.normal(size=(30, 6)) * scale, "action": rng.uniform(-1, 1, (30, 2)),
                 "task_index": 0, "next.reward": np.zeros(30), "next.success": np.zeros(30, bool)} for _ in range(2)]
    write_episodes(root, episodes, ["mine"], 10, overwrite=True)
    return str(root)


def _ds_args(ds, out, *more):
    return ["train", "--dataset", ds, "--output-dir", str(out), "--batch-size", "8", "--hidden-size", "32",
            "--num-layers", "1", "--log-every", "1", "--eval-episodes", "0", "--no-progress", *more]


class _Res:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


@pytest.fixture
def cli_main(capsys, monkeypatch, env):
    """The CLI in this process (no interpreter start-up): args -> (returncode, stdout, stderr)."""
    from action_decoder import cli

    monkeypatch.setenv("ACTION_DECODER_CACHE", env["ACTION_DECODER_CACHE"])

    def call(args):
        capsys.readouterr()
        code = cli.main(list(args))
        out = capsys.readouterr()
        return _Res(code, out.out, out.err)

    return call


def _one_line(res, *words):
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("action-decoder: error:"), res.stderr
    assert all(w in lines[0] for w in words), (words, lines[0])
    return lines[0]


def test_train_defaults_to_flow_matching_with_ten_euler_steps():
    from action_decoder.train import TrainConfig, decoder_config

    cfg = TrainConfig()
    dconf = decoder_config(cfg, 39, 4, ["push-v3"])
    assert (cfg.decoder, dconf.decoder_type, dconf.num_inference_timesteps) == ("flow_matching", "flow_matching", 10)
    assert (cfg.steps, cfg.demos, cfg.task) == (1500, 10, "metaworld/push")


def test_train_meanflow_target_flag_reaches_the_decoder_config():
    import tyro

    from action_decoder.train import TrainConfig, decoder_config

    cfg = tyro.cli(TrainConfig, args=["--decoder", "mean_flow", "--meanflow-target", "split"])
    assert decoder_config(cfg, 39, 4, ["push-v3"]).meanflow_target == "split"
    assert decoder_config(TrainConfig(decoder="mean_flow"), 39, 4, ["push-v3"]).meanflow_target == "identity"


def test_a_second_run_on_a_locked_directory_fails_at_once_and_a_killed_holder_blocks_nothing(tmp_path, env):
    from action_decoder.run_dir import run_dir_lock

    out = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom action_decoder.run_dir import run_dir_lock\n"
                               "with run_dir_lock(sys.argv[1]):\n    print('held', flush=True)\n    time.sleep(120)",
                               str(out)], env=env, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        start = time.time()
        res = run(["train", *TINY, "--steps", "2", "--output-dir", str(out), "--eval-episodes", "0"], env)
        _one_line(res, "--output-dir", str(out), "in use", f"pid {holder.pid}")
        assert time.time() - start < 60 and not (out / "checkpoints").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert (out / ".lock").exists()                  # left behind by the killed holder...
    with run_dir_lock(out):                          # ...and it blocks nothing: the kernel dropped the lock
        pass


def test_output_dir_that_is_a_file_is_refused_before_training(tmp_path, cli_main):
    path = tmp_path / "a_file"
    path.write_text("x")
    res = cli_main(["train", *TINY, "--steps", "2", "--output-dir", str(path), "--eval-episodes", "0"])
    _one_line(res, "--output-dir", str(path), "file")
    assert "demonstrations" not in res.stdout and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("args, words", [
    (["train", "--device", "gpu"], ["--device", "'gpu'"]),
    (["train", "--device", "cuda:99"], ["--device", "cuda:99"]),
    (["eval", "--checkpoint", "CKPT", "--device", "tpu:0"], ["--device", "tpu:0"]),
    (["eval", "--checkpoint", "CKPT", "--device", "cuda:99"], ["--device", "cuda:99"]),
])
def test_bad_device_gives_one_line_for_every_subcommand(tmp_path, cli_main, args, words):
    args = [str(tmp_path) if a == "CKPT" else a for a in args]
    _one_line(cli_main([*args, "--output-dir", str(tmp_path / "o")] if args[0] == "train" else args), *words)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_cuda_without_cuda_gives_one_line(tmp_path, cli_main):
    _one_line(cli_main(["train", "--device", "cuda", "--output-dir", str(tmp_path / "o")]), "--device", "not available")


def test_progress_goes_to_stderr_and_results_to_stdout(tmp_path, env):
    ds = _tiny_dataset(tmp_path / "ds")
    args = [a for a in _ds_args(ds, tmp_path / "out", "--steps", "5") if a != "--no-progress"]
    with open(tmp_path / "log", "w") as log:
        res = subprocess.run([sys.executable, "-m", "action_decoder.cli", *args], env=env, stdout=log,
                             stderr=subprocess.PIPE, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    text = (tmp_path / "log").read_bytes()          # bytes: read_text() would turn "\r" into "\n"
    assert b"\r" not in text and b"saved " in text, text[:300]


def test_dataset_training_and_errors_without_the_simulator(tmp_path, env):
    ds = _tiny_dataset(tmp_path / "ds")
    script = tmp_path / "no_sim.py"
    script.write_text("import sys\nfor name in ('gymnasium', 'metaworld', 'mujoco'):\n    sys.modules[name] = None\n"
                      "from action_decoder.cli import main\nsys.exit(main(sys.argv[1:]))\n")
    res = subprocess.run([sys.executable, str(script), *_ds_args(ds, tmp_path / "out", "--steps", "3")], env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert ActionDecoderPolicy.from_pretrained(tmp_path / "out" / "final").config.extra["tasks"] == ["mine"]
    # A policy of another robot needs no simulator to be told that eval runs Meta-World tasks...
    res = subprocess.run([sys.executable, str(script), "eval", "--checkpoint", str(tmp_path / "out" / "final")],
                         env=env, capture_output=True, text=True, timeout=300)
    _one_line(res, "closed-loop evaluation runs Meta-World tasks", "['mine']", "model card")
    # ...and a Meta-World policy without the simulator is told how to install it.
    from action_decoder import DecoderConfig

    ActionDecoderPolicy(DecoderConfig(hidden_size=32, num_hidden_layers=1, extra={"tasks": ["reach-v3"]})) \
        .save_pretrained(tmp_path / "mw")
    res = subprocess.run([sys.executable, str(script), "eval", "--checkpoint", str(tmp_path / "mw")],
                         env=env, capture_output=True, text=True, timeout=300)
    _one_line(res, "gymnasium", "action-decoder[sim]")


def test_resume_refuses_changed_settings_in_one_line_and_accepts_more_steps(tmp_path, cli_main):
    ds, out = _tiny_dataset(tmp_path / "ds"), tmp_path / "out"
    assert cli_main(_ds_args(ds, out, "--steps", "2")).returncode == 0
    line = _one_line(cli_main(_ds_args(ds, out, "--steps", "4", "--resume", "--decoder", "mean_flow",
                                       "--hidden-size", "64")),
                     "--decoder: flow_matching → mean_flow", "--hidden-size: 32 → 64")
    assert "--steps" not in line
    _one_line(cli_main(_ds_args(_tiny_dataset(tmp_path / "other", seed=1), out, "--steps", "4", "--resume")),
              "--dataset:", str(tmp_path / "other"))
    _one_line(cli_main(_ds_args(ds, out, "--steps", "1", "--resume")), "--steps", "step 2")
    _tiny_dataset(tmp_path / "ds", seed=0, scale=3.0)          # same directory, other data
    _one_line(cli_main(_ds_args(ds, out, "--steps", "4", "--resume")), "normalisation statistics")
    _tiny_dataset(tmp_path / "ds", seed=0)
    res = cli_main(_ds_args(ds, out, "--steps", "4", "--resume", "--checkpoint-every", "3", "--log-every", "2"))
    assert res.returncode == 0 and "continuing from" in res.stdout, res.stderr
    assert json.loads((out / "train_log.json").read_text())["history"][-1]["step"] == 4


def test_resume_conflicts_compare_what_takes_effect():
    from dataclasses import asdict

    from action_decoder.train import TrainConfig, resume_conflicts

    saved = asdict(TrainConfig(task="metaworld/push", seed=0))
    assert resume_conflicts(saved, TrainConfig(task="metaworld/push-v3", steps=3000, device="cpu",
                                               output_dir="elsewhere", state_layout="metaworld")) == []
    assert resume_conflicts(saved, TrainConfig(task="metaworld/reach", seed=1, lr=3e-4)) == [
        "--task: push-v3 → reach-v3", "--seed: 0 → 1", "--lr: 0.001 → 0.0003"]
    # Defaults that follow the decoder (head, sampling steps) are not listed as changes of their own.
    assert resume_conflicts(saved, TrainConfig(decoder="mean_flow")) == ["--decoder: flow_matching → mean_flow"]


def test_resume_falls_back_to_the_newest_intact_checkpoint(tmp_path, cli_main):
    ds, out = _tiny_dataset(tmp_path / "ds"), tmp_path / "out"
    ckpts = out / "checkpoints"
    assert cli_main(_ds_args(ds, out, "--steps", "4", "--checkpoint-every", "2")).returncode == 0
    (ckpts / "step_0000004" / "training_state.safetensors").write_bytes(b"garbage")
    res = cli_main(_ds_args(ds, out, "--steps", "6", "--checkpoint-every", "2", "--resume"))
    assert res.returncode == 0, res.stderr
    lines = [line for line in res.stdout.splitlines() if line.startswith("resume:")]
    assert len(lines) == 1 and "names step_0000004, which does not load" in lines[0], res.stdout
    assert f"continuing from {ckpts / 'step_0000002'} (step 2)" in lines[0]
    shutil.rmtree(ckpts / "step_0000006")                    # `last` now names a deleted checkpoint
    res = cli_main(_ds_args(ds, out, "--steps", "8", "--checkpoint-every", "2", "--resume"))
    assert res.returncode == 0, res.stderr
    assert "names step_0000006, which is missing" in res.stdout
    assert f"continuing from {ckpts / 'step_0000004'} (step 4)" in res.stdout
    assert [h["step"] for h in json.loads((out / "train_log.json").read_text())["history"]] == list(range(1, 9))


def test_full_disk_gives_one_line_and_keeps_the_previous_checkpoint(tmp_path, monkeypatch, capsys):
    import errno

    from action_decoder import cli, run_dir

    ds, out = _tiny_dataset(tmp_path / "ds"), tmp_path / "out"
    real_save, calls = run_dir.save_state, []

    def save(state, directory):                 # the second checkpoint's training state finds the disk full
        calls.append(directory)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_save(state, directory)

    monkeypatch.setattr(run_dir, "save_state", save)
    assert cli.main(_ds_args(ds, out, "--steps", "4", "--checkpoint-every", "2")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no space left" in err[0] and "step_0000002 is intact" in err[0], err
    kept = out / "checkpoints" / "step_0000002"
    assert ActionDecoderPolicy.from_pretrained(kept) is not None
    assert run_dir.load_state(kept)["step"] == 2
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["last", "step_0000002"]


def test_a_run_without_its_checkpoints_is_not_overwritten(tmp_path, cli_main):
    ds, out = _tiny_dataset(tmp_path / "ds"), tmp_path / "out"
    assert cli_main(_ds_args(ds, out, "--steps", "2")).returncode == 0
    shutil.rmtree(out / "checkpoints")                          # freed for disk space; final/ and the logs stay
    weights = (out / "final" / "model.safetensors").read_bytes()
    _one_line(cli_main(_ds_args(ds, out, "--steps", "3")), "--output-dir", "already holds a training run",
              "a final policy")
    _one_line(cli_main(_ds_args(ds, out, "--steps", "3", "--resume")), "--resume", "no checkpoint to continue from")
    assert (out / "final" / "model.safetensors").read_bytes() == weights
    assert json.loads((out / "final" / "step.json").read_text()) == {"step": 2}


def test_record_image_size_without_cameras_and_a_failing_expert_are_one_line(tmp_path, cli_main, monkeypatch):
    _one_line(cli_main(["record", "--task", "metaworld/reach", "--demos", "1", "--output-dir", str(tmp_path / "r"),
                        "--image-size", "128"]), "--image-size", "--cameras")
    monkeypatch.setattr("action_decoder.data.demos._rollout", lambda *a, **k: None)    # the expert never succeeds
    _one_line(cli_main(["record", "--task", "metaworld/reach", "--demos", "2", "--output-dir", str(tmp_path / "r")]),
              "--demos: the scripted expert of reach-v3 succeeded in 0 of 6 attempts")


def test_an_interrupted_eval_does_not_point_to_a_resume_it_lacks(tmp_path, cli_main, monkeypatch):
    def interrupted(cfg):
        raise KeyboardInterrupt

    monkeypatch.setattr("action_decoder.evaluate.run_eval", interrupted)
    res = cli_main(["eval", "--checkpoint", str(tmp_path)])
    assert res.returncode == 130 and "--resume" not in res.stderr and "nothing was saved" in res.stderr


def test_torchrun_resume_continues_each_processes_own_streams(tmp_path, env):
    """Two processes, interrupted after step 4 and resumed from the checkpoint of step 3, end with the
    uninterrupted run's weights and log rows (each rank restores its own data and noise streams)."""
    script = tmp_path / "ddp_resume.py"
    script.write_text(textwrap.dedent("""
        import json, os, sys, torch, torch.distributed as dist
        from pathlib import Path
        from action_decoder.train import TrainConfig, train
        import action_decoder.train as T

        def cfg(out, **kw):
            return TrainConfig(task="metaworld/reach", demos=2, batch_size=16, hidden_size=32, num_layers=1,
                               steps=6, checkpoint_every=3, log_every=2, output_dir=out, eval_episodes=0,
                               progress=False, device="cpu", **kw)

        root = Path(sys.argv[1])
        train(cfg(str(root / "a")))
        real, calls = T._batch, [0]
        def stop_at_five(*a, **k):
            calls[0] += 1
            if calls[0] == 5:
                raise KeyboardInterrupt
            return real(*a, **k)
        T._batch = stop_at_five
        try:
            train(cfg(str(root / "b")))
        except KeyboardInterrupt:
            pass
        T._batch = real
        dist.barrier()
        train(cfg(str(root / "b"), resume=True))
        if dist.get_rank() == 0:
            from safetensors.torch import load_file
            a, b = (load_file(str(root / d / "final" / "model.safetensors")) for d in "ab")
            print("MAXDIFF", max(float((a[k] - b[k]).abs().max()) for k in a), flush=True)
            logs = [json.loads((root / d / "train_log.json").read_text())["history"] for d in "ab"]
            print("SAMELOG", logs[0] == logs[1], flush=True)
        dist.barrier()
        dist.destroy_process_group()
        os._exit(0)
    """))
    from action_decoder.data import generate_demos
    os.environ["ACTION_DECODER_CACHE"] = env["ACTION_DECODER_CACHE"]
    generate_demos("reach-v3", 2, 0)
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2",
                          "--master_port", str(29700 + os.getpid() % 1000), str(script), str(tmp_path)],
                         env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    assert float(res.stdout.split("MAXDIFF")[1].split()[0]) == 0.0 and "SAMELOG True" in res.stdout, res.stdout


def test_a_refused_run_leaves_no_directory_holding_only_its_lock(tmp_path, cli_main):
    missing = tmp_path / "no_such_dataset"
    out = tmp_path / "train_out"
    res = cli_main(_ds_args(str(missing), out, "--steps", "2"))
    assert res.returncode == 2 and not out.exists(), sorted(p.name for p in out.iterdir())
    kept = tmp_path / "kept"                                   # a directory the user made stays, without a lock
    kept.mkdir()
    assert cli_main(_ds_args(str(missing), kept, "--steps", "2")).returncode == 2
    assert kept.is_dir() and not any(kept.iterdir())
    ft = tmp_path / "ft_out"
    res = cli_main(["finetune", "--checkpoint", str(tmp_path / "no_such_checkpoint"), "--output-dir", str(ft)])
    assert res.returncode == 2 and not ft.exists()


def _saved_policy(path, decoder="flow_matching", state_dim=39, action_dim=4, tasks=("reach-v3",)):
    from action_decoder import DecoderConfig

    cfg = DecoderConfig(decoder_type=decoder, state_dim=state_dim, action_dim=action_dim, hidden_size=32,
                        num_hidden_layers=1, context_dim=len(tasks) if len(tasks) > 1 else None,
                        extra={"tasks": list(tasks), "train": {"dataset": "data/blocks"}})
    ActionDecoderPolicy(cfg).save_pretrained(path)
    return str(path)


@pytest.mark.parametrize("tasks", [("push the block",), ("push the block", "lift the cube")])
def test_finetune_of_a_policy_of_another_robot_is_one_line_without_a_circle(tmp_path, cli_main, tasks):
    ckpt = _saved_policy(tmp_path / "blocks", state_dim=6, action_dim=2, tasks=tasks)
    for more in ([], ["--task", "metaworld/push"]):           # naming a Meta-World task does not send it elsewhere
        line = _one_line(cli_main(["finetune", "--checkpoint", ckpt, "--output-dir", str(tmp_path / "o"), *more]),
                         "RL fine-tuning runs Meta-World tasks", "push the block", "6-d state")
        assert "--task" not in line and "not among" not in line
    if len(tasks) > 1:      # Meta-World's widths, other tasks: --task cannot give a multi-task policy its token
        ckpt = _saved_policy(tmp_path / "mw_widths", tasks=tasks)
        line = _one_line(cli_main(["finetune", "--checkpoint", ckpt, "--output-dir", str(tmp_path / "o"),
                                   "--task", "metaworld/push"]), "RL fine-tuning runs Meta-World tasks")
        assert "not among" not in line


def test_finetune_of_a_ddpm_policy_reaches_its_refusal_whatever_its_tasks(tmp_path, cli_main):
    for name, kw in (("other_robot", {"state_dim": 6, "action_dim": 2, "tasks": ("push the block",)}),
                     ("multi_task", {"tasks": ("reach-v3", "push-v3")})):
        ckpt = _saved_policy(tmp_path / name, decoder="DDPM", **kw)
        _one_line(cli_main(["finetune", "--checkpoint", ckpt, "--output-dir", str(tmp_path / "o")]),
                  "flow_matching or mean_flow", "decoder_type='DDPM'")


@pytest.mark.parametrize("command", ["train", "eval", "finetune", "relabel"])
def test_help_gives_each_option_one_line_without_measurements(command, capsys, monkeypatch):
    """`--help`: per option one line saying what it does and its default; measurements live in the
    benchmark pages."""
    from dataclasses import fields

    from action_decoder.evaluate import EvalConfig
    from action_decoder.relabel import RelabelConfig
    from action_decoder.rl import FinetuneConfig
    from action_decoder.train import TrainConfig

    from action_decoder import cli

    monkeypatch.setenv("COLUMNS", "400")
    with pytest.raises(SystemExit) as exit_:
        cli.main([command, "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    body = text[text.index("--help"):]                     # the options, boxed (a terminal) or not
    rows = [line.strip("│ ").rstrip() for line in body.splitlines() if line.strip("│ ─-╰╯╭╮")]
    options, current = {}, None
    for row in rows:
        if row.startswith("-"):
            current = row.split()[0].rstrip(",")
            options[current] = [row]
        elif current is not None:
            options[current].append(row)
    config = {"train": TrainConfig, "eval": EvalConfig, "finetune": FinetuneConfig, "relabel": RelabelConfig}[command]
    flags = {f"--{f.name.replace('_', '-')}" for f in fields(config)}
    assert flags <= set(options), flags - set(options)
    for flag in flags:
        text = " ".join(options[flag])
        help_lines = [r for r in options[flag] if not r.startswith("-")] or [options[flag][0]]
        # The flag and its metavar may take a line of their own; the help itself is one line.
        assert len(help_lines) == 1, (flag, options[flag])
        described = re.sub(r"\((default|required)[^)]*\)", "", help_lines[0].split("  ")[-1]).strip()
        assert len(described) > 8 and not described.startswith("-"), (flag, text)
        assert "%" not in text and "→" not in text, (flag, text)


def test_record_into_a_read_only_place_names_output_dir_before_recording(tmp_path, cli_main):
    import tempfile

    try:                                        # /sys refuses new files even to root (sysfs)
        tempfile.TemporaryFile(dir="/sys").close()
        pytest.skip("/sys is writable here")
    except OSError:
        pass
    for out in ("/sys/action_decoder_demos", str(tmp_path / "a_file" / "demos")):
        (tmp_path / "a_file").write_text("x")
        res = cli_main(["record", "--task", "metaworld/reach", "--demos", "1", "--output-dir", out])
        _one_line(res, "--output-dir: cannot write the dataset to", out)
        assert "recorded" not in res.stdout
