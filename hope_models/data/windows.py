"""Fixed-size windows cut by time, so a 10 Hz and a 50 Hz episode give windows of equal duration.

A window is K points on a regular time grid that ends at the anchor step's time; each point holds
the latest step at or before it (zero-order hold: causal, never a value from after the grid time
or after the anchor). Grid points before the episode's first step are masked and zero-filled.
All of it is vectorised over a batch of anchors (no per-anchor Python in "mmap" mode).

Scales: fast 50-100 ms (default 100 ms, K=5: a 20 ms grid, the control period), mid
1-10 s (default 2 s, K=20), strategic 60-600 s (default 60 s, K=60). Optional future targets for
the latent dynamics of mid_loop: the held values at anchor time + each horizon (and the held
frames, when frames are asked for).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from hope_models.data.dataset_cache import WINDOW_EPS_S as EPS_S
from hope_models.data.dataset_cache import DatasetCache

# scale -> (min duration s, max duration s, default duration s, default K)
SCALES: dict[str, tuple[float, float, float, int]] = {
    "fast": (0.05, 0.1, 0.1, 5),
    "mid": (1.0, 10.0, 2.0, 20),
    "strategic": (60.0, 600.0, 60.0, 60),
}
MAX_K = 4096


@dataclass(frozen=True)
class WindowSpec:
    scale: str
    duration_s: float
    k: int
    horizons_s: tuple[float, ...] = ()

    @property
    def grid_step_s(self) -> float:
        return self.duration_s / self.k

    @cached_property
    def lags(self) -> np.ndarray:
        """Seconds before the anchor of each grid point, oldest first; the last is 0. Read-only."""
        lags = np.arange(self.k - 1, -1, -1, dtype=np.float64) * self.grid_step_s
        lags.flags.writeable = False
        return lags

    @cached_property
    def lags_minus_eps(self) -> np.ndarray:
        out = self.lags - EPS_S
        out.flags.writeable = False
        return out

    def to_json_obj(self) -> dict:
        return {"scale": self.scale, "duration_s": self.duration_s, "k": self.k, "horizons_s": list(self.horizons_s)}


def window_spec(scale: str = "fast", duration_s: float | None = None, k: int | None = None,
                horizons_s: tuple[float, ...] | list[float] = ()) -> WindowSpec:
    """A validated window spec; out-of-range values raise ValueError naming the parameter."""
    if scale not in SCALES:
        raise ValueError(f"window scale {scale!r} is not one of {', '.join(SCALES)}")
    lo, hi, default_d, default_k = SCALES[scale]
    d = default_d if duration_s is None else duration_s
    if isinstance(d, bool) or not isinstance(d, (int, float)) or not math.isfinite(d) or not lo <= d <= hi:
        raise ValueError(f"duration_s={d!r} is outside the allowed range for the {scale} window: {lo:g}-{hi:g} s")
    n = default_k if k is None else k
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_K:
        raise ValueError(f"k={n!r} (grid points of the {scale} window) must be an integer in 1-{MAX_K}")
    hs = tuple(float(h) for h in horizons_s)
    for h in hs:
        if not math.isfinite(h) or h <= 0:
            raise ValueError(f"horizons_s contains {h!r}; each horizon must be a positive number of seconds")
    return WindowSpec(scale, float(d), n, hs)


@dataclass
class WindowBatch:
    obs: np.ndarray  # [B, K, D_obs] float32, normalised unless asked otherwise; 0 where masked
    act: np.ndarray  # [B, K, A] float32, the held action at each grid point (the last one is the
    #                  anchor's own action: a model fed past actions must drop it)
    mask: np.ndarray  # [B, K] bool, False before the episode's first step
    target_act: np.ndarray  # [B, A] the action taken at the anchor step
    anchors: np.ndarray  # [B] int64 step indices into the cache
    episodes: np.ndarray  # [B] int64 episode indices into the cache
    frames: np.ndarray | None = None  # [B, K, H, W, 3] uint8, when asked for and present
    future_obs: np.ndarray | None = None  # [B, H, D_obs] held values at anchor + horizon
    future_act: np.ndarray | None = None  # [B, H, A]
    future_mask: np.ndarray | None = None  # [B, H] bool, False past the episode's last step
    future_frames: np.ndarray | None = None  # [B, H, H_img, W_img, 3] uint8 frames held at anchor + horizon,
    #                                          when frames are asked for; 0 where future_mask is False
    codes: np.ndarray | None = None  # [B, K, G] the frozen tokenizer's codes of those frames, when a code
    #                                  table is given (then no frame is read); 0 where masked
    future_codes: np.ndarray | None = None  # [B, H, G] likewise at anchor + horizon


def _count_at_or_before(tb: np.ndarray, g: np.ndarray) -> np.ndarray:
    """For each row b and grid time g[b, k]: how many of the ascending tb[b, :] are <= g[b, k]."""
    if tb.shape[1] <= 16:  # a compare per column: numpy sums along a short last axis slowly
        count = (tb[:, :1] <= g).astype(np.int64)
        for c in range(1, tb.shape[1]):
            count += tb[:, c:c + 1] <= g
        return count
    if tb.shape[1] <= 64:  # one broadcast compare beats a loop for short blocks
        return (tb[:, None, :] <= g[:, :, None]).sum(axis=2)
    return np.stack([np.searchsorted(row, gk, side="right") for row, gk in zip(tb, g, strict=True)])


def _normalised(cache: DatasetCache, j: np.ndarray, normalize: bool, first: np.ndarray, n: int) -> np.ndarray:
    x = cache.x_rows(j, first, n)  # observation and action columns in one read
    if normalize:
        x *= cache.x_inv_std
        x -= cache.x_shift
    return x


def make_windows(cache: DatasetCache, anchors, spec: WindowSpec, *, normalize: bool = True,
                 frames: bool = False, codes: np.ndarray | None = None) -> WindowBatch:
    """Windows for a batch of anchor step indices (see the module doc for the grid rule).

    With `codes` (a [N, G] table of the frozen tokenizer's codes of every cache row,
    components/code_table.py) a window that asks for frames gets their codes instead: the table's
    rows at the same points, and no frame is read.

    The search for each grid point's step runs over a short block of t that ends at the anchor
    (as long as the densest stretch of the dataset needs), so it reads only memory next to the
    anchor and never a step after it. obs and act are views of one [B, K, D_obs + A] array.
    """
    a = np.asarray(anchors, dtype=np.int64)
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"anchors must be a non-empty 1-D array of step indices, got shape {a.shape}")
    if a.min() < 0 or a.max() >= cache.n_steps:
        raise ValueError(f"anchor indices must be within 0-{cache.n_steps - 1}")
    if frames and cache.frames is None:
        raise ValueError(f"{cache.path}: frames asked for, but the feature spec has no frame feature")
    ep = cache.episode_of(a)
    start = cache.starts[ep]
    n = cache.block_rows(float(spec.lags[0]))
    first = a - (n - 1)
    tb = cache.t_block(first, n, pad=-np.inf)
    # Rows of the previous episode read as -inf: "at or before" every grid time, so the count
    # below lands on them only for grid times before this episode, and those points are masked.
    tb[np.arange(n) < (start - first)[:, None]] = -np.inf
    g = tb[:, -1:] - spec.lags_minus_eps
    mask = g >= 0.0  # t is 0 at an episode's first step
    j = first[:, None] + (_count_at_or_before(tb, g) - 1)
    np.maximum(j, start[:, None], out=j)  # masked points: any in-episode row, zeroed below
    x = _normalised(cache, j, normalize, first, n)
    full = bool(mask.all())
    if not full:
        x[~mask] = 0.0
    d = cache.spec.obs_dim
    act = x[..., d:]
    batch = WindowBatch(x[..., :d], act, mask, act[:, -1], a, ep)  # the anchor's point is never masked
    if frames and codes is not None:
        batch.codes = np.asarray(codes[j])
        if not full:
            batch.codes[~mask] = 0
    elif frames:
        batch.frames = cache.frame_rows(j)
        if not full:
            batch.frames[~mask] = 0
    if spec.horizons_s:
        _add_futures(cache, batch, spec, tb[:, -1], normalize, frames, codes)
    return batch


def _add_futures(cache: DatasetCache, batch: WindowBatch, spec: WindowSpec, ta: np.ndarray,
                 normalize: bool, frames: bool = False, codes: np.ndarray | None = None) -> None:
    a, ep = batch.anchors, batch.episodes
    horizons = np.asarray(spec.horizons_s)
    n = cache.block_rows(float(horizons.max()), forward=True)
    tb = cache.t_block(a, n, pad=np.inf)
    tb[np.arange(n) > (cache.ends[ep] - a)[:, None]] = np.inf  # rows of the next episode
    tf = ta[:, None] + horizons
    j = a[:, None] + (_count_at_or_before(tb, tf + EPS_S) - 1)  # row a itself always counts
    fx = _normalised(cache, j, normalize, a, n)
    fmask = tf <= cache.durations[ep][:, None] + EPS_S
    if not fmask.all():
        fx[~fmask] = 0.0
    d = cache.spec.obs_dim
    batch.future_obs, batch.future_act, batch.future_mask = fx[..., :d], fx[..., d:], fmask
    if frames and codes is not None:
        batch.future_codes = np.asarray(codes[j])
        if not fmask.all():
            batch.future_codes[~fmask] = 0
    elif frames:
        batch.future_frames = cache.frame_rows(j)
        if not fmask.all():
            batch.future_frames[~fmask] = 0


class WindowLoader:
    """Iterates window batches of a sampler, building `chunk` batches per vectorised call.

    Batch b is still exactly make_windows(sampler.batch(b)); only the work is grouped, which
    spreads numpy's per-call cost over several batches. The sampler's cursor counts batches
    handed out, so its state_dict() resumes exactly after the last batch the caller received.
    """

    def __init__(self, cache: DatasetCache, sampler, spec: WindowSpec, *, chunk: int = 16,
                 normalize: bool = True, frames: bool = False, codes: np.ndarray | None = None):
        if chunk < 1:
            raise ValueError(f"chunk={chunk} must be >= 1")
        self.cache, self.sampler, self.spec = cache, sampler, spec
        self.chunk, self.normalize, self.frames, self.codes = chunk, normalize, frames, codes
        self._ready: list[WindowBatch] = []
        self._ready_from = -1  # batch index of _ready[0]

    def __iter__(self):
        return self

    def __next__(self) -> WindowBatch:
        b = self.sampler.cursor
        if not (self._ready_from <= b < self._ready_from + len(self._ready)):
            self._fill(b)
        self.sampler.cursor = b + 1
        return self._ready[b - self._ready_from]

    def _fill(self, b: int) -> None:
        parts = [self.sampler.batch(i) for i in range(b, b + self.chunk)]
        big = make_windows(self.cache, np.concatenate(parts), self.spec, normalize=self.normalize,
                           frames=self.frames, codes=self.codes)
        self._ready, self._ready_from = [], b
        lo = 0
        for p in parts:
            hi = lo + len(p)
            sl = slice(lo, hi)
            self._ready.append(WindowBatch(
                big.obs[sl], big.act[sl], big.mask[sl], big.target_act[sl], big.anchors[sl], big.episodes[sl],
                None if big.frames is None else big.frames[sl],
                None if big.future_obs is None else big.future_obs[sl],
                None if big.future_act is None else big.future_act[sl],
                None if big.future_mask is None else big.future_mask[sl],
                None if big.future_frames is None else big.future_frames[sl],
                None if big.codes is None else big.codes[sl],
                None if big.future_codes is None else big.future_codes[sl]))
            lo = hi
