"""How the reacher's frames are drawn: "flat" (the default, no shadow map or floor reflection) or
"shaded" (MuJoCo's defaults, the recordings before the choice); the style is written into each
episode, and a camera reflex is evaluated on frames drawn as the ones it learned from."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hope_models.promote.render_style import trained_render_style

REPO = Path(__file__).resolve().parents[1]

# In a child: dm_control must be imported with MUJOCO_GL=egl to render. Prints, per style, the
# first frame's hash, and whether a policy stepped by evaluate.run_episode saw the same first frame.
RENDER_CHILD = r"""
import hashlib, json, sys
import numpy as np
from hope_models.sim.evaluate import run_episode
from hope_models.sim.reacher import make_env

class Looks:  # a camera policy that keeps the frames it is shown
    frame_size = 64
    def __init__(self, style): self.render_style, self.seen = style, []
    def act(self, obs): self.seen.append(obs["camera"]); return np.zeros(2)

out = {}
for style in ("flat", "shaded"):
    env = make_env("reach", 5, frames=True, render_style=style)
    env.reset()
    first = env.render(64)
    again = env.render(64)  # the kept camera draws the same scene twice the same
    policy = Looks(style)
    run_episode(policy, "reach", 5, steps=3)
    out[style] = {"hash": hashlib.sha256(first.tobytes()).hexdigest(), "shape": list(first.shape),
                  "dtype": str(first.dtype), "stable": bool(np.array_equal(first, again)),
                  "policy_saw_it": bool(np.array_equal(policy.seen[0], first)),
                  "mean": float(first.mean())}
try:
    make_env("reach", 5, frames=True, render_style="glossy")
except ValueError as exc:
    out["error"] = str(exc)
print(json.dumps(out))
"""


def test_the_two_styles_draw_different_frames_and_an_episode_is_shown_its_policys_style():
    proc = subprocess.run([sys.executable, "-c", RENDER_CHILD], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "MUJOCO_GL": "egl"}, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    for style in ("flat", "shaded"):
        assert out[style]["shape"] == [64, 64, 3] and out[style]["dtype"] == "uint8"
        assert out[style]["stable"] and out[style]["policy_saw_it"], out[style]
    assert out["flat"]["hash"] != out["shaded"]["hash"]
    assert out["error"] == "render style 'glossy' is not one of flat, shaded"


def _dataset(root: Path, sim: dict) -> Path:
    ep = root / "data" / "ep-0"
    ep.mkdir(parents=True)
    (ep / "metadata.json").write_text(json.dumps({"provenance": {"origin": "sim:dm_control", "sim": sim}}))
    return root / "data"


def _checkpoint(data: Path | str) -> dict:
    """A checkpoint's config.json as ReflexPolicy reads it."""
    return {"component": "fast_loop", "train": {"data": str(data)}}


@pytest.mark.parametrize("sim, expected", [
    ({"observation": "camera", "frame_size": 64, "render": "flat"}, "flat"),
    ({"observation": "camera", "frame_size": 64, "render": "shaded"}, "shaded"),
    ({"observation": "camera", "frame_size": 64}, "shaded"),  # recorded before there was a choice
])
def test_the_style_a_reflex_learned_from_is_read_off_its_training_data(tmp_path, sim, expected):
    data = _dataset(tmp_path, sim)
    style, where = trained_render_style(_checkpoint(data))
    assert style == expected and where == str(data / "ep-0" / "metadata.json")


def test_without_its_training_data_the_style_is_the_default_and_says_why(tmp_path):
    style, where = trained_render_style(_checkpoint(tmp_path / "gone"))
    assert style == "flat" and "is not here" in where and "gone" in where
    state_only = _dataset(tmp_path / "state", {"observation": "state"})  # no frames: says nothing
    style, where = trained_render_style(_checkpoint(state_only))
    assert style == "flat" and "no simulated episode with frames" in where
    assert trained_render_style({"component": "fast_loop"})[1].endswith("names no training data)")


def test_sim_demos_writes_the_style_into_every_episode(tmp_path):
    out = tmp_path / "cam"
    proc = subprocess.run([sys.executable, "run_trainer.py", "sim-demos", "--episodes", "1", "--steps", "3",
                           "--observation", "camera", "--render", "shaded", "--out", str(out), "--json"],
                          cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={k: v for k, v in os.environ.items() if k != "MUJOCO_GL"})
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["render"] == "shaded"
    meta = json.loads((Path(result["episodes"][0]["path"]) / "metadata.json").read_text())
    assert meta["provenance"]["sim"]["render"] == "shaded"
    bad = subprocess.run([sys.executable, "run_trainer.py", "sim-demos", "--episodes", "1", "--out", str(out),
                          "--observation", "camera", "--render", "glossy"], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert bad.returncode == 2 and "--render: invalid choice: 'glossy'" in bad.stderr
