"""The Fast Loop's keypoints learn where things are from the frames (drawing the codes back from the
points), the policy reads them without moving them, and reads them turned into its first joint's
frame too (components/code_keypoints.py)."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hope_models.components.code_keypoints import CodeKeypoints, turned
from hope_models.components.fast_loop import view_joint
from hope_models.components.fast_loop.model import FastLoop, FastLoopConfig
from hope_models.components.fast_loop.train import FastLoopComponent
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig

GRID = (8, 8)


def _scenes(n: int, gen: torch.Generator, size: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """n grids of background code 0 with a size x size 'ball' (code 1) somewhere: (codes [n, G],
    the ball's centre [n, 2] in frame units)."""
    r = torch.randint(0, GRID[0] - size + 1, (n,), generator=gen)
    c = torch.randint(0, GRID[1] - size + 1, (n,), generator=gen)
    rows, cols = torch.arange(GRID[0])[None, :, None], torch.arange(GRID[1])[None, None, :]
    ball = ((rows >= r[:, None, None]) & (rows < r[:, None, None] + size)
            & (cols >= c[:, None, None]) & (cols < c[:, None, None] + size))
    centre = torch.stack([(c + size / 2) / GRID[1] * 2 - 1, (r + size / 2) / GRID[0] * 2 - 1], -1)
    return ball.reshape(n, -1).long(), centre


@pytest.mark.parametrize("draw", ["vectors", "codes"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drawing_the_codes_back_puts_a_point_on_the_target_without_a_label(seed, draw):
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed + 100)
    # several points, as the Fast Loop has (16): one that starts far from everything may stay idle
    kp = CodeKeypoints(n_codes=4, grid=GRID, keypoints=4, d_out=4, reader="frames", draw=draw, code_dim=8)
    vectors = torch.nn.functional.layer_norm(torch.randn(4, 8, generator=gen), (8,))  # a codebook's rows
    opt = torch.optim.Adam(kp.parameters(), lr=1e-2)

    def miss(codes, centre) -> float:  # frame units from the ball to the nearest point, mean
        where, _ = kp.locate(codes)
        return float((where - centre[:, None]).norm(dim=-1).min(-1).values.mean())

    test_codes, test_cell = _scenes(64, gen)
    with torch.no_grad():
        before = miss(test_codes, test_cell)
    first = last = None
    for _ in range(300):
        loss, _ = kp.draw_back(_scenes(32, gen)[0], vectors)
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = loss.item() if first is None else first
        last = loss.item()
    with torch.no_grad():
        after = miss(test_codes, test_cell)
    cell_width = 2 / GRID[0]
    assert last < first / 2
    assert before > cell_width and after < cell_width / 2, (before, after)


def test_a_policy_reader_has_no_drawing():
    kp = CodeKeypoints(n_codes=4, grid=GRID, keypoints=2, d_out=4)
    with pytest.raises(AssertionError, match="no drawing"):
        kp.draw_back(torch.zeros(1, 64, dtype=torch.long))
    with pytest.raises(ValueError, match="keypoint reader='x'"):
        CodeKeypoints(n_codes=4, grid=GRID, keypoints=2, d_out=4, reader="x")


@pytest.mark.parametrize("reader", ["frames", "policy"])
def test_only_a_policy_reader_is_moved_by_the_policys_loss(reader):
    torch.manual_seed(0)
    kp = CodeKeypoints(n_codes=4, grid=GRID, keypoints=2, d_out=3, reader=reader)
    codes, _ = _scenes(8, torch.Generator().manual_seed(0))
    kp(codes).pow(2).sum().backward()
    moved = kp.score.weight.grad is not None and kp.score.weight.grad.abs().sum() > 0
    assert moved == (reader == "policy")
    assert kp.out.weight.grad.abs().sum() > 0  # what the points mean is the policy's to learn


def test_points_read_in_the_joints_frame_stay_put_when_the_scene_turns_with_the_joint():
    torch.manual_seed(0)
    r = torch.randn(5, 3, 2)
    angle = torch.rand(5) * 6 - 3
    theta = torch.rand(5) * 6 - 3

    def rot(v, a):
        c, s = torch.cos(a)[:, None], torch.sin(a)[:, None]
        return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)

    back, ahead = turned(r, angle)
    back_t, _ = turned(rot(r, theta), angle + theta)  # the view turns the way the joint does
    _, ahead_m = turned(rot(r, -theta), angle + theta)  # a mirrored camera sees it turn the other way
    assert torch.allclose(back, back_t, atol=1e-5) and torch.allclose(ahead, ahead_m, atol=1e-5)
    assert not torch.allclose(back, turned(rot(r, theta), angle)[0], atol=1e-3)


def _grid_vq() -> VQVAE:
    vq = VQVAE(VQVAEConfig(input="frame", groups=256, code_dim=256 * 8, layout="grid", patch=4, n_codes=32, channels=8))
    vq(torch.randint(0, 256, (8, *vq.cfg.frame_shape), dtype=torch.uint8), init_codebook=True)
    return vq


def _spec(paths, mean=(0.5, -1.0, 0.0, 0.0), std=(2.0, 1.5, 1.0, 1.0)):
    group = SimpleNamespace(fields=[SimpleNamespace(path=p, size=n) for p, n in paths], mean=list(mean),
                            std=list(std), has_stats=True)
    return SimpleNamespace(observation=group)


def test_the_view_joint_is_the_observations_first_joint_angle_with_its_statistics():
    vq = _grid_vq().cfg
    reacher = _spec([("observation.robot_state.joint_velocities", 2), ("observation.robot_state.joint_positions", 2)])
    assert view_joint(reacher, vq) == {"view_joint": 2, "view_joint_mean": 0.0, "view_joint_std": 1.0}
    assert view_joint(_spec([("observation.state", 4)]), vq) == {"view_joint": -1}
    assert view_joint(reacher, None) == {"view_joint": -1}  # no camera codes: nothing to turn
    assert view_joint(reacher, VQVAEConfig(input="vector", obs_dim=4, n_codes=32)) == {"view_joint": -1}


@pytest.mark.parametrize("draw", ["vectors", "codes"])
def test_the_fast_loop_trains_its_points_on_the_drawing_and_is_validated_on_the_action_alone(draw):
    torch.manual_seed(0)
    cfg = FastLoopConfig(obs_dim=4, act_dim=2, n_codes=32, view_joint=0, view_joint_mean=0.5, view_joint_std=2.0,
                         keypoint_draw=draw)
    model = FastLoop(cfg, _grid_vq())
    obs = torch.randn(4, 5, 4)
    assert torch.allclose(model.view_angle(obs), obs[..., 0] * 2.0 + 0.5)
    batch = SimpleNamespace(obs=obs.numpy(), mask=np.ones((4, 5), bool), target_act=np.zeros((4, 2), np.float32),
                            codes=np.random.default_rng(0).integers(0, 32, (4, 5, 256)), frames=None)
    comp = FastLoopComponent(None, model, cfg, SimpleNamespace(k=5), "fp")
    loss, metrics = comp.loss(batch)
    drawn = metrics["render_ce" if draw == "codes" else "render_mse"]
    assert drawn > 0 and math.isclose(float(loss), metrics["mse"] + drawn, rel_tol=1e-5)
    assert math.isclose(comp.evaluate(batch)["loss"], comp.evaluate(batch)["mse"], rel_tol=1e-6)
    loss.backward()
    assert model.keypoints.score.weight.grad.abs().sum() > 0  # moved by the drawing
    with pytest.raises(ValueError, match="pass the joint angle"):
        model.keypoints(torch.zeros(1, 256, dtype=torch.long))


def test_a_camera_policy_saved_before_the_frames_reader_loads_as_it_was_trained(tmp_path):
    """Its config.json has neither keypoint_reader nor view_joint: its points were placed by its
    own loss and read unturned, in torch and in the NumPy runtime alike."""
    import json

    from frame_fixtures import FAST_SMALL, _save, camera_checkpoints, camera_spec

    from hope_models.components.build import build_component, component_from_checkpoint
    from hope_models.components.fast_loop.numpy_form import FastLoopNumpy

    torch.manual_seed(0)
    vq = camera_checkpoints(tmp_path, "grid")["vq"]
    old = build_component("fast_loop", camera_spec(), model_config={**FAST_SMALL, "keypoint_reader": "policy",
                                                                    "view_joint": -1}, vqvae_dir=vq)
    assert old.model.keypoints.render is None and old.model.keypoints.view is None
    ckpt = _save(tmp_path / "old", old)
    cfg = json.loads((ckpt / "config.json").read_text())
    for key in ("keypoint_reader", "view_joint", "view_joint_mean", "view_joint_std"):
        del cfg["model_config"][key]
    (ckpt / "config.json").write_text(json.dumps(cfg))
    loaded = component_from_checkpoint(ckpt).model
    assert (loaded.cfg.keypoint_reader, loaded.cfg.view_joint) == ("policy", -1)
    runtime = FastLoopNumpy.from_checkpoint(ckpt)
    obs = torch.randn(2, 5, 4)
    codes = torch.randint(0, loaded.cfg.n_codes, (2, 5, 256))
    with torch.no_grad():
        want = loaded(obs, codes=codes).numpy()
    got = runtime.forward(obs.numpy(), codes=codes.numpy())
    assert np.abs(want - got).max() < 1e-4
    fresh = build_component("fast_loop", camera_spec(), model_config=FAST_SMALL, vqvae_dir=vq).model
    assert (fresh.cfg.keypoint_reader, fresh.cfg.view_joint) == ("frames", 0)  # a new run reads both ways


def test_a_camera_policy_that_drew_codes_loads_and_trains_as_it_was_made(tmp_path):
    """A frames-reader checkpoint from before the vector drawing has no keypoint_draw: its drawing's
    background is n_codes logits a cell, and it loads (and resumes) with that drawing."""
    import json

    from frame_fixtures import FAST_SMALL, _save, camera_checkpoints, camera_spec

    from hope_models.components.build import build_component, component_from_checkpoint

    torch.manual_seed(0)
    vq = camera_checkpoints(tmp_path, "grid")["vq"]
    old = build_component("fast_loop", camera_spec(), model_config={**FAST_SMALL, "keypoint_draw": "codes"},
                          vqvae_dir=vq)
    n_codes = old.model.cfg.n_codes
    assert old.model.keypoints.render.background.shape == (256, n_codes)
    ckpt = _save(tmp_path / "old", old)
    cfg = json.loads((ckpt / "config.json").read_text())
    del cfg["model_config"]["keypoint_draw"]
    (ckpt / "config.json").write_text(json.dumps(cfg))
    loaded = component_from_checkpoint(ckpt).model
    assert loaded.cfg.keypoint_draw == "codes" and loaded.keypoints.draw == "codes"
    assert torch.equal(loaded.keypoints.render.background, old.model.keypoints.render.background)
    fresh = build_component("fast_loop", camera_spec(), model_config=FAST_SMALL, vqvae_dir=vq).model
    assert fresh.cfg.keypoint_draw == "vectors"  # a new run draws the cells' code vectors
    assert fresh.keypoints.render.background.shape == (256, fresh.vqvae.codebook.shape[1])
