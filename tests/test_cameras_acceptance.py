"""Every camera a Continuon producer writes reaches the trainer: acceptance, end to end.

Each producer's real output (tests/upstream_producers.py: the app's record-screen handoff, the Pi
runtime's upload package, the XR app's zip, an episode over one H.264 video) goes through the real
webapp (create_app on a fresh $HOPE_HOME, Flask's test client) and then the real command line:

- it is stored once: the same upload again is "unchanged" and writes nothing;
- the stored frame files are what was sent, and hope_models.media decodes them to the pixels a
  reference decode made here straight with Pillow / NumPy / PyAV gives (exactly at the native size,
  within JPEG's draft-mode slack at 64x64, and each step nearest its own picture);
- the verdict (the upload or handoff answer, and GET /api/episodes) and `run_trainer.py dataset`
  say one line per camera, e.g. "egocentric_video: 3/3 frames, JPEG 480x640 -> 64x64";
- the cache's frame rows are those pictures, and `train --component vqvae` trains a frame VQ-VAE
  (its checkpoint's config says input "frame").

Bad media a producer gone wrong could send (a truncated JPEG, a PNG declaring 10^10 pixels, an
MP4 without a video stream, a float64 .npy) is a 4xx naming the file or a stored episode with a
warning naming it, never a 500, and `dataset` says the camera is unusable and why.
"""
from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import upstream_producers as up
from PIL import Image
from test_app_handoff import make_client

REPO = Path(__file__).resolve().parents[1]
OUT_HW = (64, 64)  # the cache's default frame size
UPLOAD_MAX_MB = 256


# -- the server and the command line ------------------------------------------------------------------

@pytest.fixture
def client(tmp_path):
    c = make_client(tmp_path / "home", UPLOAD_MAX_MB)
    yield c
    c.close()


def _auth(client) -> dict[str, str]:
    return {"authorization": f"Bearer {client.token}"}


def handoff(client, session: up.AppSession):
    body, ctype = session.body()
    return client.post("/api/training/episode_handoff", data=body, content_type=ctype, headers=_auth(client))


def upload(client, body: bytes, *, content_type: str, headers: dict[str, str] | None = None):
    # HttpRldsUploader / a browser drop / curl: the package as the raw body
    return client.post("/api/episodes/upload", data=body, content_type=content_type,
                       headers={**_auth(client), **(headers or {})})


def only_episode(answer: dict) -> dict:
    (pkg,) = answer["packages"]
    (ep,) = pkg["episodes"]
    return ep


def listed(client, episode_id: str) -> dict:
    r = client.get("/api/episodes", headers=_auth(client))
    assert r.status_code == 200, r.get_json()
    return next(e for e in r.get_json()["episodes"] if e["episode_id"] == episode_id)


def inbox_tree(client) -> dict[str, int]:
    inbox = client.settings.inbox_dir
    return {str(p.relative_to(inbox)): p.stat().st_mtime_ns for p in sorted(inbox.rglob("*"))}


def cli(client, *args: str, timeout: int = 900) -> subprocess.CompletedProcess:
    env = {**os.environ, "HOPE_HOME": str(client.settings.home), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}
    return subprocess.run([sys.executable, str(REPO / "run_trainer.py"), *args], capture_output=True, text=True,
                          cwd=REPO, env=env, timeout=timeout)


def dataset(client, cache: Path) -> str:
    done = cli(client, "dataset", str(client.settings.inbox_dir), "--cache-dir", str(cache))
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    assert done.returncode == 0, done.stdout + done.stderr
    return done.stdout


def train_vqvae(client, cache: Path, run_dir: Path) -> dict:
    """`train --component vqvae` on the inbox; the last checkpoint's config.json."""
    done = cli(client, "train", "--component", "vqvae", "--data", str(client.settings.inbox_dir), "--run-dir",
               str(run_dir), "--steps", "20", "--seed", "0", "--batch-size", "8", "--threads", "1",
               "--checkpoint-every", "20", "--cache-dir", str(cache), "--json")
    assert done.returncode == 0, done.stdout + done.stderr
    out = json.loads(done.stdout)
    assert out["outcome"] == "completed" and out["steps"] == 20, out
    return json.loads((Path(out["checkpoint"]) / "config.json").read_text())


def camera_line(camera: str, n: int, fmt: str, native_hw: tuple[int, int]) -> str:
    return f"{camera}: {n}/{n} frames, {fmt} {native_hw[0]}x{native_hw[1]} -> {OUT_HW[0]}x{OUT_HW[1]}"


def strings(obj) -> list[str]:
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in strings(v)]
    if isinstance(obj, list):
        return [s for v in obj for s in strings(v)]
    return []


def says(verdict: dict, line: str) -> bool:
    """Some text of the verdict holds `line` (a camera line may be a list item or a line of a text)."""
    return any(line in s for s in strings(verdict))


# -- the stored episode and its frames ------------------------------------------------------------------

def stored_steps(client, episode_id: str) -> tuple[Path, list]:
    from hope_models.rlds.discover import read_path

    ep_dir = client.settings.inbox_dir / episode_id
    reports = read_path(ep_dir)
    episodes = [ep for r in reports for ep in r.episodes]
    assert len(episodes) == 1, reports
    return ep_dir, episodes[0].steps


def camera_file(ep_dir: Path, step, camera: str) -> Path:
    """The stored file a step's `observation.<camera>` names: inside the stored episode, present."""
    ref = step.observation.get(camera)
    assert isinstance(ref, dict) and isinstance(ref.get("uri"), str), (camera, sorted(step.observation))
    path = (ep_dir / ref["uri"]).resolve()
    assert path.is_relative_to(ep_dir.resolve()), ref
    assert path.is_file(), ref
    return path


def ref_rgb(data: bytes | np.ndarray, hw: tuple[int, int] | None = None) -> np.ndarray:
    """Reference colour decode: Pillow, full size, RGB; then the area (box) resize to hw."""
    img = Image.fromarray(data) if isinstance(data, np.ndarray) else Image.open(io.BytesIO(data)).convert("RGB")
    if hw is not None and img.size != (hw[1], hw[0]):
        img = img.resize((hw[1], hw[0]), Image.Resampling.BOX)
    return np.asarray(img, dtype=np.uint8)


def ref_depth_m(mm: np.ndarray, hw: tuple[int, int] | None = None) -> np.ndarray:
    """Reference depth: millimetres -> metres [h, w, 1]; resized as the mean of the valid (non-zero)
    readings under each output pixel's box (edges weighted by the fraction covered), 0 where none is."""
    metres = mm.astype(np.float64) / 1000.0
    if hw is None or metres.shape == hw:
        return metres.astype(np.float32)[..., None]
    valid = (mm > 0).astype(np.float64)
    wy, wx = _box_weights(metres.shape[0], hw[0]), _box_weights(metres.shape[1], hw[1])
    total, share = wy @ (metres * valid) @ wx.T, wy @ valid @ wx.T
    out = np.divide(total, share, out=np.zeros_like(total), where=share > 1e-9)
    return out.astype(np.float32)[..., None]


def _box_weights(n_in: int, n_out: int) -> np.ndarray:
    """[n_out, n_in]: how much of input pixel j output pixel i's box covers."""
    edges = np.arange(n_out + 1) * n_in / n_out
    idx = np.arange(n_in)
    lo, hi = edges[:-1, None], edges[1:, None]
    return np.clip(np.minimum(idx + 1, hi) - np.maximum(idx, lo), 0, None)


def media_still(path: Path, hw: tuple[int, int], kind: str) -> np.ndarray:
    from hope_models.media import decode_still

    return np.asarray(decode_still(path, hw, kind))


def assert_nearest_own(got: dict[int, np.ndarray], want: dict[int, np.ndarray], *, tol: float, what: str) -> None:
    """Each decoded frame is within `tol` (mean absolute difference) of its own step's reference and
    nearer to it than to any other step's: no frame lands on the wrong step."""
    for i, g in got.items():
        assert g.shape == want[i].shape and g.dtype == want[i].dtype, (what, i, g.shape, g.dtype, want[i].shape)
        errs = {j: float(np.abs(g.astype(np.float64) - w.astype(np.float64)).mean()) for j, w in want.items()}
        assert errs[i] <= tol, f"{what}: step {i} differs from its reference by {errs[i]:.3f} (> {tol})"
        nearest = min(errs, key=errs.__getitem__)
        assert nearest == i, f"{what}: step {i}'s frame is nearest step {nearest}'s picture ({errs})"


def assert_cache_frames(client, cache_root: Path, episode_id: str, camera: str, want: dict[int, np.ndarray],
                        tol: float) -> None:
    """The built cache's primary frame is `camera`, and its rows for the episode are the pictures."""
    from hope_models.data.cache import load_or_build

    cache, info = load_or_build(client.settings.inbox_dir, cache_root)
    assert info.reused, "dataset built the cache; loading it again must reuse it"
    assert cache.spec.frame is not None and cache.spec.frame.path == f"observation.{camera}", cache.spec.frame
    assert cache.frames is not None and tuple(cache.frames.shape[1:]) == (*OUT_HW, 3)
    e = cache.episode_ids.index(episode_id)
    start = int(cache.offsets[e])
    got = {i: np.asarray(cache.frame_rows(np.array([start + i]))[0]) for i in want}
    assert_nearest_own(got, want, tol=tol, what=f"cache {camera}")


# -- the app: record screen handoff -------------------------------------------------------------------------

JPEG_TOL_64 = 4.0  # draft-mode JPEG decode at reduced scale vs a full decode, then the same box resize


def test_app_record_screen_handoff_reaches_the_trainer(client, tmp_path):
    session = up.app_session(3)
    r = handoff(client, session)
    assert r.status_code == 200, r.get_json()
    answer = r.get_json()
    eid = answer["episode_id"]
    assert answer["action"] == "written", answer
    before = inbox_tree(client)
    again = handoff(client, session)
    assert again.status_code == 200 and again.get_json()["episode_id"] == eid
    assert again.get_json()["action"] == "unchanged" and inbox_tree(client) == before

    ep_dir, steps = stored_steps(client, eid)
    assert len(steps) == 3
    native, small = {}, {}
    for i, step in enumerate(steps):
        path = camera_file(ep_dir, step, "egocentric_video")
        assert path.read_bytes() == session.frames[i]  # the JPEG still in its .mp4-named file
        native[i] = media_still(path, (480, 640), "rgb")
        assert np.array_equal(native[i], ref_rgb(session.frames[i])), f"step {i}: native decode differs"
        small[i] = media_still(path, OUT_HW, "rgb")
    assert_nearest_own(small, {i: ref_rgb(session.frames[i], OUT_HW) for i in small}, tol=JPEG_TOL_64,
                       what="egocentric_video 64x64")

    line = camera_line("egocentric_video", 3, "JPEG", (480, 640))
    assert says(answer, line), answer
    assert says(listed(client, eid), line)
    assert "vqvae" in answer["trainable"], answer
    # the WAVs are sound, not cameras
    assert not any(re.search(r"(device|robot)_mic: \d+/\d+ frames", s) for s in strings(answer)), answer

    cache = tmp_path / "cache"
    assert line in dataset(client, cache)
    assert_cache_frames(client, cache, eid, "egocentric_video", {i: ref_rgb(session.frames[i], OUT_HW) for i in range(3)},
                        tol=JPEG_TOL_64)
    assert train_vqvae(client, cache, tmp_path / "run")["model_config"]["input"] == "frame"


def test_app_handoff_of_2000_taps_with_depth_reaches_the_trainer(client, tmp_path):
    """The size a long session really is: 2,000 taps, four files each (two WAVs, the still, the
    depth), 8,000 file parts in one body; small pictures keep it quick."""
    n, hw = 2000, (96, 128)
    session = up.app_session(n, depth=True, hw=hw)
    assert len(session.files) == 4 * n
    r = handoff(client, session)
    assert r.status_code == 200, r.get_json()
    answer = r.get_json()
    eid = answer["episode_id"]
    assert answer["action"] == "written", answer
    assert set(answer["remote_uris"]) == {a["local_uri"] for a in session.assets}  # keyed as the app sent them
    before = inbox_tree(client)
    again = handoff(client, session)
    assert again.status_code == 200 and again.get_json()["action"] == "unchanged", again.get_json()
    assert inbox_tree(client) == before

    ep_dir, steps = stored_steps(client, eid)
    assert len(steps) == n
    for step in steps:  # every step's four media, however the app spelled them, on a stored file
        uris = [step.observation["audio"]["device_mic"]["uri"], step.observation["audio"]["robot_mic"]["uri"],
                step.observation["egocentric_video"]["uri"], step.observation["egocentric_depth"]["uri"]]
        assert all(u.startswith("blobs/assets/") and (ep_dir / u).is_file() for u in uris), uris
    assert len(list((ep_dir / "blobs" / "assets").iterdir())) == 4 * n
    sample = [0, 1, 2, 997, 998, n - 2, n - 1]
    video, depth = {}, {}
    for i in sample:
        vpath = camera_file(ep_dir, steps[i], "egocentric_video")
        dpath = camera_file(ep_dir, steps[i], "egocentric_depth")
        assert vpath.read_bytes() == session.frames[i] and dpath.read_bytes() == session.depth[i]
        assert np.array_equal(media_still(vpath, hw, "rgb"), ref_rgb(session.frames[i]))
        got_depth = media_still(dpath, hw, "depth")
        assert got_depth.dtype == np.float32 and np.allclose(got_depth, ref_depth_m(session.depths[i]), atol=1e-6)
        video[i] = media_still(vpath, OUT_HW, "rgb")
        depth[i] = media_still(dpath, OUT_HW, "depth")
    assert_nearest_own(video, {i: ref_rgb(session.frames[i], OUT_HW) for i in sample}, tol=JPEG_TOL_64,
                       what="egocentric_video 64x64")
    assert_nearest_own(depth, {i: ref_depth_m(session.depths[i], OUT_HW) for i in sample}, tol=1e-3,
                       what="egocentric_depth 64x64")

    lines = [camera_line("egocentric_video", n, "JPEG", hw), camera_line("egocentric_depth", n, "PNG", hw)]
    for line in lines:
        assert says(answer, line), (line, {k: v for k, v in answer.items() if k != "remote_uris"})
        assert says(listed(client, eid), line)
    cache = tmp_path / "cache"
    out = dataset(client, cache)
    for line in lines:
        assert line in out, out
    assert_cache_frames(client, cache, eid, "egocentric_video",
                        {i: ref_rgb(session.frames[i], OUT_HW) for i in sample}, tol=JPEG_TOL_64)
    assert train_vqvae(client, cache, tmp_path / "run")["model_config"]["input"] == "frame"


# -- the Pi runtime: create_upload_package ------------------------------------------------------------------

def upload_once(client, body: bytes, kind: str, content_type: str, headers: dict | None = None) -> dict:
    """Uploads a package twice, as a producer retrying: the first answer writes its one episode,
    the second changes nothing. Returns the first answer's episode."""
    r = upload(client, body, content_type=content_type, headers=headers)
    assert r.status_code == 200, r.get_json()
    assert r.get_json()["packages"][0]["kind"] == kind
    ep = only_episode(r.get_json())
    assert ep["action"] == "written", ep
    before = inbox_tree(client)
    again = upload(client, body, content_type=content_type, headers=headers)
    assert again.status_code == 200 and only_episode(again.get_json())["action"] == "unchanged"
    assert inbox_tree(client) == before
    return ep


def test_pi_upload_package_rgb_and_depth_reach_the_trainer(client, tmp_path):
    pkg = up.pi_package(tmp_path / "pi", 6)
    ep = upload_once(client, pkg.body, "pi", "application/gzip")
    assert ep["episode_id"] == pkg.episode_id, ep

    ep_dir, steps = stored_steps(client, pkg.episode_id)
    assert len(steps) == 6
    rgb64, depth64 = {}, {}
    for i, step in enumerate(steps):
        assert step.observation["rgb"].get("found_by") == "file_name", step.observation["rgb"]
        assert step.observation["depth"].get("found_by") == "file_name", step.observation["depth"]
        rpath, dpath = camera_file(ep_dir, step, "rgb"), camera_file(ep_dir, step, "depth")
        assert np.array_equal(np.load(rpath, allow_pickle=False), pkg.rgb[i])
        assert np.array_equal(np.load(dpath, allow_pickle=False), pkg.depth[i])
        assert np.array_equal(media_still(rpath, up.PI_HW, "rgb"), pkg.rgb[i])
        assert np.allclose(media_still(dpath, up.PI_HW, "depth"), ref_depth_m(pkg.depth[i]), atol=1e-6)
        rgb64[i] = media_still(rpath, OUT_HW, "rgb")
        depth64[i] = media_still(dpath, OUT_HW, "depth")
    assert_nearest_own(rgb64, {i: ref_rgb(pkg.rgb[i], OUT_HW) for i in range(6)}, tol=1.0, what="rgb 64x64")
    assert_nearest_own(depth64, {i: ref_depth_m(pkg.depth[i], OUT_HW) for i in range(6)}, tol=1e-3,
                       what="depth 64x64")

    lines = [camera_line("rgb", 6, "NPY", up.PI_HW), camera_line("depth", 6, "NPY", up.PI_HW)]
    for line in lines:
        assert says(ep, line), (line, ep)
        assert says(listed(client, pkg.episode_id), line)
    assert "vqvae" in ep["trainable"], ep
    cache = tmp_path / "cache"
    out = dataset(client, cache)
    for line in lines:
        assert line in out, out
    # the runtime's OAK-D hands the recorder getCvFrame()'s BGR array (continuonbrain/sensors/
    # oak_depth.py) and it is saved as it is: the reference says so, the cache holds RGB
    assert step.observation["rgb"].get("channel_order") == "bgr"
    assert_cache_frames(client, cache, pkg.episode_id, "rgb",
                        {i: ref_rgb(np.ascontiguousarray(pkg.rgb[i][..., ::-1]), OUT_HW) for i in range(6)}, tol=1.0)
    assert train_vqvae(client, cache, tmp_path / "run")["model_config"]["input"] == "frame"


def test_pi_mock_mode_package_of_blank_frames_is_taken_and_its_cameras_named(client, tmp_path):
    """Mock mode (no OAK-D attached) saves all-zero rgb and depth: a package that compresses ~1000x,
    which is what the Pi really sends, not a bomb."""
    pkg = up.pi_package(tmp_path / "pi", 6, mock=True)
    ep = upload_once(client, pkg.body, "pi", "application/gzip")

    ep_dir, steps = stored_steps(client, pkg.episode_id)
    for step in steps:
        assert not media_still(camera_file(ep_dir, step, "rgb"), OUT_HW, "rgb").any()
        assert not media_still(camera_file(ep_dir, step, "depth"), OUT_HW, "depth").any()
    verdict_text = "\n".join(strings(ep))
    out = dataset(client, tmp_path / "cache")
    for camera in ("rgb", "depth"):
        assert re.search(rf"(^|\s){camera}: ", verdict_text, re.M), (camera, ep)
        assert re.search(rf"(^|\s){camera}: ", out, re.M), (camera, out)
        # taken, but never passed off as a picture: the verdict says the frames are blank
        assert re.search(rf"(^|\s){camera}: 6/6 frames, .*; blank: ", verdict_text, re.M), (camera, ep)


# -- the XR app: RldsEpisodeWriter + HttpRldsUploader ----------------------------------------------------------

def test_xr_zip_with_its_video_frames_reaches_the_trainer(client, tmp_path):
    xr = up.xr_zip(6)
    ep = upload_once(client, xr.body, "xr", "application/zip", xr.headers)

    ep_dir, steps = stored_steps(client, ep["episode_id"])
    assert len(steps) == 6
    small = {}
    for i, step in enumerate(steps):
        path = camera_file(ep_dir, step, "video_frame")
        assert path.read_bytes() == xr.frames[xr.frame_ids[i]]
        assert np.array_equal(media_still(path, up.XR_HW, "rgb"), ref_rgb(xr.frames[xr.frame_ids[i]]))
        small[i] = media_still(path, OUT_HW, "rgb")
    want = {i: ref_rgb(xr.frames[xr.frame_ids[i]], OUT_HW) for i in range(6)}
    assert_nearest_own(small, want, tol=JPEG_TOL_64, what="video_frame 64x64")

    line = camera_line("video_frame", 6, "JPEG", up.XR_HW)
    assert says(ep, line), ep
    assert says(listed(client, ep["episode_id"]), line)
    cache = tmp_path / "cache"
    assert line in dataset(client, cache)
    assert_cache_frames(client, cache, ep["episode_id"], "video_frame", want, tol=JPEG_TOL_64)
    assert train_vqvae(client, cache, tmp_path / "run")["model_config"]["input"] == "frame"


def test_xr_zip_without_its_frames_claims_no_camera(client, tmp_path):
    """createTrainerRldsRecorder's default videoDir sits beside the episode dir, so the zip holds
    frame ids but no frame: nothing may pretend there is a camera."""
    xr = up.xr_zip(6, frames_in_episode_dir=False)
    ep = upload_once(client, xr.body, "xr", "application/zip", xr.headers)
    # ... and says where the frames went
    assert any(re.search(r"video_frame.*\b6 frame ids", w) for w in ep["warnings"]), ep["warnings"]
    _, steps = stored_steps(client, ep["episode_id"])
    assert all("video_frame" not in s.observation for s in steps)
    assert not any(re.search(r"\d+/\d+ frames, JPEG", s) for s in strings(ep)), ep
    assert not re.search(r"video_frame: [1-9]\d*/\d+ frames", dataset(client, tmp_path / "cache"))


# -- one H.264 video shared by the steps ------------------------------------------------------------------------

def _pyav_frames(video: bytes, times_s: list[float], hw: tuple[int, int] | None) -> dict[int, np.ndarray]:
    """Reference video decode with PyAV: every frame as rgb24, the one nearest each time, box-resized."""
    import av  # FFmpeg bindings: the reference decode of the video test only

    decoded: list[tuple[float, np.ndarray]] = []
    with av.open(io.BytesIO(video)) as container:
        stream = container.streams.video[0]
        for frame in container.decode(stream):
            decoded.append((float(frame.pts * stream.time_base), frame.to_ndarray(format="rgb24")))
    out = {}
    for k, t in enumerate(times_s):
        _, img = min(decoded, key=lambda d: abs(d[0] - t))
        out[k] = ref_rgb(img, hw) if hw is not None else img
    return out


def test_an_episode_over_one_h264_video_reaches_the_trainer(client, tmp_path):
    vid = up.video_episode_zip(8)
    ep = upload_once(client, vid.body, "xr", "application/zip")
    assert ep["episode_id"] == vid.episode_id, ep

    ep_dir, steps = stored_steps(client, vid.episode_id)
    paths = {camera_file(ep_dir, s, vid.camera) for s in steps}
    assert len(paths) == 1  # one video, stored once, named by every step
    (path,) = paths
    assert path.read_bytes() == vid.video
    from hope_models.media import VideoFrames

    with VideoFrames(path) as frames:
        native = np.stack(list(frames.frames_at(vid.times_s, up.VIDEO_HW)))
    with VideoFrames(path) as frames:
        small = np.stack(list(frames.frames_at(vid.times_s, OUT_HW)))
    want_native = _pyav_frames(vid.video, vid.times_s, None)
    want_small = _pyav_frames(vid.video, vid.times_s, OUT_HW)
    assert native.shape == (8, *up.VIDEO_HW, 3) and small.shape == (8, *OUT_HW, 3)
    assert_nearest_own(dict(enumerate(native)), want_native, tol=1.0, what="front_camera native")
    assert_nearest_own(dict(enumerate(small)), want_small, tol=1.0, what="front_camera 64x64")
    # and frame 3k is what step k shows: the encoder's input, through H.264
    assert_nearest_own(dict(enumerate(small)), {k: ref_rgb(up.picture(3 * k, up.VIDEO_HW), OUT_HW) for k in range(8)},
                       tol=6.0, what="front_camera vs the encoded pictures")

    line = camera_line(vid.camera, 8, "MP4", up.VIDEO_HW)
    assert says(ep, line), ep
    assert says(listed(client, vid.episode_id), line)
    cache = tmp_path / "cache"
    assert line in dataset(client, cache)
    assert_cache_frames(client, cache, vid.episode_id, vid.camera, want_small, tol=1.0)
    assert train_vqvae(client, cache, tmp_path / "run")["model_config"]["input"] == "frame"


# -- bad media, end to end --------------------------------------------------------------------------------------

def _bad_truncated_jpeg(client, tmp_path):
    session = up.app_session(3, egocentric=[up.truncated_jpeg(i, (480, 640)) for i in range(3)])
    name = session.local("egocentric")[0].rsplit("/", 1)[-1]
    r = handoff(client, session)
    return r, (lambda body: body), "egocentric_video", name, "truncated"


def _bad_huge_png(client, tmp_path):
    xr = up.xr_zip(4, frame_bytes={i: up.huge_png() for i in range(4)})
    r = upload(client, xr.body, content_type="application/zip", headers=xr.headers)
    return r, only_episode, "video_frame", f"{xr.frame_ids[0]}.jpg", "pixels"


def _bad_no_video_stream(client, tmp_path):
    vid = up.video_episode_zip(6, video=up.audio_only_mp4())
    r = upload(client, vid.body, content_type="application/zip")
    return r, only_episode, vid.camera, "front.mp4", "no video stream"


def _bad_npy_dtype(client, tmp_path):
    # float64 in [0, 1]: the recorder's rgb_image gone through a float conversion
    wrong = {i: up.picture(i, up.PI_HW).astype(np.float64) / 255.0 for i in range(4)}
    pkg = up.pi_package(tmp_path / "pi", 4, rgb_override=wrong)
    r = upload(client, pkg.body, content_type="application/gzip")
    return r, only_episode, "rgb", "step_0000_rgb.npy", "float64"


BAD = {"truncated jpeg (app)": _bad_truncated_jpeg, "png declaring 10^10 pixels (xr)": _bad_huge_png,
       "mp4 without a video stream": _bad_no_video_stream, "float64 .npy (pi)": _bad_npy_dtype}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_camera_media_is_named_never_a_500_and_dataset_says_why(client, tmp_path, case):
    r, episode_of, camera, name, reason = BAD[case](client, tmp_path)
    assert r.status_code < 500, (case, r.status_code, r.get_data(as_text=True)[:2000])
    body = r.get_json()
    assert isinstance(body, dict), r.get_data(as_text=True)[:2000]
    assert "Traceback" not in r.get_data(as_text=True)
    # the file is named as the producer knows it, not by where this server keeps it
    assert str(client.settings.home) not in r.get_data(as_text=True), (case, r.get_json())
    if 400 <= r.status_code < 500:
        assert name in body["error"], (case, body)
        return
    assert r.status_code == 200, body
    ep = episode_of(body)
    assert ep["action"] == "written", ep
    told = {k: v for k, v in ep.items() if k not in ("remote_uris", "source")}
    assert any(name in s for s in strings(told)), (case, "no warning names the file", told)

    # the camera was the episode's only picture: `dataset` may find nothing left to build, but it
    # says so, and says why the camera is unusable, without a traceback
    done = cli(client, "dataset", str(client.settings.inbox_dir), "--cache-dir", str(tmp_path / "cache"))
    out = done.stdout + done.stderr
    assert "Traceback" not in out, out
    # its camera line ("...: 0/3 frames; step 0: ...") or the line excluding its episode, naming the field
    lines = [ln for ln in out.splitlines() if re.search(rf"\b{camera}\b", ln)]
    assert lines, (case, out)
    assert any(reason in ln.lower() for ln in lines), (case, lines)
    assert not any(re.search(rf"{camera}: ([1-9]\d*)/\d+ frames", ln) for ln in lines), (case, lines)
