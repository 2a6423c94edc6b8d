"""Closed-loop evaluation of any chunking policy on a Meta-World task.

Several environments step in lockstep so that one policy call serves every environment
that needs a new plan; each episode's layout depends only on its own seed (``eval_seeds``).
A ``policy_fn`` that takes ``episode_seeds`` and ``plan_indices`` (as ``make_policy_fn``'s
does) learns which episode and which of its plans each row is, so it can draw each row's
noise from that identity: then results do not depend on ``num_envs`` either. An episode
counts as a success as soon as ``info["success"]`` is 1, and stops there (later steps cannot
change the outcome and cost time); its return is summed up to that step. Building an env costs
~0.25 s (MuJoCo compiles the scene), so the envs of the last evaluated task are kept for
the next call: reuse is safe because every episode re-seeds and fully resets its env.
"""

from __future__ import annotations

import inspect
import time
from typing import Callable

import numpy as np

from .metaworld_tasks import MAX_EPISODE_STEPS, SeededLayoutEnv, canonical_task, eval_seeds, make_env

_idle_envs: dict[str, list[SeededLayoutEnv]] = {}

PolicyFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``policy_fn(states [B, S] float32, task_index [B] int64) -> actions [B, H, D]`` in env units.

It may also take keywords ``episode_seeds [B]`` (each row's episode seed) and ``plan_indices [B]``
(0 for an episode's first plan, then 1, 2, ...), or ``**kwargs``: then it is given both."""


def _takes_episode_keys(policy_fn: PolicyFn) -> bool:
    try:
        params = inspect.signature(policy_fn).parameters.values()
    except (TypeError, ValueError):     # a builtin without a signature: the two-argument form
        return False
    return any(p.kind is p.VAR_KEYWORD for p in params) or \
        {"episode_seeds", "plan_indices"} <= {p.name for p in params}


def _plan(policy_fn: PolicyFn, states: np.ndarray, task_index: int, n_action_steps: int, keys: dict) -> np.ndarray:
    chunk = np.asarray(policy_fn(states, np.full(len(states), task_index, dtype=np.int64), **keys))
    expected = f"[{len(states)}, H >= {n_action_steps}, 4]"
    if chunk.ndim != 3 or chunk.shape[0] != len(states) or chunk.shape[2] != 4 or chunk.shape[1] < n_action_steps:
        raise ValueError(f"policy_fn output: expected an action chunk of shape {expected}, got {chunk.shape}")
    if not np.isfinite(chunk).all():
        raise ValueError("policy_fn output: expected finite actions, got NaN or Inf")
    return np.clip(chunk[:, :n_action_steps], -1.0, 1.0)


def _borrow_envs(name: str, n: int) -> list[SeededLayoutEnv]:
    envs = _idle_envs.pop(name, [])
    for env in [e for pool in _idle_envs.values() for e in pool] + envs[n:]:
        env.close()
    _idle_envs.clear()
    return envs[:n] + [make_env(name) for _ in range(n - len(envs[:n]))]


def evaluate(
    policy_fn: PolicyFn,
    task: str,
    episodes: int = 50,
    seed: int = 0,
    n_action_steps: int = 8,
    max_steps: int = 500,
    num_envs: int = 10,
    task_index: int = 0,
    progress: Callable[[int, int, int, bool], None] | None = None,
    record: bool = False,
    on_step: Callable[[int, SeededLayoutEnv], None] | None = None,
) -> dict:
    """Run ``episodes`` receding-horizon episodes: execute the first ``n_action_steps``
    actions of each chunk (clipped to [-1, 1]), then re-plan from the new state.

    ``task_index`` is passed to ``policy_fn`` (multi-task policies), and so are each row's episode seed
    and plan index if it takes them (see ``PolicyFn``); ``progress(done, total, episode, success)`` is
    called after each finished episode: ``done`` finished so far, ``episode`` its index in [0, total).
    ``record=True`` adds ``trajectories``: per episode the hand positions ``[T, 3]`` (obs[0:3]) and
    the goal (obs[36:39]). ``on_step(episode, env)`` is called after each reset and after each step
    of an episode, before the next reset of its env (``envs.render.EpisodeCamera`` films episodes so).
    Returns ``task``, ``success_rate``, and per
    episode ``successes``, ``lengths``, ``returns``, ``seeds``, plus ``env_steps`` and
    ``wall_time_s``.
    """
    name = canonical_task(task)
    for arg, value, low in (("episodes", episodes, 1), ("n_action_steps", n_action_steps, 1), ("num_envs", num_envs, 1)):
        if not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{arg}: expected an integer >= {low}, got {value!r}")
    if not isinstance(max_steps, (int, np.integer)) or not 1 <= max_steps <= MAX_EPISODE_STEPS:
        raise ValueError(f"max_steps: expected an integer in [1, {MAX_EPISODE_STEPS}] (Meta-World's episode cap), got {max_steps!r}")
    envs = _borrow_envs(name, min(num_envs, episodes))

    seeds = eval_seeds(seed, episodes)
    successes, lengths, returns = [False] * episodes, [0] * episodes, [0.0] * episodes
    hands: list[list[np.ndarray]] = [[] for _ in range(episodes)]
    goals: list[np.ndarray | None] = [None] * episodes
    obs = np.zeros((len(envs), envs[0].observation_space.shape[0]), dtype=np.float32)
    slot_episode = [-1] * len(envs)
    plans: list[np.ndarray | None] = [None] * len(envs)
    plan_count = [0] * episodes                 # plans made so far, per episode
    keyed = _takes_episode_keys(policy_fn)
    next_episode, finished, start = 0, 0, time.perf_counter()

    def begin(slot: int) -> None:
        nonlocal next_episode
        slot_episode[slot], plans[slot] = -1, None
        if next_episode < episodes:
            obs[slot] = envs[slot].reset(seed=seeds[next_episode])[0]
            if record:
                hands[next_episode].append(obs[slot][:3].copy())
                goals[next_episode] = obs[slot][36:39].copy()
            if on_step is not None:
                on_step(next_episode, envs[slot])
            slot_episode[slot], next_episode = next_episode, next_episode + 1

    for slot in range(len(envs)):
        begin(slot)
    while finished < episodes:
        active = [s for s in range(len(envs)) if slot_episode[s] >= 0]
        replan = [s for s in active if plans[s] is None or len(plans[s]) == 0]
        if replan:
            eps_now = [slot_episode[s] for s in replan]
            keys = {"episode_seeds": np.array([seeds[e] for e in eps_now], dtype=np.int64),
                    "plan_indices": np.array([plan_count[e] for e in eps_now], dtype=np.int64)} if keyed else {}
            for s, chunk in zip(replan, _plan(policy_fn, obs[replan], task_index, n_action_steps, keys)):
                plans[s] = chunk
            for e in eps_now:
                plan_count[e] += 1
        for s in active:
            ep, action, plans[s] = slot_episode[s], plans[s][0], plans[s][1:]
            obs[s], reward, _, _, info = envs[s].step(action)
            lengths[ep] += 1
            if record:
                hands[ep].append(obs[s][:3].copy())
            if on_step is not None:
                on_step(ep, envs[s])
            returns[ep] += float(reward)
            successes[ep] = bool(info["success"])
            if successes[ep] or lengths[ep] >= max_steps:
                finished += 1
                if progress is not None:
                    progress(finished, episodes, ep, successes[ep])
                begin(s)
    _idle_envs.setdefault(name, []).extend(envs)
    extra = {"trajectories": [{"hand": np.stack(h).tolist(), "goal": g.tolist()} for h, g in zip(hands, goals)]} \
        if record else {}
    return {
        **extra,
        "task": name,
        "success_rate": float(np.mean(successes)),
        "successes": successes,
        "lengths": lengths,
        "returns": returns,
        "seeds": seeds,
        "env_steps": int(sum(lengths)),
        "wall_time_s": time.perf_counter() - start,
    }
