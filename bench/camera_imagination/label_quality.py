"""Diagnosis only (uses the simulator): the imagined labels against the expert's at the imagined
states, and how far the imagined states' true fingertip is from the true target.

    MUJOCO_GL=disabled python label_quality.py IMAGINED_DIR
"""
import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parents[2]))  # the checkout, as the other benches

import sys

import numpy as np

from bench.camera_imagination import replay
from hope_models.sim.expert import ExpertController
from hope_models.sim.reacher import TOLERANCE_M

root = sys.argv[1]
expert = ExpertController()
mse, cos, dist, reached, dist_first = [], [], [], [], []
for _, env, steps in replay.episodes(root):
    ep_dist = []
    for t in range(0, len(steps), 5):
        replay.put_arm(env, steps[t])
        obs = env.observation_dict()
        u = np.asarray(expert.act(obs))
        lab = np.asarray(steps[t]["action"]["command"])
        mse.append(float(((u - lab) ** 2).mean()))
        cos.append(float(u @ lab / (np.linalg.norm(u) * np.linalg.norm(lab) + 1e-9)))
        ep_dist.append(float(np.linalg.norm(obs["target_offset"])))
    dist.append(ep_dist[-1]); dist_first.append(ep_dist[0])
    reached.append(np.mean(np.array(ep_dist[len(ep_dist) // 2:]) < TOLERANCE_M))
print(f"{root}: label vs expert MSE {np.mean(mse):.3f} (median {np.median(mse):.3f}), cosine mean {np.mean(cos):.3f}")
print(f"true fingertip-target distance: at the start median {np.median(dist_first):.3f} m, at the end median {np.median(dist):.3f} m "
      f"(tolerance {TOLERANCE_M:.3f}); share of second-half steps within tolerance {np.mean(reached):.2f}; "
      f"episodes ending within tolerance {np.mean(np.array(dist) < TOLERANCE_M):.2f}")
