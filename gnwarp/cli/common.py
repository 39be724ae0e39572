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
    """A --set value (``gnwarp.validation.parse_value``): JSON when it parses, else the string."""
    from gnwarp.validation import parse_value as parse
    return parse(text)


def read_config(path: str | None) -> dict:
    """A JSON or TOML (``.toml``) config file of TrainConfig keys as a dict ({} for None); the
    reader is ``gnwarp.validation.read_config_file``."""
    from gnwarp.validation import read_config_file
    return {} if path is None else read_config_file(path, "TrainConfig keys")


def apply_overrides(cfg: dict, items: list[str]) -> dict:
    """``key=value`` overrides into a nested dict (``gnwarp.validation.apply_overrides``)."""
    from gnwarp.validation import apply_overrides as apply
    return apply(cfg, items)


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
