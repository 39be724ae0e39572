"""Videos: the formats a video path may name, checked before any work, and a video written whole
or not at all (to a temporary file beside it, then renamed), so that a failed write leaves an
existing file as it was."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from gnwarp.files import atomic_write, check_output_path

__all__ = ["video_suffixes", "check_video_path", "write_video"]

# animated through Pillow (an imageio dependency); the container formats need an ffmpeg plugin
PILLOW_SUFFIXES = (".gif", ".png", ".webp")
FFMPEG_SUFFIXES = (".mp4", ".mkv", ".mov", ".avi")


def video_suffixes() -> tuple[str, ...]:
    """The file endings a video may have here: GIF, APNG (.png) and WebP always; MP4 and other
    containers where imageio has an ffmpeg plugin (``imageio-ffmpeg`` or ``av``)."""
    ffmpeg = any(importlib.util.find_spec(m) is not None for m in ("imageio_ffmpeg", "av"))
    return PILLOW_SUFFIXES + (FFMPEG_SUFFIXES if ffmpeg else ())


def check_video_path(path) -> Path:
    """``path`` as a ``Path`` once it is known that a video can be written there: a writable place
    (``files.check_output_path``) and a known ending (``video_suffixes``; else ``ValueError``
    naming them)."""
    p = check_output_path(path)
    suffix = p.suffix.lower()
    if suffix not in video_suffixes():
        more = "" if suffix not in FFMPEG_SUFFIXES else " (install imageio-ffmpeg for it)"
        raise ValueError(f"video {p}: cannot write a {suffix or 'suffix-less'} video{more}; its name must end in "
                         f"one of {', '.join(video_suffixes())}")
    return p


def write_video(path, frames: np.ndarray, duration_ms: int) -> Path:
    """Write ``frames`` [F, H, W, 3] uint8 to ``path`` in the format its ending names, each frame
    shown ``duration_ms``, looping; whole or not at all."""
    import imageio.v3 as iio
    p = check_video_path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise ValueError(f"video {p}: frames must be [F >= 1, H, W, 3], got {frames.shape}")
    with atomic_write(p) as tmp:
        iio.imwrite(tmp, frames, extension=p.suffix.lower(), duration=int(duration_ms), loop=0)
    return p
