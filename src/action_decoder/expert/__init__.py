"""The Action Expert network and its conditioning prefix."""

from .action_expert import ActionExpert
from .attention import forward_ad_active
from .conditioning import Prefix
from .image_encoder import ImageEncoder

__all__ = ["ActionExpert", "ImageEncoder", "Prefix", "forward_ad_active"]
