"""Building a dataset cache: every episode streamed into flat files in a temp dir, then renamed.

Pass 1 (when the spec request leaves anything open) infers the feature spec (dataset_spec.py);
pass 2 reads every source one episode at a time, excludes with the reason each episode that does
not fit the spec, appends the rest to the step arrays and merges their normalisation statistics.
The manifest is written last and the dir renamed into place only when complete, so a crash never
leaves a half cache under a valid name. The layout is in dataset_cache.py.
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from hope_models.data.cameras import read_camera
from hope_models.data.dataset_cache import CACHE_FORMAT, CacheError, is_play_episode
from hope_models.data.dataset_spec import infer_dataset_spec
from hope_models.data.extract import EpisodeMismatch, field_matrix, group_matrix
from hope_models.data.features import FRAME_SHAPE, FeatureField, FeatureSpec, FrameFeature
from hope_models.data.frames import BlobFrameError, floats_to_uint8
from hope_models.data.running_stats import RunningStats
from hope_models.data.source import iter_sources, read_source
from hope_models.data.spec_request import SpecRequest, spec_from_request
from hope_models.durable import fsync_path
from hope_models.media import area_resize


@dataclass
class Excluded:
    episode_id: str
    source: str
    reason: str

    def as_dict(self) -> dict[str, str]:
        return {"episode_id": self.episode_id, "source": self.source, "reason": self.reason}


def _clean_stale_builds(root: Path) -> None:
    for d in root.glob(".building-*"):
        try:
            pid = int(d.name.split("-")[2])
        except (IndexError, ValueError):
            continue
        if pid != os.getpid() and not _pid_alive(pid):
            shutil.rmtree(d, ignore_errors=True)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def camera_arrays(spec: FeatureSpec) -> list[tuple[str, str, FrameFeature]]:
    """(array name, file name, camera) of every camera the cache stores; the tokenizer's is `frames`."""
    out = [("frames", "frames.bin", spec.frame)] if spec.frame is not None else []
    for i, cam in enumerate(spec.cameras):
        safe = re.sub(r"[^A-Za-z0-9_]+", "_", cam.name)[:48]
        out.append((f"camera.{cam.name}", f"camera_{i}_{safe}.bin", cam))
    return out


class _Writer:
    """Appends one episode's arrays at a time to the flat files of a cache being built; an episode
    whose frames fail half-way is cut off again (`mark` / `rollback`)."""

    def __init__(self, tmp: Path, spec: FeatureSpec):
        self.tmp = tmp
        names = {"steps": "steps.bin", "t": "t.bin"}
        names.update({name: file for name, file, _cam in camera_arrays(spec)})
        self.files: dict[str, BinaryIO] = {n: open(tmp / file, "wb") for n, file in names.items()}

    def append(self, name: str, arr: np.ndarray) -> None:
        self.files[name].write(np.ascontiguousarray(arr).tobytes())

    def mark(self) -> dict[str, int]:
        return {n: f.tell() for n, f in self.files.items()}

    def rollback(self, mark: dict[str, int]) -> None:
        for n, f in self.files.items():
            f.seek(mark[n])
            f.truncate()

    def close(self) -> None:
        for f in self.files.values():
            f.flush()
            os.fsync(f.fileno())
            f.close()


_FRAME_CHUNK = 64  # frames written per call: one decoded frame at a time in memory, few writes


def _write_camera(writer: _Writer, name: str, ep, cam: FrameFeature, sources: Counter) -> None:
    """One episode's frames of one camera, decoded one at a time and written in chunks; `sources`
    counts them by what they were decoded from."""
    if cam.source == "inline":
        raw = field_matrix(ep.steps, FeatureField(cam.path, math.prod(FRAME_SHAPE)), np.float32)
        try:
            frames = floats_to_uint8(raw).reshape((len(ep.steps), *FRAME_SHAPE))
        except BlobFrameError as exc:
            raise EpisodeMismatch(str(exc), None, cam.path) from None
        if frames.shape[1:] != cam.shape:
            frames = np.stack([area_resize(f, cam.shape[:2]) for f in frames])
        writer.append(name, frames)
        sources[f"inline floats {FRAME_SHAPE[0]}x{FRAME_SHAPE[1]}"] += len(frames)
        return
    chunk = np.empty((_FRAME_CHUNK, *cam.shape), dtype=np.dtype(cam.dtype))
    k = 0
    for img in read_camera(ep.steps, cam, ep.blob_root, sources):
        chunk[k] = img
        k += 1
        if k == _FRAME_CHUNK:
            writer.append(name, chunk)
            k = 0
    writer.append(name, chunk[:k])


def _episode_rows(ep, spec: FeatureSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t seconds, obs, act) of one episode, or EpisodeMismatch with the step and field."""
    steps = ep.steps
    if not steps:
        raise EpisodeMismatch("no steps")
    stamps = [s.timestamp_ns for s in steps]
    if len(steps) == 1 and stamps[0] is None:
        stamps = [0]  # a single step sits at t = 0 whatever the clock; time matters only between steps
    for i, ts in enumerate(stamps):
        if not isinstance(ts, int) or isinstance(ts, bool):
            raise EpisodeMismatch("no timestamp (windows are cut by time)", i, "timestamp_ns")
    ts = np.asarray(stamps, dtype=np.int64)
    back = np.flatnonzero(np.diff(ts) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise EpisodeMismatch(f"timestamp goes backwards ({ts[i]} ns after {ts[i - 1]} ns)", i, "timestamp_ns")
    t = (ts - ts[0]).astype(np.float64) / 1e9
    obs = group_matrix(steps, spec.observation).astype(np.float32)
    act = group_matrix(steps, spec.action).astype(np.float32)
    return t, obs, act


def build_cache(dataset: Path, root: Path, key: str, data_fp: str, request: SpecRequest,
                skip: Path | None = None) -> Path:
    """Pass 2 (after inference when needed): stream every episode into a temp dir, then rename."""
    started = time.perf_counter()
    root.mkdir(parents=True, exist_ok=True)
    _clean_stale_builds(root)
    if request.needs_inference:
        spec = infer_dataset_spec(dataset, request, skip)
    else:
        spec = spec_from_request(request)
    tmp = root / f".building-{key}-{os.getpid()}-{os.urandom(4).hex()}"
    tmp.mkdir()
    try:
        manifest = _stream_episodes(dataset, tmp, spec, skip)
        manifest.update({"format": CACHE_FORMAT, "fingerprint": key, "data_fingerprint": data_fp,
                         "dataset_dir": str(dataset), "build_seconds": round(time.perf_counter() - started, 3),
                         "built_at_unix": time.time()})
        # The manifest is written last: a dir without one is never mistaken for a cache.
        _write_json(tmp / "manifest.json", manifest)
        final = root / key
        try:
            os.rename(tmp, final)
        except OSError:
            if (final / "manifest.json").is_file():  # another process built it first
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                raise
        fsync_path(root)
        return final
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _place_episode(writer: _Writer, ep, spec: FeatureSpec, cameras: list[tuple[str, str, FrameFeature]],
                   sources: dict[str, Counter]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Appends one episode's rows and frames; on EpisodeMismatch nothing of it stays written."""
    mark = writer.mark()
    counted: dict[str, Counter] = {name: Counter() for name, _f, _c in cameras}
    try:
        t, obs, act = _episode_rows(ep, spec)
        for name, _file, cam in cameras:  # last: the cheap checks fail first
            _write_camera(writer, name, ep, cam, counted[name])
    except EpisodeMismatch:
        writer.rollback(mark)
        raise
    for name in counted:
        sources[name].update(counted[name])
    writer.append("steps", np.concatenate([obs, act], axis=1))
    writer.append("t", t)
    return t, obs, act


def _stream_episodes(dataset: Path, tmp: Path, spec: FeatureSpec, skip: Path | None) -> dict[str, Any]:
    writer = _Writer(tmp, spec)
    cameras = camera_arrays(spec)
    sources: dict[str, Counter] = {name: Counter() for name, _f, _c in cameras}
    obs_stats, act_stats = RunningStats(spec.obs_dim), RunningStats(spec.act_dim)
    offsets = [0]
    imagined: list[bool] = []
    play: list[bool] = []
    episodes: list[dict[str, Any]] = []
    excluded: list[Excluded] = []
    seen: dict[str, str] = {}
    try:
        for src in iter_sources(dataset, skip):
            for report in read_source(src):
                if report.skipped or not report.episodes:
                    reason = report.skip_reason or "; ".join(str(p) for p in report.problems[:3]) or "no episodes"
                    excluded.append(Excluded(Path(report.source).name, report.source, reason))
                for ep in report.episodes:
                    if ep.errors:
                        more = f" (+{len(ep.errors) - 1} more errors)" if len(ep.errors) > 1 else ""
                        excluded.append(Excluded(ep.episode_id, ep.source, f"reader: {ep.errors[0]}{more}"))
                        continue
                    if ep.episode_id in seen:
                        excluded.append(Excluded(ep.episode_id, ep.source,
                                                 f"duplicate episode_id (also in {seen[ep.episode_id]})"))
                        continue
                    try:
                        t, obs, act = _place_episode(writer, ep, spec, cameras, sources)
                    except EpisodeMismatch as exc:
                        excluded.append(Excluded(ep.episode_id, ep.source, str(exc)))
                        continue
                    seen[ep.episode_id] = ep.source
                    obs_stats.add(obs)
                    act_stats.add(act)
                    offsets.append(offsets[-1] + len(t))
                    is_imagined = ep.is_imagined
                    imagined.append(is_imagined)
                    is_play = is_play_episode(ep.metadata, ep.steps)
                    play.append(is_play)
                    dt = np.diff(t)
                    episodes.append({
                        "episode_id": ep.episode_id, "source": ep.source, "steps": len(t),
                        "duration_s": float(t[-1]),
                        "rate_hz": round(1.0 / float(np.median(dt)), 2) if dt.size and np.median(dt) > 0 else None,
                        "imagined": is_imagined,
                        "play": is_play,
                        "origin": _origin(ep.metadata),
                    })
    finally:
        writer.close()
    n = offsets[-1]
    if n == 0:
        reasons = "; ".join(f"{e.episode_id}: {e.reason}" for e in excluded[:5])
        raise CacheError(f"{dataset}: no episode fits the feature spec" + (f" ({reasons})" if reasons else ""))
    if not spec.observation.has_stats:
        spec.observation.mean, spec.observation.std = obs_stats.result(spec.std_floor)
    if not spec.action.has_stats:
        spec.action.mean, spec.action.std = act_stats.result(spec.std_floor)
    _write_json(tmp / "spec.json", spec.to_json_obj())
    _write_json(tmp / "episodes.json", episodes)
    _save_npy(tmp / "offsets.npy", np.asarray(offsets, dtype=np.int64))
    _save_npy(tmp / "imagined.npy", np.asarray(imagined, dtype=bool))
    _save_npy(tmp / "play.npy", np.asarray(play, dtype=bool))
    arrays = {
        "steps": {"file": "steps.bin", "dtype": "<f4", "shape": [n, spec.obs_dim + spec.act_dim]},
        "t": {"file": "t.bin", "dtype": "<f8", "shape": [n]},
    }
    for name, file, cam in cameras:
        arrays[name] = {"file": file, "dtype": cam.dtype, "shape": [n, *cam.shape], "path": cam.path, "kind": cam.kind,
                        "decoded_from": dict(sources[name].most_common())}
    return {"steps": n, "episodes": len(episodes), "obs_dim": spec.obs_dim, "act_dim": spec.act_dim,
            "imagined_episodes": int(sum(imagined)), "play_episodes": int(sum(play)), "arrays": arrays,
            "excluded": [e.as_dict() for e in excluded]}


def _origin(metadata: dict) -> str:
    provenance = metadata.get("provenance")
    return str(provenance.get("origin") or "") if isinstance(provenance, dict) else ""


def _write_json(path: Path, obj: Any) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=1)
        f.flush()
        os.fsync(f.fileno())


def _save_npy(path: Path, arr: np.ndarray) -> None:
    with open(path, "wb") as f:
        np.save(f, arr, allow_pickle=False)
        f.flush()
        os.fsync(f.fileno())
