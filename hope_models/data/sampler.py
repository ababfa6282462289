"""Batches of anchor steps that a restarted job draws exactly as an uninterrupted one would.

Batch b is a pure function of (seed, b): each pool (real, imagined) is walked through per-epoch
permutations from `default_rng([seed, split, pool, epoch])`, and the number of imagined anchors
before batch b is floor(b * batch_size * ratio) in exact fractions. So the sampler's whole
position is its cursor, and `state_dict()`/`load_state_dict()` carry it in a checkpoint.

Each pool is an int32 array of its eligible step indices plus one shuffled copy per epoch, 8 bytes
per step in all; the sampler never touches the dataset itself.

Anchors by block (`anchors_per_block` k > 1, opt-in; the default 1 draws every anchor on its
own): the pool is cut into blocks of consecutive eligible steps, as many as one cheap read of the
cache covers (row_access.MERGE_GAP_BYTES of step rows: 16 steps of 26 floats), and each epoch is
still a permutation of the pool, drawn so that each run of k positions comes from one block (each
block's steps shuffled and cut into k-tuples, the tuples shuffled). So every anchor is still drawn
once an epoch, but a batch of 64 holds 16 blocks of 4 nearby anchors instead of 64 independent
ones, and a cache read past its resident budget fetches each block with one pread instead of
four (1.4-1.8x the batches/s there). Not the default: at equal steps it trained a fast_loop to a
7-17% higher validation loss (docs/benchmarks.md), and a fast_loop step costs 100-200x the
sampling of its batch. The state records the grouping; a state of another grouping is refused.

exclude_play drops play episodes (unlabeled exploration, dataset_cache.is_play_episode) from both
pools: a component that clones the recorded actions (the fast_loop) must never see them as targets.
A dataset with nothing but play then has nothing to clone, and the sampler says so.

The validation split is by episode: an episode is in it when the hash of its id falls under
`val_fraction`, so adding episodes never moves an existing one from training into validation
(a model is never validated on an episode an earlier model of the same data trained on). A small
dataset gets a floor: at least min(MIN_VAL_EPISODES, a third of its episodes) are held out, the ones
with the smallest hashes, because a "validation" of one episode decides nothing (10 demos at 0.1
would otherwise hold out 0-2, often 1). Adding episodes can only move a floor episode back into
training, never the other way.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from fractions import Fraction

import numpy as np

from hope_models.data.dataset_cache import DatasetCache
from hope_models.data.row_access import MERGE_GAP_BYTES

STATE_FORMAT = "hope.anchor_sampler/1"
SPLITS = {"train": 0, "val": 1, "all": 2}
_EPS = 1e-6


MIN_VAL_EPISODES = 3


def _episode_hash(episode_id: str) -> float:
    return int.from_bytes(hashlib.sha256(episode_id.encode("utf-8")).digest()[:8], "big") / 2**64


def is_validation_episode(episode_id: str, val_fraction: float) -> bool:
    """The hash rule alone (validation_mask adds the small-dataset floor)."""
    return _episode_hash(episode_id) < val_fraction


def validation_mask(episode_ids, val_fraction: float) -> np.ndarray:
    """bool [E]: which episodes are held out (the hash rule plus the floor of the module doc)."""
    hashes = np.array([_episode_hash(e) for e in episode_ids], dtype=np.float64)
    val = hashes < val_fraction
    floor = min(MIN_VAL_EPISODES, len(hashes) // 3) if val_fraction > 0 else 0
    if int(val.sum()) < floor:
        val[np.argsort(hashes, kind="stable")[:floor]] = True
    return val


def split_episodes(cache: DatasetCache, split: str, val_fraction: float) -> np.ndarray:
    """Indices of the cache's episodes in the split."""
    if split not in SPLITS:
        raise ValueError(f"split={split!r} is not one of {', '.join(SPLITS)}")
    if split == "all":
        return np.arange(cache.n_episodes)
    val = validation_mask(cache.episode_ids, val_fraction)
    return np.flatnonzero(val if split == "val" else ~val)


class _Pool:
    """Eligible anchor steps, walked through one shuffled copy per epoch (grouped in k-tuples of
    one block each when `group` (k, block rows) has k > 1)."""

    def __init__(self, starts: np.ndarray, lengths: np.ndarray, seed_key: list[int], shuffle: bool,
                 group: tuple[int, int] = (1, 1)):
        keep = lengths > 0
        total = int(lengths[keep].sum())
        # int32 halves the memory; caches beyond 2^31 steps are far past what a Pi holds
        dtype = np.int32 if int(starts.max(initial=0)) + total < 2**31 else np.int64
        self.steps = np.concatenate([np.arange(s, s + n, dtype=dtype)
                                     for s, n in zip(starts[keep], lengths[keep], strict=True)]
                                    or [np.empty(0, dtype=dtype)])
        self.size = total
        self.seed_key = seed_key
        self.shuffle = shuffle
        self.group = group
        self._epochs: OrderedDict[int, np.ndarray] = OrderedDict()

    def _order(self, epoch: int) -> np.ndarray:
        if not self.shuffle:
            return self.steps
        if epoch in self._epochs:
            return self._epochs[epoch]
        rng = np.random.default_rng([*self.seed_key, epoch])
        if self.group[0] > 1:
            order = _grouped_order(self.steps, *self.group, rng)
        else:
            order = self.steps.copy()
            rng.shuffle(order)
        self._epochs[epoch] = order
        while len(self._epochs) > 2:  # a batch spans at most two epochs
            self._epochs.popitem(last=False)
        return order

    def take(self, first: int, count: int) -> np.ndarray:
        """Step indices at pool positions first .. first+count-1 of the endless epoch sequence."""
        epoch, within = divmod(first, self.size) if self.size else (0, 0)
        if within + count <= self.size:  # the usual case: a slice of one epoch's order
            return self._order(epoch)[within:within + count]
        out = np.empty(count, dtype=np.int64)
        done = 0
        while done < count:
            epoch, within = divmod(first + done, self.size)
            n = min(count - done, self.size - within)
            out[done:done + n] = self._order(epoch)[within:within + n]
            done += n
        return out


def _grouped_order(steps: np.ndarray, k: int, block_rows: int, rng: np.random.Generator) -> np.ndarray:
    """A permutation of `steps` whose runs of k (from position 0) each lie in one block of
    `block_rows` (a multiple of k) consecutive steps; only the last run may be shorter."""
    full = len(steps) // block_rows * block_rows
    blocks = rng.permuted(steps[:full].reshape(-1, block_rows), axis=1)  # each block's steps shuffled
    tail = rng.permutation(steps[full:])  # the last, partial block
    cut = len(tail) // k * k
    tuples = np.concatenate([blocks.reshape(-1), tail[:cut]]).reshape(-1, k)
    # the one short tuple last: before it, every run of k stays aligned with the batches
    return np.concatenate([tuples[rng.permutation(len(tuples))].reshape(-1), tail[cut:]])


class AnchorSampler:
    def __init__(self, cache: DatasetCache, batch_size: int, seed: int = 0, imagined_ratio: float = 0.0,
                 split: str = "train", val_fraction: float = 0.1, min_history_s: float = 0.0,
                 horizon_s: float = 0.0, shuffle: bool = True, exclude_play: bool = False,
                 anchors_per_block: int = 1):
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size={batch_size!r} must be a positive integer")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed={seed!r} must be a non-negative integer")
        if not 0.0 <= imagined_ratio <= 1.0:
            raise ValueError(f"imagined_ratio={imagined_ratio!r} must be within [0, 1]")
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"val_fraction={val_fraction!r} must be within [0, 1)")
        if min_history_s < 0 or horizon_s < 0:
            raise ValueError("min_history_s and horizon_s must be >= 0")
        if isinstance(anchors_per_block, bool) or not isinstance(anchors_per_block, int) or anchors_per_block < 1:
            raise ValueError(f"anchors_per_block={anchors_per_block!r} must be a positive integer")
        self.cache = cache
        self.batch_size = batch_size
        self.seed = seed
        self.ratio = Fraction(str(imagined_ratio))
        self._ratio_num, self._ratio_den = self.ratio.numerator, self.ratio.denominator
        self.split = split
        self.val_fraction = float(val_fraction)
        self.min_history_s = float(min_history_s)
        self.horizon_s = float(horizon_s)
        self.shuffle = shuffle
        self.exclude_play = bool(exclude_play)
        self.cursor = 0
        if self.exclude_play and cache.n_episodes and bool(cache.play.all()):
            data = cache.manifest.get("dataset_dir") or cache.path.name
            raise ValueError(f"{data}: all {cache.n_episodes} episodes are play (unlabeled exploration); "
                             "the fast_loop clones expert actions and needs demonstrations (record them with "
                             "sim-demos --policy expert, or train mid_loop/vqvae on play)")
        episodes = split_episodes(cache, split, self.val_fraction)
        n_play = int(cache.play[episodes].sum())
        if self.exclude_play:
            episodes = episodes[~cache.play[episodes]]
        starts, lengths = self._eligible(episodes)
        flags = cache.imagined[episodes]
        key = [seed, SPLITS[split]]
        group = _block_group(cache, anchors_per_block)
        self.real = _Pool(starts[~flags], lengths[~flags], key + [0], shuffle, group)
        self.imagined = _Pool(starts[flags], lengths[flags], key + [1], shuffle, group)
        n_imag_eps = int(flags.sum())
        skipped = f", {n_play} play episodes excluded" if self.exclude_play and n_play else ""
        where = f"the {split} split of {cache.path.name} ({len(episodes)} episodes, {n_imag_eps} imagined{skipped})"
        if self.ratio > 0 and self.imagined.size == 0:
            raise ValueError(f"imagined_ratio={imagined_ratio} asks for imagined episodes, but {where} has no "
                             "imagined anchors")
        if self.ratio < 1 and self.real.size == 0:
            raise ValueError(f"imagined_ratio={imagined_ratio} needs real episodes, but {where} has no real anchors")

    def _eligible(self, episodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = self.cache
        starts = c.starts[episodes].astype(np.int64)
        ends = c.offsets[episodes + 1].astype(np.int64)
        if self.min_history_s == 0 and self.horizon_s == 0:
            return starts, ends - starts
        first, last = starts.copy(), ends.copy()
        for i, (s, e) in enumerate(zip(starts, ends, strict=True)):
            t = c.t[s:e]  # binary search only: touches a few pages, not the whole episode
            first[i] = s + np.searchsorted(t, self.min_history_s - _EPS, side="left")
            last[i] = s + np.searchsorted(t, t[-1] - self.horizon_s + _EPS, side="right")
        return first, np.maximum(last - first, 0)

    # -- drawing --------------------------------------------------------------------------------
    def _imagined_before(self, b: int) -> int:
        return b * self.batch_size * self._ratio_num // self._ratio_den  # floor, exact

    def batch(self, b: int) -> np.ndarray:
        """Anchor step indices of batch b, ascending (windows read memory forwards that way)."""
        if b < 0:
            raise ValueError(f"batch index {b} must be >= 0")
        im0, im1 = self._imagined_before(b), self._imagined_before(b + 1)
        real0 = b * self.batch_size - im0
        n_im = im1 - im0
        real = self.real.take(real0, self.batch_size - n_im)
        parts = [real] if n_im == 0 else [real, self.imagined.take(im0, n_im)]
        out = np.concatenate(parts).astype(np.int64)
        out.sort()
        return out

    def next_batch(self) -> np.ndarray:
        out = self.batch(self.cursor)
        self.cursor += 1
        return out

    def __iter__(self):
        while True:
            yield self.next_batch()

    @property
    def anchor_group(self) -> tuple[int, int]:
        """(anchors per block, rows per block); (1, 1) when every anchor is drawn on its own."""
        return self.real.group

    @property
    def anchors_per_epoch(self) -> int:
        """Anchors the sampler draws from: real ones unless the ratio is 1, imagined ones if it is > 0."""
        return (self.real.size if self.ratio < 1 else 0) + (self.imagined.size if self.ratio > 0 else 0)

    # -- resume ---------------------------------------------------------------------------------
    def _config(self) -> dict:
        # exclude_play is not a key of its own: the pool sizes and the cache fingerprint pin the
        # pools, and a new key would refuse every checkpoint saved before it existed
        return {"seed": self.seed, "batch_size": self.batch_size, "imagined_ratio": str(self.ratio),
                "split": self.split, "val_fraction": self.val_fraction, "min_history_s": self.min_history_s,
                "horizon_s": self.horizon_s, "shuffle": self.shuffle,
                "pool_sizes": [self.real.size, self.imagined.size], "cache_fingerprint": self.cache.fingerprint,
                **_group_entry(self.anchor_group)}

    def state_dict(self) -> dict:
        return {"format": STATE_FORMAT, "cursor": self.cursor, **self._config()}

    def load_state_dict(self, state: dict) -> None:
        if not isinstance(state, dict) or state.get("format") != STATE_FORMAT:
            raise ValueError(f"not a sampler state (format {STATE_FORMAT!r} expected)")
        saved = state.get("anchor_group", [1, 1])  # a state without it drew every anchor on its own
        if saved != list(self.anchor_group):
            raise ValueError(f"sampler state does not match this sampler: anchor_group was {saved!r}, "
                             f"now {list(self.anchor_group)!r} (anchors_per_block, block rows)")
        for key, value in self._config().items():
            if state.get(key) != value:
                raise ValueError(f"sampler state does not match this sampler: {key} was {state.get(key)!r}, "
                                 f"now {value!r}")
        cursor = state.get("cursor")
        if isinstance(cursor, bool) or not isinstance(cursor, int) or cursor < 0:
            raise ValueError(f"sampler state has an invalid cursor {cursor!r}")
        self.cursor = cursor


def _block_group(cache: DatasetCache, k: int) -> tuple[int, int]:
    """(k, rows per block): the rows one read of the cache's steps covers, a multiple of k."""
    if k == 1:
        return (1, 1)
    rows = MERGE_GAP_BYTES // max(int(cache.x.strides[0]), 1)
    return (k, max(k, rows // k * k))


def _group_entry(group: tuple[int, int]) -> dict:
    # only when grouped: a state saved before grouping existed has no such key and still matches
    return {} if group[0] == 1 else {"anchor_group": list(group)}
