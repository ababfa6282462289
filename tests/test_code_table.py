"""The frozen tokenizer's code table (components/code_table.py): computed once per dataset cache and
tokenizer, the Fast and Mid Loop learn from it exactly what they would from the frames."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hope_models.components.build import build_component
from hope_models.components.code_table import table_path
from hope_models.data import synthetic as gen
from hope_models.data.cache import load_or_build
from hope_models.data.sampler import AnchorSampler
from hope_models.data.windows import make_windows

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A frame dataset and a frame VQ-VAE trained on it for a few steps (the CLI, as a user would)."""
    root = tmp_path_factory.mktemp("codes")
    gen.generate_dataset(root / "ds", 160, obs_dim=4, act_dim=2, rates_hz=(10,), episode_seconds=(4, 6), seed=3,
                         frame_blobs=True)
    cache_dir = root / "cache"
    proc = subprocess.run([sys.executable, "run_trainer.py", "train", "--component", "vqvae", "--data",
                           str(root / "ds"), "--cache-dir", str(cache_dir), "--run-dir", str(root / "vq"),
                           "--steps", "6", "--batch-size", "16"], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ckpt = max(p for p in (root / "vq" / "checkpoints").iterdir() if p.is_dir())  # checkpoints/<step>/
    cache, _ = load_or_build(root / "ds", cache_dir)
    return cache, ckpt


@pytest.mark.parametrize("name", ["fast_loop", "mid_loop"])
def test_the_loops_learn_the_same_from_the_table_as_from_the_frames(trained, name):
    cache, ckpt = trained
    comp = build_component(name, cache.spec, vqvae_dir=ckpt, data_fingerprint=cache.fingerprint)
    assert comp.wants_frames
    table = comp.code_table(cache)
    assert table.shape == (cache.n_steps, comp.model.vqvae.cfg.groups) and table.dtype == np.int16
    anchors = AnchorSampler(cache, 24, seed=1, split="all").batch(0)
    from_frames = make_windows(cache, anchors, comp.window, frames=True)
    from_codes = make_windows(cache, anchors, comp.window, frames=True, codes=table)
    assert from_codes.frames is None and from_codes.codes.shape == (24, comp.window.k, table.shape[1])
    assert from_frames.codes is None
    assert comp.evaluate(from_codes) == comp.evaluate(from_frames)  # the same numbers, not close ones


def test_the_table_is_computed_once_and_redone_when_it_does_not_fit(trained):
    cache, ckpt = trained
    comp = build_component("fast_loop", cache.spec, vqvae_dir=ckpt, data_fingerprint=cache.fingerprint)
    path = table_path(cache.path, comp.vqvae_ref["weights_sha256"])
    first = np.array(comp.code_table(cache))  # a copy: the overwrite below changes the mapped file
    stamp = path.stat().st_mtime_ns
    again = comp.code_table(cache)
    assert path.stat().st_mtime_ns == stamp and np.array_equal(first, again)
    path.unlink()
    np.save(path, np.zeros((3, first.shape[1]), np.int16))  # a table of another cache's size
    redone = comp.code_table(cache)
    assert np.array_equal(redone, first)
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".codes-")]  # no temp left behind
    assert build_component("vqvae", cache.spec).code_table(cache) is None  # the tokenizer reads frames itself


class _Untouchable:
    """A frames array that may be described but not indexed: the table must come from pread."""

    def __init__(self, arr):
        self.shape, self.strides, self.dtype, self.nbytes = arr.shape, arr.strides, arr.dtype, arr.nbytes

    def __getitem__(self, key):
        raise AssertionError(f"the frames mapping was indexed ({key!r}): its pages would stay resident")


def test_a_large_cache_builds_its_table_without_mapping_the_frames(trained):
    """Past the resident budget the frames are read with pread: a pass over every frame must not
    fault the whole frames file into the job's RSS (50 000 64x64 frames are 614 MB)."""
    from hope_models.data.dataset_cache import open_cache

    cache, ckpt = trained
    comp = build_component("fast_loop", cache.spec, vqvae_dir=ckpt, data_fingerprint=cache.fingerprint)
    expected = np.array(comp.code_table(cache))
    small = open_cache(cache.path, resident_budget_mb=0.001)
    assert small.frames_mode == "read"
    for lo, hi in ((0, 1), (5, 37), (small.n_steps - 3, small.n_steps)):
        assert np.array_equal(small.frame_block(lo, hi), cache.frames[lo:hi])
    table_path(small.path, comp.vqvae_ref["weights_sha256"]).unlink()
    small.frames = _Untouchable(small.frames)
    assert np.array_equal(comp.code_table(small), expected)
