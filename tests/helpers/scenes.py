"""Small random Gaussian scenes and cameras shared by the renderer tests (CPU and GPU)."""

from __future__ import annotations

import math

import torch

from anycity.geometry import make_intrinsics
from anycity.structures import Gaussians, Views

F64 = torch.float64


def make_gaussians(B=1, N=80, K=1, seed=0, dtype=F64, z=4.0, spread=(1.0, 0.7, 0.5), scale=(0.01, 0.2)):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(B, N, 3, generator=g, dtype=dtype) * torch.tensor(spread, dtype=dtype)
    means[..., 2] += z
    return Gaussians(
        means=means,
        quats=torch.randn(B, N, 4, generator=g, dtype=dtype),
        scales=scale[0] + (scale[1] - scale[0]) * torch.rand(B, N, 3, generator=g, dtype=dtype),
        opacities=0.05 + 0.9 * torch.rand(B, N, generator=g, dtype=dtype),
        sh=0.5 * torch.randn(B, N, K, 3, generator=g, dtype=dtype),
    )


def make_cameras(B=1, V=1, width=40, height=32, dtype=F64, seed=1):
    """V different cameras per scene: small rotations and translations around a look-down-+z camera."""
    g = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4, dtype=dtype).repeat(B, V, 1, 1)
    for b in range(B):
        for v in range(V):
            ang = 0.15 * torch.randn(3, generator=g, dtype=dtype)
            c0, s0, c1, s1 = math.cos(ang[0]), math.sin(ang[0]), math.cos(ang[1]), math.sin(ang[1])
            Rx = torch.tensor([[1, 0, 0], [0, c0, -s0], [0, s0, c0]], dtype=dtype)
            Ry = torch.tensor([[c1, 0, s1], [0, 1, 0], [-s1, 0, c1]], dtype=dtype)
            w2c[b, v, :3, :3] = Rx @ Ry
            w2c[b, v, :3, 3] = 0.3 * torch.randn(3, generator=g, dtype=dtype)
    f = 1.1 * width
    K = torch.tensor([[f, 0, width / 2 + 1.3], [0, 1.05 * f, height / 2 - 0.7], [0, 0, 1]], dtype=dtype)
    return w2c, K.repeat(B, V, 1, 1)


def make_views(n, seed, index=None, plane=None, size=32):
    """``n`` random ``size`` x ``size`` views of one batch stepping 0.1 along x (fx = fy = 30, centred principal
    point), depth in [1, 2) or ``plane`` everywhere, all pixels valid; ``index``: their positions in the scene."""
    g = torch.Generator().manual_seed(seed)
    w2c = torch.eye(4).repeat(1, n, 1, 1)
    w2c[..., 0, 3] = torch.linspace(0, 0.3, n)
    K = make_intrinsics(30.0, 30.0, size / 2, size / 2).expand(1, n, 3, 3).clone()
    images = torch.rand(1, n, 3, size, size, generator=g)
    depth = torch.rand(1, n, 1, size, size, generator=g) + 1 if plane is None else torch.full((1, n, 1, size, size),
                                                                                               float(plane))
    return Views(images=images, w2c=w2c, K=K, depth=depth, mask=torch.ones(1, n, 1, size, size, dtype=torch.bool),
                 index=None if index is None else torch.tensor([index]))
