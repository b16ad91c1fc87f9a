"""Static GPU memory and checkpoint size of the two paper stages, counted on the meta device (no weights, no RAM).

    python benchmarks/memory.py

Stage I: ``vggt-1b``, no completion branch, everything trainable (stage1.yaml). Stage II: the same scaffold frozen,
the completion branch and the Wan 2.2 TI2V-5B prior (bf16, cut after ``wan_block`` = the middle block, LoRA r=16 in
float32 on attn1 q/k/v/out of the kept blocks) (stage2.yaml). Wan's modules are built from its published
Diffusers configs, so no weights are needed.

Counted: weights (float32, Wan bf16 except the modules diffusers keeps in float32), gradients (float32, trainable
only), AdamW moments (2 x float32, trainable only), with Lightning ``bf16-mixed`` (float32 master weights). Not
counted: activations, autocast weight copies, DDP buckets, the CUDA context (see docs/cluster.md and
/work/shared/research/cluster.md section 4). Checkpoint: what ``last.ckpt`` holds, i.e. the state dict (Stage II:
without the frozen Wan weights, which it references by folder + sha256) plus the AdamW moments.
"""

from __future__ import annotations

from unittest import mock

import torch

GB = 1e9

# Wan2.2-TI2V-5B-Diffusers transformer/config.json and vae/config.json (the fields that set parameter shapes)
WAN22_5B_TRANSFORMER = dict(patch_size=(1, 2, 2), num_attention_heads=24, attention_head_dim=128, in_channels=48,
                            out_channels=48, text_dim=4096, freq_dim=256, ffn_dim=14336, num_layers=30,
                            cross_attn_norm=True, qk_norm="rms_norm_across_heads", eps=1e-6, rope_max_seq_len=1024)
WAN22_VAE = dict(base_dim=160, decoder_base_dim=256, z_dim=48, dim_mult=[1, 2, 4, 4], num_res_blocks=2,
                 attn_scales=[], temperal_downsample=[False, True, True], dropout=0.0, is_residual=True,
                 in_channels=12, out_channels=12, patch_size=2, scale_factor_spatial=16, scale_factor_temporal=4)


def keep_fp32_modules(model):
    """Put the parameters of ``model._keep_in_fp32_modules`` back to float32 after a cast, as diffusers'
    ``from_pretrained(torch_dtype=...)`` keeps them (its rule: a listed name is one of the parameter name's
    dot-separated parts); ``.to(dtype)`` alone casts them too."""
    keep = set(getattr(model, "_keep_in_fp32_modules", None) or ())
    for name, p in model.named_parameters():
        if keep & set(name.split(".")):
            p.data = p.data.float()
    return model


def _meta_wan(block=None, lora_rank=16):
    import diffusers

    from anycity.models.video_prior import WanVideoPrior

    diffusers.utils.logging.set_verbosity_error()  # .to(bf16) on meta: its "keep some modules in fp32" notice
    with torch.device("meta"):
        tr = keep_fp32_modules(diffusers.WanTransformer3DModel(**WAN22_5B_TRANSFORMER).to(torch.bfloat16))
        vae = diffusers.AutoencoderKLWan(**WAN22_VAE, latents_mean=[0.0] * 48, latents_std=[1.0] * 48)
        full = sum(p.numel() for p in tr.parameters())
        prior = WanVideoPrior(vae, tr, block=block)
        if lora_rank:
            prior.add_lora(lora_rank)
    return prior, full


def stage_modules():
    """``{"Stage I": net, "Stage II": net}`` on the meta device, trainable flags as in training; and Wan's size."""
    from anycity.models import build_network

    with torch.device("meta"):
        s1 = build_network("vggt-1b", completion=False)
    prior, wan_full = _meta_wan(lora_rank=0)  # the network adds the LoRA (NetConfig.wan_lora_rank = 16)
    with mock.patch("anycity.models.anycity.build_video_prior", lambda *a, **k: prior), torch.device("meta"):
        s2 = build_network("vggt-1b", completion=True, video_prior="wan", wan_dir="(meta)")
    s2.freeze_scaffold()
    return {"Stage I": s1, "Stage II": s2}, wan_full


def _bytes(p: torch.Tensor) -> int:
    return p.numel() * p.element_size()


def account(net) -> dict[str, float]:
    params = list(net.named_parameters())
    trainable = [p for _, p in params if p.requires_grad]
    frozen_prior = [p for n, p in params if n.startswith(("video_prior.vae.", "video_prior.transformer."))
                    and "lora_" not in n]
    n_train = sum(p.numel() for p in trainable)
    weights = sum(_bytes(p) for _, p in params)
    grads = sum(p.numel() * 4 for p in trainable)
    adam = 2 * grads
    ckpt = weights - sum(_bytes(p) for p in frozen_prior) + adam
    return {"params": sum(p.numel() for _, p in params), "trainable": n_train, "weights": weights, "grads": grads,
            "adam": adam, "static": weights + grads + adam, "ckpt": ckpt}


def main() -> None:
    nets, wan_full = stage_modules()
    print(f"Wan 2.2 TI2V-5B transformer (all 30 blocks): {wan_full / 1e9:.3f} B params; "
          f"kept up to block {nets['Stage II'].video_prior.block} "
          f"({len(nets['Stage II'].video_prior.transformer.blocks)} blocks)")
    print("| stage | params (B) | trainable (M) | weights GB | grads GB | AdamW GB | static total GB | last.ckpt GB |")
    print("|---|---|---|---|---|---|---|---|")
    for name, net in nets.items():
        a = account(net)
        print(f"| {name} | {a['params'] / 1e9:.3f} | {a['trainable'] / 1e6:.1f} | {a['weights'] / GB:.2f} | "
              f"{a['grads'] / GB:.2f} | {a['adam'] / GB:.2f} | {a['static'] / GB:.2f} | {a['ckpt'] / GB:.2f} |")
    print("GB = 1e9 bytes; static = weights + grads + AdamW (no activations); bf16-mixed keeps float32 masters.")


if __name__ == "__main__":
    main()
