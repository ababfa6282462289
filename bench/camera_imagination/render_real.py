"""Diagnosis only (uses the simulator): a copy of imagined episodes whose frames are rendered by the
simulator at the imagined joints with the start seed's true target (the drawing's error removed).

    MUJOCO_GL=egl python render_real.py IMAGINED_DIR OUT_DIR
"""
import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parents[2]))  # the checkout, as the other benches

import shutil
import sys

import numpy as np

from bench.camera_imagination import replay

src, out = sys.argv[1], sys.argv[2]
shutil.rmtree(out, ignore_errors=True)
shutil.copytree(src, out)
for d, env, steps in replay.episodes(out, frames=True):
    for s in steps:
        replay.put_arm(env, s)
        np.save(f"{d}/{s['observation']['camera']['uri']}", env.render(64), allow_pickle=False)
print("rendered", out)
