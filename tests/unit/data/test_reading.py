"""The fast read path: lazy tar members, reduced JPEG decoding, optional stored normals and masks, normals derived
from depth, compact batches."""

import cv2
import numpy as np
import pytest
import torch
import webdataset as wds

from anycity.data import tario
from anycity.data.pipeline import SampleBuilder, _normals_from_depth, make_pipeline, to_float32
from anycity.data.schema import SceneRecord, ViewRecord, decode_normals, encode_normals, encode_scene
from anycity.data.synthetic import synth
from anycity.data.tario import Member, tar_samples
from anycity.data.views import resize_view
from anycity.data.writer import ShardSetWriter, shard_urls
from anycity.geometry import depth_to_normals
from anycity.lit.datamodule import AerialDataModule


def _raise(e):
    raise e


@pytest.mark.parametrize("pread", [True, False], ids=["pread", "seek_read"])
def test_lazy_members_and_truncated_shard(synth_root, tmp_path, monkeypatch, pread):
    """Both read paths: ``os.pread`` and, where it is missing (Windows), seek and read under the shard's lock."""
    if not pread:
        monkeypatch.setattr(tario, "_pread", None)
    url = shard_urls(synth_root, "train")[0]
    sample = next(tar_samples([{"url": url}], handler=_raise))
    assert isinstance(sample["cameras.json"], bytes) and isinstance(sample["000.jpg"], Member)
    ref = next(iter(wds.WebDataset(url, shardshuffle=False)))
    assert sample["__key__"] == ref["__key__"]
    members = [k for k, v in sample.items() if isinstance(v, Member)]
    assert len(members) > 2 and all(sample[k].read() == ref[k] for k in members)
    cut = tmp_path / "train-000000.tar"
    data = open(url, "rb").read()
    cut.write_bytes(data[: data.find(b"cameras.json") - 3000])  # inside the last view's payload
    with pytest.raises(ValueError, match=r"train-000000.tar: member 'x' is truncated \(10 of 100 bytes\)"):
        Member(tario._File(str(cut)), cut.stat().st_size - 10, 100, "x").read()
    with pytest.raises(ValueError, match=r"train-000000.tar.*(truncated|unexpected end)"):
        list(make_pipeline([str(cut)], SampleBuilder(2, 2, 0, (16, 16), train=False), train=False))


def test_reduced_jpeg_decode_matches_full_decode(tmp_path):
    h, w = 96, 128
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([xx * 2, yy * 2, 128 + 60 * np.sin(xx / 9.0) * np.cos(yy / 7.0)], -1).clip(0, 255).astype(np.uint8)
    K = np.array([[90.0, 0, 61.0], [0, 92.0, 50.0], [0, 0, 1]])
    rec = SceneRecord(key="r", views=[ViewRecord(name="a.jpg", image=img, w2c=np.eye(4), K=K, width=w, height=h)
                                      for _ in range(3)], source="t", units="m")
    sample = encode_scene(rec, "test")
    out = SampleBuilder(1, 1, 0, (40, 40), train=False, with_depth=False)(sample)[0]  # decoded at 1/2
    full = cv2.cvtColor(cv2.imdecode(np.frombuffer(sample["000.jpg"], np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    ref, K_ref, *_ = resize_view(full, K, (40, 40))
    got = (out["context"]["images"][0].permute(1, 2, 0).numpy() * 255).round()
    assert np.abs(got - ref.astype(float)).mean() < 2.0  # same pixels up to resampling
    assert np.allclose(out["context"]["K"][0].numpy(), K_ref, atol=1e-5)


def test_mask_written_only_when_informative():
    depth = np.full((8, 8), 3.0, np.float32)
    depth[0] = 0
    v = lambda m: ViewRecord(name="a.png", image=np.zeros((8, 8, 3), np.uint8), w2c=np.eye(4), K=np.eye(3),  # noqa: E731
                             width=8, height=8, depth=depth, mask=m, ext="png")
    s = encode_scene(SceneRecord(key="m", views=[v(depth > 0), v(np.ones((8, 8), bool))], source="t", units="m"),
                     "train")
    assert "000.mask.png" not in s and "001.mask.png" in s


@pytest.fixture(scope="module")
def normals_root(tmp_path_factory):
    out = tmp_path_factory.mktemp("normals")
    synth(out, scenes=1, views=3, size="96x128", seed=1, trajectory="orbit", workers=1, normals=True, aa=False,
          depth_dtype="float32")
    return out


def test_normals_octahedral_roundtrip():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(64, 64, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[0] = 0  # no normal
    c = encode_normals(n)
    assert c.dtype == np.uint8 and c.shape == (64, 64, 2)
    back = decode_normals(c)
    cos = (back[1:] * n[1:]).sum(-1)
    assert np.degrees(np.arccos(cos.clip(-1, 1))).max() < 1.0 and (back[0] == 0).all()


def test_fast_normals_match_geometry_depth_to_normals():
    """The closed-form normals of the data path agree with the reference finite differences of the points."""
    K = torch.tensor([[60.0, 0, 33.0], [0, 62.0, 23.0], [0, 0, 1]])
    H, W = 48, 64
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    rx, ry = (u - 33.0) / 60.0, (v - 23.0) / 62.0
    n_true = torch.tensor([0.3, -0.5, -0.8]) / torch.tensor([0.3, -0.5, -0.8]).norm()
    depth = (-1.0 / (n_true[0] * rx + n_true[1] * ry + n_true[2])) * 10  # plane n.P = 10 seen from the camera
    depth = depth[None, None].float()
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    mask[..., 10, 20] = False
    fast = _normals_from_depth(depth, mask, K[None])[0]
    ref = depth_to_normals(depth[0], K)
    ok = fast.abs().sum(0) > 0
    assert ok.sum() == (H - 2) * (W - 2) - 5  # border and the invalid pixel's 4-neighbourhood are zero
    assert torch.allclose(fast[:, ok], ref[:, ok], atol=1e-4)
    assert torch.allclose(fast[:, ok], n_true[:, None].expand(3, int(ok.sum())), atol=1e-4)


def test_stored_and_derived_normals_agree(normals_root):
    url = shard_urls(normals_root, "train")[0]
    sample = next(iter(wds.WebDataset(url, shardshuffle=False)))
    assert "000.normal.npy" in sample and "000.mask.png" not in sample
    item = SampleBuilder(2, 1, 0, (96, 128), train=False)(sample)[0]
    ctx = item["context"]
    derived = _normals_from_depth(ctx["depth"], ctx["mask"], ctx["K"])
    ok = derived.abs().sum(1) > 0
    cos = (derived * ctx["normal"]).sum(1)[ok]
    # they agree except next to depth discontinuities (central differences straddle them)
    assert ok.float().mean() > 0.5 and cos.median() > 0.999 and (cos > 0.99).float().mean() > 0.6


def test_compact_batches_and_derived_normals(synth_root):
    kw = dict(root=str(synth_root), image_size=(32, 32), num_context=2, num_dense=2, num_targets=2, batch_size=2,
              num_workers=0, epoch_samples=2, seed=4)
    f = next(iter(AerialDataModule(**kw).train_dataloader()))
    dm = AerialDataModule(**kw, compact_batches=True)
    c = next(iter(dm.train_dataloader()))
    assert c.context.images.dtype == torch.uint8 and c.context.depth.dtype == c.target.normal.dtype == torch.float16
    c = dm.on_after_batch_transfer(c, 0)
    assert torch.equal(c.context.images, f.context.images) and torch.equal(c.dense.images, f.dense.images)
    assert c.context.depth.dtype == torch.float32 and torch.equal(c.context.mask, f.context.mask)
    assert torch.allclose(c.context.depth, f.context.depth, rtol=1e-3)
    assert torch.allclose(c.target.normal, f.target.normal, atol=2e-3)
    assert to_float32(f) is f and f.context.images.dtype == torch.float32
    # the fixture stores no normals: they come from depth, unit length where valid and zero elsewhere
    n = f.target.normal
    norm = n.norm(dim=2)
    assert ((norm - 1).abs() < 1e-4)[norm > 0].all() and (norm[~f.target.mask[:, :, 0]] == 0).all()


def test_resampled_single_sample_shard_repeats(tmp_path):
    """The same one-sample shard drawn twice in a row yields two samples (samples never span shards)."""
    with ShardSetWriter(tmp_path) as w:
        w.write(SceneRecord(key="one", views=[ViewRecord(name=f"{i}.png", image=np.full((8, 8, 3), i, np.uint8),
                                                         w2c=np.eye(4), K=np.eye(3), width=8, height=8, ext="png")
                                              for i in range(4)], source="t", units="m"), "train")
    pipe = make_pipeline(shard_urls(tmp_path, "train"), SampleBuilder(1, 1, 0, (8, 8), with_depth=False),
                         train=True, epoch_samples=3, shuffle=0)
    assert [s["scene"] for s in pipe] == ["one"] * 3


def test_derived_normals_are_zero_not_nan_where_there_is_no_depth():
    """rsqrt(0) = inf and 0 x inf = NaN: pixels without depth (sky) got NaN normals, which poisoned any sum of
    ``normal * mask``; they are zero, as the docstring and docs/design.md say."""
    z = torch.zeros(1, 1, 6, 6)
    z[..., 3:, :] = 5.0
    K = torch.tensor([[[10.0, 0, 3], [0, 10, 3], [0, 0, 1]]])
    n = _normals_from_depth(z, z > 0, K)
    assert torch.isfinite(n).all() and (n[..., :4, :] == 0).all()
    depth = np.full((16, 16), 10.0, np.float32)
    depth[:8] = 0.0  # the top half is sky
    views = [ViewRecord(name=f"{i}.png", image=np.full((16, 16, 3), 9 * i, np.uint8), w2c=np.eye(4),
                        K=np.array([[16.0, 0, 8], [0, 16, 8], [0, 0, 1]]), width=16, height=16, depth=depth, ext="png")
             for i in range(3)]
    sample = encode_scene(SceneRecord(key="sky", views=views, source="t", units="m"), "test")
    ctx = SampleBuilder(2, 1, 0, (16, 16), train=False, with_normals=True)(sample)[0]["context"]
    assert torch.isfinite(ctx["normal"]).all() and (ctx["normal"] * ctx["mask"]).sum().isfinite()
    assert (ctx["normal"][:, :, :9] == 0).all() and (ctx["normal"][:, 2, 10:-1, 1:-1] != 0).all()


@pytest.mark.parametrize("size", [10**13, 10**19])
def test_a_member_claiming_more_bytes_than_the_shard_holds_is_a_corrupt_shard(tmp_path, size):
    """A tar header claiming an absurd size: the eager ``cameras.json`` read allocated it (MemoryError at 1e13 bytes,
    OverflowError at 1e19), which neither ``skip_corrupt`` nor the no-sample guard catches. The member is refused
    when its header is read, naming the shard and the member."""
    import tarfile

    info = tarfile.TarInfo("s0.cameras.json")
    info.size = size
    shard = tmp_path / "huge.tar"
    shard.write_bytes(info.tobuf(format=tarfile.PAX_FORMAT) + b'{"a": 1}' + b"\0" * 1024)
    with pytest.raises(ValueError, match=rf"shard .*huge.tar: member 's0.cameras.json' claims {size} bytes at offset "
                                         r"\d+, past the end of the \d+-byte file \(truncated or corrupt\)"):
        list(tario.local_members(str(shard)))
    builder = SampleBuilder(2, 1, 0, (16, 16), train=False)
    with pytest.raises(ValueError, match=r"huge.tar.*member 's0.cameras.json' claims"):
        list(make_pipeline([str(shard)], builder, train=False))
    with pytest.raises(ValueError, match=r"none of the 1 shard\(s\) gives a sample .*huge.tar.*claims"):
        list(make_pipeline([str(shard)], builder, train=False, skip_corrupt=True))


def test_world_from_source_and_scale_map_source_metres_into_the_batch():
    """A record stores cameras in the converter's frame (``p_stored = wfs @ p_source``) and ``metres_per_unit`` of
    that frame; the batch's ``world_from_source`` must take a source point to where the batch cameras see it, and its
    ``scale`` must turn normalised depth back into metres, or exports land in the wrong place and size."""
    from anycity.data.raycast import look_at

    a = np.radians(30)
    wfs = np.eye(4)
    wfs[:3, :3] = 100 * np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    wfs[:3, 3] = [50.0, -20.0, 10.0]  # a similarity of scale 100, as MatrixCity's split files
    mpu, h, w = 0.5, 16, 20
    K = np.array([[20.0, 0, 10], [0, 20.0, 8], [0, 0, 1]])
    rng = np.random.default_rng(0)
    eyes = [[300, 0, 200], [0, 300, 200], [-300, 0, 200], [0, -300, 200]]
    views = [ViewRecord(f"v{i}.png", rng.integers(0, 255, (h, w, 3), dtype=np.uint8), look_at(e, [0, 0, 0]), K, w,
                        h, depth=np.full((h, w), 360.0, np.float32), ext="png") for i, e in enumerate(eyes)]
    rec = SceneRecord("s", views, "t", "metres", metres_per_unit=mpu, world_from_source=wfs)
    item = SampleBuilder(2, 2, 0, (h, w), seed=0)(encode_scene(rec, "train"))[0]

    def pixel(p, w2c, k):  # pinhole projection, written out
        c = w2c[:3, :3] @ p + w2c[:3, 3]
        return (k @ c)[:2] / c[2]

    p_src = np.linalg.solve(wfs, [30.0, -20.0, 10.0, 1.0])  # a source point near the cameras' target
    p_norm = item["world_from_source"].double().numpy() @ p_src
    for g in ("context", "target"):
        for j, i in enumerate(item[g]["index"].tolist()):
            want = pixel((wfs @ p_src)[:3], views[i].w2c, K)
            got = pixel(p_norm[:3], item[g]["w2c"][j].double().numpy(), item[g]["K"][j].double().numpy())
            np.testing.assert_allclose(got, want, atol=1e-3)
    # metres of a normalised unit: the stored depth (360 units of 0.5 m) over the batch's depth (float16 in shards)
    d_norm = item["context"]["depth"][item["context"]["mask"]].double()
    assert float(item["scale"]) == pytest.approx(360 * mpu / float(d_norm.mean()), rel=1e-3)


def _scene(key: str, n: int = 4, hw: int = 16, mask: np.ndarray | None = None) -> SceneRecord:
    """A tiny scene of ``n`` png views at constant depth 10 (``mask`` for each view, if given)."""
    rng = np.random.default_rng(0)
    K = np.array([[16.0, 0, 8.0], [0, 16.0, 8.0], [0, 0, 1]])
    views = []
    for i in range(n):
        w2c = np.eye(4)
        w2c[0, 3] = 0.1 * i
        views.append(ViewRecord(name=f"{i}.png", image=rng.integers(0, 255, (hw, hw, 3), dtype=np.uint8), w2c=w2c,
                                K=K, width=hw, height=hw, depth=np.full((hw, hw), 10.0, np.float32), mask=mask,
                                ext="png"))
    return SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0)


def _shard(folder, keys: list[str]) -> str:
    with ShardSetWriter(folder, maxcount=64, check_views=False) as w:
        for k in keys:
            w.write(_scene(k), "test")
    return shard_urls(folder, "test")[0]


def test_a_corrupt_tar_header_mid_shard_is_an_error_not_the_end_of_the_shard(tmp_path):
    """One flipped bit in the header of a shard's 4th sample: tarfile stopped there quietly, so the rest of the shard
    was dropped with no error and no skip counted. Now it is a ``ValueError`` naming the shard; with ``skip_corrupt``
    the shard's failure is counted once and the samples before it still come out."""
    import tarfile

    from anycity.data.pipeline import SkipCounter, count_samples

    url = _shard(tmp_path, [f"s{i}" for i in range(6)])
    with tarfile.open(url) as t:
        first = next(m for m in t.getmembers() if m.name.startswith("s3."))
    data = bytearray(open(url, "rb").read())
    data[first.offset + 100] ^= 0x01  # the mode field: the header checksum no longer matches
    open(url, "wb").write(bytes(data))
    builder = SampleBuilder(2, 1, 0, (16, 16), train=False, with_normals=False)
    with pytest.raises(ValueError, match=r"test-000000\.tar.*invalid tar header at byte \d+ \(corrupt\)") as e:
        list(make_pipeline([url], builder, train=False))
    assert "\n" not in str(e.value) and str(e.value).count("test-000000.tar") == 1, str(e.value)
    counter = SkipCounter(tmp_path / "skips")
    out = list(make_pipeline([url], builder, train=False, skip_corrupt=True, counter=counter))
    assert [s["scene"] for s in out] == ["s0", "s1", "s2"] and counter.count == 1
    assert count_samples([url]) == 3  # those before the corrupt header


def test_a_member_twice_in_a_shard_is_an_error_naming_the_shard(tmp_path):
    """A shard with a member repeated (``tar -r`` twice, two tars concatenated) raised "corrupt or unreadable shard:
    ('a.000.depth.npy: duplicate file name ...', None, None)", a tuple naming no shard."""
    import io
    import tarfile

    url = _shard(tmp_path, ["a", "b"])
    with tarfile.open(url) as t:
        members = [(m, t.extractfile(m).read()) for m in t.getmembers()]
    bad = tmp_path / "dup.tar"
    with tarfile.open(bad, "w") as out:
        for i, (m, b) in enumerate(members):
            for _ in range(2 if i == 0 else 1):
                out.addfile(m, io.BytesIO(b))
    with pytest.raises(ValueError, match=r"^shard \S*dup\.tar: a\.\S+: duplicate file name in tar file .*re-create "
                                         r"the shard$") as e:
        list(make_pipeline([str(bad)], SampleBuilder(2, 1, 0, (16, 16), train=False), train=False))
    assert "\n" not in str(e.value) and "None" not in str(e.value)


def test_a_stored_mask_is_the_sample_mask():
    """The stored validity mask (here: the left half invalid, at a depth valid everywhere) is what the sample's mask
    says, not depth > 0."""
    mask = np.ones((16, 16), bool)
    mask[:, :8] = False
    s = encode_scene(_scene("m", n=3, mask=mask), "test")
    ctx = SampleBuilder(2, 1, 0, (16, 16), train=False, with_normals=False)(s)[0]["context"]
    assert not ctx["mask"][..., :8].any() and ctx["mask"][..., 8:].all()


def test_each_epoch_draws_its_own_views_reproducibly():
    """A training builder seeds its view draws per epoch: epoch 1 draws other views than epoch 0, and begun again
    it draws the same."""
    b = SampleBuilder(2, 2, 0, (16, 16), seed=0)

    def draws(epoch):
        b.begin_epoch(epoch)
        return [(tuple(s.context), tuple(s.target)) for s in (b.selections(16)[0] for _ in range(3))]

    first, second = draws(0), draws(1)
    assert first != second and draws(1) == second
