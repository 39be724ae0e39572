"""Small file helpers shared by the stages that write files: checksums and JSON-safe values."""
from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["sha256_file", "jsonable", "pid_alive"]


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
