"""A 2-D point mass that must pass a disc obstacle above or below to reach a goal.

A closed-loop task whose demonstrations are genuinely bimodal: the scripted expert picks one side
per episode, 50/50, and the state does not say which. Start, obstacle and goal lie on the x axis,
so the layout is mirror-symmetric and nothing in the state breaks the tie; the obstacle sits close
to the start, so the side is decided within the first executed chunk (`N_ACTION_STEPS` actions),
and averaging the two routes drives straight into it. Observation `[6]`: position, goal, obstacle
centre; action `[2]`: a velocity command in [−1, 1]² that moves the point by `SPEED` per step.
Success: within `GOAL_TOL` of the goal without ever entering the obstacle (radius `RADIUS`);
a collision ends the episode.
"""

from __future__ import annotations

from typing import Optional

import gymnasium as gym
import numpy as np
import torch

RADIUS = 0.3            # obstacle radius
MARGIN = 0.3            # the expert's waypoint clears the obstacle by this much
SPEED = 0.08            # distance per step at |action| = 1
GOAL_TOL = 0.1
MAX_STEPS = 60          # the expert needs about 30
N_ACTION_STEPS = 8      # actions executed per chunk in closed loop before re-planning
OBS_DIM, ACTION_DIM = 6, 2


class ObstacleRoutesEnv(gym.Env):
    """Start near (−1, 0), obstacle near (−0.45, 0), goal near (1, 0), all on the x axis; layouts
    (the three x positions) from `reset(seed=)`."""

    observation_space = gym.spaces.Box(-2.0, 2.0, (OBS_DIM,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def reset(self, *, seed: Optional[int] = None, options=None):
        super().reset(seed=seed)
        u = self.np_random.uniform(-1.0, 1.0, 3)
        self.pos = np.array([-1.0 + 0.05 * u[0], 0.0])
        self.center = np.array([-0.45 + 0.05 * u[1], 0.0])
        self.goal = np.array([1.0 + 0.1 * u[2], 0.0])
        self.steps, self.route = 0, None     # route: +1 passed above, −1 below (set once past x = 0)
        return self.obs(), {}

    def obs(self) -> np.ndarray:
        return np.concatenate([self.pos, self.goal, self.center]).astype(np.float32)

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(ACTION_DIM), -1.0, 1.0)
        self.pos = self.pos + SPEED * a
        self.steps += 1
        if self.route is None and self.pos[0] >= self.center[0]:
            self.route = 1 if self.pos[1] > self.center[1] else -1
        collided = bool(np.linalg.norm(self.pos - self.center) < RADIUS)
        success = bool(not collided and np.linalg.norm(self.pos - self.goal) < GOAL_TOL)
        info = {"success": success, "collided": collided, "route": self.route}
        return self.obs(), float(success), success or collided, self.steps >= MAX_STEPS, info


def expert_action(obs: np.ndarray, side: int) -> np.ndarray:
    """The scripted expert's action [2] for observation [6], passing above (side = +1) or below (−1):
    head for the waypoint beside the obstacle until past its centre, then for the goal."""
    pos, goal, center = obs[:2], obs[2:4], obs[4:6]
    target = goal if pos[0] >= center[0] - 0.02 else center + np.array([0.0, side * (RADIUS + MARGIN)])
    d = (target - pos) / SPEED
    return (d / max(1.0, float(np.linalg.norm(d)))).astype(np.float32)


def expert_episode(seed: int, side: int, horizon: int = 16):
    """One expert episode: (observations [T, 6], action chunks [T, horizon, 2], success).

    Each chunk is the expert's next `horizon` actions from that frame, simulated past the episode's
    end when needed (the expert holds still at the goal), so no chunk is padded."""
    env = ObstacleRoutesEnv()
    obs, _ = env.reset(seed=seed)
    observations, actions, success = [], [], False
    for _ in range(MAX_STEPS + horizon):
        a = expert_action(obs, side)
        if len(observations) < MAX_STEPS and not success:
            observations.append(obs)
        actions.append(a)
        obs, _, done, _, info = env.step(a)
        success = success or info["success"]
        if info["collided"]:
            break
        if success and len(actions) >= len(observations) + horizon:
            break
    chunks = np.stack([np.stack(actions[i:i + horizon]) for i in range(len(observations))])
    return np.stack(observations), chunks, success


def expert_dataset(episodes: int, seed: int = 0, horizon: int = 16):
    """Demonstrations from layouts seed·10⁴ + i, the side drawn 50/50 per episode:
    (states [N, 6], chunks [N, horizon, 2]) as float32 tensors."""
    rng = np.random.default_rng(seed)
    states, chunks = [], []
    for i in range(episodes):
        s, c, _ = expert_episode(seed * 10_000 + i, int(rng.choice([-1, 1])), horizon)
        states.append(s)
        chunks.append(c)
    return torch.from_numpy(np.concatenate(states)), torch.from_numpy(np.concatenate(chunks))


def rollout(act, seed: int, n_action_steps: int = N_ACTION_STEPS) -> dict:
    """One closed-loop episode on layout `seed`: `act(obs [6]) -> chunk [H, 2]` is called every
    `n_action_steps` actions. Returns success, collision and the side it passed (+1, −1 or None)."""
    env = ObstacleRoutesEnv()
    obs, _ = env.reset(seed=seed)
    info = {"success": False, "collided": False, "route": None}
    done = truncated = False
    while not (done or truncated):
        chunk = act(obs)
        for a in chunk[:n_action_steps]:
            obs, _, done, truncated, info = env.step(a)
            if done or truncated:
                break
    return {"success": info["success"], "collided": info["collided"], "route": info["route"]}
