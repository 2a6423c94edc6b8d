"""Closed-loop relabelling for real-time chunking: DAgger (Ross et al. 2011) with inference delays.

With real-time chunking a new chunk is planned while the previous one keeps executing: its first d
actions are committed before it exists, and training-time RTC feeds them to the network as a clean
prefix. A scripted expert's demonstrations only show prefixes that agree with the state (its actions
are a function of it); in closed loop the prefix is the policy's own, often slightly wrong.

``relabel_episodes`` rolls a policy out on demonstration layouts with an inference delay d
(`envs.evaluate` with ``rtc``) and, at every plan, keeps the state it plans from and a label: the
committed prefix (the d rows the plan was given; none for an episode's first plan) followed by the
scripted expert's actions from the state that prefix reaches (`demos.expert_continuation`:
simulated from a saved MuJoCo state and rewound). One rollout becomes one episode of plan frames,
``n_action_steps`` control steps apart, whose ``action.continuation`` is the label and
``action.prefix_length`` the number of committed rows it starts with, so ``train --dataset`` cuts
each frame's chunk from it as from DART demonstrations and, with training-time RTC, feeds exactly
those rows in as the clean prefix (docs/benchmarks/rtc.md).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .demos import expert_continuation
from .episodes import ACTION, CONTINUATION, PREFIX_LENGTH, STATE


def relabel_episodes(policy_fn: Callable, task: str, layout_seeds: list[int], delay: int, n_action_steps: int,
                     max_steps: int = 300, num_envs: int = 10) -> tuple[list[dict], float]:
    """Roll ``policy_fn`` (an `envs.evaluate.PolicyFn` that takes ``prev_chunks`` and ``delay``) out on
    each layout of ``layout_seeds`` with inference ``delay`` and real-time chunking, executing
    ``n_action_steps`` actions a chunk, for at most ``max_steps`` steps an episode. Returns one episode
    per layout (``observation.state [P, S]`` at its P plans, ``action.continuation [P, LOOKAHEAD, D]``
    their labels, ``action.prefix_length [P]`` their committed rows (``delay``; 0 at the first plan),
    ``action [P, D]`` the labels' first rows, ``seed``, ``task_index`` 0) and the
    rollouts' success rate."""
    from ..envs.metaworld_tasks import canonical_task, expert_policy
    from ..envs.evaluate import evaluate

    name = canonical_task(task)
    expert, envs = expert_policy(name), {}
    plans: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {int(s): [] for s in layout_seeds}
    if len(plans) != len(layout_seeds):
        raise ValueError(f"layout_seeds: expected distinct layouts, got {list(layout_seeds)}")

    def on_step(episode: int, env) -> None:
        envs[int(layout_seeds[episode])] = env          # after each reset and step: the env a layout runs in

    def labelled(states, task_index, episode_seeds=None, plan_indices=None, prev_chunks=None, delay=0, **keys):
        chunks = policy_fn(states, task_index, episode_seeds=episode_seeds, plan_indices=plan_indices,
                           prev_chunks=prev_chunks, delay=delay, **keys)             # [B, H, D]
        for b, seed in enumerate(episode_seeds.tolist()):
            prefix = prev_chunks[b, :delay] if prev_chunks is not None else chunks[b, :0]   # [d, D]
            plans[seed].append((np.asarray(states[b], np.float32),
                                expert_continuation(envs[seed], expert, prefix, states[b]), len(prefix)))
        return chunks

    result = evaluate(labelled, name, episodes=len(layout_seeds), n_action_steps=n_action_steps,
                      max_steps=max_steps, num_envs=num_envs, on_step=on_step, delay=delay, rtc=True,
                      layout_seeds=list(layout_seeds))
    episodes = []
    for seed, rows in plans.items():
        labels = np.stack([label for _, label, _ in rows]).astype(np.float32)        # [P, LOOKAHEAD, D]
        episodes.append({STATE: np.stack([state for state, _, _ in rows]), ACTION: labels[:, 0],
                         CONTINUATION: labels, PREFIX_LENGTH: np.array([d for *_, d in rows], np.int64),
                         "task_index": 0, "seed": seed})
    return episodes, result["success_rate"]
