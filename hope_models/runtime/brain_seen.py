"""The camera frame of one BrainService request, decoded once per frame size and encoded once per
frame encoder, whichever served components read it. Torch-free.

    seen = SeenFrame(request_value)          # nothing decoded yet
    seen.codes(model.frame_vq)               # uint8 [H, W, 3] at that VQ-VAE's size -> its codes [G]

A served model reads the camera when its `frame_shape` is not None; its `frame_vq` (a VQVAENumpy
with a frame encoder) turns the frame into codes. Two models whose frame VQ-VAEs are the same
weights (the promoted tokenizer and the one a camera reflex carries, usually) share one encode:
codes are kept by the encoder's fingerprint (a sha256 of its weights and codebook, computed at
load), never by a name or a path. Decoding errors are brain_frame's BrainError(400).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from hope_models.runtime.brain_frame import frame_from_request
from hope_models.runtime.brain_input import BrainError

FRAME_FORMS = ("a base64 JPEG/PNG (a data: URL is fine), {\"encoding\": \"jpeg\"|\"png\", \"data\": ...}, "
               "{\"encoding\": \"raw\", \"shape\": [H, W, 3], \"data\": <base64 of H*W*3 bytes>} or [H][W][3] "
               "integer lists")


def frame_shape(model: Any) -> tuple[int, ...] | None:
    """The camera frame a served model reads, or None (a runtime without the attribute reads none)."""
    return getattr(model, "frame_shape", None)


def describe_shape(shape: tuple[int, ...]) -> str:
    return "x".join(map(str, shape))


class SeenFrame:
    def __init__(self, value: Any):
        self.value = value
        self._pixels: dict[tuple[int, ...], np.ndarray] = {}
        self._codes: dict[str, np.ndarray] = {}

    def pixels(self, shape: tuple[int, ...]) -> np.ndarray:
        px = self._pixels.get(shape)
        if px is None:
            px = self._pixels[shape] = frame_from_request(self.value, (shape[0], shape[1], shape[2]))
        return px

    def codes(self, vq: Any) -> np.ndarray:
        """The codes of the frame by the frame VQ-VAE `vq` (VQVAENumpy) -> int [G]."""
        got = self._codes.get(vq.fingerprint)
        if got is None:
            got = self._codes[vq.fingerprint] = vq.codes(self.pixels(vq.frame_shape))
        return got


def check_frame(frame: Any, readers: dict[str, Any], component: str, model: Any) -> SeenFrame | None:
    """The request's frame against the served models that read one (readers: name -> model):
    BrainError(400) when they read a camera and no frame came, or a frame came and none reads one."""
    if frame is None:
        if readers:
            names = ", ".join(f"{name} {m.version} ({describe_shape(frame_shape(m) or ())})" for name, m in readers.items())
            raise BrainError(f"frame is missing: {names} read the camera; send `frame` with the joints: {FRAME_FORMS}")
        return None
    if not readers:
        raise BrainError(f"frame: no served component answering this request reads a camera ({component} "
                         f"{model.version} reads {model.describe_observation()}); send no frame")
    return SeenFrame(frame)


__all__ = ["FRAME_FORMS", "SeenFrame", "check_frame", "describe_shape", "frame_shape"]
