"""Remote shards (``pipe:``, ``file:``, ``http://``): read like local ones, with the local reader's checks, and their
failures named in one line."""

import http.server
import shutil
import threading
from functools import partial

import pytest

from anycity.data.pipeline import SampleBuilder, SkipCounter, make_pipeline
from anycity.data.tario import is_url
from anycity.lit.datamodule import AerialDataModule

from .test_reading import _shard


def _keys(urls, skip_corrupt=False, counter=None):
    builder = SampleBuilder(2, 1, 0, (16, 16), train=False, with_normals=False)
    return [s["scene"] for s in make_pipeline(urls, builder, train=False, skip_corrupt=skip_corrupt,
                                              counter=counter)]


@pytest.fixture
def shard(tmp_path):
    return _shard(tmp_path, [f"s{i}" for i in range(5)])


def test_a_pipe_or_file_url_reads_every_sample_with_no_skip(shard, tmp_path):
    """webdataset's end-of-shard marker ``{}`` became ``{"url": ...}``: every remote shard then counted as a corrupt
    sample skipped (``skip_corrupt``) or stopped the run (without it)."""
    local = _keys([shard])
    assert local == [f"s{i}" for i in range(5)]
    for url in (f"pipe:cat {shard}", f"file:{shard}"):
        assert _keys([url]) == local
        counter = SkipCounter(tmp_path / "skips")
        assert _keys([url], skip_corrupt=True, counter=counter) == local and counter.count == 0


def _cut_after_member(shard: str, out) -> str:
    """``shard`` cut just after its 3rd sample's last member: no end-of-archive block."""
    import tarfile

    with tarfile.open(shard) as t:
        m = [m for m in t.getmembers() if m.name.startswith("s2.")][-1]
    data = open(shard, "rb").read()
    out.write_bytes(data[: m.offset_data + -(-m.size // 512) * 512])
    return str(out)


def test_a_shard_cut_after_a_member_is_an_error_not_a_shorter_shard(shard, tmp_path):
    """tarfile stops quietly at the end of a file that has no end-of-archive block: a shard cut at a member's end
    lost its other samples with no error and no skip counted, locally and remotely."""
    cut = _cut_after_member(shard, tmp_path / "cut.tar")
    for url in (cut, f"pipe:cat {cut}"):
        with pytest.raises(ValueError, match=r"cut\.tar.*without the end-of-archive block \(truncated"):
            _keys([url])
        counter = SkipCounter(tmp_path / f"skips{len(url)}")
        assert _keys([url], skip_corrupt=True, counter=counter) == ["s0", "s1", "s2"] and counter.count == 1


def test_a_corrupt_header_in_a_remote_shard_is_an_error(shard, tmp_path):
    import tarfile

    with tarfile.open(shard) as t:
        first = next(m for m in t.getmembers() if m.name.startswith("s3."))
    data = bytearray(open(shard, "rb").read())
    data[first.offset + 100] ^= 0x01
    bad = tmp_path / "bad.tar"
    bad.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"^shard pipe:cat \S+bad\.tar: .*invalid tar header at byte \d+ \(corrupt"):
        _keys([f"pipe:cat {bad}"])


def test_a_failing_pipe_is_one_line_naming_its_status(tmp_path):
    url = f"pipe:cat {tmp_path}/missing.tar"
    with pytest.raises(ValueError, match=r"^shard pipe:cat \S+missing\.tar: .*exited with status 1; check the URL"
                       ) as e:
        _keys([url])
    assert "\n" not in str(e.value) and "<" not in str(e.value)


@pytest.mark.timeout(120)  # the old code drew the failing URL forever
def test_a_training_stream_whose_remote_shards_all_fail_stops(tmp_path):
    """The remote branch told the no-sample guard nothing: a resampled training stream of failing URLs (with
    ``skip_corrupt``) drew them forever instead of stopping."""
    builder = SampleBuilder(2, 1, 0, (16, 16), train=True, with_normals=False)
    pipe = make_pipeline([f"pipe:cat {tmp_path}/gone.tar"], builder, train=True, epoch_samples=4,
                         skip_corrupt=True, counter=SkipCounter(tmp_path / "skips"))
    with pytest.raises(ValueError, match=r"none of the 1 shard\(s\) gives a sample .*gone\.tar"):
        next(iter(pipe))


@pytest.mark.skipif(shutil.which("curl") is None, reason="webdataset reads http:// with curl")
def test_http_shards_and_a_404(shard, tmp_path):
    folder = str(tmp_path)
    handler = partial(http.server.SimpleHTTPRequestHandler, directory=folder)
    handler.log_message = lambda *a: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        base = f"http://127.0.0.1:{server.server_address[1]}"
        rel = shard.removeprefix(folder)
        assert _keys([base + rel]) == [f"s{i}" for i in range(5)]
        with pytest.raises(ValueError, match=r"nope\.tar: .*curl exit 22: the server answered with an HTTP error"):
            _keys([f"{base}/nope.tar"])
    finally:
        server.shutdown()
        server.server_close()


def test_urls_are_told_from_paths(shard):
    assert all(is_url(u) for u in ("http://h/a.tar", "pipe:cat a.tar", "file:a.tar", "s3://b/a.tar"))
    assert not any(is_url(p) for p in ("shards/a.tar", "C:\\shards\\a.tar", "/abs/a-{000..001}.tar"))
    # a pipe: spec as data.root was refused as a missing folder
    AerialDataModule(root=f"pipe:cat {shard}", val_shards=[f"pipe:cat {shard}"])
