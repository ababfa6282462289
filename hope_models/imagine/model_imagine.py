"""`imagine --method model`: imagined episodes from a learned world model, no simulator anywhere.

    result = imagine_model_dataset("D/imagined", 50, model="D/wm", demos=["D/demos"], play=["D/play"])

1. The world model is a trained mid_loop with its action-conditioned wm_* heads (planner.WorldModel).
2. Start states: N steps drawn (seeded) from the recorded episodes, demos and play alike, each with
   its real 2 s history as the Mid Loop's context (recorded.grid_history). The goal is where the
   demos were rewarded (recorded.Goal).
3. All N episodes are rolled forward together, one grid step (100 ms) at a time. At each grid point
   the CEM planner (planner.ModelCEM) plans held commands in the model; DART's rule (Laskey et al.
   2017) as in hope_models/sim/imagine.py: what is executed is the plan's first command + N(0,
   noise^2), clipped, held for the grid step; the world model predicts where that leaves the arm.
4. The episode is written at the recordings' control period (20 ms): the grid step's 5 control
   steps hold states interpolated linearly between the grid points the model predicted (the model
   predicts at its grid; over 100 ms the reacher's state is smooth enough that a line is within the
   model's own error, measured in docs/reflex.md), and every one of them is labelled with the
   planner's command *at that state* (a fresh plan from it): the correction, as DART labels.
5. Each episode is a canonical RLDS dir: the recorded episodes' observation layout (denormalised
   with the checkpoint's statistics), action {command: the plan, source "model_planner",
   executed_command}, reward 0 (no simulator scores it; step_metadata.goal_distance says how far
   the model thinks the state is from the goal), provenance origin "imagined:model" and the tag
   "continuon.imagined", validated with the train profile before it is written.

From a camera world model (a grid mid_loop, whose wm_* heads predict the joints): the recorded
frames are encoded with its tokenizer (the Mid Loop's context reads the codes), the goal is read off
the frames (frame_goal.FrameGoal: the target is what the joints do not explain, the tip where the
rewarded steps put it; the cost is their distance in cells), each imagined step's codes are drawn
from its joints over the start frame's scene (camera_scene.CameraScene) and written as frames (the
tokenizer's decoder; write.py).

The same model, data, seed and settings give the same episodes (torch runs deterministic CPU ops).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from hope_models.imagine.camera_scene import CameraScene
from hope_models.imagine.frame_goal import FrameGoal
from hope_models.imagine.planner import ACTION_BOUNDS, ModelCEM, PlanConfig, WorldModel
from hope_models.imagine.recorded import Goal, Recorded, control_period_s, grid_history, read_recorded
from hope_models.imagine.write import ModelEpisode, episode_id_for, write_model_episode

METHOD = "model"
DEFAULT_NOISE = 0.5  # per grid step, held 100 ms (the sim's DART noise is white per 20 ms step)


@dataclass
class ModelImagineResult:
    out_dir: Path
    seed: int
    settings: dict[str, Any]
    episodes: list[dict[str, Any]] = field(default_factory=list)
    elapsed_s: float = 0.0

    def to_json_obj(self) -> dict[str, Any]:
        dist = [e["final_goal_distance"] for e in self.episodes]
        return {"out": str(self.out_dir), "method": METHOD, "origin": f"imagined:{METHOD}",
                "tag": "continuon.imagined", "seed": self.seed, "settings": self.settings,
                "mean_final_goal_distance": round(float(np.mean(dist)), 4) if dist else None,
                "steps": sum(e["steps"] for e in self.episodes), "elapsed_s": round(self.elapsed_s, 3),
                "episodes": self.episodes}


def pick_starts(eps: Sequence[Recorded], n: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """n (episode, step) start states, episodes uniformly, then a step uniformly within it."""
    out = []
    for _ in range(n):
        e = int(rng.integers(len(eps)))
        out.append((e, int(rng.integers(len(eps[e].t)))))
    return out


def _lerp(a: np.ndarray, b: np.ndarray, f: float) -> np.ndarray:
    return a + (b - a) * f


def imagine_batch(wm: WorldModel, goal: Goal | Any, eps: Sequence[Recorded], starts: list[tuple[int, int]], *,
                  steps: int, period_s: float, noise: float, plan: PlanConfig, seed: int,
                  scene: CameraScene | None = None) -> list[ModelEpisode]:
    """Roll all starts forward together (module doc, 3-4); the episodes in memory, normalised. scene:
    a camera world model's (camera_scene.py): its goal replaces `goal`, and every step gets its codes."""
    sub = int(round(wm.grid_s / period_s))
    if sub < 1 or abs(sub * period_s - wm.grid_s) > 1e-6:
        raise ValueError(f"the world model's grid step {wm.grid_s:g} s is not a whole number of the recordings' "
                         f"{period_s:g} s control periods")
    hist = [grid_history(eps[e], s, wm.k, wm.grid_s) for e, s in starts]
    h_obs, h_act, h_mask = (np.stack([h[i] for h in hist]) for i in range(3))
    h_codes = None if scene is None else scene.history_codes
    b = len(starts)
    cem = ModelCEM(wm, goal if scene is None else scene.goal, plan, seed, b)
    rng = np.random.default_rng([int(seed), 0xDA27, 3])
    out = [ModelEpisode(eps[e].episode_id, s) for e, s in starts]
    lo, hi = ACTION_BOUNDS
    obs0 = h_obs[:, -1].copy()
    for _ in range(-(-steps // sub)):
        y = wm.context(h_obs, h_act, h_mask, h_codes)
        label, cost = cem.plan(y, obs0)
        executed = np.clip(label + noise * rng.standard_normal(label.shape), lo, hi) if noise else label
        obs1 = wm.predict(y, obs0, wm.norm_act(executed)[:, None].astype(np.float32))[:, 0].numpy()
        if scene is not None:  # kept within the joints it was trained on (camera_scene.CameraScene.bounds)
            obs1 = np.clip(obs1, *scene.bounds)
        for j in range(sub):
            state = _lerp(obs0, obs1, j / sub)
            if j:
                label, cost = cem.plan(y, state)
            dist = cem.goal_distance(torch.from_numpy(state)).numpy()
            codes = None if scene is None else scene.arm(state)  # the written frame's arm layer
            for i, ep in enumerate(out):
                if len(ep.obs) < steps:
                    ep.add(state[i], label[i], executed[i], float(dist[i]), None if codes is None else codes[i])
        cem.shift()
        if scene is not None and h_codes is not None:
            h_codes = np.concatenate([h_codes[:, 1:], scene.draw(obs1)[:, None]], axis=1)
        h_obs = np.concatenate([h_obs[:, 1:], obs1[:, None]], axis=1)
        h_act = np.concatenate([h_act[:, 1:], wm.norm_act(executed).astype(np.float32)[:, None]], axis=1)
        h_mask = np.concatenate([h_mask[:, 1:], np.ones((b, 1), dtype=bool)], axis=1)
        obs0 = obs1
    return out


def imagine_model_dataset(out_dir: str | Path, episodes: int, *, model: str | Path, demos: Sequence[str | Path],
                          play: Sequence[str | Path] | None = None, seed: int = 0, noise: float = DEFAULT_NOISE,
                          steps: int = 300, plan: PlanConfig | None = None,
                          progress: Callable[[dict[str, Any]], None] | None = None) -> ModelImagineResult:
    """Imagine `episodes` episodes into out_dir (module doc). demos: recorded demos (start states
    and the goal); play: more recorded episodes for start states; None: the play episodes of the
    dataset the world model was trained on (its config.json's train.data), when it is still there."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes={episodes!r} must be a positive integer")
    if not demos:
        raise ValueError("--demos is required: the goal is where the demos were rewarded")
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise={noise!r} must be a non-negative standard deviation (command units)")
    plan = plan or PlanConfig()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out}: exists and is not a directory")
    taken = [i for i in range(episodes) if (out / episode_id_for(seed, i)).exists()]
    if taken:
        raise FileExistsError(f"{out / episode_id_for(seed, taken[0])}: episode dir already exists ({len(taken)} of "
                              f"the {episodes} would clash); imagine into another --out or from another --seed")
    t0 = time.perf_counter()
    wm = WorldModel.load(model)
    encode = wm.encode_frames if wm.grid else None  # a camera world model reads the frames too
    eps = read_recorded([*demos, *(play or ())], wm.spec, encode)
    play_from = [str(p) for p in play or ()]
    if play is None:  # the play the model saw: the play episodes of the dataset it was trained on
        seen = wm.training_data()
        if seen is not None:
            eps += [e for e in read_recorded([seen], wm.spec, encode) if e.play]
            play_from = [f"{seen} (the world model's training data, play episodes only)"]
    period = control_period_s(eps)
    rng = np.random.default_rng([int(seed), 0x57A7])
    scene = None
    goal: Any  # what the planner's cost reads: its distance(obs)
    if wm.grid:
        rows, cols = wm.model.vqvae.cfg.grid_shape
        frame_goal = FrameGoal.fit(eps, wm.model.cfg.n_codes, (int(rows), int(cols)), seed)
        located = [i for i, t in enumerate(frame_goal.targets) if t is not None]
        if not located:
            raise ValueError("no target located in any recorded episode's frames: no start state has a goal")
        starts = [(located[e], s) for e, s in pick_starts([eps[i] for i in located], episodes, rng)]
        scene = CameraScene(frame_goal, eps, starts, wm.k, wm.grid_s)
        goal_obj = {**frame_goal.to_json_obj(), "episodes_without_target": len(eps) - len(located)}
        goal = scene.goal
    else:
        starts = pick_starts(eps, episodes, rng)
        vector = Goal.from_rewarded(eps)
        goal_obj, goal = vector.to_json_obj(wm.spec.observation.dim_names()), vector
    settings = {"noise_std": noise, "steps": steps, "control_period_s": period, "model": wm.version(),
                "model_checkpoint": str(wm.checkpoint), "goal": goal_obj,
                "start_episodes": len(eps), "play_episodes": int(sum(e.play for e in eps)), "play_from": play_from,
                **ModelCEM(wm, goal, plan, seed, 1).settings()}
    result = ModelImagineResult(out, seed, settings)
    imagined = imagine_batch(wm, goal, eps, starts, steps=steps, period_s=period, noise=noise, plan=plan, seed=seed,
                             scene=scene)
    for i, ep in enumerate(imagined):
        if scene is not None:
            ep.target = [round(float(v), 4) for v in scene.targets[i]]
            ep.layers = scene.layers(i)
        rec = write_model_episode(out, ep, i, seed, wm.spec, eps[starts[i][0]].metadata, period, settings,
                                  wm.decode_codes if scene is not None else None)
        result.episodes.append(rec)
        if progress is not None:
            progress(rec)
    result.elapsed_s = time.perf_counter() - t0
    return result
