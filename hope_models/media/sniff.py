"""What a file holds, told by its first bytes only (never its name or a declared content type)."""
from __future__ import annotations

import os

_NPY = b"\x93NUMPY"
_JPEG = b"\xff\xd8\xff"
_PNG = b"\x89PNG\r\n\x1a\n"
_EBML = b"\x1a\x45\xdf\xa3"  # Matroska and WebM share the EBML header
# An ISO base media file (mp4, mov) opens with a box: 4-byte size, then its type; a camera's
# file starts with ftyp, an old QuickTime one may start straight with moov.
_ISO_FIRST_BOXES = (b"ftyp", b"moov")

SNIFF_BYTES = 16


def sniff_bytes(head: bytes) -> str | None:
    """"npy", "jpeg", "png", "mp4", "webm", "empty" (no bytes) or None for the first bytes of a file."""
    if not head:
        return "empty"
    if head.startswith(_NPY):
        return "npy"
    if head.startswith(_JPEG):
        return "jpeg"
    if head.startswith(_PNG):
        return "png"
    if head.startswith(_EBML):
        return "webm"
    if len(head) >= 8 and head[4:8] in _ISO_FIRST_BOXES:
        return "mp4"
    return None


def sniff(path: str | os.PathLike) -> str | None:
    """The kind of media in a file by its magic bytes; OSError when it cannot be read."""
    with open(path, "rb") as f:
        return sniff_bytes(f.read(SNIFF_BYTES))
