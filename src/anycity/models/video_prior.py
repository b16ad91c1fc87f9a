"""Video priors: turn the V context views into feature tokens ``[B, L, D]`` for the completion branch.

``VideoPrior`` is the protocol (an ``nn.Module`` with ``out_dim`` and ``forward(images [B, V, 3, H, W] in
[0, 1]) -> [B, L, out_dim]``). Two implementations:

* :class:`SmallVideoPrior`: a light conv stem + spatio-temporal transformer, trained from scratch; used by the
  tiny/small presets and CPU training.
* :class:`WanVideoPrior`: a frozen Wan 2.x diffusion backbone from diffusers (``AutoencoderKLWan`` +
  ``WanTransformer3DModel`` cut after block ``k``). Each view is encoded as its own single-frame clip (the
  causal VAE would drop frames 1-3 of a 4-frame clip), latents are stacked as V frames, the transformer runs
  at timestep ``t_feat * 1000`` (default 0, clean) with an empty-text embedding (from a file, else zeros) and
  the hidden states of block ``k`` are taken by a forward hook. LoRA (peft) on ``attn1`` q/k/v/out is the
  only trainable part. Weights load from a local diffusers folder only (``HF_HUB_OFFLINE=1``). The VAE keeps only
  its encoder (the decoder is never run) and encodes one view at a time (diffusers' slicing).

This is the only module under ``anycity`` that imports diffusers (lazily).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anycity.atomic import atomic_write_bytes
from anycity.models.layers import Block
from anycity.safe_load import missing_reason, safe_torch_load, user_path

LORA_TARGETS = ("attn1.to_q", "attn1.to_k", "attn1.to_v", "attn1.to_out.0")
EMPTY_PROMPT_FILE = "empty_prompt.pt"
WEIGHTS_GLOB = "diffusion_pytorch_model*.safetensors"
# VAE parts the prior never runs, replaced by parameter-free stand-ins (Wan 2.2 TI2V-5B: 555M parameters, 2.2 GB in
# float32 on every GPU); checkpoints saved before they were dropped still carry their keys (lit/prior_ckpt.py)
DROPPED_VAE_MODULES = ("decoder", "post_quant_conv")
EVAL_NOISE_SEED = 0


def folder_hash(root: str | Path, subfolders: tuple[str, ...] = ("transformer", "vae")) -> str:
    """SHA-256 over the files of ``root/<subfolder>`` (relative names and bytes, sorted): identifies a frozen prior
    that checkpoints reference instead of copying. Reading every byte takes a while (about 10 GB for Wan 2.2
    TI2V-5B), so the result is cached in ``$XDG_CACHE_HOME/anycity/folder_hash.json`` under the folder's path,
    keyed by every file's name, size and modification time."""
    import hashlib
    import json

    root = Path(root).resolve()
    files = sorted(p for sub in subfolders for p in (root / sub).rglob("*") if p.is_file())
    key = [[str(f.relative_to(root)), f.stat().st_size, f.stat().st_mtime_ns] for f in files]
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "anycity" / "folder_hash.json"
    try:
        table = json.loads(cache.read_text())
    except (OSError, ValueError):
        table = {}
    hit = table.get(str(root))
    if hit and hit.get("key") == key:
        return hit["sha256"]
    h = hashlib.sha256()
    for f in files:
        h.update(str(f.relative_to(root)).encode() + b"\0")
        with open(f, "rb") as fh:
            while chunk := fh.read(1 << 24):
                h.update(chunk)
    table[str(root)] = {"key": key, "sha256": h.hexdigest()}
    try:  # temp file + rename: DDP ranks write it at once, and a reader must never see half a table
        atomic_write_bytes(cache, json.dumps(table).encode())
    except OSError:  # a read-only home is fine: the hash is just recomputed next time
        pass
    return table[str(root)]["sha256"]


@runtime_checkable
class VideoPrior(Protocol):
    out_dim: int

    def __call__(self, images: Tensor) -> Tensor: ...


def _frame_embedding(v: int, dim: int, device) -> Tensor:
    """``[v, dim]`` sin-cos embedding of the view index (the 'time' axis of the clip)."""
    freqs = torch.exp(-math.log(10000.0) * torch.arange(dim // 2, device=device) / max(dim // 2, 1))
    ang = torch.arange(v, device=device)[:, None] * freqs
    return torch.cat([ang.sin(), ang.cos()], dim=-1)


class SmallVideoPrior(nn.Module):
    """Conv stem (stride ``stride``) + ``depth`` transformer blocks over all views' tokens.

    ``[B, V, 3, H, W] -> [B, V * (H'/stride) * (W'/stride), dim]``: a side under ``stride`` (a very wide photo's
    height) is first resized up to ``stride`` (``H' = max(H, stride)``), as the Wan prior does.
    """

    def __init__(self, dim: int = 64, depth: int = 1, num_heads: int = 4, stride: int = 16):
        super().__init__()
        if stride not in (4, 8, 16, 32):
            raise ValueError(f"SmallVideoPrior: stride must be 4, 8, 16 or 32, got {stride}")
        if dim < 2 or dim % 2 or dim % num_heads:  # the frame embedding is sin-cos pairs: 2 * (dim // 2) channels
            raise ValueError(f"net.prior_dim: the small video prior needs an even width that its {num_heads} "
                             f"attention head(s) divide, got {dim}; use a multiple of 64 "
                             f"(e.g. {64 * max(1, round(dim / 64))})")
        self.out_dim, self.stride = dim, stride
        self.stem = nn.Sequential(nn.Conv2d(3, dim // 2, 4, 4), nn.GELU(),
                                  nn.Conv2d(dim // 2, dim, stride // 4, stride // 4))
        self.blocks = nn.ModuleList(Block(dim, num_heads, init_values=0.1) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)

    def forward(self, images: Tensor) -> Tensor:
        b, v, _, h, w = images.shape
        x = images.flatten(0, 1)
        if h < self.stride or w < self.stride:  # else the stem leaves no token
            size = (max(h, self.stride), max(w, self.stride))
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        x = self.stem(x * 2 - 1)  # [B*V, D, h, w]
        x = x.flatten(2).transpose(1, 2).unflatten(0, (b, v))  # [B, V, h*w, D]
        x = (x + _frame_embedding(v, self.out_dim, x.device)[None, :, None].to(x.dtype)).flatten(1, 2)
        for blk in self.blocks:
            x = blk(x)
        return self.norm(x)


def _diffusers():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # read at import time: set before diffusers loads the hub
    import diffusers

    return diffusers


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def _load_part(model_cls, root: Path, sub: str, ignore: tuple[str, ...] = (), **kwargs) -> nn.Module:
    """``model_cls.from_pretrained(root, subfolder=sub)`` from local files, refusing a folder without weights and
    one that lacks some of the model's weights (diffusers leaves those on the meta device, and the first forward
    then fails naming nothing). Keys starting with ``ignore`` may be missing. A file that does not parse (a damaged
    ``*.index.json`` raises a bare ``JSONDecodeError`` in diffusers) is one line naming the folder."""
    folder = root / sub
    try:
        model, info = model_cls.from_pretrained(root, subfolder=sub, local_files_only=True, output_loading_info=True,
                                                **kwargs)
    except (OSError, ValueError) as e:
        if isinstance(e, OSError) and not any(folder.glob("diffusion_pytorch_model*")):
            raise FileNotFoundError(f"Wan weights: no {WEIGHTS_GLOB} in {folder}; copy {sub}/ of the Diffusers-format "
                                    "Wan folder in full (config.json and its weight files)") from e
        why = _first_line(e)
        if isinstance(e, json.JSONDecodeError):  # names no file: the shard index is the one JSON diffusers reads bare
            index = sorted(p.name for p in folder.glob("*.index.json"))
            why = f"{index[0] if len(index) == 1 else 'a JSON file in it'} is not valid JSON ({why})"
        raise OSError(f"Wan weights: cannot load {folder}: {why}; copy {sub}/ of the Diffusers-format "
                      "Wan folder again") from e
    meta = [n for n, t in (*model.named_parameters(), *model.named_buffers()) if t.is_meta]
    missing = sorted(k for k in {*info["missing_keys"], *meta} if not k.startswith(ignore))
    if missing:
        raise ValueError(f"Wan weights: {folder} lacks {len(missing)} of the {model_cls.__name__} weights (e.g. "
                         f"{missing[:3]}); it is incomplete or another model's: copy {sub}/ of the Diffusers-format "
                         "Wan folder again")
    return model


def _as_empty_prompt(obj, text_dim: int, where: str) -> Tensor:
    """The text embedding of "" as ``[1, L, text_dim]``, from a ``[L, text_dim]`` or ``[1, L, text_dim]`` tensor, or
    from the ``(prompt_embeds, negative_prompt_embeds)`` pair ``WanPipeline.encode_prompt`` returns (its first)."""
    if isinstance(obj, (tuple, list)) and len(obj) == 2 and isinstance(obj[0], Tensor):
        obj = obj[0]
    fits = (isinstance(obj, Tensor) and obj.is_floating_point() and obj.shape[-1:] == (text_dim,)
            and (obj.ndim == 2 or (obj.ndim == 3 and obj.shape[0] == 1)) and obj.shape[-2] > 0)
    finite = fits and bool(torch.isfinite(obj).all())
    if not finite:
        got = f"{list(obj.shape)} {obj.dtype}" if isinstance(obj, Tensor) else type(obj).__name__
        got += " with non-finite values" if fits else ""
        raise ValueError(f"{where}: expected the umT5 embedding of '' as a finite [1, L, {text_dim}] float tensor "
                         f"(torch.save), got {got}; save WanPipeline.encode_prompt('')[0] of this Wan model")
    return obj.reshape(1, -1, text_dim)


class _Dropped(nn.Module):
    """Parameter-free stand-in for a VAE part the prior never runs (:data:`DROPPED_VAE_MODULES`)."""

    def forward(self, *args, **kwargs):
        raise RuntimeError("WanVideoPrior: its VAE decoder was dropped (the prior only encodes); decode with an "
                           "AutoencoderKLWan loaded on its own")


def _encoder_only(vae: nn.Module) -> nn.Module:
    """Drop the decoder and turn slicing on: encoding all B*V frames at once keeps diffusers' causal-conv cache
    of every conv input for all of them (about 16 GB for 64 views at 448 px with Wan 2.2's VAE, 0.26 GB sliced)."""
    for name in DROPPED_VAE_MODULES:
        setattr(vae, name, _Dropped())
    vae.enable_slicing()
    return vae


class WanVideoPrior(nn.Module):
    """Frozen Wan VAE + transformer (truncated after ``block``) with optional LoRA; see the module docstring.

    Args:
        vae: an ``AutoencoderKLWan``; transformer: a ``WanTransformer3DModel`` (both frozen here; the VAE loses its
            decoder and encodes with slicing on, the transformer loses the blocks after ``block``).
        block: index of the transformer block whose output is returned; later blocks are dropped. None: the middle
            block, ``(n - 1) // 2`` of n (14 of Wan 2.2 TI2V-5B's 30).
        t_feat: noise level s in [0, 1]; latents become ``(1-s) z + s eps`` and the timestep ``1000 s`` (eps fixed
            in eval mode: see :meth:`_noise`).
        empty_prompt: ``[1, L, text_dim]`` text embedding of "" (zeros ``[1, 1, text_dim]`` if None); also
            ``[L, text_dim]`` or ``encode_prompt``'s ``(embeds, negative)`` pair, whose first is used.
    """

    def __init__(self, vae: nn.Module, transformer: nn.Module, block: int | None = None, t_feat: float = 0.0,
                 empty_prompt: Tensor | None = None):
        super().__init__()
        n = len(transformer.blocks)
        block = (n - 1) // 2 if block is None else block
        if not 0 <= block < n:
            raise ValueError(f"WanVideoPrior: block must be in [0, {n - 1}] for this transformer, got {block}")
        if not 0.0 <= t_feat <= 1.0:
            raise ValueError(f"WanVideoPrior: t_feat is a noise level in [0, 1], got {t_feat}")
        transformer.blocks = nn.ModuleList(list(transformer.blocks)[: block + 1])
        self.vae, self.transformer = _encoder_only(vae).requires_grad_(False), transformer.requires_grad_(False)
        self.t_feat = t_feat
        cfg = transformer.config
        self.out_dim = cfg.num_attention_heads * cfg.attention_head_dim
        self.stride = (vae.config.scale_factor_spatial or 8) * cfg.patch_size[1]
        text = (torch.zeros(1, 1, cfg.text_dim) if empty_prompt is None
                else _as_empty_prompt(empty_prompt, cfg.text_dim, "WanVideoPrior: empty_prompt"))
        self.register_buffer("empty_prompt", text.float(), persistent=False)
        self._feat: Tensor | None = None
        self.block = block
        self.transformer.blocks[block].register_forward_hook(self._grab)
        self.source: dict | None = None  # {"dir", "subfolders"} when loaded from a folder
        self._sha256: str | None = None

    def _grab(self, module, args, output) -> None:
        self._feat = output

    @classmethod
    def from_pretrained(cls, root: str | Path, subfolder: str = "transformer", vae_subfolder: str = "vae",
                        dtype: torch.dtype = torch.bfloat16, empty_prompt_path: str | Path | None = None,
                        **kwargs) -> WanVideoPrior:
        """Load from a local Diffusers-format folder (e.g. ``Wan2.2-TI2V-5B-Diffusers``; ``~`` expanded); never
        downloads."""
        root = user_path(root)
        if not root.is_dir() and (why := missing_reason(root)) not in (None, "not found"):
            raise FileNotFoundError(f"Wan weights: {root} {why}")
        for sub in (subfolder, vae_subfolder):
            if not (root / sub / "config.json").is_file():
                raise FileNotFoundError(f"Wan weights: {root / sub / 'config.json'} not found; point wan_dir at a "
                                        "local Diffusers-format Wan folder (with transformer/ and vae/)")
        d = _diffusers()
        # `torch_dtype`: the name every diffusers we allow (>= 0.35, the first with the Wan 2.2 VAE) reads; `dtype=`
        # only arrived later, and an older diffusers would ignore it and load 5B parameters in float32 (20 GB)
        tr = _load_part(d.WanTransformer3DModel, root, subfolder, torch_dtype=dtype)
        vae = _load_part(d.AutoencoderKLWan, root, vae_subfolder, ignore=tuple(f"{m}." for m in DROPPED_VAE_MODULES),
                         torch_dtype=torch.float32)
        got = tr.blocks[0].attn1.to_q.weight.dtype  # (diffusers keeps a few norm/time modules in float32 on purpose)
        if got != dtype:
            raise RuntimeError(f"Wan weights: transformer loaded as {got}, asked for {dtype}; upgrade diffusers "
                               "(pip install -e '.[wan]')")
        prompt = None
        if empty_prompt_path is None and (root / EMPTY_PROMPT_FILE).is_file():
            empty_prompt_path = root / EMPTY_PROMPT_FILE
        if empty_prompt_path is not None:
            empty_prompt_path = user_path(empty_prompt_path)
            if not empty_prompt_path.is_file():
                raise FileNotFoundError(f"empty_prompt_path: {empty_prompt_path} not found; precompute the umT5 "
                                        "embedding of '' as a [1, L, text_dim] tensor or pass None for zeros")
            prompt = _as_empty_prompt(safe_torch_load(empty_prompt_path, what="empty_prompt_path"),
                                      tr.config.text_dim, f"empty prompt file {empty_prompt_path}")
        prior = cls(vae, tr, empty_prompt=prompt, **kwargs)
        prior.source = {"dir": str(root), "subfolders": (subfolder, vae_subfolder)}
        return prior

    def content_hash(self) -> str | None:
        """SHA-256 of the weights folder this prior was loaded from (None for a prior built in memory); computed
        on first use, i.e. when a checkpoint is saved or loaded, not at construction."""
        if self.source is None:
            return None
        if self._sha256 is None:
            self._sha256 = folder_hash(self.source["dir"], tuple(self.source["subfolders"]))
        return self._sha256

    @staticmethod
    def tiny_parts(z_dim: int = 16) -> tuple[nn.Module, nn.Module]:
        """Random tiny Wan 2.2-style ``(AutoencoderKLWan, WanTransformer3DModel)`` (~0.2M + ~40k parameters), whole
        (decoder and all 4 blocks kept): what a test saves as a Diffusers folder."""
        d = _diffusers()
        vae = d.AutoencoderKLWan(base_dim=8, decoder_base_dim=8, z_dim=z_dim, in_channels=12, out_channels=12,
                                 is_residual=True, patch_size=2, dim_mult=[1, 2, 2, 2], num_res_blocks=1,
                                 temperal_downsample=[False, True, True], scale_factor_spatial=16,
                                 scale_factor_temporal=4, latents_mean=[0.0] * z_dim, latents_std=[1.0] * z_dim)
        tr = d.WanTransformer3DModel(patch_size=(1, 2, 2), num_attention_heads=2, attention_head_dim=12,
                                     in_channels=z_dim, out_channels=z_dim, text_dim=32, freq_dim=32, ffn_dim=48,
                                     num_layers=4, cross_attn_norm=True, qk_norm="rms_norm_across_heads",
                                     rope_max_seq_len=32)
        return vae, tr

    @classmethod
    def tiny_random(cls, z_dim: int = 16, block: int = 1, **kwargs) -> WanVideoPrior:
        """A prior on :meth:`tiny_parts`, for tests; no weights needed."""
        return cls(*cls.tiny_parts(z_dim), block=block, **kwargs)

    # LoRA --------------------------------------------------------------------------------------------------
    def add_lora(self, rank: int = 16, alpha: float | None = None, targets: tuple[str, ...] = LORA_TARGETS) -> None:
        """Inject LoRA into the kept blocks' ``targets`` (fp32 adapters); only ``lora_`` params train."""
        from peft import LoraConfig

        self.transformer.add_adapter(LoraConfig(r=rank, lora_alpha=alpha or rank, target_modules=list(targets)))
        for name, p in self.transformer.named_parameters():
            p.requires_grad_("lora_" in name)
            if "lora_" in name:  # float32 whatever the prior's dtype: a bf16 lora_A would round its small updates away
                p.data = p.data.float()

    def lora_state_dict(self) -> dict[str, Tensor]:
        from peft.utils import get_peft_model_state_dict

        sd = get_peft_model_state_dict(self.transformer)
        if not sd:
            raise ValueError("WanVideoPrior: no LoRA adapter to save; call add_lora() first")
        return sd

    def save_lora(self, path: str | Path) -> None:
        from safetensors.torch import save_file

        save_file({k: v.detach().contiguous().cpu() for k, v in self.lora_state_dict().items()}, str(path))

    def load_lora(self, path: str | Path) -> None:
        """Load the adapters :meth:`save_lora` wrote. Every adapter of this prior must be in the file, at its shape,
        finite, and nothing else: one line naming the file otherwise (a truncated file included)."""
        from peft.utils import set_peft_model_state_dict
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        from anycity.models.pretrained import first_nonfinite, weight_problems

        path = user_path(path)
        if not path.is_file():
            why = missing_reason(path) or "is not a file"
            raise FileNotFoundError(f"LoRA weights: {path} {why}; save them with save_lora() first")
        own = self.lora_state_dict()  # raises if no adapter was injected
        fix = "save them with save_lora() from a prior with the same LoRA rank, targets and Wan block"
        try:
            sd = load_file(str(path))
        except SafetensorError as e:
            raise ValueError(f"LoRA weights {path}: cannot read it ({_first_line(e)}); the file is truncated or not "
                             f"a safetensors file: {fix}") from None
        problems = weight_problems(own, sd)
        if problems:
            raise ValueError(f"LoRA weights {path} do not fit this prior's adapters: {'; '.join(problems)}; {fix}")
        if (bad := first_nonfinite(sd)) is not None:
            raise ValueError(f"LoRA weights {path} hold non-finite values (NaN or Inf) in {bad}; the run that saved "
                             "them diverged: use an earlier file")
        try:
            result = set_peft_model_state_dict(self.transformer, sd)
        except (RuntimeError, ValueError, KeyError) as e:
            raise ValueError(f"LoRA weights {path}: {_first_line(e)}; {fix}") from None
        if getattr(result, "unexpected_keys", None):
            raise ValueError(f"LoRA weights {path}: unexpected keys {result.unexpected_keys[:3]}...; {fix}")

    # forward -----------------------------------------------------------------------------------------------
    def _noise(self, z: Tensor) -> Tensor:
        """Gaussian noise like ``z`` for ``t_feat > 0``: fresh in training; in eval drawn from a generator seeded
        with :data:`EVAL_NOISE_SEED` on every call, so validation/test/predict features repeat run to run."""
        if self.training:
            return torch.randn_like(z)
        g = torch.Generator(device=z.device).manual_seed(EVAL_NOISE_SEED)
        return torch.randn(z.shape, generator=g, device=z.device, dtype=z.dtype)

    def forward(self, images: Tensor) -> Tensor:
        """``[B, V, 3, H, W]`` in [0, 1] -> ``[B, V * (H'/s) * (W'/s), out_dim]`` (H', W' rounded to the stride s)."""
        b, v, _, h, w = images.shape
        s = self.stride
        size = (max(s, round(h / s) * s), max(s, round(w / s) * s))
        x = images.flatten(0, 1)
        if (h, w) != size:
            x = F.interpolate(x, size=size, mode="bilinear", antialias=True, align_corners=False)
        x = (x * 2 - 1)[:, :, None].to(next(self.vae.parameters()).dtype)  # [B*V, 3, 1, H, W]
        with torch.no_grad():
            z = self.vae.encode(x).latent_dist.mode()
            cfg = self.vae.config
            mean = torch.tensor(cfg.latents_mean, device=z.device, dtype=z.dtype).view(1, -1, 1, 1, 1)
            std = torch.tensor(cfg.latents_std, device=z.device, dtype=z.dtype).view(1, -1, 1, 1, 1)
            z = ((z - mean) / std)[:, :, 0].unflatten(0, (b, v)).transpose(1, 2)  # [B, z, V, h, w]
            if self.t_feat > 0:
                z = (1 - self.t_feat) * z + self.t_feat * self._noise(z)
        dtype = self.transformer.dtype
        t = torch.full((b,), self.t_feat * 1000.0, device=z.device)
        text = self.empty_prompt.to(device=z.device, dtype=dtype).expand(b, -1, -1)
        self._feat = None
        self.transformer(hidden_states=z.to(dtype), timestep=t, encoder_hidden_states=text, return_dict=False)
        feat, self._feat = self._feat, None
        return feat.float()


def build_video_prior(kind: str, dim: int = 64, depth: int = 1, num_heads: int = 4, stride: int = 16,
                      wan_dir: str | None = None, **wan_kwargs) -> nn.Module | None:
    """``kind``: ``"small"`` (built-in), ``"wan"`` (needs ``wan_dir``), ``"wan-tiny"`` (random, tests) or ``"none"``."""
    if kind == "none":
        return None
    if kind == "small":
        return SmallVideoPrior(dim, depth, num_heads, stride)
    if kind == "wan":
        if not wan_dir:
            raise ValueError("video_prior='wan' needs wan_dir=<local Diffusers Wan folder>; or use 'small'")
        return WanVideoPrior.from_pretrained(wan_dir, **wan_kwargs)
    if kind == "wan-tiny":
        return WanVideoPrior.tiny_random(**wan_kwargs)
    raise ValueError(f"video_prior: expected 'small', 'wan', 'wan-tiny' or 'none', got {kind!r}")
