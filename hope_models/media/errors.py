"""MediaError, the one error of the media layer, and how its messages name the file."""
from __future__ import annotations

import os

DEFAULT_MAX_PIXELS = 50_000_000  # a 50 MP frame: far above any robot camera, far below a bomb


class MediaError(ValueError):
    """A media file cannot be used; the message names the file (and its URI when given) and what is wrong."""


def label(path: str | os.PathLike, where: str | None) -> str:
    """How a message names the file: `where` (a URI, a field) with the path, or the path alone."""
    return f"{where} ({os.fspath(path)})" if where else os.fspath(path)


def check_pixels(height: int, width: int, max_pixels: int, what: str, name: str) -> None:
    """MediaError before decoding when a declared size is empty or above the pixel limit."""
    if height <= 0 or width <= 0:
        raise MediaError(f"{name}: {what} declares an empty size {height}x{width}")
    if height * width > max_pixels:
        raise MediaError(f"{name}: {what} declares {height}x{width} = {height * width} pixels, "
                         f"above the limit of {max_pixels} (max_pixels); refused before decoding")
