"""The Action Expert network and its conditioning prefix."""

from .action_expert import ActionExpert
from .attention import forward_ad_active
from .conditioning import Prefix

__all__ = ["ActionExpert", "Prefix", "forward_ad_active"]
