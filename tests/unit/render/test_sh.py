"""Spherical harmonics: orthonormal real basis (degree 0-4) and the colour convention."""

import math

import pytest
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



_RP = math.sqrt(math.pi)
# Real SH normalisation constants in closed form (sqrt((2l+1)/4pi * (l-m)!/(l+m)!) times the Legendre factors),
# with the signs of Inria 3DGS (utils/sh_utils.py) and gsplat.
_C = (
    (1 / (2 * _RP),),
    (math.sqrt(3) / (2 * _RP),),
    (math.sqrt(15) / (2 * _RP), -math.sqrt(15) / (2 * _RP), math.sqrt(5) / (4 * _RP), -math.sqrt(15) / (2 * _RP),
     math.sqrt(15) / (4 * _RP)),
    (-math.sqrt(35 / 2) / (4 * _RP), math.sqrt(105) / (2 * _RP), -math.sqrt(21 / 2) / (4 * _RP),
     math.sqrt(7) / (4 * _RP), -math.sqrt(21 / 2) / (4 * _RP), math.sqrt(105) / (4 * _RP),
     -math.sqrt(35 / 2) / (4 * _RP)),
    (3 * math.sqrt(35) / (4 * _RP), -3 * math.sqrt(35 / 2) / (4 * _RP), 3 * math.sqrt(5) / (4 * _RP),
     -3 * math.sqrt(5 / 2) / (4 * _RP), 3 / (16 * _RP), -3 * math.sqrt(5 / 2) / (4 * _RP),
     3 * math.sqrt(5) / (8 * _RP), -3 * math.sqrt(35 / 2) / (4 * _RP), 3 * math.sqrt(35) / (16 * _RP)),
)
# The literal values gsplat and Inria ship.
_LITERAL = (
    (0.28209479177387814,),
    (0.4886025119029199,),
    (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396),
    (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
     1.445305721320277, -0.5900435899266435),
    (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892, 0.10578554691520431,
     -0.6690465435572892, 0.47308734787878004, -1.7701307697799304, 0.6258357354491761),
)


def _inria_basis(d):
    """The basis to degree 4 at one unit direction, written out as Inria's eval_sh and gsplat's kernels do."""
    x, y, z = d
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    (c0,), (c1,), c2, c3, c4 = _C
    return [
        c0,
        -c1 * y, c1 * z, -c1 * x,
        c2[0] * xy, c2[1] * yz, c2[2] * (2 * zz - xx - yy), c2[3] * xz, c2[4] * (xx - yy),
        c3[0] * y * (3 * xx - yy), c3[1] * xy * z, c3[2] * y * (4 * zz - xx - yy),
        c3[3] * z * (2 * zz - 3 * xx - 3 * yy), c3[4] * x * (4 * zz - xx - yy), c3[5] * z * (xx - yy),
        c3[6] * x * (xx - 3 * yy),
        c4[0] * xy * (xx - yy), c4[1] * yz * (3 * xx - yy), c4[2] * xy * (7 * zz - 1), c4[3] * yz * (7 * zz - 3),
        c4[4] * (zz * (35 * zz - 30) + 3), c4[5] * xz * (7 * zz - 3), c4[6] * (xx - yy) * (7 * zz - 1),
        c4[7] * xz * (xx - 3 * yy), c4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)),
    ]


def test_basis_values_and_signs_match_inria_and_gsplat():
    """Each basis function at three fixed directions, sign by sign: an orthonormal basis with one sign or constant
    wrong still passes the Gram test, but renders every gsplat/Inria-trained (or exported) PLY with wrong colours."""
    for closed, literal in zip(_C, _LITERAL):
        assert closed == pytest.approx(literal, rel=1e-14)
    dirs = [(1 / 3, 2 / 3, 2 / 3), (2 / 7, -3 / 7, 6 / 7), (-4 / 9, 4 / 9, -7 / 9)]  # exact unit vectors
    expected = torch.tensor([_inria_basis(d) for d in dirs], dtype=torch.float64)
    d = torch.tensor(dirs, dtype=torch.float64)
    for degree in range(5):
        torch.testing.assert_close(sh_basis(d, degree), expected[:, : (degree + 1) ** 2], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("degree", [-1, 5])
def test_degrees_outside_0_to_4_are_refused(degree):
    """Only degrees 0..4 have a basis; -1 or 5 is refused in one line rather than returning a truncated basis."""
    with pytest.raises(ValueError, match="sh degree: expected 0..4"):
        sh_basis(torch.tensor([[0.0, 0.0, 1.0]]), degree)
