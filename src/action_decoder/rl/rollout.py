"""Chunk-level episodes on lockstep Meta-World envs: one decision = one action chunk.

Each call runs one full episode per env, from layouts given by seeds (so an iteration is
reproducible and a resumed run re-collects exactly what it would have). A decision
executes the chunk's first `n_action_steps` actions (clipped to [−1, 1]); its reward is the
sum of the env rewards over the steps executed (the env reward of the last step before and
of the last step of the decision are kept too: they serve as potentials for shaping). With
`stop_on_success` the episode ends at the first success (terminal), otherwise it runs on (the
dense-reward protocol of Meta-World's RL baselines); it is truncated at `max_steps` (the critic
bootstraps there). Rows are returned
episode by episode, in time order, which is what GAE needs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

ActFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, dict]]
"""act(states [B, S] float32, progress [B] float32) -> (chunks [B, H, D] env units, {name: Tensor [B, ...]})."""


@dataclass
class Rollout:
    """N decisions of E episodes; `records` holds what the act function stored per decision."""

    states: Tensor          # [N, S] env units
    next_states: Tensor     # [N, S]
    progress: Tensor        # [N] env steps done before the decision / max_steps
    next_progress: Tensor   # [N]
    env_rewards: Tensor     # [N] sum of env rewards over the executed steps
    reward_before: Tensor   # [N] env reward of the step before the decision (first decision: 0, whatever it does)
    reward_after: Tensor    # [N] env reward of the decision's last step
    success: Tensor         # [N] bool: the success flag was raised during this decision
    terminal: Tensor        # [N] bool: the episode ended in a terminal state (success with stop_on_success)
    last: Tensor            # [N] bool: the episode ended after this decision
    executed: Tensor        # [N] long: actions of the chunk executed (fewer than n_action_steps where it ended)
    records: dict           # name -> Tensor [N, ...]
    episode_returns: list   # [E] env return per episode
    episode_success: list   # [E] bool
    episode_lengths: list   # [E] env steps
    env_steps: int


def collect(envs: list, seeds: list[int], act: ActFn, n_action_steps: int, max_steps: int,
            stop_on_success: bool = True) -> Rollout:
    """Run one episode per env (layout `seeds[i]`) with chunks from `act`."""
    n = len(envs)
    obs = np.stack([env.reset(seed=int(s))[0] for env, s in zip(envs, seeds)]).astype(np.float32)
    steps = np.zeros(n, dtype=np.int64)
    active = list(range(n))
    rows: list[list[dict]] = [[] for _ in range(n)]
    returns, wins = [0.0] * n, [False] * n
    latest: list = [None] * n                   # env reward of each env's latest step
    while active:
        progress = (steps[active] / max_steps).astype(np.float32)
        chunks, record = act(obs[active], progress)
        chunks = np.clip(np.asarray(chunks)[:, :n_action_steps], -1.0, 1.0)
        still = []
        for j, e in enumerate(active):
            # The first decision's "before" is 0: the reward after its first action would depend on that action.
            state, reward, success, executed = obs[e].copy(), 0.0, False, 0
            before = 0.0 if latest[e] is None else latest[e]
            for action in chunks[j]:
                o, r, _, _, info = envs[e].step(action)
                executed += 1
                obs[e], steps[e], reward = o, steps[e] + 1, reward + float(r)
                latest[e] = float(r)
                success = success or bool(info["success"])
                if (success and stop_on_success) or steps[e] >= max_steps:
                    break
            returns[e] += reward
            wins[e] = wins[e] or success
            terminal = success and stop_on_success
            last = terminal or steps[e] >= max_steps
            rows[e].append({"state": state, "next_state": obs[e].copy(), "progress": progress[j],
                            "next_progress": steps[e] / max_steps, "reward": reward, "reward_before": before,
                            "reward_after": latest[e], "success": success,
                            "terminal": terminal, "last": last, "executed": executed,
                            **{k: v[j] for k, v in record.items()}})
            if not last:
                still.append(e)
        active = still
    flat = [r for ep in rows for r in ep]
    keys = [k for k in flat[0] if k not in ("state", "next_state", "progress", "next_progress", "reward",
                                            "reward_before", "reward_after", "success", "terminal", "last",
                                            "executed")]
    col = lambda k, dt=torch.float32: torch.as_tensor(np.array([r[k] for r in flat]), dtype=dt)  # noqa: E731
    return Rollout(states=col("state"), next_states=col("next_state"), progress=col("progress"),
                   next_progress=col("next_progress"), env_rewards=col("reward"),
                   reward_before=col("reward_before"), reward_after=col("reward_after"),
                   success=col("success", torch.bool), terminal=col("terminal", torch.bool),
                   last=col("last", torch.bool), executed=col("executed", torch.long),
                   records={k: torch.stack([r[k] for r in flat]) for k in keys},
                   episode_returns=returns, episode_success=wins,
                   episode_lengths=[int(s) for s in steps], env_steps=int(steps.sum()))
