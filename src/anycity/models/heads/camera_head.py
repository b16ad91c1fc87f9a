"""Camera head (VGGT ``CameraHead``): 9-D pose encoding refined iteratively with an adaLN-modulated trunk.

Reads the camera token (index 0) of the last aggregator layer ``[B, V, 2C]``. Each iteration embeds the
previous (detached) encoding, modulates the normalised tokens (shift, scale, gate), runs a small transformer
across the V views and adds a predicted delta to the encoding. Returns one activated ``[B, V, 9]`` encoding
per iteration (translation and quaternion linear, FoV ReLU); the quaternion is xyzw and not normalised.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from anycity.models.heads.activations import activate_pose
from anycity.models.layers import Block, Mlp


class CameraHead(nn.Module):
    def __init__(self, dim_in: int = 2048, trunk_depth: int = 4, num_heads: int = 16, mlp_ratio: float = 4.0,
                 init_values: float = 0.01):
        super().__init__()
        self.target_dim = 9
        self.trunk = nn.Sequential(*[Block(dim_in, num_heads, mlp_ratio, init_values=init_values)
                                     for _ in range(trunk_depth)])
        self.token_norm = nn.LayerNorm(dim_in)
        self.trunk_norm = nn.LayerNorm(dim_in)
        self.empty_pose_tokens = nn.Parameter(torch.zeros(1, 1, self.target_dim))
        self.embed_pose = nn.Linear(self.target_dim, dim_in)
        self.poseLN_modulation = nn.Sequential(nn.SiLU(), nn.Linear(dim_in, 3 * dim_in))
        self.adaln_norm = nn.LayerNorm(dim_in, elementwise_affine=False, eps=1e-6)
        self.pose_branch = Mlp(dim_in, dim_in // 2, self.target_dim)

    def init_pose_bias(self, fov: float = 1.0, iterations: int = 4) -> None:
        """Random init only: bias the output towards an identity rotation and a ``fov``-radian field of view.
        With VGGT's init the ReLU FoV starts at 0 for about half the outputs (infinite focal length, no gradient)
        and a zero quaternion has no rotation. Each iteration adds its output, so the bias is spread over them."""
        fc2 = self.pose_branch.fc2
        iters = max(1, int(iterations))
        with torch.no_grad():
            fc2.weight[3:9].mul_(0.01)
            fc2.bias[3:9] = 0.0
            fc2.bias[6] = 1.0 / iters  # quaternion xyzw: w
            fc2.bias[7:9] = fov / iters

    def forward(self, tokens_list: list[Tensor | None], num_iterations: int = 4) -> list[Tensor]:
        tokens = self.token_norm(tokens_list[-1][:, :, 0])
        b, v, _ = tokens.shape
        enc, out = None, []
        for _ in range(num_iterations):
            cond = self.embed_pose(self.empty_pose_tokens.expand(b, v, -1) if enc is None else enc.detach())
            shift, scale, gate = self.poseLN_modulation(cond).chunk(3, dim=-1)
            x = gate * (self.adaln_norm(tokens) * (1 + scale) + shift) + tokens
            delta = self.pose_branch(self.trunk_norm(self.trunk(x)))
            enc = delta if enc is None else enc.detach() + delta  # VGGT: no gradient across iterations
            out.append(activate_pose(enc))
        return out
