"""python -m benchmarks [--quick] [--tiny] [--out DIR] [--quality-dir DIR] [--device cpu|cuda]
python -m benchmarks rtc [...]   (real-time chunking grid, benchmarks/rtc.py)
python -m benchmarks multimodal [--quick] [--tiny] ...   (the multimodal benchmark, benchmarks/multimodal.py)
python -m benchmarks cameras [...]   (image- against state-conditioned policies, benchmarks/cameras.py)
python -m benchmarks export [...]   (eager, compiled and onnxruntime latency per chunk, benchmarks/export.py)
python -m benchmarks rtc-latency [...]   (trained and guided RTC chunk against a plain chunk, benchmarks/rtc_latency.py)
python -m benchmarks serve [...]   (action-decoder serve with LeRobot's RobotClient: latency, queue; benchmarks/serve.py)
"""

from __future__ import annotations

import os
import sys

# One torch thread unless the user says otherwise (set before torch is imported).
os.environ.setdefault("OMP_NUM_THREADS", "1")


def main(argv: list[str] | None = None) -> int:
    import argparse

    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["rtc"]:
        from .rtc import main as rtc_main

        rtc_main(argv[1:])
        return 0
    if argv[:1] == ["multimodal"]:
        from .multimodal import main as multimodal_main

        return multimodal_main(argv[1:])
    if argv[:1] == ["export"]:
        from .export import main as export_main

        return export_main(argv[1:])
    if argv[:1] == ["rtc-latency"]:
        from .rtc_latency import main as rtc_latency_main

        return rtc_latency_main(argv[1:])
    if argv[:1] == ["serve"]:
        from .serve import main as serve_main

        return serve_main(argv[1:])
    if argv[:1] == ["cameras"]:
        from .cameras import main as cameras_main

        return cameras_main(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer rounds (< 3 min on one core)")
    parser.add_argument("--tiny", action="store_true", help="tiny networks and few rounds (smoke test)")
    parser.add_argument("--out", default=None,
                        help="where README.md, results.json, the plot go (default: docs/benchmarks for the full "
                             "run; outputs/benchmarks-quick for --quick/--tiny, so they never overwrite "
                             "the committed tables)")
    parser.add_argument("--quality-dir", default=None,
                        help="directory searched (recursively) for eval JSON files (action-decoder eval)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda (CUDA events on a GPU)")
    parser.add_argument("--threads", type=int, default=int(os.environ["OMP_NUM_THREADS"]))
    parser.add_argument("--sections", default="sampling,training,peers,memory,quality",
                        help="comma-separated subset of sampling,training,peers,memory,quality")
    parser.add_argument("--no-plot", action="store_true")
    args = parser.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    from .suite import BenchConfig, run_suite

    mode = "tiny" if args.tiny else ("quick" if args.quick else "default")
    out = {} if args.out is None else {"out": args.out}
    cfg = BenchConfig.preset(mode, device=args.device, quality_dir=args.quality_dir, **out,
                             sections=tuple(s.strip() for s in args.sections.split(",") if s.strip()),
                             plot=not args.no_plot)
    run_suite(cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())
