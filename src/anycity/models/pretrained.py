"""Load VGGT-1B or AnySplat weights into an :class:`AnyCityNet` (local files only, never the network).

Key map (documented, nothing else is renamed):

* ``kind="vggt"``: a plain ``model.pt`` state dict (or safetensors). ``aggregator.*``, ``camera_head.*`` and
  ``depth_head.*`` load as they are; ``point_head.*`` and ``track_head.*`` have no counterpart and are
  reported as unexpected.
* ``kind="anysplat"``: optional Lightning ``state_dict`` nesting and ``model.`` prefix, then ``encoder.`` is
  stripped and ``gaussian_param_head.`` becomes ``gaussian_head.``; ``distill_*`` teacher copies are
  reported as unexpected. bf16 tensors are cast to the network's dtype. Only a file that has AnySplat's keys
  switches the network to AnySplat's focal decode; a VGGT-layout file (``aggregator.*`` at the top) is refused.

``path`` may be a folder holding one weights file (e.g. a downloaded snapshot with its ``model.safetensors``), or a
sharded download (``model-0000k-of-0000n.safetensors`` + ``model.safetensors.index.json``): the folder, its index or
any of its shards loads every shard the index lists. ``~`` is expanded. Wrapper prefixes (``module.``, ``model.``,
torch.compile's ``_orig_mod.``, nested in any order) are stripped. A non-finite (NaN/Inf) tensor is refused.
Tensors whose shape differs from the network's are skipped and listed (a mismatch never breaks the net).
:meth:`LoadReport.require_backbone` (which the Lightning modules call) then insists on the whole aggregator, and
names the real cause when the file has another layout (AnySplat's ``encoder.*`` read as VGGT, or an anycity
checkpoint's ``net.*``). A file none of whose tensors fit is refused in one line.

An anycity training checkpoint (``anycity fit``'s ``last.ckpt``, Stage I or II) is not read here: it holds the network
it trained, built from its own ``hyper_parameters``, which :func:`load_checkpoint` rebuilds and loads strictly.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from anycity.models.anycity import REFINEMENT_PREFIXES
from anycity.models.pose_prior import rebuild_pose_prior
from anycity.models.presets import build_network
from anycity.safe_load import missing_reason, safe_torch_load, user_path

if TYPE_CHECKING:
    from anycity.models.anycity import AnyCityNet

KINDS = ("vggt", "anysplat")
WEIGHT_SUFFIXES = (".safetensors", ".pt", ".pth", ".ckpt", ".bin")
PREFERRED_NAMES = ("model.safetensors", "model.pt")  # what a VGGT / AnySplat download folder holds
ANYSPLAT_PREFIXES = ("encoder.", "gaussian_param_head.")
WRAPPER_PREFIXES = ("module.", "model.", "_orig_mod.")  # DDP, Lightning/AnySplat nesting, torch.compile
SHARD_RE = re.compile(r"^(?P<stem>.+)-(?P<k>\d{5})-of-(?P<n>\d{5})\.(?P<ext>safetensors|bin|pt|pth)$")
INDEX_SUFFIX = ".index.json"  # e.g. model.safetensors.index.json: {"weight_map": {key: shard file name}}
# the first name part most keys the network has no place for share -> what the file really is
LAYOUT_HINTS = {
    "encoder": "this is an AnySplat checkpoint: set model.init_args.pretrained_kind: anysplat",
    "net": "this is an anycity checkpoint: pass it as --ckpt_path (resume/test) or model.init_args.init_from "
           "(Stage II)",
}
NET_PREFIX = "net."  # the Lightning modules hold the network as ``self.net``
STAGE1_CLASS = "ScaffoldModule"  # lit/scaffold.py: Stage I, which builds no completion branch


@dataclass
class LoadReport:
    """What :func:`load_pretrained` did. ``missing``: network keys the file did not provide (the completion
    branch and, for VGGT, the Gaussian head are expected here); ``unexpected``: file keys the network has no
    place for; ``mismatched``: ``(key, file shape, network shape)`` skipped (not in ``missing``)."""

    loaded: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    mismatched: list[tuple[str, tuple, tuple]] = field(default_factory=list)
    picked: str | None = None  # the weights file read when a folder was given

    def summary(self) -> str:
        def top(keys: list[str]) -> str:
            groups: dict[str, int] = {}
            for k in keys:
                groups[k.split(".")[0]] = groups.get(k.split(".")[0], 0) + 1
            return ", ".join(f"{g}.* x{n}" for g, n in sorted(groups.items())) or "none"

        read = f"read {self.picked}; " if self.picked else ""
        return (f"{read}loaded {len(self.loaded)} tensors; missing: {top(self.missing)}; unexpected: "
                f"{top(self.unexpected)}; shape mismatches: {self._mismatches()}")

    def _mismatches(self, shown: int = 3) -> str:
        """``2 (k file [21, 32] vs net [36, 32], ...)``: the count and the first ``shown`` keys with both shapes."""
        if not self.mismatched:
            return "0"
        named = ", ".join(f"{k} file {list(theirs)} vs net {list(ours)}" for k, theirs, ours in self.mismatched[:shown])
        more = f", +{len(self.mismatched) - shown} more" if len(self.mismatched) > shown else ""
        return f"{len(self.mismatched)} ({named}{more}; skipped, left as built)"

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
        fix = "build the preset the weights were made for (model.preset: vggt-1b for VGGT-1B and AnySplat)"
        top, n = Counter(k.split(".")[0] for k in self.unexpected).most_common(1)[0] if self.unexpected else ("", 0)
        if top in LAYOUT_HINTS and 2 * n > len(self.unexpected):
            parts.append(f"{n} of its keys start with '{top}.'")
            fix = LAYOUT_HINTS[top]
        raise ValueError(f"model.pretrained: {source} does not fit this network's backbone: {'; '.join(parts)}; "
                         f"{fix}")


def _is_shard(path: Path) -> bool:
    """``path`` is named as one of several shards (``...-00001-of-00002.safetensors``)."""
    m = SHARD_RE.match(path.name)
    return m is not None and int(m["n"]) > 1


def _shard_index(shard: Path) -> Path | None:
    """The ``*.index.json`` next to the shard ``shard`` that lists it; else the one that does not parse (its read
    then says so), if any."""
    damaged = None
    for index in sorted(shard.parent.glob("*" + INDEX_SUFFIX)):
        try:
            if shard.name in (json.loads(index.read_text()).get("weight_map") or {}).values():
                return index
        except (OSError, ValueError, AttributeError, TypeError):
            damaged = damaged or index
    return damaged


def _no_index(where: Path, shards: list[Path]) -> ValueError:
    """One line for shards without the index that lists them: never load (or suggest) one shard alone, as each
    holds only part of the network."""
    m = SHARD_RE.match(shards[0].name)
    what = (f"is shard {int(m['k'])} of {int(m['n'])} of a sharded checkpoint" if where.is_file() else
            f"holds {len(shards)} of the {int(m['n'])} shards of a sharded checkpoint ({shards[0].name}, ...)")
    return ValueError(f"pretrained weights: {where} {what}, and no {m['stem']}.{m['ext']}{INDEX_SUFFIX} next to it "
                      "lists its shards; copy the whole download folder (every shard and its index) and pass the "
                      "folder")


def weights_file(path: str | Path) -> Path:
    """``path`` itself, or the one weights file in the folder ``path`` (``model.safetensors`` / ``model.pt`` when
    the folder holds several files and exactly one of those), or the ``*.index.json`` of a sharded checkpoint (in the
    folder ``path``, or next to the shard ``path``). Raises one line when there is none or no one."""
    path = user_path(path)
    if not path.is_dir():
        if _is_shard(path) and path.is_file():  # one shard: the rest of the network is in the others
            index = _shard_index(path)
            if index is None:
                raise _no_index(path, [path])
            return index
        return path
    found = sorted(p for p in path.iterdir() if p.is_file() and p.name.endswith(WEIGHT_SUFFIXES))
    named = [p for p in found if p.name in PREFERRED_NAMES]
    indexes = sorted(path.glob("*" + INDEX_SUFFIX), key=lambda p: (".safetensors" not in p.name, p.name))
    if len(named) != 1 and indexes:  # a sharded download; safetensors first when both formats are there
        return indexes[0]
    pick = named if len(named) == 1 else found
    if len(pick) == 1 and not _is_shard(pick[0]):
        return pick[0]
    if found and all(_is_shard(p) for p in found):
        raise _no_index(path, found)
    if not found:
        raise FileNotFoundError(f"pretrained weights: {path} is a folder with no weights file "
                                f"({', '.join('*' + s for s in WEIGHT_SUFFIXES)}) in it; pass the weights file")
    names = ", ".join(p.name for p in found[:8]) + (f", ... ({len(found)} in all)" if len(found) > 8 else "")
    raise ValueError(f"pretrained weights: {path} is a folder; pass the weights file inside it (candidates: {names})")


def _check_file(path: Path) -> None:
    if not path.is_file():
        why = missing_reason(path) or "is not a file"
        if why == "not found":
            raise FileNotFoundError(f"pretrained weights: {path} not found; download VGGT-1B model.pt or an AnySplat "
                                    "checkpoint to a local path first (this loader never downloads)")
        raise FileNotFoundError(f"pretrained weights: {path} {why}")


def _unreadable_safetensors(path: Path, e: BaseException) -> ValueError:
    why = (str(e).strip().splitlines() or [type(e).__name__])[0]
    return ValueError(f"cannot read pretrained weights {path}: {why}; the file looks truncated or corrupt "
                      "(re-download it)")


def shard_files(index: Path) -> dict[Path, list[str]]:
    """The shard files a ``*.index.json`` lists (next to it), each with the keys it maps to that file; one line
    naming ``index`` for an index that does not parse, or a shard that is not there."""
    try:
        weight_map = json.loads(index.read_text()).get("weight_map")
    except (ValueError, AttributeError) as e:  # JSONDecodeError is a ValueError; AttributeError: not an object
        raise ValueError(f"cannot read pretrained weights {index}: {_first(e)}; the index of a sharded checkpoint "
                         "is damaged (re-download it)") from None
    if not (isinstance(weight_map, dict) and weight_map
            and all(isinstance(k, str) and isinstance(v, str) for k, v in weight_map.items())):
        raise ValueError(f"cannot read pretrained weights {index}: no weight_map of key -> shard file in it; the "
                         "index of a sharded checkpoint is damaged (re-download it)")
    files: dict[Path, list[str]] = {}
    for k, name in weight_map.items():
        files.setdefault(index.parent / name, []).append(k)
    absent = [f for f in files if not f.is_file()]
    if absent:
        raise FileNotFoundError(f"pretrained weights: {index} lists {len(files)} shards, {len(absent)} of which are "
                                f"not in {index.parent} (e.g. {absent[0].name}); copy the whole download folder")
    return files


def _first(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def _read_one(path: Path) -> dict[str, Tensor]:
    if path.suffix == ".safetensors":
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            return load_file(str(path))
        except SafetensorError as e:
            raise _unreadable_safetensors(path, e) from None
    obj = safe_torch_load(path, mmap=True, what="pretrained weights")  # mmap keeps a 5 GB file out of RAM
    return _state_dict_of(obj, path)


def _sharded(index: Path, read) -> dict:
    """``read(shard)`` of every shard ``index`` lists, merged; one line for a key the index maps to a shard that
    does not hold it (an incomplete download)."""
    out: dict = {}
    for shard, keys in shard_files(index).items():
        part = read(shard)
        lost = [k for k in keys if k not in part]
        if lost:
            raise ValueError(f"pretrained weights: {index} maps {len(lost)} keys to {shard.name}, which lacks them "
                             f"(e.g. {lost[0]}); the shard is incomplete or another model's (re-download it)")
        out.update(part)
    return out


def read_state_dict(path: str | Path) -> dict[str, Tensor]:
    """A ``.pt``/``.pth``/``.ckpt`` (torch) or ``.safetensors`` file, a folder holding one, or a sharded checkpoint
    (:func:`weights_file`) -> flat state dict (CPU)."""
    path = weights_file(path)
    _check_file(path)
    if path.name.endswith(INDEX_SUFFIX):
        return _sharded(path, _read_one)
    return _read_one(path)


def _safetensors_shapes(path: Path) -> dict[str, tuple]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return {k: tuple(f.get_slice(k).get_shape()) for k in f.keys()}
    except SafetensorError as e:
        raise _unreadable_safetensors(path, e) from None


def read_shapes(path: str | Path) -> dict[str, tuple]:
    """``{key: shape}`` of the weights file(s) :func:`read_state_dict` reads, without reading the tensors
    (safetensors: the header; torch: memory-mapped). The same one-line errors."""
    path = weights_file(path)
    _check_file(path)

    def one(f: Path) -> dict[str, tuple]:
        if f.suffix == ".safetensors":
            return _safetensors_shapes(f)
        return {k: tuple(v.shape) for k, v in _read_one(f).items()}

    return _sharded(path, one) if path.name.endswith(INDEX_SUFFIX) else one(path)


def first_nonfinite(tensors) -> str | None:
    """The first key of ``tensors`` (a dict, or ``(key, tensor)`` pairs) whose floating tensor holds a NaN or Inf;
    one ``isfinite().all()`` per tensor."""
    for k, v in (tensors.items() if isinstance(tensors, dict) else tensors):
        if not (isinstance(v, Tensor) and v.is_floating_point()) or v.is_meta or v.numel() == 0:
            continue
        try:
            ok = bool(torch.isfinite(v).all())
        except (RuntimeError, TypeError, NotImplementedError):  # e.g. float8 on some builds
            ok = bool(torch.isfinite(v.float()).all())
        if not ok:
            return k
    return None


def first_non_tensor(state: dict) -> tuple[object, str] | None:
    """``(key, type name)`` of the first entry of ``state`` that is not a tensor under a string key, else None."""
    return next(((k, type(v).__name__) for k, v in state.items() if not (isinstance(k, str) and isinstance(v, Tensor))),
                None)


def weight_problems(own: dict[str, Tensor], weights: dict, *, strict: bool = True,
                    ignore: tuple[str, ...] = ()) -> list[str]:
    """What keeps ``weights`` from loading into a module whose ``state_dict()`` is ``own``, as short phrases: a
    non-tensor value, then (with ``strict``) missing and unexpected keys, then shapes. Keys starting with ``ignore``
    may be missing. Empty when it loads."""
    bad = first_non_tensor(weights)
    if bad is not None:
        return [f"it holds a {bad[1]} under the key {bad[0]!r}, not a tensor"]
    missing = sorted(k for k in own if k not in weights and not k.startswith(ignore)) if strict else []
    unexpected = sorted(k for k in weights if k not in own) if strict else []
    shapes = [k for k in weights if k in own and tuple(weights[k].shape) != tuple(own[k].shape)]
    out = [f"{len(ks)} {what} (e.g. {ks[0]})" for ks, what in
           ((missing, "weights of the network are not in it"), (unexpected, "of its weights have no place"))
           if ks]
    if shapes:
        k = shapes[0]
        out.append(f"{len(shapes)} shapes differ (e.g. {k}: {list(weights[k].shape)} there, {list(own[k].shape)} "
                   "here)")
    return out


def _state_dict_of(obj, source: str | Path) -> dict[str, Tensor]:
    """The flat state dict in ``obj``: itself, or under a Lightning ``state_dict`` / a ``model`` key; one line naming
    ``source`` and the key when it holds anything but tensors under string keys."""
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    elif isinstance(obj, dict) and isinstance(obj.get("model"), dict):
        obj = obj["model"]
    if not isinstance(obj, dict):
        raise ValueError(f"pretrained weights: {source} holds a {type(obj).__name__}, expected a state dict")
    bad = next(((k, v) for k, v in obj.items() if not (isinstance(k, str) and isinstance(v, Tensor))), None)
    if bad is not None:
        raise ValueError(f"pretrained weights: {source} holds a {type(bad[1]).__name__} under the key {bad[0]!r}, "
                         "expected a state dict of named tensors; pass a VGGT model.pt/.safetensors or an AnySplat "
                         "checkpoint (re-download it if it is one)")
    return obj


def _strip_wrappers(k: str) -> str:
    """``k`` without its wrapper prefixes (:data:`WRAPPER_PREFIXES`), however nested (``model.module.``,
    ``module._orig_mod.``, ...)."""
    while k.startswith(WRAPPER_PREFIXES):
        k = k[len(next(p for p in WRAPPER_PREFIXES if k.startswith(p))):]
    return k


def remap_keys(sd: dict[str, Tensor], kind: str) -> dict[str, Tensor]:
    """Apply the documented key map of ``kind`` (see the module docstring)."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    out = {}
    for k, v in sd.items():
        k = _strip_wrappers(k)
        if kind == "anysplat":
            k = k[len("encoder."):] if k.startswith("encoder.") else k
            k = "gaussian_head." + k[len("gaussian_param_head."):] if k.startswith("gaussian_param_head.") else k
        out[k] = v
    return out


def load_pretrained(net: nn.Module, path: str | Path | dict, kind: str = "vggt") -> LoadReport:
    """Copy the matching tensors of ``path`` (a file, a folder holding one, or an already-read state dict) into
    ``net``, which must live on a real device (a network built on ``meta`` has no storage to copy into)."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    report = LoadReport()
    if isinstance(path, dict):
        source, raw = "the state dict", _state_dict_of(path, "the state dict")
    else:
        source = weights_file(path)
        report.picked = str(source) if source != user_path(path) else None
        raw = read_state_dict(source)
    stripped = [_strip_wrappers(k) for k in raw]
    is_anysplat = any(k.startswith(ANYSPLAT_PREFIXES) for k in stripped)
    if kind == "anysplat" and not is_anysplat and any(k.startswith("aggregator.") for k in stripped):
        # AnySplat's focal decode would silently shift every focal length of a VGGT-trained camera head
        raise ValueError(f"pretrained weights: {source} is a VGGT file (aggregator.* keys, no encoder.* or "
                         "gaussian_param_head.*), not AnySplat; use model.init_args.pretrained_kind: vggt")
    sd = remap_keys(raw, kind)
    own = net.state_dict()
    usable = {}
    for k, v in sd.items():
        if k not in own:
            report.unexpected.append(k)
        elif tuple(v.shape) != tuple(own[k].shape):
            report.mismatched.append((k, tuple(v.shape), tuple(own[k].shape)))
        else:
            usable[k] = v
    meta = [k for k in usable if own[k].is_meta]
    if meta:  # load_state_dict would copy nothing and report success
        raise ValueError(f"pretrained weights: the network is on the meta device (e.g. {meta[0]}), where loading "
                         "copies nothing; build the network on a real device (cpu/cuda) first")
    if not usable:  # the network would stay as built (random) with nothing but a report saying so
        raise _nothing_loaded(source, sd, report, kind)
    if (bad := first_nonfinite(usable)) is not None:  # NaN weights train NaN from the first step, saying nothing
        raise ValueError(f"pretrained weights: {source} holds non-finite values (NaN or Inf) in {bad}; the file is "
                         "damaged or was saved from a diverged run: re-download it")
    net.load_state_dict(usable, strict=False)
    if kind == "anysplat" and is_anysplat and hasattr(net, "cfg"):  # decode the cameras as the checkpoint trained
        net.cfg = replace(net.cfg, focal_decode="anysplat")
    report.loaded = sorted(usable)
    report.missing = sorted(k for k in own if k not in sd)  # a shape mismatch is in the file: listed apart
    return report


def _nothing_loaded(source, sd: dict[str, Tensor], report: LoadReport, kind: str) -> ValueError:
    """The one-line error for a file none of whose tensors fit, with the fix its key layout points to."""
    if not sd:
        return ValueError(f"pretrained weights: {source} holds no tensors; pass a VGGT model.pt/.safetensors or an "
                          "AnySplat checkpoint")
    top, n = Counter(k.split(".")[0] for k in sd).most_common(1)[0]
    if top == NET_PREFIX[:-1] and 2 * n > len(sd):
        return ValueError(f"pretrained weights: {source} is an anycity training checkpoint ({n} of its {len(sd)} "
                          "tensors start with 'net.'), not VGGT/AnySplat weights; load it with "
                          "anycity.models.load_checkpoint(path), or on the command line pass it as --ckpt_path "
                          "(resume/test) or model.init_args.init_from (Stage II)")
    if top == "encoder" and 2 * n > len(sd):
        fix = "it is an AnySplat checkpoint: use kind='anysplat' (model.init_args.pretrained_kind: anysplat)"
    elif report.mismatched:
        k, theirs, ours = report.mismatched[0]
        fix = (f"its shapes differ (e.g. {k}: {list(theirs)} there, {list(ours)} here); build the preset the weights "
               "were made for (vggt-1b for VGGT-1B and AnySplat)")
    else:
        fix = f"none of its names is this network's (e.g. {report.unexpected[0]}); pass VGGT or AnySplat weights"
    return ValueError(f"pretrained weights: {source} loaded 0 of its {len(sd)} tensors (kind={kind!r}); {fix}")


def checkpoint_network_options(hparams: dict, source: str | Path = "checkpoint") -> tuple[str, dict]:
    """``(preset, net overrides)`` of the network a training checkpoint's ``hyper_parameters`` describe, as the
    Lightning modules build it (``build_network(preset, **net)``): Stage I (``ScaffoldModule``, recorded by
    LightningCLI as ``_class_path``) adds ``completion=False``. One line naming ``source`` for anything else."""
    preset = hparams.get("preset") if isinstance(hparams, dict) else None
    net = hparams.get("net") if isinstance(hparams, dict) else None
    if not isinstance(preset, str) or not isinstance(net, (dict, type(None))):
        raise ValueError(f"checkpoint {source}: not an anycity training checkpoint (its hyper_parameters hold no "
                         "network preset); pass the last.ckpt or best .ckpt an `anycity fit` wrote (Stage I or II)")
    net = dict(net or {})
    if str(hparams.get("_class_path", "")).rpartition(".")[2] == STAGE1_CLASS:
        net["completion"] = False
    return preset, net


def check_video_prior_record(ref, source: str = "checkpoint") -> dict:
    """A checkpoint's ``video_prior`` record (``{"dir": str, "sha256": str, "block": int}``, written by
    ``lit/prior_ckpt.drop_frozen_prior``; ``block`` may be absent in older ones) as it is; one line starting with
    ``source`` (e.g. ``"checkpoint runs/x/last.ckpt"``) otherwise."""
    ok = (isinstance(ref, dict) and isinstance(ref.get("dir"), str) and isinstance(ref.get("sha256"), str)
          and (ref.get("block") is None or (isinstance(ref["block"], int) and not isinstance(ref["block"], bool))))
    if not ok:
        got = (f"a dict with keys {sorted(map(str, ref))}" if isinstance(ref, dict) else f"a {type(ref).__name__}")
        raise ValueError(f"{source}: its video_prior record is {got}, not {{'dir': str, 'sha256': str, "
                         "'block': int}; the checkpoint is damaged or was written by another anycity version: pass a "
                         "checkpoint that this anycity version's fit wrote")
    return ref


def load_checkpoint(path: str | Path, *, map_location: str | torch.device = "cpu") -> AnyCityNet:
    """The trained network of an anycity training checkpoint (``anycity fit``'s ``last.ckpt``, Stage I or II) as a
    plain :class:`~anycity.models.anycity.AnyCityNet` in eval mode on ``map_location``, without Lightning.

    Built as its ``hyper_parameters`` say (:func:`checkpoint_network_options`); every weight is then loaded
    strictly, read as tensors and plain data only (:func:`anycity.safe_load.safe_torch_load`). Run it under
    ``torch.inference_mode()``: no autograd graph, a fraction of the memory::

        net = load_checkpoint("runs/quickstart/stage2/checkpoints/last.ckpt")
        with torch.inference_mode():
            out = net(images)  # images [B, V, 3, H, W] in [0, 1], H and W multiples of net.cfg.patch_size

    A checkpoint that references a Wan prior's folder instead of holding it needs the Lightning module
    (``RefinementModule.load_from_checkpoint(path).net``), which checks that folder's content hash.
    One-line ``ValueError`` for a file that is not an anycity training checkpoint (a VGGT/AnySplat state dict:
    :func:`load_pretrained`) or whose weights do not fit the network it describes.
    """
    ckpt = safe_torch_load(path, mmap=True, what="checkpoint")  # mmap: the optimiser state is never read
    state = ckpt.get("state_dict") if isinstance(ckpt, dict) else None
    if not isinstance(state, dict):
        plain = isinstance(ckpt, dict) and any(isinstance(v, Tensor) for v in ckpt.values())
        what = "a plain state dict (VGGT/AnySplat weights?)" if plain else f"a {type(ckpt).__name__}"
        raise ValueError(f"checkpoint {path}: not an anycity training checkpoint ({what}, no state_dict); load "
                         "VGGT/AnySplat weights with load_pretrained(build_network(preset), path, kind=...)")
    preset, options = checkpoint_network_options(ckpt.get("hyper_parameters"), path)
    if ckpt.get("video_prior") is not None:
        ref = check_video_prior_record(ckpt["video_prior"], f"checkpoint {path}")
        raise ValueError(f"checkpoint {path}: its Wan video prior is referenced ({ref['dir']}), "
                         "not stored in the file; load it with anycity.lit.RefinementModule.load_from_checkpoint"
                         "(path).net, which checks that folder")
    if (bad := first_non_tensor(state)) is not None:
        raise ValueError(f"checkpoint {path}: its state_dict holds a {bad[1]} under the key {bad[0]!r}, not a tensor; "
                         "the file is damaged: pass a checkpoint that an anycity fit wrote")
    try:
        net = build_network(preset, **options)
    except ValueError as e:
        raise ValueError(f"checkpoint {path}: {e} (written by another anycity version?)") from None
    weights = {k[len(NET_PREFIX):]: v for k, v in state.items() if k.startswith(NET_PREFIX)}
    if net.completion is None:  # as ScaffoldModule.on_load_checkpoint
        weights = {k: v for k, v in weights.items() if not k.startswith(REFINEMENT_PREFIXES)}
    rebuild_pose_prior(net, weights, "pose_prior.", ckpt.get("pose_prior") or {})
    _load_strict(net, weights, path)
    return net.to(map_location).eval()


def _load_strict(net: nn.Module, weights: dict[str, Tensor], source: str | Path) -> None:
    """``net.load_state_dict(weights)`` with every key, type and shape checked first, and every floating tensor
    finite: one line naming ``source``."""
    problems = weight_problems(net.state_dict(), weights) if weights else ["it holds no 'net.*' weights"]
    if problems:
        raise ValueError(f"checkpoint {source} does not fit the network its hyper_parameters describe: "
                         f"{'; '.join(problems)}; pass a checkpoint that this anycity version's fit wrote")
    if (bad := first_nonfinite(weights)) is not None:
        raise ValueError(f"checkpoint {source} holds non-finite values (NaN or Inf) in net.{bad}; the run diverged "
                         "before it was saved, or the file is damaged: use an earlier checkpoint")
    net.load_state_dict(weights)
