"""Camera frames a producer writes as files beside its steps, attached to the steps as blob references.

Two producers keep their frames out of the step JSON:

    Pi runtime   `<ep>/episode.json` plus `step_%04d_rgb.npy` (uint8 HxWx3) and `step_%04d_depth.npy`
                 (uint16 mm) per step (continuonbrain/recording/arm_episode_recorder.py); the step
                 says only `rgb_shape`/`depth_shape`, and upstream's reader pairs file and step by
                 the step's position in the list (continuonbrain/aina_impl/dataset.py:
                 `ep_path / f"step_{step_idx:04d}_rgb.npy"` for `episode["steps"][step_idx]`).
                 `attach_pi_files` sets `observation.rgb` / `observation.depth` =
                 {"uri": "step_0003_rgb.npy", "found_by": "file_name"} by that position; the rgb
                 reference also says `"channel_order": "bgr"`: the runtime's OAK-D camera hands it
                 getCvFrame()'s BGR array (continuonbrain/sensors/oak_depth.py), saved as it is.
    XR app       `observation.videoFrameId` = "frame_<ms>_<i>" naming `<id>.jpg`, written to a
                 `video_frames/` dir that by default sits beside the episode dir, not in it
                 (apps/continuonxr/.../trainer/TrainerRldsExtensions.kt), so a zip of the episode
                 dir seldom holds it. `attach_frame_ids` sets `observation.video_frame` (and
                 `depth_frame` for depth_frame_id) = {"uri": "video_frames/<id>.jpg", "found_by":
                 "frame_id"} when the file is in the episode dir (in video_frames/ or beside the steps).

The references then go the way of every blob (write_episode_dir.blob_refs): checked, copied into the
stored episode's blobs/, named in a warning when missing. A key the producer already set is never
overwritten (a warning says so); one we set earlier (`found_by`) is left as it is, so reading a
stored episode again changes nothing. What is absent is said once per kind, with a count, never
once per step. The readers call these (read_single_json for episode.json, read_episode_dir for a
non-canonical dir), so validate, ingest and the upload path all see the same episode.
"""
from __future__ import annotations

import os
from pathlib import Path

from .episode import Episode

PI_FILES = (("rgb", "step_{:04d}_rgb.npy", "rgb_shape"), ("depth", "step_{:04d}_depth.npy", "depth_shape"))
PI_CHANNEL_ORDER = {"rgb": "bgr"}  # what the Pi runtime's camera writes into step_*_rgb.npy
BY_NAME = "file_name"
XR_IDS = (("video_frame", "video_frame_id"), ("depth_frame", "depth_frame_id"))
BY_ID = "frame_id"
XR_FRAMES_DIR = "video_frames"
XR_SUFFIX = ".jpg"


def _names(directory: Path) -> set[str]:
    try:
        return {e.name for e in os.scandir(directory) if e.is_file(follow_symlinks=False)}
    except OSError:
        return set()


def _ours(value: object, found_by: str) -> bool:
    return isinstance(value, dict) and value.get("found_by") == found_by


def attach_pi_files(ep: Episode, root: Path) -> None:
    """The Pi's per-step .npy files in `root` (the dir of episode.json) attached by list position."""
    names = _names(root)
    for key, pattern, shape_key in PI_FILES:
        lacking: list[int] = []
        clash: list[int] = []
        attached = 0
        for i, step in enumerate(ep.steps):
            name = pattern.format(i)
            if name not in names:
                lacking.append(i)
                continue
            existing = step.observation.get(key)
            if _ours(existing, BY_NAME):
                attached += 1
            elif existing is not None:
                clash.append(i)
            else:
                ref = {"uri": name, "found_by": BY_NAME}
                if key in PI_CHANNEL_ORDER:
                    ref["channel_order"] = PI_CHANNEL_ORDER[key]
                step.observation[key] = ref
                attached += 1
        field = f"observation.{key}"
        if clash:
            ep.warn(f"{len(clash)} step(s) already have observation.{key}, so the file beside them "
                    f"({pattern.format(clash[0])} for step {clash[0]}) is not attached", step=clash[0], field=field)
        if attached or clash:
            if lacking:
                ep.warn(f"{len(lacking)} of {len(ep.steps)} steps have no {pattern.format(lacking[0])} "
                        f"(first: step {lacking[0]}); the others are attached", step=lacking[0], field=field)
        elif lacking:
            declared = [i for i, s in enumerate(ep.steps) if shape_key in s.observation]
            if declared:
                ep.warn(f"{len(declared)} step(s) declare observation.{shape_key} but no "
                        f"{pattern.format(declared[0])}-style file is beside {root.name or 'episode.json'} "
                        "(a package made without images?)", step=declared[0], field=field)
        extra = sorted(n for n in names if _beyond(n, pattern, len(ep.steps)))
        if extra:
            ep.warn(f"{len(extra)} file(s) name a step the episode does not have, e.g. {extra[0]} "
                    f"({len(ep.steps)} steps); not attached", field=field)


def _beyond(name: str, pattern: str, steps: int) -> bool:
    prefix, suffix = pattern.split("{:04d}")
    middle = name[len(prefix):len(name) - len(suffix)] if name.startswith(prefix) and name.endswith(suffix) else ""
    return middle.isdigit() and int(middle) >= steps


def attach_frame_ids(ep: Episode, root: Path) -> None:
    """The XR app's frame ids matched to `<id>.jpg` in `root/video_frames/` or `root`."""
    where = {"": _names(root), XR_FRAMES_DIR + "/": _names(root / XR_FRAMES_DIR)}
    for key, id_key in XR_IDS:
        ids = 0
        lacking: list[int] = []
        clash: list[int] = []
        for i, step in enumerate(ep.steps):
            frame_id = step.observation.get(id_key)
            if not isinstance(frame_id, str) or not frame_id:
                continue
            ids += 1
            name = frame_id + XR_SUFFIX
            found = next((prefix + name for prefix in (XR_FRAMES_DIR + "/", "") if name in where[prefix]), None)
            if found is None:
                lacking.append(i)
                continue
            existing = step.observation.get(key)
            if existing is None:
                step.observation[key] = {"uri": found, "found_by": BY_ID}
            elif not _ours(existing, BY_ID):
                clash.append(i)
        field = f"observation.{id_key}"
        if lacking and len(lacking) == ids:
            ep.warn(f"{ids} frame ids, no frame files in the upload (the XR app writes them to "
                    f"{XR_FRAMES_DIR}/ beside the episode dir)", field=field)
        elif lacking:
            ep.warn(f"{len(lacking)} of {ids} frame ids have no {XR_FRAMES_DIR}/<id>{XR_SUFFIX} in the upload "
                    f"(first: step {lacking[0]}); the others are attached", step=lacking[0], field=field)
        if clash:
            ep.warn(f"{len(clash)} step(s) already have observation.{key}, so their frame file is not "
                    "attached", step=clash[0], field=f"observation.{key}")


__all__ = ["BY_ID", "BY_NAME", "attach_frame_ids", "attach_pi_files"]
