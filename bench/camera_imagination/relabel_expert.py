"""Diagnosis only (uses the simulator): a copy of imagined episodes whose labels are the expert's
command at each imagined state (the start seed's true target).

    MUJOCO_GL=disabled python relabel_expert.py IMAGINED_DIR OUT_DIR
"""
import sys as _sys
from pathlib import Path as _Path

_sys.path.insert(0, str(_Path(__file__).resolve().parents[2]))  # the checkout, as the other benches

import glob
import json
import shutil
import sys

from hope_models.sim.expert import ExpertController
from hope_models.sim.reacher import ReacherEnv

src, out = sys.argv[1], sys.argv[2]
shutil.rmtree(out, ignore_errors=True)
shutil.copytree(src, out)
expert = ExpertController()
for d in sorted(glob.glob(f"{out}/imagined-model-*")):
    meta = json.load(open(f"{d}/metadata.json"))
    seed = int(meta["provenance"]["imagined"]["start"]["episode_id"].rsplit("-s", 1)[1])
    env = ReacherEnv("reach", seed)
    env.reset()
    lines = []
    for line in open(f"{d}/steps/000000.jsonl"):
        s = json.loads(line)
        rs = s["observation"]["robot_state"]
        env.physics.data.qpos[:] = rs["joint_positions"]
        env.physics.data.qvel[:] = rs["joint_velocities"]
        env.physics.forward()
        s["action"]["command"] = [float(v) for v in expert.act(env.observation_dict())]
        lines.append(json.dumps(s, sort_keys=True))
    open(f"{d}/steps/000000.jsonl", "w").write("\n".join(lines) + "\n")
print("relabelled", out)
