"""AnyCity: feed-forward 3D Gaussian Splatting from a few unposed aerial images."""

from typing import TYPE_CHECKING

__version__ = "0.1.0"
__all__ = ["Gaussians", "RenderOutput", "Views", "ViewBatch", "__version__"]

if TYPE_CHECKING:
    from anycity.structures import Gaussians, RenderOutput, ViewBatch, Views


def __getattr__(name: str):  # the structures (and torch) load on first use, so `anycity --help` starts at once
    if name in __all__:
        from anycity import structures

        return getattr(structures, name)
    raise AttributeError(f"module 'anycity' has no attribute {name!r}")
