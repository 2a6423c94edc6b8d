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

from ..history import ObservationHistory
from .metaworld_tasks import MAX_EPISODE_STEPS, SeededLayoutEnv, canonical_task, eval_seeds, make_env

_idle_envs: dict[str, list[SeededLayoutEnv]] = {}

PolicyFn = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""``policy_fn(states [B, S] float32, task_index [B] int64) -> actions [B, H, D]`` in env units.

It may also take keywords ``episode_seeds [B]`` (each row's episode seed) and ``plan_indices [B]``
(0 for an episode's first plan, then 1, 2, ...), or ``**kwargs``: then it is given both. With
``rtc=True`` it must take ``prev_chunks [B, L, D]`` and ``delay`` (real-time chunking): the rows
that continue an episode are then planned in their own call, given the previous chunk's actions
for the new chunk's steps 0..L−1. With a ``camera_rig`` it must take ``images`` [B, N_cam, 3, S, S]
uint8: each planning row's env rendered at the observation it plans from, cameras in the rig's order.
With ``n_obs_steps`` n > 1 it is given each row's last n observations, oldest first: ``states [B, n, S]``
and ``images [B, n, N_cam, 3, S, S]`` (an episode's first observation standing in for those before it)."""


def _takes_episode_keys(policy_fn: PolicyFn) -> bool:
    try:
        params = inspect.signature(policy_fn).parameters.values()
    except (TypeError, ValueError):     # a builtin without a signature: the two-argument form
        return False
    return any(p.kind is p.VAR_KEYWORD for p in params) or \
        {"episode_seeds", "plan_indices"} <= {p.name for p in params}


def _takes_keys(policy_fn: PolicyFn, names: set) -> bool:
    try:
        params = inspect.signature(policy_fn).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.kind is p.VAR_KEYWORD for p in params) or names <= {p.name for p in params}


def _takes_rtc_keys(policy_fn: PolicyFn) -> bool:
    return _takes_keys(policy_fn, {"prev_chunks", "delay"})


def camera_images(frames: dict) -> np.ndarray:
    """A rig's ``{camera: [S, S, 3] uint8}`` → [N_cam, 3, S, S] uint8, cameras in the dict's order."""
    return np.stack([np.asarray(f).transpose(2, 0, 1) for f in frames.values()])


def _plan(policy_fn: PolicyFn, states: np.ndarray, task_index: int, needed: int, keys: dict) -> np.ndarray:
    """The whole chunk [B, H, 4], clipped to [-1, 1]; H must cover the `needed` actions."""
    chunk = np.asarray(policy_fn(states, np.full(len(states), task_index, dtype=np.int64), **keys))
    expected = f"[{len(states)}, H >= {needed}, 4]"
    if chunk.ndim != 3 or chunk.shape[0] != len(states) or chunk.shape[2] != 4 or chunk.shape[1] < needed:
        raise ValueError(f"policy_fn output: expected an action chunk of shape {expected}, got {chunk.shape}")
    if not np.isfinite(chunk).all():
        raise ValueError("policy_fn output: expected finite actions, got NaN or Inf")
    return np.clip(chunk, -1.0, 1.0)


def jerk_stats(actions: list, switches: list) -> tuple[float, int, float, int]:
    """Squared jerk |a_k+1 − 2·a_k + a_k−1|² of executed actions (Meta-World's actions are hand
    displacements per step, so their second difference is the hand's jerk): summed over every
    stencil that spans a chunk boundary (the first action of a new chunk at index k: the stencils
    centred at k − 1 and k), and over all stencils. Returns (boundary sum, count, all sum, count)."""
    a = np.asarray(actions, dtype=np.float64).reshape(-1, 4)                  # [T, 4]
    sq = np.square(a[2:] - 2 * a[1:-1] + a[:-2]).sum(-1) if len(a) >= 3 else np.zeros(0)  # [T-2], centred at 1..T-2
    centres = sorted({c for k in switches for c in (k - 1, k) if 1 <= c <= len(a) - 2})
    return float(sum(sq[c - 1] for c in centres)), len(centres), float(sq.sum()), len(sq)


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
    delay: int = 0,
    rtc: bool = False,
    camera_rig: Callable[[SeededLayoutEnv], dict] | None = None,
    n_obs_steps: int = 1,
    layout_seeds: list[int] | None = None,
) -> dict:
    """Run ``episodes`` receding-horizon episodes: execute the first ``n_action_steps``
    actions of each chunk (clipped to [-1, 1]), then re-plan from the new state.

    ``delay`` d simulates inference that takes d control steps. An episode's first chunk is
    planned before it moves and executes its actions 0..s+d−1 (s = ``n_action_steps``). Every
    later chunk is planned from the observation at a re-planning time k, while the env goes on
    executing the old chunk's actions for steps k..k+d−1; the new chunk, whose step j is time
    k + j, takes over at k + d and executes its actions d..d+s−1. So a new plan starts every s
    steps (d ≤ s, s + d ≤ H), and d = 0 is the synchronous loop. With ``rtc`` the new chunk is
    conditioned on the old chunk's remaining actions (``prev_chunks`` = old[s:], the first d of
    them those executed during inference); without it the chunks switch naively.

    ``task_index`` is passed to ``policy_fn`` (multi-task policies), and so are each row's episode seed
    and plan index if it takes them (see ``PolicyFn``); ``progress(done, total, episode, success)`` is
    called after each finished episode: ``done`` finished so far, ``episode`` its index in [0, total).
    ``camera_rig(env) -> {camera: frame [S, S, 3] uint8}`` (``envs.render.CameraObservation``; one
    rig serves every env) renders the observation of each row that plans, passed as ``images``.
    ``n_obs_steps`` n > 1 stacks each env's last n observations (`history.ObservationHistory`, reset
    at each episode start, where the first observation is repeated); the rig then renders the n
    observations up to each plan.
    ``layout_seeds`` (one per episode) replaces the evaluation layouts ``eval_seeds(seed, episodes)``:
    `data.relabel` rolls a policy out on demonstration layouts so.
    ``record=True`` adds ``trajectories``: per episode the hand positions ``[T, 3]`` (obs[0:3]) and
    the goal (obs[36:39]). ``on_step(episode, env)`` is called after each reset and after each step
    of an episode, before the next reset of its env (``envs.render.EpisodeCamera`` films episodes so).
    Returns ``task``, ``success_rate``, and per
    episode ``successes``, ``lengths``, ``returns``, ``seeds``, plus ``env_steps``,
    ``wall_time_s``, ``delay``, ``rtc``, ``boundary_jerk`` (mean squared jerk of the executed
    actions over the stencils that span a chunk switch, ``jerk_stats``; None without switches),
    ``jerk`` (over all stencils), ``boundaries`` (the number of boundary stencils) and
    ``episode_boundary_jerk`` (each episode's own mean, None without a switch).
    """
    name = canonical_task(task)
    for arg, value, low in (("episodes", episodes, 1), ("n_action_steps", n_action_steps, 1), ("num_envs", num_envs, 1),
                            ("n_obs_steps", n_obs_steps, 1)):
        if not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{arg}: expected an integer >= {low}, got {value!r}")
    if not isinstance(max_steps, (int, np.integer)) or not 1 <= max_steps <= MAX_EPISODE_STEPS:
        raise ValueError(f"max_steps: expected an integer in [1, {MAX_EPISODE_STEPS}] (Meta-World's episode cap), got {max_steps!r}")
    if isinstance(delay, bool) or not isinstance(delay, (int, np.integer)) or not 0 <= delay <= n_action_steps:
        raise ValueError(f"delay: expected an integer in [0, n_action_steps={n_action_steps}] (one inference "
                         f"per n_action_steps steps), got {delay!r}")
    if rtc and not _takes_rtc_keys(policy_fn):
        raise ValueError("rtc: expected a policy_fn that takes prev_chunks and delay keywords (see PolicyFn), "
                         f"got {getattr(policy_fn, '__name__', type(policy_fn).__name__)} without them")
    if camera_rig is not None and not _takes_keys(policy_fn, {"images"}):
        raise ValueError("camera_rig: expected a policy_fn that takes an images keyword (see PolicyFn), "
                         f"got {getattr(policy_fn, '__name__', type(policy_fn).__name__)} without it")
    if layout_seeds is not None and (len(layout_seeds) != episodes or
                                     not all(isinstance(x, (int, np.integer)) and x >= 0 for x in layout_seeds)):
        raise ValueError(f"layout_seeds: expected {episodes} integers >= 0 (one per episode), got {layout_seeds!r}")
    envs = _borrow_envs(name, min(num_envs, episodes))

    seeds = eval_seeds(seed, episodes) if layout_seeds is None else [int(x) for x in layout_seeds]
    successes, lengths, returns = [False] * episodes, [0] * episodes, [0.0] * episodes
    hands: list[list[np.ndarray]] = [[] for _ in range(episodes)]
    goals: list[np.ndarray | None] = [None] * episodes
    obs = np.zeros((len(envs), envs[0].observation_space.shape[0]), dtype=np.float32)
    slot_episode = [-1] * len(envs)
    plans: list[np.ndarray | None] = [None] * len(envs)       # actions queued for execution, [n, 4]
    chunks: list[np.ndarray | None] = [None] * len(envs)      # the slot's latest whole chunk [H, 4]
    plan_count = [0] * episodes                 # plans made so far, per episode
    executed: list[list[np.ndarray]] = [[] for _ in range(episodes)]
    switches: list[list[int]] = [[] for _ in range(episodes)]   # step index of each new chunk's first action
    keyed = _takes_episode_keys(policy_fn)
    next_episode, finished, start = 0, 0, time.perf_counter()
    stacking = n_obs_steps > 1
    history = [ObservationHistory(n_obs_steps) for _ in envs] if stacking else []
    stacked: list[dict] = [{} for _ in envs]       # each slot's last n observations, [1, n, ...] per key

    def observe(slot: int) -> None:
        """Push the slot's observation (and its rendered frames, from n steps before its next plan on)."""
        if not stacking:
            return
        stacked[slot].update(history[slot].push({"state": obs[slot][None]}))
        if camera_rig is not None and (plans[slot] is None or len(plans[slot]) - delay < n_obs_steps):
            stacked[slot].update(history[slot].push({"images": camera_images(camera_rig(envs[slot]))[None]}))

    def begin(slot: int) -> None:
        nonlocal next_episode
        slot_episode[slot], plans[slot], chunks[slot] = -1, None, None
        if next_episode < episodes:
            obs[slot] = envs[slot].reset(seed=seeds[next_episode])[0]
            if stacking:
                history[slot].reset()
                observe(slot)
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
        first = [s for s in active if plans[s] is None]
        later = [s for s in active if plans[s] is not None and len(plans[s]) == delay]
        # With RTC the continuing rows carry their previous chunk: planned in a call of their own.
        for group in ([first, later] if rtc else [sorted(first + later)]):
            if not group:
                continue
            eps_now = [slot_episode[s] for s in group]
            keys = {"episode_seeds": np.array([seeds[e] for e in eps_now], dtype=np.int64),
                    "plan_indices": np.array([plan_count[e] for e in eps_now], dtype=np.int64)} if keyed else {}
            if rtc and group is later:
                keys.update(prev_chunks=np.stack([chunks[s][n_action_steps:] for s in group]), delay=int(delay))
            states = obs[group]                                                     # [B, S]
            if stacking:
                states = np.concatenate([stacked[s]["state"] for s in group])          # [B, n, S]
            if camera_rig is not None:
                keys["images"] = np.concatenate([stacked[s]["images"] for s in group]) if stacking else \
                    np.stack([camera_images(camera_rig(envs[s])) for s in group])       # [B, (n,) N, 3, S, S]
            for s, chunk in zip(group, _plan(policy_fn, states, task_index, n_action_steps + delay, keys)):
                if plans[s] is None:                          # an episode's first chunk: planned before it moves
                    plans[s] = chunk[: n_action_steps + delay]
                else:                                         # takes over after the d queued old actions
                    switches[slot_episode[s]].append(lengths[slot_episode[s]] + delay)
                    plans[s] = np.concatenate([plans[s], chunk[delay: delay + n_action_steps]])
                chunks[s] = chunk
            for e in eps_now:
                plan_count[e] += 1
        for s in active:
            ep, action, plans[s] = slot_episode[s], plans[s][0], plans[s][1:]
            executed[ep].append(action)
            obs[s], reward, _, _, info = envs[s].step(action)
            observe(s)
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
    per_episode = np.array([jerk_stats(a, k) for a, k in zip(executed, switches)]).reshape(-1, 4)   # [episodes, 4]
    jerks = per_episode.sum(0)
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
        "delay": int(delay),
        "rtc": bool(rtc),
        "boundary_jerk": float(jerks[0] / jerks[1]) if jerks[1] else None,
        "jerk": float(jerks[2] / jerks[3]) if jerks[3] else None,
        "boundaries": int(jerks[1]),
        "episode_boundary_jerk": [float(b / n) if n else None for b, n in per_episode[:, :2]],
    }
