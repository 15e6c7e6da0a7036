"""Short rollout videos for the eye: a third-person camera next to the agent's own view."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import imageio.v2 as imageio
import numpy as np


def write_video(path: str | Path, frames: Sequence[np.ndarray], fps: float) -> Path:
    """mp4 through imageio-ffmpeg; falls back to gif if ffmpeg is unavailable."""
    path = Path(path)
    try:
        imageio.mimwrite(path, list(frames), fps=fps, macro_block_size=1)
        return path
    except (RuntimeError, ValueError, ImportError):
        gif = path.with_suffix(".gif")
        imageio.mimwrite(gif, list(frames), duration=1.0 / fps)
        return gif
