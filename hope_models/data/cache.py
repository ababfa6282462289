"""A dataset compiled once into memory-mapped arrays, keyed by a content fingerprint.

Training reads windows from these arrays instead of JSON, so its memory does not grow with the
dataset: the build streams one episode at a time into flat files, and readers map them (or, past
a resident budget, read just the rows they need; see DatasetCache). The cache
dir is named by sha256(dataset file paths + contents, the spec request, the cache format), so it is
reused while the data is unchanged and rebuilt when any file changes. A build writes into a
`.building-*` temp dir and renames it into place only when complete (manifest written last), so
a crash never leaves a half cache under a valid name.

Layout of <cache_root>/<key>/:
    manifest.json   counts, dims, array shapes/dtypes, excluded episodes, fingerprints, build time
    spec.json       the feature spec with normalisation statistics
    episodes.json   one entry per included episode: id, source, steps, duration, rate, imagined
    steps.bin float32 [N, D_obs + D_act]  observation then action columns of each step; `obs`
                          and `act` are column views of it, so a window is one gather, not two
    t.bin    float64 [N]  seconds since the episode's first step
    frames.bin uint8 [N, H, W, 3]  only when the spec has a frame feature (inline floats or .npy
                          frame blobs, loaded step by step during the build; see frames.py)
    offsets.npy int64 [E+1]   imagined.npy bool [E]
"""
from __future__ import annotations

import hashlib
import json
import math
import mmap
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from hope_models.data.features import (
    EpisodeMismatch, EpisodeSignature, FeatureSpec, FeatureSpecError, RunningStats, SpecRequest,
    blob_frames, episode_signature, field_matrix, group_matrix, infer_spec, spec_from_request,
)
from hope_models.data.frames import BlobFrameError, floats_to_uint8
from hope_models.data.source import iter_sources, read_source
from hope_models.durable import fsync_path
from hope_models.rlds.discover import is_manifest, kind_from_name
from hope_models.rlds.episode import ERROR

CACHE_FORMAT = "hope.dataset_cache/5"  # 5: frame blobs (inference may now choose a frame it did not before)
# Spec inference reads an even sample of sources beyond this many: choosing fields is a vote that a
# few hundred episodes settle, and the build pass then checks every step of every episode anyway.
INFER_MAX_SOURCES = 200
DEFAULT_RESIDENT_BUDGET_MB = 64  # step arrays larger than this are read with pread, not mapped
# probe_dataset_spec reads at most this much, in a process that must stay small (the webapp)
PROBE_MAX_SOURCES = 20
PROBE_EPISODES = 8
PROBE_MAX_SOURCE_BYTES = 16 << 20  # parsed JSON takes several times its size


class CacheError(RuntimeError):
    """The cache cannot be built or opened; the message says which dataset or file and why."""


# -- fingerprints --------------------------------------------------------------------------------

def data_fingerprint(dataset_dir: Path, skip: Path | None = None) -> str:
    """sha256 over every file's relative path, size and contents (sorted; hidden entries skipped)."""
    h = hashlib.sha256()
    root = Path(dataset_dir)
    files = []
    for dirpath, dirnames, filenames in os.walk(root):
        d = Path(dirpath)
        dirnames[:] = sorted(n for n in dirnames if not n.startswith(".") and (skip is None or d / n != skip))
        files.extend(d / n for n in filenames if not n.startswith("."))
    for path in sorted(files, key=lambda p: p.relative_to(root).as_posix()):
        rel = path.relative_to(root).as_posix().encode("utf-8")
        size = path.stat().st_size
        h.update(len(rel).to_bytes(4, "little") + rel + size.to_bytes(8, "little"))
        with open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                h.update(chunk)
    return h.hexdigest()


def cache_key(data_fp: str, request: SpecRequest) -> str:
    h = hashlib.sha256()
    for part in (CACHE_FORMAT, data_fp, request.identity()):
        h.update(part.encode("utf-8") + b"\0")
    return h.hexdigest()[:32]


# -- the opened cache ----------------------------------------------------------------------------

class DatasetCache:
    """Read-only view of a built cache: the step arrays plus the small per-episode tables.

    Access mode, chosen from `resident_budget_mb` (the share of the job's memory the data may
    take): "mmap" when the step arrays fit in it (random rows read straight from the mapping; its
    touched pages count in RSS but never exceed the arrays' size), "read" otherwise (rows fetched
    with pread into small buffers, so RSS stays flat however large the dataset is; the kernel's
    page cache still holds the hot data). Both give identical values.
    """

    def __init__(self, path: Path, resident_budget_mb: float = DEFAULT_RESIDENT_BUDGET_MB):
        self.path = Path(path)
        try:
            self.manifest: dict[str, Any] = json.loads((self.path / "manifest.json").read_text(encoding="utf-8"))
            self.spec = FeatureSpec.load(self.path / "spec.json")
            self.episodes: list[dict[str, Any]] = json.loads((self.path / "episodes.json").read_text(encoding="utf-8"))
            self.offsets = np.load(self.path / "offsets.npy", allow_pickle=False)
            self.imagined = np.load(self.path / "imagined.npy", allow_pickle=False)
        except (OSError, ValueError, KeyError, FeatureSpecError) as exc:
            raise CacheError(f"{self.path}: not a readable dataset cache: {exc}") from None
        if self.manifest.get("format") != CACHE_FORMAT:
            raise CacheError(f"{self.path}: cache format {self.manifest.get('format')!r} is not {CACHE_FORMAT!r}")
        self.n_steps = int(self.manifest["steps"])
        self.n_episodes = int(self.manifest["episodes"])
        if (self.offsets.shape != (self.n_episodes + 1,) or int(self.offsets[-1]) != self.n_steps
                or self.imagined.shape != (self.n_episodes,) or len(self.episodes) != self.n_episodes):
            raise CacheError(f"{self.path}: episode tables disagree with the manifest")
        self._files: dict[str, Any] = {}
        self.x = self._map("steps")
        d = self.spec.obs_dim
        if self.x.shape[1] != d + self.spec.act_dim:
            raise CacheError(f"{self.path}: steps.bin has {self.x.shape[1]} columns, the spec needs "
                             f"{d} + {self.spec.act_dim}")
        self.obs = self.x[:, :d]  # [N, D_obs] view
        self.act = self.x[:, d:]  # [N, D_act] view
        self.t = self._map("t")
        self.frames = self._map("frames") if "frames" in self.manifest["arrays"] else None
        self.episode_ids = [e["episode_id"] for e in self.episodes]
        self.durations = np.array([e["duration_s"] for e in self.episodes], dtype=np.float64)
        obs_mean, obs_std, act_mean, act_std = self.spec.normalizer()
        # normalised = x * inv_std - mean * inv_std: two in-place ops per batch
        self.x_inv_std = (1.0 / np.concatenate([obs_std, act_std])).astype(np.float32)
        self.x_shift = (np.concatenate([obs_mean, act_mean]) * self.x_inv_std).astype(np.float32)
        self.starts = self.offsets[:-1]
        self.ends = self.offsets[1:] - 1  # index of each episode's last step
        budget = resident_budget_mb * (1 << 20)
        step_bytes = self.x.nbytes + self.t.nbytes
        self.mode = "mmap" if step_bytes <= budget else "read"
        self.frames_mode = "mmap" if self.frames is not None and step_bytes + self.frames.nbytes <= budget else "read"
        self._block_rows: dict[tuple[float, bool], int] = {}

    def _map(self, name: str) -> np.ndarray:
        desc = self.manifest["arrays"][name]
        dtype = np.dtype(desc["dtype"])
        shape = tuple(desc["shape"])
        file = self.path / desc["file"]
        expected = math.prod(shape) * dtype.itemsize
        try:
            size = file.stat().st_size
        except OSError as exc:
            raise CacheError(f"{file}: missing from the cache: {exc.strerror}") from None
        if size != expected:
            raise CacheError(f"{file}: {size} bytes, the manifest says {expected}; the cache is damaged")
        f = open(file, "rb")
        self._files[name] = f
        if size == 0:
            return np.zeros(shape, dtype=dtype)
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        return np.frombuffer(mm, dtype=dtype).reshape(shape)

    @property
    def fingerprint(self) -> str:
        return self.manifest["fingerprint"]

    def episode_of(self, idx: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.offsets, idx, side="right") - 1

    # -- random access ----------------------------------------------------------------------
    def t_block(self, first: np.ndarray, n: int, pad: float) -> np.ndarray:
        """t of rows first[b] .. first[b]+n-1 for each b, as [B, n]; rows outside 0..N-1 read `pad`."""
        if self.mode == "mmap":
            idx = first[:, None] + np.arange(n)
            out = self.t[np.clip(idx, 0, self.n_steps - 1)]
            out[(idx < 0) | (idx >= self.n_steps)] = pad
            return out
        raw = _pread_blocks(self._files["t"].fileno(), 8, self.n_steps, first, n, np.float64(pad).tobytes())
        return np.frombuffer(raw, dtype="<f8").reshape(len(first), n).copy()

    def x_rows(self, j: np.ndarray, first: np.ndarray | None = None, n: int = 0) -> np.ndarray:
        """Step rows (observation then action columns) at indices j [B, K] -> [B, K, D_obs + A], a copy.

        `first`/`n`, when given, promise that row b's indices lie in first[b] .. first[b]+n-1, which
        lets "read" mode fetch each anchor's rows with one pread.
        """
        if self.mode == "mmap":
            return self.x[j]
        fd = self._files["steps"].fileno()
        if first is not None and n <= 256:
            w = self.x.shape[1]
            pad = bytes(self.x.strides[0])
            block = np.frombuffer(_pread_blocks(fd, self.x.strides[0], self.n_steps, first, n, pad),
                                  dtype=self.x.dtype).reshape(-1, w)
            return block[j - first[:, None] + (np.arange(len(first)) * n)[:, None]]
        return _pread_rows(fd, self.x, j)

    def frame_rows(self, j: np.ndarray) -> np.ndarray:
        if self.frames is None:
            raise CacheError(f"{self.path}: the feature spec has no frame feature")
        if self.frames_mode == "mmap":
            return self.frames[j]
        return _pread_rows(self._files["frames"].fileno(), self.frames, j)

    def block_rows(self, span_s: float, forward: bool = False) -> int:
        """Most rows any step needs to reach the latest step at or before t - span_s (backward) or
        at or before t + span_s (forward), itself included; computed once per span from t."""
        key = (float(span_s), forward)
        if key not in self._block_rows:
            worst = 1
            fd = self._files["t"].fileno()
            for s, e in zip(self.starts.tolist(), (self.ends + 1).tolist()):
                # pread, not the mapping: this pass must not leave the whole of t resident
                t = np.frombuffer(os.pread(fd, (e - s) * 8, s * 8), dtype="<f8")
                i = np.arange(len(t))
                if forward:
                    j = np.searchsorted(t, t + span_s + WINDOW_EPS_S, side="right") - 1
                    worst = max(worst, int((j - i).max(initial=0)) + 1)
                else:
                    j = np.searchsorted(t, t - span_s + WINDOW_EPS_S, side="right") - 1
                    worst = max(worst, int((i - j + (j >= 0)).max(initial=1)))
            self._block_rows[key] = worst
        return self._block_rows[key]


# A step stamped within a microsecond after a grid time counts as "at" it: grid times are computed
# in float seconds and must not miss a step that lands on them exactly.
WINDOW_EPS_S = 1e-6


def _pread_blocks(fd: int, row_bytes: int, n_rows: int, first: np.ndarray, n: int, pad_row: bytes) -> bytes:
    parts = []
    pread = os.pread
    for f in first.tolist():
        lo, hi = max(f, 0), min(f + n, n_rows)
        data = pread(fd, (hi - lo) * row_bytes, lo * row_bytes) if hi > lo else b""
        if lo > f or f + n > hi:
            data = pad_row * (min(lo, f + n) - f) + data + pad_row * (f + n - max(hi, f))
        parts.append(data)
    return b"".join(parts)


def _pread_rows(fd: int, arr: np.ndarray, j: np.ndarray) -> np.ndarray:
    """arr[j] for the file behind arr, one pread per row."""
    row_bytes = arr.strides[0]
    pread = os.pread
    raw = b"".join([pread(fd, row_bytes, r * row_bytes) for r in j.ravel().tolist()])
    return np.frombuffer(raw, dtype=arr.dtype).reshape(j.shape + arr.shape[1:]).copy()


def open_cache(path: str | Path, resident_budget_mb: float = DEFAULT_RESIDENT_BUDGET_MB) -> DatasetCache:
    return DatasetCache(Path(path), resident_budget_mb)


# -- building ------------------------------------------------------------------------------------

@dataclass
class Excluded:
    episode_id: str
    source: str
    reason: str

    def as_dict(self) -> dict[str, str]:
        return {"episode_id": self.episode_id, "source": self.source, "reason": self.reason}


@dataclass
class CacheInfo:
    path: Path
    fingerprint: str  # the cache key: data + spec request + format
    data_fingerprint: str
    reused: bool
    build_seconds: float  # of this call's build (0 when reused); the original is in the manifest
    fingerprint_seconds: float
    notes: list[str] = field(default_factory=list)


def _spec_request(spec_path: str | Path | None) -> SpecRequest:
    return SpecRequest() if spec_path is None else SpecRequest.load(spec_path)


def load_or_build(dataset_dir: str | Path, cache_root: str | Path, spec_path: str | Path | None = None,
                  request: SpecRequest | None = None,
                  resident_budget_mb: float = DEFAULT_RESIDENT_BUDGET_MB) -> tuple[DatasetCache, CacheInfo]:
    """Open the cache of this dataset + spec, building it first if the data changed or it never existed."""
    dataset = Path(dataset_dir).resolve()
    root = Path(cache_root).resolve()
    if not dataset.is_dir():
        raise CacheError(f"{dataset}: dataset dir not found")
    if request is None:
        request = _spec_request(spec_path)
    started = time.perf_counter()
    skip = root if root.is_relative_to(dataset) else None
    data_fp = data_fingerprint(dataset, skip)
    key = cache_key(data_fp, request)
    fp_seconds = time.perf_counter() - started
    final = root / key
    notes: list[str] = []
    if final.is_dir():
        try:
            return open_cache(final, resident_budget_mb), CacheInfo(final, key, data_fp, True, 0.0, fp_seconds)
        except CacheError as exc:  # damaged (disk trouble, manual edits): rebuild it, say so
            notes.append(f"rebuilt a damaged cache: {exc}")
            shutil.rmtree(final, ignore_errors=True)
    t0 = time.perf_counter()
    build_cache(dataset, root, key, data_fp, request, skip)
    build_s = time.perf_counter() - t0
    return open_cache(final, resident_budget_mb), CacheInfo(final, key, data_fp, False, build_s, fp_seconds, notes)


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


def _signatures(reports, problems: list[str] | None = None) -> list[EpisodeSignature]:
    """Signatures of the usable episodes of these source reports (`problems` collects why the
    others are not)."""
    signatures: list[EpisodeSignature] = []
    for report in reports:
        for ep in report.episodes:
            if not ep.errors and ep.steps:
                signatures.append(episode_signature(ep.episode_id, ep.steps, ep.blob_root))
            elif problems is not None:
                problems.append(str(ep.errors[0]) if ep.errors else f"{report.source}: episode {ep.episode_id} "
                                                                    "has no steps")
        if problems is not None:
            problems.extend(str(x) for x in report.problems if x.severity == ERROR)
    return signatures


def infer_dataset_spec(dataset: Path, request: SpecRequest, skip: Path | None = None) -> FeatureSpec:
    """Pass 1: episode signatures (first/last step) from the sources, then choose fields."""
    sources = list(iter_sources(dataset, skip))
    sample = sources
    if len(sources) > INFER_MAX_SOURCES:
        stride = len(sources) / INFER_MAX_SOURCES
        sample = [sources[int(i * stride)] for i in range(INFER_MAX_SOURCES)]
    signatures = _signatures(report for src in sample for report in read_source(src))
    try:
        spec = infer_spec(signatures, request)
    except FeatureSpecError as exc:
        raise FeatureSpecError(f"{dataset}: {exc}") from None
    if sample is not sources:
        spec.notes.append(f"fields inferred from an even sample of {len(sample)} of {len(sources)} sources")
    return spec


def probe_dataset_spec(data: str | Path, request: SpecRequest | None = None) -> FeatureSpec | None:
    """The feature spec of the first few usable episodes of `data` (a dataset dir, an episode dir
    or an episode file), read as the cache build reads them, torch-free and in bounded time.

    It lets a run request be refused at the door (registry/run_request.py) when its path holds no
    usable episode, and its memory be estimated from the dims the build will most likely infer (the
    build votes over up to INFER_MAX_SOURCES sources). FeatureSpecError names the path and why; None
    when every source it looked at is larger than PROBE_MAX_SOURCE_BYTES (not read here: the
    training job's own checks still apply)."""
    data = Path(data)
    if data.is_dir():
        sources = iter_sources(data)
    elif data.is_file() and kind_from_name(data.name) is not None and not is_manifest(data.name):
        sources = iter([data])
    else:
        raise FeatureSpecError(f"{data}: not a dataset (an RLDS dataset dir, an episode dir, or an episode file: "
                               ".json, .jsonl, TFRecord or .mcap)")
    problems: list[str] = []
    signatures: list[EpisodeSignature] = []
    looked = too_big = 0
    try:
        for src in sources:
            if looked >= PROBE_MAX_SOURCES or len(signatures) >= PROBE_EPISODES:
                break
            looked += 1
            if _source_bytes(src) > PROBE_MAX_SOURCE_BYTES:
                too_big += 1
                continue
            signatures += _signatures(read_source(src), problems)
    except OSError as exc:
        raise FeatureSpecError(f"{data}: cannot read it: {exc.strerror or exc}") from None
    if not signatures:
        if looked and too_big == looked:
            return None
        if not looked:
            raise FeatureSpecError(f"{data}: no episode files in it (.json, .jsonl, TFRecord or .mcap)")
        why = f": {problems[0]}" if problems else ""
        raise FeatureSpecError(f"{data}: no usable episode in the first {looked} source(s){why}")
    try:
        return infer_spec(signatures, request)
    except FeatureSpecError as exc:
        raise FeatureSpecError(f"{data}: {exc}") from None


def _source_bytes(src: Path) -> int:
    """What reading `src` parses: its episode files, not the frame blobs it loads one at a time."""
    if not src.is_dir():
        return src.stat().st_size
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(src) for f in files
               if kind_from_name(f) is not None)


class _Writer:
    """Appends one episode's arrays at a time to the flat files of a cache being built."""

    def __init__(self, tmp: Path, spec: FeatureSpec):
        self.tmp = tmp
        self.names = ["steps", "t"] + (["frames"] if spec.frame else [])
        self.files: dict[str, BinaryIO] = {n: open(tmp / f"{n}.bin", "wb") for n in self.names}

    def append(self, name: str, arr: np.ndarray) -> None:
        self.files[name].write(np.ascontiguousarray(arr).tobytes())

    def close(self) -> None:
        for f in self.files.values():
            f.flush()
            os.fsync(f.fileno())
            f.close()


def _episode_rows(ep, spec: FeatureSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """(t seconds, obs, act, frames) of one episode, or EpisodeMismatch with the step and field."""
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
    frames = None
    if spec.frame is not None and spec.frame.source == "blob":
        frames = blob_frames(steps, spec.frame, ep.blob_root)  # last: the cheap checks fail first
    elif spec.frame is not None:
        raw = field_matrix(steps, spec.frame, np.float32)
        try:
            frames = floats_to_uint8(raw).reshape((len(steps), *spec.frame.shape))
        except BlobFrameError as exc:
            raise EpisodeMismatch(str(exc), None, spec.frame.path) from None
    return t, obs, act, frames


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


def _stream_episodes(dataset: Path, tmp: Path, spec: FeatureSpec, skip: Path | None) -> dict[str, Any]:
    writer = _Writer(tmp, spec)
    obs_stats, act_stats = RunningStats(spec.obs_dim), RunningStats(spec.act_dim)
    offsets = [0]
    imagined: list[bool] = []
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
                        t, obs, act, frames = _episode_rows(ep, spec)
                    except EpisodeMismatch as exc:
                        excluded.append(Excluded(ep.episode_id, ep.source, str(exc)))
                        continue
                    seen[ep.episode_id] = ep.source
                    writer.append("steps", np.concatenate([obs, act], axis=1))
                    writer.append("t", t)
                    if frames is not None:
                        writer.append("frames", frames)
                    obs_stats.add(obs)
                    act_stats.add(act)
                    offsets.append(offsets[-1] + len(t))
                    is_imagined = ep.is_imagined
                    imagined.append(is_imagined)
                    dt = np.diff(t)
                    episodes.append({
                        "episode_id": ep.episode_id, "source": ep.source, "steps": len(t),
                        "duration_s": float(t[-1]),
                        "rate_hz": round(1.0 / float(np.median(dt)), 2) if dt.size and np.median(dt) > 0 else None,
                        "imagined": is_imagined,
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
    arrays = {
        "steps": {"file": "steps.bin", "dtype": "<f4", "shape": [n, spec.obs_dim + spec.act_dim]},
        "t": {"file": "t.bin", "dtype": "<f8", "shape": [n]},
    }
    if spec.frame is not None:
        arrays["frames"] = {"file": "frames.bin", "dtype": "|u1", "shape": [n, *spec.frame.shape]}
    return {"steps": n, "episodes": len(episodes), "obs_dim": spec.obs_dim, "act_dim": spec.act_dim,
            "imagined_episodes": int(sum(imagined)), "arrays": arrays,
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
