"""Rendered episodes to files: an mp4 at full size and a light gif for the MLflow UI."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

#: The gif keeps every n-th frame at 1/n of the size in each dimension (mp4 keeps everything).
GIF_STRIDE = 2


def write_mp4(frames: list[np.ndarray], path: Path, fps: float) -> Path:
    iio.imwrite(path, np.stack(frames), fps=fps, macro_block_size=1)
    return path


def write_gif(frames: list[np.ndarray], path: Path, fps: float, stride: int = GIF_STRIDE) -> Path:
    small = np.stack(frames[::stride])[:, ::stride, ::stride]
    iio.imwrite(path, small, duration=1000 * stride / fps, loop=0)
    return path


def write_videos(frames: list[np.ndarray], stem: Path, fps: float) -> list[Path]:
    """``stem``.mp4 and ``stem``.gif from the same frames."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    return [
        write_mp4(frames, stem.with_suffix(".mp4"), fps),
        write_gif(frames, stem.with_suffix(".gif"), fps),
    ]
