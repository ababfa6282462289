"""How well the frame goal reads the target and the tip, on held-out recorded episodes.

    python measure_goal.py MODEL_RUN DEMOS PLAY [--hold 1,4]

The truth (for this measurement only): the target's centre = the centroid of its red pixels in the
episode's frames (reacher's flat render), in cells; the reward says when the tip is on it.
"""
from __future__ import annotations

import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parents[2]))  # the checkout, as the other benches


import sys
import time

import numpy as np
import torch

from hope_models.data.cameras import read_camera
from hope_models.imagine.frame_goal import FrameGoal
from hope_models.imagine.planner import WorldModel
from hope_models.imagine.recorded import read_recorded
from hope_models.rlds.discover import iter_reports

torch.set_num_threads(1)
model, demos, play = sys.argv[1:4]
wm = WorldModel.load(model)
t0 = time.perf_counter()
eps = read_recorded([demos, play], wm.spec, wm.encode_frames)
print(f"read + encoded {sum(len(e.obs) for e in eps)} frames of {len(eps)} episodes in {time.perf_counter() - t0:.1f} s")

# truth: red centroid per episode (median over 20 frames), in cells (4 px)
truth = {}
for report in iter_reports([demos, play]):
    for ep in report.episodes:
        pts = []
        for t, img in enumerate(read_camera(ep.steps, wm.spec.frame, ep.blob_root)):
            if t % 50:
                continue
            r, g = img[..., 0].astype(int), img[..., 1].astype(int)
            m = (r > 150) & (g < 130)
            if m.sum() > 5:
                yy, xx = np.nonzero(m)
                pts.append([(xx.mean() + 0.5) / 4, (yy.mean() + 0.5) / 4])
        truth[ep.episode_id] = np.median(np.array(pts), 0)

demo_eps = [e for e in eps if not e.play]
play_eps = [e for e in eps if e.play]
held = [demo_eps[-1], *play_eps[-4:]]
train = [e for e in eps if e not in held]
t0 = time.perf_counter()
rows, cols = wm.model.vqvae.cfg.grid_shape
goal = FrameGoal.fit(train, wm.model.cfg.n_codes, (rows, cols), seed=0)
print(f"fit on {len(train)} episodes in {time.perf_counter() - t0:.1f} s: {goal.to_json_obj()}")
from hope_models.imagine.frame_goal import episode_scene

for name, group in (("train", train), ("held-out", held)):
    errs = []
    for e in group:
        found = episode_scene(goal.arm, e, (rows, cols)).target
        errs.append(np.inf if found is None else float(np.linalg.norm(found - truth[e.episode_id])))
    print(f"target locator, {name}: error (cells) per episode {np.round(errs, 2).tolist()}; mean {np.mean(errs):.2f}")
for name, group in (("train", train), ("held-out", held)):
    d_rew, d_not = [], []
    for e in group:
        d = (goal.tip(e.obs).numpy() - truth[e.episode_id]).__abs__()
        d = np.linalg.norm(goal.tip(e.obs).numpy() - truth[e.episode_id], axis=1)
        d_rew += d[e.reward > 0].tolist()
        d_not += d[e.reward <= 0].tolist()
    d_rew, d_not = np.array(d_rew), np.array(d_not)
    auc = np.mean(d_rew[:, None] < d_not[None, :]) if len(d_rew) and len(d_not) else float("nan")
    print(f"tip - true target (cells), {name}: rewarded steps median {np.median(d_rew) if len(d_rew) else np.nan:.2f} "
          f"(n {len(d_rew)}), not rewarded median {np.median(d_not) if len(d_not) else np.nan:.2f} (n {len(d_not)}); "
          f"P(rewarded closer than not) {auc:.3f}")
