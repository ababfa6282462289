"""The learned world model (a trained mid_loop with its wm_* heads) and a CEM planner inside it.

    wm = WorldModel.load("runs/wm")            # a run dir holding mid_loop/, the mid_loop run, or a checkpoint
    y = wm.context(hist_obs, hist_act, mask)    # [B, d] at the last grid point of each window
    cem = ModelCEM(wm, goal, PlanConfig(), seed=0, batch=B)
    label, cost = cem.plan(y, obs)              # raw commands [B, A] (the first held action of the plan)

Everything is in the checkpoint's normalised units except the commands, which the planner samples
in the action's own units and clips to [-1, 1] (ACTION_BOUNDS: the commands a robot's action spec
allows; the reacher's). One plan step is one grid step of the Mid Loop's window (100 ms): the world
model predicts what holding each action for a grid step does (mid_loop.py, "World model").

CEM as the simulator's planner does it (hope_models/sim/imagine.py): the current plan and "do
nothing" always compete, the perturbations are drawn once (common random numbers) so the plan is a
smooth function of the state, and the plan is warm-started from the previous one. Cost: the sum
over the plan's steps of the goal's Mahalanobis distance (recorded.Goal), + action_cost x |u|^2.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from hope_models.checkpoint_format import CONFIG_FILE, MODEL_FILE, read_json_object
from hope_models.checkpoints import latest_complete
from hope_models.components import PREDICTOR
from hope_models.components.mid_loop.model import MidLoop, previous_actions
from hope_models.durable import file_sha256
from hope_models.imagine.recorded import Goal

ACTION_BOUNDS = (-1.0, 1.0)


@dataclass
class PlanConfig:
    horizon: int = 3  # grid steps (<= the world model's wm_horizon)
    population: int = 32
    iterations: int = 2
    elites: int = 6
    init_std: float = 0.6  # command units
    min_std: float = 0.05
    action_cost: float = 0.01

    def validate(self, wm_horizon: int) -> None:
        for name in ("horizon", "population", "iterations", "elites"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"plan {name}={v!r} must be a positive integer")
        if self.horizon > wm_horizon:
            raise ValueError(f"plan horizon={self.horizon} exceeds the world model's wm_horizon={wm_horizon}")
        if self.elites > self.population or self.population < 3:
            raise ValueError(f"plan elites={self.elites} must be <= population={self.population} (>= 3)")
        if not (self.init_std > 0 and self.min_std >= 0 and self.action_cost >= 0):
            raise ValueError("plan init_std must be > 0, min_std and action_cost >= 0")


def find_mid_loop_checkpoint(path: str | Path) -> Path:
    """A checkpoint dir, a mid_loop run dir, or a `train --sequential` run dir holding mid_loop/ ->
    the newest complete mid_loop checkpoint dir."""
    p = Path(path)
    if (p / "config.json").is_file():
        return p
    for run in (p, p / PREDICTOR):
        if (run / "checkpoints").is_dir():
            ckpt = latest_complete(run)
            if ckpt is not None:
                return ckpt
    raise FileNotFoundError(f"{p}: no mid_loop checkpoint (expected a checkpoint dir, a mid_loop run dir, or a "
                            "`train --sequential ...,mid_loop` run dir with mid_loop/ in it)")


class WorldModel:
    def __init__(self, component, checkpoint: Path):
        model: MidLoop = component.model
        if component.name != PREDICTOR:
            raise ValueError(f"{checkpoint}: a {component.name} checkpoint, not a {PREDICTOR}")
        self.grid = bool(getattr(model, "grid", False))  # over a grid frame VQ-VAE: a camera world model
        if not model.has_world_model:
            raise ValueError(f"{checkpoint}: this mid_loop has no world model (no wm_* heads: trained with "
                             f"wm_horizon 0{', or a grid mid_loop made before its world model' if self.grid else ''}); "
                             "retrain it with the default model_config")
        self.component, self.checkpoint = component, checkpoint
        self.model: Any = model.eval()  # a MidLoop, or a GridMidLoop (self.grid): their context() differ
        self.spec, self.window = component.spec, component.window
        self.grid_s, self.k = self.window.grid_step_s, self.window.k
        self.act_mean = np.asarray(self.spec.action.mean, dtype=np.float32)
        self.act_std = np.asarray(self.spec.action.std, dtype=np.float32)

    @classmethod
    def load(cls, path: str | Path) -> "WorldModel":
        from hope_models.components.build import component_from_checkpoint  # lazy: loads safetensors

        ckpt = find_mid_loop_checkpoint(path)
        return cls(component_from_checkpoint(ckpt), ckpt)

    def training_data(self) -> Path | None:
        """The dataset the mid_loop was trained on (its config.json's train.data), if it is still there."""
        train = read_json_object(self.checkpoint / CONFIG_FILE).get("train")
        data = train.get("data") if isinstance(train, dict) else None
        return Path(data) if isinstance(data, str) and Path(data).is_dir() else None

    def version(self) -> str:
        return f"{self.checkpoint.parent.parent.name}@{self.checkpoint.name}:{file_sha256(self.checkpoint / MODEL_FILE)[:12]}"

    def norm_act(self, u: np.ndarray | torch.Tensor):
        return (u - self.act_mean) / self.act_std

    def raw_act(self, a: np.ndarray) -> np.ndarray:
        return a * self.act_std + self.act_mean

    @torch.no_grad()
    def encode_frames(self, frames: np.ndarray) -> np.ndarray:
        """A camera world model's frames [n, H, W, 3] uint8 -> its tokenizer's codes [n, G]."""
        return self.model.vqvae.encode(torch.from_numpy(np.ascontiguousarray(frames))).numpy()

    @torch.no_grad()
    def decode_codes(self, codes: np.ndarray) -> np.ndarray:
        """A grid tokenizer's cell codes [n, G] -> frames [n, H, W, 3] uint8 (its frozen decoder)."""
        pixels = self.model.vqvae.decode(torch.from_numpy(np.ascontiguousarray(codes, dtype=np.int64)))
        return (pixels.permute(0, 2, 3, 1).clamp(0.0, 1.0).numpy() * 255.0 + 0.5).astype(np.uint8)

    @torch.no_grad()
    def context(self, obs: np.ndarray, act: np.ndarray, mask: np.ndarray, codes: np.ndarray | None = None
                ) -> torch.Tensor:
        """Windows obs [B, K, D], held actions [B, K, A] (normalised), mask [B, K] (and a camera world
        model's codes [B, K, G]) -> context at the last point [B, d]."""
        o, a = torch.from_numpy(np.ascontiguousarray(obs)), torch.from_numpy(np.ascontiguousarray(act))
        m = torch.from_numpy(np.ascontiguousarray(mask))
        if self.grid:
            if codes is None:
                raise ValueError("a camera world model's context needs the window's codes")
            return self.model.context(torch.from_numpy(np.ascontiguousarray(codes, dtype=np.int64)),
                                      previous_actions(a), o, m)[:, -1]
        return self.model.context(self.model.codes(o), previous_actions(a), m)[:, -1]

    @torch.no_grad()
    def predict(self, y: torch.Tensor, obs: np.ndarray | torch.Tensor, actions: np.ndarray | torch.Tensor) -> torch.Tensor:
        """y [..., d], obs [..., D] normalised, normalised actions held [..., M, A] -> obs after each [..., M, D]."""
        return self.model.wm_predict(y, torch.as_tensor(obs, dtype=torch.float32),
                                     torch.as_tensor(actions, dtype=torch.float32))


class ModelCEM:
    """CEM over held command sequences, scored by the world model against the goal (module doc)."""

    def __init__(self, wm: WorldModel, goal: Goal | Any, cfg: PlanConfig, seed: int, batch: int):
        cfg.validate(wm.model.cfg.wm_horizon)
        self.wm, self.cfg, self.batch = wm, cfg, batch
        a = len(wm.act_mean)
        rng = np.random.default_rng([int(seed), 0xC3E, 7])
        self._noise = torch.from_numpy(rng.standard_normal((cfg.iterations, cfg.population, cfg.horizon, a))
                                       .astype(np.float32))
        self._goal = goal  # its distance(obs [B, ..., D]) is the cost of a state
        self.mean = torch.zeros(batch, cfg.horizon, a)
        self._act_mean = torch.from_numpy(wm.act_mean)
        self._act_std = torch.from_numpy(wm.act_std)

    def settings(self) -> dict[str, Any]:
        what = ("the distance (cells) from the tip the joints put in the frame to the target the frame shows"
                if self.wm.grid else "the goal's Mahalanobis distance (normalised observation)")
        return {"plan": asdict(self.cfg), "cost": f"sum over the plan of {what} + action_cost x |command|^2",
                "plan_step_s": self.wm.grid_s}

    def goal_distance(self, obs: torch.Tensor) -> torch.Tensor:
        """[B, ..., D] normalised -> the goal's distance [B, ...]."""
        return self._goal.distance(obs)

    @torch.no_grad()
    def plan(self, y: torch.Tensor, obs: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        """From context y [B, d] and observation [B, D]: (the plan's first command [B, A] raw, its cost [B]).
        The rest of the plan stays as the warm start of the next call (shift() moves it one step)."""
        cfg = self.cfg
        lo, hi = ACTION_BOUNDS
        obs = torch.as_tensor(obs, dtype=torch.float32)
        b = obs.shape[0]
        h0 = self.wm.model.wm_encode(y, obs)[:, None]  # once per state, shared by its candidates
        mu, sd = self.mean.clone(), torch.full_like(self.mean, cfg.init_std)
        best = torch.zeros(b)
        for it in range(cfg.iterations):
            u = (mu[:, None] + sd[:, None] * self._noise[it][None]).clamp(lo, hi)  # [B, P, M, A]
            u[:, 0] = mu.clamp(lo, hi)  # the current plan always competes
            u[:, 1] = 0.0  # and so does doing nothing
            pred = self.wm.model.wm_unroll(h0, obs[:, None], (u - self._act_mean) / self._act_std)  # [B, P, M, D]
            cost = self.goal_distance(pred).sum(-1) + cfg.action_cost * (u ** 2).sum((-1, -2))
            order = cost.argsort(dim=1, stable=True)[:, :cfg.elites]
            elite = torch.gather(u, 1, order[..., None, None].expand(-1, -1, *u.shape[2:]))
            mu, sd = elite.mean(1), elite.std(1, unbiased=False) + cfg.min_std
            best = cost.gather(1, order[:, :1])[:, 0]
        self.mean = mu
        return mu[:, 0].clamp(lo, hi).numpy().astype(np.float64), best.numpy()

    def shift(self) -> None:
        """One grid step has passed: the plan's second step becomes its first."""
        self.mean = torch.cat([self.mean[:, 1:], self.mean[:, -1:]], dim=1)
