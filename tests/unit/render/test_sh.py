"""Spherical harmonics: orthonormal real basis (degree 0-4) and the colour convention."""

import torch

from anycity.render.sh import C0, eval_sh, sh_basis


def test_basis_is_orthonormal_on_the_sphere():
    # Fibonacci sphere quadrature: ∫ Y_i Y_j dΩ ≈ 4π/n Σ = δ_ij.
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = torch.pi * (1 + 5**0.5) * i
    d = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], -1)
    Y = sh_basis(d, 4)
    gram = 4 * torch.pi / n * Y.T @ Y
    torch.testing.assert_close(gram, torch.eye(25, dtype=torch.float64), atol=2e-3, rtol=0)


def test_degree_zero_colour_and_clamp():
    sh = torch.tensor([[[1.0, -10.0, 0.0]]])
    c = eval_sh(sh, None)
    torch.testing.assert_close(c, torch.tensor([[C0 + 0.5, 0.0, 0.5]]))
    d = torch.nn.functional.normalize(torch.randn(1, 3), dim=-1)
    sh4 = torch.cat([sh, torch.zeros(1, 3, 3)], 1)
    torch.testing.assert_close(eval_sh(sh4, d), c)  # higher bands at zero change nothing
