"""The AnyCity network: VGGT-compatible scaffold, Gaussian head, aerial completion tokens, video prior.

Plain PyTorch; nothing here imports lightning or ``anycity.data``. Entry points: :func:`build_network` (a network of
a preset, random weights) and :func:`load_checkpoint` (the trained network of an ``anycity fit`` checkpoint).
"""

from anycity.models.anycity import AnyCityNet
from anycity.models.presets import PRESETS, NetConfig, build_network
from anycity.models.pretrained import load_checkpoint

__all__ = ["AnyCityNet", "NetConfig", "PRESETS", "build_network", "load_checkpoint"]
