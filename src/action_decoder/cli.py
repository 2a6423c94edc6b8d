"""`action-decoder` console script: train, eval, finetune, record, relabel, convert, export, serve (every option from a dataclass, via tyro)."""

from __future__ import annotations

import os
import sys


SIM_MODULES = ("gymnasium", "metaworld", "mujoco")


def check_device(name: str, option: str = "--device") -> None:
    """Refuse a device string torch cannot parse, or a device this machine does not have, in one
    line (before any work: otherwise torch fails deep inside the first tensor move)."""
    import torch

    if name == "auto":
        return
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise ValueError(f"{option}: expected auto, cpu, cuda, cuda:N or another torch device, got {name!r}") from None
    if device.type == "cpu":
        return
    backend = getattr(torch, device.type, None) if device.type != "mps" else torch.backends.mps
    if backend is None or not hasattr(backend, "is_available") or not backend.is_available():
        raise ValueError(f"{option}: {name!r} is not available on this machine (torch {torch.__version__}); "
                         f"use --device cpu or auto")
    count = backend.device_count() if hasattr(backend, "device_count") else 1
    if device.index is not None and device.index >= count:
        raise ValueError(f"{option}: {name!r} names device {device.index}, but this machine has {count} "
                         f"{device.type} device(s) (0..{count - 1})")


def main(argv: list[str] | None = None) -> int:
    # One torch thread unless the user says otherwise: two run 10-100x slower on small CPUs.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch
    import tyro

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    from .evaluate import EvalConfig, run_eval
    from .export import ExportConfig, run_export
    from .lerobot_checkpoint import ConvertConfig, run_convert
    from .record import RecordConfig, run_record
    from .relabel import RelabelConfig, run_relabel
    from .rl import FinetuneConfig, finetune
    from .serving import ServeConfig, run_serve
    from .train import TrainConfig, closed_loop_env, train

    args = sys.argv[1:] if argv is None else list(argv)
    # `action-decoder train` with no options runs the default task end to end.
    commands = {"train": TrainConfig, "eval": EvalConfig, "finetune": FinetuneConfig, "record": RecordConfig,
                "relabel": RelabelConfig, "convert": ConvertConfig, "export": ExportConfig, "serve": ServeConfig}
    cfg = tyro.extras.subcommand_cli_from_dict(commands, args=args, prog="action-decoder")
    try:
        if hasattr(cfg, "device"):
            check_device(cfg.device)
        if isinstance(cfg, TrainConfig):
            final = train(cfg)
            rank = int(os.environ.get("RANK", 0))
            # Closed loop only where the dataset names an environment the library runs; otherwise
            # training reported its held-out validation (train.load_training_data).
            if cfg.eval_episodes and rank == 0 and closed_loop_env(cfg):
                run_eval(EvalConfig(checkpoint=str(final), episodes=cfg.eval_episodes, seed=cfg.seed,
                                    device="cpu", wandb=cfg.wandb, wandb_project=cfg.wandb_project))
        elif isinstance(cfg, FinetuneConfig):
            finetune(cfg)
        elif isinstance(cfg, RecordConfig):
            run_record(cfg)
        elif isinstance(cfg, RelabelConfig):
            run_relabel(cfg)
        elif isinstance(cfg, ConvertConfig):
            run_convert(cfg)
        elif isinstance(cfg, ExportConfig):
            run_export(cfg)
        elif isinstance(cfg, ServeConfig):
            run_serve(cfg)
        else:
            run_eval(cfg)
    except (ValueError, OSError, FloatingPointError) as err:
        # An OSError built with (errno, message) prints its message; a system one keeps its path.
        message = err.strerror if isinstance(err, OSError) and err.strerror and err.filename is None else err
        print(f"action-decoder: error: {message}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as err:
        if err.name not in SIM_MODULES:
            raise
        print(f"action-decoder: error: {err.name} is not installed; the Meta-World simulator comes with: "
              f"pip install \"action-decoder[sim]\"", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if isinstance(cfg, (TrainConfig, FinetuneConfig)):
            from pathlib import Path

            from .run_dir import last_checkpoint

            ckpt = last_checkpoint(Path(cfg.output_dir))   # name only a checkpoint that exists
            print(f"action-decoder: interrupted; continue from {ckpt} with --resume" if ckpt is not None else
                  f"action-decoder: interrupted before the first checkpoint in {cfg.output_dir}: nothing to "
                  f"resume, run it again", file=sys.stderr)
        elif isinstance(cfg, ServeConfig):
            print("action-decoder: serve stopped", file=sys.stderr)
            return 0
        else:
            print(f"action-decoder: interrupted; {type(cfg).__name__.removesuffix('Config').lower()} writes its "
                  f"results at the end, so nothing was saved: run it again", file=sys.stderr)
        return 130
    finally:
        # A gloo group left for interpreter shutdown can abort the process (SIGABRT) at exit.
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
    return 0


def entry() -> None:
    """The console script and `python -m action_decoder.cli`: `main()`'s code as the exit status.

    A rank under torchrun or accelerate leaves without interpreter teardown: gloo's worker threads
    can abort a finished process there ("terminate called without an active exception", seen in
    CI; pytorch#179291). Its group is destroyed and its files are closed by then."""
    code = main()
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
