"""The grid Mid Loop's picture of held-out windows (train/held_out_picture.py writes it into the run
dir as predicted_frames.png; the Robot Editor's run page shows it):

    one row per window:  now | predicted +h1 | real +h1 | predicted +h2 | real +h2 ...

"now" is the window's anchor frame; "predicted +h" is the frozen VQ-VAE's decoder applied to the
most probable code of every cell h seconds ahead (the window's horizons_s: 0.5 s and 1 s by
default, horizon_steps grid points); "real +h" is the frame the camera recorded then, read from
the cache (the same held frame the horizon's code target is taken from, data/windows.py), not a
decoding of its codes: the picture shows the tokenizer's loss as well as the predictor's.

The most probable code is the copy-mixed one (grid_metrics.mixed_argmax): the argmax of the
distribution the loss and the held-out accuracy score, (1 - copy_mix) x the decoder's + copy_mix
x copy-last's, so a cell the decoder is unsure about keeps its code now, as accuracy counts it.
"""
from __future__ import annotations

import numpy as np
import torch

from hope_models.components import picture
from hope_models.components.mid_loop.grid_metrics import mixed_argmax
from hope_models.components.mid_loop.model import previous_actions
from hope_models.components.training_base import as_tensor
from hope_models.data.windows import WindowSpec, make_windows

ROWS = 4  # held-out windows in the picture: 5 columns x 4 rows of 192 px at 64x64 frames
_EPS = 1e-6


def picture_anchors(cache, episodes: np.ndarray, window: WindowSpec, n: int = ROWS) -> np.ndarray:
    """n anchor rows evenly spread through `episodes` (cache episode indices) among the steps whose
    window is whole (its oldest grid point inside the episode) and whose every horizon is still in
    it (future_mask all true); fewer when there are fewer such steps, none when none."""
    lead, ahead = float(window.lags[0]), max(window.horizons_s)
    rows = []
    for e in episodes:
        s, end = int(cache.starts[e]), int(cache.ends[e]) + 1
        t = cache.t[s:end]  # binary search only, as the sampler's eligibility does
        lo = s + int(np.searchsorted(t, lead - _EPS, side="left"))
        hi = s + int(np.searchsorted(t, t[-1] - ahead + _EPS, side="right"))
        rows.append(np.arange(lo, max(lo, hi), dtype=np.int64))
    return picture.spread(np.concatenate(rows or [np.empty(0, dtype=np.int64)]), n)


@torch.no_grad()
def predicted_frames(model, cache, episodes: np.ndarray, window: WindowSpec, n: int = ROWS) -> np.ndarray | None:
    """The picture (module doc) of up to n held-out windows of `episodes`, uint8 [rows x frame
    height x s, (1 + 2 x horizons) x frame width x s, 3] (components/picture.py grid); None when no
    step of them has a whole window and every horizon ahead. The model (GridMidLoop) is put in eval
    mode for it and left in the mode it was found in; nothing is counted or changed."""
    anchors = picture_anchors(cache, episodes, window, n)
    if not len(anchors):
        return None
    batch = make_windows(cache, anchors, window, frames=True)  # the real frames: the window's and the futures'
    assert batch.frames is not None and batch.future_frames is not None
    was_training = model.training
    model.eval()
    try:
        codes = model.codes(None, as_tensor(batch.frames))  # [B, K, G]
        y = model.context(codes, previous_actions(as_tensor(batch.act)), as_tensor(batch.obs),
                          as_tensor(batch.mask))[:, -1]
        now = codes[:, -1]
        predicted = [mixed_argmax(model, h, model.cell_logits(y, h, now), now)
                     for h in range(len(model.cfg.horizon_steps))]
        pixels = model.vqvae.decode(torch.cat(predicted))  # [H x B, 3, height, width]
    finally:
        model.train(was_training)
    decoded = picture.to_uint8(pixels.permute(0, 2, 3, 1).numpy()).reshape(len(predicted), len(anchors),
                                                                           *batch.frames.shape[-3:])
    columns = [batch.frames[:, -1]]
    for h in range(len(predicted)):
        columns += [decoded[h], batch.future_frames[:, h]]
    return picture.grid(np.stack(columns, axis=1))


__all__ = ["ROWS", "picture_anchors", "predicted_frames"]
