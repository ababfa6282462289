"""What the Continuon producers actually send is taken whole, stored once, and anything missing is named.

Every input is built the way the upstream writer builds it (mirror of continuonai/continuon-clients):

- the Flutter app's handoff (continuonai/lib/services/brain_client.dart handoffEpisodeAssets): a
  multipart body of `manifest`, `assets` and one `asset` file part per file that exists, named by
  `file.uri.pathSegments.last`; per tap (continuonai/lib/screens/record_screen.dart
  _applyCaptureToInputs, services/media_capture_service.dart toAssets) a device_mic and a robot_mic
  wav and an egocentric `.mp4`-named file (a JPEG still, or 0 bytes when native capture fails), plus
  a depth file when there is one; the step's URIs are `Uri.file(path).toString()`, the asset's
  local_uri the bare path;
- the Pi runtime's arm recorder (continuonbrain/recording/arm_episode_recorder.py save_episode):
  `episode.json` + `step_%04d_rgb.npy` / `step_%04d_depth.npy` + a step-level `audio: {uri}` wav,
  and its upload package (continuonbrain/recording/episode_upload.py create_upload_package): one
  `<episode_id>/` dir with episode.json, every step_*.npy and upload_manifest.json, no wavs;
- the XR app (apps/continuonxr/.../trainer/TrainerRldsExtensions.kt): observation.videoFrameId
  "frame_<ms>_<i>" naming `video_frames/<id>.jpg`, by default outside the zipped episode dir.
"""
from __future__ import annotations

import gzip
import hashlib
import io
import json
import tarfile
import time
import zipfile
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest
from test_app_handoff import inbox_files, make_client, multipart
from upstream_producers import create_upload_package

CACHE = "/data/user/0/com.continuonxr.fluttercompanion.flutter_companion/cache"
JPEG = b"\xff\xd8\xff\xe0\x00\x10JFIF\x00" + bytes(40) + b"\xff\xd9"
WAV = b"RIFF\x24\x00\x00\x00WAVEfmt \x10\x00\x00\x00\x01\x00\x01\x00\x80>\x00\x00\x00}\x00\x00\x02\x00\x10\x00data\x00\x00\x00\x00"


def dart_uri_file(path: str) -> str:
    """Dart's `Uri.file(path).toString()` on Android: `file://` + the path with every byte outside
    the path characters (unreserved, sub-delims, ':', '@', '/') percent-encoded as UTF-8."""
    return "file://" + quote(path, safe="/!$&'()*+,;=:@~")


# -- the Flutter app's handoff ----------------------------------------------------------------------

def tap(ms: int, *, depth: bool, empty_video: bool = False, cache: str = CACHE):
    """One record-screen tap: the step (MultimodalInputs.buildObservation) and its assets with files
    (MediaCaptureResult.toAssets order: device_mic, robot_mic, egocentric, depth)."""
    paths = {"device_mic": f"{cache}/device_mic-{ms}.wav", "robot_mic": f"{cache}/robot_mic-{ms}.wav",
             "egocentric": f"{cache}/egocentric-{ms}.mp4"}
    if depth:
        paths["egocentric_depth"] = f"{cache}/egocentric-depth-{ms}.bin"
    obs = {"audio": {mic: {"uri": dart_uri_file(paths[mic]), "sample_rate_hz": 16000, "num_channels": 1,
                           "frame_id": f"{mic}-{ms}", "timestamp_ms": ms, "source": mic}
                     for mic in ("device_mic", "robot_mic")},
           "egocentric_video": {"uri": dart_uri_file(paths["egocentric"]), "frame_id": f"egocentric-{ms}",
                                "timestamp_ms": ms, "mount": "chest"},
           "gaze": {"origin": {"x": 0, "y": 0, "z": 0}, "direction": {"x": 0, "y": 0, "z": -1},
                    "confidence": 0.8, "target_id": "ui:record_chest"},
           "ui_context": {"notes": "pick up the cup"}}
    if depth:
        obs["egocentric_depth"] = {"uri": dart_uri_file(paths["egocentric_depth"]), "frame_id": f"egocentric-{ms}"}
    step = {"observation": obs, "action": {"command": [], "source": "human_teleop_xr"}, "is_terminal": False,
            "step_metadata": {"capture": "tap"}}
    mime = {"device_mic": "audio/wav", "robot_mic": "audio/wav", "egocentric": "video/mp4",
            "egocentric_depth": "application/octet-stream"}
    assets = [{"local_uri": path, "sensor": sensor, "frame_id": f"{sensor}-{ms}", "captured_at_ms": ms,
               **({"mount": "chest"} if sensor.startswith("egocentric") else {}), "mime_type": mime[sensor],
               "status": "pending"} for sensor, path in paths.items()]
    data = {"device_mic": WAV, "robot_mic": WAV, "egocentric": b"" if empty_video else JPEG,
            "egocentric_depth": b"\x00\x01" * 32}
    files = [("asset", path.rsplit("/", 1)[-1], data[sensor]) for sensor, path in paths.items()]
    return step, assets, files


def session(taps: int, *, depth: bool, **kw):
    steps, assets, files = [], [], []
    for i in range(taps):
        step, a, f = tap(1_764_000_000_000 + 250 * i, depth=depth, **kw)
        steps.append(step)
        assets += a
        files += f
    steps[-1]["is_terminal"] = True
    record = {"metadata": {"xr_mode": "trainer", "control_role": "human_teleop", "environment_id": "lab-mock",
                           "tags": ["multimodal_audio_video"], "software": {"xr_app": "1.0.0"}},
              "steps": steps, "assets": assets}
    return record, assets, files


def post_handoff(client, record, assets, files):
    body, ctype = multipart({"manifest": json.dumps(record), "assets": json.dumps(assets)}, files)
    return client.post("/api/training/episode_handoff", data=body, content_type=ctype,
                       headers={"authorization": f"Bearer {client.token}"})


def stored_steps(ep_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (ep_dir / "steps" / "000000.jsonl").read_text().splitlines()]


MEDIA = (("audio", "device_mic"), ("audio", "robot_mic"), ("egocentric_video",), ("egocentric_depth",))


def media_uris(step: dict) -> list[str]:
    """The step's media URIs: its two WAVs, its still and its depth (when the session has depth)."""
    out = []
    for path in MEDIA:
        node = step["observation"]
        for key in path:
            node = node.get(key, {})
        if "uri" in node:
            out.append(node["uri"])
    return out


@pytest.fixture
def client(tmp_path):
    c = make_client(tmp_path / "home", 32)
    yield c
    c.close()


# The 2,000-tap session with depth (8,000 file parts; once refused at 1,000) is
# tests/test_cameras_acceptance.py::test_app_handoff_of_2000_taps_with_depth_reaches_the_trainer:
# stored once, every step's four media URIs on a stored file, its frames decoded and trained on.


@pytest.mark.parametrize("cache", [CACHE, "/storage/emulated/0/Android/data/app/files/Mes captures/été 2026"])
def test_every_spelling_of_an_asset_path_is_rewritten_to_the_stored_file(client, cache):
    record, assets, files = session(4, depth=False, cache=cache)
    steps = record["steps"]
    mic = assets[0]["local_uri"]
    steps[1]["observation"]["audio"]["device_mic"]["uri"] = assets[3]["local_uri"]  # the bare path
    steps[2]["observation"]["audio"]["device_mic"]["uri"] = quote(assets[6]["local_uri"])  # percent-encoded
    steps[3]["observation"]["audio"]["device_mic"]["uri"] = "file://localhost" + quote(assets[9]["local_uri"])
    assert steps[0]["observation"]["audio"]["device_mic"]["uri"] == dart_uri_file(mic)
    r = post_handoff(client, record, assets, files)
    assert r.status_code == 200, r.get_json()
    body = r.get_json()
    ep_dir = client.settings.inbox_dir / body["episode_id"]
    for i, step in enumerate(stored_steps(ep_dir)):
        for uri in media_uris(step):
            assert uri.startswith("blobs/assets/") and (ep_dir / uri).is_file(), (i, uri)
    assert body["remote_uris"][mic] == f"datasets/inbox/{body['episode_id']}/blobs/assets/{mic.rsplit('/', 1)[-1]}"
    assert not any("did not send" in w for w in body["warnings"])


def test_an_asset_file_the_app_did_not_send_and_an_empty_one_are_named(client):
    record, assets, files = session(3, depth=False, empty_video=True)
    files = [f for f in files if not f[1].startswith("robot_mic")]  # File(...).exists() was false
    r = post_handoff(client, record, assets, files)
    assert r.status_code == 200, r.get_json()
    warnings = r.get_json()["warnings"]
    unsent = [w for w in warnings if "did not send" in w]
    assert len(unsent) == 1, warnings
    assert "step 0: observation.audio.robot_mic.uri: 3 step(s)" in unsent[0]
    assert dart_uri_file(assets[1]["local_uri"]) in unsent[0]
    assert any("3 asset file(s) came empty" in w and "egocentric-" in w for w in warnings), warnings


# -- the Pi runtime ---------------------------------------------------------------------------------

def pi_step(i: int, t0: int, *, audio: bool) -> dict:
    """StepData.to_dict of arm_episode_recorder.py."""
    t = t0 + i * 100_000_000
    step = {"step_index": i, "timestamp_ns": t,
            "observation": {"frame_timestamp_ns": t, "video_frame_id": f"frame_{i:06d}",
                            "depth_frame_id": f"depth_{i:06d}", "rgb_shape": [480, 640, 3], "depth_shape": [480, 640],
                            "robot_state": {"joint_positions": [0.1 * i % 1, 0.0, 0.2, 0.0, 0.1, 0.5],
                                            "frame_id": f"frame_{i:06d}", "timestamp_nanos": t}},
            "action": {"command": [0.1, 0.0, 0.2, 0.0, 0.1, 0.5], "source": "human_teleop_xr",
                       "timestamp_nanos": t},
            "is_terminal": False, "language_instruction": "wave", "reward": 0.0, "step_metadata": {}}
    if audio:
        step["audio"] = {"uri": f"step_{i:04d}_audio.wav", "sample_rate_hz": 16000, "num_channels": 1,
                         "format": "wav_pcm16", "frame_id": f"frame_{i:06d}", "timestamp_ns": t, "delta_ms_to_frame": 0}
    return step


def pi_episode(ep_dir: Path, steps: int, *, audio: bool = False, shape=(480, 640)) -> Path:
    """arm_episode_recorder.save_episode: episode.json, then per step np.save of the rgb and depth
    frames (all zeros: mock mode or a dropped camera) and the wav of step.audio_uri."""
    ep_dir.mkdir(parents=True)
    t0 = 1_764_000_000_000_000_000
    metadata = {"episode_id": ep_dir.name, "robot_type": "SO-ARM101", "robot_id": None, "xr_mode": "trainer",
                "control_role": "human_teleop", "action_source": "human_teleop_xr", "camera_config": {},
                "frame_convention": "base_link", "environment_id": "pi5-lab", "software": {},
                "start_timestamp_ns": t0, "end_timestamp_ns": t0 + steps * 100_000_000, "total_steps": steps,
                "tags": ["pi5", "oak-d-lite", "pca9685", "continuon.xr_mode:trainer"], "glove_sample_rate_hz": None,
                "glove_drop_count": 0, "glove_valid": False, "schema_version": "1.1",
                "continuon": {"xr_mode": "trainer", "control_role": "human_teleop"}}
    doc = {"metadata": metadata, "steps": [pi_step(i, t0, audio=audio) for i in range(steps)]}
    doc["steps"][-1]["is_terminal"] = True
    (ep_dir / "episode.json").write_text(json.dumps(doc, indent=2))
    for i in range(steps):
        np.save(ep_dir / f"step_{i:04d}_rgb.npy", np.zeros((*shape, 3), dtype=np.uint8))
        np.save(ep_dir / f"step_{i:04d}_depth.npy", np.zeros(shape, dtype=np.uint16))
        if audio:
            (ep_dir / f"step_{i:04d}_audio.wav").write_bytes(WAV)
    return ep_dir


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def upload(client, body: bytes):
    return client.post("/api/episodes/upload", data=body, content_type="application/gzip",
                       headers={"Authorization": f"Bearer {client.token}"})


def test_a_zero_frame_pi_package_of_300_steps_is_stored_with_its_frames(client, tmp_path):
    """All-zero 480x640 frames inflate ~740x: once refused as a gzip bomb."""
    package = create_upload_package(pi_episode(tmp_path / "src" / "ep_20261127_zero", 300), tmp_path / "staging")
    unpacked = sum(p.stat().st_size for p in (tmp_path / "staging" / "ep_20261127_zero").iterdir())
    assert unpacked > 400 * package.stat().st_size  # far past the old 200:1
    r = upload(client, package.read_bytes())
    assert r.status_code == 200, r.get_json()
    (episode,) = r.get_json()["packages"][0]["episodes"]
    assert episode["action"] == "written", episode
    ep_dir = client.settings.inbox_dir / episode["episode_id"]
    steps = stored_steps(ep_dir)
    assert len(steps) == 300
    for i in (0, 3, 299):
        obs = steps[i]["observation"]
        assert obs["rgb"] == {"uri": f"blobs/step_{i:04d}_rgb.npy", "found_by": "file_name",
                              "channel_order": "bgr"}
        assert obs["depth"] == {"uri": f"blobs/step_{i:04d}_depth.npy", "found_by": "file_name"}
        assert np.load(ep_dir / obs["rgb"]["uri"]).shape == (480, 640, 3)
    assert len(list((ep_dir / "blobs").glob("step_*_rgb.npy"))) == 300
    assert list((Path(client.settings.home) / "tmp").iterdir()) == []


def test_pi_frames_are_attached_by_position_and_the_missing_ones_counted(tmp_path):
    from hope_models.rlds.discover import read_path

    ep_dir = pi_episode(tmp_path / "ep_partial", 6, shape=(4, 6))
    for i in (2, 4):
        (ep_dir / f"step_{i:04d}_rgb.npy").unlink()
    (ep_dir / "step_0000_depth.npy").unlink()
    doc = json.loads((ep_dir / "episode.json").read_text())
    doc["steps"][5]["observation"]["depth"] = "the producer's own"  # never overwritten
    (ep_dir / "episode.json").write_text(json.dumps(doc))
    (ep,) = read_path(ep_dir / "episode.json")[0].episodes
    rgb = [s.observation.get("rgb") for s in ep.steps]
    assert rgb[0] == {"uri": "step_0000_rgb.npy", "found_by": "file_name", "channel_order": "bgr"} and rgb[2] is None and rgb[4] is None
    assert ep.steps[5].observation["depth"] == "the producer's own"
    assert ep.steps[1].observation["depth"] == {"uri": "step_0001_depth.npy", "found_by": "file_name"}
    words = [str(p) for p in ep.warnings]
    assert any("2 of 6 steps have no step_0002_rgb.npy" in w for w in words), words
    assert any("1 of 6 steps have no step_0000_depth.npy" in w for w in words), words
    assert any("1 step(s) already have observation.depth" in w for w in words), words


def test_a_step_level_audio_blob_is_copied_and_a_missing_one_named(tmp_path):
    """The arm recorder's step `audio: {uri: "step_0003_audio.wav"}` sits beside the observation."""
    from hope_models.intake.inbox import ingest_into_inbox

    ep_dir = pi_episode(tmp_path / "src" / "ep_audio", 4, audio=True, shape=(4, 6))
    (ep_dir / "step_0002_audio.wav").unlink()
    result = ingest_into_inbox([ep_dir], tmp_path / "inbox", origin="test")
    (entry,) = result["episodes"]
    assert entry["action"] == "written", entry
    missing = [w for w in entry["warnings"] if "step_0002_audio.wav" in w]
    assert len(missing) == 1 and "step 2: audio.uri" in missing[0], entry["warnings"]
    stored = tmp_path / "inbox" / entry["episode_id"]
    steps = stored_steps(stored)
    assert steps[3]["audio"]["uri"] == "blobs/step_0003_audio.wav"
    assert (stored / "blobs" / "step_0003_audio.wav").read_bytes() == WAV
    assert steps[2]["audio"]["uri"] == "step_0002_audio.wav"  # kept as it was, named in the warning


# -- the XR app -------------------------------------------------------------------------------------

def xr_zip(steps: int, *, frames: bool) -> bytes:
    """HttpRldsUploader's zip of the episode dir (metadata.json, steps/000000.jsonl in camelCase);
    TrainerRldsExtensions names each frame `frame_<ms>_<i>` and writes `<id>.jpg` to video_frames/."""
    ids = [f"frame_{1764000000000 + 33 * i}_{i}" for i in range(steps)]
    lines = [json.dumps({"observation": {"robotState": {"timestampNanos": 1_764_000_000_000_000_000 + i * 33_000_000,
                                                        "jointPositions": [0.0, 0.1, 0.2], "frameId": ids[i]},
                                         "videoFrameId": ids[i]},
                         "action": {"command": [0.0, 0.1, 0.2], "source": "human_teleop_xr"},
                         "isTerminal": i == steps - 1}) for i in range(steps)]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("metadata.json", json.dumps({"xrMode": "trainer", "controlRole": "human_teleop",
                                                "environmentId": "lab", "tags": ["xr"]}))
        z.writestr("steps/000000.jsonl", "\n".join(lines) + "\n")
        if frames:
            for frame_id in ids:
                z.writestr(f"video_frames/{frame_id}.jpg", JPEG)
    return buf.getvalue()


def test_xr_frame_ids_without_their_files_are_one_warning(client):
    r = client.post("/api/episodes/upload", data=xr_zip(5, frames=False), content_type="application/zip",
                    headers={"Authorization": f"Bearer {client.token}"})
    assert r.status_code == 200, r.get_json()
    (episode,) = r.get_json()["packages"][0]["episodes"]
    named = [w for w in episode["warnings"] if "frame ids" in w]
    assert len(named) == 1, episode["warnings"]
    assert named[0].endswith("observation.video_frame_id: 5 frame ids, no frame files in the upload (the XR app "
                             "writes them to video_frames/ beside the episode dir)")


def test_xr_frame_files_in_the_zip_are_attached_and_stored(client):
    r = client.post("/api/episodes/upload", data=xr_zip(5, frames=True), content_type="application/zip",
                    headers={"Authorization": f"Bearer {client.token}"})
    assert r.status_code == 200, r.get_json()
    (episode,) = r.get_json()["packages"][0]["episodes"]
    assert not any("frame ids" in w for w in episode["warnings"]), episode["warnings"]
    ep_dir = client.settings.inbox_dir / episode["episode_id"]
    for step in stored_steps(ep_dir):
        frame = step["observation"]["video_frame"]
        assert frame["found_by"] == "frame_id" and frame["uri"].startswith("blobs/video_frames/frame_")
        assert (ep_dir / frame["uri"]).read_bytes() == JPEG


# -- bombs are still refused, by what they would cost -----------------------------------------------

def test_a_gzip_of_20_gb_of_zeros_is_refused_at_once_naming_the_file_and_the_cap(client):
    member = tarfile.TarInfo("ep_bomb/step_0000_rgb.npy")
    member.size = 20 << 30
    zeros = gzip.compress(bytes(64 << 20), compresslevel=9)
    body = gzip.compress(member.tobuf(tarfile.PAX_FORMAT)) + zeros * 320  # 20 GiB of zeros behind the header
    assert len(body) < 32 << 20
    t0 = time.monotonic()
    r = upload(client, body)
    assert r.status_code == 413, r.get_json()
    error = r.get_json()["error"]
    assert "request body" in error and "upload_unpack_max_mb=3072" in error, error
    assert time.monotonic() - t0 < 10
    assert list((Path(client.settings.home) / "tmp").iterdir()) == [] and inbox_files(client) == []


def test_a_stream_past_the_cap_stops_inflating_there(tmp_path):
    """Members whose sizes each look harmless: the scan stops once their sum passes the cap, having
    inflated about the cap's worth and written nothing."""
    from hope_models.rlds.upload_package import PackageError, scan_tar

    parts = []
    for i in range(64):
        member = tarfile.TarInfo(f"ep/blob_{i:02d}.bin")
        member.size = 8 << 20
        parts.append(gzip.compress(member.tobuf(tarfile.PAX_FORMAT) + bytes(8 << 20), compresslevel=9))
    path = tmp_path / "many.tar.gz"
    path.write_bytes(b"".join(parts))  # 512 MiB inflated
    t0 = time.monotonic()
    with pytest.raises(PackageError, match=r"more than 33554432 bytes uncompressed \(cap-words\)") as caught:
        scan_tar(path, "file 'many.tar.gz'", 32 << 20, cap_words="cap-words")
    assert caught.value.status == 413 and time.monotonic() - t0 < 5
    assert [p.name for p in tmp_path.iterdir()] == ["many.tar.gz"]


def test_past_the_cap_is_413_and_within_it_but_past_the_room_now_is_507(tmp_path):
    from webapp.uploads import TmpRoom

    c = make_client(tmp_path / "home", 1, HOPE_UPLOAD_UNPACK_MAX_MB="8", HOPE_UPLOAD_TMP_MAX_MB="8")
    try:
        def package(mb: int) -> bytes:
            buf = io.BytesIO()
            with tarfile.open(fileobj=buf, mode="w:gz") as tar:
                member = tarfile.TarInfo("ep_room/step_0000_rgb.npy")
                member.size = mb << 20
                tar.addfile(member, io.BytesIO(bytes(member.size)))
            return buf.getvalue()

        r = upload(c, package(10))
        assert r.status_code == 413 and "upload_unpack_max_mb=8" in r.get_json()["error"], r.get_json()
        other = TmpRoom(c.settings)  # another upload in progress holds 4 MB of $HOPE_HOME/tmp
        other.take(4 << 20, "another upload")
        try:
            r = upload(c, package(6))
            assert r.status_code == 507, r.get_json()
            assert "unpacks to 6291456 bytes" in r.get_json()["error"] and "has room for" in r.get_json()["error"]
        finally:
            other.release()
        r = upload(c, package(6))  # fits now; refused only for what it is (no upload_manifest.json)
        assert r.status_code == 400 and "upload_manifest.json" in r.get_json()["error"], r.get_json()
    finally:
        c.close()


def test_form_fields_are_bounded_in_all_not_only_one_by_one(tmp_path):
    """Fields are held in memory: many just under the one-field limit must not add up unbounded."""
    from webapp.uploads import MAX_FIELD_BYTES, MAX_FIELDS_BYTES

    c = make_client(tmp_path / "home", 128)
    try:
        fields = {f"f{i}": "x" * (MAX_FIELD_BYTES - 1024) for i in range(MAX_FIELDS_BYTES // MAX_FIELD_BYTES + 1)}
        body, ctype = multipart(fields, [])
        r = c.post("/api/training/episode_handoff", data=body, content_type=ctype,
                   headers={"authorization": f"Bearer {c.token}"})
        assert r.status_code == 413 and f"more than {MAX_FIELDS_BYTES} bytes" in r.get_json()["error"], r.get_json()
        assert inbox_files(c) == []
    finally:
        c.close()
