"""AnyCity: feed-forward 3D Gaussian Splatting from a few unposed aerial images.

The structures (``Gaussians``, ``RenderOutput``, ``Views``, ``ViewBatch``) and the subpackages (``anycity.models``,
``anycity.render``, ...) load on first use, so ``import anycity`` (and ``anycity --help``) does not import torch.
"""

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"
__all__ = ["Gaussians", "RenderOutput", "Views", "ViewBatch", "__version__"]
# reachable as attributes, imported on first access; not in __all__, so `from anycity import *` stays light. Not
# the Lightning layers (lit, callbacks): tab completion or help(anycity) would import Lightning (5 s); import them
SUBPACKAGES = ("city", "data", "export", "geometry", "losses", "metrics", "models", "render", "viewer")

if TYPE_CHECKING:
    from anycity.structures import Gaussians, RenderOutput, ViewBatch, Views


def __getattr__(name: str):  # the structures (and torch) load on first use, so `anycity --help` starts at once
    if name in __all__:
        from anycity import structures

        return getattr(structures, name)
    if name in SUBPACKAGES:
        return importlib.import_module(f"anycity.{name}")  # the import system also binds it here
    raise AttributeError(f"module 'anycity' has no attribute {name!r}")


def __dir__() -> list[str]:  # dir() and tab completion list the lazy names too
    return sorted({*globals(), *__all__, *SUBPACKAGES})
