"""Imagined rollouts: offline search in the simulator from start states the demos never saw, as RLDS.

    result = imagine_dataset("datasets/imag50", episodes=50, method="dart", task="reach")
    result.paths, result.mean_return

Two searches, both using the reacher simulator itself as the model, and one labelling rule:

- **dart** (Laskey et al. 2017, "DART: Noise Injection for Robust Imitation Learning"). The expert
  is the searcher: at each visited state it gives the corrective command toward the target.
- **cem** (cross-entropy method, model-predictive control; no expert involved). At every control
  step the physics state is cloned (mj_getState, the full physics state) and
  CEMConfig.population candidate action sequences over CEMConfig.horizon steps are rolled out in
  the simulator (mujoco.rollout: the env's own MuJoCo model and integrator); the cost is the summed
  fingertip-to-target distance (+ a small command penalty); the elites refit a Gaussian for
  CEMConfig.iterations rounds; the first action of the final mean is the searcher's command. The
  current plan and the all-zero sequence are always candidates, and the perturbations are drawn
  once per episode (common random numbers), which keeps the commands smooth in the state. On the
  track task the planner knows the target's circle (the task's target_xy(t)): the simulator is
  the model, target motion included.

Labelling (DART's rule, for both): what is *executed* is the searcher's command plus Gaussian noise
N(0, noise^2), clipped to [-1, 1]; what is *recorded* as the label `action.command` is the
searcher's command at the state actually visited, i.e. the correction back toward the target, not
the noisy command (which is kept beside it as `action.executed_command`, as the recorder does for
its noisy demos; the feature spec takes `action.command` as the action). The rollouts thus cover
the states a wrong policy drifts into, each labelled with what the searcher would do there.
noise = 0 records the searcher's own trajectories (labels = executed commands).

Noise: DART_NOISE_STD = 2.0 for both methods, chosen by measurement (docs/reflex.md, "Imagined
rollouts"): a fast_loop trained on 5 demos + 50 imagined rollouts scores 216 (demos alone) -> 641
(dart, noise 0) -> 975 (0.5) -> 981 (1.0) -> 983 (2.0) on 20 held-out seeds (expert 986); with the
earlier world-frame observation only 2.0 reached ~980. The expert still scores ~940 while driven
with noise 2.0, so the rollouts mostly reach the target. The noise is large against the [-1, 1]
command range because the arm low-passes white noise at 50 Hz (0.5 costs the expert ~2 points).

Start states. Episode i uses the task seed `seed + i` (from DEFAULT_SEED_BASE); imagine_dataset
refuses seeds that evaluation or the demos use (seed_ranges.py says which, and how).

Each episode is a canonical RLDS v1.1 dir with the recorder's layout (observation block, action
{command, source, executed_command}, reward, 20 ms timestamps; optional 64x64 frames as .npy
blobs), provenance origin `imagined:<method>` and the tag `continuon.imagined` in metadata.tags
(so Episode.is_imagined and the sampler's imagined pool see it), validated with the train profile
before it is written (an error there is a bug and raises). The same (method, task, seed, settings)
gives the same episode, byte for byte.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from hope_models.rlds.episode import Episode
from hope_models.rlds.validation_report import episode_report
from hope_models.rlds.write_episode_dir import safe_episode_id, write_episode_dir
from hope_models.sim.expert import ExpertController
from hope_models.sim.reacher import (
    ACT_DIM,
    ACTION_HIGH,
    ACTION_LOW,
    CONTROL_PERIOD_S,
    EPISODE_STEPS,
    LINK_LENGTHS_M,
    TASKS,
    make_env,
)
from hope_models.sim.recorder import rollout, sim_metadata, software_versions
from hope_models.sim.seed_ranges import DEFAULT_SEED_BASE, check_seeds

METHODS = ("dart", "cem")
IMAGINED_TAG = "continuon.imagined"
DART_NOISE_STD = 2.0  # std of the Gaussian injected into executed commands (see the module doc)
DEFAULT_NOISE = {"dart": DART_NOISE_STD, "cem": DART_NOISE_STD}


def origin_for(method: str) -> str:
    return f"imagined:{method}"


@dataclass
class CEMConfig:
    horizon: int = 12  # steps (0.24 s)
    population: int = 32  # candidate sequences per iteration
    iterations: int = 2
    elites: int = 6
    init_std: float = 0.5  # of the sampling Gaussian at each control step (commands are in [-1, 1])
    min_std: float = 0.05  # added to the elites' std so the search never collapses
    action_cost: float = 0.01  # x sum of squared commands, per step (m-equivalent)
    velocity_cost: float = 0.0  # x sum of squared joint velocities (rad/s), per step

    def validate(self) -> None:
        for name in ("horizon", "population", "iterations", "elites"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"cem {name}={v!r} must be a positive integer")
        if self.elites > self.population:
            raise ValueError(f"cem elites={self.elites} must be <= population={self.population}")
        for name in ("init_std", "min_std", "action_cost", "velocity_cost"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"cem {name}={v!r} must be a non-negative number")
        if self.init_std == 0:
            raise ValueError("cem init_std must be > 0")


# -- the two searches ----------------------------------------------------------------------------

def fingertip_xy(qpos: np.ndarray) -> np.ndarray:
    """Fingertip position(s) from joint angles [..., 2] (two-link forward kinematics) -> [..., 2]."""
    l1, l2 = LINK_LENGTHS_M
    a = qpos[..., 0]
    b = a + qpos[..., 1]
    return np.stack([l1 * np.cos(a) + l2 * np.cos(b), l1 * np.sin(a) + l2 * np.sin(b)], axis=-1)


def _check_noise(noise: float) -> float:
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not np.isfinite(noise) or noise < 0:
        raise ValueError(f"noise={noise!r} must be a non-negative standard deviation (command units)")
    return float(noise)


class _NoiseInjection:
    """DART's rule for both searches: execute clip(label + N(0, noise^2)), record the label (the
    searcher's action at the state actually visited) and the executed command beside it."""

    def __init__(self, seed: int, noise: float, stream: int):
        self.noise = _check_noise(noise)
        self._rng = np.random.default_rng([int(seed), 0xDA27, stream])  # not the recorder's stream

    def apply(self, label: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        if self.noise == 0:
            return label, {}
        executed = np.clip(label + self._rng.normal(0.0, self.noise, ACT_DIM), ACTION_LOW, ACTION_HIGH)
        return executed, {"executed_command": [float(v) for v in executed]}


class DartSearch:
    """The expert with noise injected into what is executed; labels are the expert's actions."""

    method = "dart"

    def __init__(self, env, seed: int, noise: float = DART_NOISE_STD):
        self.env = env
        self.inject = _NoiseInjection(seed, noise, 1)
        self.expert = ExpertController()

    def settings(self) -> dict[str, Any]:
        return {"noise_std": self.inject.noise, "label": "expert action at the visited state",
                "expert": self.expert.config()}

    def choose(self, obs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, dict[str, Any], dict[str, Any]]:
        """(label, executed, extra action keys, step_metadata) at the current state."""
        label = np.clip(np.asarray(self.expert.act(obs), dtype=np.float64), ACTION_LOW, ACTION_HIGH)
        executed, extra = self.inject.apply(label)
        return label, executed, extra, {}


class CEMPlanner:
    """Sampling-based MPC with the simulator as the model (see the module doc)."""

    method = "cem"

    def __init__(self, env, seed: int, cfg: CEMConfig | None = None, noise: float = 0.0):
        import mujoco  # lazy: loads mujoco
        from mujoco import rollout  # lazy: loads mujoco

        self.cfg = cfg or CEMConfig()
        self.cfg.validate()
        self.env = env
        self._mujoco, self._rollout = mujoco, rollout
        self.model = env.physics.model.ptr
        self.data = env.physics.data.ptr
        self.scratch = mujoco.MjData(self.model)  # rollouts never touch the env's own data
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.nstate = mujoco.mj_stateSize(self.model, self.spec)
        nq = self.model.nq
        # mjSTATE_FULLPHYSICS = [time, qpos, qvel, act, history, plugin state]
        self._qpos = slice(1, 1 + nq)
        self._qvel = slice(1 + nq, 1 + nq + self.model.nv)
        if self.model.nu != ACT_DIM:
            raise RuntimeError(f"the reacher model has {self.model.nu} actuators, expected {ACT_DIM}")
        rng = np.random.default_rng([int(seed), 0xCE3, 1])
        # Common random numbers: one draw of the standard-normal perturbations per episode, reused at
        # every control step. The plan is then a smooth function of the state and the warm start,
        # and the recorded labels are far less jittery than with fresh samples each step (which
        # a cloned policy would have to average out).
        self._noise = rng.standard_normal((self.cfg.iterations, self.cfg.population, self.cfg.horizon, ACT_DIM))
        self._target_fn = getattr(env.task, "target_xy", None)  # track: the target's circle
        self.mean = np.zeros((self.cfg.horizon, ACT_DIM))
        self.last_cost = float("nan")
        self.inject = _NoiseInjection(seed, noise, 2)

    def settings(self) -> dict[str, Any]:
        return {"cem": asdict(self.cfg), "noise_std": self.inject.noise, "label": "the plan's first action at "
                "the visited state", "cost": "sum over the horizon of |fingertip - target| (m) "
                "+ action_cost x |command|^2", "model": "the reacher's own MuJoCo model (mujoco.rollout)"}

    def _targets(self, t0: float) -> np.ndarray:
        """Target centre at the end of each horizon step [H, 2]."""
        h = self.cfg.horizon
        if self._target_fn is None:
            return np.broadcast_to(self.env.target_xy(), (h, 2))
        return np.array([self._target_fn(t0 + (k + 1) * CONTROL_PERIOD_S) for k in range(h)])

    def state(self) -> np.ndarray:
        s = np.empty(self.nstate)
        self._mujoco.mj_getState(self.model, self.data, s, self.spec)
        return s

    def rollout(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """Physics states after each step of each control sequence: [P, H, 2] -> [P, H, nstate]."""
        states, _ = self._rollout.rollout(self.model, self.scratch, state, np.ascontiguousarray(controls))
        return states

    def predict(self, state: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """Fingertip positions after each step of each control sequence: [P, H, 2] -> [P, H, 2]."""
        return fingertip_xy(self.rollout(state, controls)[..., self._qpos])

    def costs(self, states: np.ndarray, controls: np.ndarray, targets: np.ndarray) -> np.ndarray:
        tips = fingertip_xy(states[..., self._qpos])
        cost = np.linalg.norm(tips - targets[None], axis=-1).sum(axis=1)
        cost += self.cfg.action_cost * np.square(controls).sum(axis=(1, 2))
        if self.cfg.velocity_cost:
            cost += self.cfg.velocity_cost * np.square(states[..., self._qvel]).sum(axis=(1, 2))
        return cost

    def choose(self, obs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, dict[str, Any], dict[str, Any]]:
        cfg = self.cfg
        s0 = self.state()
        targets = self._targets(float(s0[0]))
        mu = self.mean.copy()
        sd = np.full_like(mu, cfg.init_std)
        for it in range(cfg.iterations):
            u = np.clip(mu + sd * self._noise[it], ACTION_LOW, ACTION_HIGH)
            u[0] = np.clip(mu, ACTION_LOW, ACTION_HIGH)  # the current plan always competes
            if cfg.population > 1:
                u[1] = 0.0  # and so does doing nothing (holding on the target)
            cost = self.costs(self.rollout(s0, u), u, targets)
            elite = u[np.argsort(cost, kind="stable")[:cfg.elites]]
            mu = elite.mean(axis=0)
            sd = elite.std(axis=0) + cfg.min_std
            self.last_cost = float(cost.min())
        label = np.clip(mu[0], ACTION_LOW, ACTION_HIGH)
        self.mean = np.vstack([mu[1:], mu[-1:]])  # warm start: the rest of the plan, shifted
        executed, extra = self.inject.apply(label)
        return label, executed, extra, {"plan_cost": round(self.last_cost, 6)}


def make_search(method: str, env, seed: int, noise: float | None = None, cem: CEMConfig | None = None):
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not one of {', '.join(METHODS)}")
    noise = DEFAULT_NOISE[method] if noise is None else noise
    if method == "dart":
        return DartSearch(env, seed, noise)
    if method == "cem":
        return CEMPlanner(env, seed, cem, noise)
    raise ValueError(f"method {method!r} is not one of {', '.join(METHODS)}")


# -- one episode ---------------------------------------------------------------------------------

def episode_id_for(method: str, task: str, seed: int, prefix: str = "imagined") -> str:
    return safe_episode_id(f"{prefix}-{method}-{task}-s{seed:06d}")


def imagine_episode(task: str, seed: int, method: str = "dart", *, noise: float | None = None,
                    cem: CEMConfig | None = None, steps: int = EPISODE_STEPS, frames: bool = False,
                    frame_dir: str | Path | None = None, episode_id: str | None = None) -> tuple[Episode, float]:
    """One imagined episode in memory (frames saved under frame_dir/blobs/) and the return of
    what was executed. noise=None: the method's default (DEFAULT_NOISE)."""
    if task not in TASKS:
        raise ValueError(f"task {task!r} is not one of {', '.join(TASKS)}")
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not one of {', '.join(METHODS)}")
    if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= EPISODE_STEPS:
        raise ValueError(f"steps={steps!r} must be an integer within 1-{EPISODE_STEPS}")
    if frames and frame_dir is None:
        raise ValueError("frames=True needs frame_dir, where the .npy frames are written before the episode dir")
    env = make_env(task, seed, frames=frames)
    obs = env.reset()
    search = make_search(method, env, seed, noise, cem)
    source = "sim_expert" if method == "dart" else "sim_planner"
    out, total = rollout(env, obs, search.choose, source, steps, frame_dir if frames else None)
    origin = origin_for(method)
    ep_id = episode_id or episode_id_for(method, task, seed)
    metadata = sim_metadata(ep_id, task, source, [IMAGINED_TAG, f"imagined_{method}"],
                            software_versions("imagine", "hope_models.sim.imagine"), len(out), {
                                "origin": origin,
                                "imagined": {"method": method, **search.settings()},
                                "sim": {"domain": "reacher", "task": task, "seed": int(seed),
                                        "control_period_s": CONTROL_PERIOD_S, "noise_std": search.inject.noise,
                                        "policy": method, "return": total},
                            })
    ep = Episode(ep_id, metadata, out, source=f"{origin}#{ep_id}", layout="sim",
                 blob_root=str(frame_dir) if frames else None)
    return ep, total


# -- a dataset -----------------------------------------------------------------------------------

@dataclass
class ImaginedEpisode:
    path: Path
    episode_id: str
    seed: int
    ret: float
    steps: int
    status: str  # the train-profile verdict (accepted / accepted_with_warnings)

    def to_json_obj(self) -> dict[str, Any]:
        return {"episode_id": self.episode_id, "path": str(self.path), "seed": self.seed,
                "return": self.ret, "steps": self.steps, "status": self.status}


@dataclass
class ImagineResult:
    out_dir: Path
    method: str
    task: str
    seed: int
    settings: dict[str, Any]
    episodes: list[ImaginedEpisode] = field(default_factory=list)
    elapsed_s: float = 0.0

    @property
    def paths(self) -> list[Path]:
        return [e.path for e in self.episodes]

    @property
    def mean_return(self) -> float:
        return float(np.mean([e.ret for e in self.episodes])) if self.episodes else float("nan")

    def to_json_obj(self) -> dict[str, Any]:
        return {"out": str(self.out_dir), "method": self.method, "origin": origin_for(self.method),
                "tag": IMAGINED_TAG, "task": self.task,
                "seeds": [self.seed, self.seed + len(self.episodes)],
                "settings": self.settings, "mean_return": round(self.mean_return, 4),
                "steps": sum(e.steps for e in self.episodes), "elapsed_s": round(self.elapsed_s, 3),
                "episodes": [e.to_json_obj() for e in self.episodes]}


def imagine_dataset(out_dir: str | Path, episodes: int, seed: int = DEFAULT_SEED_BASE, method: str = "dart",
                    task: str = "reach", *, noise: float | None = None, cem: CEMConfig | None = None,
                    steps: int = EPISODE_STEPS, frames: bool = False, demos: Sequence[str | Path] = (),
                    allow_overlap: bool = False, episode_id_prefix: str = "imagined",
                    progress: Callable[[ImaginedEpisode], None] | None = None) -> ImagineResult:
    """Imagine `episodes` rollouts (task seeds seed .. seed+episodes-1) into out_dir."""
    if task not in TASKS:
        raise ValueError(f"task {task!r} is not one of {', '.join(TASKS)}")
    if method not in METHODS:
        raise ValueError(f"method {method!r} is not one of {', '.join(METHODS)}")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes={episodes!r} must be a positive integer")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed={seed!r} must be a non-negative integer")
    noise = _check_noise(DEFAULT_NOISE[method] if noise is None else noise)
    cem = cem or CEMConfig()
    if method == "cem":
        cem.validate()
    check_seeds(seed, episodes, task, demos, allow_overlap)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out}: exists and is not a directory")
    ids = [episode_id_for(method, task, seed + i, episode_id_prefix) for i in range(episodes)]
    taken = [i for i in ids if (out / i).exists()]
    if taken:
        raise FileExistsError(f"{out / taken[0]}: episode dir already exists ({len(taken)} of the {episodes} "
                              "episodes would clash); imagine into another --out or from another --seed")
    settings = {"noise_std": noise, **({"cem": asdict(cem)} if method == "cem" else {}), "steps": steps}
    result = ImagineResult(out, method, task, seed, settings)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for i, ep_id in enumerate(ids):
        s = seed + i
        with tempfile.TemporaryDirectory(prefix=".frames-", dir=out) as tmp:
            ep, ret = imagine_episode(task, s, method, noise=noise, cem=cem, steps=steps, frames=frames,
                                      frame_dir=tmp if frames else None, episode_id=ep_id)
            report = episode_report(ep, "train")
            if not report["ok"]:
                raise RuntimeError(f"imagined episode {ep_id} fails the train profile: "
                                   + "; ".join(report["errors"][:3]))
            path = write_episode_dir(ep, out)
        rec = ImaginedEpisode(path, ep_id, s, ret, len(ep.steps), report["status"])
        result.episodes.append(rec)
        if progress is not None:
            progress(rec)
    result.elapsed_s = time.perf_counter() - t0
    return result


__all__ = ["imagine_dataset", "imagine_episode", "ImagineResult", "ImaginedEpisode", "CEMConfig", "CEMPlanner",
           "DartSearch", "make_search", "fingertip_xy", "METHODS", "IMAGINED_TAG", "DART_NOISE_STD",
           "origin_for", "episode_id_for"]
