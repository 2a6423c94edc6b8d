"""The ceiling of the MP1 benchmark: Meta-World's scripted expert itself, run closed-loop on the
same evaluation layouts as the policies. Behaviour cloning learns from this expert's successful
episodes, so a task where the expert fails often (soccer, stick-pull, box-close) caps what a
cloned policy can be expected to reach.

    python -m benchmarks.scripted_expert --task metaworld/soccer --seed 0

`--output-dir` writes `eval_expert.json` in the schema of `action-decoder eval`, so
`benchmarks.metaworld_bc` tabulates it as a column beside the decoders.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from action_decoder.envs import evaluate, expert_policy


def run(task: str, seed: int, episodes: int = 50) -> dict:
    """The expert's success on the evaluation layouts of `seed` (re-planned at every step)."""
    expert = expert_policy(task)
    res = evaluate(lambda state, _task_index: expert(state)[:, None, :], task, episodes=episodes, seed=seed,
                   n_action_steps=1)                                  # a chunk of one action per step
    return {"checkpoint": None, "decoder_type": "scripted_expert", "sampler": "expert", "steps": 1,
            "episodes_per_task": episodes, "seed": seed, "success_rate": res["success_rate"],
            "per_task": {res["task"]: res["success_rate"]}, "results": [res]}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="metaworld/soccer")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--output-dir", default=None, help="directory for eval_expert.json")
    args = p.parse_args(argv)
    res = run(args.task, args.seed, args.episodes)
    print(f"{args.task}: success_rate={res['success_rate']}")
    if args.output_dir:
        Path(args.output_dir).mkdir(parents=True, exist_ok=True)
        (Path(args.output_dir) / "eval_expert.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
