"""Streaming rendered reacher frames as JSON lines while an episode runs (eval-reflex --stream-frames).

    stream = FrameStream(sys.stdout, fps=10, size=128, speed=1.0)
    evaluate_policy(policy, seeds, task, frames=stream)   # the first episode is rendered
    stream.summary()  # {"fps", "size", "speed", "sent", "error"}

One line per frame, flushed at once:

    {"frame": {"episode": 0, "seed": S, "step": t, "image": "data:image/png;base64,...",
               "return_so_far": R, "done": false}}

`step` is the number of control steps taken (0 = after reset, before the first action; the last
frame has step = the episode's length and "done": true), `return_so_far` the sum of the rewards of
those steps. A frame is rendered every round(50 / fps) control steps (fps frames per simulated
second; the control period is 20 ms), plus the last step. With speed > 0 the episode is paced so that
simulated time does not run ahead of speed x wall time (1.0: real time, 20 s for 1000 steps), so the
frames arrive at about fps per second; speed 0 runs as fast as the sim goes.

Rendering needs a GL backend chosen before dm_control is imported (MUJOCO_GL=egl; see reacher.py).
If the first render fails (no EGL, no GPU/Mesa driver), one line {"frame_error": "..."} is written,
`error` says why, no frame is sent, and the episode itself goes on unchanged: the evaluation is still
valid, and its result reports the frames' failure instead of pretending there were some.

PNGs are written by png_bytes (zlib, 8-bit RGB, no filter): no imaging library is needed.
"""
from __future__ import annotations

import base64
import json
import os
import struct
import time
import zlib
from typing import Any, Callable, TextIO

import numpy as np

from hope_models.sim.reacher import CONTROL_PERIOD_S

MAX_FPS = 1.0 / CONTROL_PERIOD_S  # one frame per control step
MIN_SIZE, MAX_SIZE = 16, 480


def png_bytes(rgb: np.ndarray) -> bytes:
    """An 8-bit RGB PNG of a uint8 [H, W, 3] array."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError(f"png_bytes needs a uint8 [H, W, 3] array, got {a.dtype} {a.shape}")
    h, w, _ = a.shape
    raw = np.zeros((h, 1 + 3 * w), dtype=np.uint8)  # filter byte 0 (None) before each row
    raw[:, 1:] = np.ascontiguousarray(a).reshape(h, 3 * w)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8-bit, colour type 2 (RGB)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw.tobytes(), 6))
            + chunk(b"IEND", b""))


def png_data_url(rgb: np.ndarray) -> str:
    return "data:image/png;base64," + base64.b64encode(png_bytes(rgb)).decode("ascii")


class FrameStream:
    """Renders one episode's frames to `out` as JSON lines (see the module docstring)."""

    def __init__(self, out: TextIO, *, fps: float, size: int = 128, speed: float = 1.0,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
        if not 0 < fps <= MAX_FPS:
            raise ValueError(f"fps={fps} must be within (0, {MAX_FPS:g}] (one frame per 20 ms control step at most)")
        if not MIN_SIZE <= size <= MAX_SIZE:
            raise ValueError(f"size={size} must be within {MIN_SIZE}-{MAX_SIZE} pixels")
        if speed < 0:
            raise ValueError(f"speed={speed} must be >= 0 (0: as fast as the sim runs)")
        self.out, self.fps, self.size, self.speed = out, float(fps), int(size), float(speed)
        self.every = max(1, round(MAX_FPS / fps))
        self.clock, self.sleep = clock, sleep
        self.sent = 0
        self.error: str | None = None
        self._t0: float | None = None

    def on_step(self, env, *, episode: int, seed: int, step: int, return_so_far: float, last: bool) -> None:
        """Called after reset (step 0) and after every control step; renders the due ones."""
        if self.error is not None or (step % self.every and not last):
            return
        now = self.clock()
        if self._t0 is None:
            self._t0 = now
        elif self.speed > 0:  # pace: simulated time must not run ahead of speed x wall time
            ahead = step * CONTROL_PERIOD_S / self.speed - (now - self._t0)
            if ahead > 0:
                self.sleep(ahead)
        try:
            image = png_data_url(env.render(self.size))
        except Exception as exc:  # noqa: BLE001 - any GL failure means "no frames", said once, clearly
            self.error = (f"cannot render the reacher (MUJOCO_GL={os.environ.get('MUJOCO_GL', '')}): {type(exc).__name__}: {exc}"
                          .strip())
            self._write({"frame_error": self.error})
            return
        self._write({"frame": {"episode": episode, "seed": seed, "step": step, "image": image,
                               "return_so_far": round(float(return_so_far), 6), "done": bool(last)}})
        self.sent += 1

    def _write(self, obj: dict[str, Any]) -> None:
        self.out.write(json.dumps(obj) + "\n")
        self.out.flush()

    def summary(self) -> dict[str, Any]:
        return {"fps": self.fps, "size": self.size, "speed": self.speed, "sent": self.sent, "error": self.error}


__all__ = ["FrameStream", "MAX_FPS", "png_bytes", "png_data_url"]
