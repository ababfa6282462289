"""The memory-mapped dataset cache: contents, fingerprint reuse/rebuild, crash safety, access modes."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import hope_models.data.cache_build as cache_build
from hope_models.data.cache import CacheError, load_or_build, open_cache
from hope_models.data.sampler import AnchorSampler
from hope_models.data.windows import make_windows, window_spec

REPO = Path(__file__).resolve().parents[1]


from hope_models.data import synthetic as gen  # noqa: E402


@pytest.fixture()
def dataset(tmp_path) -> Path:
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 2000, obs_dim=6, act_dim=2, rates_hz=(10, 50), seed=1, episode_seconds=(4, 8))
    return ds


def test_arrays_hold_exactly_the_episode_values(dataset, tmp_path):
    cache, info = load_or_build(dataset, tmp_path / "cache")
    assert not info.reused and cache.n_steps == 2000
    ep_dirs = sorted(p for p in dataset.iterdir() if p.is_dir())
    assert cache.episode_ids == [p.name for p in ep_dirs]
    for e, ep_dir in enumerate(ep_dirs):
        steps = [json.loads(line) for line in (ep_dir / "steps" / "000000.jsonl").read_text().splitlines()]
        lo, hi = cache.offsets[e], cache.offsets[e + 1]
        assert hi - lo == len(steps)
        rs = [s["observation"]["robot_state"] for s in steps]
        np.testing.assert_array_equal(cache.obs[lo:hi], np.array([r["joint_positions"] + r["joint_velocities"] for r in rs],
                                                                 dtype=np.float32))
        np.testing.assert_array_equal(cache.act[lo:hi], np.array([s["action"]["command"] for s in steps], dtype=np.float32))
        ts = np.array([s["timestamp_ns"] for s in steps], dtype=np.int64)
        np.testing.assert_array_equal(cache.t[lo:hi], (ts - ts[0]) / 1e9)
    rates = sorted({e["rate_hz"] for e in cache.episodes})
    assert rates == [10.0, 50.0]
    assert cache.obs.dtype == np.float32 and cache.t.dtype == np.float64 and not cache.imagined.any()


def test_reused_while_unchanged_rebuilt_when_a_file_changes(dataset, tmp_path):
    root = tmp_path / "cache"
    first, info1 = load_or_build(dataset, root)
    again, info2 = load_or_build(dataset, root)
    assert (info1.reused, info2.reused) == (False, True)
    assert info2.path == info1.path and info2.fingerprint == info1.fingerprint

    victim = sorted(dataset.glob("*/steps/000000.jsonl"))[0]
    lines = victim.read_text().splitlines()
    obj = json.loads(lines[0])
    obj["action"]["command"][0] = 123.5
    lines[0] = json.dumps(obj)
    victim.write_text("\n".join(lines) + "\n")
    changed, info3 = load_or_build(dataset, root)
    assert not info3.reused and info3.fingerprint != info1.fingerprint
    assert changed.act[0, 0] == 123.5 and first.act[0, 0] != 123.5

    gen.write_episode(dataset, "zz_extra", [{"timestamp_ns": i * 10**8, "observation": {"robot_state": {
        "joint_positions": [0.0] * 3, "joint_velocities": [0.0] * 3}}, "action": {"command": [0.0, 0.0]}} for i in range(3)])
    grown, info4 = load_or_build(dataset, root)
    assert not info4.reused and grown.n_steps == 2003 and grown.episode_ids[-1] == "zz_extra"
    assert load_or_build(dataset, root)[1].reused


def test_a_crash_mid_build_leaves_nothing_that_looks_like_a_cache(dataset, tmp_path, monkeypatch):
    root = tmp_path / "cache"
    real = cache_build._episode_rows
    calls = {"n": 0}

    def dies_on_third(ep, spec):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt("power cut")
        return real(ep, spec)

    monkeypatch.setattr(cache_build, "_episode_rows", dies_on_third)
    with pytest.raises(KeyboardInterrupt):
        load_or_build(dataset, root)
    assert list(root.iterdir()) == []  # no final dir, no temp dir left behind
    monkeypatch.setattr(cache_build, "_episode_rows", real)

    # a temp dir left by a process that died without cleaning up is removed on the next build
    stale = root / ".building-abc-999999999-0000"
    stale.mkdir()
    (stale / "steps.bin").write_bytes(b"half")
    cache, info = load_or_build(dataset, root)
    assert not info.reused and cache.n_steps == 2000
    assert [p.name for p in root.iterdir()] == [info.path.name]


def test_a_damaged_cache_is_rebuilt_and_says_so(dataset, tmp_path):
    root = tmp_path / "cache"
    _, info = load_or_build(dataset, root)
    steps_bin = info.path / "steps.bin"
    with open(steps_bin, "r+b") as f:
        f.truncate(steps_bin.stat().st_size - 4)
    with pytest.raises(CacheError, match="steps.bin: .* the cache is damaged"):
        open_cache(info.path)
    cache, again = load_or_build(dataset, root)
    assert not again.reused and again.path == info.path
    assert any("rebuilt a damaged cache" in n for n in again.notes)
    assert cache.n_steps == 2000


def test_read_mode_gives_the_same_windows_as_mmap_mode(dataset, tmp_path):
    _, info = load_or_build(dataset, tmp_path / "cache")
    mapped = open_cache(info.path)  # 2000 steps: far under the default budget
    streamed = open_cache(info.path, resident_budget_mb=0.01)
    assert (mapped.mode, streamed.mode) == ("mmap", "read")
    for spec in (window_spec("fast"), window_spec("mid", horizons_s=(0.5, 3.0)), window_spec("strategic", 60.0, 10)):
        sampler = AnchorSampler(mapped, 32, seed=5, split="all")
        for b in range(5):
            a = sampler.batch(b)
            w1, w2 = make_windows(mapped, a, spec), make_windows(streamed, a, spec)
            for name in ("obs", "act", "mask", "target_act", "future_obs", "future_act", "future_mask"):
                v1, v2 = getattr(w1, name), getattr(w2, name)
                assert (v1 is None and v2 is None) or np.array_equal(v1, v2), (spec.scale, name)


def test_cache_inside_the_dataset_dir_does_not_change_the_fingerprint(dataset):
    root = dataset / ".cache"
    _, info1 = load_or_build(dataset, root)
    _, info2 = load_or_build(dataset, root)
    assert info2.reused and info1.fingerprint == info2.fingerprint


def test_no_pickle_in_the_data_modules():
    for name in ("features", "frames", "cache", "windows", "sampler", "source", "summary", "synthetic"):
        text = (REPO / "hope_models" / "data" / f"{name}.py").read_text()
        assert "import pickle" not in text and "allow_pickle=True" not in text, name
        for line in text.splitlines():
            if "np.load(" in line:
                assert "allow_pickle=False" in line, (name, line)
