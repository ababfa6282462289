"""`imagine --method model` from a camera world model: a grid mid_loop's wm_* heads predict the
joints, the goal and each imagined step's frame are read off the recorded frames (imagine/frame_arm.py,
frame_goal.py, camera_scene.py), and no simulator is imported.

A tiny world model (a few train steps: the test checks the plumbing, not what the episodes are worth)
over 2 camera demos + 2 camera play episodes recorded in a child with EGL; the CLI runs under
test_imagine_model's import hook that refuses dm_control, mujoco and hope_models.sim."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hope_models.imagine.model_imagine import imagine_model_dataset
from hope_models.imagine.planner import PlanConfig
from hope_models.rlds.discover import read_path

REPO = Path(__file__).resolve().parent.parent
TINY_VQ = '{"layout": "grid", "patch": 8, "n_codes": 32, "channels": 8}'
TINY_MID = '{"d_model": 32, "d_state": 16, "keypoints": 4, "cell_rank": 8, "wm_hidden": 32}'


def _run(args: list[str], env: dict, tmp: Path, hook: bool = False) -> subprocess.CompletedProcess:
    from test_imagine_model import NO_SIM

    cmd = [sys.executable, "-c", NO_SIM, *args] if hook else [sys.executable, "run_trainer.py", *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600,
                          env={**env, "LOADED_OUT": str(tmp / "loaded.json")})


def _ok(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def camera_world(tmp_path_factory):
    root = tmp_path_factory.mktemp("camwm")
    env = {**os.environ, "HOPE_HOME": str(root / "home"), "MUJOCO_GL": "egl"}
    for name, policy in (("demos", "expert"), ("play", "play")):
        _ok(_run(["sim-demos", "--observation", "camera", "--episodes", "2", "--steps", "120", "--policy", policy,
                  "--out", str(root / name)], env, root))
    for src in ("demos", "play"):
        _ok(_run(["ingest", str(root / src), "--into", str(root / "ds")], env, root))
    common = ["--data", str(root / "ds"), "--threads", "1", "--checkpoint-every", "20", "--json"]
    _ok(_run(["train", "--component", "vqvae", "--run-dir", str(root / "vq"), "--steps", "20", "--lr", "3e-3",
              "--model-config", TINY_VQ, *common], env, root))
    _ok(_run(["train", "--component", "mid_loop", "--run-dir", str(root / "wm"), "--vqvae", str(root / "vq"),
              "--steps", "20", "--model-config", TINY_MID, *common], env, root))
    return root, {**env, "MUJOCO_GL": "disabled"}


def test_a_camera_world_model_imagines_episodes_with_frames_without_the_simulator(camera_world):
    root, env = camera_world
    out = root / "imagined"
    proc = _ok(_run(["imagine", "--method", "model", "--model", str(root / "wm"), "--demos", str(root / "demos"),
                     "--play", str(root / "play"), "--episodes", "3", "--steps", "15", "--seed", "7",
                     "--population", "8", "--elites", "3", "--out", str(out), "--json"], env, root, hook=True))
    loaded = json.loads((root / "loaded.json").read_text())
    assert not [m for m in loaded if m.split(".")[0] in ("dm_control", "mujoco") or m.startswith("hope_models.sim")]
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    assert doc["outcome"] == "completed" and doc["steps"] == 45
    goal = doc["settings"]["goal"]
    assert goal["kind"] == "frame" and goal["rewarded_steps"] > 0 and "tip" in doc["settings"]["cost"]
    assert all(e["status"].startswith("accepted") for e in doc["episodes"])
    demo = next(e for r in read_path(root / "demos") for e in r.episodes)
    eps = sorted((e for r in read_path(out) for e in r.episodes), key=lambda e: e.episode_id)
    assert len(eps) == 3
    for ep in eps:
        assert ep.is_imagined and ep.metadata["provenance"]["origin"] == "imagined:model"
        target = ep.metadata["provenance"]["imagined"]["start"]["target_cells"]
        assert len(target) == 2 and all(0.0 <= v <= 8.0 for v in target)  # an 8x8 grid of 8-px cells
        frames = []
        for s in ep.steps:
            assert set(s.observation) == set(demo.steps[0].observation) == {"robot_state", "camera"}
            ref = s.observation["camera"]
            assert ref["format"] == "npy_uint8_hwc" and ref["width"] == 64
            frames.append(np.load(Path(ep.blob_root) / ref["uri"], allow_pickle=False))
        assert all(f.shape == (64, 64, 3) and f.dtype == np.uint8 for f in frames)
    # the same model, data, seed and settings: the same steps and the same frames
    imagine_model_dataset(root / "again", 3, model=root / "wm", demos=[root / "demos"], play=[root / "play"], seed=7,
                          steps=15, plan=PlanConfig(population=8, elites=3))
    for ep in eps:
        for pattern in ("steps/*.jsonl", "blobs/*.npy"):
            a, b = sorted((out / ep.episode_id).glob(pattern)), sorted((root / "again" / ep.episode_id).glob(pattern))
            assert a and [p.read_bytes() for p in a] == [p.read_bytes() for p in b], pattern
    # the dataset takes them and a Fast Loop reading frames through the same tokenizer trains on them
    _ok(_run(["ingest", str(out), "--into", str(root / "ds")], env, root))
    fast = _ok(_run(["train", "--component", "fast_loop", "--data", str(root / "ds"), "--run-dir", str(root / "fast"),
                     "--vqvae", str(root / "vq"), "--steps", "4", "--imagined-ratio", "0.5", "--threads", "1",
                     "--model-config", '{"d_model": 16, "keypoints": 4}', "--json"], env, root))
    result = json.loads(fast.stdout.strip().splitlines()[-1])
    assert result["outcome"] == "completed", result


def test_a_mid_loop_without_world_model_heads_is_refused_by_name(camera_world, tmp_path):
    from frame_fixtures import camera_checkpoints
    from grid_mid_fixtures import grid_mid_checkpoint

    root, _ = camera_world
    nowm = grid_mid_checkpoint(tmp_path, camera_checkpoints(tmp_path, "grid")["vq"],
                               model_config={"grid_world_model": 0})
    with pytest.raises(ValueError, match="no world model .*wm_"):
        imagine_model_dataset(tmp_path / "out", 1, model=nowm, demos=[root / "demos"], steps=5)
