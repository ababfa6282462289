"""Time-based windows: equal duration across rates, zero-order hold, masks, futures, errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hope_models.data.cache import load_or_build
from hope_models.data.sampler import AnchorSampler
from hope_models.data.windows import WindowLoader, make_windows, window_spec

REPO = Path(__file__).resolve().parents[1]


from hope_models.data import synthetic as gen  # noqa: E402
T0 = 1_767_225_600 * 10**9  # epoch ns, as real producers write


def _episode(ds: Path, name: str, times_ns: list[int]) -> None:
    """obs = [step index, 10 * step index], action = [-step index]: every held value names its step."""
    gen.write_episode(ds, name, [{"timestamp_ns": T0 + t, "observation": {"robot_state": {"joint_positions": [i, 10 * i]}},
                                  "action": {"command": [-i]}} for i, t in enumerate(times_ns)])


@pytest.fixture(scope="module")
def handmade(tmp_path_factory):
    ds = tmp_path_factory.mktemp("handmade")
    _episode(ds, "a_10hz", [i * 100_000_000 for i in range(100)])  # 9.9 s
    _episode(ds, "b_50hz", [i * 20_000_000 for i in range(500)])  # 9.98 s
    cache, _ = load_or_build(ds, tmp_path_factory.mktemp("cache"))
    return cache


def _anchor(cache, episode_id: str, step: int) -> int:
    return int(cache.offsets[cache.episode_ids.index(episode_id)] + step)


def _held(w, b=0) -> list[int]:
    return [int(v) for v in w.obs[b, :, 0]]


def test_10hz_and_50hz_windows_have_equal_duration_and_exact_held_values(handmade):
    fast = window_spec("fast")  # 100 ms, K=5: grid points 80, 60, 40, 20, 0 ms before the anchor
    assert fast.grid_step_s == pytest.approx(0.02)
    a = [_anchor(handmade, "a_10hz", 20), _anchor(handmade, "b_50hz", 100)]  # both at t = 2.0 s
    w = make_windows(handmade, a, fast, normalize=False)
    assert w.obs.shape == (2, 5, 2) and w.act.shape == (2, 5, 1) and w.mask.all()
    # 10 Hz: grid 1.92..2.00 s holds step 19 (1.9 s) until step 20 arrives at 2.0 s
    assert _held(w, 0) == [19, 19, 19, 19, 20]
    # 50 Hz: one step per grid point
    assert _held(w, 1) == [96, 97, 98, 99, 100]
    np.testing.assert_array_equal(w.obs[:, :, 1], 10 * w.obs[:, :, 0])
    np.testing.assert_array_equal(w.act[:, :, 0], -w.obs[:, :, 0])
    assert list(w.target_act[:, 0]) == [-20, -100]

    mid = window_spec("mid")  # 2 s, K=20: a 100 ms grid from 1.1 s to 3.0 s
    w = make_windows(handmade, [_anchor(handmade, "a_10hz", 30), _anchor(handmade, "b_50hz", 150)], mid, normalize=False)
    assert _held(w, 0) == list(range(11, 31))
    assert _held(w, 1) == list(range(55, 151, 5))


def test_grid_points_before_the_episode_start_are_masked_and_zero(handmade):
    fast = window_spec("fast")
    w = make_windows(handmade, [_anchor(handmade, "a_10hz", 0), _anchor(handmade, "a_10hz", 1),
                                _anchor(handmade, "b_50hz", 2)], fast, normalize=False)
    assert w.mask.tolist() == [[False, False, False, False, True], [True] * 5, [False, False, True, True, True]]
    assert _held(w, 0) == [0, 0, 0, 0, 0] and _held(w, 1) == [0, 0, 0, 0, 1] and _held(w, 2) == [0, 0, 0, 1, 2]
    assert (w.act[0, :4] == 0).all()

    normed = make_windows(handmade, [_anchor(handmade, "b_50hz", 3)], window_spec("mid"))
    # anchor at 0.06 s: grid points -1.84, -1.74, ..., -0.04, 0.06 s; only the last is in the episode,
    # and masked values are zero even after normalisation
    grid = 0.06 - window_spec("mid").lags
    assert normed.mask[0].tolist() == list(grid >= -1e-9)
    assert (normed.obs[0][~normed.mask[0]] == 0).all() and (normed.obs[0][normed.mask[0]] != 0).any()


def test_windows_never_look_past_the_anchor_even_with_duplicate_timestamps(tmp_path):
    ds = tmp_path / "ds"
    _episode(ds, "dup", [0, 100_000_000, 100_000_000, 200_000_000])
    cache, _ = load_or_build(ds, tmp_path / "c")
    w = make_windows(cache, [1, 2], window_spec("fast"), normalize=False)
    assert _held(w, 0) == [0, 0, 0, 0, 1]  # step 2 shares step 1's time but comes after it
    assert _held(w, 1) == [0, 0, 0, 0, 2]


def _reference_windows(t: np.ndarray, values: np.ndarray, offsets: np.ndarray, anchors, lags, horizons):
    """Brute force, one grid point at a time: what the vectorised code must reproduce."""
    obs, mask, fut, fmask = [], [], [], []
    for a in anchors:
        e = int(np.searchsorted(offsets, a, side="right") - 1)
        lo, hi = offsets[e], offsets[e + 1]
        row, mrow = [], []
        for lag in lags:
            g = t[a] - lag
            held = [k for k in range(lo, a + 1) if t[k] <= g + 1e-6]
            mrow.append(bool(held))
            row.append(values[held[-1]] if held else 0.0)
        frow, fm = [], []
        for h in horizons:
            g = t[a] + h
            held = [k for k in range(a, hi) if t[k] <= g + 1e-6]
            fm.append(t[hi - 1] >= g - 1e-6)
            frow.append(values[held[-1]] if fm[-1] else 0.0)
        obs.append(row), mask.append(mrow), fut.append(frow), fmask.append(fm)
    return np.array(obs), np.array(mask), np.array(fut), np.array(fmask)


def test_jittered_irregular_timestamps_match_a_brute_force_reference(tmp_path):
    rng = np.random.default_rng(7)
    ds = tmp_path / "ds"
    for e, period_ms in enumerate([100, 50, 20, 500]):
        gaps = rng.uniform(0.3, 1.7, 300) * period_ms * 1e6
        gaps[rng.integers(0, 300, 5)] = 0  # duplicate stamps
        gaps[rng.integers(0, 300, 2)] *= 40  # dropouts
        _episode(ds, f"ep{e}", [0] + np.cumsum(gaps).astype(np.int64).tolist()[:-1])
    cache, _ = load_or_build(ds, tmp_path / "c")
    values = cache.obs[:, 0].astype(np.float64)
    anchors = np.sort(rng.choice(cache.n_steps, 150, replace=False))
    for spec in (window_spec("fast", 0.05), window_spec("fast"), window_spec("mid", 10.0, 37, horizons_s=(0.3, 2.0, 30.0)),
                 window_spec("strategic", 60.0, 13)):
        w = make_windows(cache, anchors, spec, normalize=False)
        ref_obs, ref_mask, ref_fut, ref_fmask = _reference_windows(cache.t, values, cache.offsets, anchors,
                                                                   spec.lags, spec.horizons_s)
        np.testing.assert_array_equal(w.mask, ref_mask, err_msg=spec.scale)
        np.testing.assert_array_equal(w.obs[:, :, 0], ref_obs, err_msg=spec.scale)
        if spec.horizons_s:
            np.testing.assert_array_equal(w.future_mask, ref_fmask)
            np.testing.assert_array_equal(w.future_obs[:, :, 0], ref_fut)


def test_future_targets_hold_the_value_at_anchor_plus_horizon(handmade):
    spec = window_spec("mid", horizons_s=(0.5, 1.0))
    a = [_anchor(handmade, "a_10hz", 10), _anchor(handmade, "a_10hz", 95)]  # t = 1.0 s and 9.5 s of 9.9 s
    w = make_windows(handmade, a, spec, normalize=False)
    assert w.future_obs[0, :, 0].tolist() == [15, 20] and w.future_mask[0].tolist() == [True, True]
    assert w.future_mask[1].tolist() == [False, False] and (w.future_obs[1] == 0).all()
    assert w.future_act[0, :, 0].tolist() == [-15, -20]


@pytest.mark.parametrize("args, message", [
    (("fast", 0.2), "duration_s=0.2 is outside the allowed range for the fast window: 0.05-0.1 s"),
    (("fast", 0.01), "duration_s=0.01 is outside the allowed range for the fast window"),
    (("mid", 0.5), "duration_s=0.5 is outside the allowed range for the mid window: 1-10 s"),
    (("mid", 11.0), "for the mid window"),
    (("strategic", 30.0), "duration_s=30.0 is outside the allowed range for the strategic window: 60-600 s"),
    (("strategic", 601.0), "for the strategic window"),
    (("slow",), "window scale 'slow' is not one of fast, mid, strategic"),
    (("fast", None, 0), "k=0"),
])
def test_out_of_range_windows_raise_naming_the_parameter(args, message):
    with pytest.raises(ValueError) as info:
        window_spec(*args)
    assert message in str(info.value)
    with pytest.raises(ValueError, match="horizons_s"):
        window_spec("mid", horizons_s=(-1.0,))


def test_bad_anchors_are_refused(handmade):
    with pytest.raises(ValueError, match="anchor indices must be within"):
        make_windows(handmade, [handmade.n_steps], window_spec("fast"))
    with pytest.raises(ValueError, match="anchor indices must be within"):
        make_windows(handmade, [-1], window_spec("fast"))
    with pytest.raises(ValueError, match="no frame feature"):
        make_windows(handmade, [0], window_spec("fast"), frames=True)


def test_loader_batches_equal_make_windows_and_resume_exactly(handmade):
    spec = window_spec("fast")
    sampler = AnchorSampler(handmade, 16, seed=3, split="all")
    loader = WindowLoader(handmade, sampler, spec, chunk=4)
    got = [next(loader) for _ in range(10)]
    for b, w in enumerate(got):
        ref = make_windows(handmade, AnchorSampler(handmade, 16, seed=3, split="all").batch(b), spec)
        np.testing.assert_array_equal(w.obs, ref.obs)
        np.testing.assert_array_equal(w.anchors, ref.anchors)
    # a job stopped after 6 batches (mid-chunk) resumes at batch 6, whatever the chunk size
    assert sampler.state_dict()["cursor"] == 10
    first = AnchorSampler(handmade, 16, seed=3, split="all")
    first_loader = WindowLoader(handmade, first, spec, chunk=4)
    for _ in range(6):
        next(first_loader)
    resumed = AnchorSampler(handmade, 16, seed=3, split="all")
    resumed.load_state_dict(first.state_dict())
    resumed_loader = WindowLoader(handmade, resumed, spec, chunk=3)
    for b in range(6, 10):
        np.testing.assert_array_equal(next(resumed_loader).obs, got[b].obs)


def test_frames_are_windowed_with_the_mask(tmp_path):
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 12, obs_dim=2, act_dim=1, rates_hz=(50,), frames=True)
    cache, _ = load_or_build(ds, tmp_path / "c")
    w = make_windows(cache, [0, 4], window_spec("fast"), frames=True)
    assert w.frames.shape == (2, 5, 64, 64, 3) and w.frames.dtype == np.uint8
    assert (w.frames[0, :4] == 0).all() and np.array_equal(w.frames[1, 0], cache.frames[0])
    assert np.array_equal(w.frames[1, 4], cache.frames[4])


def test_future_frames_are_the_frames_held_at_anchor_plus_horizon_masked_like_future_obs(tmp_path):
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 150, obs_dim=2, act_dim=1, rates_hz=(50,), episode_seconds=(2.0, 2.0), frames=True)
    cache, _ = load_or_build(ds, tmp_path / "c")
    assert cache.frames is not None and len(cache.offsets) >= 3  # two episodes: 100 + 50 steps
    spec = window_spec("fast", horizons_s=(0.1, 0.5))
    anchors = [10, 90, 100]  # ep0 at 0.2 s; ep0 at 1.8 s (0.5 s ahead is past its 1.98 s end); ep1's first step
    w = make_windows(cache, anchors, spec, frames=True)
    assert w.future_frames.shape == (3, 2, 64, 64, 3) and w.future_frames.dtype == np.uint8
    assert w.future_mask.tolist() == [[True, True], [True, False], [True, True]]
    for b, rows in enumerate([(15, 35), (95, None), (105, 125)]):  # 50 Hz: 0.1 s = 5 steps, 0.5 s = 25
        for h, row in enumerate(rows):
            if row is None:
                assert (w.future_frames[b, h] == 0).all()
            else:
                np.testing.assert_array_equal(w.future_frames[b, h], cache.frames[row])
    assert not np.array_equal(cache.frames[15], cache.frames[35])  # the frames differ, so the rows are checked
    # the same held rows as future_obs
    np.testing.assert_array_equal(make_windows(cache, anchors, spec, normalize=False).future_obs[0, :, 0],
                                  cache.obs[[15, 35], 0])
    # only when frames are asked for, and the loader's slices carry them
    assert make_windows(cache, anchors, spec).future_frames is None
    loader = WindowLoader(cache, AnchorSampler(cache, 4, seed=0, split="all", horizon_s=0.5), spec, chunk=3,
                          frames=True)
    for _ in range(4):
        got = next(loader)
        ref = make_windows(cache, got.anchors, spec, frames=True)
        np.testing.assert_array_equal(got.future_frames, ref.future_frames)
