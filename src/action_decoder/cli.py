"""`action-decoder` console script: train, eval, finetune (every option from a dataclass, via tyro)."""

from __future__ import annotations

import os
import sys


def main(argv: list[str] | None = None) -> int:
    # One torch thread unless the user says otherwise: two run 10-100x slower on small CPUs.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch
    import tyro

    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))
    from .evaluate import EvalConfig, run_eval
    from .rl import FinetuneConfig, finetune
    from .train import TrainConfig, train

    args = sys.argv[1:] if argv is None else list(argv)
    # `action-decoder train` with no options runs the default task end to end.
    commands = {"train": TrainConfig, "eval": EvalConfig, "finetune": FinetuneConfig}
    cfg = tyro.extras.subcommand_cli_from_dict(commands, args=args, prog="action-decoder")
    try:
        if isinstance(cfg, TrainConfig):
            final = train(cfg)
            rank = int(os.environ.get("RANK", 0))
            if cfg.eval_episodes and rank == 0:
                run_eval(EvalConfig(checkpoint=str(final), episodes=cfg.eval_episodes, seed=cfg.seed,
                                    device="cpu"))
        elif isinstance(cfg, FinetuneConfig):
            finetune(cfg)
        else:
            run_eval(cfg)
    except (ValueError, FileNotFoundError, FloatingPointError) as err:
        print(f"action-decoder: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("action-decoder: interrupted; continue with --resume", file=sys.stderr)
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
