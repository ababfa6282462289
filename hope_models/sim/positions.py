"""Where the target and the fingertip really were, step by step, in a recorded reacher episode: the
answers a probe of the frame tokenizer's codes is scored against (components/vqvae/probe.py).

They are never in an observation (a robot does not know them): they come back from the simulator.
The target of a "reach" episode is fixed for the whole episode and drawn from its seed alone, so a
fresh env of the same seed shows it after reset(); the fingertip follows from the recorded joint
positions by forward kinematics (qpos set, mj_forward). A "track" episode's or a target jump's
moving target is not supported (the reach camera datasets have neither).

    target_xy, fingertip_xy = episode_positions(Path("data/dmc-reacher-reach-s300000"))  # [T, 2] m each
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from hope_models.sim.reacher import make_env


def episode_positions(episode_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """(target_xy, fingertip_xy), [T, 2] float64 in metres each (the arena's world frame), one row
    per recorded step in order, of a recorded reacher reach episode dir (metadata.json, steps/*.jsonl)."""
    meta = json.loads((episode_dir / "metadata.json").read_text())
    sim = meta.get("provenance", {}).get("sim", {})
    if sim.get("domain") != "reacher" or sim.get("task") != "reach" or not isinstance(sim.get("seed"), int):
        raise ValueError(f"{episode_dir / 'metadata.json'}: provenance.sim must be a reacher reach episode "
                         f"with its seed, got {sim!r}")
    env = make_env("reach", sim["seed"])
    env.reset()
    target = env.target_xy()
    physics = env.physics
    tips = []
    for path in sorted((episode_dir / "steps").glob("*.jsonl")):
        for line in path.read_text().splitlines():
            if not line.strip():
                continue
            q = json.loads(line)["observation"]["robot_state"]["joint_positions"]
            physics.data.qpos[:] = q
            physics.forward()
            tips.append(env.fingertip_xy())
    if not tips:
        raise ValueError(f"{episode_dir / 'steps'}: no steps")
    return np.repeat(target[None], len(tips), axis=0), np.stack(tips)
