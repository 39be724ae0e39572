"""Videos: the formats a video path may name, checked before any work, and a video written whole
or not at all (to a temporary file beside it, then renamed), so that a failed write leaves an
existing file as it was."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gnwarp.files import atomic_write, check_output_path, remove_stale_temporaries

__all__ = ["video_suffixes", "check_video_path", "write_video"]

# animated through Pillow (an imageio dependency): the formats written with a frame duration and looping
VIDEO_SUFFIXES = (".gif", ".png", ".webp")


def video_suffixes() -> tuple[str, ...]:
    """The file endings a video may have: GIF, APNG (.png) and WebP."""
    return VIDEO_SUFFIXES


def check_video_path(path) -> Path:
    """``path`` as a ``Path`` once it is known that a video can be written there: a writable place
    (``files.check_output_path``) and a known ending (``video_suffixes``; else ``ValueError``
    naming them)."""
    p = check_output_path(path)
    suffix = p.suffix.lower()
    if suffix not in video_suffixes():
        raise ValueError(f"video {p}: cannot write a {suffix or 'suffix-less'} video; its name must end in one of "
                         f"{', '.join(video_suffixes())}")
    return p


def write_video(path, frames: np.ndarray, duration_ms: int) -> Path:
    """Write ``frames`` [F, H, W, 3] uint8 to ``path`` in the format its ending names, each frame
    shown ``duration_ms``, looping; whole or not at all (the temporaries of earlier writes that
    were killed removed)."""
    import imageio.v3 as iio
    p = check_video_path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise ValueError(f"video {p}: frames must be [F >= 1, H, W, 3], got {frames.shape}")
    remove_stale_temporaries(p)   # what a write to this path killed before its rename left
    with atomic_write(p) as tmp:
        iio.imwrite(tmp, frames, extension=p.suffix.lower(), duration=int(duration_ms), loop=0)
    return p
