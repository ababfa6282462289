"""Diagnosis only (uses the simulator): a copy of imagined episodes whose frames are rendered by the
simulator at the imagined joints with the start seed's true target (the drawing's error removed).

    MUJOCO_GL=egl python render_real.py IMAGINED_DIR OUT_DIR
"""
import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parents[2]))  # the checkout, as the other benches

import glob
import json
import shutil
import sys

import numpy as np

from hope_models.sim.reacher import ReacherEnv

src, out = sys.argv[1], sys.argv[2]
shutil.rmtree(out, ignore_errors=True)
shutil.copytree(src, out)
for d in sorted(glob.glob(f"{out}/imagined-model-*")):
    meta = json.load(open(f"{d}/metadata.json"))
    seed = int(meta["provenance"]["imagined"]["start"]["episode_id"].rsplit("-s", 1)[1])
    env = ReacherEnv("reach", seed, frames=True)
    env.reset()
    for line in open(f"{d}/steps/000000.jsonl"):
        s = json.loads(line)
        rs = s["observation"]["robot_state"]
        env.physics.data.qpos[:] = rs["joint_positions"]
        env.physics.data.qvel[:] = rs["joint_velocities"]
        env.physics.forward()
        np.save(f"{d}/{s['observation']['camera']['uri']}", env.render(64), allow_pickle=False)
print("rendered", out)
