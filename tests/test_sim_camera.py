"""The reacher's camera observation: what a robot has (its joints and its camera frame), nothing
about the target; the simulator still scores the episode, and the dataset's spec reads the frame."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hope_models.data.cache import load_or_build

REPO = Path(__file__).resolve().parents[1]
PRIVILEGED = ("target_offset", "to_target", "target", "fingertip")


def _record(out: Path, observation: str, frame_size: int = 64, seed: int = 11, episodes: int = 2) -> list[dict]:
    """record_dataset in a child: dm_control must be imported with MUJOCO_GL=egl to render."""
    code = ("import json, sys; from hope_models.sim.recorder import record_dataset; "
            f"r = record_dataset(sys.argv[1], {episodes}, seed={seed}, steps=25, noise=1.0, "
            f"observation={observation!r}, frame_size={frame_size}); "
            "print(json.dumps([{'path': str(e.path), 'ret': e.ret} for e in r.episodes]))")
    proc = subprocess.run([sys.executable, "-c", code, str(out)], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": "egl"}, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _keys(value, prefix="") -> list[str]:
    if isinstance(value, dict):
        return [k for key, sub in value.items() for k in [f"{prefix}{key}", *_keys(sub, f"{prefix}{key}.")]]
    return []


def _steps(path: str) -> list[dict]:
    return [json.loads(line) for line in (Path(path) / "steps" / "000000.jsonl").read_text().splitlines()]


def test_the_camera_observation_holds_the_joints_and_the_frame_and_nothing_privileged(tmp_path):
    camera = _record(tmp_path / "camera", "camera")
    state = _record(tmp_path / "state", "state")
    # the same seeds and noise drive the same arm: the simulator scores both the same
    assert [e["ret"] for e in camera] == [e["ret"] for e in state]
    for ep in camera:
        steps = _steps(ep["path"])
        assert len(steps) == 25
        for step in steps:
            keys = _keys(step["observation"])
            assert not [k for k in keys if any(word in k.split(".")[-1] for word in PRIVILEGED)], keys
            assert set(step["observation"]) == {"robot_state", "camera"}
            assert set(step["observation"]["robot_state"]) == {"joint_positions", "joint_velocities"}
        frames = [np.load(Path(ep["path"]) / s["observation"]["camera"]["uri"], allow_pickle=False) for s in steps]
        assert all(f.shape == (64, 64, 3) and f.dtype == np.uint8 for f in frames)
        assert not np.array_equal(frames[0], frames[-1])  # the arm moved and the camera saw it
        sim = json.loads((Path(ep["path"]) / "metadata.json").read_text())["provenance"]["sim"]
        assert sim["observation"] == "camera" and sim["frame_size"] == 64 and sim["render"] == "flat"
    # the joints are the state's own
    for cam_ep, state_ep in zip(camera, state, strict=True):
        for c, s in zip(_steps(cam_ep["path"]), _steps(state_ep["path"]), strict=True):
            assert c["observation"]["robot_state"] == s["observation"]["robot_state"]

    cache, _ = load_or_build(tmp_path / "camera", tmp_path / "cache")
    assert cache.spec.frame is not None and cache.spec.frame.path == "observation.camera"
    assert [f.path for f in cache.spec.observation.fields] == ["observation.robot_state.joint_positions",
                                                                "observation.robot_state.joint_velocities"]
    assert cache.frames.shape == (50, 64, 64, 3)


def test_96_pixel_frames_and_a_bad_observation_or_size_is_named(tmp_path):
    (ep,) = _record(tmp_path / "big", "camera", frame_size=96, episodes=1)
    first = _steps(ep["path"])[0]["observation"]["camera"]
    assert (first["width"], first["height"]) == (96, 96)
    assert np.load(Path(ep["path"]) / first["uri"], allow_pickle=False).shape == (96, 96, 3)

    from hope_models.sim.recorder import record_dataset

    with pytest.raises(ValueError, match="observation='pixels' must be one of state, camera"):
        record_dataset(tmp_path / "x", 1, observation="pixels")
    with pytest.raises(ValueError, match="frame_size=80 must be one of 64, 96"):
        record_dataset(tmp_path / "x", 1, observation="camera", frame_size=80)


def test_sim_demos_records_the_camera_observation_from_the_command_line(tmp_path):
    out = tmp_path / "cam"
    proc = subprocess.run([sys.executable, "run_trainer.py", "sim-demos", "--episodes", "1", "--steps", "5",
                           "--observation", "camera", "--frame-size", "96", "--out", str(out), "--json"],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={k: v for k, v in os.environ.items() if k != "MUJOCO_GL"})  # set by the command
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["observation"] == "camera" and result["frame_size"] == 96 and result["noise"] == 1.0
    (step,) = _steps(result["episodes"][0]["path"])[:1]
    assert set(step["observation"]) == {"robot_state", "camera"} and step["observation"]["camera"]["width"] == 96
    bad = subprocess.run([sys.executable, "run_trainer.py", "sim-demos", "--episodes", "1", "--out", str(out),
                          "--observation", "pixels"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--observation: invalid choice: 'pixels'" in bad.stderr
