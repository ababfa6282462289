"""Diagnosis only (uses the simulator): a copy of imagined episodes whose labels are the expert's
command at each imagined state (the start seed's true target).

    MUJOCO_GL=disabled python relabel_expert.py IMAGINED_DIR OUT_DIR
"""
import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parents[2]))  # the checkout, as the other benches

import json
import shutil
import sys

from bench.camera_imagination import replay
from hope_models.sim.expert import ExpertController

src, out = sys.argv[1], sys.argv[2]
shutil.rmtree(out, ignore_errors=True)
shutil.copytree(src, out)
expert = ExpertController()
for d, env, steps in replay.episodes(out):
    for s in steps:
        replay.put_arm(env, s)
        s["action"]["command"] = [float(v) for v in expert.act(env.observation_dict())]
    with open(f"{d}/steps/000000.jsonl", "w") as f:
        f.write("".join(json.dumps(s, sort_keys=True) + "\n" for s in steps))
print("relabelled", out)
