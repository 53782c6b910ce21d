"""Offscreen output: frames rendered through an EGL standalone context to PNG files and an MP4.

No display is needed: Mesa's EGL + llvmpipe (Debian: libegl1, libgl1-mesa-dri) renders on the
CPU. Video goes through OpenCV's VideoWriter (MPEG-4 part 2, 'mp4v', in the pip wheels' FFmpeg).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from viewer.errors import create_context  # noqa: F401  (re-exported: the offscreen context)


class FrameWriter:
    """Write BGR frames to ``video`` (.mp4) and/or numbered PNGs in ``frames_dir``."""

    def __init__(self, video: str | Path | None, frames_dir: str | Path | None, fps: float,
                 size: tuple[int, int]) -> None:
        self.size, self.count = tuple(size), 0
        self.video_path = Path(video) if video else None
        self.frames_dir = Path(frames_dir) if frames_dir else None
        self._video = None
        if self.frames_dir is not None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
        if self.video_path is not None:
            if self.video_path.suffix.lower() not in (".mp4", ".m4v", ".mov"):
                raise ValueError(f"{self.video_path}: preview video must be .mp4")
            self.video_path.parent.mkdir(parents=True, exist_ok=True)
            self._video = cv2.VideoWriter(str(self.video_path), cv2.VideoWriter_fourcc(*"mp4v"),
                                          float(fps), self.size)
            if not self._video.isOpened():
                raise OSError(f"{self.video_path}: OpenCV cannot open an MP4 writer here")

    def write(self, image: np.ndarray, frame: int | None = None) -> None:
        h, w = image.shape[:2]
        if (w, h) != self.size:
            raise ValueError(f"frame is {w}x{h}, writer expects {self.size[0]}x{self.size[1]}")
        if self._video is not None:
            self._video.write(image)
        if self.frames_dir is not None:
            name = self.frames_dir / f"frame_{self.count if frame is None else frame:06d}.png"
            if not cv2.imwrite(str(name), image):
                raise OSError(f"{name}: cannot write PNG")
        self.count += 1

    def close(self) -> None:
        if self._video is not None:
            self._video.release()
            self._video = None

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
