"""Cameras in an episode: finding every frame file a step references, checking it, reading it.

A camera is an observation object with a `uri` naming an image, a video or a `.npy` frame, at any
depth (`observation.egocentric_video`, the Pi package's `observation.rgb` / `observation.depth`
attached by file name, `observation.media.rgb`, the XR app's `observation.video_frame`). What a
file holds is read from its bytes, never from its name or content type: the Continuon app writes
JPEG stills into `.mp4`-named files, and files its unimplemented native capture leaves empty.

A camera whose name says depth is a depth camera (uint16 millimetres -> float32 metres, one
channel); every other one is colour (uint8 RGB). Each frame is resized (area filter) to the spec's
frame size. A video referenced by several steps gives each step the frame nearest its time: the
step's clock minus the clock of the first step that references the same file.

One frame is decoded at a time; `read_camera` yields them so the cache build never holds an
episode's frames (a 10-minute session at 30 fps is 18,000 of them).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np

from hope_models.data.extract import _MISSING, EpisodeMismatch, _get
from hope_models.data.features import FrameFeature, camera_kind, frame_shape
from hope_models.data.frames import BlobFrameError, resolve_blob_uri
from hope_models.media import FrameInfo, MediaError, VideoFrames, decode_still, probe, sniff

# What a camera's URI may end in; the bytes decide what it is. Other files (WAVs, JSON, ...) are
# not cameras, and neither are objects whose name says they hold no picture.
CAMERA_SUFFIXES = (".npy", ".jpg", ".jpeg", ".png", ".mp4", ".m4v", ".mov", ".webm", ".mkv")
_NOT_A_PICTURE = ("audio", "mic", "segment", "mask", "normal", "flow", "lidar", "point", "thermal", "gaze")
VIDEO_KINDS = ("mp4", "webm")


def frame_uri(value: Any) -> str | None:
    """The URI of a frame reference (an object with a `uri`, or the URI string itself), else None."""
    if isinstance(value, dict):
        value = value.get("uri")
    return value if isinstance(value, str) and value else None


def camera_refs(observation: Any, prefix: str = "observation") -> dict[str, str]:
    """Dotted path -> URI of every object in the observation that references a camera frame."""
    out: dict[str, str] = {}
    if not isinstance(observation, dict):
        return out
    for key, value in observation.items():
        if not isinstance(key, str) or not isinstance(value, dict):
            continue
        path = f"{prefix}.{key}"
        if "uri" not in value:
            out.update(camera_refs(value, path))
            continue
        uri = frame_uri(value)
        if uri is None or not uri.lower().split("?")[0].endswith(CAMERA_SUFFIXES):
            continue
        if any(word in key.lower() for word in _NOT_A_PICTURE):
            continue
        out[path] = uri
    return out


@dataclass
class CameraCheck:
    """What one episode's camera gives: how many steps have a usable frame, in what format, or why not."""

    path: str
    kind: str  # "rgb" or "depth"
    steps: int  # steps checked
    usable: int = 0
    info: FrameInfo | None = None  # of the first usable frame
    problem: str | None = None  # the first step's reason when a frame is not usable
    blank: bool | None = None  # every fully decoded frame was flat / held no depth (None: none decoded)

    @property
    def ok(self) -> bool:
        return self.usable == self.steps and self.steps > 0

    @property
    def name(self) -> str:
        return self.path.removeprefix("observation.")

    def source(self, size: int) -> str | None:
        """What its frames are decoded from and into: "JPEG 480x640 -> 64x64" (None: none decodes)."""
        return None if self.info is None else self.info.describe(frame_shape(size, self.kind)[:2])

    def describe(self, size: int) -> str:
        """"egocentric_video: 12/12 frames, JPEG 480x640 -> 64x64", or why not."""
        line = f"{self.name}: {self.usable}/{self.steps} frames"
        if self.info is not None:
            line += f", {self.source(size)}"
            if self.kind == "depth":
                line += " (depth, metres)"
        if self.problem:
            line += f"; {self.problem}"
        if self.blank and self.usable:
            line += ("; blank: the frames checked hold " + ("no reading (all zeros" if self.kind == "depth" else
                                                            "one flat value (all zeros") +
                     " is what a recorder in mock mode or with a dropped camera saves)")
        return line


CHANNEL_ORDERS = ("rgb", "bgr")


def channel_order(step, path: str) -> str:
    """"bgr" when the step's reference says its colour frame is stored blue first, else "rgb"."""
    v = _get(step.observation, tuple(path.split(".")[1:]))
    order = v.get("channel_order", "rgb") if isinstance(v, dict) else "rgb"
    return order if order in CHANNEL_ORDERS else "rgb"


def _step_file(steps: list, i: int, path: str, blob_root: str | None) -> tuple[str, Any]:
    """(uri, local path) of step i's frame file; EpisodeMismatch names the step and what is wrong."""
    v = _get(steps[i].observation, tuple(path.split(".")[1:]))
    if v is _MISSING or v is None:
        raise EpisodeMismatch("no frame at this step", i, path)
    uri = frame_uri(v)
    if uri is None:
        raise EpisodeMismatch(f"not a frame reference (needs a 'uri' string, got {type(v).__name__})", i, path)
    try:
        return uri, resolve_blob_uri(uri, blob_root)
    except BlobFrameError as exc:
        raise EpisodeMismatch(str(exc), i, f"{path}.uri") from None


def check_camera(steps: list, path: str, blob_root: str | None, size: int, every_step: bool = True) -> CameraCheck:
    """Checks a camera: the first usable frame is decoded in full, the others' headers are read
    (`every_step`), or only the first and last step's are (spec inference over many episodes)."""
    kind = camera_kind(path)
    indices = range(len(steps)) if every_step else sorted({0, len(steps) - 1})
    check = CameraCheck(path, kind, len(indices))
    seen: dict[str, str | None] = {}  # uri -> None when usable, else why not
    last = indices[-1] if indices else -1
    for i in indices:
        try:
            uri, local = _step_file(steps, i, path, blob_root)
        except EpisodeMismatch as exc:
            check.problem = check.problem or str(exc)
            continue
        if uri not in seen:
            # the first usable frame and the last step's decode in full (a header can lie, and a
            # blank camera shows at both ends); the rest only have their headers read
            seen[uri] = _check_file(local, uri, kind, size, check, full=check.info is None or i == last)
        if seen[uri] is None:
            check.usable += 1
        else:
            check.problem = check.problem or f"step {i}: {seen[uri]}"
    return check


def _check_file(local, uri: str, kind: str, size: int, check: CameraCheck, full: bool) -> str | None:
    where = repr(uri)  # the media layer adds the local path
    try:
        info = probe(local, where)
        if full:
            if _is_video(local, where):
                with VideoFrames(local, where) as video:
                    img = next(iter(video.frames_at([0.0], frame_shape(size, kind)[:2], kind)))
            else:
                img = decode_still(local, frame_shape(size, kind)[:2], kind, where)
            # blank: a colour frame of one flat value, a depth frame with no reading at all (a
            # flat depth frame is a wall)
            flat = bool(img.max() == 0) if kind == "depth" else bool(img.min() == img.max())
            check.blank = flat if check.blank is None else (check.blank and flat)
            check.info = check.info or info
    except MediaError as exc:  # named by its URI alone: a verdict goes back to the producer
        return str(exc).replace(f" ({local})", "")
    except StopIteration:
        return f"{where}: the video has no frame"
    return None


def read_camera(steps: list, frame: FrameFeature, blob_root: str | None,
                sources: Counter | None = None) -> Iterator[np.ndarray]:
    """Every step's frame, in step order, resized to `frame.shape`; EpisodeMismatch names the step,
    the field and the file. Never a placeholder: one bad or missing file fails the episode.
    `sources` counts the frames by what they were decoded from ("JPEG 480x640")."""
    out_hw = frame.shape[:2]
    # every reference first: the cheap checks fail before any decode
    files = [_step_file(steps, i, frame.path, blob_root) for i in range(len(steps))]
    first_step: dict[str, int] = {}
    for i, (uri, _local) in enumerate(files):
        first_step.setdefault(uri, i)
    i = 0
    while i < len(files):
        uri, local = files[i]
        run_end = i + 1
        while run_end < len(files) and files[run_end][0] == uri:  # a slower camera or one video
            run_end += 1
        where = repr(uri)  # the media layer adds the local path
        try:
            if sources is not None:
                info = probe(local, where)
                sources[f"{info.format} {info.height}x{info.width}"] += run_end - i
            if _is_video(local, where):
                t0 = _clock(steps[first_step[uri]])
                times = [max(0.0, (_clock(steps[j]) - t0) / 1e9) for j in range(i, run_end)]
                with VideoFrames(local, where) as video:
                    got = 0
                    for img in video.frames_at(times, out_hw, frame.kind):
                        got += 1
                        yield img
                if got != len(times):
                    raise MediaError(f"{where} ({local}): gave {got} of the {len(times)} frames asked for")
            else:
                img = decode_still(local, out_hw, frame.kind, where)
                if frame.kind == "rgb" and channel_order(steps[i], frame.path) == "bgr":
                    img = np.ascontiguousarray(img[..., ::-1])
                for _ in range(i, run_end):
                    yield img
        except MediaError as exc:
            raise EpisodeMismatch(str(exc), i, f"{frame.path}.uri") from None
        i = run_end


def _is_video(local, where: str) -> bool:
    try:
        return sniff(local) in VIDEO_KINDS
    except FileNotFoundError:
        raise MediaError(f"{where} ({local}): file not found") from None
    except OSError as exc:
        raise MediaError(f"{where} ({local}): unreadable: {exc.strerror or exc}") from None


def _clock(step) -> int:
    return step.timestamp_ns if isinstance(step.timestamp_ns, int) else 0
