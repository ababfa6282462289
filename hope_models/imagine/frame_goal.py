"""The goal of a camera robot's recordings, without labels beyond the reward: where the target is in a
frame, and where the robot's tip is given its joints (imagination from a camera world model).

    goal = FrameGoal.fit(eps, n_codes=256, grid_shape=(16, 16), seed=0)   # eps: recorded.Recorded with codes
    goal.targets[i]                       # (x, y) of episode i's target in cell units, or None
    goal.scenes[i]                        # its target's cells and their codes (camera_scene.py draws them)
    goal.pool                             # recorded arms to draw imagined frames with (frame_draw.py)
    goal.tip(joints)                      # [..., 2]: where the tip is at those joints (normalised joints)
    goal.bind(targets).distance(obs)      # |tip(obs) - target| per episode row (cells): the planner's cost

What it assumes, in plain words (frame_arm.py for the arm model's own assumptions):
- the target does not move within an episode, and it is the one compact thing in view the joints do
  not explain: over TARGET_FRAMES frames spread through the episode, each cell's evidence is how much
  more often it is off its background code than the arm model expects at those frames' joints (less
  EXCESS_FLOOR); the target is the evidence-weighted centroid of the WINDOW x WINDOW cells holding
  the most. WINDOW is wide because a grid tokenizer's code describes a cell's neighbourhood: the
  cells 2-3 around a small object change code too (measured on the reacher's 16x16 grid);
- a rewarded step is one where the robot's tip is on the target (the reward says so): the tip's
  position as a function of the joints is a regression (a small MLP) fitted on the rewarded steps of
  every recorded episode (demos, and play when its steps carry rewards), its label the episode's
  located target. The demos must have rewarded steps (the goal is taken from them);
- nothing about the robot's kinematics or colours is written here: positions are in cells of the
  tokenizer's grid (x the column, y the row, cell centres at +0.5).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from hope_models.imagine.frame_arm import ArmFit, ArmModel
from hope_models.imagine.frame_draw import ArmPool

# the target: the WINDOW x WINDOW block holding the most evidence. Reacher camera episodes (25, 16x16
# cells): 7 locates every target within 0.74 cells of its true centre, 3 and 5 within 2-3 (the block
# sits anywhere inside the ~6-cell patch the object changes)
WINDOW = 7
EXCESS_FLOOR = 0.3  # a cell off its background in < 30 % more of the frames than the arm explains is no evidence
TARGET_FRAMES = 32  # frames spread through an episode that its target is located from
ARM_STRIDE = 2  # every 2nd recorded frame trains the arm model


def cell_centres(grid_shape: tuple[int, int]) -> np.ndarray:
    """[G, 2] (x = column, y = row) of each cell's centre, row-major as the tokenizer's cells."""
    rows, cols = grid_shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    return np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], 1).astype(np.float64)


def evidence(arm: ArmModel, codes: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Frames [n, G] of one scene and their joints [n, D] -> each cell's evidence of something the
    arm does not explain [G] (module doc)."""
    off = (codes != arm.background).astype(np.float64) - arm.off_background(joints)
    return np.clip(off.mean(0) - EXCESS_FLOOR, 0.0, None)


def locate(evidence: np.ndarray, grid_shape: tuple[int, int], window: int = WINDOW) -> np.ndarray | None:
    """Each cell's evidence [G] -> (x, y) of the compact thing it shows (module doc), or None when
    there is none."""
    w = evidence.reshape(grid_shape)
    if not (w > 0).any():
        return None
    rows, cols = grid_shape
    pad = np.pad(w, window)
    box = sum(pad[window + dy:window + dy + rows, window + dx:window + dx + cols]
              for dy in range(-(window // 2), window - window // 2) for dx in range(-(window // 2), window - window // 2))
    r, c = np.unravel_index(int(np.argmax(box)), grid_shape)
    lo_r, lo_c = r - window // 2, c - window // 2
    block = np.zeros_like(w)
    block[max(0, lo_r):lo_r + window, max(0, lo_c):lo_c + window] = 1.0
    wb = (w * block).ravel()
    return (cell_centres(grid_shape) * wb[:, None]).sum(0) / wb.sum()


@dataclass
class TipFit:
    steps: int = 1500  # at most; fewer on fewer rewarded steps (epochs passes over them, at least 50)
    epochs: float = 40.0
    batch: int = 256
    lr: float = 3e-3
    hidden: int = 64
    weight_decay: float = 1e-4


class _BoundGoal:
    def __init__(self, tip: nn.Module, targets: torch.Tensor):
        self.tip, self.targets = tip, targets

    @torch.no_grad()
    def distance(self, obs: torch.Tensor) -> torch.Tensor:
        """[B, ..., D] normalised joints -> |tip - target| [B, ...] in cells (row b: episode b's target)."""
        t = self.targets.view(self.targets.shape[0], *([1] * (obs.dim() - 2)), 2)
        return (self.tip(obs) - t).norm(dim=-1)


class FrameGoal:
    def __init__(self, arm: ArmModel, pool: ArmPool, tip: nn.Module, grid_shape: tuple[int, int],
                 scenes: list[Scene], rewarded: int, tip_error: float):
        self.arm, self.pool, self._tip, self.grid_shape = arm, pool, tip.eval(), grid_shape
        self.scenes, self.rewarded, self.tip_error = scenes, rewarded, tip_error
        self.targets = [sc.target for sc in scenes]

    @classmethod
    def fit(cls, eps: Sequence[Any], n_codes: int, grid_shape: tuple[int, int], seed: int = 0,
            tip_cfg: TipFit | None = None, arm_cfg: ArmFit | None = None) -> "FrameGoal":
        """eps: recorded episodes with codes [T, G] and obs [T, D] (normalised joints)."""
        if not any((e.reward > 0).any() for e in eps if not e.play):
            raise ValueError("no rewarded step in the demos: the goal (where the tip is on the target) is read off "
                             "the steps they were rewarded on; record demos with rewards")
        arm_eps = [i for i, e in enumerate(eps) if e.play] or list(range(len(eps)))
        arm = ArmModel.fit([(eps[i].codes[::ARM_STRIDE], eps[i].obs[::ARM_STRIDE]) for i in arm_eps], n_codes, seed,
                           arm_cfg)
        scenes = [episode_scene(arm, e, grid_shape) for e in eps]
        targets = [sc.target for sc in scenes]
        shapes = [eps[i].codes[::ARM_STRIDE].shape for i in arm_eps]
        pool = ArmPool(arm, np.concatenate([eps[i].codes[::ARM_STRIDE] for i in arm_eps]),
                       np.concatenate([eps[i].obs[::ARM_STRIDE] for i in arm_eps]),
                       np.concatenate([np.broadcast_to(scenes[i].cells, sh) for i, sh in zip(arm_eps, shapes, strict=True)]),
                       np.concatenate([np.broadcast_to(scenes[i].codes, sh) for i, sh in zip(arm_eps, shapes, strict=True)]))
        q = [e.obs[e.reward > 0] for e, t in zip(eps, targets, strict=True) if t is not None]
        xy = [np.repeat(t[None], int((e.reward > 0).sum()), 0) for e, t in zip(eps, targets, strict=True)
              if t is not None]
        rows = np.concatenate(q) if q else np.zeros((0, eps[0].obs.shape[1]))
        if not len(rows):
            raise ValueError("no target located in any rewarded episode: nothing in their frames is left "
                             "unexplained by the arm model")
        tip, err = _fit_tip(rows, np.concatenate(xy), seed, tip_cfg or TipFit())
        return cls(arm, pool, tip, grid_shape, scenes, int(len(rows)), err)

    @torch.no_grad()
    def tip(self, joints: np.ndarray | torch.Tensor) -> torch.Tensor:
        return self._tip(torch.as_tensor(joints, dtype=torch.float32))

    def bind(self, targets: np.ndarray) -> _BoundGoal:
        """The goal of a batch of episodes: row b's target targets[b] (x, y)."""
        return _BoundGoal(self._tip, torch.as_tensor(np.asarray(targets), dtype=torch.float32))

    def to_json_obj(self) -> dict[str, Any]:
        return {"kind": "frame", "rewarded_steps": self.rewarded, "tip_fit_rms_cells": round(self.tip_error, 4),
                "arm_model": {"frames": self.arm.frames, "cross_entropy": round(self.arm.loss, 4),
                              "joint_weights": [round(float(w), 4) for w in self.pool.weights]},
                "grid": list(self.grid_shape), "excess_floor": EXCESS_FLOOR, "window": WINDOW,
                "assumes": "a static camera and target; the target is what the joints do not explain; a rewarded "
                           "step has the tip on the target"}


@dataclass
class Scene:
    """What one recorded episode shows beside the arm: its target's position (cells, or None), the
    cells holding it and their codes (each cell's most frequent code over the frames looked at)."""
    target: np.ndarray | None
    cells: np.ndarray  # [G] bool
    codes: np.ndarray  # [G]


def episode_scene(arm: ArmModel, ep: Any, grid_shape: tuple[int, int]) -> Scene:
    """One recorded episode's scene, from TARGET_FRAMES frames spread through it (module doc)."""
    idx = np.unique(np.linspace(0, len(ep.obs) - 1, TARGET_FRAMES).round().astype(int))
    codes = ep.codes[idx]
    ev = evidence(arm, codes, ep.obs[idx])
    mode = np.array([np.bincount(codes[:, g]).argmax() for g in range(codes.shape[1])])
    return Scene(locate(ev, grid_shape), ev > 0, mode)


def _fit_tip(q: np.ndarray, xy: np.ndarray, seed: int, cfg: TipFit) -> tuple[nn.Module, float]:
    """A small MLP joints -> (x, y), fitted on the rewarded steps; its RMS error on them (cells)."""
    torch.manual_seed(seed)
    head = nn.Linear(cfg.hidden, 2)
    net = nn.Sequential(nn.Linear(q.shape[1], cfg.hidden), nn.SiLU(), nn.Linear(cfg.hidden, cfg.hidden), nn.SiLU(), head)
    x, y = torch.from_numpy(q.astype(np.float32)), torch.from_numpy(xy.astype(np.float32))
    with torch.no_grad():
        head.bias.copy_(y.mean(0))
    opt = torch.optim.AdamW(net.parameters(), cfg.lr, weight_decay=cfg.weight_decay)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(int(min(cfg.steps, max(50, np.ceil(cfg.epochs * len(x) / cfg.batch))))):
        i = torch.randint(0, len(x), (min(cfg.batch, len(x)),), generator=gen)
        loss = ((net(x[i]) - y[i]) ** 2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        err = float(((net(x) - y) ** 2).sum(-1).mean().sqrt())
    return net.eval(), err


__all__ = ["EXCESS_FLOOR", "FrameGoal", "Scene", "TipFit", "WINDOW", "cell_centres", "episode_scene", "evidence", "locate"]
