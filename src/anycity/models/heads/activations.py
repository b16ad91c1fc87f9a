"""Output activations of the heads (VGGT ``head_act``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def activate_pose(enc: Tensor, trans_act: str = "linear", quat_act: str = "linear", fov_act: str = "relu") -> Tensor:
    """``[..., 9]`` raw pose encoding -> activated (T, quaternion xyzw, FoV); VGGT uses linear/linear/relu."""
    parts = (enc[..., :3], enc[..., 3:7], enc[..., 7:])
    return torch.cat([_act(p, a) for p, a in zip(parts, (trans_act, quat_act, fov_act))], dim=-1)


def _act(x: Tensor, kind: str) -> Tensor:
    if kind == "linear":
        return x
    if kind == "relu":
        return F.relu(x)
    if kind == "exp":
        return torch.exp(x)
    if kind == "inv_log":
        return torch.sign(x) * torch.expm1(x.abs())
    raise ValueError(f"activation: expected linear|relu|exp|inv_log, got {kind!r}")


def activate_dense(out: Tensor, activation: str = "exp", conf_activation: str = "expp1") -> tuple[Tensor, Tensor]:
    """``[N, C, H, W]`` raw DPT output -> values ``[N, H, W, C-1]`` and confidence ``[N, H, W]`` (last channel)."""
    fmap = out.permute(0, 2, 3, 1)
    values, conf = _act(fmap[..., :-1], activation), fmap[..., -1]
    if conf_activation == "expp1":
        conf = 1 + conf.exp()
    elif conf_activation == "sigmoid":
        conf = torch.sigmoid(conf)
    else:
        raise ValueError(f"conf_activation: expected expp1|sigmoid, got {conf_activation!r}")
    return values, conf
