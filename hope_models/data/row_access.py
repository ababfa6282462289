"""Rows of one cache array read inside a resident budget: a mapped head, pread past it.

A step array that does not fit the budget is not all-or-nothing: its first `mapped_rows` rows are
read through a mapping of just that head of the file (its touched pages count in RSS, and can
never exceed the head's size, since the mapping ends there), the rows after it with pread. The
values are the same either way. Mapping the head rather than caching hot rows keeps the reader
free of state: which rows come from where depends on the budget only, never on what was read.

The pread side pays one system call per anchor's block (a random read through the page cache,
2-4 microseconds whatever its size up to a few KB), or, when most of a call's blocks lie within
MERGE_GAP_BYTES of each other (the sampler's opt-in anchors by block make them so), one per run
of such blocks. So the budget buys speed in proportion to the rows it maps, and grouped anchors
in proportion to the reads they share.
"""
from __future__ import annotations

import mmap
import os
from typing import BinaryIO

import numpy as np


class HeadMapped:
    """`full` (the cache file `f` as an array, never touched past the head) read through the head
    mapping for rows below `mapped_rows` and with pread from `f` for the others."""

    def __init__(self, f: BinaryIO, full: np.ndarray, mapped_rows: int):
        self.fd = f.fileno()
        self.full = full
        self.n_rows = full.shape[0]
        self.row_bytes = full.strides[0] if full.ndim else full.itemsize
        self.mapped_rows = max(0, min(int(mapped_rows), self.n_rows))
        if self.mapped_rows == self.n_rows:
            self.head = full
        elif self.mapped_rows == 0:
            self.head = full[:0]
        else:
            # a mapping of the head alone: the kernel maps whole folios around a touched page, but
            # never past the end of the mapping, so the head's size bounds what it adds to RSS
            mm = mmap.mmap(self.fd, self.mapped_rows * self.row_bytes, access=mmap.ACCESS_READ)
            self.head = np.frombuffer(mm, dtype=full.dtype).reshape(self.mapped_rows, *full.shape[1:])

    @property
    def resident_bytes(self) -> int:
        """The most this array's reads can add to RSS (its mapped head)."""
        return self.mapped_rows * self.row_bytes

    def blocks(self, first: np.ndarray, n: int, pad: float) -> np.ndarray:
        """Rows first[b] .. first[b]+n-1 for each b, as a writable [B, n, ...]; rows outside the
        array read `pad`."""
        idx = first[:, None] + np.arange(n)
        if len(first) == 0:
            return np.empty((0, n, *self.full.shape[1:]), dtype=self.full.dtype)
        lo, hi = int(first.min()), int(first.max()) + n
        whole = self.mapped_rows == self.n_rows
        if self.mapped_rows and (whole or hi <= self.mapped_rows):
            # take, not fancy indexing: a few times faster for whole rows
            out = self.head.take(idx, axis=0, mode="clip")
        else:
            in_head = first + n <= self.mapped_rows
            out = np.empty((len(first), n, *self.full.shape[1:]), dtype=self.full.dtype)
            if in_head.any():
                out[in_head] = self.head.take(idx[in_head], axis=0, mode="clip")
            rest = ~in_head
            pad_row = np.full(self.full.shape[1:], pad, dtype=self.full.dtype).tobytes()
            block, slot = self._read_blocks(first[rest], n, pad_row)
            out[rest] = block.take(slot[:, None] + np.arange(n), axis=0)
        if lo < 0 or hi > self.n_rows:
            out[(idx < 0) | (idx >= self.n_rows)] = pad
        return out

    def rows(self, j: np.ndarray, first: np.ndarray | None = None, n: int = 0) -> np.ndarray:
        """full[j] for indices j [B, K] -> [B, K, ...], a writable copy. `first`/`n`, when given,
        promise that row b's indices lie in first[b] .. first[b]+n-1, which lets one pread fetch
        each row b that lies past the head."""
        if self.mapped_rows == self.n_rows:
            return self.head.take(j, axis=0)
        if first is not None and n > 256:
            first = None  # long blocks: one pread per row reads less
        in_head = (first + n <= self.mapped_rows) if first is not None else (j.max(axis=1) < self.mapped_rows)
        if in_head.all():
            return self.head.take(j, axis=0)
        out = np.empty(j.shape + self.full.shape[1:], dtype=self.full.dtype)
        if in_head.any():
            out[in_head] = self.head.take(j[in_head], axis=0)
        rest = ~in_head
        jr = j[rest]
        if first is not None:
            fr = first[rest]
            block, slot = self._read_blocks(fr, n, bytes(self.row_bytes))
            out[rest] = block.take(jr - fr[:, None] + slot[:, None], axis=0)
        else:
            out[rest] = pread_rows(self.fd, self.full, jr)
        return out

    def _read_blocks(self, first: np.ndarray, n: int, pad_row: bytes) -> tuple[np.ndarray, np.ndarray]:
        """The blocks of n rows at `first`, as rows [R, ...], and the row of it where each block
        starts. Read in file order (about a fifth less time a read than the batches' order, from
        what the page cache's lookups leave in the CPU's caches), blocks that lie within
        MERGE_GAP_BYTES of each other in one pread (see pread_runs)."""
        order = np.argsort(first, kind="stable")
        gap = max(0, MERGE_GAP_BYTES // self.row_bytes)
        raw, at = pread_runs(self.fd, self.row_bytes, self.n_rows, first[order], n, gap, pad_row)
        slot = np.empty(len(first), dtype=np.int64)
        slot[order] = at
        return np.frombuffer(raw, dtype=self.full.dtype).reshape(-1, *self.full.shape[1:]), slot


# Blocks closer than this share one pread: a random read of up to ~2 KB costs about what one of
# 100 bytes does (2-4 us here, mostly the page-cache lookup), one of 8 KB twice that.
MERGE_GAP_BYTES = 2048


def pread_runs(fd: int, row_bytes: int, n_rows: int, first: np.ndarray, n: int, gap: int,
               pad_row: bytes) -> tuple[bytes, np.ndarray]:
    """Rows first[b] .. first[b]+n-1 of the file for each b (`first` ascending), read as runs:
    blocks whose start is at most n + gap rows after the previous block's start share one pread
    of the rows from the run's first block to its last block's end (when at least an eighth of
    the blocks do; else one pread a block). Returns the runs' rows concatenated (rows outside
    0 .. n_rows-1 read as pad_row) and the row where each block starts in them."""
    if len(first) == 0:
        return b"", np.empty(0, dtype=np.int64)
    d = np.diff(first)
    apart = d > n + gap
    if np.count_nonzero(apart) * 8 >= 7 * len(d):
        # few blocks to share a read (independent anchors): working out the runs would cost more
        # than the reads it saves
        return pread_blocks(fd, row_bytes, n_rows, first, n, pad_row), np.arange(0, len(first) * n, n)
    # each block starts where the previous one did plus the rows between them (same run) or n
    at = np.zeros(len(first), dtype=np.int64)
    np.cumsum(np.where(apart, n, d), out=at[1:])
    heads = np.flatnonzero(apart)
    heads += 1
    heads = np.concatenate(([0], heads))
    lo = first[heads]
    return _read_spans(fd, row_bytes, n_rows, lo, np.diff(at[heads], append=at[-1] + n), pad_row), at


def pread_blocks(fd: int, row_bytes: int, n_rows: int, first: np.ndarray, n: int, pad_row: bytes) -> bytes:
    """Rows first[b] .. first[b]+n-1 of the file for each b, concatenated: one pread a block, rows
    outside 0 .. n_rows-1 read as pad_row."""
    if len(first) == 0:
        return b""
    if int(first.min()) >= 0 and int(first.max()) + n <= n_rows:  # the usual case: no block at an end
        pread, size = os.pread, n * row_bytes
        return b"".join([pread(fd, size, off) for off in (first * row_bytes).tolist()])
    return _read_spans(fd, row_bytes, n_rows, first, np.full(len(first), n), pad_row)


def _read_spans(fd: int, row_bytes: int, n_rows: int, lo: np.ndarray, rows: np.ndarray, pad_row: bytes) -> bytes:
    """Rows lo[i] .. lo[i]+rows[i]-1 of the file for each i, concatenated, one pread a span; rows
    outside 0 .. n_rows-1 read as pad_row."""
    pread = os.pread
    if int(lo.min()) >= 0 and int((lo + rows).max()) <= n_rows:  # the usual case: no span at an end
        return b"".join([pread(fd, size, off) for size, off in zip((rows * row_bytes).tolist(),
                                                                   (lo * row_bytes).tolist(), strict=True)])
    parts = []
    for f, e in zip(lo.tolist(), (lo + rows).tolist(), strict=True):
        a, b = max(f, 0), min(e, n_rows)
        data = pread(fd, (b - a) * row_bytes, a * row_bytes) if b > a else b""
        if a > f or e > b:
            data = pad_row * (min(a, e) - f) + data + pad_row * (e - max(b, f))
        parts.append(data)
    return b"".join(parts)


def pread_rows(fd: int, arr: np.ndarray, j: np.ndarray) -> np.ndarray:
    """arr[j] for the file behind arr, one pread per row, a writable copy."""
    row_bytes = arr.strides[0]
    pread = os.pread
    raw = b"".join([pread(fd, row_bytes, r * row_bytes) for r in j.ravel().tolist()])
    return np.frombuffer(raw, dtype=arr.dtype).reshape(j.shape + arr.shape[1:]).copy()
