"""Load VGGT-1B or AnySplat weights into an :class:`AnyCityNet` (local files only, never the network).

Key map (documented, nothing else is renamed):

* ``kind="vggt"``: a plain ``model.pt`` state dict (or safetensors). ``aggregator.*``, ``camera_head.*`` and
  ``depth_head.*`` load as they are; ``point_head.*`` and ``track_head.*`` have no counterpart and are
  reported as unexpected.
* ``kind="anysplat"``: optional Lightning ``state_dict`` nesting and ``model.`` prefix, then ``encoder.`` is
  stripped and ``gaussian_param_head.`` becomes ``gaussian_head.``; ``distill_*`` teacher copies are
  reported as unexpected. bf16 tensors are cast to the network's dtype.

Tensors whose shape differs from the network's are skipped and listed (a mismatch never breaks the net).
:meth:`LoadReport.require_backbone` (which the Lightning modules call) then insists on the whole aggregator.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from torch import Tensor, nn

from anycity.safe_load import safe_torch_load

KINDS = ("vggt", "anysplat")


@dataclass
class LoadReport:
    """What :func:`load_pretrained` did. ``missing``: network keys the file did not provide (the completion
    branch and, for VGGT, the Gaussian head are expected here); ``unexpected``: file keys the network has no
    place for; ``mismatched``: ``(key, file shape, network shape)`` skipped."""

    loaded: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    mismatched: list[tuple[str, tuple, tuple]] = field(default_factory=list)

    def summary(self) -> str:
        def top(keys: list[str]) -> str:
            groups: dict[str, int] = {}
            for k in keys:
                groups[k.split(".")[0]] = groups.get(k.split(".")[0], 0) + 1
            return ", ".join(f"{g}.* x{n}" for g, n in sorted(groups.items())) or "none"

        return (f"loaded {len(self.loaded)} tensors; missing: {top(self.missing)}; unexpected: "
                f"{top(self.unexpected)}; shape mismatches: {len(self.mismatched)}")

    __str__ = summary

    def require_backbone(self, source: str | Path) -> None:
        """Raise one line unless every ``aggregator.*`` weight loaded. Heads may legitimately differ (VGGT has no
        Gaussian head; another SH degree reshapes its last conv), but weights made for another preset would leave
        the whole backbone random while training went on as if pretrained."""
        shapes = [m for m in self.mismatched if m[0].startswith("aggregator.")]
        absent = [k for k in self.missing if k.startswith("aggregator.") and k not in {m[0] for m in shapes}]
        if not (shapes or absent):
            return
        parts = []
        if absent:
            parts.append(f"{len(absent)} aggregator weights are not in it (e.g. {absent[0]})")
        if shapes:
            k, theirs, ours = shapes[0]
            parts.append(f"{len(shapes)} aggregator shapes differ (e.g. {k}: {list(theirs)} there, {list(ours)} here)")
        raise ValueError(f"model.pretrained: {source} does not fit this network's backbone: {'; '.join(parts)}; "
                         "build the preset the weights were made for (model.preset: vggt-1b for VGGT-1B and AnySplat)")


def read_state_dict(path: str | Path) -> dict[str, Tensor]:
    """A ``.pt``/``.pth``/``.ckpt`` (torch) or ``.safetensors`` file -> flat state dict (CPU)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pretrained weights: {path} not found; download VGGT-1B model.pt or an AnySplat "
                                "checkpoint to a local path first (this loader never downloads)")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    obj = safe_torch_load(path, mmap=True, what="pretrained weights")  # mmap keeps a 5 GB file out of RAM
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    elif isinstance(obj, dict) and isinstance(obj.get("model"), dict):
        obj = obj["model"]
    if not isinstance(obj, dict):
        raise ValueError(f"pretrained weights: {path} holds a {type(obj).__name__}, expected a state dict")
    return obj


def remap_keys(sd: dict[str, Tensor], kind: str) -> dict[str, Tensor]:
    """Apply the documented key map of ``kind`` (see the module docstring)."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    out = {}
    for k, v in sd.items():
        for prefix in ("module.", "model."):
            k = k[len(prefix):] if k.startswith(prefix) else k
        if kind == "anysplat":
            k = k[len("encoder."):] if k.startswith("encoder.") else k
            k = "gaussian_head." + k[len("gaussian_param_head."):] if k.startswith("gaussian_param_head.") else k
        out[k] = v
    return out


def load_pretrained(net: nn.Module, path: str | Path | dict, kind: str = "vggt") -> LoadReport:
    """Copy the matching tensors of ``path`` (a file, or an already-read state dict) into ``net``."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    sd = remap_keys(path if isinstance(path, dict) else read_state_dict(path), kind)
    own = net.state_dict()
    report = LoadReport()
    usable = {}
    for k, v in sd.items():
        if k not in own:
            report.unexpected.append(k)
        elif tuple(v.shape) != tuple(own[k].shape):
            report.mismatched.append((k, tuple(v.shape), tuple(own[k].shape)))
        else:
            usable[k] = v
    net.load_state_dict(usable, strict=False)
    if kind == "anysplat" and hasattr(net, "cfg"):  # decode the cameras the way the checkpoint was trained
        net.cfg = replace(net.cfg, focal_decode="anysplat")
    report.loaded = sorted(usable)
    report.missing = sorted(k for k in own if k not in usable)
    return report
