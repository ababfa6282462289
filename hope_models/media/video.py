"""Camera video (H.264 mp4, VP8/VP9 webm, anything FFmpeg reads in those containers) as frames
picked by time, streamed: PyAV decodes one frame after another and only the frame to return is
converted; the video is never held whole.

The frame for a time t (seconds from the stream's first frame) is the last decoded frame whose
presentation time is at or before t, or the first frame when t comes before it. Deciding that
needs the frame after the candidate, so at most two decoded frames are held (plus what the codec
keeps for its own reference frames).
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.media.errors import DEFAULT_MAX_PIXELS, MediaError, check_pixels, label
from hope_models.media.info import FORMAT_NAMES, FrameInfo
from hope_models.media.pixels import area_resize, check_out_hw
from hope_models.media.sniff import sniff

VIDEO_KINDS = ("mp4", "webm")
# A frame counts as at or before t up to this far after it: a requested time is a float (0.3,
# i / 30) while a frame's is exact ticks (3072 / 10240), and the float may fall a hair short.
# A microsecond is far below any frame interval.
TIME_SLACK_S = 1e-6


def sniff_video(path: Path, name: str) -> str:
    try:
        kind = sniff(path)
    except OSError as exc:
        raise MediaError(f"{name}: unreadable: {exc.strerror or exc}") from None
    if kind == "empty":
        raise MediaError(f"{name}: empty file (0 bytes)")
    if kind not in VIDEO_KINDS:
        raise MediaError(f"{name}: not a video (its first bytes are {'a ' + kind if kind else 'no known format'}; "
                         "expected mp4 or webm)")
    return kind


def open_video(path: Path, name: str, max_pixels: int, threads: int = 1) -> tuple[Any, Any, FrameInfo, float | None]:
    """(container, its first video stream, FrameInfo, duration in s or None) from the headers only."""
    kind = sniff_video(path, name)
    # lazy: PyAV loads FFmpeg's libraries (about 18 MB of RSS), which a process reading only stills
    # (or only importing hope_models.data.frames) should not pay for
    import av

    try:
        container = av.open(os.fspath(path), mode="r")
    except Exception as exc:  # untrusted bytes: FFmpeg's errors come as av.error.* (and OSError)
        raise MediaError(f"{name}: undecodable {FORMAT_NAMES[kind]}: {type(exc).__name__}: {exc}") from None
    try:
        if not container.streams.video:
            found = ", ".join(s.type for s in container.streams) or "none"
            raise MediaError(f"{name}: {FORMAT_NAMES[kind]} has no video stream (streams: {found})")
        stream = container.streams.video[0]
        width, height = int(stream.codec_context.width or 0), int(stream.codec_context.height or 0)
        if width or height:  # 0x0 until decoded in some files: the first frame is checked then
            check_pixels(height, width, max_pixels, f"{FORMAT_NAMES[kind]} video stream", name)
        stream.thread_count = threads  # 1: one core and one frame in flight; FFmpeg's frame threads hold more
        duration = None
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        elif container.duration is not None:
            duration = container.duration / av.time_base
        return container, stream, FrameInfo(FORMAT_NAMES[kind], height, width, 3, "uint8"), duration
    except MediaError:
        container.close()
        raise
    except Exception as exc:
        container.close()
        raise MediaError(f"{name}: undecodable {FORMAT_NAMES[kind]}: {type(exc).__name__}: {exc}") from None


class VideoFrames:
    """A video file opened for frames picked by time; use as a context manager.

    `where` names the file in messages (a URI, a field) along with its path. MediaError on open:
    not a video, no video stream, a declared size above max_pixels, or no decodable first frame.
    """

    def __init__(self, path: str | os.PathLike, where: str | None = None, max_pixels: int = DEFAULT_MAX_PIXELS,
                 threads: int = 1):
        self.path = Path(path)
        self.name = label(path, where)
        self._max_pixels, self._threads = max_pixels, threads
        self._container: Any = None
        self._started = False
        self._open()
        self.info: FrameInfo = self._info
        self.duration_s: float | None = self._duration

    def _open(self) -> None:
        self._container, self._stream, self._info, self._duration = open_video(
            self.path, self.name, self._max_pixels, self._threads)
        self._decoded = self._container.decode(self._stream)
        try:
            self._first = self._next()
        except MediaError:
            self.close()
            raise
        if self._first is None:
            self.close()
            raise MediaError(f"{self.name}: {self._info.format} video stream holds no decodable frame")
        self._pts0 = self._first.pts

    def _next(self) -> Any:
        """The next decoded frame, or None at the end; MediaError on bad bytes or a frame without time."""
        try:
            frame = next(self._decoded, None)
        except Exception as exc:  # untrusted bytes: FFmpeg's decode errors
            raise MediaError(f"{self.name}: undecodable {self._info.format} frame: {type(exc).__name__}: {exc}") from None
        if frame is None:
            return None
        if frame.pts is None or frame.time_base is None:
            raise MediaError(f"{self.name}: a {self._info.format} frame has no presentation time")
        check_pixels(frame.height, frame.width, self._max_pixels, f"{self._info.format} frame", self.name)
        return frame

    def frames_at(self, times_s: Sequence[float], out_hw: tuple[int, int], kind: str = "rgb") -> Iterator[np.ndarray]:
        """uint8 [H, W, 3] per requested time (seconds from the first frame, non-decreasing), area-resized.

        A second call starts again from the first frame (the file is reopened)."""
        if kind == "depth":  # the file, not the call, is what does not fit: a depth camera's video
            raise MediaError(f"{self.name}: a {self.info.format} video holds colour frames, not depth")
        if kind != "rgb":
            raise ValueError(f"kind {kind!r}: expected 'rgb' (or 'depth', which no video holds)")
        hw = check_out_hw(out_hw)
        if self._container is None:
            raise ValueError(f"{self.name}: the video is closed")
        if self._started:
            self.close()
            self._open()
        self._started = True
        return self._pick(times_s, hw)

    def _pick(self, times_s: Sequence[float], out_hw: tuple[int, int]) -> Iterator[np.ndarray]:
        current, following = self._first, None
        self._first = None  # the iterator holds it now; one reference, released as soon as it is passed
        ended, chosen, previous = False, None, -math.inf
        for t in times_s:
            t = float(t)
            if not math.isfinite(t) or t < previous:
                raise ValueError(f"times_s: {t!r} after {previous!r}; times must be finite and non-decreasing")
            previous = t
            while not ended:
                if following is None:
                    following = self._next()
                    ended = following is None
                if following is None or self._since_first(following) > t + TIME_SLACK_S:
                    break
                current, following, chosen = following, None, None
            if chosen is None:
                chosen = area_resize(self._rgb(current), out_hw)
                current = None  # converted: the decoded frame is not needed any more
            yield chosen.copy()

    def _since_first(self, frame: Any) -> float:
        """Seconds from the first frame (ticks counted from the first frame's, then scaled once)."""
        return float((frame.pts - self._pts0) * Fraction(frame.time_base))

    def _rgb(self, frame: Any) -> np.ndarray:
        try:
            return frame.to_ndarray(format="rgb24")
        except Exception as exc:  # a frame FFmpeg decoded but cannot convert (odd pixel format)
            raise MediaError(f"{self.name}: {self._info.format} frame not convertible to RGB: {exc}") from None

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
            self._container, self._decoded, self._first = None, None, None

    def __enter__(self) -> VideoFrames:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
