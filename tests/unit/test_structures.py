"""Containers validate shapes, dtypes, devices and finiteness with messages that name the field."""

from __future__ import annotations

import pytest
import torch

from anycity.structures import Gaussians, RenderOutput, ViewBatch, Views, sh_degree_from_k


def gaussians(B=2, N=5, K=4):
    return Gaussians(torch.zeros(B, N, 3), torch.ones(B, N, 4), torch.ones(B, N, 3), torch.ones(B, N),
                     torch.zeros(B, N, K, 3))


def test_gaussians_validate_and_properties():
    g = gaussians().validate()
    assert (g.batch_size, g.num_gaussians, g.sh_degree) == (2, 5, 1)
    g64 = g.to(dtype=torch.float64)
    assert g64.means.dtype == torch.float64
    masked = Gaussians(**{**vars(g), "valid": torch.ones(2, 5, dtype=torch.bool)})
    assert masked.to(dtype=torch.float64).valid.dtype == torch.bool


@pytest.mark.parametrize("field, value, match", [
    ("means", torch.zeros(2, 5, 2), "means"),
    ("quats", torch.zeros(2, 5, 3), "quats"),
    ("scales", torch.zeros(2, 4, 3), "scales"),
    ("opacities", torch.zeros(2, 5, 1), "opacities"),
    ("sh", torch.zeros(2, 5, 3, 3), "K=3"),
    ("sh", torch.zeros(2, 5, 4), "sh"),
    ("valid", torch.ones(2, 5), "bool"),
    ("valid", torch.ones(2, 4, dtype=torch.bool), "valid"),
    ("opacities", torch.tensor([[float("nan")] * 5] * 2), "NaN"),
    ("means", torch.zeros(2, 5, 3).index_fill(2, torch.tensor([1]), float("inf")), "means: contains NaN"),
    ("sh", torch.zeros(2, 5, 4, 3).index_fill(1, torch.tensor([4]), -float("inf")), "sh: contains NaN"),
])
def test_gaussians_validate_errors(field, value, match):
    kwargs = vars(gaussians())
    kwargs[field] = value
    with pytest.raises(ValueError, match=match):
        Gaussians(**kwargs).validate()


def test_gaussians_whose_finite_values_overflow_a_sum_validate():
    # the finiteness check sums first; a sum that overflows must not make finite values look corrupt
    g = gaussians()
    g.means = torch.full_like(g.means, 3e38)
    g.validate()


def test_sh_degree_from_k():
    assert [sh_degree_from_k(k) for k in (1, 4, 9, 16, 25)] == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError):
        sh_degree_from_k(5)


def test_render_output_and_views_validate():
    RenderOutput(torch.zeros(1, 2, 3, 4, 5), torch.zeros(1, 2, 1, 4, 5), torch.zeros(1, 2, 1, 4, 5)).validate()
    with pytest.raises(ValueError, match="render.depth"):
        RenderOutput(torch.zeros(1, 2, 3, 4, 5), torch.zeros(1, 2, 1, 4, 4), torch.zeros(1, 2, 1, 4, 5)).validate()
    v = Views(torch.zeros(1, 3, 3, 8, 8), torch.eye(4).repeat(1, 3, 1, 1), torch.eye(3).repeat(1, 3, 1, 1))
    batch = ViewBatch(context=v, target=v).validate()
    assert batch.batch_size == 1 and v.num_views == 3 and v.hw == (8, 8)
    bad = Views(torch.zeros(1, 3, 3, 8, 8), torch.eye(4).repeat(1, 2, 1, 1), torch.eye(3).repeat(1, 3, 1, 1))
    with pytest.raises(ValueError, match="batch.target.w2c"):
        ViewBatch(context=v, target=bad).validate()
