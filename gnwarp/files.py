"""Small file helpers shared by the stages that write files: atomic writes, checksums, JSON-safe
values and the check that an output path can be written before any work starts."""
from __future__ import annotations

import contextlib
import glob
import hashlib
import math
import os
import re
import shutil
from pathlib import Path

import numpy as np

__all__ = ["sha256_file", "jsonable", "plain_values", "pid_alive", "atomic_write", "temporary_of", "remove_stale_temporaries",
           "check_output_path", "write_or_check"]

_TEMPORARY = re.compile(r"^\.(?P<name>.+)\.tmp-(?P<pid>\d+)$")


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


def temporary_of(path: str | Path, kind: str = "tmp", pid: int | None = None) -> Path:
    """``.<name>.<kind>-<pid>`` beside ``path``: where ``atomic_write`` writes (kind "tmp") and
    puts a replaced folder aside (kind "old"); this process's unless ``pid``."""
    path = Path(path)
    return path.parent / f".{path.name}.{kind}-{os.getpid() if pid is None else pid}"


def tensor_digest(tensors: dict, keys=None) -> str:
    """The SHA-256 of tensors (``{name: tensor}``, in the order of ``keys``, default sorted names):
    each one's name, dtype, shape and bytes, so that a changed value, shape or name changes it.
    Files of tensors keep it beside them and compare it on loading (corruption detected)."""
    h = hashlib.sha256()
    for k in (sorted(tensors) if keys is None else keys):
        t = tensors[k]
        h.update(f"{k}:{t.dtype}:{tuple(t.shape)};".encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


@contextlib.contextmanager
def locked(path: str | Path):
    """Hold an exclusive lock for ``path`` for the block: ``flock`` on its folder (no lock file is
    left behind), so that writers that read a file, add to it and rename it over
    (``write_records``) take turns instead of losing each other's additions. Where the system
    has no ``fcntl`` (Windows), the block runs unlocked."""
    try:
        import fcntl
    except ImportError:   # no advisory locks here
        yield
        return
    try:
        fd = os.open(Path(path).parent, os.O_RDONLY)
    except OSError:   # a folder that cannot be opened for reading: the write itself will say what is wrong
        yield
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:   # a file system without flock (some network mounts): unlocked, as before
            pass
        yield
    finally:
        os.close(fd)   # (closing releases the lock)


@contextlib.contextmanager
def atomic_write(path: str | Path, folder: bool = False):
    """Write the file (or, with ``folder``, the folder) ``path`` whole or not at all.

    Yields a temporary path beside it (``temporary_of(path)``: the same folder, so the rename
    stays on one file system; with ``folder``, an empty folder) to write into. When the block
    ends, what the block wrote is flushed to the disk (fsync) and renamed over ``path``; when it
    raises, the temporary is removed and ``path`` stays as it is. A folder replacing another
    is moved aside first (``temporary_of(path, "old")``, removed after the rename; a kill between
    the two renames leaves both beside ``path``, for a recovery to pick up: the checkpoints'
    ``recover_checkpoint``). The caller makes the parent folder."""
    path = Path(path)
    tmp, old = temporary_of(path), temporary_of(path, "old")
    for p in (tmp, old):   # this process's leftovers of an earlier failed write
        _remove(p)
    if folder:
        tmp.mkdir()
    moved = False
    try:
        yield tmp
        for f in (sorted(tmp.iterdir()) if folder else [tmp]):
            _fsync(f)
        if folder and path.exists():
            os.replace(path, old)
            moved = True
        os.replace(tmp, path)
        _fsync(path.parent)   # the rename itself
    except BaseException:
        if moved and not path.exists():   # put the previous folder back
            with contextlib.suppress(OSError):
                os.replace(old, path)
        _remove(tmp)
        raise
    if moved:
        _remove(old)


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the temporaries (``.<name>.tmp-<pid>``) of ``path`` that writes killed before their
    rename left beside it: those of processes no longer running. Returns the paths removed."""
    path = Path(path)
    parent = path.parent if str(path.parent) else Path(".")
    removed = []
    for p in parent.glob("." + glob.escape(path.name) + ".tmp-*"):
        m = _TEMPORARY.match(p.name)
        if m is None or m["name"] != path.name or pid_alive(int(m["pid"])):  # a running writer's: left alone
            continue
        _remove(p)
        removed.append(p)
    return removed


def _fsync(path: Path) -> None:
    """Flush a file's (or a folder's entries') writes to the disk; a no-op where the system
    cannot open it for that (folders on some systems)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


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


def write_or_check(path: str | Path, text: str, check: bool, command: str) -> int:
    """A file generated from other files: with ``check``, 0 when ``path`` holds exactly ``text``,
    else 1 with a line on stderr naming ``command`` (what regenerates it); without, ``text`` is
    written whole (``atomic_write``, the parent folder made) and 0 returned."""
    import sys  # noqa: PLC0415
    path = Path(path)
    if check:
        if not path.exists() or path.read_text() != text:
            print(f"{path} differs from its records: run {command}", file=sys.stderr)
            return 1
        return 0
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as tmp:
        Path(tmp).write_text(text)
    print(f"wrote {path}")
    return 0


def plain_values(x, where: str):
    """``x`` as tensors and plain values only (what ``torch.load(weights_only=True)`` reads back):
    numpy scalars and arrays converted; anything else raises TypeError naming where it is (the
    checkpoints' state, ``gnwarp.train.checkpoint`` and ``gnwarp.rl.run_log``)."""
    import torch
    if isinstance(x, np.generic):  # before float: np.float64 is one
        return x.item()
    if x is None or type(x) in (bool, int, float, str):
        return x
    if isinstance(x, torch.Tensor):
        return x.detach()
    if isinstance(x, np.ndarray):
        return torch.from_numpy(x.copy())
    if isinstance(x, dict):
        for k in x:
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"{where}: key {k!r} is a {type(k).__name__}; checkpoint keys are str or int")
        return {k: plain_values(v, f"{where}[{k!r}]") for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(plain_values(v, f"{where}[{i}]") for i, v in enumerate(x))
    raise TypeError(f"{where} is a {type(x).__module__}.{type(x).__qualname__}; a checkpoint's state "
                    "holds only tensors and plain values (dict, list, tuple, int, float, bool, str, None)")
