"""Decompression bounded by what it produces, and the budget one upload's unpacking may spend.

A compressed container inside a file (an MCAP chunk, a gzipped TFRecord, an .npz member) says
how large it is, and can lie: a few KB of zstd or gzip of zeros inflate to hundreds of MB, and the
reader that trusted the header spent that memory and then minutes of CPU walking it. So every
decompressor here streams, counts what actually comes out, and stops past its cap:

    inflate_cap(compressed, limits)   what one container may inflate to: MAX_RATIO times its own
                                      size (at least RATIO_FLOOR), never past limits.max_file_bytes
    inflate_zlib                      a zlib/gzip stream's bytes, or InflateError naming the file
    open_inflated + Counted           an MCAP chunk read as it inflates, never past its stated size

An upload also carries a `Budget` (ReadLimits.budget): the bytes all its nested decompressors may
produce together (a ratio of what the client actually sent, so a zip of a file of compressed
chunks cannot multiply the ratios; kept as a ratio because these inflate into memory while a file
is read, which the absolute caps on what a package unpacks to disk do not bound), and a deadline
for its whole unpacking (the upload holds a lock while it unpacks), extended by what each package
is found to unpack to (`unpacking`). Past either, `BudgetError`: the upload is refused as a whole, never read
in part. Without a budget (the command line), a bomb is one file's error and the others are read.
"""
from __future__ import annotations

import io
import time
import zlib
from typing import Any

import lz4.frame
import zstandard

MAX_RATIO = 200  # JSON of floats inflates ~5-10x, an image array less; zeros far more
RATIO_FLOOR = 1 << 20  # below this many bytes a high ratio is harmless
CHUNK = 1 << 20


class InflateError(ValueError):
    """A container inflates past its cap; the message names the file. `status` for a view (413)."""

    def __init__(self, message: str, status: int = 413):
        super().__init__(message)
        self.message = message
        self.status = status


class BudgetError(InflateError):
    """One upload's unpacking went past its budget (bytes or time): the whole upload is refused."""


class Budget:
    """What one upload's unpacking may spend: `max_bytes` inflated by nested decompressors, and
    time until `deadline_s` seconds after it was made. Not thread-safe: one per request."""

    def __init__(self, max_bytes: int, deadline_s: float, *, setting: str = "upload_extract_s",
                 per_unpacked_mb_s: float = 0.0):
        self.max_bytes, self.seconds, self.setting = int(max_bytes), float(deadline_s), setting
        self.deadline = time.monotonic() + self.seconds
        self.inflated = 0
        self.per_unpacked_mb_s = float(per_unpacked_mb_s)

    def unpacking(self, nbytes: int) -> None:
        """A package was found to unpack to `nbytes` (within its absolute cap): writing, reading and
        storing them may take per_unpacked_mb_s per MB more. A package of mostly zeros is small to
        send and large to store (the Pi's frames from a dropped camera inflate ~740x)."""
        extra = self.per_unpacked_mb_s * nbytes / (1 << 20)
        self.seconds += extra
        self.deadline += extra

    def check(self, where: str) -> None:
        if time.monotonic() > self.deadline:
            raise BudgetError(f"{where}: unpacking this upload took more than {self.seconds:.3g} s ({self.setting} "
                              f"and its size); send fewer or smaller packages per request")

    def spend(self, n: int, where: str) -> None:
        self.inflated += n
        if self.inflated > self.max_bytes:
            raise BudgetError(f"{where}: the compressed data inside this upload inflates to more than "
                              f"{self.max_bytes} bytes, {MAX_RATIO} times what was sent (a decompression bomb?)")
        self.check(where)


def ratio_limit(compressed: int) -> int:
    return max(RATIO_FLOOR, compressed * MAX_RATIO)


def inflate_cap(compressed: int, limits: Any) -> int:
    return min(int(limits.max_file_bytes), ratio_limit(compressed))


class _Sink:
    """Collects output chunks in one buffer (no copy to join them), counting them against the cap
    and the budget."""

    def __init__(self, cap: int, where: str, what: str, budget: Budget | None):
        self.cap, self.where, self.what, self.budget = cap, where, what, budget
        self.buf = bytearray()
        self.size = 0

    def add(self, chunk: bytes) -> None:
        self.size += len(chunk)
        if self.size > self.cap:
            raise InflateError(f"{self.where}: {self.what} inflates to more than {self.cap} bytes (over "
                               f"{MAX_RATIO} times its compressed size, or max_file_bytes): refused")
        if self.budget is not None:
            self.budget.spend(len(chunk), self.where)
        self.buf += chunk

    def bytes(self) -> bytearray:
        return self.buf


def inflate_zlib(data: bytes | memoryview, wbits: int, cap: int, where: str, what: str,
                 budget: Budget | None = None) -> tuple[bytearray, Any]:
    """One zlib/gzip stream of `data` (wbits as zlib's), inflated CHUNK by CHUNK; returns (the
    bytes, the decompressobj: eof, unused_data). zlib.error passes through for the caller's words."""
    sink = _Sink(cap, where, what, budget)
    d = zlib.decompressobj(wbits=wbits)
    chunk = d.decompress(data, CHUNK)
    while chunk:
        sink.add(chunk)
        chunk = b"" if d.eof else d.decompress(d.unconsumed_tail, CHUNK)
    if not d.eof:
        sink.add(d.flush())  # what a cut-short stream still holds: at most a window
    return sink.bytes(), d


def open_inflated(compression: str, data: bytes) -> Any:
    """A file-like reader of `data` inflated as it is read: MCAP's compressions ("" = stored)."""
    if compression == "zstd":

        return zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True)
    if compression == "lz4":

        return lz4.frame.open(io.BytesIO(data), "rb")
    if compression == "":
        return io.BytesIO(data)
    raise ValueError(f"compression {compression!r} is not supported (zstd, lz4 or none)")


class Counted:
    """Reads exactly what is asked of an inflating stream, never past `size` (what its container
    states: asking for more is damage, ValueError), counting into the budget, with a running CRC32."""

    def __init__(self, stream: Any, size: int, where: str, budget: Budget | None = None):
        self.stream, self.limit, self.where, self.budget = stream, size, where, budget
        self.size = self.crc = 0

    def read(self, n: int) -> bytes:
        if self.size + n > self.limit:
            raise ValueError(f"a record runs past the end of its chunk ({self.limit} bytes)")
        parts, want = [], n
        while want:
            data = self.stream.read(min(want, CHUNK))
            if not data:
                raise ValueError(f"a chunk inflates to {self.size + n - want} bytes, less than it states")
            parts.append(data)
            want -= len(data)
            if self.budget is not None:
                self.budget.spend(len(data), self.where)
        out = b"".join(parts)
        self.size += n
        self.crc = zlib.crc32(out, self.crc)
        return out


__all__ = ["Budget", "BudgetError", "CHUNK", "Counted", "InflateError", "MAX_RATIO", "RATIO_FLOOR", "inflate_cap",
           "inflate_zlib", "open_inflated", "ratio_limit"]
