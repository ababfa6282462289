"""Recording reacher episodes as canonical RLDS v1.1 episode dirs (write_episode_dir).

    paths = record_episodes("datasets/reach50", episodes=50, seed=100000, task="reach", noise=0.3)

Episode i runs the task with seed `seed + i` under `policy` (default: the expert; "play" for
play, below) and is written as <out_dir>/<episode_id>/ (metadata.json, steps/000000.jsonl, blobs/
with frames). One step per 20 ms control step, 1000 steps:

    step_index, timestamp_ns = index x 20 000 000 (relative clock, starts at 0)
    observation  = the reacher observation block (reacher.py: robot_state.joint_positions[2],
                   robot_state.joint_velocities[2], target_offset[2]) observed before the action
                   (+ media.rgb = {"uri": "blobs/step_NNNNNN_rgb.npy", "width": 64, "height": 64,
                   "format": "npy_uint8_hwc"} with frames: that observation's 64x64 top-down frame);
                   with observation="camera", what a robot has instead: robot_state and
                   camera = {"uri": "blobs/step_NNNNNN_rgb.npy", ...} (64x64, or 96x96 with
                   frame_size=96), no target_offset. The expert still acts on the state.
    action       = {"command": [shoulder, wrist] (the label: the policy's action in [-1, 1]),
                    "source": "sim_expert" | "sim_policy" | "sim_play"
                    (+ "executed_command": what was actually applied, when noise is on)}
    reward       = the reward received for this step's transition (1 on target, else 0)
    is_terminal  = True on the last step only

Noise (DART, Laskey et al. 2017): with noise=sigma, the env is driven with
clip(label + N(0, sigma^2)) while the recorded action.command stays the policy's (expert's) action
at the observed state. The demos then cover the states a slightly wrong policy drifts into, each
labelled with the expert's correction, which is what makes behaviour cloning robust in closed loop.
The noise RNG is seeded from the episode seed, so recording is deterministic.

Play (policy="play", expert.PlayPolicy seeded with the episode seed): smooth random exploration
with no expert label. action.command is the command actually executed (there is nothing else to
record), action.source and control_role are "sim_play", provenance.sim.policy is "play", the tags
end with "play" and the episode id is <prefix>-<task>-play-s<seed>, so play and demos of the same
seed never clash. The dataset cache marks such episodes (dataset_cache.is_play_episode) and the
fast_loop never clones them; noise is refused (the executed command already is the noise).

Metadata: schema_version "1.1", robot_model "dmc-reacher", environment_id "dm_control/reacher-<task>",
provenance.origin = `origin` ("sim:dm_control"), provenance.sim = {task, seed, control_period_s,
noise_std, policy, observation, frame_size and render (with frames)}, tags ["sim", "dm_control", "reacher", <task>, ...tags], xr_mode "workstation",
control_role "sim_expert" (outside the documented human roles, so validation gives one warning:
undocumented value kept as a string; the episode is accepted), software versions. Every episode is
validated with the train profile before it is written; an error there is a bug and raises.
"""
from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from hope_models.rlds.episode import Episode, Step
from hope_models.rlds.validate import validate_episode
from hope_models.rlds.write_episode_dir import safe_episode_id, write_episode_dir
from hope_models.sim.expert import ExpertController, PlayPolicy
from hope_models.sim.reacher import (
    CONTROL_PERIOD_S,
    EPISODE_STEPS,
    FRAME_SIZE,
    FRAME_SIZES,
    OBSERVATIONS,
    RENDER_STYLE,
    RENDER_STYLES,
    ROBOT_MODEL,
    TASKS,
    camera_observation,
    make_env,
)

DEFAULT_SEED_BASE = 100_000  # demos start here; evaluation defaults to seeds 0..N-1 (held out)
DEFAULT_ORIGIN = "sim:dm_control"
FRAME_URI = "blobs/step_%06d_rgb.npy"
PERIOD_NS = int(round(CONTROL_PERIOD_S * 1e9))


@dataclass
class RecordedEpisode:
    path: Path
    episode_id: str
    seed: int
    ret: float
    steps: int


@dataclass
class RecordResult:
    out_dir: Path
    task: str
    episodes: list[RecordedEpisode] = field(default_factory=list)

    @property
    def paths(self) -> list[Path]:
        return [e.path for e in self.episodes]

    @property
    def mean_return(self) -> float:
        return float(np.mean([e.ret for e in self.episodes])) if self.episodes else float("nan")


def software_versions(key: str, module: str) -> dict[str, str]:
    """metadata.software of a sim episode: the module that wrote it (under `key`) and the
    simulator's versions."""
    out = {key: module}
    for pkg in ("dm-control", "mujoco"):
        try:
            out[pkg.replace("-", "_")] = version(pkg)
        except PackageNotFoundError:
            pass
    return out


def rollout(env, obs, choose: Callable[[Any], tuple[Any, Any, dict, dict]], source: str, steps: int,
            frame_dir: str | Path | None, observation: str = "state",
            frame_size: int = FRAME_SIZE) -> tuple[list[Step], float]:
    """Drive `env` from `obs` for up to `steps` control steps, one canonical Step per step.
    `choose(obs)` -> (label, executed, extra action keys, step_metadata): the label is recorded as
    action.command, the executed command is what the env gets; `choose` always sees the full
    state (the expert needs the target), the step records `observation`: "state" (with frame_dir,
    a frame per step saved under frame_dir/blobs/ and referenced from observation.media) or
    "camera" (the joints and that frame only, reacher.camera_observation). Returns the steps and
    the return (sum of the rewards of what was executed)."""
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation={observation!r} must be one of {', '.join(OBSERVATIONS)}")
    if observation == "camera" and frame_dir is None:
        raise ValueError("observation='camera' needs frame_dir, where the frames are written")
    if frame_size not in FRAME_SIZES:
        raise ValueError(f"frame_size={frame_size} must be one of {', '.join(map(str, FRAME_SIZES))}")
    if frame_dir is not None:
        (Path(frame_dir) / "blobs").mkdir(parents=True, exist_ok=True)
    out: list[Step] = []
    total = 0.0
    for t in range(steps):
        if frame_dir is not None:
            np.save(Path(frame_dir) / (FRAME_URI % t), env.render(frame_size), allow_pickle=False)
        if observation == "camera":
            recorded = camera_observation(obs, FRAME_URI % t, frame_size)
        else:
            recorded = {k: (dict(v) if isinstance(v, dict) else v) for k, v in obs.items()}
            if frame_dir is not None:
                recorded["media"] = {"rgb": {"uri": FRAME_URI % t, "width": frame_size, "height": frame_size,
                                             "format": "npy_uint8_hwc"}}
        label, executed, extra, meta = choose(obs)
        obs, reward, done = env.step(executed)
        total += reward
        action = {"command": [float(v) for v in label], "source": source, **extra}
        out.append(Step(observation=recorded, action=action, reward=float(reward),
                        is_terminal=(t == steps - 1), step_metadata=meta, timestamp_ns=t * PERIOD_NS))
        if done:
            break
    return out, total


def sim_metadata(ep_id: str, task: str, source: str, tags: Sequence[str], software: dict[str, str],
                 n_steps: int, provenance: dict[str, Any]) -> dict[str, Any]:
    """The v1.1 metadata block every reacher episode carries (recorded or imagined)."""
    return {
        "schema_version": "1.1",
        "episode_id": ep_id,
        "robot_model": ROBOT_MODEL,
        "robot_type": ROBOT_MODEL,
        "xr_mode": "workstation",
        "control_role": source,
        "action_source": source,
        "environment_id": f"dm_control/reacher-{task}",
        "tags": ["sim", "dm_control", "reacher", task, *tags],
        "software": software,
        "total_steps": n_steps,
        "duration_ms": (n_steps - 1) * PERIOD_NS // 10**6,
        "provenance": provenance,
    }


def episode_id_for(prefix: str, task: str, seed: int, play: bool = False) -> str:
    return safe_episode_id(f"{prefix}-{task}{'-play' if play else ''}-s{seed:06d}")


def _is_play(policy) -> bool:
    return isinstance(policy, str) and policy == "play"


def record_episode(task: str, seed: int, policy=None, *, frames: bool = False, noise: float | None = None,
                   origin: str = DEFAULT_ORIGIN, tags: Sequence[str] = (), episode_id: str | None = None,
                   frame_dir: str | Path | None = None, steps: int = EPISODE_STEPS, observation: str = "state",
                   frame_size: int = FRAME_SIZE, render_style: str = RENDER_STYLE) -> tuple[Episode, float]:
    """One episode as an in-memory canonical Episode (frames saved under frame_dir/blobs/), and its
    return (the sum of the rewards of the executed actions). policy="play" records play;
    observation="camera" records the joints and the camera frame instead of the state (frames on)."""
    frames = frames or observation == "camera"
    if noise is not None and (not np.isfinite(noise) or noise < 0):
        raise ValueError(f"noise={noise} must be a non-negative standard deviation (action units)")
    if frames and frame_dir is None:
        raise ValueError("frames=True needs frame_dir, where the .npy frames are written before the episode dir")
    if not 1 <= steps <= EPISODE_STEPS:
        raise ValueError(f"steps={steps} must be within 1-{EPISODE_STEPS}")
    play = _is_play(policy)
    if isinstance(policy, str) and not play:
        raise ValueError(f"policy={policy!r} is not a policy object or 'play'")
    if play and noise:
        raise ValueError(f"noise={noise}: play has no expert label to keep, its executed command is the "
                         "exploration; record play without noise")
    policy = PlayPolicy(seed) if play else policy if policy is not None else ExpertController()
    is_expert = isinstance(policy, ExpertController)
    noisy = bool(noise)
    env = make_env(task, seed, frames=frames, render_style=render_style)
    obs = env.reset()
    if hasattr(policy, "reset"):
        policy.reset()
    rng = np.random.default_rng([int(seed), 0xDA27])

    def choose(o):
        label = np.clip(np.asarray(policy.act(o), dtype=np.float64), env.action_low, env.action_high)
        if not noisy:
            return label, label, {}, {}
        executed = np.clip(label + rng.normal(0.0, noise, label.shape), env.action_low, env.action_high)
        return label, executed, {"executed_command": [float(v) for v in executed]}, {}

    source = "sim_play" if play else "sim_expert" if is_expert else "sim_policy"
    out, total = rollout(env, obs, choose, source, steps, frame_dir if frames else None, observation, frame_size)
    ep_id = episode_id or episode_id_for("dmc-reacher", task, seed, play)
    policy_name = getattr(policy, "version", None) or getattr(policy, "name", type(policy).__name__)
    extra_tags = (["dart_noise"] if noisy else []) + (["play"] if play else []) + (
        ["camera"] if observation == "camera" else [])
    metadata = sim_metadata(ep_id, task, source, [*tags, *extra_tags],
                            software_versions("recorder", "hope_models.sim.recorder"), len(out), {
                                "origin": origin,
                                "sim": {"domain": "reacher", "task": task, "seed": int(seed),
                                        "control_period_s": CONTROL_PERIOD_S,
                                        "noise_std": float(noise) if noisy else 0.0, "policy": str(policy_name),
                                        "observation": observation,
                                        **({"frame_size": frame_size, "render": render_style} if frames else {}),
                                        **({"policy_config": policy.config()} if hasattr(policy, "config") else {}),
                                        "return": total},
                            })
    ep = Episode(ep_id, metadata, out, source=f"{origin}#{ep_id}", layout="sim",
                 blob_root=str(frame_dir) if frames else None)
    return ep, total


def record_dataset(out_dir: str | Path, episodes: int, seed: int = DEFAULT_SEED_BASE, task: str = "reach",
                   policy=None, frames: bool = False, noise: float | None = None, origin: str = DEFAULT_ORIGIN,
                   tags: Sequence[str] = (), episode_id_prefix: str = "dmc-reacher",
                   progress: Callable[[RecordedEpisode], None] | None = None,
                   steps: int = EPISODE_STEPS, observation: str = "state", frame_size: int = FRAME_SIZE,
                   render_style: str = RENDER_STYLE) -> RecordResult:
    """record_episodes with the per-episode returns (see the module doc); `steps` shortens the
    episodes (smoke tests), the default is the full 1000. policy="play" records play episodes."""
    if task not in TASKS:
        raise ValueError(f"task {task!r} is not one of {', '.join(TASKS)}")
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes={episodes!r} must be a positive integer")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed={seed!r} must be a non-negative integer")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out}: exists and is not a directory")
    if _is_play(policy) and noise:
        raise ValueError(f"noise={noise}: play episodes are recorded without noise")
    if observation not in OBSERVATIONS:
        raise ValueError(f"observation={observation!r} must be one of {', '.join(OBSERVATIONS)}")
    if frame_size not in FRAME_SIZES:
        raise ValueError(f"frame_size={frame_size} must be one of {', '.join(map(str, FRAME_SIZES))}")
    if render_style not in RENDER_STYLES:
        raise ValueError(f"render_style={render_style!r} must be one of {', '.join(RENDER_STYLES)}")
    frames = frames or observation == "camera"
    ids = [episode_id_for(episode_id_prefix, task, seed + i, _is_play(policy)) for i in range(episodes)]
    taken = [i for i in ids if (out / i).exists()]
    if taken:
        raise FileExistsError(f"{out / taken[0]}: episode dir already exists ({len(taken)} of the {episodes} "
                              "episodes would clash); record into another --out or from another --seed")
    out.mkdir(parents=True, exist_ok=True)
    result = RecordResult(out, task)
    for i, ep_id in enumerate(ids):
        s = seed + i
        with tempfile.TemporaryDirectory(prefix=".frames-", dir=out) as tmp:
            ep, ret = record_episode(task, s, policy, frames=frames, noise=noise, origin=origin, tags=tags,
                                     episode_id=ep_id, frame_dir=tmp if frames else None, steps=steps,
                                     observation=observation, frame_size=frame_size, render_style=render_style)
            errors = [p for p in validate_episode(ep, "train") if p.severity == "error"]
            if errors:
                raise RuntimeError(f"recorded episode {ep_id} fails the train profile: "
                                   + "; ".join(str(p) for p in errors[:3]))
            path = write_episode_dir(ep, out)
        rec = RecordedEpisode(path, ep_id, s, ret, len(ep.steps))
        result.episodes.append(rec)
        if progress is not None:
            progress(rec)
    return result


def record_episodes(out_dir: str | Path, episodes: int, seed: int = DEFAULT_SEED_BASE, task: str = "reach",
                    policy=None, frames: bool = False, noise: float | None = None, origin: str = DEFAULT_ORIGIN,
                    tags: Sequence[str] = (), episode_id_prefix: str = "dmc-reacher") -> list[Path]:
    """Record `episodes` episodes (seeds seed .. seed+episodes-1) into out_dir; their dirs."""
    return record_dataset(out_dir, episodes, seed, task, policy, frames, noise, origin, tags,
                          episode_id_prefix).paths


__all__ = ["record_episodes", "record_dataset", "record_episode", "RecordResult", "RecordedEpisode",
           "DEFAULT_SEED_BASE", "DEFAULT_ORIGIN", "FRAME_URI", "episode_id_for", "rollout", "sim_metadata",
           "software_versions"]
