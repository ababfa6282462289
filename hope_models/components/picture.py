"""Pictures of what a component sees and makes, for people to look at: frames laid out in rows and
columns beside what the model made of them (a reconstruction, a prediction), upscaled, as a PNG.

Two users, each drawn into the run dir at the end of a frame run (train/held_out_picture.py) and
shown by the Robot Editor's run page: the frame VQ-VAE's (vqvae/train.py held_out_picture: a
`strip` of held-out frames over their reconstructions) and the grid Mid Loop's
(mid_loop/grid_picture.py: a `grid` with one held-out window a row, the frame now, then each
horizon's predicted frame beside the real one). The benches (bench/vqvae_frames.py,
bench/vqvae_grid.py) draw theirs with the same functions.
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


def spread(rows: np.ndarray, n: int) -> np.ndarray:
    """n of `rows` (int64) evenly spaced through them, first and last included; all of them when fewer."""
    rows = np.asarray(rows, dtype=np.int64)
    if len(rows) == 0:
        return rows
    return rows[np.unique(np.linspace(0, len(rows) - 1, min(n, len(rows))).round().astype(np.int64))]


def spread_rows(cache, episodes: np.ndarray, n: int = FRAMES) -> np.ndarray:
    """n cache rows evenly spaced through the steps of `episodes` (cache episode indices, in the
    cache's order), first and last step included; fewer when those episodes hold fewer steps."""
    return spread(np.concatenate([np.arange(int(cache.starts[e]), int(cache.ends[e]) + 1) for e in episodes]
                                 or [np.empty(0, dtype=np.int64)]), n)


def grid(frames: np.ndarray, scale: int | None = None) -> np.ndarray:
    """uint8 [R, C, H, W, 3] frames -> one uint8 image [R H s, C W s, 3]: frame [r, c] in row r,
    column c, no gaps, every pixel an s x s block (s = scale_for(H) unless given)."""
    a = np.asarray(frames)
    if a.dtype != np.uint8 or a.ndim != 5 or a.shape[-1] != 3 or not a.shape[0] or not a.shape[1]:
        raise ValueError(f"grid needs uint8 [rows, columns, H, W, 3] frames, got {a.dtype} {list(a.shape)}")
    s = scale_for(a.shape[2]) if scale is None else int(scale)
    if s < 1:
        raise ValueError(f"grid: scale={scale} must be >= 1")
    r, c, h, w, _ = a.shape
    image = a.transpose(0, 2, 1, 3, 4).reshape(r * h, c * w, 3)
    return np.ascontiguousarray(image.repeat(s, axis=0).repeat(s, axis=1))


def strip(originals: np.ndarray, reconstructions: np.ndarray, scale: int | None = None) -> np.ndarray:
    """uint8 [N, H, W, 3] frames and their uint8 reconstructions (same shape) -> one uint8 image
    [2 H s, N W s, 3]: the frames side by side on top, each one's reconstruction under it, every
    pixel an s x s block (s = scale_for(H) unless given)."""
    a, b = np.asarray(originals), np.asarray(reconstructions)
    if a.dtype != np.uint8 or b.dtype != np.uint8 or a.ndim != 4 or a.shape[-1] != 3 or a.shape != b.shape or not len(a):
        raise ValueError(f"strip needs uint8 [N, H, W, 3] frames and reconstructions of the same shape, "
                         f"got {a.dtype} {list(a.shape)} and {b.dtype} {list(b.shape)}")
    if scale is not None and int(scale) < 1:
        raise ValueError(f"strip: scale={scale} must be >= 1")
    return grid(np.stack([a, b]), scale)


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


__all__ = ["FRAMES", "grid", "png", "scale_for", "spread", "spread_rows", "strip", "to_uint8"]
