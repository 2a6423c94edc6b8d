"""A simulated robot for LeRobot's `RobotClient`: `--robot.type=action_decoder_sim`.

It lets `action-decoder serve` be tried and tested without hardware: the state is `state_dim`
named values `s0, s1, ...`, the action `action_dim` values `a0, a1, ...`; the first
min(state_dim, action_dim) state values integrate the action (gain `gain` per control step), the
rest oscillate slowly. Every action it is sent is kept in `executed`. Registered when LeRobot
imports the plugin (the client's `register_third_party_plugins`), so the client's command line
finds it by name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from lerobot.robots.config import RobotConfig
from lerobot.robots.robot import Robot

NAME = "action_decoder_sim"


@RobotConfig.register_subclass(NAME)
@dataclass
class SimRobotConfig(RobotConfig):
    """The simulated robot's sizes."""

    state_dim: int = 6
    action_dim: int = 3
    gain: float = 0.1

    def __post_init__(self):
        super().__post_init__()
        for name in ("state_dim", "action_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"robot.{name}: expected a positive integer, got {value!r}")


class SimRobot(Robot):
    """`SimRobotConfig`'s robot (module docstring); connect/disconnect only flip a flag."""

    config_class = SimRobotConfig
    name = NAME

    def __init__(self, config: SimRobotConfig):
        super().__init__(config)
        self.config = config
        self.state = [0.1 * ((-1) ** i) * (i + 1) for i in range(config.state_dim)]
        self.executed: list[dict] = []
        self._connected = False

    @property
    def observation_features(self) -> dict:
        return {f"s{i}": float for i in range(self.config.state_dim)}

    @property
    def action_features(self) -> dict:
        return {f"a{i}": float for i in range(self.config.action_dim)}

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict:
        return {f"s{i}": float(v) for i, v in enumerate(self.state)}

    def send_action(self, action: dict) -> dict:
        moved = min(self.config.state_dim, self.config.action_dim)
        for i in range(moved):
            self.state[i] += self.config.gain * float(action[f"a{i}"])
        for i in range(moved, self.config.state_dim):
            self.state[i] = math.sin(len(self.executed) / 10 + i)
        self.executed.append(dict(action))
        return action

    def disconnect(self) -> None:
        self._connected = False
