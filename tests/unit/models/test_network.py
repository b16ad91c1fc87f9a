import math
from dataclasses import fields

import pytest
import torch

from anycity.models import build_network
from anycity.models.completion import scale_layers
from anycity.models.presets import INT_RANGES, PAPER_INJECT_LAYERS, VGGT_HEAD_LAYERS, preset_config
from anycity.structures import Gaussians


@pytest.fixture(scope="module")
def tiny():
    torch.manual_seed(0)
    return build_network("tiny")


def test_tiny_output_contract(tiny):
    b, v, h, w = 2, 3, 64, 48
    out = tiny(torch.rand(b, v, 3, h, w))
    assert out["w2c"].shape == (b, v, 4, 4) and out["K"].shape == (b, v, 3, 3)
    assert out["depth"].shape == (b, v, 1, h, w) and out["depth_conf"].shape == (b, v, 1, h, w)
    assert (out["depth"] > 0).all() and (out["depth_conf"] >= 1).all()
    assert out["pose_enc"].shape == (b, v, 9) and len(out["pose_enc_list"]) == tiny.cfg.camera_iterations
    assert out["pixel_means"].shape == (b, v, h, w, 3)
    assert (out["K"][..., 0, 2] == w / 2).all() and (out["K"][..., 1, 2] == h / 2).all()
    g = out["gaussians"]
    assert isinstance(g, Gaussians) and g.num_gaussians == v * h * w and g.valid is None
    g.validate()
    assert torch.equal(g.means, out["pixel_means"].reshape(b, -1, 3))
    assert len(out["delta"]) == len(tiny.head_layers)
    assert out["delta"][0].shape == (b, v, (h // 8) * (w // 8), 2 * tiny.cfg.embed_dim)
    assert all(x.shape == (b, tiny.cfg.completion_tokens, 1) for x in out["gates"])
    # centres lie on the predicted depth along each pixel's ray: camera-frame z equals the depth
    R, t = out["w2c"][..., :3, :3], out["w2c"][..., None, None, :3, 3]
    cam = torch.einsum("bvij,bvhwj->bvhwi", R, out["pixel_means"]) + t
    assert torch.allclose(cam[..., 2], out["depth"][:, :, 0], rtol=1e-4, atol=1e-5)


def test_scaffold_only_returns_the_same_object(tiny):
    out = tiny(torch.rand(1, 2, 3, 64, 64), refine=False)
    assert out["gaussians"] is out["scaffold_gaussians"]
    assert out["delta"] is None and out["gates"] is None


def test_zero_init_refined_equals_scaffold(tiny):
    with torch.no_grad():
        out = tiny(torch.rand(1, 2, 3, 64, 64), refine=True)
    assert out["gaussians"] is not out["scaffold_gaussians"]
    for f in fields(Gaussians):
        a, s = getattr(out["gaussians"], f.name), getattr(out["scaffold_gaussians"], f.name)
        assert (a is None and s is None) or torch.equal(a, s), f.name
    assert all(float(d.abs().max()) == 0.0 for d in out["delta"])


def test_voxel_merge_in_network():
    net = build_network("tiny", voxel_size=0.05, completion=False)
    out = net(torch.rand(2, 2, 3, 32, 32))
    g = out["gaussians"].validate()
    assert g.valid is not None and g.num_gaussians <= 2 * 32 * 32
    assert out["pixel_means"].shape == (2, 2, 32, 32, 3)


def test_stage2_frozen_scaffold_gets_no_gradient():
    torch.manual_seed(0)
    net = build_network("tiny")
    net.freeze_scaffold()
    out = net(torch.rand(1, 2, 3, 32, 32))
    (out["gaussians"].opacities.mean() + out["gaussians"].sh.mean() + sum(g.mean() for g in out["gates"])).backward()
    for n, p in net.named_parameters():
        if n.startswith(("aggregator.", "camera_head.", "depth_head.", "gaussian_head.")):
            assert p.grad is None, n
    assert all(p.grad is not None for n, p in net.named_parameters() if n.startswith("completion.delta_proj"))
    assert net.completion.delta_proj[0].weight.grad.abs().sum() > 0


def test_parameter_groups_partition_by_name(tiny):
    scaffold = {id(p) for p in tiny.scaffold_parameters()}
    refine = {id(p) for p in tiny.refinement_parameters()}
    assert scaffold and refine and not scaffold & refine
    assert len(scaffold) + len(refine) == len(list(tiny.parameters()))
    names = [n for n, _ in tiny.named_parameters()]
    assert all(n.split(".")[0] in {"aggregator", "camera_head", "depth_head", "gaussian_head", "completion",
                                   "video_prior"} for n in names)


def test_tiny_budget(tiny):
    # the speed target (4 views at 112x112 in <= 1 s on 2 cores) is measured by benchmarks/inference.py
    assert sum(p.numel() for p in tiny.parameters()) <= 2_000_000


@pytest.mark.parametrize("bad, match", [
    (torch.rand(3, 64, 64), "expected \\[B, V, 3, H, W\\]"),
    (torch.rand(1, 2, 4, 64, 64), "expected \\[B, V, 3, H, W\\]"),
    (torch.rand(1, 0, 3, 64, 64), "at least 1"),
    (torch.rand(1, 2, 3, 60, 64), "multiples of the patch size 8"),
    (torch.rand(1, 2, 3, 64, 60), "multiples of the patch size 8"),  # the width too, not only the height
    (torch.zeros(1, 2, 3, 64, 64, dtype=torch.uint8), "float"),
])
def test_bad_input_errors(tiny, bad, match):
    with pytest.raises(ValueError, match=match):
        tiny(bad)


def test_unknown_preset_and_option():
    with pytest.raises(ValueError, match="preset"):
        build_network("huge")
    with pytest.raises(ValueError, match="unknown option"):
        build_network("tiny", embed_dimm=3)
    # a shallower aggregator than the heads' 4 layers: one line, not an unpacking error inside the DPT head
    with pytest.raises(ValueError, match=r"head_layers: the DPT heads read 4 aggregator layers of 0\.\.1, got "
                                         r"\[0, 1\] \(depth 2\); use depth >= 4"):
        build_network("tiny", depth=2)
    with pytest.raises(ValueError, match=r"got \[0, 1, 9, 3\]"):
        build_network("tiny", head_layers=(0, 1, 9, 3))

    # the last layer is depth - 1: the depth itself is one past the aggregator's outputs
    with pytest.raises(ValueError, match=r"^head_layers: the DPT heads read 4 aggregator layers of 0\.\.3, got "
                                         r"\[0, 1, 2, 4\] \(depth 4\)"):
        preset_config("tiny", head_layers=(0, 1, 2, 4))
    assert preset_config("tiny", head_layers=(0, 1, 2, 3)).resolved_head_layers() == (0, 1, 2, 3)


def test_preset_sizes_are_pinned():
    """VGGT-1B's camera head refines 4 times on a 4-block trunk; small and base are their documented sizes."""
    vggt = preset_config("vggt-1b")
    assert (vggt.camera_iterations, vggt.camera_trunk_depth) == (4, 4)
    for preset, size in [("small", (8, 256, 14)), ("base", (12, 768, 14))]:
        cfg = preset_config(preset)
        assert (cfg.depth, cfg.embed_dim, cfg.patch_size) == size, preset
    with torch.device("meta"):
        base = build_network("base")
    assert round(sum(p.numel() for p in base.aggregator.patch_embed.parameters()) / 1e6, 1) == 86.6  # DINOv2-B/14


@pytest.mark.parametrize("preset, depth", [("tiny", 4), ("base", 12)])
def test_inject_layers_beyond_the_depth_are_refused_when_configured(preset, depth):
    # stage2.yaml pins the paper's [4, 7, 11, 23]; on a shallower preset that was an IndexError at the first forward
    with pytest.raises(ValueError, match=rf"^inject_layers: .* 0\.\.{depth - 1} .*got \[4, 7, 11, 23\]; set "
                                         r"net.inject_layers: null"):
        preset_config(preset, inject_layers=(4, 7, 11, 23))
    with pytest.raises(ValueError, match=r"got \[-1, 2\]"):
        preset_config(preset, inject_layers=(-1, 2))
    assert preset_config(preset, inject_layers=(0, depth - 1)).resolved_inject_layers() == (0, depth - 1)
    assert preset_config(preset, inject_layers=(4, 7, 11, 23), completion=False).completion is False  # unused
    assert preset_config("vggt-1b", inject_layers=(4, 7, 11, 23)).depth == 24


def test_layer_scaling():
    assert scale_layers((4, 11, 17, 23), 24) == (4, 11, 17, 23)
    assert scale_layers((4, 11, 17, 23), 4) == (0, 1, 2, 3)
    assert scale_layers((4, 7, 11, 23), 8) == (1, 2, 3, 7)


@pytest.mark.parametrize("depth, inject, heads", [
    (4, (0, 1, 3), (0, 1, 2, 3)),  # tiny: two paper layers land on layer 0, so 3 injection stages
    (12, (1, 3, 5, 11), (1, 5, 8, 11)),  # base: round half to even (layer 4: 2.5 -> 2, so 1)
    (24, (4, 7, 11, 23), (4, 11, 17, 23)),
])
def test_scaled_layers_are_pinned(depth, inject, heads):
    # trained checkpoints (the quickstart's) depend on this mapping: change it only with them
    cfg = preset_config("tiny", depth=depth)
    assert cfg.resolved_inject_layers() == scale_layers(PAPER_INJECT_LAYERS, depth) == inject
    assert cfg.resolved_head_layers() == scale_layers(VGGT_HEAD_LAYERS, depth) == heads
    assert preset_config("tiny").resolved_inject_layers() == (0, 1, 3)


def test_gradient_checkpointing_gives_the_same_outputs():
    torch.manual_seed(0)
    net = build_network("tiny", completion=False).train()
    x = torch.rand(1, 2, 3, 32, 32)
    ref = net(x)["depth"]
    net.set_gradient_checkpointing(True)
    out = net(x)["depth"]
    assert torch.allclose(out, ref, atol=1e-6)
    out.mean().backward()
    assert net.aggregator.frame_blocks[0].attn.qkv.weight.grad is not None


def test_pixel_colour_mode_reproduces_input_colours_at_init(tiny):
    assert tiny.cfg.color_mode == "pixel"
    images = torch.rand(1, 2, 3, 32, 32)
    with torch.no_grad():
        g = tiny(images, refine=False)["gaussians"]
    colour = 0.5 + 0.28209479177387814 * g.sh[0, :, 0, :]  # DC colour [N, 3]
    assert torch.allclose(colour, images[0].permute(0, 2, 3, 1).reshape(-1, 3), atol=0.02)
    torch.manual_seed(0)
    head = build_network("tiny", color_mode="head", completion=False)
    with torch.no_grad():
        gh = head(images, refine=False)["gaussians"]
    assert not torch.allclose(0.5 + 0.28209479177387814 * gh.sh[0, :, 0, :],
                              images[0].permute(0, 2, 3, 1).reshape(-1, 3), atol=0.02)


def test_pixel_scale_mode_scales_with_depth_over_focal(tiny):
    from anycity.models.gaussians import raw_to_gaussians

    raw = torch.zeros(1, 1, 9 + 3 * 4, 2, 2)
    means = torch.zeros(1, 1, 2, 2, 3)
    footprint = torch.tensor([0.01, 0.02, 0.04, 0.08]).reshape(1, 1, 1, 2, 2)
    g = raw_to_gaussians(raw, means, 1, footprint=footprint)
    expected = footprint.flatten() * torch.log(torch.tensor(2.0))
    assert torch.allclose(g.scales[0], expected[:, None].expand(4, 3))
    with torch.no_grad():
        out = tiny(torch.rand(1, 2, 3, 32, 32), refine=False)
    ratio = out["gaussians"].scales.reshape(1, 2, 32, 32, 3)[..., 0] / out["depth"][:, :, 0]
    focal = 0.5 * (out["K"][..., 0, 0] + out["K"][..., 1, 1])
    # scale / (depth / focal) = softplus(raw): of order one pixel at init, independent of depth
    per_px = ratio * focal[..., None, None]
    assert 0.1 < float(per_px.median()) < 3.0


def test_mode_options_validated_and_camera_init():
    with pytest.raises(ValueError, match="scale_mode"):
        build_network("tiny", scale_mode="pixels")
    with pytest.raises(ValueError, match="color_mode"):
        build_network("tiny", color_mode="rgb")
    torch.manual_seed(0)
    net = build_network("tiny", completion=False)
    with torch.no_grad():
        enc = net(torch.rand(1, 2, 3, 32, 32), refine=False)["pose_enc"]
    assert (enc[..., 7:] > 0.5).all() and (enc[..., 7:] < 1.5).all()  # FoV near 1 rad: finite focal
    assert (enc[..., 6] > 0.5).all()  # quaternion w near 1: identity rotation


def test_zero_offsets_keep_centres_on_their_rays_and_refinement_starts_at_the_scaffold():
    """The centre-offset output is zero-initialised: centres are exactly the unprojected depth (Stage I starts where
    it did without offsets), and Stage II's final Gaussians, depth and centres equal the scaffold's before training."""
    from anycity.models.gaussians import pixel_centres

    torch.manual_seed(0)
    net = build_network("tiny")
    out = net(torch.rand(1, 3, 3, 32, 32), refine=True)
    assert not out["offset"].any()
    assert torch.equal(out["scaffold_pixel_means"], pixel_centres(out["scaffold_depth"], out["K"], out["w2c"]))
    assert torch.equal(out["pixel_means"], out["scaffold_pixel_means"])
    assert torch.equal(out["depth"], out["scaffold_depth"])
    assert torch.equal(out["gaussians"].means, out["scaffold_gaussians"].means)
    assert torch.equal(out["gaussians"].sh, out["scaffold_gaussians"].sh)


def _tiny_with_residual(offsets: bool = False):
    """The tiny network (seed 0) with a non-zero completion residual, and non-zero centre offsets if asked."""
    torch.manual_seed(0)
    net = build_network("tiny")
    with torch.no_grad():
        for lin in net.completion.delta_proj:
            lin.bias.normal_(0, 0.5)
        if offsets:
            net.gaussian_head.offset_conv.weight.normal_(0, 0.1)
    return net


def test_completion_residual_reaches_centres_and_depth():
    """Z_final goes through the whole decoder: a non-zero residual moves centres (offsets) and depth."""
    net = _tiny_with_residual()
    out = net(torch.rand(1, 2, 3, 32, 32), refine=True)
    assert not torch.equal(out["depth"], out["scaffold_depth"])
    assert not torch.equal(out["gaussians"].opacities, out["scaffold_gaussians"].opacities)
    with torch.no_grad():
        net.gaussian_head.offset_conv.weight.normal_(0, 0.1)
    out = net(torch.rand(1, 2, 3, 32, 32), refine=True)
    assert not torch.equal(out["gaussians"].means, out["scaffold_gaussians"].means)
    (out["gaussians"].means.sum() + out["depth"].sum()).backward()
    assert net.completion.delta_proj[0].bias.grad.abs().sum() > 0


def test_offsets_respond_to_the_residual_even_when_the_hidden_relu_layer_is_dead():
    """The offset conv reads the pre-activation input of the head's last block: a Stage I head whose ReLU layer died
    (every unit negative everywhere, seen in the tiny quickstart model) still lets Stage II move the centres."""
    torch.manual_seed(0)
    net = build_network("tiny", gaussian_head_slope=0.0)
    assert isinstance(net.gaussian_head.scratch.output_conv2[1], torch.nn.ReLU)
    with torch.no_grad():
        net.gaussian_head.scratch.output_conv2[0].bias.fill_(-1e4)  # dead: the hidden layer is 0 on every pixel
        net.gaussian_head.offset_conv.weight.normal_(0, 0.1)
        for lin in net.completion.delta_proj:
            lin.bias.normal_(0, 0.5)
    out = net(torch.rand(1, 2, 3, 32, 32), refine=True)
    torch.testing.assert_close(out["gaussians"].opacities, out["scaffold_gaussians"].opacities)  # dead: constant
    assert (out["pixel_means"] - out["scaffold_pixel_means"]).abs().amax() > 1e-4


def test_presets_trained_from_scratch_use_a_leaky_head_and_vggt_1b_keeps_relu():
    assert isinstance(build_network("tiny").gaussian_head.scratch.output_conv2[1], torch.nn.LeakyReLU)
    with torch.device("meta"):
        assert isinstance(build_network("vggt-1b", completion=False).gaussian_head.scratch.output_conv2[1],
                          torch.nn.ReLU)


def test_refine_cameras_starts_at_the_scaffold_cameras_and_leaves_every_other_init_unchanged():
    """``refine_cameras`` (beyond the paper) adds a zero-initialised camera-token residual built after every other
    module: the same seed gives the same weights elsewhere, and before training the final cameras and Gaussians are
    the scaffold's."""
    torch.manual_seed(0)
    plain = build_network("tiny").state_dict()
    torch.manual_seed(0)
    net = build_network("tiny", refine_cameras=True)
    own = net.state_dict()
    extra = {k for k in own if k not in plain}
    assert extra and all(k.startswith(("completion.camera_attn.", "completion.camera_proj.")) for k in extra)
    assert all(torch.equal(own[k], v) for k, v in plain.items())
    out = net(torch.rand(1, 3, 3, 32, 32), refine=True)
    torch.testing.assert_close(out["w2c"], out["scaffold_w2c"])
    torch.testing.assert_close(out["K"], out["scaffold_K"])
    torch.testing.assert_close(out["gaussians"].means, out["scaffold_gaussians"].means)


def test_camera_residual_re_places_the_views_and_trains_through_the_frozen_camera_head():
    torch.manual_seed(0)
    net = build_network("tiny", refine_cameras=True)
    net.freeze_scaffold()
    with torch.no_grad():
        net.completion.camera_proj.bias.normal_(0, 0.5)
    out = net(torch.rand(1, 3, 3, 32, 32), refine=True)
    assert (out["w2c"] - out["scaffold_w2c"]).abs().amax() > 1e-4
    # the refined Gaussians follow the re-placed cameras; the scaffold's keep the scaffold's
    from anycity.models.gaussians import pixel_centres

    torch.testing.assert_close(out["pixel_means"], pixel_centres(out["depth"], out["K"], out["w2c"], out["offset"]))
    torch.testing.assert_close(out["scaffold_pixel_means"],
                               pixel_centres(out["scaffold_depth"], out["scaffold_K"], out["scaffold_w2c"]))
    out["pose_enc"].sum().backward()
    assert net.completion.camera_proj.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in net.camera_head.parameters())
    # off (the paper's): the final cameras are the scaffold's tensors, and the branch has no camera residual
    net = build_network("tiny")
    out = net(torch.rand(1, 2, 3, 32, 32), refine=True)
    assert out["w2c"] is out["scaffold_w2c"] and net.completion.camera_proj is None


def test_camera_video_gives_each_view_a_residual_that_knows_its_place_in_the_clip():
    """``camera_video`` (beyond the paper): each view's camera residual also reads its own frame's video-prior
    features. The scaffold is equivariant over views 1..V-1, which is why its camera head falls back to one mean
    relative pose: three identical views get three identical cameras. The video prior knows each frame's position
    in the clip, so the re-placed cameras of those three views differ; without ``camera_video`` they do not."""
    torch.manual_seed(0)
    plain = build_network("tiny", refine_cameras=True).state_dict()
    torch.manual_seed(0)
    net = build_network("tiny", refine_cameras=True, camera_video=True)
    own = net.state_dict()
    assert {k for k in own if k not in plain} and all(k.startswith("completion.camera_vid.") for k in own
                                                      if k not in plain)
    assert all(torch.equal(own[k], v) for k, v in plain.items())
    images = torch.rand(1, 2, 3, 32, 32)[:, [0, 1, 1, 1]]  # views 1, 2 and 3 are the same image
    out = net(images, refine=True)
    torch.testing.assert_close(out["w2c"], out["scaffold_w2c"])  # zero-initialised: starts at the scaffold

    def spread(net):  # how far apart the re-placed cameras of the three identical views are
        with torch.no_grad():
            net.completion.camera_proj.weight.normal_(0, 0.5)
        out = net(images, refine=True)
        same = out["scaffold_w2c"][:, 1:]
        torch.testing.assert_close(same, same[:, :1].expand_as(same), atol=1e-5, rtol=1e-5)
        return (out["w2c"][:, 2:] - out["w2c"][:, 1:2]).abs().amax().item(), out

    moved, out = spread(net)
    assert moved > 1e-3
    torch.manual_seed(0)
    assert spread(build_network("tiny", refine_cameras=True))[0] < 1e-5
    out["pose_enc"].sum().backward()
    assert net.completion.camera_vid[1].fc2.weight.grad.abs().sum() > 0
    for bad in ({"camera_video": True}, {"camera_video": True, "refine_cameras": True, "video_prior": "none"}):
        with pytest.raises(ValueError, match="camera_video"):
            build_network("tiny", **bad)


@pytest.mark.parametrize("bad, match", [
    (torch.rand(1, 2, 3, 32, 32, dtype=torch.float64), r"^images: float64; pass images.float\(\)$"),
    (torch.rand(1, 2, 3, 32, 32) * 255, r"^images: expected values in \[0, 1\], got a maximum of .*; images look like "
                                        r"0-255; divide by 255$"),
    (torch.rand(1, 2, 3, 32, 32) + 0.2, r"maximum of 1\.\d+; clamp them to \[0, 1\]$"),
    (torch.rand(1, 2, 3, 32, 32) * 2 - 1, r"^images: expected values in \[0, 1\], got a minimum of -\S+ "
                                          r"\(maximum \S+\); they look like \[-1, 1\]; use \(x \+ 1\) / 2$"),
    ((torch.rand(1, 2, 3, 32, 32) - torch.tensor([0.485, 0.456, 0.406])[:, None, None])
     / torch.tensor([0.229, 0.224, 0.225])[:, None, None],
     r"^images: expected values in \[0, 1\], got a minimum of -[12]\S* \(maximum 2\S*\); they look "
     r"mean/std-normalised \(e\.g\. ImageNet\); undo the normalisation: x \* std \+ mean$"),
    (torch.rand(1, 2, 3, 32, 32).index_fill_(3, torch.tensor([5]), float("nan")),
     r"^images: expected finite values in \[0, 1\], got NaN; find the non-finite pixels"),
    (torch.rand(1, 2, 3, 32, 32).index_fill_(3, torch.tensor([5]), float("inf")),
     r"^images: expected finite values in \[0, 1\], got a minimum of .* and a maximum of inf; "),
])
def test_images_of_another_dtype_or_range_are_one_line(tiny, bad, match):
    """float64 images were a conv dtype error, 0-255 floats ran on silently into a garbage reconstruction; [-1, 1]
    and NaN images did too (only the maximum was checked), and ImageNet-normalised ones were told to divide by 255."""
    with pytest.raises(ValueError, match=match):
        tiny(bad)


def test_images_just_above_one_and_half_precision_images_still_run(tiny):
    x = torch.rand(1, 2, 3, 32, 32)
    x[0, 0, 0, 0, 0] = 1.0005  # a resize's rounding
    x[0, 1, 0, 0, 0] = -0.0005
    with torch.no_grad():
        for images in (x, x.bfloat16(), x.half()):
            assert tiny(images, refine=False)["depth"].dtype == torch.float32


def test_a_network_cast_to_half_precision_names_autocast():
    """net.bfloat16() failed deep inside a layer norm ('mixed dtype'); the heads and geometry need float32 weights."""
    net = build_network("tiny", completion=False).bfloat16()
    with pytest.raises(ValueError, match=r"^network: weights are bfloat16 .*keep float32 weights and run under "
                                         r"torch.autocast \(Lightning: trainer.precision bf16-mixed"):
        net(torch.rand(1, 2, 3, 32, 32).bfloat16())


@pytest.mark.parametrize("option, value, match", [
    ("sh_degree", 5, r"^net.sh_degree: expected an integer 0\.\.4 .*got 5$"),
    ("sh_degree", -1, r"^net.sh_degree: expected an integer 0\.\.4"),
    ("sh_degree", 1.5, r"^net.sh_degree: .*got 1.5$"),
    ("sh_degree", True, r"^net.sh_degree: expected an integer 0\.\.4 .*got True$"),  # a bool is no degree
    ("camera_iterations", 0, r"^net.camera_iterations: expected an integer >= 1 .*got 0$"),
    ("num_heads", 0, r"^net.num_heads: expected an integer >= 1"),
    ("completion_tokens", 0, r"^net.completion_tokens: expected an integer >= 1"),
    ("num_register_tokens", -1, r"^net.num_register_tokens: expected an integer >= 0"),
])
def test_integer_options_out_of_range_are_one_line(option, value, match):
    """sh_degree 5 built a network whose Gaussians no renderer takes, camera_iterations 0 was an IndexError in
    forward, a 0 head count a ZeroDivisionError."""
    with pytest.raises(ValueError, match=match):
        preset_config("tiny", **{option: value})
    lowest = INT_RANGES[option][0]
    assert getattr(preset_config("tiny", **{option: lowest}), option) == lowest  # the bound itself is allowed



@pytest.mark.parametrize("option, value, match", [
    ("dpt_features", 20, r"^net.dpt_features: expected a multiple of 8 .*got 20; use 24$"),
    ("dpt_out_channels", (16, 32, 64, 66), r"^net.dpt_out_channels: expected 4 positive multiples of 4 .*"
                                           r"got \[16, 32, 64, 66\]; e.g. \[16, 32, 64, 64\]$"),
    ("dpt_out_channels", (16, 32, 64), r"^net.dpt_out_channels: expected 4 .*got \[16, 32, 64\]; "),
    ("dpt_out_channels", (16, 32, 64, 0), r"^net.dpt_out_channels: expected 4 positive .*got \[16, 32, 64, 0\]; "),
    ("num_heads", 32, r"^net.num_heads: expected a divisor of embed_dim 64 that leaves a head width divisible by 4 "
                      r"\(the aggregator's 2D RoPE\), got 32 \(head width 2\); use num_heads 16$"),
    ("num_heads", 5, r"^net.num_heads: .*got 5 \(head width 12.8\); use num_heads 4$"),
    ("camera_num_heads", 3, r"^net.camera_num_heads: expected a divisor of the camera head's width, 2 \* embed_dim "
                            r"\(128\), got 3; use camera_num_heads 2$"),
    ("completion_heads", 3, r"^net.completion_heads: expected a divisor of completion_dim \(64\), got 3; "
                            r"use completion_heads 2$"),
])
def test_widths_the_layers_cannot_split_are_one_line(option, value, match):
    """The DPT heads' UV embedding splits each projected width (and half of dpt_features) in 4, the aggregator's 2D
    RoPE each attention head: such widths built, then failed at the first forward with a reshape error or a RoPE
    error that named no option (3 out_channels: an IndexError at build time); heads that do not divide the camera
    head's or the completion branch's width were refused naming their layer, not the option."""
    with pytest.raises(ValueError, match=match):
        build_network("tiny", completion=option == "completion_heads", **{option: value})


def test_uncommon_widths_that_the_layers_can_split_still_run():
    """Widths that are not the presets' but split (dpt_features 24, out_channels multiples of 4 only, a head width
    of exactly 4) build and run."""
    torch.manual_seed(0)
    net = build_network("tiny", completion=False, dpt_features=24, dpt_out_channels=[12, 20, 28, 36], num_heads=16)
    with torch.no_grad():
        assert net(torch.rand(1, 2, 3, 16, 16), refine=False)["depth"].shape == (1, 2, 1, 16, 16)
    for preset in ("small", "base", "vggt-1b"):
        preset_config(preset)

def test_forward_on_the_meta_device():
    """torch.autocast('meta', enabled=False) raised 'unsupported scalarType': shapes could not be traced on meta."""
    with torch.device("meta"):
        net = build_network("tiny")
    with torch.no_grad():
        out = net(torch.empty(1, 2, 3, 32, 48, device="meta"))
    assert out["depth"].is_meta and tuple(out["depth"].shape) == (1, 2, 1, 32, 48)
    assert tuple(out["gaussians"].means.shape) == (1, 2 * 32 * 48, 3)


@pytest.mark.parametrize("images, fix", [
    (torch.randint(0, 255, (3, 32, 24, 3), dtype=torch.uint8),
     r"they are channels-last: permute to \[\.\.\., 3, H, W\] with images.permute\(0, 3, 1, 2\)\[None\], then "
     r"\.float\(\) / 255$"),
    (torch.rand(1, 3, 32, 24, 3), r"they are channels-last: permute to \[\.\.\., 3, H, W\] with "
                                  r"images.permute\(0, 1, 4, 2, 3\)$"),
    (torch.rand(32, 24, 3), r"they are channels-last: .*images.permute\(2, 0, 1\)\[None, None\]$"),
    (torch.rand(3, 3, 32, 24), r"add the missing leading dims with images\[None\] \(V views of one sample\)$"),
    (torch.rand(3, 32, 24), r"add the missing leading dims with images\[None, None\] \(one image\)$"),
    (torch.rand(1, 3, 32, 24).numpy(), r"pass a torch tensor: torch.from_numpy\(images\)"),
])
def test_a_wrong_image_layout_gets_the_fix_for_that_layout(tiny, images, fix):
    """Channels-last images ([V, H, W, 3], [B, V, H, W, 3]) were told to 'add the batch/view dims with images[None]',
    which still fails: the channel axis was the problem."""
    with pytest.raises(ValueError, match=r"^images: expected \[B, V, 3, H, W\] float in \[0, 1\], got .*; " + fix):
        tiny(images)


def test_a_network_cast_to_float64_names_float64():
    """net.double() was reported as '(net.bfloat16()/.half())' with an autocast fix that does not apply."""
    net = build_network("tiny", completion=False).double()
    with pytest.raises(ValueError, match=r"^network: weights are float64, expected float32; cast them back with "
                                         r"net.float\(\)$"):
        net(torch.rand(1, 2, 3, 32, 32))
    with pytest.raises(ValueError, match=r"^network: weights are float16 \(net.half\(\)\); keep float32"):
        build_network("tiny", completion=False).half()(torch.rand(1, 2, 3, 32, 32))


def test_a_depth_8_network_keeps_the_injection_layers_the_heads_do_not_read():
    """The aggregator must keep the completion's injection layers too, not only the head layers."""
    torch.manual_seed(0)
    net = build_network("tiny", depth=8)
    assert net.completion.inject_layers == (1, 2, 3, 7) and net.head_layers == (1, 3, 5, 7)
    with torch.no_grad():
        out = net(torch.rand(1, 2, 3, 32, 32), refine=True)
    assert len(out["gates"]) == 4


def test_refined_centres_and_scales_come_from_the_refined_depth_and_cameras():
    """The refined Gaussians are placed from the refined depth (not the scaffold's)."""
    from anycity.models.gaussians import pixel_centres

    net = _tiny_with_residual(offsets=True)
    x = torch.rand(1, 2, 3, 32, 32)
    with torch.no_grad():
        out = net(x)
        ref = net.place_gaussians(out["raw_gaussians"], out["depth"], out["offset"], out["w2c"], out["K"], x)
    assert (out["depth"] - out["scaffold_depth"]).abs().max() > 1e-4
    assert torch.equal(out["gaussians"].means, ref.means) and torch.equal(out["gaussians"].scales, ref.scales)
    assert torch.equal(out["pixel_means"], pixel_centres(out["depth"], out["K"], out["w2c"], out["offset"]))


def _completion_reference(br, toks, vid):
    """The branch's forward written out: per injection layer its own geometry layer, gated video, FFN residual;
    per head layer its own patch tokens query; camera tokens (index 0) of the last layer."""
    z = br.tokens.expand(toks[0].shape[0], -1, -1)
    v = br.p_vid(vid)
    for i, layer in enumerate(br.inject_layers):
        z = z + br.geo_attn[i](z, toks[layer].flatten(1, 2))
        z = z + torch.sigmoid(br.gate[i](z)) * br.vid_attn[i](z, v)
        z = z + br.ffn[i](br.ffn_norm[i](z))
    delta = [br.delta_proj[j](br.delta_attn[j](toks[layer][:, :, 1:].flatten(1, 2), z)).view_as(toks[layer][:, :, 1:])
             for j, layer in enumerate(br.head_layers)]
    return delta, br.camera_proj(br.camera_attn(toks[-1][:, :, 0], z))


def test_completion_branch_matches_a_written_out_reference_and_a_closed_gate_ignores_the_video():
    """The sigmoid gate, each stage's own injection layer, the FFN residual, each head layer's own patch tokens and
    camera token 0, as written out; a closed gate ignores the video."""
    from anycity.models.completion import CompletionBranch

    torch.manual_seed(0)
    br = CompletionBranch(16, 8, 4, 2, (0, 1), (1, 2), video_dim=6, camera=True)
    with torch.no_grad():
        for p in [*br.delta_proj, br.camera_proj]:
            p.weight.normal_(0, 0.5)
        toks = [torch.randn(1, 2, 5, 16) for _ in range(3)]
        vid = torch.randn(1, 7, 6)
        delta, gates, cam, _ = br(toks, 1, vid)
        ref_delta, ref_cam = _completion_reference(br, toks, vid)
        assert len(gates) == 2
        for a, b in zip(delta, ref_delta, strict=True):
            assert a.shape == (1, 2, 4, 16) and torch.allclose(a, b, atol=1e-6)
        assert torch.allclose(cam, ref_cam, atol=1e-6)
        for gl in br.gate:
            gl.weight.zero_()
            gl.bias.fill_(-50.0)
        d1, d2 = br(toks, 1, vid)[0], br(toks, 1, vid * 3 + 1)[0]
    assert all(torch.allclose(a, b, atol=1e-6) for a, b in zip(d1, d2, strict=True))


def test_the_gaussian_head_reads_the_images_as_well_as_the_tokens(tiny):
    """The image merger adds the views' pixels to the decoded features."""
    torch.manual_seed(0)
    x = torch.rand(1, 2, 3, 32, 32)
    with torch.no_grad():
        tokens = tiny.aggregator(x, keep=set(tiny.head_layers))
        psi = tiny.aggregator.patch_start_idx
        raw_a, _ = tiny.gaussian_head(tokens, x, psi)
        raw_b, _ = tiny.gaussian_head(tokens, torch.rand_like(x), psi)
    assert (raw_a - raw_b).abs().max() > 1e-4



def test_aggregator_token_layout_frame_half_first_and_two_camera_slots():
    """With the frame blocks' LayerScales at 0 (identity blocks), the first half of each output is the frame
    attention's input: camera and register slot 0 for view 0, slot 1 for every other view, then the patch embedding
    of the ImageNet-normalised image; the global attention's output is the second half."""
    from anycity.models.aggregator import IMAGENET_MEAN, IMAGENET_STD, Aggregator

    torch.manual_seed(0)
    agg = Aggregator(img_size=32, patch_size=8, embed_dim=32, depth=1, num_heads=2, patch_embed="conv").eval()
    c, r = 32, agg.patch_start_idx - 1
    with torch.no_grad():
        agg.camera_token.normal_()
        agg.register_token.normal_()
        agg.frame_blocks[0].ls1.gamma.zero_()
        agg.frame_blocks[0].ls2.gamma.zero_()
        x = torch.rand(1, 3, 3, 16, 16)
        out = agg(x)[0]  # [1, V, T, 2C]
        mean, std = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        patches = agg.patch_embed((x[0] - mean) / std)
    assert out.shape == (1, 3, 1 + r + 4, 2 * c)
    for v, slot in ((0, 0), (1, 1), (2, 1)):
        assert torch.equal(out[0, v, 0, :c], agg.camera_token[0, slot, 0]), v
        assert torch.equal(out[0, v, 1:1 + r, :c], agg.register_token[0, slot]), v
    assert torch.allclose(out[0, :, 1 + r:, :c], patches, atol=1e-6)
    assert not torch.allclose(out[..., c:], out[..., :c], atol=1e-3)  # the global half is another tensor


def test_more_views_than_a_decoding_chunk_take_their_own_residual():
    """The DPT heads decode frames_chunk_size (8) views at a time; each chunk adds the Stage II residual of its
    own views: 9 views give the same depth and Gaussian channels as one unchunked decode."""
    net = _tiny_with_residual().eval()
    assert net.depth_head.frames_chunk_size == net.gaussian_head.frames_chunk_size == 8
    x = torch.rand(1, 9, 3, 16, 16)
    with torch.no_grad():
        out = net(x)
        net.depth_head.frames_chunk_size = net.gaussian_head.frames_chunk_size = 0
        ref = net(x)
    assert (out["depth"] - out["scaffold_depth"]).abs().max() > 1e-4  # the residual is there
    torch.testing.assert_close(out["depth"], ref["depth"], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out["raw_gaussians"], ref["raw_gaussians"], atol=1e-5, rtol=1e-5)


def test_refined_cameras_size_the_refined_gaussians():
    """With refine_cameras, the final Gaussians' pixel-footprint scales use the re-placed intrinsics, as
    place_gaussians with the final cameras does, not the scaffold's."""
    torch.manual_seed(0)
    net = build_network("tiny", refine_cameras=True, scale_mode="pixel").eval()
    x = torch.rand(1, 2, 3, 32, 32)
    with torch.no_grad():
        net.completion.camera_proj.weight.normal_(0, 0.5)
        net.completion.camera_proj.bias.normal_(0, 0.5)
        out = net(x)
        ref = net.place_gaussians(out["raw_gaussians"], out["depth"], out["offset"], out["w2c"], out["K"], x)
    assert (out["K"] - out["scaffold_K"]).abs().max() > 1e-3  # the focal length moved
    assert torch.equal(out["gaussians"].scales, ref.scales)


def test_camera_head_modulation_is_vggts_adaln():
    """VGGT's camera-token modulation is gate * (LN(t) * (1 + scale) + shift) + t: with shift 0, scale 0 and gate 1
    one iteration is the pose branch of trunk(LN(t) + t), FoV through a ReLU."""
    from anycity.models.heads import CameraHead

    torch.manual_seed(0)
    head = CameraHead(dim_in=32, trunk_depth=1, num_heads=2).eval()
    with torch.no_grad():
        lin = head.poseLN_modulation[1]
        lin.weight.zero_()
        lin.bias.zero_()
        lin.bias[64:] = 1.0  # (shift, scale, gate) = (0, 0, 1)
        tok = torch.randn(1, 2, 5, 32)
        out = head([tok], num_iterations=1)
        t = head.token_norm(tok[:, :, 0])
        ref = head.pose_branch(head.trunk_norm(head.trunk(head.adaln_norm(t) + t)))
    assert len(out) == 1
    torch.testing.assert_close(out[0], torch.cat([ref[..., :7], ref[..., 7:].relu()], -1), atol=1e-6, rtol=1e-6)


def test_camera_head_passes_no_gradient_across_iterations():
    """Each iteration starts from the previous encoding detached (VGGT): the last encoding's gradient does not reach
    the empty pose token, which only the first iteration reads."""
    from anycity.models.heads import CameraHead

    torch.manual_seed(0)
    head = CameraHead(dim_in=32, trunk_depth=1, num_heads=2)
    out = head([torch.randn(1, 3, 5, 32)], num_iterations=2)
    out[-1].sum().backward()
    assert head.embed_pose.weight.grad is not None and head.pose_branch.fc2.weight.grad.abs().sum() > 0
    assert head.empty_pose_tokens.grad is None


def test_dpt_uv_embedding_spans_aspect_over_diagonal_in_x():
    """VGGT's create_uv_grid: x spans +-aspect/diag * (W-1)/W, y +-1/diag * (H-1)/H (diag = sqrt(aspect^2 + 1));
    channel 0 is sin(x), channel C/2 sin(y) at the lowest frequency (1)."""
    from anycity.models.heads.dpt import uv_embedding

    e = uv_embedding(2, 4, 8, aspect=2.0, dtype=torch.float32, device=None)  # [C, H, W]
    assert e.shape == (8, 2, 4)
    assert math.isclose(float(e[0, 0, 0]), math.sin(-(2 / math.sqrt(5)) * 3 / 4), abs_tol=1e-6)
    assert math.isclose(float(e[4, 0, 0]), math.sin(-(1 / math.sqrt(5)) * 1 / 2), abs_tol=1e-6)


def test_dpt_fusion_upsamples_with_aligned_corners():
    """The RefineNet fusion doubles its map with bilinear align_corners=True (VGGT): [0, 3] becomes [0, 1, 2, 3]."""
    from anycity.models.heads.dpt import FusionBlock

    fb = FusionBlock(1, has_residual=False)
    with torch.no_grad():
        for conv in (fb.resConfUnit2.conv1, fb.resConfUnit2.conv2):
            conv.weight.zero_()
            conv.bias.zero_()
        fb.out_conv.weight.fill_(1.0)
        fb.out_conv.bias.zero_()
        y = fb(torch.tensor([[[[0.0, 3.0], [6.0, 9.0]]]]))
    assert y.shape == (1, 1, 4, 4)
    torch.testing.assert_close(y[0, 0, 0], torch.tensor([0.0, 1.0, 2.0, 3.0]))
    torch.testing.assert_close(y[0, 0, :, 0], torch.tensor([0.0, 2.0, 4.0, 6.0]))
