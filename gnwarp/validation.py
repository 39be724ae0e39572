"""Typed, validated configurations: the one place every gnwarp config (``GNBlockConfig``,
``RunOptions``, ``ModelConfig``, ``TrainConfig``, ...) checks its values.

Each dataclass field's annotation says what it allows (pydantic types with constraints, e.g.
``PositiveInt``, ``Width``); ``check_fields`` validates a config against its annotations in
``__post_init__``, and every refusal is one ``ConfigError`` that names the key path
(``model.gn.latent``) and the allowed values, whether the value came from Python, a config file or
``gnwarp train --set``.
"""
from __future__ import annotations

import dataclasses
import inspect
import os
import re
import sys
import types
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Sequence, Union

import numpy as np
import pydantic
from pydantic import BeforeValidator, Field, Strict

__all__ = ["ConfigError", "Allowed", "check_fields", "check_keys", "allowed_values", "MAX_WIDTH", "MAX_LAYERS", "IntRange", "FloatRange", "Flag", "Count", "PositiveInt", "PositiveFloat", "InputWidth", "Width", "Widths", "LayerCount", "described", "flag_name",
           "add_config_flags", "config_flags_given", "config_from_flags", "config_keys", "read_config_file", "parse_value", "apply_overrides", "available_memory",
           "check_memory"]


class ConfigError(ValueError):
    """A refused configuration value: ``path`` is the key (dotted through nested configs:
    ``model.gn.latent``; empty for a whole-config problem), ``reason`` what is wrong, with the
    allowed values."""

    def __init__(self, path: str, reason: str):
        self.path, self.reason = path, reason
        super().__init__(f"{path}: {reason}" if path else reason)

    def __reduce__(self):
        return type(self), (self.path, self.reason)

    def within(self, prefix: str) -> "ConfigError":
        """The same error seen from the config that holds this one under key ``prefix``."""
        return type(self)(f"{prefix}.{self.path}" if self.path else prefix, self.reason)


@dataclass(frozen=True)
class Allowed:
    """Annotation metadata: how a refusal describes the allowed values (``Annotated[int, ...,
    Allowed("an integer >= 1")]``)."""
    text: str


def _no_bool(v):
    if isinstance(v, (bool, np.bool_)):  # pydantic reads True as 1; a config never means that
        raise ValueError("a boolean is not a number")
    return v


def _plain_bool(v):
    return bool(v) if isinstance(v, np.bool_) else v


def _bounds(lo, hi, gt=None) -> str:
    n = lambda x: str(x) if isinstance(x, int) else f"{x:g}"  # noqa: E731
    if gt is not None:
        return f"> {n(gt)}" + (f" and <= {n(hi)}" if hi is not None else "")
    if hi is None:
        return f">= {n(lo)}"
    return f"from {n(lo)} to {n(hi)}"


def IntRange(lo: int, hi: int | None = None):
    """An integer type from ``lo`` to ``hi`` (inclusive; None: no upper bound)."""
    return Annotated[int, BeforeValidator(_no_bool), Field(ge=lo, le=hi), Allowed(f"an integer {_bounds(lo, hi)}")]


def FloatRange(gt: float | None = None, ge: float | None = None, le: float | None = None,
               lt: float | None = None):
    """A finite number type: > ``gt`` (or >= ``ge``), <= ``le`` (or < ``lt``)."""
    bounds = [f"{op} {v:g}" for op, v in ((">", gt), (">=", ge), ("<=", le), ("<", lt)) if v is not None]
    text = " ".join(["a finite number", " and ".join(bounds)]).strip()
    return Annotated[float, BeforeValidator(_no_bool), Field(gt=gt, ge=ge, le=le, lt=lt, allow_inf_nan=False),
                     Allowed(text)]


MAX_WIDTH = 1 << 16    # widest layer a config may ask for (a 65536 x 65536 layer is 16 GiB in float32)
MAX_LAYERS = 64        # most hidden layers of one MLP
Flag = Annotated[bool, BeforeValidator(_plain_bool), Strict(), Allowed("true or false")]
Count = IntRange(0)                 # an integer >= 0
PositiveInt = IntRange(1)           # an integer >= 1
BatchSize = IntRange(1, 1 << 24)    # examples a gradient step: more is a mistake, not a batch
Seed = IntRange(0, (1 << 63) - 1)   # what numpy and torch take as a seed
Width = IntRange(1, MAX_WIDTH)
InputWidth = IntRange(0, 1 << 20)     # input widths: a model's static features plus latents
LayerCount = IntRange(0, MAX_LAYERS)
PositiveFloat = FloatRange(gt=0)        # a finite number > 0
Widths = Annotated[tuple[Width, ...], Field(max_length=MAX_LAYERS),
                   Allowed(f"a list of at most {MAX_LAYERS} layer widths, each an integer from 1 to {MAX_WIDTH}")]


def allowed_values(tp) -> str:
    """Words for what an annotation allows (its ``Allowed`` text where it has one)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        for m in tp.__metadata__:
            if isinstance(m, Allowed):
                return m.text
        return allowed_values(args[0])
    if origin in (Union, types.UnionType):
        return " or ".join(allowed_values(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if tp is type(None):
        return "None"
    if origin in (list, tuple, Sequence):
        return f"a list of {allowed_values(args[0])}" if args else "a list"
    if dataclasses.is_dataclass(tp):
        return f"a table of {tp.__name__} keys"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp)))


def _nested_class(tp):
    """The config dataclass an annotation holds (through Annotated / Optional), else None."""
    if typing.get_origin(tp) is Annotated:
        return _nested_class(typing.get_args(tp)[0])
    if typing.get_origin(tp) in (Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return _nested_class(inner[0]) if len(inner) == 1 else None
    return tp if isinstance(tp, type) and dataclasses.is_dataclass(tp) else None


_FIELD_CHECKS: dict[type, dict[str, tuple]] = {}


def _field_checks(cls) -> dict[str, tuple]:
    """{field: (annotation, pydantic TypeAdapter or None, nested config class or None)} of a
    dataclass, built once per class. A field whose annotation cannot be read is not checked here."""
    checks = _FIELD_CHECKS.get(cls)
    if checks is None:
        module = vars(sys.modules[cls.__module__])
        checks = {}
        for f in dataclasses.fields(cls):
            tp = f.type
            try:
                if isinstance(tp, str):
                    tp = eval(tp, dict(module), dict(vars(cls)))  # noqa: S307 (our own annotations)
                nested = _nested_class(tp)
                adapter = None if nested is not None else pydantic.TypeAdapter(tp)
            except Exception:  # an annotation pydantic cannot read: left to the class's own checks
                tp, nested, adapter = None, None, None
            checks[f.name] = (tp, adapter, nested)
        _FIELD_CHECKS[cls] = checks
    return checks


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 80 else r[:77] + "..."


def _nested_value(name: str, tp, cls, v):
    if isinstance(v, cls) or (v is None and _accepts_none(tp)):
        return v
    if isinstance(v, dict):
        try:
            return cls.from_dict(dict(v)) if hasattr(cls, "from_dict") else cls(**check_keys(cls, v))
        except ConfigError as e:
            raise e.within(name) from None
    raise ConfigError(name, f"must be {allowed_values(tp)}, got {_short(v)}")


def _accepts_none(tp) -> bool:
    return typing.get_origin(tp) in (Union, types.UnionType) and type(None) in typing.get_args(tp)


def check_fields(obj) -> None:
    """Validate every field of the dataclass ``obj`` against its annotation and store the
    validated value (``[1, 2]`` becomes ``(1, 2)`` for a tuple, a dict a nested config); raise
    ``ConfigError`` naming the first refused field and the allowed values."""
    for name, (tp, adapter, nested) in _field_checks(type(obj)).items():
        v = getattr(obj, name)
        if nested is not None:
            new = _nested_value(name, tp, nested, v)
        elif adapter is not None:
            try:
                new = adapter.validate_python(v)
            except pydantic.ValidationError:
                raise ConfigError(name, f"must be {allowed_values(tp)}, got {_short(v)}") from None
        else:
            continue
        if new is not v:
            object.__setattr__(obj, name, new)


def check_keys(cls, d: Any, what: str | None = None) -> dict:
    """``d`` as a dict of ``cls``'s fields; ConfigError for a non-dict or unknown keys (naming
    the first, listing the known ones)."""
    if not isinstance(d, dict):
        raise ConfigError("", f"a {cls.__name__} needs a table (dict) of keys, got {_short(d)}")
    known = sorted(f.name for f in dataclasses.fields(cls))
    unknown = sorted(str(k) for k in set(d) - set(known))
    if unknown:
        raise ConfigError(unknown[0], f"unknown {what or cls.__name__ + ' keys'} {unknown} (known: {known})")
    return d


# -- command-line flags generated from a config's fields -----------------------------------------
def described(default=dataclasses.MISSING, help: str = "", **kwargs) -> dataclasses.Field:  # noqa: A002
    """A dataclass field with a description (``help``), which its generated command-line flag
    shows (``add_config_flags``); other arguments as ``dataclasses.field``'s."""
    return dataclasses.field(default=default, metadata={"help": help}, **kwargs)


def flag_name(name: str) -> str:
    """The command-line flag of config field ``name``: ``param_loss`` -> ``--param-loss``."""
    return "--" + name.replace("_", "-")


def _base_type(tp):
    """The plain type under an annotation (through Annotated and Optional)."""
    if typing.get_origin(tp) is Annotated:
        return _base_type(typing.get_args(tp)[0])
    if typing.get_origin(tp) in (Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return _base_type(inner[0]) if len(inner) == 1 else tp
    return tp


def _flag_parser(flag: str, tp, adapter):
    """argparse's ``type=`` for a flag: the text as the field's type, validated by its annotation
    (an ``ArgumentTypeError`` naming the allowed values otherwise)."""
    import argparse
    base = _base_type(tp)
    convert = base if base in (int, float) else (type(typing.get_args(base)[0]) if typing.get_origin(base) is Literal
                                                 else str)

    def parse(text: str):
        try:
            return adapter.validate_python(convert(text))
        except (ValueError, pydantic.ValidationError):
            raise argparse.ArgumentTypeError(f"must be {allowed_values(tp)}, got {text!r}") from None
    parse.__name__ = flag
    return parse


def add_config_flags(parser, cls, names: Sequence[str] | None = None) -> list[str]:
    """A flag per field of the config dataclass ``cls`` (``names``: those fields only, default
    all) on ``parser`` (a parser or an argument group): ``--field-name`` (``flag_name``), its help
    the field's description (``described``) and default, its values checked against the field's
    annotation as they are parsed. A flag left out reads as None (``config_flags_given``); a
    boolean field defaulting to False is a switch. Returns the flags."""
    checks = _field_checks(cls)
    unknown = sorted(set(names or ()) - set(checks))
    if unknown:
        raise TypeError(f"{cls.__name__} has no field {unknown[0]!r} to make a flag of")
    out = []
    for f in dataclasses.fields(cls):
        if names is not None and f.name not in names:
            continue
        tp, adapter, _ = checks[f.name]
        if adapter is None:
            raise TypeError(f"{cls.__name__}.{f.name}: a nested config has no flag")
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        flag, text = flag_name(f.name), f.metadata.get("help", "")
        if _base_type(tp) is bool and default is False:
            parser.add_argument(flag, dest=f.name, action="store_true", default=None,
                                help=f"{text} (default: off)" if text else "default: off")
        else:
            base = _base_type(tp)
            choices = list(typing.get_args(base)) if typing.get_origin(base) is Literal else None
            parser.add_argument(flag, dest=f.name, default=None, type=_flag_parser(flag, tp, adapter), choices=choices,
                                metavar=None if choices else {int: "N", float: "X"}.get(base, "TEXT"),
                                help=f"{text} (default: {default!r})" if text else f"default: {default!r}")
        out.append(flag)
    return out


def config_flags_given(args, cls, names: Sequence[str] | None = None) -> dict[str, Any]:
    """{field: value} of the flags of ``add_config_flags(parser, cls, names)`` set in ``args``
    (an ``argparse.Namespace``)."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
            if (names is None or f.name in names) and getattr(args, f.name, None) is not None}


def config_from_flags(cls, args, names: Sequence[str] | None = None, **fields):
    """``cls(**fields, **flags set)`` from ``add_config_flags``' flags in ``args``; a refused value
    raises ``ConfigError`` naming its flag."""
    given = config_flags_given(args, cls, names)
    try:
        return cls(**{**fields, **given})
    except ConfigError as e:
        head = e.path.split(".")[0]
        raise ConfigError(flag_name(head) if head in given else e.path, e.reason) from None


def read_config_file(path, what: str = "config keys") -> dict:
    """A JSON or TOML (``.toml``) config file as a dict; ``what`` names what its table holds (for
    the error). A file that is missing raises FileNotFoundError; one that does not parse, or holds
    no table, raises ``ConfigError`` naming the file and the line."""
    import json
    from pathlib import Path
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no config file at {p}")
    try:
        text = p.read_text()
    except UnicodeDecodeError as e:
        raise ConfigError(str(p), f"not a text file ({e.reason} at byte {e.start})") from None
    if p.suffix == ".toml":
        try:
            import tomllib
        except ImportError:  # Python 3.10
            import tomli as tomllib
        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(str(p), f"not valid TOML: {e}") from None
    else:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(str(p), f"not valid JSON: {e.msg} (at line {e.lineno}, column {e.colno}); "
                                      "TOML files need the .toml suffix") from None
    if not isinstance(d, dict):
        raise ConfigError(str(p), f"a config file holds a table of {what}, got a {type(d).__name__}")
    return d


def parse_value(text: str):
    """A ``--set`` value: JSON when it parses (numbers, true/false/null, lists), else the string;
    the config's validation then checks it like any other value."""
    import json
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def apply_overrides(cfg: dict, items: Sequence[str] | None) -> dict:
    """``KEY=VALUE`` overrides (``--set``) into the nested dict ``cfg`` (changed in place and
    returned); dotted keys reach nested tables (``model.gn.latent=64``)."""
    for item in items or []:
        if "=" not in item:
            raise ConfigError("--set", f"expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        *parents, leaf = key.strip().split(".")
        if not all(k.strip() for k in parents + [leaf]):
            raise ConfigError("--set", f"malformed key {key!r} in {item!r} (keys are dotted names: model.gn.latent)")
        d = cfg
        for i, k in enumerate(parents):
            d = d.setdefault(k, {})
            if not isinstance(d, dict):
                raise ConfigError(".".join(parents[:i + 1]), f"is not a nested config, so --set {key} cannot "
                                                             "set a key inside it")
        d[leaf] = parse_value(value)
    return cfg


def _field_docs(cls) -> dict[str, str]:
    """{field: the first sentence of its description} from ``cls``'s docstring: entries written
    ``name``: text (or ``name`` (note): text), or ``name: text`` lines under an "Args:" heading."""
    doc = inspect.cleandoc(cls.__doc__ or "")
    found: dict[str, str] = {}
    entry = r"(?:\A|(?<=\n)|(?<=\. ))``(\w+)``(?:\s*\([^)]*\))?:"  # at a line's or a sentence's start
    for m in re.finditer(entry + r"\s*(.+?)(?=\s" + entry + r"|\n\s*\n|$)", doc, re.S):
        found.setdefault(m.group(1), m.group(2))
    args = doc.split("Args:", 1)
    if len(args) == 2:
        for m in re.finditer(r"^ {1,4}(\w+): (.+(?:\n {5,}.+)*)", args[1], re.M):
            found.setdefault(m.group(1), m.group(2))
    out = {}
    for name, text in found.items():
        text = " ".join(text.replace("``", "").split())
        text = re.split(r"(?<=[.])\s+(?=[A-Z(])", text)[0]
        text = text[:-1] if text.endswith(".") and not text.endswith("...") else text
        out[name] = text if len(text) <= 120 else text[:117].rsplit(" ", 1)[0] + " ..."
    return out


def config_keys(cls, prefix: str = "") -> list[tuple[str, Any, str, str]]:
    """Every key of the config dataclass ``cls`` (nested configs' keys dotted: ``model.gn.latent``)
    as (key, default, allowed values, description from the docstring or ""), in field order;
    what ``gnwarp train --help`` lists for ``--set``."""
    defaults, docs = cls(), _field_docs(cls)
    rows = []
    for name, (tp, _, nested) in _field_checks(cls).items():
        value = getattr(defaults, name)
        if nested is not None and dataclasses.is_dataclass(value):
            rows += config_keys(type(value), f"{prefix}{name}.")
            continue
        rows.append((prefix + name, value, allowed_values(tp) if tp is not None else "", docs.get(name, "")))
    return rows


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux: MemAvailable), else physical memory,
    else None (cannot be told)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def check_memory(nbytes: int, what: str, hint: str = "") -> None:
    """Refuse, before allocating, work that needs about ``nbytes`` of host memory when this machine
    has less available: ``ValueError`` naming ``what`` (its sizes), the estimate and the limit,
    then ``hint`` (what to make smaller)."""
    avail = available_memory()
    if avail is not None and nbytes > avail:
        gib = lambda n: f"{n / 2**30:.3g} GiB"  # noqa: E731
        raise ValueError(f"{what} needs about {gib(nbytes)} of memory; this machine has {gib(avail)} "
                          f"available" + (f". {hint}" if hint else ""))
