"""Aerial completion branch (Stage II): M learned tokens that read the geometry and the video prior and
write a zero-initialised residual ΔZ into the geometry tokens the Gaussian head reads.

At each injection layer l (paper {4, 7, 11, 23} of 24):
``Z~ = Z + CrossAttn(Z, Z_geo^l)``; ``g = sigmoid(h(Z~))`` per token; ``Z = Z~ + g * CrossAttn(Z~, P_vid(F_vid))``;
``Z = Z + FFN(Z)``. Then ``P_Δ``: for each head layer j the patch tokens of ``Z_geo^j`` query the completion
tokens and a zero-initialised linear maps the result to the token width, so ``Z_final = Z_geo + ΔZ`` equals
``Z_geo`` at initialisation (Stage II starts exactly at the scaffold).

With ``camera=True`` (beyond the paper) the camera tokens of the last layer query the completion tokens the same
way and a zero-initialised linear gives their residual ``ΔZ_cam``, so the frozen camera head can re-place the views.
With ``camera_video=True`` each view's residual also reads that view's own video-prior features (its frame's
tokens, pooled): a video model knows where a frame sits in the clip, which the scaffold, equivariant over views
1..V-1, cannot tell, and on a flight path the order carries the relative pose.
With ``camera_pose=True`` each view's residual also reads a pose prior's estimate of that view's pose
(:func:`anycity.models.pose_prior.pose_features`), through a small MLP. With ``camera_mix=True`` a zero-initialised
linear of the camera residual's features (those the projection reads) also gives, per view, how far the re-placed
pose moves towards the prior's (translation, rotation), so the network can take the prior's pose itself rather
than re-derive it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from anycity.models.layers import CrossAttention, Mlp
from anycity.models.pose_prior import POSE_FEATURES


def scale_layers(layers: tuple[int, ...], depth: int, ref_depth: int = 24) -> tuple[int, ...]:
    """Map layer indices of a ``ref_depth`` network to a ``depth`` one (same relative position), unique, sorted.

    Layer ``l`` goes to ``round((l + 1) * depth / ref_depth) - 1``, clamped to ``0..depth-1``, with Python's
    ``round`` (half to even: 2.5 -> 2). Indices that land on the same layer are merged, so a shallow network can get
    fewer layers than it was given: the paper's injection layers (4, 7, 11, 23) become (0, 1, 3) at depth 4 (the
    tiny preset has 3 injection stages, not 4), (1, 2, 3, 7) at depth 8 and (1, 3, 5, 11) at depth 12; VGGT's head
    layers (4, 11, 17, 23) become (0, 1, 2, 3), (1, 3, 5, 7) and (1, 5, 8, 11). Kept as it is: trained
    checkpoints (the quickstart's) depend on it; pass ``inject_layers`` / ``head_layers`` to choose others.
    """
    return tuple(sorted({min(depth - 1, max(0, round((l + 1) * depth / ref_depth) - 1)) for l in layers}))


class CompletionBranch(nn.Module):
    """Args: geo_dim (2C of the aggregator), dim, num_tokens M, inject_layers, head_layers (those the Gaussian
    head reads), video_dim (None: no video cross-attention), camera (also a residual for the camera tokens),
    camera_video (that residual also reads each view's pooled video features; needs camera and video_dim),
    camera_pose (that residual also reads each view's pose-prior features ``[B, V, 9]``; needs camera),
    camera_mix (also per-view weights towards the prior's pose; needs camera_pose)."""

    def __init__(self, geo_dim: int, dim: int, num_tokens: int, num_heads: int, inject_layers: tuple[int, ...],
                 head_layers: tuple[int, ...], video_dim: int | None = None, camera: bool = False,
                 camera_video: bool = False, camera_pose: bool = False, camera_mix: bool = False):
        super().__init__()
        self.inject_layers, self.head_layers = tuple(inject_layers), tuple(head_layers)
        self.tokens = nn.Parameter(torch.randn(1, num_tokens, dim) * 0.02)
        n = len(self.inject_layers)
        self.geo_attn = nn.ModuleList(CrossAttention(dim, geo_dim, dim, num_heads) for _ in range(n))
        self.p_vid = nn.Linear(video_dim, dim) if video_dim else None
        self.vid_attn = nn.ModuleList(CrossAttention(dim, dim, dim, num_heads) for _ in range(n)) if video_dim else None
        self.gate = nn.ModuleList(nn.Linear(dim, 1) for _ in range(n)) if video_dim else None
        self.ffn_norm = nn.ModuleList(nn.LayerNorm(dim) for _ in range(n))
        self.ffn = nn.ModuleList(Mlp(dim, 2 * dim) for _ in range(n))
        self.delta_attn = nn.ModuleList(CrossAttention(geo_dim, dim, dim, num_heads) for _ in self.head_layers)
        self.delta_proj = nn.ModuleList(nn.Linear(dim, geo_dim) for _ in self.head_layers)
        # built last, so that turning it on leaves every other module's random init unchanged
        self.camera_attn = CrossAttention(geo_dim, dim, dim, num_heads) if camera else None
        self.camera_proj = nn.Linear(dim, geo_dim) if camera else None
        if camera_video and not (camera and video_dim):
            raise ValueError("camera_video: the camera residual reads the video prior; it needs refine_cameras and a "
                             "video prior (video_prior != 'none')")
        self.camera_vid = nn.Sequential(nn.LayerNorm(dim), Mlp(dim, 2 * dim, dim)) if camera_video else None
        if camera_pose and not camera:
            raise ValueError("pose_prior: the camera residual reads the pose prior; it needs refine_cameras: true")
        self.camera_pose = Mlp(POSE_FEATURES, dim, dim) if camera_pose else None
        if camera_mix and not camera_pose:
            raise ValueError("pose_prior_mix: the re-placed cameras move towards the pose prior's; set net.pose_prior")
        self.camera_mix = nn.Linear(dim, 2) if camera_mix else None
        for lin in [*self.delta_proj, self.camera_proj, self.camera_mix]:
            if lin is None:
                continue
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)

    def forward(self, tokens_list: list[Tensor | None], patch_start_idx: int, video_tokens: Tensor | None = None,
                pose: Tensor | None = None
                ) -> tuple[list[Tensor], list[Tensor] | None, Tensor | None, Tensor | None]:
        """``tokens_list``: aggregator outputs ``[B, V, T, 2C]``; ``video_tokens [B, L, D_vid]`` or None;
        ``pose [B, V, 9]``: the pose prior's features (read with ``camera_pose``), or None.

        Returns ``delta``: one ``[B, V, P, 2C]`` residual per head layer (P patch tokens); ``gates``: one
        ``[B, M, 1]`` per injection layer (None without video); ``camera_delta [B, V, 2C]``: the residual of the
        last layer's camera tokens (index 0), or None without ``camera``; ``camera_mix [B, V, 2]``: how far each
        view's pose moves towards the prior's (translation, rotation; zero at initialisation), or None.
        """
        b = tokens_list[self.head_layers[0]].shape[0]
        z = self.tokens.expand(b, -1, -1)
        vid = self.p_vid(video_tokens) if (self.p_vid is not None and video_tokens is not None) else None
        gates = [] if vid is not None else None
        for i, layer in enumerate(self.inject_layers):
            z = z + self.geo_attn[i](z, tokens_list[layer].flatten(1, 2))
            if vid is not None:
                g = torch.sigmoid(self.gate[i](z))
                z = z + g * self.vid_attn[i](z, vid)
                gates.append(g)
            z = z + self.ffn[i](self.ffn_norm[i](z))
        delta = []
        for j, layer in enumerate(self.head_layers):
            patches = tokens_list[layer][:, :, patch_start_idx:]
            q = patches.flatten(1, 2)
            delta.append(self.delta_proj[j](self.delta_attn[j](q, z)).view_as(patches))
        camera_delta = camera_mix = None
        if self.camera_attn is not None:
            cam = self.camera_attn(tokens_list[-1][:, :, 0], z)  # [B, V, dim]
            if self.camera_vid is not None and vid is not None:
                v = cam.shape[1]
                if vid.shape[1] % v:
                    raise ValueError(f"camera_video: {vid.shape[1]} video tokens do not split into {v} frames")
                cam = cam + self.camera_vid(vid.unflatten(1, (v, -1)).mean(2))  # each view's own frame
            if self.camera_pose is not None:
                if pose is None:
                    raise ValueError("camera_pose: the completion branch needs the pose prior's features")
                cam = cam + self.camera_pose(pose.to(cam.dtype))
            camera_delta = self.camera_proj(cam)
            if self.camera_mix is not None:
                camera_mix = self.camera_mix(cam)
        return delta, gates, camera_delta, camera_mix
