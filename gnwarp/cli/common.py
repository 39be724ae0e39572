"""What the commands share: the help formatter, config files and ``--set`` overrides, and
argument checks. Imports nothing heavy (``gnwarp --help`` loads neither torch nor Warp)."""
from __future__ import annotations

import argparse

__all__ = ["IMPLS", "Help", "paragraphs", "merged", "flat", "parse_value", "read_config", "apply_overrides",
           "config_source", "positive_ints"]

# the GN implementations (``gnwarp.gn.options.IMPLS``, which imports torch and Warp; a test keeps the two
# equal): each command imports what it needs inside its function, so --help loads neither
IMPLS = ("warp", "torch")


class Help(argparse.RawDescriptionHelpFormatter):
    """Help with each option's default appended, unless its text names one already or there is
    none to show (None, an empty list, an off switch); descriptions keep their own lines."""

    def _get_help_string(self, action):
        text = action.help or ""
        d = action.default
        if ("default" in text or d is None or d is False or d == [] or d is argparse.SUPPRESS
                or action.required or not (action.option_strings or action.nargs == "?")):
            return text
        shown = " ".join(d) if isinstance(d, list) else d
        return f"{text} (default: {shown})"


def paragraphs(*texts: str) -> str:
    """Paragraphs wrapped to 78 columns, a blank line between them (a parser's description)."""
    import textwrap
    return "\n\n".join(textwrap.fill(" ".join(t.split()), 78) for t in texts)


def merged(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s keys on top, nested tables merged key by key."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def flat(d: dict, prefix: str = "") -> list[str]:
    """A nested dict as ``key=value`` strings, nested keys dotted (what --set would take)."""
    import json
    out = []
    for k, v in d.items():
        out += flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}={json.dumps(v)}"]
    return out


def parse_value(text: str):
    """A --set value: JSON when it parses (numbers, true/false/null, lists), else the string; the
    config's validation then checks it like any other value."""
    import json
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def read_config(path: str | None) -> dict:
    """A JSON or TOML (``.toml``) config file as a dict; a file that does not parse raises
    ``ConfigError`` naming the file and the line."""
    import json
    from pathlib import Path

    from gnwarp.validation import ConfigError
    if path is None:
        return {}
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
        raise ConfigError(str(p), f"a config file holds a table of TrainConfig keys, got a {type(d).__name__}")
    return d


def apply_overrides(cfg: dict, items: list[str]) -> dict:
    """``key=value`` overrides into a nested dict; dotted keys reach nested configs (model.gn.latent=64)."""
    from gnwarp.validation import ConfigError
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


def config_source(path: str, items: list[str], flags: dict, config: str | None) -> str:
    """Where the value of config key ``path`` came from, for an error message."""
    parts = path.split(".")
    for item in reversed(items or []):
        key = item.split("=", 1)[0].strip()
        if key.split(".") == parts[:len(key.split("."))] or parts == key.split(".")[:len(parts)]:
            return f"--set {item}"
    if parts[0] in flags:
        return flags[parts[0]]
    return config or "the defaults"


def positive_ints(option: str, values) -> list[int]:
    """``values`` (strings; commas also separate) as integers >= 1, or ValueError naming ``option``."""
    out = []
    for v in values:
        for part in str(v).split(","):
            try:
                n = int(part.strip())
            except ValueError:
                n = None
            if n is None or n < 1:
                raise ValueError(f"{option} must be an integer >= 1, got {part.strip()!r}")
            out.append(n)
    if not out:
        raise ValueError(f"{option} needs at least one integer >= 1")
    return out
