"""Meta-World v3 tasks: names, difficulty groups, seeded environments and scripted experts.

Why this module exists: ``gym.make("Meta-World/MT1")`` ignores ``reset(seed=...)`` and
draws each layout from 50 pre-made ones, so "fresh" evaluation layouts can repeat the
training layouts. Here every episode's object/goal layout is drawn from its own seed, and
demonstration seeds and evaluation seeds come from disjoint ranges.
"""

from __future__ import annotations

import functools
import warnings
from typing import Callable

import gymnasium as gym
import numpy as np

PREFIX = "metaworld/"
EVAL_SEED_OFFSET = 1_000_000
"""Demonstration episodes use seeds below this offset, evaluation episodes at or above it."""
SEED_STRIDE = 1_000
"""Layouts per run seed: seed s owns demonstration layouts s·1000 + [0, 1000) and evaluation layouts
EVAL_SEED_OFFSET + s·1000 + [0, 1000), so seeds give disjoint demonstration subsets (seed 0 keeps 0, 1, …)."""
DEMO_SEED_LIMIT = 500_000
"""Demonstration layouts stay below this (RL fine-tuning trains on [500 000, 900 000))."""
MAX_EPISODE_STEPS = 500
"""Meta-World's episode cap (``max_path_length``): stepping past it raises."""

# Difficulty groups of Seo et al. 2022 ("Masked World Models"), used by DP3, MP1 and LeRobot.
TASK_GROUPS: dict[str, tuple[str, ...]] = {
    "medium": tuple(
        f"{t}-v3"
        for t in (
            "basketball", "bin-picking", "box-close", "coffee-pull", "coffee-push", "hammer",
            "peg-insert-side", "push-wall", "soccer", "sweep", "sweep-into",
        )
    ),
    "hard": tuple(
        f"{t}-v3"
        for t in ("assembly", "hand-insert", "pick-out-of-hole", "pick-place", "push", "push-back")
    ),
    "very_hard": tuple(
        f"{t}-v3"
        for t in ("shelf-place", "disassemble", "stick-pull", "stick-push", "pick-place-wall")
    ),
}


@functools.cache
def all_tasks() -> tuple[str, ...]:
    """All 50 Meta-World v3 task names, e.g. ``"push-v3"``."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    return tuple(ALL_V3_ENVIRONMENTS)


@functools.cache
def _groups() -> dict[str, tuple[str, ...]]:
    from metaworld.env_dict import MT10_V3

    hard_groups = {t for group in TASK_GROUPS.values() for t in group}
    easy = tuple(t for t in all_tasks() if t not in hard_groups)
    return {"mt10": tuple(MT10_V3), "easy": easy, **TASK_GROUPS}


def _spelling_help() -> str:
    names = ", ".join(sorted(t.removesuffix("-v3") for t in all_tasks()))
    groups = ", ".join(f"{PREFIX}{g}" for g in ("MT10", "easy", "medium", "hard", "very_hard"))
    return (
        f"expected '{PREFIX}<task>' (optionally with '-v3') with <task> one of: {names}; "
        f"or a group: {groups}; or a comma-separated list of these"
    )


def resolve_tasks(spec: str) -> list[str]:
    """Expand a task spec (``"metaworld/push"``, ``"metaworld/MT10"``, ``"metaworld/hard"``,
    or a comma-separated list of these) into canonical v3 names, in order, without repeats."""
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"task spec must be a non-empty string; {_spelling_help()}; got {spec!r}")
    tasks: list[str] = []
    for item in spec.split(","):
        key = item.strip().lower().removeprefix(PREFIX)
        if key in _groups():
            found = list(_groups()[key])
        elif key in all_tasks() or f"{key}-v3" in all_tasks():
            found = [key if key.endswith("-v3") else f"{key}-v3"]
        else:
            raise ValueError(f"unknown Meta-World task {item.strip()!r} in {spec!r}: {_spelling_help()}")
        tasks += [t for t in found if t not in tasks]
    return tasks


def canonical_task(task: str) -> str:
    """The single v3 task name a spec such as ``"metaworld/push"`` or ``"push-v3"`` denotes."""
    tasks = resolve_tasks(task)
    if len(tasks) != 1:
        raise ValueError(f"task must name a single Meta-World task, got {task!r} ({len(tasks)} tasks)")
    return tasks[0]


def demo_seeds(seed: int, n: int) -> list[int]:
    """Layout seeds of demonstration attempts: ``seed·SEED_STRIDE + k`` for k < n (at most SEED_STRIDE)."""
    if not 0 <= seed < DEMO_SEED_LIMIT // SEED_STRIDE:
        raise ValueError(f"seed: expected 0 <= seed < {DEMO_SEED_LIMIT // SEED_STRIDE} for Meta-World demonstrations "
                         f"(each seed owns {SEED_STRIDE} layouts below {DEMO_SEED_LIMIT}), got {seed}")
    if n > SEED_STRIDE:
        raise ValueError(f"attempts: expected at most {SEED_STRIDE} demonstration attempts per seed (the layouts "
                         f"it owns), got {n}")
    return list(range(seed * SEED_STRIDE, seed * SEED_STRIDE + n))


def eval_seeds(seed: int, n: int) -> list[int]:
    """Layout seeds of evaluation episodes: ``EVAL_SEED_OFFSET + seed·SEED_STRIDE + j`` (beyond
    SEED_STRIDE episodes they run into the next seed's evaluation layouts, never into demonstrations)."""
    if seed < 0:
        raise ValueError(f"seed: expected an integer >= 0, got {seed}")
    start = EVAL_SEED_OFFSET + seed * SEED_STRIDE
    return list(range(start, start + n))


class SeededLayoutEnv(gym.Wrapper):
    """Goal-observable Meta-World env whose ``reset(seed=s)`` draws the layout from ``s``.

    Without a seed, reset continues the env's own random stream (a new layout each time).
    """

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.env.seed(int(seed))
        return self.env.reset()


def make_env(task: str, seed: int | None = None) -> SeededLayoutEnv:
    """Build the goal-observable v3 env of ``task`` with per-episode re-randomised layouts.

    ``seed`` seeds construction and the layout of the first ``reset()``; pass
    ``reset(seed=...)`` to pick each episode's layout.
    """
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

    name = canonical_task(task)
    if seed is None:  # a fresh seed still keeps construction off numpy's global RNG
        seed = int(np.random.SeedSequence().generate_state(1)[0])
    env = ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE[f"{name}-goal-observable"](seed=seed)
    env._freeze_rand_vec = False  # re-draw the layout at every reset ...
    env.seeded_rand_vec = True  # ... from env.np_random, which reset(seed=...) re-seeds
    env.seed(seed)
    return SeededLayoutEnv(env)


def save_state(env: SeededLayoutEnv) -> tuple:
    """Everything a Meta-World env's next steps depend on: MuJoCo's integration state and the
    env's own step state (the previous frame it stacks into obs, the step count)."""
    import mujoco

    u = env.unwrapped
    physics = np.empty(mujoco.mj_stateSize(u.model, mujoco.mjtState.mjSTATE_INTEGRATION))
    mujoco.mj_getState(u.model, u.data, physics, mujoco.mjtState.mjSTATE_INTEGRATION)
    last = None if u._last_stable_obs is None else u._last_stable_obs.copy()
    return physics, u._prev_obs.copy(), u.curr_path_length, u._did_see_sim_exception, last


def restore_state(env: SeededLayoutEnv, state: tuple) -> None:
    """Put ``env`` back where ``save_state`` found it (lookahead rollouts during recording)."""
    import mujoco

    u = env.unwrapped
    physics, prev_obs, steps, unstable, last = state
    mujoco.mj_setState(u.model, u.data, physics, mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(u.model, u.data)
    u._prev_obs, u.curr_path_length, u._did_see_sim_exception = prev_obs.copy(), steps, unstable
    u._last_stable_obs = None if last is None else last.copy()


def expert_policy(task: str) -> Callable[[np.ndarray], np.ndarray]:
    """Meta-World's scripted expert as ``obs [39] or [B, 39] -> action [4] or [B, 4]``.

    Actions are clipped to [-1, 1] (the env clips anyway; the raw expert overshoots).
    """
    from metaworld.policies import ENV_POLICY_MAP

    policy = ENV_POLICY_MAP[canonical_task(task)]()

    def act(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the experts warn on every out-of-range action
            actions = np.stack([policy.get_action(o) for o in obs.reshape(-1, obs.shape[-1])])
        return np.clip(actions, -1.0, 1.0).astype(np.float32).reshape(*obs.shape[:-1], -1)

    return act
