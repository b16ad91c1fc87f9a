"""What the command line's sources say before LightningCLI parses them: the files and options named
(``check_input_files``), where each ``-c`` sits (``check_config_placement``), which model class each source names
and what a later source drops (``replaced_net_keys``, ``dropped_model_keys``), and whether a class is a stage module
(``check_model_class``). Each check is one line, said before Lightning's imports and before the run writes
anything; :mod:`anycity.cli` calls them."""

from __future__ import annotations

from pathlib import Path

LIGHTNING = ("fit", "validate", "test", "predict")


def _init_params(cls: type) -> set[str]:
    """The keyword arguments ``cls(...)`` takes: the ``__init__`` parameters of it and its bases."""
    import inspect

    return {p for k in inspect.getmro(cls) if "__init__" in vars(k)
            for p in inspect.signature(k.__init__).parameters if p not in ("self", "args", "kwargs")}


def _option_values(args: list[str], names: tuple[str, ...]) -> list[tuple[str, str]]:
    """``(option, value)`` for every ``--name value`` or ``--name=value`` of ``names`` in ``args``."""
    out = []
    for i, a in enumerate(args):
        name, eq, value = a.partition("=")
        if name in names and eq:
            out.append((name, value))
        elif a in names and i + 1 < len(args):
            out.append((a, args[i + 1]))
    return out


def _missing_file(option: str, value: str, pattern: str, kind: str, elsewhere: str) -> FileNotFoundError:
    """One line for a file option naming a path that is not a file: a folder's ``pattern`` files, else the nearest
    ``pattern`` file beside it."""
    import difflib

    path = Path(value)
    if path.is_dir():
        inside = sorted(q.name for q in path.glob(pattern))
        shown = ", ".join(inside[:4]) + (" ..." if len(inside) > 4 else "")
        return FileNotFoundError(f"{option} {value} is a folder; pass one of its {kind} files"
                                 + (f" ({shown})" if inside else ""))
    beside = sorted(str(q) for q in path.parent.glob(pattern)) if path.parent.is_dir() else []
    near = difflib.get_close_matches(str(path), beside, n=1, cutoff=0.6)
    return FileNotFoundError(f"{option} {value}: no such file; " + (f"did you mean {near[0]}?" if near else elsewhere))


def check_input_files(args: list[str]) -> None:
    """Raise one line for a ``-c``/``--config`` or ``--ckpt_path`` file that does not exist, before Lightning's
    imports (8 s on 2 cores) and before the run writes its config. A ``--config`` value that is not a path (inline
    YAML such as ``--config '{trainer: {max_steps: 5}}'``, which jsonargparse reads) goes to the parser, and so do
    Lightning's ``--ckpt_path`` names (last, best, hpc, registry, null) and URLs."""
    for _, value in _option_values(args, ("-c", "--config")):
        if not Path(value).is_file() and not any(ch in value for ch in ":{}\n"):
            raise _missing_file("--config", value, "*.y*ml", "YAML",
                                "check the path (anycity's own configs are in the configs/ folder of its repository)")
    for option, value in _option_values(args, ("--ckpt_path",)):
        named = value.lower() in ("last", "best", "hpc", "null", "none", "") or value.startswith("registry")
        if not named and "://" not in value and not Path(value).expanduser().is_file():
            raise _missing_file(option, value, "*.ckpt", "checkpoint", "check the path (a run's checkpoints are in its "
                                "checkpoints/ folder, e.g. runs/quickstart/stage1/checkpoints/last.ckpt)")


def _load_yaml_arg(value: str):
    """A ``--config``/``--model`` value as data: the file it names, else the value as inline YAML; None where
    neither reads (a missing file or broken YAML gets its own one-line error)."""
    import yaml

    try:
        if Path(value).is_file():
            return yaml.safe_load(Path(value).read_text())
        return yaml.safe_load(value)
    except (OSError, ValueError, yaml.YAMLError):
        return None


def _model_events(args: list[str]) -> list[dict]:
    """What each source on the command line says about the model, in order: ``-c`` files (and inline YAML),
    ``--model CLASS`` or ``--model '{class_path: ..., init_args: ...}'``, ``--model.class_path``,
    ``--model.init_args.KEY`` (and ``--model.KEY``), ``--model.init_args.net`` (replaces the whole dict) and
    ``--model.init_args.net.KEY`` (merges). Each event: ``source`` (a file's path, or the option), ``label`` (how a
    message names it), ``file`` (a --config), ``cls`` (a class_path or None), ``init`` (init_args keys set, not
    ``net``), ``net`` (a dict that replaces ``net``, or None when not set) and ``net_keys`` (keys merged into it)."""
    sub = next((a for a in args if a in LIGHTNING), None)
    events, i = [], 0
    while i < len(args):
        name, eq, value = args[i].partition("=")
        if not eq:
            value = args[i + 1] if i + 1 < len(args) else ""
        step = 1 if eq else 2
        ev = {"source": value, "label": f"{name} {value}", "file": False, "cls": None, "init": {}, "net": None,
              "net_keys": {}}
        if name in ("-c", "--config"):
            cfg = _load_yaml_arg(value)
            if isinstance(cfg, dict) and cfg and set(cfg) <= set(LIGHTNING):  # a file of subcommand sections
                cfg = cfg.get(sub)
            ev.update(file=True, label=f"--config {value}")
            model = cfg.get("model") if isinstance(cfg, dict) else None
        elif name == "--model":
            model = _load_yaml_arg(value)
            ev["source"] = f"--model {value}"
        elif name.startswith("--model."):
            ev["source"] = name
            key = name[len("--model."):]
            key = key[len("init_args."):] if key.startswith("init_args.") else key
            if key == "class_path":
                model = value
            elif key == "net":
                model = {"init_args": {"net": _load_yaml_arg(value)}}
            elif key.startswith("net."):
                model, ev["net_keys"] = None, {key[len("net."):]: True}
            else:
                model, ev["init"] = None, {key: value}
        else:
            i += 1
            continue
        i += step
        if isinstance(model, str):
            ev["cls"] = model
        elif isinstance(model, dict):
            ev["cls"] = model.get("class_path")
            init = model.get("init_args") if isinstance(model.get("init_args"), dict) else {}
            init = {**{k: v for k, v in model.items() if k not in ("class_path", "init_args", "dict_kwargs")}, **init}
            if "net" in init:
                ev["net"] = init.pop("net") if isinstance(init["net"], dict) else {}
            ev["init"] = init
        events.append(ev)
    return events


def replaced_net_keys(args: list[str]) -> list[str]:
    """One message per source whose ``model.init_args.net`` drops keys an earlier one set: jsonargparse merges the
    ``--config`` files key by key, but a dict-valued key is replaced whole, so ``-c stage2.yaml -c mine.yaml`` with
    ``net: {wan_lora_rank: 8}`` in ``mine.yaml`` silently builds the network without stage2.yaml's ``video_prior``
    (and falls back to the preset's). A ``--model.init_args.net '{...}'`` on the command line replaces it whole too;
    ``--model.init_args.net.KEY VALUE`` merges (and its key is dropped by a later whole ``net``)."""
    out, earlier = [], {}  # net key -> the source that set it
    for ev in _model_events(args):
        for key in ev["net_keys"]:
            earlier[key] = ev["source"]
        if ev["net"] is None:
            continue
        later = ev["net"]
        # `completion` is the stage module's to set (Stage I drops the branch, Stage II builds it), and the wan_*
        # keys mean nothing once the later file picks another prior (configs/debug/cpu_ddp.yaml on stage2.yaml)
        moot = {"completion"} | ({k for k in earlier if k.startswith("wan_")}
                                 if str(later.get("video_prior", "small")).startswith(("small", "none")) else set())
        dropped = {}
        for k, source in earlier.items():
            if k not in later and k not in moot:
                dropped.setdefault(source, []).append(k)
        if dropped:
            n = sum(len(v) for v in dropped.values())
            where = " and ".join(f"{', '.join(keys)} from {source}" for source, keys in dropped.items())
            this = ev["source"] if ev["file"] else "this value"
            what = (f"--config {ev['source']}: its model.init_args.net replaces the one" if ev["file"] else
                    f"{ev['label']}: it replaces the model.init_args.net")
            first = next(iter(dropped))
            out.append(f"{what} from {first} whole, so {where} {'is' if n == 1 else 'are'} not used; repeat "
                       f"{'it' if n == 1 else 'them'} in {this}, or set single keys with dotted overrides "
                       "(--model.init_args.net.KEY VALUE), which merge")
        earlier = {k: ev["source"] for k in later}
    return out


def _model_class(path) -> type | None:
    """The class a ``model.class_path`` names (a dotted path, or a class name jsonargparse resolves among the
    subclasses of :class:`~anycity.lit.AnyCityModule`), or None where none is found."""
    import importlib

    if not isinstance(path, str) or not path:
        return None
    module, _, name = path.rpartition(".")
    if module:
        try:
            cls = getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError, ValueError):
            return None
        return cls if isinstance(cls, type) else None
    import anycity.lit

    todo, seen = [anycity.lit.AnyCityModule], []
    while todo:
        c = todo.pop()
        seen.append(c)
        todo += c.__subclasses__()
    return next((c for c in seen if c.__name__ == name), None)


def dropped_model_keys(args: list[str]) -> list[str]:
    """One message per source that switches ``model.class_path`` to a class that does not take ``init_args`` keys an
    earlier source set: jsonargparse keeps the keys both classes take and silently drops the others
    (``-c quickstart_stage2.yaml -c quickstart.yaml`` lost ``init_from``, ``pres_weight``, ...). Not named: the
    Stage I settings of a Stage I config that a Stage II config is stacked on (``-c quickstart.yaml -c
    quickstart_stage2.yaml``, the documented order); a Stage I key given on the command line or in an overlay is."""
    from anycity.lit import RefinementModule, ScaffoldModule

    out, keys, cls = [], {}, None  # init_args key -> (source, set by a config that also names the class)
    for ev in _model_events(args):
        new = _model_class(ev["cls"]) if ev["cls"] else None
        if new is not None and not _is_stage_module(new):
            new = None  # check_model_class refuses it
        if new is not None and cls is not None and new is not cls:
            forward = issubclass(cls, ScaffoldModule) and issubclass(new, RefinementModule)
            takes = _init_params(new)
            dropped = {}
            for k, (source, staged) in keys.items():
                if k not in takes and not (forward and staged):
                    dropped.setdefault(source, []).append(k)
            keys = {k: v for k, v in keys.items() if k in takes}
            if dropped:
                n = sum(len(v) for v in dropped.values())
                where = " and ".join(f"{', '.join(ks)} from {source}" for source, ks in dropped.items())
                first = next(iter(dropped))
                out.append(f"{ev['label']} switches model.class_path from {cls.__name__} to {new.__name__}, which does "
                           f"not take {where}: {'it is' if n == 1 else 'they are'} not used; if {new.__name__} is "
                           f"what you meant, leave {'it' if n == 1 else 'them'} out, else give {first} after "
                           f"{ev['label']}")
        if new is not None:
            cls = new
        for k in ev["init"]:
            keys[k] = (ev["source"], bool(ev["cls"]) and ev["file"])
    return out


def check_config_placement(args: list[str]) -> None:
    """Refuse a ``-c``/``--config`` placed before the Lightning subcommand (``anycity -c FILE fit``): there
    jsonargparse reads only subcommand sections (``fit:``, ``test:``, ...), so a plain config's keys were silently
    not used (``--print_config`` showed the defaults) or reported as unknown keys. A file of subcommand sections
    alone is accepted, as jsonargparse reads it."""
    sub = next((a for a in args if a in LIGHTNING), None)
    before = args[:args.index(sub)] if sub else args
    for option, value in _option_values(before, ("-c", "--config")):
        cfg = _load_yaml_arg(value)
        if cfg is None or (isinstance(cfg, dict) and set(cfg) <= set(LIGHTNING)):
            continue
        where = "before the subcommand" if sub else "with no subcommand"
        raise ValueError(f"{option} {value} {where}: only a file of subcommand sections (fit:, test:, ...) is read "
                         f"there, so its settings would not be used; put -c after the subcommand: anycity "
                         f"{sub or 'fit'} -c {value}")


def _is_stage_module(cls: type) -> bool:
    """A concrete stage module: a subclass of :class:`~anycity.lit.AnyCityModule` with its own ``training_step``
    (ScaffoldModule, RefinementModule, or a subclass of one); the base class has Lightning's, which trains nothing."""
    from anycity.lit import AnyCityModule

    return (isinstance(cls, type) and issubclass(cls, AnyCityModule)
            and getattr(cls, "training_step", None) is not AnyCityModule.training_step)


def check_model_class(class_path) -> None:
    """Refuse, in one line, a ``model.class_path`` that is not a concrete stage module: the base class
    :class:`~anycity.lit.AnyCityModule` (documented as not used directly; also what jsonargparse builds when the
    configs give ``model.init_args`` and no class) passed the parse and ``fit`` then failed in a 40-line
    traceback ("No `training_step()` method defined"). A subclass of one of the stage modules is accepted."""

    from anycity.lit import AnyCityModule

    cls = _model_class(class_path)
    if cls is None or _is_stage_module(cls):
        return  # (jsonargparse names a class it cannot find)
    if cls is AnyCityModule:
        why = "the base class the stage modules share (no config named a model class_path?), which trains nothing"
    elif cls.__name__ == "PosePriorModule":
        why = "the pose prior's pretraining module, which scripts/pose_prior.py runs, not a stage of anycity's CLI"
    else:
        why = "not an anycity stage module"
    raise ValueError(f"model.class_path {class_path}: {why}; pass --model anycity.lit.ScaffoldModule (Stage I) or "
                     "--model anycity.lit.RefinementModule (Stage II), or a stage's config (-c configs/stage1.yaml, "
                     "-c configs/stage2.yaml, or -c configs/quickstart.yaml)")
