"""A compiled dataset cache opened for reading: DatasetCache, and the layout it reads.

Readers map the step arrays (or, past a resident budget, read just the rows they need; see
DatasetCache), so training's memory does not grow with the dataset. cache.py keys and finds a
cache (load_or_build), cache_build.py writes one.

Layout of <cache_root>/<key>/:
    manifest.json   counts, dims, array shapes/dtypes, excluded episodes, fingerprints, build time
    spec.json       the feature spec with normalisation statistics
    episodes.json   one entry per included episode: id, source, steps, duration, rate, imagined, play
    steps.bin float32 [N, D_obs + D_act]  observation then action columns of each step; `obs`
                          and `act` are column views of it, so a window is one gather, not two
    t.bin    float64 [N]  seconds since the episode's first step
    frames.bin uint8 [N, H, W, 3]  the camera the tokenizer reads (the spec's frame), when there
                          is one: inline floats or frame files (.npy, JPEG, PNG, video) decoded
                          one at a time during the build and resized (see cameras.py)
    camera_<i>_<name>.bin  every other camera of the spec (`cameras`): colour uint8 [N, H, W, 3],
                          depth float32 metres [N, H, W, 1]; array `camera.<name>` in the manifest
    offsets.npy int64 [E+1]   imagined.npy bool [E]   play.npy bool [E]

Play episodes (is_play_episode) are unlabeled exploration: their actions are what was executed,
not what an expert would do, so world models and the VQ-VAE learn from them while behaviour
cloning (the fast_loop) must not (sampler.AnchorSampler's exclude_play). An episode is play when
its producer says so in the metadata: the tag "play" (the documented mark, docs/rlds.md; a real
robot's producer sets it), or provenance.sim.policy "play" (sim-demos --policy play), or when
every step's action.source is "sim_play" or "play". The metadata marks win because a producer
writes them once per episode; the per-step rule only catches copies whose metadata lost them.
"""
from __future__ import annotations

import json
import math
import mmap
import os
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.data.features import FeatureSpecError
from hope_models.data.row_access import HeadMapped, pread_rows
from hope_models.data.spec_request import load_spec

# 5: frame blobs (inference may now choose a frame it did not before); 6: play.npy. A format change
# changes every cache key (cache.cache_key), so older caches are rebuilt, never read without play.npy.
CACHE_FORMAT = "hope.dataset_cache/6"
PLAY_TAG = "play"
PLAY_SOURCES = ("sim_play", "play")  # action.source values of play steps
DEFAULT_RESIDENT_BUDGET_MB = 64  # step arrays larger than this are read with pread, not mapped


class CacheError(RuntimeError):
    """The cache cannot be built or opened; the message says which dataset or file and why."""


class DatasetCache:
    """Read-only view of a built cache: the step arrays plus the small per-episode tables.

    Access mode, chosen from `resident_budget_mb` (the share of the job's memory the data may
    take): "mmap" when the step arrays fit in it (random rows read straight from the mapping; its
    touched pages count in RSS but never exceed the arrays' size), "read" otherwise: t and then
    the leading rows of steps, as many as fit the budget, are read through mappings of just those
    heads, the other rows fetched with pread into small buffers (row_access.HeadMapped), so RSS
    stays within the budget however large the dataset is; the kernel's page cache still holds the
    hot data. `resident_bytes` is what the mappings can add to RSS. Both give identical values.
    """

    def __init__(self, path: Path, resident_budget_mb: float = DEFAULT_RESIDENT_BUDGET_MB):
        self.path = Path(path)
        try:
            self.manifest: dict[str, Any] = json.loads((self.path / "manifest.json").read_text(encoding="utf-8"))
            self.spec = load_spec(self.path / "spec.json")
            self.episodes: list[dict[str, Any]] = json.loads((self.path / "episodes.json").read_text(encoding="utf-8"))
            self.offsets = np.load(self.path / "offsets.npy", allow_pickle=False)
            self.imagined = np.load(self.path / "imagined.npy", allow_pickle=False)
            self.play = np.load(self.path / "play.npy", allow_pickle=False)
        except (OSError, ValueError, KeyError, FeatureSpecError) as exc:
            raise CacheError(f"{self.path}: not a readable dataset cache: {exc}") from None
        if self.manifest.get("format") != CACHE_FORMAT:
            raise CacheError(f"{self.path}: cache format {self.manifest.get('format')!r} is not {CACHE_FORMAT!r}")
        self.n_steps = int(self.manifest["steps"])
        self.n_episodes = int(self.manifest["episodes"])
        if (self.offsets.shape != (self.n_episodes + 1,) or int(self.offsets[-1]) != self.n_steps
                or self.imagined.shape != (self.n_episodes,) or self.play.shape != (self.n_episodes,)
                or len(self.episodes) != self.n_episodes):
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
        # every other camera, mapped up front so a damaged file is found when the cache opens
        self.cameras = {cam.name: self._map(f"camera.{cam.name}") for cam in self.spec.cameras}
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
        # Past the budget, t is mapped first (every window searches a block of it, for 8 bytes a
        # row), then as many leading rows of steps as the rest of the budget holds; a page is kept
        # for each mapping's last, partly used page.
        room = max(0, int(budget) - 2 * mmap.PAGESIZE)
        t_rows = min(self.n_steps, room // 8)
        x_rows = min(self.n_steps, (room - 8 * t_rows) // max(self.x.strides[0], 1))
        self.t_reader = HeadMapped(self._files["t"], self.t, self.n_steps if self.mode == "mmap" else t_rows)
        self.x_reader = HeadMapped(self._files["steps"], self.x, self.n_steps if self.mode == "mmap" else x_rows)
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
    @property
    def resident_bytes(self) -> int:
        """What reading windows (and, when mapped, frames) can add to RSS: the mapped rows (each
        mapping's last page may hold a few bytes more, inside the budget all the same)."""
        frames = self.frames.nbytes if self.frames is not None and self.frames_mode == "mmap" else 0
        return self.t_reader.resident_bytes + self.x_reader.resident_bytes + frames

    def t_block(self, first: np.ndarray, n: int, pad: float) -> np.ndarray:
        """t of rows first[b] .. first[b]+n-1 for each b, as [B, n]; rows outside 0..N-1 read `pad`."""
        return self.t_reader.blocks(first, n, pad)

    def x_rows(self, j: np.ndarray, first: np.ndarray | None = None, n: int = 0) -> np.ndarray:
        """Step rows (observation then action columns) at indices j [B, K] -> [B, K, D_obs + A], a copy.

        `first`/`n`, when given, promise that row b's indices lie in first[b] .. first[b]+n-1, which
        lets "read" mode fetch each anchor's rows past the mapped head with one pread.
        """
        return self.x_reader.rows(j, first, n)

    def frame_rows(self, j: np.ndarray) -> np.ndarray:
        if self.frames is None:
            raise CacheError(f"{self.path}: the feature spec has no frame feature")
        if self.frames_mode == "mmap":
            return self.frames[j]
        return pread_rows(self._files["frames"].fileno(), self.frames, j)

    def frame_block(self, lo: int, hi: int) -> np.ndarray:
        """Frames lo .. hi-1 in order, a writable copy; "read" mode fetches them with one pread, so a
        pass over every frame (a tokenizer's code table) does not leave the whole file resident."""
        if self.frames is None:
            raise CacheError(f"{self.path}: the feature spec has no frame feature")
        if not 0 <= lo <= hi <= self.n_steps:
            raise IndexError(f"frames {lo}..{hi} outside the cache's {self.n_steps}")
        if self.frames_mode == "mmap":
            return np.array(self.frames[lo:hi])
        row = self.frames.strides[0]
        raw = os.pread(self._files["frames"].fileno(), (hi - lo) * row, lo * row)
        return np.frombuffer(raw, dtype=self.frames.dtype).reshape(hi - lo, *self.frames.shape[1:]).copy()

    def block_rows(self, span_s: float, forward: bool = False) -> int:
        """Most rows any step needs to reach the latest step at or before t - span_s (backward) or
        at or before t + span_s (forward), itself included; computed once per span from t."""
        key = (float(span_s), forward)
        if key not in self._block_rows:
            worst = 1
            fd = self._files["t"].fileno()
            for s, e in zip(self.starts.tolist(), (self.ends + 1).tolist(), strict=True):
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


def is_play_episode(metadata: dict[str, Any], steps: Any = ()) -> bool:
    """Whether an episode is play (unlabeled exploration); the rule is in the module doc."""
    tags = metadata.get("tags")
    if isinstance(tags, list) and any(isinstance(t, str) and t.strip().lower() == PLAY_TAG for t in tags):
        return True
    provenance = metadata.get("provenance")
    sim = provenance.get("sim") if isinstance(provenance, dict) else None
    if isinstance(sim, dict) and sim.get("policy") == "play":
        return True
    actions = [getattr(s, "action", None) for s in steps]
    sources = [a.get("source") if isinstance(a, dict) else None for a in actions]
    return bool(sources) and all(src in PLAY_SOURCES for src in sources)


# A step stamped within a microsecond after a grid time counts as "at" it: grid times are computed
# in float seconds and must not miss a step that lands on them exactly.
WINDOW_EPS_S = 1e-6


def open_cache(path: str | Path, resident_budget_mb: float = DEFAULT_RESIDENT_BUDGET_MB) -> DatasetCache:
    return DatasetCache(Path(path), resident_budget_mb)
