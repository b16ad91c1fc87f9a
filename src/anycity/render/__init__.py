"""Differentiable 3D Gaussian rasterisation (gsplat semantics) for CPU and CUDA."""

from anycity.render.api import render, resolve_backend
from anycity.render.sh import eval_sh, sh_basis

__all__ = ["render", "resolve_backend", "eval_sh", "sh_basis"]
