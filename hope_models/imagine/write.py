"""Model-imagined episodes as canonical RLDS dirs (the layout hope_models/sim/imagine.py writes,
without anything of the simulator: the observation block is rebuilt from the checkpoint's feature
spec and the metadata from the recorded episode the rollout started from)."""
from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hope_models.data.dataset_cache import PLAY_TAG
from hope_models.data.features import FeatureSpec
from hope_models.rlds.episode import Episode, Step
from hope_models.rlds.validation_report import episode_report
from hope_models.rlds.write_episode_dir import safe_episode_id, write_episode_dir

IMAGINED_TAG = "continuon.imagined"
ORIGIN = "imagined:model"
SOURCE = "model_planner"  # action.source, control_role and action_source of every step
# metadata keys copied from the start episode: what robot and setting the imagination is about
COPIED = ("schema_version", "robot_model", "robot_type", "xr_mode", "environment_id")
DROPPED_TAGS = (PLAY_TAG, "dart_noise")  # marks of how the start episode was recorded, not of this one
FRAME_URI = "blobs/step_%06d_rgb.npy"  # a camera world model's frames, named as the recordings name theirs
FRONT_LEVEL = 40  # of 255: a decoded scene pixel this far from the background's is the target's (camera_scene.py)


@dataclass
class ModelEpisode:
    start_episode: str
    start_step: int
    obs: list[np.ndarray] = field(default_factory=list)  # normalised
    label: list[np.ndarray] = field(default_factory=list)  # raw commands
    executed: list[np.ndarray] = field(default_factory=list)
    goal_distance: list[float] = field(default_factory=list)
    codes: list[np.ndarray] = field(default_factory=list)  # a camera world model's: each step's cell codes
    target: list[float] | None = None  # a camera world model's: where the start episode's target is (cells)
    layers: tuple[np.ndarray, np.ndarray] | None = None  # and its scene layer and background codes [G] (camera_scene)

    def add(self, obs, label, executed, dist: float, codes: np.ndarray | None = None) -> None:
        self.obs.append(np.array(obs, dtype=np.float64))
        self.label.append(np.array(label, dtype=np.float64))
        self.executed.append(np.array(executed, dtype=np.float64))
        self.goal_distance.append(dist)
        if codes is not None:
            self.codes.append(np.array(codes, dtype=np.int64))


def episode_id_for(seed: int, index: int) -> str:
    return safe_episode_id(f"imagined-model-s{seed:06d}-{index:04d}")


def _nested(spec: FeatureSpec, row: np.ndarray) -> dict[str, Any]:
    """A raw observation vector in spec order -> the observation block ({"robot_state": {...}, ...})."""
    out: dict[str, Any] = {}
    i = 0
    for f in spec.observation.fields:
        parts = f.path.split(".")[1:]  # without the leading "observation"
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        vals = [float(v) for v in row[i:i + f.size]]
        node[parts[-1]] = vals if f.size > 1 or len(parts) == 1 else vals[0]
        i += f.size
    return out


def _metadata(ep_id: str, start_meta: dict[str, Any], n: int, period_s: float, provenance: dict) -> dict:
    meta = {k: start_meta[k] for k in COPIED if k in start_meta}
    tags = [t for t in start_meta.get("tags", []) if isinstance(t, str) and t not in DROPPED_TAGS]
    meta.update({"episode_id": ep_id, "control_role": SOURCE, "action_source": SOURCE,
                 "tags": [*tags, IMAGINED_TAG, "imagined_model"],
                 "software": {"imagine": "hope_models.imagine.model_imagine"},
                 "total_steps": n, "duration_ms": int(round((n - 1) * period_s * 1000)), "provenance": provenance})
    meta.setdefault("schema_version", "1.1")
    return meta


def _frames(spec: FeatureSpec, ep: ModelEpisode, decode: Callable[[np.ndarray], np.ndarray] | None,
            blobs: Path) -> list[dict[str, Any]] | None:
    """A camera world model's episode: each step's frame decoded from its codes, saved as
    blobs/FRAME_URI (uint8 HWC .npy, as the recordings store them); the references the steps hold."""
    if not ep.codes:
        return None
    if decode is None or spec.frame is None:
        raise ValueError("imagined codes need the tokenizer's decoder and a camera in the feature spec")
    (blobs / "blobs").mkdir()
    front = None
    if ep.layers is not None:  # the scene's pixels that differ from the background are laid over the arm
        scene_px, bg_px = decode(np.stack(ep.layers))
        front = np.abs(scene_px.astype(np.int16) - bg_px.astype(np.int16)).max(-1) > FRONT_LEVEL
    refs = []
    for s in range(0, len(ep.codes), 256):
        frames = decode(np.stack(ep.codes[s:s + 256]))
        if front is not None:
            frames = np.where(front[None, ..., None], scene_px[None], frames)
        for t, img in enumerate(frames, start=s):
            np.save(blobs / (FRAME_URI % t), img, allow_pickle=False)
            refs.append({"uri": FRAME_URI % t, "width": int(img.shape[1]), "height": int(img.shape[0]),
                         "format": "npy_uint8_hwc"})
    return refs


def _with_frame(obs: dict[str, Any], path: str, ref: dict[str, Any]) -> dict[str, Any]:
    parts = path.split(".")[1:]  # without the leading "observation"
    node = obs
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = ref
    return obs


def write_model_episode(out: Path, ep: ModelEpisode, index: int, seed: int, spec: FeatureSpec,
                        start_meta: dict[str, Any], period_s: float, settings: dict[str, Any],
                        decode: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, Any]:
    """Validate (train profile) and write one episode; its summary for the result. decode: a camera
    world model's codes [n, G] -> frames [n, H, W, 3] uint8, written beside the steps."""
    ep_id = episode_id_for(seed, index)
    mean, std = np.asarray(spec.observation.mean), np.asarray(spec.observation.std)
    period_ns = int(round(period_s * 1e9))
    n = len(ep.obs)
    with tempfile.TemporaryDirectory(prefix=".imagined-", dir=out if out.is_dir() else None) as tmp:
        refs = _frames(spec, ep, decode, Path(tmp))
        steps = []
        for t in range(n):
            action = {"command": [float(v) for v in ep.label[t]], "source": SOURCE,
                      "executed_command": [float(v) for v in ep.executed[t]]}
            obs = _nested(spec, ep.obs[t] * std + mean)
            if refs is not None and spec.frame is not None:
                obs = _with_frame(obs, spec.frame.path, refs[t])
            steps.append(Step(observation=obs, action=action, reward=0.0, is_terminal=(t == n - 1),
                              step_metadata={"goal_distance": round(ep.goal_distance[t], 5)},
                              timestamp_ns=t * period_ns))
        start = {"episode_id": ep.start_episode, "step": ep.start_step,
                 **({"target_cells": ep.target} if ep.target is not None else {})}
        provenance = {"origin": ORIGIN, "imagined": {"method": "model", "seed": int(seed), "index": index,
                                                     "start": start, **settings}}
        episode = Episode(ep_id, _metadata(ep_id, start_meta, n, period_s, provenance), steps,
                          source=f"{ORIGIN}#{ep_id}", layout="sim", blob_root=tmp if refs is not None else None)
        report = episode_report(episode, "train")
        if not report["ok"]:
            raise RuntimeError(f"imagined episode {ep_id} fails the train profile: " + "; ".join(report["errors"][:3]))
        path = write_episode_dir(episode, out)
    return {"episode_id": ep_id, "path": str(path), "steps": n, "status": report["status"], "start": start,
            "final_goal_distance": round(ep.goal_distance[-1], 4)}
