"""FrameInfo: what a media file's header says about its frames, before any pixel is decoded."""
from __future__ import annotations

from dataclasses import dataclass

# sniff() kind -> the container family as a user would name it
FORMAT_NAMES = {"npy": "NPY", "jpeg": "JPEG", "png": "PNG", "mp4": "MP4", "webm": "WEBM"}


@dataclass(frozen=True)
class FrameInfo:
    format: str  # "JPEG", "PNG", "NPY", "MP4", "WEBM"
    height: int  # native size, before any resize
    width: int
    channels: int
    dtype: str  # "uint8", "uint16", "float32"

    def describe(self, out_hw: tuple[int, int]) -> str:
        """e.g. "JPEG 480x640 -> 64x64" (height x width, as numpy shapes read)."""
        return f"{self.format} {self.height}x{self.width} -> {out_hw[0]}x{out_hw[1]}"
