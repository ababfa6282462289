"""What a camera shows of the robot, read off its recordings: each cell's background code and the
arm's look as a function of the joints, for imagining from a camera world model (frame_goal.py).

    arm = ArmModel.fit([(codes, joints), ...], n_codes)   # per episode: codes [T, G], joints [T, D] normalised
    arm.off_background(joints)                        # [N, G] P(a cell is off its background | joints)

What it assumes, in plain words:
- the camera does not move: a cell shows the same thing (its background code, the cell's most frequent
  code over the recordings) unless something is in front of it;
- the robot's own body is a function of its joints: P(code of cell g | joints) is learned from the
  recorded frames (a small MLP to a rank-r code space shared by every cell, plus a bias per cell and
  code). Whatever else is in view and does not follow the joints (a target) is what the model cannot
  explain (frame_goal.py).
- what stays put in an episode while the arm moves is not the arm: before the model is fitted, the
  cells of each training episode that are not their background code in >= STATIC_SHARE of its
  frames are set to their background code (a target would otherwise be a common sight there).
It is trained on play when there is play: there the arm moves and the rest of the scene is
uncorrelated with the joints, while demonstrations hold the arm on the target, which would teach it
that the target is part of the arm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

STATIC_SHARE = 0.9  # a cell off its background this often in an episode holds something that is not the arm


def background_codes(codes: np.ndarray, n_codes: int) -> np.ndarray:
    """Each cell's most frequent code over frames [N, G] -> [G]."""
    counts = np.zeros((codes.shape[1], n_codes))
    np.add.at(counts, (np.broadcast_to(np.arange(codes.shape[1]), codes.shape), codes), 1.0)
    return counts.argmax(1)


def without_static(codes: np.ndarray, background: np.ndarray) -> np.ndarray:
    """One episode's codes [T, G] with the cells that stay off their background (module doc) set to it."""
    static = (codes != background).mean(0) >= STATIC_SHARE
    return np.where(static, background, codes)


class _ArmNet(nn.Module):
    def __init__(self, obs_dim: int, groups: int, n_codes: int, hidden: int, rank: int):
        super().__init__()
        self.groups, self.rank = groups, rank
        self.net = nn.Sequential(nn.Linear(obs_dim, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
                                 nn.Linear(hidden, groups * rank))
        self.code = nn.Linear(rank, n_codes, bias=False)  # shared by every cell: a piece of arm looks the same anywhere
        self.bias = nn.Parameter(torch.zeros(groups, n_codes))

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """joints [N, D] -> logits [N, G, n_codes]."""
        return self.code(self.net(q).view(-1, self.groups, self.rank)) + self.bias


@dataclass
class ArmFit:
    # 3000 steps, rank 32, hidden 256: on 20 reacher play episodes (16x16 cells, 256 codes) the targets
    # of 25 episodes are located within 0.74 cells (600 steps, rank 16, hidden 128: 3.5 cells on a demo
    # whose arm rests on its target all episode); ~160 s on one core
    steps: int = 3000  # at most; fewer on fewer frames (epochs passes over them, at least 50)
    epochs: float = 20.0
    batch: int = 64
    lr: float = 3e-3
    hidden: int = 256
    rank: int = 32

    def steps_for(self, n: int) -> int:
        return int(min(self.steps, max(50, np.ceil(self.epochs * n / self.batch))))


class ArmModel:
    def __init__(self, net: _ArmNet, background: np.ndarray, n_codes: int, frames: int, loss: float):
        self.net, self.background, self.n_codes = net.eval(), background, n_codes
        self.frames, self.loss = frames, loss  # how many frames it was fitted on, its final cross-entropy

    @classmethod
    def fit(cls, episodes: list[tuple[np.ndarray, np.ndarray]], n_codes: int, seed: int = 0,
            cfg: ArmFit | None = None) -> "ArmModel":
        """episodes: (codes [T, G] of recorded frames, joints [T, D] (normalised) at them) each."""
        cfg = cfg or ArmFit()
        if sum(len(c) for c, _ in episodes) < 2:
            raise ValueError("the arm model needs recorded frames: fewer than 2 were given")
        background = background_codes(np.concatenate([c for c, _ in episodes]), n_codes)
        codes = np.concatenate([without_static(c, background) for c, _ in episodes])
        joints = np.concatenate([q for _, q in episodes])
        n, g = codes.shape
        counts = np.zeros((g, n_codes))
        np.add.at(counts, (np.broadcast_to(np.arange(g), codes.shape), codes), 1.0)
        torch.manual_seed(seed)
        net = _ArmNet(joints.shape[1], g, n_codes, cfg.hidden, cfg.rank)
        with torch.no_grad():  # start from each cell's code frequencies: the background is right from step 0
            net.bias.copy_(torch.from_numpy(np.log((counts + 0.1) / (counts + 0.1).sum(1, keepdims=True))))
        opt = torch.optim.Adam(net.parameters(), cfg.lr)
        gen = torch.Generator().manual_seed(seed)
        c, q = torch.from_numpy(codes.astype(np.int64)), torch.from_numpy(joints.astype(np.float32))
        loss = torch.zeros(())
        for _ in range(cfg.steps_for(n)):
            i = torch.randint(0, n, (min(cfg.batch, n),), generator=gen)
            loss = nn.functional.cross_entropy(net(q[i]).flatten(0, 1), c[i].reshape(-1))
            opt.zero_grad()
            loss.backward()
            opt.step()
        return cls(net, background, n_codes, n, float(loss.detach()))

    @torch.no_grad()
    def log_probs(self, joints: np.ndarray | torch.Tensor) -> torch.Tensor:
        """[N, D] -> log P(code | joints) [N, G, n_codes]."""
        return self.net(torch.as_tensor(joints, dtype=torch.float32)).log_softmax(-1)

    @torch.no_grad()
    def off_background(self, joints: np.ndarray, chunk: int = 256) -> np.ndarray:
        """P(each cell's code is not its background code | joints) [N, G]: where the arm is expected."""
        bg = torch.from_numpy(self.background.astype(np.int64))
        out = [1.0 - self.log_probs(joints[s:s + chunk]).gather(-1, bg.expand(len(joints[s:s + chunk]), -1)[..., None])
               [..., 0].exp() for s in range(0, len(joints), chunk)]
        return torch.cat(out).numpy() if out else np.zeros((0, len(self.background)), np.float32)


__all__ = ["ArmFit", "ArmModel", "STATIC_SHARE", "background_codes", "without_static"]
