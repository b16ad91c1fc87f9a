"""AnyCity: feed-forward 3D Gaussian Splatting from a few unposed aerial images."""

from anycity.structures import Gaussians, RenderOutput, ViewBatch, Views

__version__ = "0.1.0"
__all__ = ["Gaussians", "RenderOutput", "Views", "ViewBatch", "__version__"]
