"""Offscreen output: frames rendered through an EGL standalone context to PNG files and an MP4.

No display is needed: Mesa's EGL + llvmpipe (Debian: libegl1, libgl1-mesa-dri) renders on the
CPU. Video is H.264 (yuv420p, the profile every browser plays) through PyAV, whose wheels ship
FFmpeg with libx264; OpenCV's pip wheels only write MPEG-4 part 2 ('mp4v'), which most browsers
do not play and which came out ~10x larger. The index (moov) is written before the media data
(mp4 muxer's ``movflags=faststart``, a second pass at close) so a browser or a DCC tool can start
playing or seeking before the whole file has arrived.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np

from viewer.errors import create_context  # noqa: F401  (re-exported: the offscreen context)

VIDEO_CODEC = "libx264"


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
            if self.size[0] % 2 or self.size[1] % 2:
                raise ValueError(f"{self.video_path}: H.264 (yuv420p) needs an even frame size, got "
                                 f"{self.size[0]}x{self.size[1]}")
            self._video = av.open(str(self.video_path), "w", options={"movflags": "faststart"})
            self._stream = self._video.add_stream(VIDEO_CODEC, rate=Fraction(fps).limit_denominator(1001),
                                                  options={"crf": "23", "preset": "veryfast"})
            self._stream.width, self._stream.height = self.size
            self._stream.pix_fmt = "yuv420p"

    def write(self, image: np.ndarray, frame: int | None = None) -> None:
        h, w = image.shape[:2]
        if (w, h) != self.size:
            raise ValueError(f"frame is {w}x{h}, writer expects {self.size[0]}x{self.size[1]}")
        if self._video is not None:
            frame_ = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="bgr24")
            self._video.mux(self._stream.encode(frame_))
        if self.frames_dir is not None:
            name = self.frames_dir / f"frame_{self.count if frame is None else frame:06d}.png"
            if not cv2.imwrite(str(name), image):
                raise OSError(f"{name}: cannot write PNG")
        self.count += 1

    def close(self) -> None:
        if self._video is not None:
            self._video.mux(self._stream.encode())  # flush the encoder's delayed frames
            self._video.close()
            self._video = None

    def __enter__(self) -> FrameWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
