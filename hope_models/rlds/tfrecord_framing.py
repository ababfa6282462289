"""TFRecord framing: finding the records in a byte stream, and undoing gzip, both at native speed.

Framing per record: u64 length, masked CRC32C of the length, payload, masked CRC32C of the
payload. After damage the reader looks for the next offset where a whole valid record starts.
Trying every offset in Python cost ~1 s per MB (a gzip of zeros took minutes), so the offsets are
sifted with numpy first: CRC32C is affine over GF(2), so the CRC of the 8 length bytes at every
offset of a block is a constant XOR a few table lookups, compared with the stored CRC at once;
only the offsets that pass (for garbage or zeros: almost none) are checked record by record.

gzip is inflated chunk by chunk under inflate_cap (rlds/inflate.py): a file whose gzip data
inflates past it is refused with InflateError, never inflated whole first.
"""
from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field

import crc32c
import numpy as np

from .episode import WARNING, Problem
from .inflate import Budget, inflate_cap, inflate_zlib
from .json_text import ReadLimits

GZIP_MAGIC = b"\x1f\x8b"
HEADER = 12  # u64 length + u32 masked crc
FOOTER = 4
MASK_DELTA = 0xA282EAD8
BLOCK = 1 << 20  # offsets sifted at once: ~40 MB of numpy temporaries
_TABLES: tuple[np.ndarray, np.ndarray] | None = None
_ZERO_CRC = crc32c.crc32c(bytes(8))


def masked_crc(data: bytes) -> int:
    crc = crc32c.crc32c(data)
    return (((crc >> 15) | (crc << 17)) + MASK_DELTA) & 0xFFFFFFFF


def _tables() -> tuple[np.ndarray, np.ndarray]:
    """Each byte position's part of the CRC of 8 bytes ([8, 256]), and each byte pair's ([4, 65536])."""
    global _TABLES
    if _TABLES is None:
        by_byte = np.zeros((8, 256), np.uint32)
        for i in range(8):
            for b in range(256):
                probe = bytearray(8)
                probe[i] = b
                by_byte[i, b] = crc32c.crc32c(bytes(probe)) ^ _ZERO_CRC
        pair = np.arange(65536)
        by_pair = np.stack([by_byte[2 * j][pair & 0xFF] ^ by_byte[2 * j + 1][pair >> 8] for j in range(4)])
        _TABLES = (by_byte, by_pair)
    return _TABLES


@dataclass
class RecordScan:
    records: list[tuple[int, bytes]] = field(default_factory=list)  # (offset, payload)
    corrupt: list[tuple[int, int]] = field(default_factory=list)  # (offset, length) of skipped bytes
    truncated_tail: int = 0  # bytes of an incomplete last record


def valid_record_at(data: bytes, pos: int) -> int | None:
    """Length of a fully valid record starting at `pos`, else None."""
    end = len(data)
    if pos + HEADER + FOOTER > end:
        return None
    (length,) = struct.unpack_from("<Q", data, pos)
    if pos + HEADER + length + FOOTER > end:
        return None
    (length_crc,) = struct.unpack_from("<I", data, pos + 8)
    if masked_crc(data[pos:pos + 8]) != length_crc:
        return None
    payload_start = pos + HEADER
    (data_crc,) = struct.unpack_from("<I", data, payload_start + length)
    if masked_crc(data[payload_start:payload_start + length]) != data_crc:
        return None
    return length


def _masked(crc: np.ndarray) -> np.ndarray:
    return ((crc >> np.uint32(15)) | (crc << np.uint32(17))) + np.uint32(MASK_DELTA)


def _dense(data: bytes, start: int, n: int) -> np.ndarray:
    """The masked CRC of the 8 bytes at each of n offsets, and the u32 stored after them: each from
    aligned views interleaved (no gather from the data), the CRC from four byte-pair lookups."""
    by_pair = _tables()[1]
    pairs = np.empty(n + 6, np.uint16)
    for k in (0, 1):
        view = np.frombuffer(data, np.uint16, count=(n + 7 - k) // 2, offset=start + k)
        pairs[k::2] = view[:len(pairs[k::2])]
    crc = by_pair[0][pairs[0:n]] ^ by_pair[1][pairs[2:n + 2]]
    crc ^= by_pair[2][pairs[4:n + 4]]
    crc ^= by_pair[3][pairs[6:n + 6]]
    crc ^= np.uint32(_ZERO_CRC)
    stored = np.empty(n, np.uint32)
    for k in range(4):
        view = np.frombuffer(data, np.uint32, count=(n + 3 - k) // 4, offset=start + 8 + k)
        stored[k::4] = view[:len(stored[k::4])]
    return np.flatnonzero(_masked(crc) == stored) + start


def _length_crc_matches(data: bytes, start: int, stop: int) -> np.ndarray:
    """The offsets p in [start, stop) whose 8 bytes' masked CRC32C equals the u32 at p + 8.

    Sifted first by what a record there needs: a length below 4 GiB (the data is smaller), and not
    twelve zero bytes (the masked CRC of a zero length is not zero); the CRC is worked out only for
    the offsets left (or for all at once when most are left, as in a run of small numbers)."""
    n = stop - start
    a = np.frombuffer(data, np.uint8, count=n + 11, offset=start)
    if len(data) >= 1 << 32:
        return _dense(data, start, n)
    high = a[4:n + 4] | a[5:n + 5] | a[6:n + 6] | a[7:n + 7]
    rest = a[0:n] | a[1:n + 1] | a[2:n + 2] | a[3:n + 3] | a[8:n + 8] | a[9:n + 9] | a[10:n + 10] | a[11:n + 11]
    idx = np.flatnonzero((high == 0) & (rest != 0))
    if len(idx) > n // 8:
        return _dense(data, start, n)
    by_byte = _tables()[0]
    crc = np.full(len(idx), _ZERO_CRC, np.uint32)
    stored = np.zeros(len(idx), np.uint32)
    for i in range(8):
        crc ^= by_byte[i][a[idx + i]]
    for i in range(4):
        stored |= a[idx + 8 + i].astype(np.uint32) << np.uint32(8 * i)
    return idx[_masked(crc) == stored] + start


def next_valid_record(data: bytes, start: int, budget: Budget | None = None, where: str = "") -> int:
    """The first offset >= start where a whole valid record starts, else len(data)."""
    last = len(data) - HEADER - FOOTER  # a record needs at least this many bytes after it
    for block in range(start, last + 1, BLOCK):
        for pos in _length_crc_matches(data, block, min(block + BLOCK, last + 1)).tolist():
            if budget is not None:
                budget.check(where)
            if valid_record_at(data, pos) is not None:
                return pos
    return len(data)


def _truncated_at(data: bytes, pos: int) -> bool:
    """A header whose length CRC is valid but whose record runs past the end: a write cut short."""
    end = len(data)
    if pos + HEADER > end:
        return False
    (length_crc,) = struct.unpack_from("<I", data, pos + 8)
    (claimed,) = struct.unpack_from("<Q", data, pos)
    return masked_crc(data[pos:pos + 8]) == length_crc and pos + HEADER + claimed + FOOTER > end


def scan_records(data: bytes, base_offset: int = 0, budget: Budget | None = None, where: str = "") -> RecordScan:
    """All valid records in `data`, resynchronising after damage. Offsets include base_offset."""
    scan = RecordScan()
    pos = 0
    end = len(data)
    while pos < end:
        length = valid_record_at(data, pos)
        if length is not None:
            scan.records.append((base_offset + pos, data[pos + HEADER:pos + HEADER + length]))
            pos += HEADER + length + FOOTER
            continue
        if _truncated_at(data, pos):
            scan.truncated_tail = end - pos
            break
        start = pos
        pos = next_valid_record(data, pos + 1, budget, where)
        scan.corrupt.append((base_offset + start, pos - start))
    return scan


@dataclass
class Container:
    """The TFRecord byte stream(s) of one file after undoing gzip."""

    parts: list[tuple[int, bytes]]  # (offset in the file, or -1 for decompressed data, bytes)
    notes: list[Problem] = field(default_factory=list)


def unwrap_gzip(data: bytes, source: str, limits: ReadLimits) -> Container:
    """The gzip members at the start of `data` inflated (InflateError past inflate_cap), and what
    follows them as uncompressed TFRecord bytes."""
    if data[:2] != GZIP_MAGIC:
        return Container(parts=[(0, data)])
    out: list[bytes] = []
    left = inflate_cap(len(data), limits)
    pos = members = 0
    notes: list[Problem] = []
    while pos < len(data) and data[pos:pos + 2] == GZIP_MAGIC:
        try:
            chunk, d = inflate_zlib(memoryview(data)[pos:], 31, left, source, "its gzip data", limits.budget)
        except zlib.error as exc:
            notes.append(Problem(WARNING, source, f"gzip member at byte {pos} is damaged ({exc}); "
                                 f"data from there on is not read"))
            pos = len(data)
            break
        left -= len(chunk)
        out.append(chunk)
        members += 1
        if not d.eof:
            notes.append(Problem(WARNING, source, f"gzip member at byte {pos} is truncated; "
                                 f"its {len(chunk)} decompressed bytes are read"))
            pos = len(data)
            break
        pos = len(data) - len(d.unused_data)
    produced = sum(len(c) for c in out)
    parts: list[tuple[int, bytes]] = [(-1, out[0] if len(out) == 1 else b"".join(out))]
    if pos < len(data):
        notes.append(Problem(WARNING, source, (
            f"gzip data ends at byte {pos} ({members} member(s), {produced} bytes decompressed); the "
            f"remaining {len(data) - pos} bytes are not gzip and are read as uncompressed TFRecord")))
        parts.append((pos, data[pos:]))
    return Container(parts=parts, notes=notes)


__all__ = ["Container", "GZIP_MAGIC", "RecordScan", "masked_crc", "next_valid_record", "scan_records",
           "unwrap_gzip", "valid_record_at"]
