"""Episode GIFs at real speed: every control step one frame, shown for 1/10 s, with a step, coverage and success line.

`annotated_frame` is the runner's `record_frames` callable in `training.evaluate` and the HTTP client,
so both write the same GIF of the same episode; `write_gif` saves the frames (Pillow only).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["FPS", "GIF_SIZE", "annotated_frame", "write_gif"]

FPS = 10
"""The env's control rate (10 steps per simulated second), so one frame per step plays at real speed."""
GIF_SIZE = 256
_BAND = 18  # pixels of the caption band at the top
_SUCCESS = (0, 130, 0)
_RUNNING = (40, 40, 40)


def annotated_frame(frame: np.ndarray, step: int, coverage: float, success: bool) -> np.ndarray:
    """The frame shrunk to GIF_SIZE with a caption band: `step N  coverage 0.87` and `success` once reached."""
    from PIL import Image, ImageDraw  # lazy: the client imports this module without needing Pillow for scores only

    image = Image.fromarray(np.asarray(frame, dtype=np.uint8)).resize((GIF_SIZE, GIF_SIZE), Image.BILINEAR)
    draw = ImageDraw.Draw(image)
    draw.rectangle([0, 0, GIF_SIZE, _BAND], fill=_SUCCESS if success else _RUNNING)
    caption = f"step {step:3d}  coverage {coverage:.2f}" + ("  success" if success else "")
    draw.text((4, 3), caption, fill=(255, 255, 255))
    return np.asarray(image)


def write_gif(frames: list[np.ndarray], path: str | Path, fps: int = FPS) -> Path:
    """Write `frames` as a looping GIF at `fps` frames per second; returns the path."""
    if not frames:
        raise ValueError("no frames were recorded for the GIF")
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0)
    return path
