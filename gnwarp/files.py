"""Small file helpers shared by the stages that write files: checksums, JSON-safe values and the
check that an output path can be written before any work starts."""
from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["sha256_file", "jsonable", "pid_alive", "check_output_path"]


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` may still be running (True when it cannot be told, e.g. another
    user's process): files a killed writer left may be removed only when this is False."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def jsonable(x):
    """``x`` with numpy scalars made Python numbers, tuples made lists, dict keys made strings and
    non-finite floats made None (JSON has no NaN), recursively."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer, np.bool_)):
        return x.item()
    return x


def check_output_path(path: str | os.PathLike, folder: bool = False) -> Path:
    """``path`` as a ``Path`` once it is known that it can be written, before any work starts.

    A file (``folder`` False): its parent folder must exist and be writable, and ``path`` must
    not be a folder. A folder (``folder`` True; made with its parents): ``path`` must be a folder
    if it exists, and the nearest existing folder above it must be writable (no file on the way).
    Raises ``FileNotFoundError`` (a missing parent folder), ``NotADirectoryError`` /
    ``IsADirectoryError`` (a file where a folder goes, or the reverse) or ``PermissionError``
    (not writable), each naming the path."""
    p = Path(path)
    if str(p) == "":
        raise FileNotFoundError("empty output path")
    if folder:
        if p.exists() and not p.is_dir():
            raise NotADirectoryError(f"output folder {p} is a file")
        base = p
        while not base.exists():  # the folder is made with its parents: the first existing one decides
            if base.parent == base:
                break
            base = base.parent
        if base.exists() and not base.is_dir():
            raise NotADirectoryError(f"cannot make output folder {p}: {base} is a file")
    else:
        if p.is_dir():
            raise IsADirectoryError(f"output file {p} is a folder")
        base = p.parent
        if not base.exists():
            raise FileNotFoundError(f"folder of output file {p} does not exist: {base} (make it first)")
        if not base.is_dir():
            raise NotADirectoryError(f"folder of output file {p} is a file: {base}")
    target = p if p.exists() else base
    if not os.access(target, os.W_OK) or (target.is_dir() and not os.access(target, os.X_OK)):
        raise PermissionError(f"cannot write {'output folder' if folder else 'output file'} {p}: "
                              f"{target} is not writable")
    return p
