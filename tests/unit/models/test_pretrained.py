"""VGGT/AnySplat checkpoint compatibility: key names and shapes, exact sizes, the loader's report."""

import re
from pathlib import Path

import pytest
import torch

from anycity.models import build_network
from anycity.models.pretrained import load_pretrained

KEYS_TSV = Path(__file__).with_name("vggt_keys.tsv")  # from instantiating upstream VGGT() @ 44b3afb
OURS_ONLY = {"gaussian_head.offset_conv.weight", "gaussian_head.offset_conv.bias"}  # zero-initialised centre offsets


def _expected_keys() -> dict[str, tuple[tuple[int, ...], int]]:
    out = {}
    for line in KEYS_TSV.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, shape, count = line.split("\t")
        if name.startswith(("point_head.", "track_head.")):
            continue  # VGGT heads AnyCity does not use
        name = name.replace("encoder.gaussian_param_head.", "gaussian_head.")
        out[name] = (tuple(int(s) for s in re.findall(r"\d+", shape)), int(count[1:]))
    return out


@pytest.fixture(scope="module")
def meta_1b():
    with torch.device("meta"):
        return build_network("vggt-1b")


def test_vggt_1b_keys_and_shapes_match_checkpoint(meta_1b):
    ours: dict[str, list] = {}
    for k, v in meta_1b.state_dict().items():
        if k.startswith(("aggregator.", "camera_head.", "depth_head.", "gaussian_head.")):
            kk = re.sub(r"(blocks|trunk)\.\d+\.", r"\1.N.", k)
            entry = ours.setdefault(kk, [tuple(v.shape), 0])
            assert entry[0] == tuple(v.shape), k
            entry[1] += 1
    expected = _expected_keys()
    assert set(ours) == set(expected) | OURS_ONLY
    for k, (shape, count) in expected.items():
        assert tuple(ours[k]) == (shape, count), k


def test_vggt_1b_exact_sizes(meta_1b):
    def count(m):
        return sum(p.numel() for p in m.parameters())

    assert count(meta_1b.aggregator) == 909_112_320
    assert count(meta_1b.camera_head) == 216_174_610
    assert count(meta_1b.depth_head) == 32_654_562
    assert round(count(meta_1b.aggregator.patch_embed) / 1e6, 2) == 304.37
    assert meta_1b.head_layers == (4, 11, 17, 23)


def test_vggt_1b_layer_norm_eps_match_vggt(meta_1b):
    # VGGT's aggregator blocks (qk-norm included) use nn.LayerNorm's 1e-5, its DINOv2 patch embed 1e-6
    agg = meta_1b.aggregator
    blocks = [*agg.frame_blocks, *agg.global_blocks]
    assert {m.eps for b in blocks for m in b.modules() if isinstance(m, torch.nn.LayerNorm)} == {1e-5}
    assert all(isinstance(b.attn.q_norm, torch.nn.LayerNorm) for b in blocks)
    assert {m.eps for m in agg.patch_embed.modules() if isinstance(m, torch.nn.LayerNorm)} == {1e-6}


def test_load_vggt_state_dict_reports_and_copies(tmp_path):
    torch.manual_seed(0)
    src, dst = build_network("tiny", completion=False), build_network("tiny")
    sd = {k: v for k, v in src.state_dict().items() if not k.startswith("gaussian_head.")}
    sd["point_head.norm.weight"] = torch.ones(3)  # present in VGGT checkpoints, no counterpart here
    sd["depth_head.norm.bias"] = torch.zeros(7)  # wrong shape: skipped, never crashes
    path = tmp_path / "model.pt"
    torch.save(sd, path)
    rep = load_pretrained(dst, path, kind="vggt")
    assert rep.unexpected == ["point_head.norm.weight"]
    assert rep.mismatched == [("depth_head.norm.bias", (7,), tuple(dst.depth_head.norm.bias.shape))]
    assert rep.loaded == sorted(set(sd) - {"point_head.norm.weight", "depth_head.norm.bias"})  # what was copied
    assert {k.split(".")[0] for k in rep.missing} == {"gaussian_head", "completion", "video_prior"}
    assert torch.equal(dst.aggregator.frame_blocks[0].attn.qkv.weight, src.aggregator.frame_blocks[0].attn.qkv.weight)
    assert "unexpected: point_head.* x1" in rep.summary()


def test_the_report_names_shape_mismatches_and_counts_them_apart_from_missing():
    """The printed report said only 'shape mismatches: 2' (no key, no shapes), and counted those keys as missing
    too although the file had them: AnySplat weights into another SH degree read 'missing: gaussian_head.* x4'."""
    torch.manual_seed(0)
    src, dst = build_network("tiny", completion=False, sh_degree=0), build_network("tiny", completion=False)
    sd = {k: v for k, v in src.state_dict().items() if k not in OURS_ONLY}
    rep = load_pretrained(dst, sd, kind="vggt")
    assert rep.missing == sorted(OURS_ONLY)
    w, b = "gaussian_head.scratch.output_conv2.2.weight", "gaussian_head.scratch.output_conv2.2.bias"
    n_w, n_b = list(dst.state_dict()[w].shape), list(dst.state_dict()[b].shape)
    assert rep.summary().endswith(f"; missing: gaussian_head.* x2; unexpected: none; shape mismatches: 2 ({w} file "
                                  f"{list(src.state_dict()[w].shape)} vs net {n_w}, {b} file "
                                  f"{list(src.state_dict()[b].shape)} vs net {n_b}; skipped, left as built)")
    sd.update({k: torch.zeros(1) for k in ("depth_head.norm.bias", "depth_head.norm.weight", "camera_head.x")})
    sd["camera_head.embed_pose.weight"] = torch.zeros(1)
    many = load_pretrained(build_network("tiny", completion=False), sd, kind="vggt").summary()
    assert "shape mismatches: 5 (" in many and many.endswith(", +2 more; skipped, left as built)")
    assert many.count(" vs net ") == 3 and "\n" not in many


def test_load_anysplat_lightning_checkpoint(tmp_path):
    torch.manual_seed(0)
    src, dst = build_network("tiny", completion=False), build_network("tiny", completion=False)
    sd = {}
    for k, v in src.state_dict().items():
        if k in OURS_ONLY:
            continue  # an AnySplat checkpoint has no centre-offset conv
        k = k.replace("gaussian_head.", "gaussian_param_head.")
        sd[f"model.encoder.{k}"] = v.to(torch.bfloat16)
    sd["model.encoder.distill_camera_head.embed_pose.weight"] = torch.zeros(2, 2)
    path = tmp_path / "anysplat.ckpt"
    torch.save({"state_dict": sd, "epoch": 3}, path)
    rep = load_pretrained(dst, path, kind="anysplat")
    assert rep.missing == sorted(OURS_ONLY) and rep.unexpected == ["distill_camera_head.embed_pose.weight"]
    assert not dst.gaussian_head.offset_conv.weight.any() and not dst.gaussian_head.offset_conv.bias.any()
    w = src.gaussian_head.input_merger[0].weight
    assert torch.allclose(dst.gaussian_head.input_merger[0].weight, w.to(torch.bfloat16).float())


def test_load_errors(tmp_path):
    net = build_network("tiny", completion=False)
    with pytest.raises(FileNotFoundError, match="not found"):
        load_pretrained(net, tmp_path / "missing.pt")
    with pytest.raises(ValueError, match="kind"):
        load_pretrained(net, {}, kind="dust3r")


@pytest.mark.parametrize("state", [{"aggregator.camera_token": [1.0, 2.0]}, {"unused": "text"}, {5: torch.zeros(1)}])
def test_a_state_dict_of_anything_but_named_tensors_is_one_line_naming_the_file_and_key(tmp_path, state):
    """A list under a real key raised a raw AttributeError ('list' object has no attribute 'shape') in the loader,
    and in the Stage II gap check, which reads every value's shape."""
    from anycity.lit.refinement import pretrained_scaffold_gaps
    from anycity.models.pretrained import read_state_dict

    net = build_network("tiny", completion=False)
    path = tmp_path / "nontensor.pt"
    torch.save({"state_dict": state}, path)
    key = repr(next(iter(state)))
    for load in (lambda: load_pretrained(net, path), lambda: read_state_dict(path),
                 lambda: pretrained_scaffold_gaps(net, str(path), "vggt")):
        with pytest.raises(ValueError, match=f"pretrained weights: {re.escape(str(path))} holds a .* under the key "
                                             f"{re.escape(key)}, expected a state dict of named tensors") as e:
            load()
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="pretrained weights: the state dict holds a"):
        load_pretrained(net, state)


def test_weights_for_another_preset_are_one_line_not_a_random_backbone(tmp_path, caplog):
    """The Lightning modules dropped the load report: VGGT weights given to another preset skipped every mismatched
    tensor and trained a random backbone with nothing said. Now the whole aggregator must load (heads may differ),
    and the report is printed."""
    from anycity.lit import ScaffoldModule

    torch.manual_seed(0)
    path = tmp_path / "model.pt"
    torch.save(build_network("tiny", completion=False, embed_dim=32, num_heads=2).state_dict(), path)
    with pytest.raises(ValueError, match="model.pretrained: .*model.pt does not fit this network's backbone: .*"
                                         "aggregator shapes differ \\(e.g. aggregator.camera_token: \\[1, 2, 1, 32\\] "
                                         "there, \\[1, 2, 1, 64\\] here\\).*model.preset") as e:
        ScaffoldModule(preset="tiny", pretrained=str(path))
    assert "\n" not in str(e.value)
    shallow = {k: v for k, v in build_network("tiny", completion=False).state_dict().items()
               if not k.startswith("aggregator.global_blocks.3.")}
    torch.save(shallow, path)
    with pytest.raises(ValueError, match="aggregator weights are not in it \\(e.g. aggregator.global_blocks.3"):
        ScaffoldModule(preset="tiny", pretrained=str(path))
    # heads may differ: another SH degree reshapes the Gaussian head's last conv, the backbone still loads
    src = build_network("tiny", completion=False, sh_degree=0)
    torch.save(src.state_dict(), path)
    with caplog.at_level("INFO"):
        m = ScaffoldModule(preset="tiny", pretrained=str(path))
    assert torch.equal(m.net.aggregator.camera_token, src.aggregator.camera_token)
    assert "shape mismatches: 2" in caplog.text and str(path) in caplog.text


def _anysplat_layout(sd: dict) -> dict:
    """Our scaffold's tensors under AnySplat's names (``encoder.``, ``gaussian_param_head.``)."""
    out = {f"encoder.{k}": v for k, v in sd.items() if k.startswith(("aggregator.", "camera_head.", "depth_head."))}
    out.update({f"encoder.gaussian_param_head.{k[len('gaussian_head.'):]}": v for k, v in sd.items()
                if k.startswith("gaussian_head.") and k not in OURS_ONLY})
    return out


def test_a_file_of_another_layout_names_the_real_cause(tmp_path):
    """An AnySplat file read as VGGT, or our own Lightning checkpoint passed as pretrained, was told to 'build the
    preset the weights were made for', which cannot help. load_pretrained now refuses such a file itself, as none of
    it loads (test_load_pretrained_refuses_a_file_of_which_nothing_loads); require_backbone still names the layout
    that most of a partly loaded file's unused keys have."""
    from anycity.models.pretrained import LoadReport

    absent = ["aggregator.camera_token"]
    rep = LoadReport(loaded=["camera_head.x"], missing=absent, unexpected=["encoder.a", "encoder.b", "other"])
    with pytest.raises(ValueError, match=r"^model.pretrained: anysplat.pt does not fit .*2 of its keys start with "
                                         r"'encoder.'; this is an AnySplat checkpoint: set "
                                         r"model.init_args.pretrained_kind: anysplat$"):
        rep.require_backbone("anysplat.pt")
    rep = LoadReport(loaded=["camera_head.x"], missing=absent, unexpected=["net.a", "net.b"])
    with pytest.raises(ValueError, match=r"this is an anycity checkpoint: pass it as --ckpt_path \(resume/test\) "
                                         r"or model.init_args.init_from \(Stage II\)$"):
        rep.require_backbone("last.ckpt")
    vggt = build_network("tiny", embed_dim=32, num_heads=2).state_dict()
    with pytest.raises(ValueError, match=r"build the preset the weights were made for"):  # another preset: as before
        load_pretrained(build_network("tiny"), vggt).require_backbone("model.pt")


def test_anysplat_kind_on_a_vggt_file_is_refused_not_a_silent_decode_switch(tmp_path):
    """kind='anysplat' on a plain VGGT file loaded it and switched the focal decode to AnySplat's (fx off by 0.2 %)."""
    src = build_network("tiny").state_dict()
    vggt = {k: v for k, v in src.items() if k.startswith(("aggregator.", "camera_head.", "depth_head."))}
    torch.save(vggt, path := tmp_path / "model.pt")
    net = build_network("tiny")
    with pytest.raises(ValueError, match=r"^pretrained weights: .*model.pt is a VGGT file .*; use "
                                         r"model.init_args.pretrained_kind: vggt$"):
        load_pretrained(net, path, kind="anysplat")
    assert net.cfg.focal_decode == "vggt"
    load_pretrained(net, _anysplat_layout(src), kind="anysplat").require_backbone("anysplat")
    assert net.cfg.focal_decode == "anysplat"  # a real AnySplat file still switches


def test_a_truncated_safetensors_file_is_one_line(tmp_path):
    """An interrupted download raised safetensors' own SafetensorError: a traceback in the CLI."""
    from safetensors.torch import save_file

    path = tmp_path / "model.safetensors"
    save_file({"aggregator.camera_token": torch.zeros(1, 2, 1, 64)}, str(path))
    path.write_bytes(path.read_bytes()[:-64])
    with pytest.raises(ValueError, match=r"^cannot read pretrained weights .*model.safetensors: .*; the file looks "
                                         r"truncated or corrupt \(re-download it\)$") as e:
        load_pretrained(build_network("tiny"), path)
    assert "\n" not in str(e.value)


def test_a_folder_reads_its_one_weights_file(tmp_path):
    """A downloaded snapshot folder was reported as 'not found'."""
    from safetensors.torch import save_file

    src = build_network("tiny", completion=False)
    save_file({k: v.contiguous() for k, v in src.state_dict().items()}, str(tmp_path / "model.safetensors"))
    (tmp_path / "config.json").write_text("{}")
    net = build_network("tiny")
    rep = load_pretrained(net, tmp_path)
    rep.require_backbone(tmp_path)
    assert torch.equal(net.aggregator.camera_token, src.aggregator.camera_token)
    assert f"read {tmp_path / 'model.safetensors'}; loaded" in str(rep)
    torch.save({"step": torch.zeros(1)}, tmp_path / "optimizer.pt")  # model.safetensors is still the one
    assert load_pretrained(build_network("tiny"), tmp_path).loaded == rep.loaded
    (tmp_path / "model.safetensors").rename(tmp_path / "a.safetensors")
    with pytest.raises(ValueError, match=r"^pretrained weights: .* is a folder; pass the weights file inside it "
                                         r"\(candidates: a.safetensors, optimizer.pt\)$"):
        load_pretrained(build_network("tiny"), tmp_path)
    (empty := tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match=r"is a folder with no weights file .* in it"):
        load_pretrained(build_network("tiny"), empty)


def test_loading_into_a_network_on_the_meta_device_is_refused():
    """It reported every tensor loaded and left them all on meta (load_state_dict copies nothing there)."""
    sd = build_network("tiny", completion=False).state_dict()
    with torch.device("meta"):
        net = build_network("tiny")
    with pytest.raises(ValueError, match=r"^pretrained weights: the network is on the meta device .*; build the "
                                         r"network on a real device \(cpu/cuda\) first$"):
        load_pretrained(net, sd)


def _lightning_ckpt(path: Path, module, class_path: str | None, net: dict | None) -> dict:
    """``module`` saved as Lightning saves it (its ``on_save_checkpoint`` hook included). ``class_path``: the
    hyperparameters LightningCLI records (the config's ``net``, ``_class_path``); None: ``save_hyperparameters``'s."""
    import lightning

    hp = dict(module.hparams)
    if class_path is not None:
        hp.update(net=net, _class_path=class_path)
    ckpt = {"pytorch-lightning_version": lightning.__version__, "epoch": 0, "global_step": 1,
            "state_dict": module.state_dict(), "optimizer_states": [], "hyper_parameters": hp}
    module.on_save_checkpoint(ckpt)
    torch.save(ckpt, path)
    return ckpt


def _trained(module):
    """``module`` with every weight moved off its init (the zero-initialised completion residual included)."""
    torch.manual_seed(1)
    with torch.no_grad():
        for p in module.net.parameters():
            p.add_(torch.randn_like(p) * 0.02)
    return module.eval()


@pytest.mark.parametrize("stage, class_path", [
    ("stage1", "anycity.lit.ScaffoldModule"), ("stage1", None),
    ("stage1-with-old-branch", "anycity.lit.ScaffoldModule"), ("stage2", "anycity.lit.RefinementModule"),
    ("stage2", None)])
def test_load_checkpoint_gives_the_trained_network_of_a_lightning_checkpoint(tmp_path, stage, class_path):
    """There was no way to load an anycity checkpoint as a plain network: load_pretrained loaded 0 of its tensors
    (the 'net.' prefix), and by hand build_network('tiny') missed the stored net options (camera_trunk_depth: 2) and
    a Stage I checkpoint needed completion=False, which only the module class implies."""
    from anycity.lit import RefinementModule, ScaffoldModule
    from anycity.models import load_checkpoint

    torch.manual_seed(0)
    net = {"camera_trunk_depth": 2}
    m = _trained(ScaffoldModule(net=net) if stage.startswith("stage1") else RefinementModule(net=net))
    path = tmp_path / "last.ckpt"
    ckpt = _lightning_ckpt(path, m, class_path, net)
    if stage == "stage1-with-old-branch":  # written before Stage I stopped building the (untrained) branch
        old = build_network("tiny", **net).state_dict()
        ckpt["state_dict"].update({f"net.{k}": v for k, v in old.items() if k.startswith(("completion.", "video_"))})
        torch.save(ckpt, path)
    loaded = load_checkpoint(path)
    assert type(loaded).__name__ == "AnyCityNet" and not loaded.training
    assert loaded.cfg == m.net.cfg and (loaded.completion is None) == stage.startswith("stage1")
    images = torch.rand(1, 3, 3, 32, 24)
    with torch.inference_mode():
        ours, theirs = loaded(images), m.net(images)
    for key in ("w2c", "K", "depth", "offset"):
        assert torch.equal(ours[key], theirs[key]), key
    for field in ("means", "scales", "quats", "opacities", "sh"):
        assert torch.equal(getattr(ours["gaussians"], field), getattr(theirs["gaussians"], field)), field


def test_load_checkpoint_of_a_stage2_with_a_pose_prior_needs_no_prior_file(tmp_path):
    """The pose prior's weights travel in the checkpoint; its file (hyper_parameters) may be gone."""
    from anycity.lit import RefinementModule
    from anycity.models import load_checkpoint

    torch.manual_seed(0)
    net = {"refine_cameras": True, "pose_prior": "random"}
    m = _trained(RefinementModule(net=net))
    _lightning_ckpt(path := tmp_path / "last.ckpt", m, "anycity.lit.RefinementModule",
                    {**net, "pose_prior": str(tmp_path / "moved_away.pt")})
    images = torch.rand(1, 2, 3, 32, 32)
    with torch.inference_mode():
        assert torch.equal(load_checkpoint(path)(images)["w2c"], m.net(images)["w2c"])


def test_load_checkpoint_refuses_what_is_not_an_anycity_training_checkpoint_in_one_line(tmp_path):
    from anycity.lit import ScaffoldModule
    from anycity.models import load_checkpoint

    torch.manual_seed(0)
    plain = tmp_path / "model.pt"
    torch.save(build_network("tiny", completion=False).state_dict(), plain)
    other = tmp_path / "pose_prior.ckpt"
    torch.save({"state_dict": {"net.mlp.0.weight": torch.zeros(2, 2)}, "hyper_parameters": {"channels": 48}}, other)
    ckpt = _lightning_ckpt(misfit := tmp_path / "misfit.ckpt", ScaffoldModule(net={"camera_trunk_depth": 2}),
                           "anycity.lit.ScaffoldModule", {"camera_trunk_depth": 2})
    ckpt["hyper_parameters"]["net"] = {}  # the stored network is not the one these weights were trained in
    torch.save(ckpt, misfit)
    ckpt["hyper_parameters"]["net"] = {"old_net_key": 3}
    torch.save(ckpt, newer := tmp_path / "newer.ckpt")
    for path, match in [
        (plain, r"not an anycity training checkpoint \(a plain state dict \(VGGT/AnySplat weights\?\), no "
                r"state_dict\); load VGGT/AnySplat weights with load_pretrained\(build_network\(preset\), path"),
        (other, r"not an anycity training checkpoint \(its hyper_parameters hold no network preset\); pass the "
                r"last.ckpt"),
        (misfit, r"does not fit the network its hyper_parameters describe: \d+ of its weights have no place \(e.g. "
                 r"camera_head.trunk.1.\S+\); pass a checkpoint"),
        (newer, r"build_network: unknown option\(s\) \['old_net_key'\].* \(written by another anycity version\?\)$"),
    ]:
        with pytest.raises(ValueError, match=rf"^checkpoint {re.escape(str(path))}:? .*{match}") as e:
            load_checkpoint(path)
        assert "\n" not in str(e.value)
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_checkpoint(tmp_path / "missing.ckpt")


def test_load_pretrained_refuses_a_file_of_which_nothing_loads(tmp_path):
    """load_pretrained on anycity's own last.ckpt loaded 0 tensors ('unexpected: net.* x512'), raised nothing and
    left the network random."""
    src = build_network("tiny").state_dict()
    torch.save({"state_dict": {f"net.{k}": v for k, v in src.items()}, "hyper_parameters": {"preset": "tiny"}},
               ours := tmp_path / "last.ckpt")
    torch.save({"other.weight": torch.zeros(3)}, unrelated := tmp_path / "unrelated.pt")
    torch.save(_anysplat_layout(src), anysplat := tmp_path / "anysplat.pt")
    for path, kind, match in [
        (ours, "vggt", r"is an anycity training checkpoint \(\d+ of its \d+ tensors start with 'net.'\), not "
                       r"VGGT/AnySplat weights; load it with anycity.models.load_checkpoint\(path\), or on the command "
                       r"line pass it as --ckpt_path \(resume/test\) or model.init_args.init_from \(Stage II\)$"),
        (ours, "anysplat", r"is an anycity training checkpoint"),
        (unrelated, "vggt", r"loaded 0 of its 1 tensors \(kind='vggt'\); none of its names is this network's \(e.g. "
                            r"other.weight\); pass VGGT or AnySplat weights$"),
        (anysplat, "vggt", r"loaded 0 of its \d+ tensors \(kind='vggt'\); it is an AnySplat checkpoint: use "
                           r"kind='anysplat' \(model.init_args.pretrained_kind: anysplat\)$"),
    ]:
        net = build_network("tiny")
        before = {k: v.clone() for k, v in net.state_dict().items()}
        with pytest.raises(ValueError, match=rf"^pretrained weights: {re.escape(str(path))} {match}") as e:
            load_pretrained(net, path, kind=kind)
        assert "\n" not in str(e.value)
        assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    with pytest.raises(ValueError, match=r"^pretrained weights: the state dict holds no tensors"):
        load_pretrained(build_network("tiny"), {})


def test_an_anysplat_file_with_extra_top_level_keys_still_switches_the_focal_decode():
    """One key outside AnySplat's encoder (its decoder's background) must not hide that the file is AnySplat's."""
    net = build_network("tiny")
    sd = _anysplat_layout(build_network("tiny").state_dict())
    sd["decoder.background"] = torch.zeros(3)
    rep = load_pretrained(net, sd, kind="anysplat")
    assert net.cfg.focal_decode == "anysplat"
    assert "decoder.background" in rep.unexpected


def test_load_checkpoint_of_a_resized_stage1_weight_names_the_shape_in_one_line(tmp_path):
    """A weight of another shape in a Stage I checkpoint is one line naming it, not load_state_dict's traceback."""
    from anycity.lit import ScaffoldModule
    from anycity.models import load_checkpoint

    torch.manual_seed(0)
    ckpt = _lightning_ckpt(path := tmp_path / "last.ckpt", ScaffoldModule(), "anycity.lit.ScaffoldModule", None)
    ckpt["state_dict"]["net.aggregator.camera_token"] = torch.zeros(1, 2, 1, 32)  # the net's: [1, 2, 1, 64]
    torch.save(ckpt, path)
    with pytest.raises(ValueError, match=r"^checkpoint .*last.ckpt does not fit the network its hyper_parameters "
                                         r"describe: 1 shapes differ \(e.g. aggregator.camera_token: \[1, 2, 1, 32\] "
                                         r"there, \[1, 2, 1, 64\] here\); pass a") as e:
        load_checkpoint(path)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("wrap", ["ddp", "model"])
def test_a_ddp_or_model_nested_state_dict_loads(tmp_path, wrap):
    """A DDP-saved state dict (``module.`` prefix) and one nested under ``{"model": ...}`` load like the plain one."""
    torch.manual_seed(0)
    src = build_network("tiny", completion=False).state_dict()
    obj = {f"module.{k}": v for k, v in src.items()} if wrap == "ddp" else {"model": src, "epoch": 3}
    torch.save(obj, path := tmp_path / "model.pt")
    net = build_network("tiny", completion=False)
    rep = load_pretrained(net, path)
    rep.require_backbone(path)
    assert rep.loaded == sorted(src) and not rep.unexpected and not rep.mismatched
    assert torch.equal(net.aggregator.camera_token, src["aggregator.camera_token"])


def test_a_folder_holding_only_pytorch_model_bin_reads_it(tmp_path):
    """Hugging Face snapshots may ship ``pytorch_model.bin``, a torch file under a ``.bin`` name."""
    src = build_network("tiny", completion=False).state_dict()
    torch.save(src, tmp_path / "pytorch_model.bin")
    (tmp_path / "config.json").write_text("{}")
    net = build_network("tiny", completion=False)
    rep = load_pretrained(net, tmp_path)
    assert rep.picked == str(tmp_path / "pytorch_model.bin") and rep.loaded == sorted(src)


def test_read_state_dict_memory_maps_a_torch_file(tmp_path, monkeypatch):
    """VGGT-1B's model.pt is 5 GB: read memory-mapped, tensors only."""
    from anycity.models.pretrained import read_state_dict

    torch.save({"aggregator.camera_token": torch.ones(1, 2, 1, 4)}, path := tmp_path / "model.pt")
    calls, real = [], torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **k: calls.append(k) or real(*a, **k))
    assert torch.equal(read_state_dict(path)["aggregator.camera_token"], torch.ones(1, 2, 1, 4))
    assert calls and calls[0].get("mmap") is True and calls[0].get("weights_only") is True


def test_a_tensor_of_the_same_size_but_another_shape_is_skipped_and_listed_not_a_crash():
    """Only the shape decides: [1, 2, 64, 1] has the numel of the camera token's [1, 2, 1, 64] but cannot load."""
    sd = build_network("tiny", completion=False).state_dict()
    sd["aggregator.camera_token"] = torch.zeros(1, 2, 64, 1)
    net = build_network("tiny", completion=False)
    before = net.aggregator.camera_token.detach().clone()
    rep = load_pretrained(net, sd)
    assert rep.mismatched == [("aggregator.camera_token", (1, 2, 64, 1), (1, 2, 1, 64))]
    assert "aggregator.camera_token" not in rep.loaded and torch.equal(net.aggregator.camera_token, before)


def test_the_layout_hint_needs_more_than_half_of_the_unused_keys():
    """Two of four unused keys under ``encoder.`` are no majority: the generic preset fix, no AnySplat hint."""
    from anycity.models.pretrained import LoadReport

    rep = LoadReport(loaded=["camera_head.x"], missing=["aggregator.camera_token"],
                     unexpected=["encoder.a", "encoder.b", "point_head.a", "track_head.b"])
    with pytest.raises(ValueError, match=r"build the preset the weights were made for") as e:
        rep.require_backbone("model.pt")
    assert "encoder." not in str(e.value) and "AnySplat checkpoint" not in str(e.value)
