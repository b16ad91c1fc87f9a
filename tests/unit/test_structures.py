"""Containers validate shapes, dtypes, devices and finiteness with messages that name the field."""

from __future__ import annotations

import pytest
import torch

from anycity.structures import IMAGE_MIN, Gaussians, RenderOutput, ViewBatch, Views, image_range, sh_degree_from_k


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
    ("sh", torch.zeros(2, 5, 1, 1), r"^gaussians.sh: expected shape \[B, N, K, 3\] with B=2, N=5, got \(2, 5, 1, 1\)$"),
    ("quats", torch.zeros(2, 5, 4, device="meta"), "^gaussians.quats: on meta, but means are on cpu$"),
    ("valid", torch.ones(2, 5), "bool"),
    ("valid", torch.ones(2, 4, dtype=torch.bool), "valid"),
    ("opacities", torch.tensor([[float("nan")] * 5] * 2), "NaN"),
    ("means", torch.zeros(2, 5, 3).index_fill(2, torch.tensor([1]), float("inf")), "means: contains NaN"),
    ("sh", torch.zeros(2, 5, 4, 3).index_fill(1, torch.tensor([4]), -float("inf")), "sh: contains NaN"),
    ("opacities", torch.ones(2, 5).index_fill(1, torch.tensor([2]), float("inf")), "opacities: contains NaN"),
    # activated opacities only: the backends disagree outside [0, 1]
    ("opacities", torch.ones(2, 5).index_fill(1, torch.tensor([2]), 1.25),
     r"gaussians.opacities: expected values in \[0, 1\], got \[1, 1.25\]; apply sigmoid"),
    ("opacities", torch.zeros(2, 5).index_fill(1, torch.tensor([0]), -0.5), r"opacities: expected values in \[0, 1\]"),
])
def test_gaussians_validate_errors(field, value, match):
    kwargs = vars(gaussians())
    kwargs[field] = value
    with pytest.raises(ValueError, match=match):
        Gaussians(**kwargs).validate()


def test_gaussians_opacities_at_the_ends_of_their_range_validate():
    for value in (0.0, 1.0):
        for dtype in (torch.float32, torch.float64, torch.bfloat16, torch.float16):
            Gaussians(**{**vars(gaussians()), "opacities": torch.full((2, 5), value)}).to(dtype=dtype).validate()
    Gaussians(torch.zeros(2, 0, 3), torch.ones(2, 0, 4), torch.ones(2, 0, 3), torch.ones(2, 0),
              torch.zeros(2, 0, 1, 3)).validate()  # no Gaussians: nothing to range-check


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


@pytest.mark.parametrize("fields, match", [
    ({"means": torch.zeros(2, 5, 3, dtype=torch.long)}, "means: expected a floating-point dtype"),
    ({"means": torch.zeros(2, 5, 3, dtype=torch.float64)}, "quats: expected dtype torch.float64 like means"),
    ({"sh": torch.zeros(2, 5, 4, 3, dtype=torch.float64)}, "sh: expected dtype torch.float32 like means"),
    ({"quats": torch.ones(2, 5, 4, dtype=torch.long)}, "quats: expected dtype"),
    ({"opacities": torch.ones(2, 5, dtype=torch.bool)}, "opacities: expected dtype"),
])
def test_gaussians_validate_refuses_mixed_or_integer_dtypes(fields, match):
    # the renderer failed on these with an unexplained RuntimeError
    with pytest.raises(ValueError, match=match):
        Gaussians(**{**vars(gaussians()), **fields}).validate()


def test_gaussians_validate_accepts_one_dtype_and_low_precision_fields():
    gaussians().to(dtype=torch.float64).validate()
    gaussians().to(dtype=torch.bfloat16).validate()
    # a mixed-precision head: render() upcasts float16/bfloat16 fields to float32
    Gaussians(**{**vars(gaussians()), "sh": torch.zeros(2, 5, 4, 3, dtype=torch.bfloat16)}).validate()
    Gaussians(**{**vars(gaussians()), "means": torch.zeros(2, 5, 3, dtype=torch.float16)}).validate()


def views(B=2, V=3, **kw):
    v = Views(torch.zeros(B, V, 3, 8, 8), torch.eye(4).repeat(B, V, 1, 1), torch.eye(3).repeat(B, V, 1, 1),
              depth=torch.ones(B, V, 1, 8, 8), mask=torch.ones(B, V, 1, 8, 8, dtype=torch.bool),
              normal=torch.zeros(B, V, 3, 8, 8), index=torch.zeros(B, V, dtype=torch.long))
    for k, val in kw.items():
        setattr(v, k, val)
    return v


def batch(**kw):
    fields = dict(context=views(), target=views(V=2), dense=views(V=4), scene=["a", "b"], scale=torch.ones(2),
                  world_from_source=torch.eye(4).repeat(2, 1, 1))
    return ViewBatch(**{**fields, **kw})


@pytest.mark.parametrize("fields, match", [
    ({"target": views(B=1)}, "batch.target: expected B=2"),
    ({"dense": views(B=3)}, "batch.dense: expected B=2"),
    ({"scale": torch.ones(5)}, r"batch.scale: expected shape \[B\]"),
    ({"scale": torch.ones(2, 1)}, "batch.scale"),
    ({"world_from_source": torch.eye(3)}, r"batch.world_from_source: expected shape \[B, 4, 4\]"),
    ({"world_from_source": torch.eye(4)}, "batch.world_from_source"),
    ({"scene": ["a"] * 7}, "batch.scene: expected 2 scene names"),
    ({"context": views(mask=torch.ones(2, 3, 1, 8, 8))}, "batch.context.mask: expected dtype bool"),
    ({"context": views(images=torch.zeros(2, 3, 3, 8, 8, dtype=torch.long))}, "batch.context.images: expected float"),
    ({"target": views(V=2, images=torch.zeros(2, 2, 3, 8, 8, dtype=torch.uint8))}, "batch.target.images"),
    ({"context": views(index=torch.zeros(2, 3))}, "batch.context.index: expected an integer dtype"),
    ({"context": views(depth=torch.ones(2, 3, 1, 8, 8, dtype=torch.long))}, "batch.context.depth"),
    ({"dense": views(V=4, w2c=torch.eye(4, dtype=torch.long).repeat(2, 4, 1, 1))}, "batch.dense.w2c"),
])
def test_view_batch_validate_refuses_inconsistent_batches(fields, match):
    with pytest.raises(ValueError, match=match):
        batch(**fields).validate()


def test_view_batch_validate_accepts_batches_and_the_compact_form_when_asked():
    assert batch().validate().batch_size == 2
    batch(dense=None, scene=None, scale=None, world_from_source=None).validate()
    compact = batch(context=views(images=torch.zeros(2, 3, 3, 8, 8, dtype=torch.uint8),
                                  depth=torch.ones(2, 3, 1, 8, 8, dtype=torch.float16)))
    compact.validate(compact=True)
    with pytest.raises(ValueError, match="batch.context.images"):
        compact.validate()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
def test_gaussians_validate_refuses_log_scales(dtype):
    # graphdeco's raw (log) scales rendered as huge blobs, and save_ply then dropped every such row
    g = Gaussians(**{**vars(gaussians()), "scales": torch.full((2, 5, 3), 0.05).index_fill(1, torch.tensor([3]), -3.0)})
    with pytest.raises(ValueError, match=r"gaussians.scales: expected standard deviations >= 0, got a minimum of -3; "
                                         r"these look like log-scales .*: pass scales.exp\(\)"):
        g.to(dtype=dtype).validate()


def test_gaussians_validate_refuses_a_slightly_negative_scale():
    """Any negative standard deviation is refused, however small: there is no tolerance below 0."""
    scales = torch.full((2, 5, 3), 0.1)
    scales[0, 0, 0] = -1e-4
    with pytest.raises(ValueError, match="^gaussians.scales: expected standard deviations >= 0, got a minimum of "
                                         "-0.0001;"):
        Gaussians(**{**vars(gaussians()), "scales": scales}).validate()


def test_image_range_flags_images_just_below_the_rounding_allowance():
    """[0, 1] images may dip to IMAGE_MIN (a resize's rounding); just below it they read as [-1, 1] ("signed"),
    below -1 as mean/std-normalised, and the callers refuse both."""
    def fault(lo):
        return image_range(torch.tensor([lo, 0.5, 1.0], dtype=torch.float64))[2]

    assert fault(0.0) is None and fault(IMAGE_MIN) is None
    assert fault(2 * IMAGE_MIN) == "signed" and fault(-0.01) == "signed" and fault(-1.0) == "signed"
    assert fault(-1.5) == "normalised"


def test_gaussians_validate_keeps_zero_scales_and_zero_quaternions():
    # the network's softplus scales underflow to 0 for logits below about -104, and its quaternion normalisation
    # keeps a zero raw quaternion zero; every training render validates, so neither may be refused
    g = Gaussians(**{**vars(gaussians()), "scales": torch.zeros(2, 5, 3), "quats": torch.zeros(2, 5, 4)})
    g.validate()
    Gaussians(**{**vars(gaussians()), "scales": torch.full((2, 5, 3), -0.0)}).validate()


def test_gaussians_validate_waits_for_the_device_once(monkeypatch):
    """Every render validates its Gaussians; on a GPU each read of a value waits for the queued work. The finiteness
    of every field and the opacity and scale ranges come back in one read (there were five)."""
    g = gaussians(2, 50)
    g.valid = torch.ones(2, 50, dtype=torch.bool)
    reads = []
    for name in ("tolist", "item", "__bool__", "__float__"):
        real = getattr(torch.Tensor, name)
        monkeypatch.setattr(torch.Tensor, name, lambda t, *a, _real=real, _n=name: reads.append(_n) or _real(t, *a))
    g.validate()
    assert reads == ["tolist"]
