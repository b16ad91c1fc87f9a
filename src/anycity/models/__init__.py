"""The AnyCity network: VGGT-compatible scaffold, Gaussian head, aerial completion tokens, video prior.

Plain PyTorch; nothing here imports lightning or ``anycity.data``. Entry point: :func:`build_network`.
"""

from anycity.models.anycity import AnyCityNet
from anycity.models.presets import PRESETS, NetConfig, build_network

__all__ = ["AnyCityNet", "NetConfig", "PRESETS", "build_network"]
