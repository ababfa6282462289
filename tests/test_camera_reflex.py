"""A reflex from pixels: the Fast Loop reads a grid VQ-VAE's codes as keypoints (where things are,
components/code_keypoints.py), and a camera fast_loop is driven in the simulator from the joints
and the rendered frame only."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hope_models.components.code_keypoints import CodeKeypoints, cell_centres
from hope_models.components.fast_loop.model import FastLoop, FastLoopConfig
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig

REPO = Path(__file__).resolve().parents[1]
GRID_VQ = {"layout": "grid", "patch": 4, "n_codes": 32, "channels": 8}


def _grid_vq() -> VQVAE:
    vq = VQVAE(VQVAEConfig(input="frame", groups=256, code_dim=256 * 8, **GRID_VQ))
    vq(torch.randint(0, 256, (16, *vq.cfg.frame_shape), dtype=torch.uint8), init_codebook=True)
    return vq


def test_keypoints_say_where_a_code_is_and_a_bag_of_codes_cannot():
    torch.manual_seed(0)
    kp = CodeKeypoints(n_codes=4, grid=(4, 4), keypoints=1, d_out=2)
    with torch.no_grad():
        kp.score.weight.copy_(torch.tensor([[0.0], [20.0], [0.0], [0.0]]))  # code 1 is "the ball"
        kp.out.weight.copy_(torch.tensor([[1.0, 0, 0], [0, 1.0, 0]]))  # out = (x, y) of the keypoint
        kp.out.bias.zero_()
    codes = torch.zeros(2, 16, dtype=torch.long)
    codes[0, 0] = 1  # top-left cell
    codes[1, 15] = 1  # bottom-right cell
    where = kp(codes)
    centres = cell_centres((4, 4))
    assert torch.allclose(where[0], centres[0], atol=1e-3) and torch.allclose(where[1], centres[15], atol=1e-3)
    codes[0, 1] = 1  # the ball over two cells: the point between them
    assert torch.allclose(kp(codes)[0], (centres[0] + centres[1]) / 2, atol=1e-3)
    with pytest.raises(ValueError, match="codes have 9 cells, the grid"):
        kp(torch.zeros(1, 9, dtype=torch.long))


def test_a_fast_loop_over_a_grid_tokenizer_tells_cells_apart_and_steps_like_its_window():
    torch.manual_seed(1)
    vq = _grid_vq()
    model = FastLoop(FastLoopConfig(obs_dim=4, act_dim=2, n_codes=32), vq)
    assert model.keypoints is not None and model.code_in is None
    obs = torch.randn(1, 5, 4)
    codes = torch.zeros(1, 5, 256, dtype=torch.long)
    moved = codes.clone()
    codes[..., 0] = 3
    moved[..., 255] = 3  # the same codes, one of them in another cell
    with torch.no_grad():
        assert (model(obs, codes=codes) - model(obs, codes=moved)).abs().max() > 1e-4
    frames = torch.randint(0, 256, (2, 5, 64, 64, 3), dtype=torch.uint8)
    obs = torch.randn(2, 5, 4)
    with torch.no_grad():
        window = model(obs, torch.ones(2, 5, dtype=torch.bool), frames)
        assert torch.equal(window, model(obs, torch.ones(2, 5, dtype=torch.bool), codes=model.codes(obs, frames)))
        state = model.init_state(2)
        for t in range(5):
            act, state = model.step(obs[:, t], state, frames[:, t])
    assert (act - window).abs().max().item() < 1e-5


@pytest.fixture(scope="module")
def camera_reflex(tmp_path_factory):
    """A grid VQ-VAE and a camera fast_loop over it with the reacher's fields, random weights, saved
    with the real checkpoint writer (tests/frame_fixtures.py): what the reflex runtime loads."""
    from frame_fixtures import camera_checkpoints

    return camera_checkpoints(tmp_path_factory.mktemp("camreflex"), "grid")["fast"]


def test_a_camera_reflex_sees_the_joints_and_the_camera_and_nothing_about_the_target(camera_reflex):
    code = r"""
import json, sys
import numpy as np
from hope_models.promote.reflex_policy import ReflexPolicy, ReflexPolicyError
from hope_models.sim.evaluate import evaluate_policy

policy = ReflexPolicy.from_checkpoint(sys.argv[1])
seen = []
class Watch:
    frame_size = policy.frame_size
    def reset(self): policy.reset()
    def act(self, obs):
        seen.append({"keys": sorted(obs), "joints": sorted(obs["robot_state"]),
                     "frame": [str(obs["camera"].dtype), list(obs["camera"].shape)]})
        return policy.act(obs)
res = evaluate_policy(Watch(), [3], steps=6)
errors = []
for bad in (np.zeros((32, 32, 3), np.uint8), np.zeros((64, 64, 3), np.float32)):
    try:
        policy.act({"robot_state": {"joint_positions": [0, 0], "joint_velocities": [0, 0]}, "camera": bad})
    except ReflexPolicyError as exc:
        errors.append(str(exc))
print(json.dumps({"size": policy.frame_size, "seen": seen, "steps": len(res.episodes), "errors": errors}))
"""
    proc = subprocess.run([sys.executable, "-c", code, str(camera_reflex)], cwd=REPO, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "MUJOCO_GL": "egl"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["size"] == 64 and len(out["seen"]) == 6
    for s in out["seen"]:
        assert s == {"keys": ["camera", "robot_state"], "joints": ["joint_positions", "joint_velocities"],
                     "frame": ["uint8", [64, 64, 3]]}
    assert len(out["errors"]) == 2 and all("observation.camera is" in e and "needs uint8 [64, 64, 3]" in e
                                           for e in out["errors"])

