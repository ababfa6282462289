"""Image frames stored as .npy blob files (observation.media.rgb = {"uri": ...}) as the frame feature."""
from __future__ import annotations

import io
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from hope_models.data import synthetic as gen
from hope_models.data.cache import CacheError, load_or_build
from hope_models.data.cameras import camera_refs
from hope_models.data.features import FeatureSpecError, FrameFeature
from hope_models.data.spec_request import SpecRequest, spec_from_json_obj
from hope_models.data.windows import make_windows, window_spec

SHAPE = (64, 64, 3)
MEDIA = {"width": 64, "height": 64, "format": "npy_uint8_hwc"}


def _uri(step: int) -> str:
    return f"blobs/step_{step:06d}_rgb.npy"


def _blob_episode(ds: Path, eid: str, n: int = 4, *, seed: int = 0, key: tuple[str, ...] = ("media", "rgb"),
                  dtype=np.uint8, uris: dict[int, str] | None = None) -> list[np.ndarray]:
    """A handmade episode whose step i references blobs/step_<i>_rgb.npy; returns the arrays saved."""
    rng = np.random.default_rng(seed)
    ep_dir = ds / eid
    (ep_dir / "blobs").mkdir(parents=True, exist_ok=True)
    images, steps = [], []
    for i in range(n):
        if dtype == np.uint8:
            img = rng.integers(0, 256, SHAPE, dtype=np.uint8)
        else:
            img = rng.random(SHAPE, dtype=np.float32)
        np.save(ep_dir / _uri(i), img, allow_pickle=False)
        images.append(img)
        ref = dict(MEDIA, uri=(uris or {}).get(i, _uri(i)))
        obs: dict = {"robot_state": {"joint_positions": [0.1 * i, float(seed)]}}
        node = obs
        for k in key[:-1]:
            node = node.setdefault(k, {})
        node[key[-1]] = ref
        steps.append({"timestamp_ns": i * 10**8, "observation": obs, "action": {"command": [0.5, -0.5]}})
    gen.write_episode(ds, eid, steps)
    return images


def _reasons(cache) -> dict[str, str]:
    return {e["episode_id"]: e["reason"] for e in cache.manifest["excluded"]}


def test_generated_blobs_are_the_frame_feature_bit_for_bit_and_windowed(tmp_path):
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 120, obs_dim=4, act_dim=2, rates_hz=(10, 50), seed=2, episode_seconds=(1, 2),
                         frame_blobs=True)
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert cache.spec.frame == FrameFeature("observation.media.rgb", SHAPE, "blob")
    assert cache.spec.to_json_obj()["frame"] == {"path": "observation.media.rgb", "shape": [64, 64, 3],
                                                 "source": "blob"}
    # the reference's width/height are not robot state
    assert [f.path for f in cache.spec.observation.fields] == [
        "observation.robot_state.joint_positions", "observation.robot_state.joint_velocities"]
    assert cache.manifest["excluded"] == [] and cache.n_steps == 120
    assert cache.frames.shape == (120, *SHAPE) and cache.frames.dtype == np.uint8
    expected = []
    for e, eid in enumerate(cache.episode_ids):
        n = int(cache.offsets[e + 1] - cache.offsets[e])
        expected += [np.load(ds / eid / _uri(s), allow_pickle=False) for s in range(n)]
    expected = np.stack(expected)
    assert expected.dtype == np.uint8 and len(np.unique(expected.reshape(120, -1), axis=0)) > 100
    assert np.array_equal(cache.frames, expected)

    anchors = np.array([0, 5, 37, 119])
    w = make_windows(cache, anchors, window_spec("fast"), frames=True)
    assert w.frames.shape == (4, 5, *SHAPE) and w.frames.dtype == np.uint8
    assert np.array_equal(w.frames[:, -1], expected[anchors])  # the anchor's own frame, last in the window
    assert (w.frames[0, :-1] == 0).all() and not w.mask[0, :-1].any()  # before the first step: masked, zero


def test_float32_blobs_convert_like_image_rgb_and_a_changed_blob_rebuilds(tmp_path):
    ds = tmp_path / "ds"
    saved = {f"ep{e}": _blob_episode(ds, f"ep{e}", seed=e, dtype=np.float32) for e in range(3)}
    cache, info = load_or_build(ds, tmp_path / "cache")
    assert cache.spec.frame is not None and cache.spec.frame.source == "blob"
    for e, eid in enumerate(cache.episode_ids):
        lo = cache.offsets[e]
        for i, img in enumerate(saved[eid]):
            assert np.array_equal(cache.frames[lo + i], np.rint(img * 255.0).astype(np.uint8))
    np.save(ds / "ep1" / _uri(2), np.zeros(SHAPE, dtype=np.uint8), allow_pickle=False)
    again, info2 = load_or_build(ds, tmp_path / "cache")
    assert not info2.reused and info2.fingerprint != info.fingerprint
    assert (again.frames[again.offsets[1] + 2] == 0).all() and not (cache.frames[cache.offsets[1] + 2] == 0).all()


def test_one_missing_blob_excludes_its_episode_with_step_field_and_file(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):
        _blob_episode(ds, f"ep{e:02d}", seed=e)
    (ds / "ep03" / _uri(2)).unlink()
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert cache.spec.frame is not None and cache.spec.frame.source == "blob"
    missing = ds.resolve() / "ep03" / _uri(2)
    assert _reasons(cache) == {
        "ep03": f"step 2: observation.media.rgb.uri: '{_uri(2)}' ({missing}): file not found"}
    assert cache.n_episodes == 9 and "ep03" not in cache.episode_ids and cache.frames.shape[0] == 36


def test_a_step_without_the_reference_excludes_the_episode(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):
        _blob_episode(ds, f"ep{e:02d}", seed=e)
    steps_file = ds / "ep05" / "steps" / "000000.jsonl"
    lines = steps_file.read_text().splitlines()
    obj = json.loads(lines[1])
    del obj["observation"]["media"]
    lines[1] = json.dumps(obj)
    steps_file.write_text("\n".join(lines) + "\n")
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert _reasons(cache) == {"ep05": "step 1: observation.media.rgb: no frame at this step"}


def _evil_touch(path: str) -> None:  # what unpickling the object array below would run
    Path(path).write_text("unpickled")


class _Evil:
    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return _evil_touch, (self.marker,)


def _npz_bytes() -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("arr_0.npy", b"\x93NUMPY")
    return buf.getvalue()


def _npy_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


@pytest.mark.parametrize("content, message", [
    (_npy_bytes(np.zeros((4, 64, 64, 3), np.uint8)), "shape [4, 64, 64, 3]"),
    (_npy_bytes(np.zeros(SHAPE, np.int16)), "dtype int16 is not a frame; accepted: uint8 (colour)"),
    (_npy_bytes(np.zeros(SHAPE, np.float64)), "dtype float64 is not a frame; accepted: uint8 (colour)"),
    (_npy_bytes(np.full(SHAPE, 1.5, np.float32)), "image values span [1.5, 1.5], expected [0, 1]"),
    (_npy_bytes(np.full(SHAPE, np.nan, np.float32)), "image values are NaN or infinite"),
    (_npy_bytes(np.zeros(SHAPE, np.uint8))[:-100], "truncated"),
    (b"\x89PNG\r\n\x1a\n not a png file", "PNG"),
    (_npz_bytes(), "not a known media file"),
    (b"\x93NUMPY\x01\x00\x10\x00{'descr': 'garbage", "unreadable .npy header"),
])
def test_malformed_blobs_exclude_the_episode_with_the_reason(tmp_path, content, message):
    ds = tmp_path / "ds"
    for e in range(10):
        _blob_episode(ds, f"ep{e:02d}", seed=e)
    (ds / "ep04" / _uri(3)).write_bytes(content)
    cache, _ = load_or_build(ds, tmp_path / "cache")
    reason = _reasons(cache)["ep04"]
    assert reason.startswith(f"step 3: observation.media.rgb.uri: '{_uri(3)}' ({ds.resolve() / 'ep04' / _uri(3)}): ")
    assert reason.endswith(message) or message in reason, reason
    assert cache.n_episodes == 9 and len(cache.manifest["excluded"]) == 1


def test_object_arrays_that_need_pickle_are_refused_and_never_unpickled(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):
        _blob_episode(ds, f"ep{e:02d}", seed=e)
    marker = tmp_path / "unpickled.txt"
    evil = np.zeros(SHAPE, dtype=object)
    evil[0, 0, 0] = _Evil(marker)
    for step in (0, 2):  # step 0 is also what spec inference looks at
        np.save(ds / "ep06" / _uri(step), evil, allow_pickle=True)
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert _reasons(cache)["ep06"] == (
        f"step 0: observation.media.rgb.uri: '{_uri(0)}' ({ds.resolve() / 'ep06' / _uri(0)}): holds Python "
        "objects (dtype object); loading it would need pickle, which is refused")
    assert cache.n_episodes == 9 and not marker.exists()
    # the file really is a pickle payload: loading it the unsafe way runs the code
    np.load(ds / "ep06" / _uri(0), allow_pickle=True)
    assert marker.read_text() == "unpickled"


@pytest.mark.parametrize("uri, message", [
    ("../ep00/blobs/step_000000_rgb.npy", "escapes the episode dir (..)"),
    ("blobs/../../ep00/blobs/step_000000_rgb.npy", "escapes the episode dir (..)"),
    ("ABSOLUTE", "is an absolute path; only paths inside the episode dir are read"),
    ("file://ABSOLUTE", "has a scheme; only paths relative to the episode dir are read"),
    ("s3://bucket/step_000001_rgb.npy", "has a scheme; only paths relative to the episode dir are read"),
])
def test_uris_that_leave_the_episode_dir_are_refused(tmp_path, uri, message):
    ds = tmp_path / "ds"
    for e in range(10):
        _blob_episode(ds, f"ep{e:02d}", seed=e)
    target = ds / "ep00" / _uri(0)  # a real, valid frame: only the rule keeps it out
    uri = uri.replace("ABSOLUTE", str(target))
    _blob_episode(ds, "sneaky", seed=99, uris={1: uri})
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert _reasons(cache) == {"sneaky": f"step 1: observation.media.rgb.uri: blob uri {uri!r} {message}"}


def test_a_symlink_out_of_the_episode_dir_is_refused(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):
        _blob_episode(ds, f"ep{e:02d}", seed=e)
    outside = tmp_path / "outside.npy"
    np.save(outside, np.zeros(SHAPE, np.uint8), allow_pickle=False)
    link = ds / "ep02" / _uri(1)
    link.unlink()
    os.symlink(outside, link)
    cache, _ = load_or_build(ds, tmp_path / "cache")
    reason = _reasons(cache)["ep02"]
    assert reason.startswith(f"step 1: observation.media.rgb.uri: blob uri '{_uri(1)}' escapes the episode dir")


def test_which_references_count_as_cameras():
    obs = {"media": {"rgb": {"uri": "blobs/a.npy", "width": 64, "height": 64},
                     "depth": {"uri": "blobs/d.npy"}, "audio": {"uri": "blobs/a.npy"}},
           "rgb_front": {"uri": "blobs/f.NPY"},
           "wrist_rgb": {"uri": "blobs/w.npy", "width": 640, "height": 480},
           "robot_state": {"joint_positions": [1.0]},
           "thumb": {"uri": "blobs/t.png"},
           "egocentric_video": {"uri": "blobs/assets/egocentric-1.mp4"},
           "device_mic": {"uri": "blobs/assets/device_mic-1.wav"},
           "notes": {"uri": "blobs/n.json"}}
    assert camera_refs(obs) == {"observation.media.rgb": "blobs/a.npy", "observation.media.depth": "blobs/d.npy",
                                "observation.rgb_front": "blobs/f.NPY", "observation.wrist_rgb": "blobs/w.npy",
                                "observation.thumb": "blobs/t.png",
                                "observation.egocentric_video": "blobs/assets/egocentric-1.mp4"}


def test_inline_image_rgb_wins_and_blobs_of_another_size_are_resized(tmp_path):
    both = tmp_path / "both"
    gen.generate_dataset(both, 40, obs_dim=2, act_dim=1, rates_hz=(10,), episode_seconds=(1, 2),
                         frames=True, frame_blobs=True)
    cache, _ = load_or_build(both, tmp_path / "c1")
    assert cache.spec.frame == FrameFeature("observation.image_rgb", SHAPE, "inline")
    # the blob camera is still stored, as a camera of its own
    assert cache.spec.cameras == [FrameFeature("observation.media.rgb", SHAPE, "blob")]
    # the generator writes the same image twice: as floats (rounded here) and as uint8 (rounded there)
    diff = np.abs(cache.cameras["media.rgb"].astype(int) - cache.frames.astype(int))
    assert cache.cameras["media.rgb"].shape == cache.frames.shape and diff.max() <= 1

    big = tmp_path / "big"
    for e in range(3):
        _blob_episode(big, f"ep{e}", seed=e)
        for i in range(4):
            np.save(big / f"ep{e}" / _uri(i), np.full((128, 128, 3), 40 * i + e, np.uint8), allow_pickle=False)
    cache, _ = load_or_build(big, tmp_path / "c2")
    assert cache.spec.frame == FrameFeature("observation.media.rgb", SHAPE, "blob") and cache.n_episodes == 3
    start = cache.episode_ids.index("ep2")
    assert cache.frames.shape[1:] == SHAPE and (cache.frames[int(cache.offsets[start]) + 3] == 40 * 3 + 2).all()


def test_spec_files_name_a_blob_frame_and_old_specs_stay_inline(tmp_path):
    ds = tmp_path / "ds"
    for e in range(10):  # rgb_front on half the episodes: too few for inference to choose it
        _blob_episode(ds, f"ep{e:02d}", seed=e, key=("rgb_front",) if e < 5 else ("media", "rgb"))
    inferred, _ = load_or_build(ds, tmp_path / "cache")
    assert inferred.spec.frame is None
    assert any(n.startswith("observation.rgb_front: not stored (frames decode in 5 of 10 episodes; needs 9")
               for n in inferred.spec.notes), inferred.spec.notes

    override = tmp_path / "spec.json"
    override.write_text(json.dumps({"frame": {"path": "observation.rgb_front", "source": "blob"}}))
    cache, _ = load_or_build(ds, tmp_path / "cache", spec_path=override)
    assert cache.spec.frame == FrameFeature("observation.rgb_front", SHAPE, "blob")
    assert cache.episode_ids == [f"ep{e:02d}" for e in range(5)]
    assert _reasons(cache)["ep07"] == "step 0: observation.rgb_front: no frame at this step"
    assert np.array_equal(cache.frames[0], np.load(ds / "ep00" / _uri(0), allow_pickle=False))

    # the same path without "source": "blob" means inline floats: the reason says what to change
    inline = tmp_path / "inline.json"
    inline.write_text(json.dumps({"frame": "observation.rgb_front"}))
    with pytest.raises(CacheError, match=r'ep00: step 0: observation.rgb_front: is a blob reference, not numbers '
                                         r'\(a frame file needs "source": "blob"'):
        load_or_build(ds, tmp_path / "cache", spec_path=inline)

    old = spec_from_json_obj(json.loads(cache.spec.to_json()) | {
        "frame": {"path": "observation.image_rgb", "shape": [64, 64, 3]}})  # written before blobs existed
    assert old.frame == FrameFeature("observation.image_rgb", SHAPE, "inline")
    back = spec_from_json_obj(json.loads(cache.spec.to_json()))
    assert back.frame == cache.spec.frame and back.to_json_obj() == cache.spec.to_json_obj()
    bad = tmp_path / "bad.json"
    for frame, msg in (({"path": "observation.rgb_front", "source": "png"}, "source must be one of inline, blob"),
                       ({"path": "observation.rgb_front", "colour": 1}, "unknown keys"),
                       ({"path": "action.rgb", "source": "blob"}, "must start with 'observation.'")):
        bad.write_text(json.dumps({"frame": frame}))
        with pytest.raises(FeatureSpecError, match=msg):
            SpecRequest.load(bad)
