"""The frozen tokenizer's codes of every frame of a dataset cache, computed once and kept beside the
frames, so a loop that reads a frame VQ-VAE trains on codes instead of re-encoding every window.

    table = frame_code_table(cache, vqvae, key)     # [N steps, G] int16/int32, memory-mapped

A window of K points over frames costs K conv encodes per sample, every step; the table costs one
encode per frame, once per (dataset cache, tokenizer weights). It lives in the cache dir as
`codes-<key>.npy`, `key` the tokenizer checkpoint's weights sha256 (its first 16 hex digits): a
new tokenizer gets a new table, a rebuilt cache (new dir) starts without one. Written to a temp
file and renamed, so a crash or a second process computing the same table never leaves half of
one under the name; a table whose shape does not fit the cache is recomputed.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from hope_models.durable import fsync_path

TABLE_PREFIX = "codes-"
ENCODE_BATCH = 256  # frames per encode: ~3 MB of 64x64 input, the conv activations a few times that


def table_path(cache_dir: str | os.PathLike, key: str) -> Path:
    if not key or not all(c in "0123456789abcdef" for c in key):
        raise ValueError(f"code table key {key!r} must be hex digits (the tokenizer weights' sha256)")
    return Path(cache_dir) / f"{TABLE_PREFIX}{key[:16]}.npy"


def _load(path: Path, n: int) -> np.ndarray | None:
    try:
        table = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError):
        return None
    return table if table.ndim == 2 and table.shape[0] == n else None


@torch.no_grad()
def frame_code_table(cache, vqvae: torch.nn.Module, key: str,
                     log: Callable[[str], None] | None = None) -> np.ndarray:
    """[cache.n_steps, G] codes of cache.frames by `vqvae` (eval mode), from the cache dir when
    there, else computed now and stored there."""
    if cache.frames is None:
        raise ValueError(f"{cache.path}: the cache holds no frames to encode")
    path = table_path(cache.path, key)
    n = int(cache.frames.shape[0])
    found = _load(path, n)
    if found is not None:
        return found
    was_training = vqvae.training
    vqvae.eval()
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{os.urandom(4).hex()}")
    try:
        first = vqvae.encode(torch.from_numpy(cache.frame_block(0, 1)))
        groups = int(first.shape[-1])
        n_codes = int(getattr(getattr(vqvae, "cfg", None), "n_codes", 1 << 15))
        dtype = np.int16 if n_codes <= np.iinfo(np.int16).max else np.int32
        out = np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=(n, groups))
        for lo in range(0, n, ENCODE_BATCH):
            hi = min(n, lo + ENCODE_BATCH)
            out[lo:hi] = vqvae.encode(torch.from_numpy(cache.frame_block(lo, hi))).numpy()
        out.flush()
        del out
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        vqvae.train(was_training)
    if log is not None:
        log(f"tokenizer codes of the cache's {n} frames computed once into {path.name}")
    table = _load(path, n)
    assert table is not None  # just written with this shape
    return table
