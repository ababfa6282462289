"""Reading a cache inside its resident budget: t and the leading rows of the steps mapped, the rest
read with pread; the windows are the mapping's, and the mapped pages stay within the budget."""
from __future__ import annotations

import mmap
import os
from pathlib import Path

import numpy as np
import pytest

from hope_models.data import synthetic as gen
from hope_models.data.cache import load_or_build, open_cache
from hope_models.data.sampler import AnchorSampler
from hope_models.data.windows import WindowLoader, make_windows, window_spec

MB = 1 << 20
PAGE = mmap.PAGESIZE
FIELDS = ("obs", "act", "mask", "target_act", "anchors", "future_obs", "future_act", "future_mask")
SPECS = (window_spec("fast"), window_spec("mid", horizons_s=(0.5, 3.0)),
         window_spec("strategic", 60.0, 10))  # strategic: blocks past 256 rows, read row by row


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    ds = tmp_path_factory.mktemp("ds")
    gen.generate_dataset(ds, 2000, obs_dim=6, act_dim=2, rates_hz=(10, 50), seed=3, episode_seconds=(4, 8))
    _, info = load_or_build(ds, tmp_path_factory.mktemp("cache"))
    return info.path


def _budgets(n: int) -> dict[str, tuple[float, int, int]]:
    """name -> (budget MB, t rows mapped, steps rows mapped) for a cache of n steps of 8 floats."""
    t, row = 8, 32
    # the reader keeps a page for each mapping's last page; half a byte: no float rounding below a row
    mb = lambda nbytes: (nbytes + 2 * PAGE + 0.5) / MB  # noqa: E731
    return {"nothing": (2 * PAGE / MB, 0, 0),
            "part of t": (mb(1000 * t), 1000, 0),
            "t and part of steps": (mb(n * t + 777 * row), n, 777),
            "most of steps": (mb(n * t + (n - 300) * row), n, n - 300)}


def _assert_same(w1, w2, where):
    for name in FIELDS:
        v1, v2 = getattr(w1, name), getattr(w2, name)
        assert (v1 is None and v2 is None) or np.array_equal(v1, v2), (where, name)


@pytest.mark.parametrize("budget", list(_budgets(2000)))
def test_every_split_of_the_budget_reads_the_windows_the_mapping_reads(cache_dir, budget):
    mapped = open_cache(cache_dir)
    mb, t_rows, x_rows = _budgets(mapped.n_steps)[budget]
    split = open_cache(cache_dir, resident_budget_mb=mb)
    assert mapped.mode == "mmap" and split.mode == "read"
    assert (split.t_reader.mapped_rows, split.x_reader.mapped_rows) == (t_rows, x_rows)
    n = mapped.n_steps
    # the edges: the first and last rows (padded blocks) and the rows around the end of the head
    edges = np.unique(np.clip(np.r_[0, 1, 2, n - 2, n - 1, np.arange(x_rows - 8, x_rows + 8),
                                    np.arange(t_rows - 8, t_rows + 8)], 0, n - 1))
    # blocks of t hanging over either end read the pad, as the mapping's do
    for first in (np.r_[-7, -1, 0, n - 9, n - 3, t_rows - 4, x_rows - 4],  # blocks near each other share reads
                  np.r_[-7, n // 2, n - 3]):  # blocks far apart: one read each
        for pad in (-np.inf, np.inf):
            assert np.array_equal(split.t_block(first, 9, pad), mapped.t_block(first, 9, pad))
    for spec in SPECS:
        _assert_same(make_windows(mapped, edges, spec), make_windows(split, edges, spec), (spec.scale, "edges"))
        for k in (1, 4):  # anchors drawn alone and by block (runs of blocks share a read)
            loaders = [WindowLoader(c, AnchorSampler(c, 32, seed=7, split="all", anchors_per_block=k), spec, chunk=4)
                       for c in (mapped, split)]
            for b in range(6):
                _assert_same(next(loaders[0]), next(loaders[1]), (spec.scale, k, b))


def test_a_resumed_loader_in_read_mode_continues_with_the_mappings_batches(cache_dir):
    mapped = open_cache(cache_dir)
    split = open_cache(cache_dir, resident_budget_mb=_budgets(mapped.n_steps)["t and part of steps"][0])
    spec = window_spec("mid", horizons_s=(0.5,))
    whole = WindowLoader(mapped, AnchorSampler(mapped, 16, seed=2, split="all", anchors_per_block=4), spec)
    expected = [next(whole) for _ in range(40)]
    first = AnchorSampler(split, 16, seed=2, split="all", anchors_per_block=4)
    loader = WindowLoader(split, first, spec)
    for _ in range(23):
        next(loader)
    resumed = AnchorSampler(split, 16, seed=2, split="all", anchors_per_block=4)
    resumed.load_state_dict(first.state_dict())
    again = WindowLoader(split, resumed, spec)
    for b in range(23, 40):
        _assert_same(expected[b], next(again), b)


def test_anchors_of_one_block_share_a_read(cache_dir, monkeypatch):
    mapped = open_cache(cache_dir)
    cache = open_cache(cache_dir, resident_budget_mb=_budgets(mapped.n_steps)["nothing"][0])  # t and steps: pread
    sampler = AnchorSampler(cache, 32, seed=4, split="all", anchors_per_block=4)
    assert AnchorSampler(cache, 32, seed=4, split="all").anchor_group == (1, 1)  # opt-in, also past the budget
    spec = window_spec("fast")
    for c in (cache, mapped):  # the block length is computed once, with reads of its own
        make_windows(c, sampler.batch(0), spec)
    reads = []
    real_pread = os.pread
    monkeypatch.setattr(os, "pread", lambda fd, size, off: reads.append(size) or real_pread(fd, size, off))
    for b in range(1, 4):
        anchors = sampler.batch(b)
        blocks = len(np.unique(np.searchsorted(sampler.real.steps, anchors) // sampler.anchor_group[1]))
        reads.clear()
        _assert_same(make_windows(cache, anchors, spec), make_windows(mapped, anchors, spec), b)
        assert blocks <= 8 and len(reads) <= 2 * blocks  # one read of t and one of steps a block, not an anchor


def _mapped_rss(cache_dir: Path) -> int:
    """Bytes of this process's resident pages mapped from the cache's files (/proc/self/smaps)."""
    total, inside = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and len(head) >= 5 and ":" not in head[0]:
            inside = len(head) >= 6 and head[5].startswith(str(cache_dir))
        elif inside and line.startswith("Rss:"):
            total += int(head[1]) * 1024
    return total


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs /proc/self/smaps (Linux)")
def test_read_mode_keeps_its_mapped_pages_inside_the_budget(tmp_path):
    ds = tmp_path / "ds"  # a cache of its own: no other test's mapping of these files is alive
    gen.generate_dataset(ds, 2000, obs_dim=6, act_dim=2, rates_hz=(10, 50), seed=3, episode_seconds=(4, 8))
    cache_dir = load_or_build(ds, tmp_path / "cache")[1].path
    mb = _budgets(2000)["t and part of steps"][0]
    cache = open_cache(cache_dir, resident_budget_mb=mb)
    assert 0 < cache.resident_bytes <= mb * MB < cache.x.nbytes + cache.t.nbytes
    for spec in SPECS:  # every anchor of the cache, through every path of the reader
        sampler = AnchorSampler(cache, 50, seed=1, split="all", shuffle=False)
        for b in range(cache.n_steps // 50):
            make_windows(cache, sampler.batch(b), spec)
    # the other rows never enter this process's pages, each mapping's last page included
    assert _mapped_rss(cache_dir) <= mb * MB
    assert _mapped_rss(cache_dir) >= cache.resident_bytes  # the heads were read through the mappings
