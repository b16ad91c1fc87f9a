"""Transformer building blocks shared by the aggregator, heads and completion branch."""

from anycity.models.layers.attention import Attention, CrossAttention
from anycity.models.layers.block import Block, LayerScale
from anycity.models.layers.mlp import Mlp
from anycity.models.layers.patch_embed import PatchEmbed
from anycity.models.layers.rope import RoPE2D, patch_positions
from anycity.models.layers.vit import DinoViT, build_vit

__all__ = ["Attention", "CrossAttention", "Block", "LayerScale", "Mlp", "PatchEmbed", "RoPE2D", "patch_positions",
           "DinoViT", "build_vit"]
