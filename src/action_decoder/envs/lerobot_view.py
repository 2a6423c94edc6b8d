"""What LeRobot's Meta-World env observes (`lerobot-eval --env.type=metaworld`, LeRobot 0.4.x,
`obs_type="pixels_agent_pos"`), made from one of our Meta-World envs.

- `observation.state`: the agent position, the first 4 entries of the simulator's state (hand
  x, y, z and the gripper opening), float32.
- `observation.image`: the `corner2` camera, moved to (0.75, 0.075, 0.7) as LeRobot moves it,
  rendered by the env's own MuJoCo renderer (gymnasium's, shadows and multisampling as the
  model sets them) at 480 × 480 px and turned by 180° (both axes flipped), uint8 [480, 480, 3].

A policy trained on demonstrations with these features runs under `lerobot-eval` as it was
trained. Rendering at this size with shadows costs about 0.6 s a frame on a CPU (llvmpipe).
"""

from __future__ import annotations

import numpy as np

AGENT_POS_DIM = 4
STATE_NAMES = ["hand_x", "hand_y", "hand_z", "gripper"]
IMAGE_KEY = "observation.image"
CAMERA = "corner2"
CAMERA_POS = (0.75, 0.075, 0.7)
IMAGE_SIZE = 480


def agent_pos(state: np.ndarray) -> np.ndarray:
    """[..., 39] simulator states → [..., 4] LeRobot agent positions (float32)."""
    return np.asarray(state, dtype=np.float32)[..., :AGENT_POS_DIM]


class LeRobotCamera:
    """``rig(env) -> {"observation.image": frame [480, 480, 3] uint8}`` as LeRobot renders it; one
    renderer per env model. ``close()`` frees the GL contexts. Call `envs.render.check_rendering()`
    before the first env is made: ``MUJOCO_GL`` binds when mujoco is imported."""

    def __init__(self, size: int = IMAGE_SIZE):
        self.size = size
        self._renderers: dict[int, object] = {}

    def __call__(self, env) -> dict[str, np.ndarray]:
        u = env.unwrapped
        renderer = self._renderers.get(id(u.model))
        if renderer is None:
            import mujoco
            from gymnasium.envs.mujoco.mujoco_rendering import MujocoRenderer

            cam = mujoco.mj_name2id(u.model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA)
            u.model.cam_pos[cam] = CAMERA_POS
            renderer = self._renderers[id(u.model)] = MujocoRenderer(u.model, u.data, None, self.size, self.size,
                                                                     camera_name=CAMERA)
        frame = renderer.render("rgb_array")                                          # [S, S, 3]
        return {IMAGE_KEY: np.ascontiguousarray(np.flip(frame, (0, 1)))}

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
