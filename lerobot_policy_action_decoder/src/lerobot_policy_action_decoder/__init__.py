"""LeRobot policy plugin for action-decoder: `--policy.type=action_decoder`.

LeRobot (>= 0.4.3) imports this distribution at start-up (its name starts with
`lerobot_policy_`), which registers `ActionDecoderConfig` under the type `action_decoder`;
its factory then finds `modeling_action_decoder.ActionDecoderPolicy` and
`processor_action_decoder.make_action_decoder_pre_post_processors` by name.

It also registers a simulated robot for LeRobot's `RobotClient` (`sim_robot`, `--robot.type=action_decoder_sim`);
`serve` is the policy server of `action-decoder serve` (LeRobot's async-inference protocol).

`convert` (batch keys, config mapping) needs only torch and action_decoder. Without LeRobot
installed the package still imports; its LeRobot classes then raise ImportError when used.
"""

from __future__ import annotations

import importlib.util

__version__ = "0.1.0"
_LEROBOT_NAMES = ("ActionDecoderConfig", "ActionDecoderPolicy", "make_action_decoder_pre_post_processors", "SimRobot",
                  "SimRobotConfig")

if importlib.util.find_spec("lerobot") is not None:
    from .configuration_action_decoder import ActionDecoderConfig
    from .modeling_action_decoder import ActionDecoderPolicy
    from .processor_action_decoder import make_action_decoder_pre_post_processors
    from .sim_robot import SimRobot, SimRobotConfig   # `--robot.type=action_decoder_sim` for RobotClient

    __all__ = list(_LEROBOT_NAMES)
else:
    __all__ = []

    def __getattr__(name: str):
        if name in _LEROBOT_NAMES:
            raise ImportError(f"lerobot_policy_action_decoder.{name}: needs LeRobot (pip install 'lerobot==0.4.4'); "
                              f"lerobot is not installed in this environment")
        raise AttributeError(f"module 'lerobot_policy_action_decoder' has no attribute {name!r}")
