"""LeRobot policy plugin for action-decoder: `--policy.type=action_decoder`.

LeRobot (0.4.3 to 0.6.x) imports this distribution at start-up (its name starts with
`lerobot_policy_`), which registers `ActionDecoderConfig` under the type `action_decoder`;
its factory then finds `modeling_action_decoder.ActionDecoderPolicy` and
`processor_action_decoder.make_action_decoder_pre_post_processors` by name. LeRobot older than
0.4.3 is refused in one line; a release newer than the tested ones gets a one-line warning.

It also registers a simulated robot for LeRobot's `RobotClient` (`sim_robot`, `--robot.type=action_decoder_sim`);
`serve` is the policy server of `action-decoder serve` (LeRobot's async-inference protocol).

`convert` (batch keys, config mapping) needs only torch and action_decoder. Without LeRobot
installed the package still imports; its LeRobot classes then raise ImportError when used.
"""

from __future__ import annotations

import importlib.util
import re
import warnings

__version__ = "0.1.0"
_LEROBOT_NAMES = ("ActionDecoderConfig", "ActionDecoderPolicy", "make_action_decoder_pre_post_processors", "SimRobot",
                  "SimRobotConfig")
LEROBOT_SUPPORTED = ((0, 4, 3), (0, 7, 0))          # [oldest, first untested release)
LEROBOT_PIN = "lerobot>=0.4.3,<0.7"


def check_lerobot_version(version: str) -> None:
    """Refuse a LeRobot older than 0.4.3 (no plugin discovery, other processor API) in one line; warn in
    one line for a release at or past 0.7 (not run against this plugin)."""
    parts = tuple(int(x) for x in re.findall(r"\d+", str(version))[:3])
    if len(parts) < 2:
        raise ImportError(f"lerobot_policy_action_decoder: cannot read LeRobot's version {version!r}; "
                          f"expected {LEROBOT_PIN}")
    parts += (0,) * (3 - len(parts))
    if parts < LEROBOT_SUPPORTED[0]:
        raise ImportError(f"lerobot_policy_action_decoder: LeRobot {version} is not supported; expected {LEROBOT_PIN} "
                          f"(pip install '{LEROBOT_PIN}')")
    if parts >= LEROBOT_SUPPORTED[1]:
        warnings.warn(f"lerobot_policy_action_decoder: LeRobot {version} is newer than the releases this plugin "
                      f"supports ({LEROBOT_PIN}); its API may differ", stacklevel=2)


if importlib.util.find_spec("lerobot") is not None:
    import lerobot as _lerobot

    check_lerobot_version(getattr(_lerobot, "__version__", "unknown"))
    from .configuration_action_decoder import ActionDecoderConfig
    from .modeling_action_decoder import ActionDecoderPolicy
    from .processor_action_decoder import make_action_decoder_pre_post_processors
    from .sim_robot import SimRobot, SimRobotConfig   # `--robot.type=action_decoder_sim` for RobotClient

    __all__ = list(_LEROBOT_NAMES)
else:
    __all__ = []

    def __getattr__(name: str):
        if name in _LEROBOT_NAMES:
            raise ImportError(f"lerobot_policy_action_decoder.{name}: needs LeRobot (pip install '{LEROBOT_PIN}'); "
                              f"lerobot is not installed in this environment")
        raise AttributeError(f"module 'lerobot_policy_action_decoder' has no attribute {name!r}")
