"""Checkpoints reference the frozen Wan prior instead of copying it (10 GB in bf16).

Saving drops the prior's frozen weights (``net.video_prior.vae.*`` and every ``net.video_prior.transformer.*``
that is not a LoRA adapter) and records ``checkpoint["video_prior"] = {"dir", "sha256", "block"}``. Loading
checks that the prior this module was built from has the same content hash, then puts its frozen weights back
into the state dict, so Lightning's strict loading still catches every other missing or unexpected key. The
LoRA adapters, the completion branch and the scaffold stay in the checkpoint. Priors not loaded from a folder
(the small built-in one, the random ``wan-tiny``) are saved as they are. The Wan VAE's decoder is dropped when the
prior is built (it is never run); loading forgets its keys, which checkpoints saved before then carry.

The small frozen pose prior (``net.pose_prior``, beyond the paper) is the opposite: its weights (2 MB) travel in
the checkpoint, with ``checkpoint["pose_prior"] = {"image_size"}``, and loading rebuilds it at the size of
those weights. So ``test`` and ``predict`` from a Stage II checkpoint need neither its file nor its size.
"""

from __future__ import annotations

from torch import nn

from anycity.models.pose_prior import rebuild_pose_prior
from anycity.models.pretrained import check_video_prior_record
from anycity.models.video_prior import DROPPED_VAE_MODULES

PREFIX = "net.video_prior."
FROZEN = (PREFIX + "vae.", PREFIX + "transformer.")
DROPPED = tuple(f"{PREFIX}vae.{m}." for m in DROPPED_VAE_MODULES)


def _is_frozen_prior_key(key: str) -> bool:
    return key.startswith(FROZEN) and "lora_" not in key


def drop_frozen_prior(net: nn.Module, checkpoint: dict) -> None:
    prior = getattr(net, "video_prior", None)
    source = getattr(prior, "source", None)
    if source is None:
        return
    sd = checkpoint["state_dict"]
    for k in [k for k in sd if _is_frozen_prior_key(k)]:
        del sd[k]
    checkpoint["video_prior"] = {"dir": source["dir"], "sha256": prior.content_hash(), "block": int(prior.block)}


def forget_dropped_vae(net: nn.Module, checkpoint: dict) -> None:
    """Remove the Wan VAE decoder keys that checkpoints saved before it was dropped carry (a ``wan-tiny`` prior is
    saved whole), so strict loading still passes."""
    sd = checkpoint.get("state_dict", {})
    dropped = [k for k in sd if k.startswith(DROPPED)]
    if not dropped:  # every checkpoint saved since: no state dict of the network to build
        return
    own = net.state_dict(prefix="net.", keep_vars=True)
    for k in dropped:
        if k not in own:
            del sd[k]


def restore_frozen_prior(net: nn.Module, checkpoint: dict, where: str = "checkpoint") -> None:
    """Put the frozen prior's weights back (see the module docstring); one line naming ``where`` for a
    ``video_prior`` record that is not ``{"dir": str, "sha256": str, "block": int}`` (a damaged checkpoint)."""
    forget_dropped_vae(net, checkpoint)
    ref = checkpoint.get("video_prior")
    if ref is None:
        return
    check_video_prior_record(ref, where)
    prior = getattr(net, "video_prior", None)
    source = getattr(prior, "source", None)
    if source is None:
        raise ValueError(f"checkpoint: its video prior is Wan from {ref['dir']} (sha256 {ref['sha256'][:12]}), not "
                         "saved in the file; build the module with net.video_prior=wan and net.wan_dir=<that folder>")
    sha = prior.content_hash()
    if sha != ref["sha256"]:
        raise ValueError(f"checkpoint: Wan prior mismatch: trained with {ref['dir']} (sha256 {ref['sha256'][:12]}), "
                         f"got {source['dir']} (sha256 {sha[:12]}); point net.wan_dir at the same weights")
    if ref.get("block") is not None and int(prior.block) != int(ref["block"]):
        raise ValueError(f"checkpoint: trained on Wan block {ref['block']}, this module cuts at block {prior.block}; "
                         f"set net.wan_block={ref['block']}")
    sd = checkpoint["state_dict"]
    for k, v in net.state_dict(prefix="net.", keep_vars=False).items():
        if _is_frozen_prior_key(k) and k not in sd:
            sd[k] = v


POSE_PREFIX = "net.pose_prior."


def save_pose_prior_meta(net: nn.Module, checkpoint: dict) -> None:
    prior = getattr(net, "pose_prior", None)
    if prior is None:
        return
    hw = prior.trained_hw  # its file is in hyper_parameters; its size is that of its weights
    checkpoint["pose_prior"] = {"image_size": list(hw) if hw else None}


def restore_pose_prior(net: nn.Module, checkpoint: dict) -> None:
    """Rebuild ``net.pose_prior`` at the size of the checkpoint's weights (which ``load_state_dict`` then fills in),
    whether or not ``net.pose_prior``'s file was found when the network was built."""
    rebuild_pose_prior(net, checkpoint.get("state_dict", {}), POSE_PREFIX, checkpoint.get("pose_prior") or {})
