"""The pair-correlation pose prior (beyond the paper): order-free poses in view 0's frame, loaded frozen, read by
Stage II's camera residual, which still starts at the scaffold."""

import re

import pytest
import torch

from anycity.models import build_network
from anycity.models.pose_prior import PairFlowPose, load_pose_prior, pose_features


def test_poses_are_in_view_0s_frame_and_follow_the_views_not_their_order():
    torch.manual_seed(0)
    prior = PairFlowPose().eval()
    with torch.no_grad():
        prior.mlp[-1].bias.normal_(0, 0.3)  # a non-trivial pose for every view
    images = torch.rand(2, 4, 3, 48, 48)
    w2c = prior(images)
    assert w2c.shape == (2, 4, 4, 4)
    torch.testing.assert_close(w2c[:, 0], torch.eye(4).expand(2, 4, 4))
    R = w2c[:, 1:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-5, rtol=0)
    assert (w2c[:, 1:] - torch.eye(4)).abs().amax() > 1e-2
    # reordering views 1..3 reorders their poses and changes nothing else
    order = [0, 3, 1, 2]
    torch.testing.assert_close(prior(images[:, order]), w2c[:, order], atol=1e-5, rtol=1e-5)
    # another image size is pooled to the same grid
    assert prior(torch.rand(1, 3, 3, 64, 96)).shape == (1, 3, 4, 4)
    assert torch.equal(prior(images[:, :1]), torch.eye(4).expand(2, 1, 4, 4))


def test_pose_features_are_zero_for_the_identity():
    w2c = torch.eye(4).repeat(1, 2, 1, 1)
    w2c[0, 1, :3, 3] = torch.tensor([1.0, 2.0, 3.0])
    f = pose_features(w2c)
    assert f.shape == (1, 2, 9)
    assert torch.equal(f[0, 0], torch.zeros(9)) and torch.equal(f[0, 1, 6:], torch.tensor([1.0, 2.0, 3.0]))


def test_load_round_trip_is_frozen_and_bad_files_say_what_to_do(tmp_path):
    torch.manual_seed(1)
    trained = PairFlowPose(channels=16, grid=6)
    path = tmp_path / "prior.pt"
    torch.save({"state_dict": trained.state_dict(), "channels": 16, "grid": 6, "image_size": [48, 48]}, path)
    loaded = load_pose_prior(str(path))
    assert not loaded.training and not any(p.requires_grad for p in loaded.parameters())
    x = torch.rand(1, 3, 3, 48, 48)
    torch.testing.assert_close(loaded(x), trained(x))
    with pytest.warns(UserWarning, match="trained on 48x48 views, given 32x64.*--image-size"):
        loaded(torch.rand(1, 2, 3, 32, 64))
    placeholder = load_pose_prior(str(tmp_path / "missing.pt"))  # a checkpoint may fill it in; on its own, it raises
    with pytest.raises(FileNotFoundError, match="net.pose_prior: .*missing.pt not found; train one with"):
        placeholder(x)
    torch.save(trained.state_dict(), tmp_path / "bare.pt")
    with pytest.raises(ValueError, match="not a pose prior written by scripts/pose_prior.py"):
        load_pose_prior(str(tmp_path / "bare.pt"))


@pytest.mark.parametrize("payload, match", [
    ({"pytorch-lightning_version": "2.4.0", "state_dict": {"net.aggregator.camera_token": torch.zeros(1)}},
     "is a Lightning checkpoint .*not a pose prior; make one with `python scripts/pose_prior.py"),
    ({"state_dict": {"net.aggregator.camera_token": torch.zeros(1)}}, "is a Lightning checkpoint"),
    ({"state_dict": {}, "channels": "48"}, r"stores channels='48', expected an int in \[1, 1024\]"),
    ({"state_dict": {}, "channels": 200000, "grid": 12}, r"stores channels=200000, expected an int"),
    ({"state_dict": {}, "grid": True}, r"stores grid=True, expected an int"),
    ({"state_dict": {}, "image_size": 48}, r"stores image_size=48, expected \[H, W\]"),
    ({"state_dict": "weights"}, "not a pose prior written by scripts/pose_prior.py"),
    ("state", "weights of a PairFlowPose\\(channels=48, grid=12\\) \\(.*size mismatch.*\\); retrain it"),
])
def test_a_wrong_file_as_net_pose_prior_is_one_line_naming_it(tmp_path, payload, match):
    """Stage I's last.ckpt, or sizes that are not ints (or would allocate terabytes), or weights of another size:
    one line naming the file, never torch's many-line RuntimeError or a TypeError."""
    if payload == "state":  # weights of a 16-channel prior stored as the default 48-channel one
        payload = {"state_dict": PairFlowPose(channels=16, grid=12).state_dict()}
    path = tmp_path / "wrong.pt"
    torch.save(payload, path)
    with pytest.raises(ValueError, match=f"net.pose_prior: {re.escape(str(path))}.*{match}") as e:
        load_pose_prior(str(path))
    assert "\n" not in str(e.value)
    if "Lightning" in match:  # also when the network is built with it
        with pytest.raises(ValueError, match="is a Lightning checkpoint"):
            build_network("tiny", refine_cameras=True, camera_video=True, pose_prior=str(path))


def test_stage2_reads_the_frozen_prior_starts_at_the_scaffold_and_trains_only_its_own_mlp():
    torch.manual_seed(0)
    plain = build_network("tiny", refine_cameras=True, camera_video=True).state_dict()
    torch.manual_seed(0)
    net = build_network("tiny", refine_cameras=True, camera_video=True, pose_prior="random")
    own = net.state_dict()
    extra = {k for k in own if k not in plain}
    assert extra and all(k.startswith(("completion.camera_pose.", "pose_prior.")) for k in extra)
    assert all(torch.equal(own[k], v) for k, v in plain.items())  # every other init unchanged
    net.freeze_scaffold()
    trainable = {id(p) for p in net.refinement_parameters()}
    assert not any(id(p) in trainable or p.requires_grad for p in net.pose_prior.parameters())
    assert all(id(p) in trainable for p in net.completion.camera_pose.parameters())

    images = torch.rand(1, 4, 3, 48, 48)
    out = net(images, refine=True)
    torch.testing.assert_close(out["w2c"], out["scaffold_w2c"])  # the residual is zero-initialised

    # once trained, the residual depends on the prior's poses: another prior moves the re-placed cameras
    with torch.no_grad():
        net.completion.camera_proj.weight.normal_(0, 0.5)
        net.pose_prior.mlp[-1].bias.normal_(0, 0.3)
    out = net(images, refine=True)
    with torch.no_grad():
        net.pose_prior.mlp[-1].bias.normal_(0, 0.3)
    assert (net(images, refine=True)["w2c"] - out["w2c"]).abs().amax() > 1e-4
    out["pose_enc"].sum().backward()
    assert net.completion.camera_pose.fc1.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in net.pose_prior.parameters())
    with pytest.raises(ValueError, match="pose_prior: .*needs refine_cameras"):
        build_network("tiny", pose_prior="random")


def test_pose_prior_mix_starts_at_the_scaffold_and_learns_to_reach_the_priors_pose():
    torch.manual_seed(0)
    plain = build_network("tiny", refine_cameras=True, camera_video=True, pose_prior="random")
    torch.manual_seed(0)
    net = build_network("tiny", refine_cameras=True, camera_video=True, pose_prior="random", pose_prior_mix=True)
    own, before = net.state_dict(), plain.state_dict()
    assert {k for k in own if k not in before} == {"completion.camera_mix.weight", "completion.camera_mix.bias"}
    assert all(torch.equal(own[k], v) for k, v in before.items() if not k.startswith("pose_prior."))
    net.freeze_scaffold()
    assert all(id(p) in {id(q) for q in net.refinement_parameters()} for p in net.completion.camera_mix.parameters())
    with torch.no_grad():
        net.pose_prior.mlp[-1].bias.normal_(0, 0.3)  # a prior pose away from the scaffold's
    images = torch.rand(1, 4, 3, 48, 48)
    out = net(images, refine=True)
    assert torch.equal(out["w2c"], out["scaffold_w2c"])  # zero-initialised: exactly the scaffold's cameras
    assert len(out["pose_enc_list"]) == net.cfg.camera_iterations + 1  # the mix is one more step the loss sees
    out["w2c"].sum().backward()
    assert net.completion.camera_mix.bias.grad.abs().sum() > 0
    with torch.no_grad():
        net.completion.camera_mix.bias.fill_(1.0)  # all the way: the prior's rotations and translations
        torch.testing.assert_close(net(images, refine=True)["w2c"], net.pose_prior(images), atol=1e-5, rtol=0)
    net.completion.camera_mix.bias.grad = None
    with torch.autocast("cpu", dtype=torch.bfloat16):  # the CUDA runs' bf16-mixed: the poses stay float32
        out = net(images, refine=True)
    assert out["w2c"].dtype == torch.float32 and torch.isfinite(out["w2c"]).all()
    out["w2c"].sum().backward()
    assert net.completion.camera_mix.bias.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="pose_prior_mix: .*set net.pose_prior"):
        build_network("tiny", refine_cameras=True, pose_prior_mix=True)


def test_a_stage2_checkpoint_holds_its_prior_so_test_and_predict_need_no_file(tmp_path):
    """The prior's file is read to train; a checkpoint rebuilds the prior at its own size (here not the default)
    and needs no file, while training from scratch without it fails at once in one line."""
    from types import SimpleNamespace

    from anycity.lit import RefinementModule

    torch.manual_seed(1)
    trained = PairFlowPose(channels=16, grid=6)
    with torch.no_grad():
        trained.mlp[-1].bias.normal_(0, 0.3)
    path = tmp_path / "prior.pt"
    torch.save({"state_dict": trained.state_dict(), "channels": 16, "grid": 6, "image_size": [32, 32]}, path)
    net = {"refine_cameras": True, "camera_video": True, "pose_prior": str(path), "pose_prior_mix": True}
    torch.manual_seed(0)
    m = RefinementModule(net=net)
    with torch.no_grad():
        m.net.completion.camera_mix.weight.normal_(0, 0.3)  # the re-placed cameras follow the prior
    ckpt = {"state_dict": m.state_dict()}
    m.on_save_checkpoint(ckpt)
    assert ckpt["pose_prior"] == {"image_size": [32, 32]}
    images = torch.rand(1, 3, 3, 32, 32)
    with torch.no_grad():
        want = m.net(images, refine=True)["w2c"]

    path.unlink()  # another machine: the config still names the training machine's file
    fresh = RefinementModule(net=net)
    fresh._trainer = SimpleNamespace(ckpt_path=None, strategy=SimpleNamespace(restore_checkpoint_after_setup=False))
    fresh.setup("fit")  # whether the fit resumes is known once it starts
    with pytest.raises(FileNotFoundError, match="net.pose_prior: .*prior.pt not found; train one with"):
        fresh.on_fit_start()
    with pytest.raises(FileNotFoundError, match="need no file: it holds the prior"):
        fresh.net(images, refine=True)
    fresh.on_load_checkpoint(ckpt)
    fresh.load_state_dict(ckpt["state_dict"])  # strict: every key at its size
    prior = fresh.net.pose_prior
    assert prior.trained_hw == (32, 32) and not prior.training and not any(p.requires_grad for p in prior.parameters())
    with torch.no_grad():
        torch.testing.assert_close(fresh.net(images, refine=True)["w2c"], want)
    assert not any(p is q for p in prior.parameters() for q in fresh.net.refinement_parameters())
