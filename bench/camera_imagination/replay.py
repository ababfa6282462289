"""Imagined episodes replayed in the simulator (diagnosis only): each one's start seed (its target),
the arm set to every recorded step's joints."""
from __future__ import annotations

import glob
import json
from typing import Iterator

from hope_models.sim.reacher import ReacherEnv


def episodes(root: str, frames: bool = False) -> Iterator[tuple[str, ReacherEnv, list[dict]]]:
    """(episode dir, an env reset on the start episode's seed, its steps) for each imagined episode."""
    for d in sorted(glob.glob(f"{root}/imagined-model-*")):
        with open(f"{d}/metadata.json") as f:
            start = json.load(f)["provenance"]["imagined"]["start"]["episode_id"]
        env = ReacherEnv("reach", int(start.rsplit("-s", 1)[1]), frames=frames)
        env.reset()
        with open(f"{d}/steps/000000.jsonl") as f:
            yield d, env, [json.loads(line) for line in f]


def put_arm(env: ReacherEnv, step: dict) -> None:
    """The arm where the step's joints say (positions and velocities), the scene recomputed."""
    rs = step["observation"]["robot_state"]
    env.physics.data.qpos[:] = rs["joint_positions"]
    env.physics.data.qvel[:] = rs["joint_velocities"]
    env.physics.forward()
