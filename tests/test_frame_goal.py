"""The goal of a camera robot without labels (imagine/frame_arm.py, frame_goal.py): the arm's look
learned from its joints, the target found as what the joints do not explain, the tip fitted on
rewarded steps. Synthetic cell codes on an 8x8 grid: a background, an "arm" (a bar of cells whose row
and length follow two joints, its last cell the tip) and a static 2x2 target per episode."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hope_models.imagine.frame_arm import ArmFit, ArmModel
from hope_models.imagine.frame_draw import ArmPool
from hope_models.imagine.frame_goal import FrameGoal, TipFit, cell_centres, episode_scene, evidence, locate
from hope_models.imagine.recorded import Recorded

pytestmark = pytest.mark.usefixtures("torch_one_thread")

SIDE, N_CODES, ARM, TIP, TARGET = 8, 6, 2, 3, 4


def _arm_cells(q: np.ndarray) -> tuple[int, int]:
    """Joints (normalised, in [-1, 1]) -> (row, length) of the bar from column 0; its tip is its last cell."""
    row = int(np.clip((q[0] + 1) / 2 * SIDE, 0, SIDE - 1))
    return row, int(np.clip((q[1] + 1) / 2 * (SIDE - 1), 0, SIDE - 2)) + 1


def _frame(q: np.ndarray, target: tuple[int, int] | None) -> np.ndarray:
    codes = np.zeros((SIDE, SIDE), np.int64)
    codes[:, SIDE - 1] = 1  # a border: background too, another code
    if target is not None:
        r, c = target
        codes[r:r + 2, c:c + 2] = TARGET
    row, length = _arm_cells(q)
    codes[row, :length] = ARM
    codes[row, length - 1] = TIP
    return codes.ravel()


def _episode(rng, target, n=200, play=True, reach=False) -> Recorded:
    q = rng.uniform(-1, 1, (n, 3)).astype(np.float32)  # the third ("a velocity") does not move the arm
    if reach:  # the tip held on the target: the joints that put the tip at the target's top-left cell
        r, c = target
        q[:, :2] = [(r + 0.5) / SIDE * 2 - 1, (c + 0.5) / (SIDE - 1) * 2 - 1]
        q += rng.normal(0, 0.01, q.shape).astype(np.float32)
    codes = np.stack([_frame(x, target) for x in q])
    reward = np.zeros(n) if target is None else \
        np.array([float(np.abs(_tip_xy(x) - np.add(target, 0.5)[::-1]).max() <= 1.0) for x in q])
    return Recorded("e", {}, q, np.zeros((n, 1), np.float32), reward, np.arange(n) * 0.02, play, codes)


def _tip_xy(q: np.ndarray) -> np.ndarray:
    row, length = _arm_cells(q)
    return np.array([length - 1 + 0.5, row + 0.5])


def _targets(rng, n):
    return [(int(rng.integers(0, SIDE - 2)), int(rng.integers(0, SIDE - 3))) for _ in range(n)]


def test_the_target_is_what_the_joints_do_not_explain_and_not_the_frame_centre():
    rng = np.random.default_rng(0)
    play = [_episode(rng, t) for t in _targets(rng, 12)]
    arm = ArmModel.fit([(e.codes, e.obs) for e in play], N_CODES, 0, ArmFit(steps=300))
    assert (arm.background.reshape(SIDE, SIDE)[:, SIDE - 1] == 1).all() and (arm.background.reshape(SIDE, SIDE)[:, 0] == 0).all()
    for target in [(0, 0), (6, 1), (5, 4)]:  # corners and off-centre, none at the frame centre
        ep = _episode(rng, target, n=16)
        found = locate(evidence(arm, ep.codes, ep.obs), (SIDE, SIDE))
        assert found is not None
        want = np.array([target[1] + 1.0, target[0] + 1.0])  # the 2x2 block's centre (x, y)
        assert np.abs(found - want).max() < 0.35, (target, found)
    # a demonstration whose arm rests on its target all episode: the arm is explained, the target is not
    ep = _episode(rng, (5, 4), n=16, play=False, reach=True)
    assert np.abs(locate(evidence(arm, ep.codes, ep.obs), (SIDE, SIDE)) - [5.0, 6.0]).max() < 0.6
    # the arm alone: nothing is left unexplained
    ep = _episode(rng, None, n=16)
    assert locate(evidence(arm, ep.codes, ep.obs), (SIDE, SIDE)) is None
    # drawing: the nearest recorded arm (its own target left out) over the kept scene (a target)
    scenes = [episode_scene(arm, e, (SIDE, SIDE)) for e in play]
    pool = ArmPool(arm, np.concatenate([e.codes for e in play]), np.concatenate([e.obs for e in play]),
                   np.concatenate([np.broadcast_to(sc.cells, e.codes.shape) for sc, e in zip(scenes, play, strict=True)]),
                   np.concatenate([np.broadcast_to(sc.codes, e.codes.shape) for sc, e in zip(scenes, play, strict=True)]))
    assert pool.weights[2] < 0.2 * pool.weights[:2].min(), pool.weights  # what does not move the arm weighs little
    q = rng.uniform(-0.9, 0.9, (20, 3)).astype(np.float32)
    want = np.stack([_frame(x, (0, 0)) for x in q])
    drawn = pool.draw(q, keep=want, where=want == TARGET)
    assert (drawn == want).mean() > 0.97, (drawn != want).sum(1)


def test_the_tip_is_fitted_on_rewarded_steps_and_the_goal_is_its_distance_to_the_target():
    rng = np.random.default_rng(1)
    eps = [_episode(rng, t, n=300) for t in _targets(rng, 16)]
    eps += [_episode(rng, t, n=100, play=False, reach=True) for t in _targets(rng, 4)]
    goal = FrameGoal.fit(eps, N_CODES, (SIDE, SIDE), seed=0, tip_cfg=TipFit(steps=800), arm_cfg=ArmFit(steps=400))
    assert all(t is not None for t in goal.targets) and goal.rewarded > 100
    q = rng.uniform(-0.8, 0.8, (200, 3)).astype(np.float32)
    err = np.abs(goal.tip(q).numpy() - np.stack([_tip_xy(x) for x in q])).mean()
    assert err < 0.8, err  # cells; the reward's own tolerance is 1 cell
    bound = goal.bind(np.array([[2.5, 3.5], [6.5, 0.5]]))
    d = bound.distance(torch.from_numpy(q[:2])[:, None, None].expand(2, 3, 4, 3))
    assert d.shape == (2, 3, 4) and torch.allclose(d[0, 0, 0], (goal.tip(q[:1])[0] - torch.tensor([2.5, 3.5])).norm())


def test_demos_without_rewards_are_refused_by_name():
    rng = np.random.default_rng(2)
    eps = [_episode(rng, t, n=50) for t in _targets(rng, 3)]
    demo = _episode(rng, (2, 2), n=50, play=False)
    demo.reward[:] = 0.0
    with pytest.raises(ValueError, match="no rewarded step in the demos"):
        FrameGoal.fit([*eps, demo], N_CODES, (SIDE, SIDE), arm_cfg=ArmFit(steps=5))


def test_cell_centres_are_row_major_x_then_y():
    c = cell_centres((2, 3))
    assert c.tolist() == [[0.5, 0.5], [1.5, 0.5], [2.5, 0.5], [0.5, 1.5], [1.5, 1.5], [2.5, 1.5]]
