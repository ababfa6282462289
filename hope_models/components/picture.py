"""Pictures of what a component sees and makes, for people to look at: a row of frames over a row
of what the model made of them (a reconstruction, a prediction), upscaled, as a PNG.

The frame VQ-VAE's held-out picture is the first user (vqvae/train.py held_out_picture: held-out
frames over their reconstructions); the trainer writes it into the run dir at the end of a frame
run (train/held_out_picture.py) and the Robot Editor's run page shows it; the benches
(bench/vqvae_frames.py, bench/vqvae_grid.py) draw theirs with the same functions.
NumPy and Pillow only: the model's part (torch) is the component's.
"""
from __future__ import annotations

import io

import numpy as np
from PIL import Image

FRAMES = 8  # frames in the trainer's picture: 8 x 192 px = 1536 px wide at 64x64
TARGET_PX = 192  # a frame is upscaled (nearest, whole factors) to about this height: a 64x64 frame's pixels stay visible


def scale_for(height: int) -> int:
    """The whole upscaling factor that brings a frame of `height` pixels closest to TARGET_PX, at least 1."""
    return max(1, round(TARGET_PX / max(1, height)))


def spread_rows(cache, episodes: np.ndarray, n: int = FRAMES) -> np.ndarray:
    """n cache rows evenly spaced through the steps of `episodes` (cache episode indices, in the
    cache's order), first and last step included; fewer when those episodes hold fewer steps."""
    rows = np.concatenate([np.arange(int(cache.starts[e]), int(cache.ends[e]) + 1) for e in episodes]
                          or [np.empty(0, dtype=np.int64)])
    if len(rows) == 0:
        return rows.astype(np.int64)
    return rows[np.unique(np.linspace(0, len(rows) - 1, min(n, len(rows))).round().astype(np.int64))]


def strip(originals: np.ndarray, reconstructions: np.ndarray, scale: int | None = None) -> np.ndarray:
    """uint8 [N, H, W, 3] frames and their uint8 reconstructions (same shape) -> one uint8 image
    [2 H s, N W s, 3]: the frames side by side on top, each one's reconstruction under it, every
    pixel an s x s block (s = scale_for(H) unless given)."""
    a, b = np.asarray(originals), np.asarray(reconstructions)
    if a.dtype != np.uint8 or b.dtype != np.uint8 or a.ndim != 4 or a.shape[-1] != 3 or a.shape != b.shape or not len(a):
        raise ValueError(f"strip needs uint8 [N, H, W, 3] frames and reconstructions of the same shape, "
                         f"got {a.dtype} {list(a.shape)} and {b.dtype} {list(b.shape)}")
    s = scale_for(a.shape[1]) if scale is None else int(scale)
    if s < 1:
        raise ValueError(f"strip: scale={scale} must be >= 1")
    image = np.concatenate([np.concatenate(list(a), axis=1), np.concatenate(list(b), axis=1)], axis=0)
    return np.ascontiguousarray(image.repeat(s, axis=0).repeat(s, axis=1))


def to_uint8(pixels: np.ndarray) -> np.ndarray:
    """Decoder pixels in ~[0, 1], [N, H, W, 3] float -> uint8, clipped and rounded."""
    return (np.clip(pixels, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def png(image: np.ndarray) -> bytes:
    """A uint8 [H, W, 3] image as PNG bytes."""
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"png needs a uint8 [H, W, 3] image, got {a.dtype} {list(a.shape)}")
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(a)).save(out, format="PNG", optimize=False)
    return out.getvalue()


__all__ = ["FRAMES", "png", "scale_for", "spread_rows", "strip", "to_uint8"]
