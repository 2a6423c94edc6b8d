"""Meta-World tasks with reproducible layouts, scripted experts and closed-loop evaluation."""

from .evaluate import evaluate
from .metaworld_tasks import (
    EVAL_SEED_OFFSET,
    MAX_EPISODE_STEPS,
    TASK_GROUPS,
    SeededLayoutEnv,
    all_tasks,
    canonical_task,
    demo_seeds,
    eval_seeds,
    expert_policy,
    make_env,
    resolve_tasks,
    restore_state,
    save_state,
)

__all__ = [
    "EVAL_SEED_OFFSET",
    "MAX_EPISODE_STEPS",
    "TASK_GROUPS",
    "SeededLayoutEnv",
    "all_tasks",
    "canonical_task",
    "demo_seeds",
    "eval_seeds",
    "evaluate",
    "expert_policy",
    "make_env",
    "resolve_tasks",
    "restore_state",
    "save_state",
]
