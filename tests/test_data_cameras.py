"""Cameras in a dataset: JPEG, PNG, .npy (any size, depth too) and video frames become cache
arrays, resized with the area filter to the spec's frame size, equal to a reference decode."""
from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hope_models.data.cache import load_or_build
from hope_models.data.features import FeatureSpecError, FrameFeature
from hope_models.data.spec_request import SpecRequest
from hope_models.data.summary import format_summary, summarise_dataset

PERIOD_NS = 100_000_000  # 10 Hz


def _reference(img: np.ndarray, size: int) -> np.ndarray:
    """What the cache must hold: Pillow's box (area) filter straight from the full-size pixels."""
    return np.asarray(Image.fromarray(img).resize((size, size), Image.Resampling.BOX))


def _episode(root: Path, episode_id: str, n: int, cameras) -> Path:
    """An episode dir as the Continuon producers leave it: episode.json, frame files beside it.
    `cameras(i)` gives step i's extra observation entries."""
    ep = root / episode_id
    ep.mkdir(parents=True)
    steps = []
    for i in range(n):
        observation = {"robot_state": {"joint_positions": [0.1 * i, -0.05 * i, 0.3]}}
        observation.update(cameras(i))
        steps.append({"observation": observation, "action": {"command": [0.2 * (i % 3), -0.1]},
                      "timestamp_ns": 1_000_000_000 + i * PERIOD_NS, "is_terminal": i == n - 1})
    (ep / "episode.json").write_text(json.dumps({"metadata": {"episode_id": episode_id}, "steps": steps}))
    return ep


def _image(seed: int, h: int = 480, w: int = 640) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # blocks, not noise: JPEG keeps them, so a mix-up of frames shows, not just codec error
    small = rng.integers(0, 255, (h // 40, w // 40, 3), dtype=np.uint8)
    return np.kron(small, np.ones((40, 40, 1), np.uint8))


def test_jpeg_png_and_npy_frames_of_any_size_are_resized_into_the_cache(tmp_path):
    ds = tmp_path / "ds"
    truth: dict[tuple[str, int], np.ndarray] = {}
    for e in range(3):
        def cams(i, e=e):
            img = _image(100 * e + i)
            # the app's JPEG still in a .mp4-named file, a PNG wrist camera and the Pi's depth .npy
            ep_dir = ds / f"ep{e}"
            ep_dir.mkdir(parents=True, exist_ok=True)
            Image.fromarray(img).save(ep_dir / f"ego-{i}.mp4", "JPEG", quality=95)
            Image.fromarray(img[:240, :320]).save(ep_dir / f"wrist-{i}.png")
            np.save(ep_dir / f"step_{i:04d}_depth.npy", np.full((400, 640), 500 + 10 * i, np.uint16))
            truth[(f"ep{e}", i)] = img
            return {"egocentric_video": {"uri": f"ego-{i}.mp4"}, "wrist_rgb": {"uri": f"wrist-{i}.png"},
                    "depth": {"uri": f"step_{i:04d}_depth.npy"}}
        _episode(ds, f"ep{e}", 12, cams)
    cache, _ = load_or_build(ds, tmp_path / "cache")
    spec = cache.spec
    assert spec.frame == FrameFeature("observation.egocentric_video", (64, 64, 3), "blob")
    assert spec.cameras == [FrameFeature("observation.wrist_rgb", (64, 64, 3), "blob"),
                            FrameFeature("observation.depth", (64, 64, 1), "blob", "depth")]
    assert cache.n_episodes == 3 and cache.n_steps == 36
    for j, ep_id in enumerate(cache.episode_ids):
        for i in range(12):
            row = int(cache.offsets[j]) + i
            img = truth[(ep_id, i)]
            # the reference decode: Pillow's JPEG draft mode at the smallest DCT scale still >= 64x64
            with Image.open(ds / ep_id / f"ego-{i}.mp4") as jpeg:
                jpeg.draft("RGB", (64, 64))
                decoded = np.asarray(jpeg.convert("RGB"))
            assert decoded.shape == (120, 160, 3)  # 1/4 scale: 1/8 would be under 64 rows
            assert np.array_equal(cache.frames[row], _reference(decoded, 64))
            assert np.array_equal(cache.cameras["wrist_rgb"][row], _reference(img[:240, :320], 64))
            assert cache.cameras["depth"].dtype == np.float32
            assert np.allclose(cache.cameras["depth"][row], (500 + 10 * i) / 1000.0)
    text = format_summary(summarise_dataset(ds, tmp_path / "cache"))
    assert "camera       egocentric_video: 36/36 frames, JPEG 480x640 -> 64x64 (the tokenizer reads it)" in text
    assert "camera       depth: 36/36 frames, NPY 400x640 -> 64x64 (depth in metres, stored" in text
    assert "camera       wrist_rgb: 36/36 frames, PNG 240x320 -> 64x64 (stored" in text


def test_frame_size_96_and_a_bad_size_is_refused(tmp_path):
    ds = tmp_path / "ds"
    for e in range(2):
        def cams(i, e=e):
            np.save(ds / f"ep{e}" / f"f{i}.npy", _image(e * 50 + i, 192, 192))
            return {"rgb": {"uri": f"f{i}.npy"}}
        _episode(ds, f"ep{e}", 8, cams)
    override = tmp_path / "spec.json"
    override.write_text(json.dumps({"frame_size": 96}))
    cache, _ = load_or_build(ds, tmp_path / "cache", spec_path=override)
    assert cache.spec.frame == FrameFeature("observation.rgb", (96, 96, 3), "blob")
    row = int(cache.offsets[cache.episode_ids.index("ep1")]) + 5
    assert np.array_equal(cache.frames[row], _reference(_image(55, 192, 192), 96))
    override.write_text(json.dumps({"frame_size": 80}))
    with pytest.raises(FeatureSpecError, match="frame_size must be one of 64, 96, 128, got 80"):
        SpecRequest.load(override)


def _write_video(path: Path, colours: list[tuple[int, int, int]], fps: int = 10) -> None:
    import av  # a test helper: PyAV writes the clip the producer would have recorded

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = 320, 240, "yuv420p"
        stream.time_base = Fraction(1, fps)
        stream.options = {"qp": "0"}
        for k, colour in enumerate(colours):
            frame = av.VideoFrame.from_ndarray(np.full((240, 320, 3), colour, np.uint8), format="rgb24")
            frame.pts = k
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)


def test_a_video_gives_each_step_the_frame_at_its_time(tmp_path):
    ds = tmp_path / "ds"
    colours = [(20 * k, 255 - 20 * k, (37 * k) % 256) for k in range(12)]
    for e in range(2):
        (ds / f"ep{e}").mkdir(parents=True)
        _write_video(ds / f"ep{e}" / "session.mp4", colours)  # 10 fps, 1.2 s
        steps = []
        for i in range(6):  # steps at 5 Hz: every other video frame
            steps.append({"observation": {"robot_state": {"joint_positions": [0.1 * i, 0.2]},
                                          "egocentric_video": {"uri": "session.mp4"}},
                          "action": {"command": [0.1 * i]}, "timestamp_ns": 5_000_000_000 + i * 2 * PERIOD_NS})
        (ds / f"ep{e}" / "episode.json").write_text(json.dumps({"metadata": {"episode_id": f"ep{e}"},
                                                               "steps": steps}))
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert cache.spec.frame == FrameFeature("observation.egocentric_video", (64, 64, 3), "blob")
    for i in range(6):
        got = cache.frames[int(cache.offsets[1]) + i].reshape(-1, 3).mean(axis=0)
        assert np.abs(got - np.array(colours[2 * i])).max() <= 3, (i, got, colours[2 * i])


def test_a_camera_that_fails_mid_episode_leaves_no_frames_behind(tmp_path):
    ds = tmp_path / "ds"
    for e in range(3):
        def cams(i, e=e):
            ep_dir = ds / f"ep{e}"
            ep_dir.mkdir(parents=True, exist_ok=True)
            data = _image(e * 10 + i, 48, 64)
            np.save(ep_dir / f"f{i}.npy", data)
            return {"rgb": {"uri": f"f{i}.npy"}}
        _episode(ds, f"ep{e}", 200, cams)
    (ds / "ep1" / "f150.npy").write_bytes(b"\x93NUMPY broken")  # past the first chunk of frames
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert cache.episode_ids == ["ep0", "ep2"] and cache.frames.shape[0] == 400
    assert "step 150: observation.rgb.uri" in cache.manifest["excluded"][0]["reason"]
    assert np.array_equal(cache.frames[200 + 7], _reference(_image(27, 48, 64), 64))


def test_a_camera_dataset_without_actions_trains_only_the_tokenizer(tmp_path):
    from hope_models.components.resolve import resolve

    ds = tmp_path / "ds"
    for e in range(2):
        def cams(i, e=e):
            (ds / f"ep{e}").mkdir(parents=True, exist_ok=True)
            Image.fromarray(_image(e * 9 + i, 96, 128)).save(ds / f"ep{e}" / f"ego-{i}.jpg", quality=90)
            return {"egocentric_video": {"uri": f"ego-{i}.jpg"}}
        ep = _episode(ds, f"ep{e}", 6, cams)
        doc = json.loads((ep / "episode.json").read_text())
        for step in doc["steps"]:  # the app's record screen: an empty command
            step["action"] = {"command": [], "source": "human_teleop_xr"}
        (ep / "episode.json").write_text(json.dumps(doc))
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert cache.spec.act_dim == 0 and cache.spec.frame is not None and cache.n_steps == 12
    assert any(n.startswith("action: none (") and "only the tokenizer trains" in n for n in cache.spec.notes)
    assert resolve("vqvae", cache.spec, None).cfg.input == "frame"
    with pytest.raises(ValueError, match="fast_loop learns from actions, and this dataset has none"):
        resolve("fast_loop", cache.spec, None)

    for e in range(2):  # the same episodes with their pictures gone: nothing to train, and it says why
        for f in (ds / f"ep{e}").glob("ego-*.jpg"):
            f.write_bytes(b"")
    with pytest.raises(FeatureSpecError, match=r"no numeric action field.*no camera for the tokenizer: "
                                         r"observation.egocentric_video: not stored \(frames decode in 0 of 2"):
        load_or_build(ds, tmp_path / "cache2")


def test_the_studio_recorders_absolute_frame_paths_are_read_inside_its_dir(tmp_path):
    """continuonbrain/recording/camera_episode_recorder.py writes <out>/<id>.json whose
    observation.media.rgb.uri is str(out_dir / f"{episode_id}_blobs" / f"{frame_id}.jpg"): an
    absolute path when out_dir is. Inside the episode's own dir, it is read; elsewhere, refused."""
    out = tmp_path / "studio"
    for e in range(2):
        episode_id = f"studio_{e}"
        blobs = out / f"{episode_id}_blobs"
        blobs.mkdir(parents=True)
        steps = []
        for i in range(8):
            frame_id = f"{episode_id}_{i:06d}"
            Image.fromarray(_image(e * 20 + i, 240, 320)).save(blobs / f"{frame_id}.jpg", quality=90)
            steps.append({"observation": {"robot_state": {"joint_positions": [0.1 * i, 0.0]},
                                          "media": {"rgb": {"uri": str(blobs / f"{frame_id}.jpg"), "frame_id": frame_id,
                                                            "width": 320, "height": 240, "format": "jpeg"}}},
                          "action": {"command": [0.0, 0.1 * i]}, "timestamp_ns": 1_000 + i * PERIOD_NS,
                          "is_terminal": i == 7})
        (out / f"{episode_id}.json").write_text(json.dumps({"metadata": {"episode_id": episode_id},
                                                            "steps": steps}))
    cache, _ = load_or_build(out, tmp_path / "cache")
    assert cache.spec.frame == FrameFeature("observation.media.rgb", (64, 64, 3), "blob") and cache.n_steps == 16
    with Image.open(out / "studio_1_blobs" / "studio_1_000003.jpg") as jpeg:
        jpeg.draft("RGB", (64, 64))
        want = _reference(np.asarray(jpeg.convert("RGB")), 64)
    assert np.array_equal(cache.frames[int(cache.offsets[cache.episode_ids.index("studio_1")]) + 3], want)

    elsewhere = tmp_path / "elsewhere.jpg"  # an absolute path out of the episode's dir stays refused
    Image.fromarray(_image(1, 48, 64)).save(elsewhere)
    doc = json.loads((out / "studio_0.json").read_text())
    doc["steps"][2]["observation"]["media"]["rgb"]["uri"] = str(elsewhere)
    (out / "studio_0.json").write_text(json.dumps(doc))
    cache, _ = load_or_build(out, tmp_path / "cache")
    (excluded,) = cache.manifest["excluded"]
    assert excluded["episode_id"] == "studio_0" and "is an absolute path; only paths inside the episode dir" in \
        excluded["reason"]
