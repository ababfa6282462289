"""What each Continuon producer writes or sends, with real pictures: the camera acceptance inputs.

Built from the producers' code (the mirror of continuonai/continuon-clients), not from prose; the
comment on each builder names the upstream file and function it follows. Every still has content
of its own (`picture(i)`, `depth_mm(i)`), so a test can tell which step a decoded frame came from.

- the Continuon app's record screen handed off to its robot (`AppSession`, `app_session`):
  record_screen.dart _recordStep/_uploadRecord, media_capture_service.dart, multimodal_inputs.dart,
  task_recorder.dart, rlds_models.dart, brain_client.dart handoffEpisodeAssets; the multipart
  body is tests/test_app_client_replay.py's `multipart`, byte for byte what package:http writes
  (MultipartFile.fromPath gives every file part `content-type: application/octet-stream`: the
  MultipartFile constructor's default when no contentType is passed, and handoffEpisodeAssets passes none);
- the Pi runtime's upload package (`pi_package`): continuonbrain/recording/arm_episode_recorder.py
  end_episode (episode.json + step_%04d_rgb.npy / step_%04d_depth.npy) and
  continuonbrain/recording/episode_upload.py EpisodeUploadPipeline.create_upload_package;
- the XR app's upload zip (`xr_zip`): apps/continuonxr logging/RldsEpisodeWriter.kt
  FileEpisodeSink, trainer/TrainerRldsExtensions.kt TrainerRldsRecorder, logging/HttpRldsUploader.kt
  upload/zipDirectory;
- an episode whose steps share one H.264 MP4 (`video_episode_zip`), written with PyAV.

No test lives here; tests/test_cameras_acceptance.py uses it.
"""
from __future__ import annotations

import hashlib
import io
import json
import shutil
import tarfile
import time
import wave
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from test_app_client_replay import dart_json, multipart

# -- pictures -----------------------------------------------------------------------------------------

def picture(i: int, hw: tuple[int, int]) -> np.ndarray:
    """uint8 RGB [h, w, 3] that says which step it is: a gradient, a step-coloured blue level and a
    bright block in one of nine places, large enough to survive JPEG and a 64x64 area resize."""
    h, w = hw
    y, x = np.mgrid[0:h, 0:w]
    img = np.empty((h, w, 3), np.uint8)
    img[..., 0] = x * 255 // max(w - 1, 1)
    img[..., 1] = y * 255 // max(h - 1, 1)
    img[..., 2] = (i * 53) % 256
    cell_h, cell_w = h // 3, w // 3
    r, c = divmod(i % 9, 3)
    img[r * cell_h:(r + 1) * cell_h, c * cell_w:(c + 1) * cell_w] = ((i * 97) % 256, 255 - (i * 31) % 256, 255)
    return img


def depth_mm(i: int, hw: tuple[int, int]) -> np.ndarray:
    """uint16 depth in millimetres [h, w]: a slope whose distance says the step, with the top eighth
    of the rows 0 ("no reading", as a stereo camera leaves where it cannot match)."""
    h, w = hw
    y, x = np.mgrid[0:h, 0:w]
    depth = (400 + 4 * (i % 5000) + 2 * x + y).astype(np.uint16)  # 4 mm further each step
    depth[: max(h // 8, 1)] = 0
    return depth


def jpeg(img: np.ndarray, quality: int = 85) -> bytes:
    out = io.BytesIO()
    Image.fromarray(img).save(out, format="JPEG", quality=quality)
    return out.getvalue()


def png16(depth: np.ndarray) -> bytes:
    """A 16-bit greyscale PNG of uint16 millimetres."""
    out = io.BytesIO()
    Image.fromarray(depth.astype(np.uint16)).save(out, format="PNG")
    return out.getvalue()


def wav(samples: int = 320, rate_hz: int = 16000, seed: int = 0) -> bytes:
    """PCM16 mono WAV as the Pi's ArmEpisodeRecorder._save_audio_file writes one (and a phone's
    recorder): 20 ms at 16 kHz by default, the app's sample_rate_hz/num_channels defaults."""
    pcm = (np.random.default_rng(seed).standard_normal(samples) * 3000).astype("<i2")
    out = io.BytesIO()
    with wave.open(out, "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(rate_hz)
        w.writeframes(pcm.tobytes())
    return out.getvalue()


# -- the Continuon app: record screen -> BrainClient.handoffEpisodeAssets ---------------------------------

# getTemporaryDirectory() of the app (applicationId in continuonai/android/app/build.gradle.kts):
# MediaCaptureService._buildStubFile names capture files `$sensor-<ms>.$extension` there.
APP_CACHE = "/data/user/0/com.continuonxr.fluttercompanion.flutter_companion/cache"
APP_T0_MS = 1_732_400_000_000
TAP_MS = 500  # a person taps "Record step" at most a couple of times a second


@dataclass
class AppSession:
    record: dict  # EpisodeRecord.toJson(): jsonEncode'd into the `manifest` field
    assets: list[dict]  # EpisodeAsset.toJson() of package.assets: the `assets` field
    files: list[tuple[str, bytes]]  # the `asset` file parts: (last path segment, bytes), in assets order
    frames: list[bytes] = field(default_factory=list)  # per tap: the egocentric file's bytes
    depth: list[bytes] = field(default_factory=list)  # per tap: the depth file's bytes (when any)
    pictures: list[np.ndarray] = field(default_factory=list)  # per tap: what was encoded into frames[i]
    depths: list[np.ndarray] = field(default_factory=list)  # per tap: depth in mm encoded into depth[i]

    def body(self) -> tuple[bytes, str]:
        """http.MultipartRequest's body and content type, as handoffEpisodeAssets sends it."""
        boundary = "dart-http-boundary-" + hashlib.sha256(dart_json(self.record).encode()).hexdigest()[:51]
        return multipart(boundary, [("manifest", dart_json(self.record)), ("assets", dart_json(self.assets))],
                         self.files)

    def local(self, sensor: str) -> list[str]:
        """Per tap, the phone path of `sensor`'s capture (device_mic, robot_mic, egocentric, egocentric_depth)."""
        return [a["local_uri"] for a in self.assets if a["sensor"] == sensor]


# _recordStep captures device_mic, then robot_mic, then egocentric, each stamped with its own
# DateTime.now(); a millisecond apart here so the files' names differ as they would.
_SENSOR_OFFSET_MS = {"device_mic": 0, "robot_mic": 1, "egocentric": 2}


def _tap_ms(tap: int) -> int:
    return APP_T0_MS + tap * TAP_MS


def app_session(n_taps: int, *, depth: bool = False, hw: tuple[int, int] = (480, 640),
                egocentric: list[bytes] | None = None) -> AppSession:
    """A record-screen session of `n_taps` taps with every sensor switched on (the screen's defaults:
    _includeDeviceMic, _includeRobotMic, _includeEgocentricVideo, mount 'chest').

    record_screen.dart _recordStep: MediaCaptureService.capture -> _applyCaptureToInputs (step
    uris are Uri.file(path).toString(), i.e. file:///...), addAssets(capture.toAssets()) (asset
    local_uri is the bare path), addStep(observation = MultimodalInputs.buildObservation(uiContext),
    action = {command: [], source: human_teleop_xr}); EpisodeStep.toJson adds is_terminal false
    and step_metadata {}. _uploadRecord hands off `_recorder.buildPackage()`: the record (with its
    assets) and the assets, before the PII pipeline touches the metadata.
    media_capture_service.dart _captureVideo: the egocentric capture is one still per tap in a file
    named `egocentric-<ms>.mp4` (mime video/mp4) -- a JPEG here, `egocentric` overriding the bytes;
    a depth_path, when the native side gives one, becomes an `egocentric_depth` asset
    (application/octet-stream) and observation.egocentric_depth {uri, frame_id}: a 16-bit PNG of
    millimetres here (upstream names no format). Audio is a WAV per tap and mic.
    """
    steps, assets, files = [], [], []
    session = AppSession(record={}, assets=assets, files=files)
    for tap in range(n_taps):
        t = _tap_ms(tap)
        obs: dict[str, Any] = {}
        tap_assets = []
        audio = {}
        for mic in ("device_mic", "robot_mic"):
            ms = t + _SENSOR_OFFSET_MS[mic]
            path = f"{APP_CACHE}/{mic}-{ms}.wav"
            # multimodal_inputs.dart AudioSample.toJson; frame_id falls back to the timestamp's text
            audio[mic] = {"uri": f"file://{path}", "sample_rate_hz": 16000, "num_channels": 1, "frame_id": str(ms),
                          "timestamp_ms": ms, "source": mic}
            tap_assets.append(({"local_uri": path, "sensor": mic, "frame_id": str(ms), "captured_at_ms": ms,
                                "mime_type": "audio/wav", "status": "queued"}, wav(seed=tap * 2 + len(audio))))
        obs["audio"] = audio
        ms = t + _SENSOR_OFFSET_MS["egocentric"]
        video_path = f"{APP_CACHE}/egocentric-{ms}.mp4"
        pic = picture(tap, hw)
        still = egocentric[tap] if egocentric is not None else jpeg(pic)
        session.pictures.append(pic)
        session.frames.append(still)
        # EgocentricFrame.toVideoJson / toDepthJson
        obs["egocentric_video"] = {"uri": f"file://{video_path}", "frame_id": str(ms), "timestamp_ms": ms,
                                   "mount": "chest"}
        tap_assets.append(({"local_uri": video_path, "sensor": "egocentric", "frame_id": str(ms), "captured_at_ms": ms,
                            "mount": "chest", "mime_type": "video/mp4", "status": "queued"}, still))
        if depth:
            depth_path = f"{APP_CACHE}/egocentric_depth-{ms}.png"
            d = depth_mm(tap, hw)
            session.depths.append(d)
            session.depth.append(png16(d))
            obs["egocentric_depth"] = {"uri": f"file://{depth_path}", "frame_id": str(ms)}
            tap_assets.append(({"local_uri": depth_path, "sensor": "egocentric_depth", "frame_id": str(ms),
                                "captured_at_ms": ms, "mount": "chest", "mime_type": "application/octet-stream",
                                "status": "queued"}, session.depth[-1]))
        # updateGaze in _applyCaptureToInputs; Vector3 holds doubles, so jsonEncode writes 0.0
        obs["gaze"] = {"origin": {"x": 0.0, "y": 0.0, "z": 0.0}, "direction": {"x": 0.0, "y": 0.0, "z": -1.0},
                       "confidence": 0.8, "target_id": "ui:record_chest"}
        obs["ui_context"] = {"notes": "", "voice_hint": ""}
        steps.append({"observation": obs, "action": {"command": [], "source": "human_teleop_xr"},
                      "is_terminal": False, "step_metadata": {}})
        for asset, data in tap_assets:
            assets.append(asset)
            # handoffEpisodeAssets: MultipartFile.fromPath('asset', path, filename: last path segment)
            files.append((asset["local_uri"].rsplit("/", 1)[-1], data))
    classification = ["motion:drive", "motion:pick_and_place", "motion:follow_path", "task:warehouse",
                      "task:kitchen", "task:lab", "skill:grasp", "skill:navigate", "skill:inspect"]
    # _buildMetadata / _buildSafetyMetadata with the screen's initial switches
    metadata = {"xr_mode": "trainer", "control_role": "human_teleop", "environment_id": "lab-mock",
                "tags": ["multimodal_audio_video", *classification],
                "safety": {"content_rating": {"audience": "general", "violence": "none", "language": "clean"},
                           "intended_audience": "general", "pii_attested": False, "pii_cleared": False,
                           "pii_redacted": False, "pending_review": True,
                           "pii_attestation": {"pii_present": True, "faces_present": True, "name_present": True,
                                               "consent": False}},
                "share": {"public": False, "slug": "", "title": "", "license": "CC-BY-4.0", "tags": classification},
                "schema_version": "1.1"}
    session.record = {"metadata": metadata, "steps": steps, "assets": list(assets)}  # EpisodeRecord.toJson
    return session


# -- the Pi runtime: ArmEpisodeRecorder.end_episode -> EpisodeUploadPipeline.create_upload_package ---------

PI_HW = (480, 640)  # the recorder's mock frame size, and what the brief's Pi packages carry
PI_T0_NS = 1_732_500_000_000_000_000
PI_STEP_NS = 50_000_000  # test_recorder's 20 Hz


@dataclass
class PiPackage:
    episode_id: str
    body: bytes  # the tar.gz
    rgb: list[np.ndarray]  # per step, as saved
    depth: list[np.ndarray]


def pi_package(tmp: Path, n_steps: int = 6, *, mock: bool = False, episode_id: str | None = None,
               rgb_override: dict[int, np.ndarray] | None = None) -> PiPackage:
    """An upload package exactly as the Pi runtime lays it out.

    arm_episode_recorder.py ArmEpisodeRecorder.start_episode/record_step/end_episode: episode.json
    ({metadata: EpisodeMetadata.to_dict(language_instruction), steps: [StepData.to_dict()]},
    json.dump indent=2) beside step_%04d_rgb.npy ((480, 640, 3) uint8; mock mode: zeros) and
    step_%04d_depth.npy ((480, 640) uint16 mm; mock: zeros) saved with np.save; the mock
    microphone's blocks are named by a step-level `audio.uri` (step_%04d_audio.wav) that
    create_upload_package does not pack (it globs step_*.npy only).
    episode_upload.py create_upload_package: a stage dir <episode_id>/ with episode.json, the .npy
    files and upload_manifest.json (EpisodeManifest.to_dict, indent=2), then
    tarfile.open(w:gz).add(stage_dir, arcname=episode_id).
    `rgb_override` replaces a step's rgb array (a producer gone wrong).
    """
    episode_id = episode_id or ("arm_episode_1732500000" if not mock else "arm_episode_1732500099")
    src = tmp / "episodes" / episode_id
    src.mkdir(parents=True)
    language = "Pick up the red cube and place it in the bin"
    start_ns = PI_T0_NS - 10_000_000
    steps, rgbs, depths = [], [], []
    rng = np.random.default_rng(7)
    for i in range(n_steps):
        ts = PI_T0_NS + i * PI_STEP_NS
        frame_ts = ts + 1_000_000  # capture_frame stamps its own time.time_ns()
        frame_id = f"frame_{frame_ts}"
        rgb = np.zeros((*PI_HW, 3), np.uint8) if mock else picture(i, PI_HW)
        depth = np.zeros(PI_HW, np.uint16) if mock else depth_mm(i, PI_HW)
        if rgb_override and i in rgb_override:
            rgb = rgb_override[i]
        rgbs.append(rgb)
        depths.append(depth)
        action = [round(float(v), 3) for v in rng.uniform(-0.5, 0.5, 6)]
        steps.append({
            "step_index": i, "timestamp_ns": ts,
            "observation": {"frame_timestamp_ns": frame_ts, "video_frame_id": frame_id, "depth_frame_id": frame_id,
                            "rgb_shape": list(rgb.shape), "depth_shape": list(depth.shape),
                            "robot_state": {"joint_positions": [round(0.05 * i, 3), -0.1, 0.2, 0.0, 0.3, -0.2],
                                            "frame_id": frame_id, "timestamp_nanos": frame_ts + 200_000}},
            "action": {"command": action, "source": "human_teleop_xr", "timestamp_nanos": frame_ts + 400_000},
            "is_terminal": i == n_steps - 1, "language_instruction": language if i == 0 else None,
            "reward": 1.0 if i == n_steps - 1 else 0.0, "step_metadata": {},
            "audio": {"uri": f"step_{i:04d}_audio.wav", "sample_rate_hz": 16000, "num_channels": 1,
                      "format": "wav_pcm16", "frame_id": f"audio_{i:04d}", "timestamp_ns": ts,
                      "delta_ms_to_frame": 0.0},
        })
    end_ns = PI_T0_NS + n_steps * PI_STEP_NS
    # EpisodeMetadata.to_dict: asdict order, share None popped, the continuon block and two tags added
    camera_config = {} if mock else {"camera_type": "OAK-D-LITE", "depth_baseline_cm": 7.5, "resolution": "640x400",
                                     "fps": 30, "intrinsics": None}
    metadata = {
        "episode_id": episode_id, "robot_type": "SO-ARM101", "robot_id": None, "xr_mode": "trainer",
        "control_role": "human_teleop", "action_source": "human_teleop_xr", "camera_config": camera_config,
        "frame_convention": "base_link", "environment_id": "pi5-lab", "software": {},
        "start_timestamp_ns": start_ns, "end_timestamp_ns": end_ns, "total_steps": n_steps,
        "tags": ["pi5", "oak-d-lite", "pca9685", "manipulation", f"instruction:{language}",
                 "continuon.xr_mode:trainer"],
        "glove_sample_rate_hz": None, "glove_drop_count": 0, "glove_valid": False,
        "safety": {"content_rating": {"audience": "general", "violence": "none", "language": "clean"},
                   "intended_audience": "local", "pii_attested": False, "pii_cleared": False, "pii_redacted": False,
                   "pending_review": True,
                   "pii_attestation": {"pii_present": False, "faces_present": False, "name_present": False,
                                       "consent": False}},
        "schema_version": "1.1",
        "continuon": {"xr_mode": "trainer", "control_role": "human_teleop"},
    }
    with open(src / "episode.json", "w") as f:
        json.dump({"metadata": metadata, "steps": steps}, f, indent=2)
    for i in range(n_steps):
        np.save(src / f"step_{i:04d}_rgb.npy", rgbs[i])
        np.save(src / f"step_{i:04d}_depth.npy", depths[i])
        (src / f"step_{i:04d}_audio.wav").write_bytes(wav(seed=i))  # written, never packed
    tar_path = create_upload_package(src, tmp / "staging")
    return PiPackage(episode_id, tar_path.read_bytes(), rgbs, depths)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def create_upload_package(episode_path: Path, staging: Path) -> Path:
    """episode_upload.EpisodeUploadPipeline.create_upload_package, step by step: a stage dir
    <episode_id>/ with episode.json, every step_*.npy (no WAVs) and upload_manifest.json, tarred."""
    metadata = json.loads((episode_path / "episode.json").read_text())["metadata"]
    episode_id = metadata["episode_id"]
    stage = staging / episode_id
    stage.mkdir(parents=True)
    shutil.copy(episode_path / "episode.json", stage / "episode.json")
    checksums = {"episode.json": _sha256(stage / "episode.json")}
    total = (stage / "episode.json").stat().st_size
    for file_path in episode_path.glob("step_*.npy"):
        shutil.copy(file_path, stage / file_path.name)
        checksums[file_path.name] = _sha256(stage / file_path.name)
        total += (stage / file_path.name).stat().st_size
    manifest = {"episode_id": episode_id, "total_steps": metadata["total_steps"], "robot_type": metadata["robot_type"],
                "xr_mode": metadata["xr_mode"], "action_source": metadata["action_source"],
                "created_timestamp_ns": metadata.get("start_timestamp_ns", time.time_ns()),
                "file_checksums": checksums, "metadata_checksum": checksums["episode.json"],
                "total_size_bytes": total, "version": "1.0.0"}
    (stage / "upload_manifest.json").write_text(json.dumps(manifest, indent=2))
    tar_path = staging / f"{episode_id}.tar.gz"
    with tarfile.open(tar_path, "w:gz") as tar:
        tar.add(stage, arcname=episode_id)
    return tar_path


# -- the XR app: TrainerRldsRecorder over RldsEpisodeWriter, zipped by HttpRldsUploader -------------------

XR_T0_MS = 1_732_600_000_000
XR_STEP_MS = 100
XR_HW = (480, 640)
XR_TAGS = ["trainer", "nexasdk", "android"]
# kotlinx.serialization's class discriminator for the sealed ControlCommand: its fully qualified name
JOINT_DELTA = "com.continuonxr.app.connectivity.ControlCommand.JointDelta"


@dataclass
class XrZip:
    episode_dir: str  # FileEpisodeSink's `episode-<ms>`
    body: bytes  # the zip HttpRldsUploader posts
    headers: dict[str, str]  # its X-Continuon-Tag-* headers
    frame_ids: list[str]
    pictures: list[np.ndarray]  # per step, what was compressed into video_frames/<id>.jpg
    frames: dict[str, bytes] = field(default_factory=dict)  # frame id -> the JPEG in the zip


def _xr_pose() -> dict:
    # logging.Pose with its defaults (encodeDefaults = true writes them)
    return {"position": [0.0, 0.0, 0.0], "orientationQuat": [0.0, 0.0, 0.0, 1.0], "valid": True}


def xr_zip(n_steps: int = 6, *, frames_in_episode_dir: bool = True, hw: tuple[int, int] = XR_HW,
           frame_bytes: dict[int, bytes] | None = None) -> XrZip:
    """The zip the XR app uploads for a trainer session.

    TrainerRldsExtensions.kt TrainerRldsRecorder.startEpisode: EpisodeMetadata(xrMode trainer,
    controlRole human_teleop, environmentId "trainer-session", tags [trainer, nexasdk, android],
    startTimeUnixMs, software xrAppVersion "1.0.0-trainer"); recordStep: saveFrame writes
    `<videoDir>/frame_<ms>_<stepIndex>.jpg` (Bitmap.compress JPEG 80) and the observation gets
    videoFrameId + videoTimestampNanos and a trainer UiContext; stepMetadata step_index/input_source.
    RldsEpisodeWriter.kt FileEpisodeSink: `episode-<ms>/metadata.json` and
    `episode-<ms>/steps/000000.jsonl`, Json { encodeDefaults = true } (camelCase property names,
    declared @SerialName keys in metadata, every null written).
    HttpRldsUploader.kt upload/zipDirectory: every file under the episode dir, named relative to it,
    DEFLATED through a stream (sizes in data descriptors), headers X-Continuon-Tag-*.
    createTrainerRldsRecorder's default videoDir is <outputDir>/video_frames, beside the episode
    dirs, so the zip holds no frame (`frames_in_episode_dir=False`); a videoDir inside the episode
    dir puts them in the zip as video_frames/<frameId>.jpg.
    """
    episode_dir = f"episode-{XR_T0_MS - 5}"
    metadata = {"continuon.xr_mode": "trainer", "continuon.control_role": "human_teleop",
                "environment_id": "trainer-session",
                "software": {"xrAppVersion": "1.0.0-trainer", "brainVersion": None, "gloveFirmwareVersion": None},
                "tags": XR_TAGS, "robot_id": None, "robot_model": None, "frame_convention": None,
                "start_time_unix_ms": XR_T0_MS - 5, "duration_ms": None}
    lines, frame_ids, pictures, frames = [], [], [], {}
    for i in range(n_steps):
        ms = XR_T0_MS + i * XR_STEP_MS
        frame_id = f"frame_{ms}_{i}"
        pic = picture(i, hw)
        frame_ids.append(frame_id)
        pictures.append(pic)
        frames[frame_id] = frame_bytes[i] if frame_bytes and i in frame_bytes else jpeg(pic, quality=80)
        robot_state = {"timestampNanos": ms * 1_000_000, "jointPositions": [round(0.1 * i, 3), -0.2, 0.3, 0.0, 0.1, 0.5],
                       "endEffectorPose": {"position": [0.0, 0.0, 0.0], "orientationQuat": [0.0, 0.0, 0.0, 1.0]},
                       "gripperOpen": i % 2 == 0, "frameId": None, "jointVelocities": [], "jointEfforts": [],
                       "endEffectorTwist": [], "wallTimeMillis": ms}
        observation = {"headsetPose": _xr_pose(), "rightHandPose": _xr_pose(), "leftHandPose": None, "gaze": None,
                       "gloveFrame": None, "robotState": robot_state, "videoFrameId": frame_id, "depthFrameId": None,
                       "videoTimestampNanos": ms * 1_000_000, "depthTimestampNanos": None, "audio": None,
                       "uiContext": {"activePanel": "trainer", "layout": {"mode": "portrait"},
                                     "focusContext": {"input_source": "joystick", "teaching_state": "idle"}},
                       "diagnostics": {"latencyMs": 0.0, "gloveDrops": 0, "gloveSampleRateHz": None, "bleRssi": None}}
        action = {"command": {"type": JOINT_DELTA, "deltaRadians": [0.01, -0.02, 0.0, 0.0, 0.0, 0.0],
                              "targetFrequencyHz": None, "safety": None},
                  "source": "human_teleop_xr", "annotation": None, "uiAction": None}
        step = {"observation": observation, "action": action, "isTerminal": False,
                "stepMetadata": {"step_index": str(i), "input_source": "joystick"}}
        lines.append(json.dumps(step, separators=(",", ":")))
    members = [("metadata.json", json.dumps(metadata, separators=(",", ":")).encode()),
               ("steps/000000.jsonl", ("\n".join(lines) + "\n").encode())]
    if frames_in_episode_dir:
        members += [(f"video_frames/{fid}.jpg", data) for fid, data in frames.items()]
    headers = {"X-Continuon-Tag-xr_mode": "trainer", "X-Continuon-Tag-control_role": "human_teleop",
               "X-Continuon-Tag-environment_id": "trainer-session", "X-Continuon-Tag-list": ",".join(XR_TAGS)}
    return XrZip(episode_dir, streamed_zip(members), headers, frame_ids, pictures,
                 frames if frames_in_episode_dir else {})


class _Stream:
    """A write-only sink: zipfile cannot seek back, so, like java.util.zip.ZipOutputStream, it writes
    each entry's sizes and CRC in a data descriptor after the data."""

    def __init__(self) -> None:
        self.data = bytearray()

    def write(self, b: bytes) -> int:
        self.data += b
        return len(b)

    def flush(self) -> None:
        pass


def streamed_zip(members: list[tuple[str, bytes]]) -> bytes:
    out = _Stream()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:  # type: ignore[arg-type]
        for name, data in members:
            z.writestr(name, data)
    return bytes(out.data)


# -- an episode whose camera is one H.264 video ----------------------------------------------------------

VIDEO_FPS = 30
VIDEO_HW = (240, 320)
VIDEO_T0_NS = 1_732_700_000_000_000_000
VIDEO_STEP_NS = 100_000_000  # 10 Hz steps over a 30 fps video: step k shows frame 3k


@dataclass
class VideoEpisode:
    episode_id: str
    body: bytes  # zip: metadata.json, steps/000000.jsonl, the video
    video: bytes
    video_name: str  # its path in the episode dir, as the steps' uri
    camera: str
    times_s: list[float]  # each step's time in the video


def h264_mp4(n_frames: int, hw: tuple[int, int] = VIDEO_HW, fps: int = VIDEO_FPS) -> bytes:
    """An H.264 MP4 (yuv420p, libx264) of picture(0..n_frames-1), written with PyAV."""
    import av  # FFmpeg bindings: only the tests that make a video load them

    out = io.BytesIO()
    with av.open(out, "w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height = hw[1], hw[0]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "18", "preset": "ultrafast"}
        for i in range(n_frames):
            frame = av.VideoFrame.from_ndarray(picture(i, hw), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return out.getvalue()


def audio_only_mp4(seconds: float = 1.0) -> bytes:
    """An MP4 holding one AAC audio stream and no video stream."""
    import av  # FFmpeg bindings: only the tests that make a video load them

    out = io.BytesIO()
    rate = 16000
    with av.open(out, "w", format="mp4") as container:
        stream = container.add_stream("aac", rate=rate)
        samples = np.zeros((1, int(rate * seconds)), dtype=np.float32)
        frame = av.AudioFrame.from_ndarray(samples, format="fltp", layout="mono")
        frame.sample_rate = rate
        for packet in stream.encode(frame):
            container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return out.getvalue()


def video_episode_zip(n_steps: int = 8, *, camera: str = "front_camera", video: bytes | None = None,
                      episode_id: str = "video_ep_1") -> VideoEpisode:
    """A canonical episode (metadata.json + steps/000000.jsonl) whose steps all name one MP4 in
    `observation.<camera>.uri`; step k is k/10 s after the first, so it shows frame 3k of the video."""
    name = "video/front.mp4"
    video = video if video is not None else h264_mp4(3 * n_steps)
    steps = []
    for k in range(n_steps):
        steps.append({"timestamp_ns": VIDEO_T0_NS + k * VIDEO_STEP_NS,
                      "observation": {"robot_state": {"joint_positions": [round(0.1 * k, 3), -0.3, 0.2]},
                                      camera: {"uri": name}},
                      "action": {"command": [0.1, round(-0.05 * k, 3)], "source": "human_teleop_xr"},
                      "is_terminal": k == n_steps - 1})
    metadata = {"episode_id": episode_id, "xr_mode": "trainer", "control_role": "human_teleop",
                "environment_id": "lab", "tags": ["video"], "software": {"xr_app": "1.0"}, "schema_version": "1.1"}
    body = streamed_zip([("metadata.json", json.dumps(metadata).encode()),
                         ("steps/000000.jsonl", "".join(json.dumps(s) + "\n" for s in steps).encode()),
                         (name, video)])
    return VideoEpisode(episode_id, body, video, name, camera, [k * VIDEO_STEP_NS / 1e9 for k in range(n_steps)])


# -- bad media, as a producer gone wrong would send it ------------------------------------------------------

def truncated_jpeg(i: int, hw: tuple[int, int]) -> bytes:
    """A JPEG cut off half way (a capture interrupted while writing)."""
    data = jpeg(picture(i, hw))
    return data[: len(data) // 2]


def huge_png(width: int = 100_000, height: int = 100_000) -> bytes:
    """A small, valid-looking PNG whose header declares width x height pixels (a decompression bomb)."""
    import struct
    import zlib

    def chunk(kind: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    # a few rows of zeros compressed: a decoder that trusts the header would allocate 30 GB first
    idat = zlib.compress(b"\0" * (1 + 3 * width) * 4, 9)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")
