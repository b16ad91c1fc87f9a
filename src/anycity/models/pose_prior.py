"""A pretrained pair-correlation pose prior (beyond the paper) for Stage II's camera residual.

The tiny scaffold's camera head predicts nearly one mean relative pose per view position (docs/stage2.md). A
video model knows how frames move against each other; at quickstart scale no pretrained Wan exists, so this small
frozen module stands in for that knowledge of camera motion, learned beforehand from the training cities' poses
(``scripts/pose_prior.py``, :class:`anycity.lit.pose_prior.PosePriorModule`):

1. a 4-layer CNN gives each view a ``grid x grid`` map of unit features (stride 4, pooled to ``grid`` cells);
2. for each view i > 0 the soft-argmax of its feature correlation with view 0, both ways, gives two flow fields;
3. an MLP shared by every view, with no view index, maps them to view i's rotation (6-D) and translation in view
   0's frame. Reordering views 1..V-1 reorders the poses and changes nothing else: it does not need capture order.

With ``NetConfig.pose_prior`` the network loads it frozen, and each view's camera residual reads its pose
(:func:`pose_features`).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anycity.safe_load import safe_torch_load

POSE_FEATURES = 9  # 6-D rotation minus the identity's, and the translation
_MAX_CHANNELS, _MAX_GRID = 1024, 64  # far above any trained prior; refuses a size that would allocate terabytes


def rotation_6d(x: Tensor) -> Tensor:
    """``[..., 6]`` (two rows) -> rotation matrices ``[..., 3, 3]`` by Gram-Schmidt."""
    a = F.normalize(x[..., :3], dim=-1)
    b = F.normalize(x[..., 3:6] - (a * x[..., 3:6]).sum(-1, keepdim=True) * a, dim=-1)
    return torch.stack([a, b, torch.cross(a, b, dim=-1)], -2)


class PairFlowPose(nn.Module):
    """Images ``[B, V, 3, H, W]`` in [0, 1] -> ``w2c [B, V, 4, 4]`` of each view in view 0's frame (view 0: the
    identity), translations in the normalised scene units of the training samples.

    Args:
        channels: feature width of the CNN.
        grid: cells per side the stride-4 features are pooled to (12 = no pooling at 48 px).
    """

    def __init__(self, channels: int = 48, grid: int = 12):
        super().__init__()
        c, self.grid_size = channels, grid
        self.encoder = nn.Sequential(nn.Conv2d(3, 32, 3, 2, 1), nn.GELU(), nn.Conv2d(32, 48, 3, 1, 1), nn.GELU(),
                                     nn.Conv2d(48, c, 3, 2, 1), nn.GELU(), nn.Conv2d(c, c, 3, 1, 1))
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, grid), torch.linspace(-1, 1, grid), indexing="ij")
        self.register_buffer("grid", torch.stack([xs, ys], -1).reshape(-1, 2), persistent=False)
        self.temperature = nn.Parameter(torch.tensor(10.0))  # used /10: a slower step for the softmax sharpness
        self.mlp = nn.Sequential(nn.Linear(grid * grid * 10, 256), nn.GELU(), nn.Linear(256, 256), nn.GELU(),
                                 nn.Linear(256, 9))
        self.trained_hw: tuple[int, int] | None = None  # set by load_pose_prior; other sizes get one warning
        self.missing: str | None = None  # the file load_pose_prior did not find, until a checkpoint fills this in
        self._warned_size = False

    def flow(self, fa: Tensor, fb: Tensor) -> Tensor:
        """Unit features ``[B, P, C]`` of two views -> per cell of ``fa``: displacement, landing point (grid
        units, [-1, 1]) and correlation peak, ``[B, P, 5]``."""
        corr = torch.einsum("bpc,bqc->bpq", fa, fb) * (self.temperature / 10) / math.sqrt(fa.shape[-1])
        prob = corr.softmax(-1)
        land = prob @ self.grid
        return torch.cat([land - self.grid, land, prob.amax(-1, keepdim=True)], -1)

    def check_loaded(self) -> None:
        """Raise the one-line ``FileNotFoundError`` if this is :func:`load_pose_prior`'s placeholder for a
        missing file that no checkpoint has filled in."""
        if self.missing is not None:
            raise FileNotFoundError(_missing_message(self.missing))

    def forward(self, images: Tensor) -> Tensor:
        self.check_loaded()
        b, v = images.shape[:2]
        if self.trained_hw is not None and not self._warned_size and tuple(images.shape[-2:]) != self.trained_hw:
            h, w = self.trained_hw
            warnings.warn(f"net.pose_prior: trained on {h}x{w} views, given {images.shape[-2]}x{images.shape[-1]}; "
                          "its poses may be off: retrain it with scripts/pose_prior.py --image-size H W",
                          stacklevel=2)
            self._warned_size = True
        f = self.encoder(images.flatten(0, 1).float())
        if f.shape[-1] != self.grid_size or f.shape[-2] != self.grid_size:
            f = F.adaptive_avg_pool2d(f, self.grid_size)
        f = f.flatten(2).transpose(1, 2)
        f = (F.normalize(f, dim=-1) * math.sqrt(f.shape[-1])).view(b, v, self.grid_size ** 2, -1)
        w2c = torch.eye(4, device=images.device).repeat(b, v, 1, 1)
        if v == 1:
            return w2c
        x = torch.stack([torch.cat([self.flow(f[:, 0], f[:, i]), self.flow(f[:, i], f[:, 0])], -1).flatten(1)
                         for i in range(1, v)], 1)
        o = self.mlp(x)
        w2c[:, 1:, :3, :3] = rotation_6d(o[..., :6] + o.new_tensor([1, 0, 0, 0, 1, 0]))
        w2c[:, 1:, :3, 3] = o[..., 6:]
        return w2c


def pose_features(w2c: Tensor) -> Tensor:
    """``w2c [B, V, 4, 4]`` -> ``[B, V, 9]``: the rotation's first two rows minus the identity's, and the
    translation (all zero for the identity)."""
    eye = w2c.new_tensor([1.0, 0, 0, 0, 1, 0])
    return torch.cat([w2c[..., :2, :3].flatten(-2) - eye, w2c[..., :3, 3]], -1)


def _missing_message(path: str) -> str:
    return (f"net.pose_prior: {path} not found; train one with `python scripts/pose_prior.py --data DATA --out "
            "runs/pose_prior.pt`, pass the file with --model.init_args.net.pose_prior FILE, or leave pose_prior unset "
            "(test and predict from a Stage II checkpoint trained with a prior need no file: it holds the prior)")


def load_pose_prior(path: str) -> PairFlowPose:
    """A frozen :class:`PairFlowPose` in eval mode from ``path``: the ``.pt`` that ``scripts/pose_prior.py`` writes
    (``{"state_dict", "channels", "grid", ...}``), or ``"random"`` (random init: tests and smoke runs only).

    A missing file gives a placeholder (``prior.missing = path``) that raises on use: a Stage II checkpoint holds
    the prior's weights and :func:`anycity.lit.prior_ckpt.restore_pose_prior` replaces the placeholder, so ``test``
    and ``predict`` need no file."""
    if path == "random":
        prior = PairFlowPose()
    elif not Path(path).is_file():
        prior = PairFlowPose()
        prior.missing = path
    else:
        saved = safe_torch_load(path, what="net.pose_prior")
        channels, grid = _checked_sizes(path, saved)
        prior = PairFlowPose(channels, grid)
        try:
            prior.load_state_dict(saved["state_dict"])
        except RuntimeError as e:  # torch's message is one line per key: keep it to one
            detail = " ".join(line.strip() for line in str(e).splitlines()[1:])[:300]
            raise ValueError(f"net.pose_prior: {path} does not hold the weights of a PairFlowPose(channels={channels}, "
                             f"grid={grid}) ({detail}); retrain it with scripts/pose_prior.py") from None
        if saved.get("image_size"):
            prior.trained_hw = tuple(saved["image_size"])
    return prior.eval().requires_grad_(False)


def _checked_sizes(path: str, saved) -> tuple[int, int]:
    """``(channels, grid)`` of a loaded pose-prior file, or a one-line ``ValueError`` naming ``path``: not a dict
    with a ``state_dict`` (a Lightning checkpoint is told apart), or sizes that are not ints in a sane range."""
    retrain = "make one with `python scripts/pose_prior.py --data DATA --out runs/pose_prior.pt`"
    state = saved.get("state_dict") if isinstance(saved, dict) else None
    if not isinstance(state, dict):
        raise ValueError(f"net.pose_prior: {path} is not a pose prior written by scripts/pose_prior.py "
                         f"(no 'state_dict'); {retrain}")
    if "pytorch-lightning_version" in saved or any(str(k).startswith("net.") for k in state):
        raise ValueError(f"net.pose_prior: {path} is a Lightning checkpoint (e.g. a run's last.ckpt), not a pose "
                         f"prior; {retrain}")
    sizes = []
    for key, default, most in (("channels", 48, _MAX_CHANNELS), ("grid", 12, _MAX_GRID)):
        value = saved.get(key, default)
        if type(value) is not int or not 1 <= value <= most:
            raise ValueError(f"net.pose_prior: {path} stores {key}={value!r}, expected an int in [1, {most}]; "
                             f"{retrain}")
        sizes.append(value)
    image_size = saved.get("image_size")
    if image_size and not (isinstance(image_size, (list, tuple)) and len(image_size) == 2
                           and all(type(s) is int and s > 0 for s in image_size)):
        raise ValueError(f"net.pose_prior: {path} stores image_size={image_size!r}, expected [H, W] in pixels; "
                         f"{retrain}")
    return sizes[0], sizes[1]


def pose_prior_from_state(state: dict[str, Tensor], prefix: str, image_size=None) -> PairFlowPose:
    """A frozen, randomly initialised :class:`PairFlowPose` of the size the weights ``state[prefix + ...]`` have
    (channels from the last encoder conv, grid from the MLP's input), ready for ``load_state_dict``."""
    channels = state[prefix + "encoder.6.weight"].shape[0]
    grid = math.isqrt(state[prefix + "mlp.0.weight"].shape[1] // 10)
    prior = PairFlowPose(channels, grid)
    prior.trained_hw = tuple(image_size) if image_size else None
    return prior.eval().requires_grad_(False)


def rebuild_pose_prior(net: nn.Module, state: dict[str, Tensor], prefix: str, meta: dict) -> None:
    """Rebuild ``net.pose_prior`` at the size of the weights ``state[prefix + ...]`` (which ``load_state_dict``
    then fills in), whether or not its file was found when the network was built. ``meta``: a checkpoint's
    ``pose_prior`` record (its ``image_size``). Nothing to do without a pose prior or its weights."""
    old = getattr(net, "pose_prior", None)
    if old is None or prefix + "mlp.0.weight" not in state:
        return
    hw = meta.get("image_size", old.trained_hw if old.missing is None else None)
    net.pose_prior = pose_prior_from_state(state, prefix, hw).to(next(old.parameters()).device)
