"""A trained fast_loop as a reflex policy: one control tick per call, O(1) recurrent state.

    policy = ReflexPolicy.from_checkpoint("runs/reach")      # a run dir or a checkpoints/<step> dir
    policy.reset()                                           # at every episode start
    action = policy.act(observation)                         # observation dict, or a raw vector

act() reads the checkpoint's feature spec: each observation field path (e.g.
`observation.robot_state.joint_positions`) is looked up in the observation dict (the RLDS
`observation` block, with or without the leading "observation." level), the values are
concatenated in the spec's order (a raw vector must already be in that order), normalised with the
spec's mean/std exactly as the dataset cache does (float32, x * 1/std - mean/std), and fed to
FastLoop.step with the policy's recurrent state. The normalised action is denormalised
(a * std + mean) and clipped to the action bounds. After any number of ticks the action equals
FastLoop.forward over the last K observations of the episode (window-exact; tested).

A fast_loop over a frame tokenizer also reads the camera: the observation dict carries the frame
(uint8 [H, W, 3], the spec's size) at the spec's camera path (`observation.camera` for the
reacher's camera observation); `frame_size` says which, and evaluate.run_episode renders it in
`render_style`, the style of the frames it was trained on (render_style.py).

`from_checkpoint` refuses what this runtime cannot drive, with the reason: a component that is not
a fast_loop, a frame fast_loop whose spec names no camera, or (by default) a spec whose fields are not the
dm_control reacher's observation / action (pass expect_observation=None, expect_action=None and
action_bounds=None to use it for another robot).

`.version` names the weights: "<run name>@<step>:<first 12 hex of sha256(model.safetensors)>"
(the run name is the run dir's name; a bare checkpoint dir gives its own name), so every action
can be traced to the file that produced it. The rule is hope_models.checkpoint_format.version_name,
shared with the promotion pointers and BrainService.

It lives with the gate, whose sim reflex check drives it (as does `eval-reflex`, that check on its
own); the torch-free serving form of the same model is hope_models/components/fast_loop/numpy_form.py.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from hope_models.checkpoint_format import CONFIG_FILE, MODEL_FILE, CheckpointError, version_name
from hope_models.checkpoints import open_checkpoint
from hope_models.components import ACTOR
from hope_models.promote.render_style import trained_render_style
from hope_models.sim.reacher import ACTION_FIELD, ACTION_HIGH, ACTION_LOW, OBS_FIELDS, RENDER_STYLE

SIM_OBSERVATION: tuple[tuple[str, int], ...] = OBS_FIELDS
SIM_ACTION: tuple[tuple[str, int], ...] = (ACTION_FIELD,)
SIM_BOUNDS = (ACTION_LOW, ACTION_HIGH)


class ReflexPolicyError(ValueError):
    """The checkpoint cannot be driven as a reflex policy here; the message names the file and why."""


def _lookup(obs: dict[str, Any], path: str) -> Any:
    parts = path.split(".")
    if parts[0] == "observation" and "observation" not in obs:
        parts = parts[1:]
    v: Any = obs
    for p in parts:
        if not isinstance(v, dict) or p not in v:
            raise KeyError(path)
        v = v[p]
    return v


def check_spec(spec, where: str, expect_observation: Sequence[tuple[str, int]] | None,
               expect_action: Sequence[tuple[str, int]] | None) -> None:
    """Refuse a spec whose observation fields are not among expect_observation (same sizes) or
    whose action fields differ from expect_action."""
    if expect_observation is not None:
        avail = dict(expect_observation)
        for f in spec.observation.fields:
            if f.path not in avail:
                raise ReflexPolicyError(
                    f"{where}: the checkpoint reads {f.path} ({f.size} values), which this environment's "
                    f"observation does not have (it has {', '.join(f'{p}[{n}]' for p, n in expect_observation)}); "
                    "it was trained on other data")
            if avail[f.path] != f.size:
                raise ReflexPolicyError(f"{where}: the checkpoint reads {f.path} with {f.size} values, this "
                                        f"environment gives {avail[f.path]}")
    if expect_action is not None:
        got = [(f.path, f.size) for f in spec.action.fields]
        if got != [tuple(x) for x in expect_action]:
            raise ReflexPolicyError(
                f"{where}: the checkpoint's action is {', '.join(f'{p}[{n}]' for p, n in got)}, this environment "
                f"needs {', '.join(f'{p}[{n}]' for p, n in expect_action)}")
    if not spec.observation.has_stats or not spec.action.has_stats:
        raise ReflexPolicyError(f"{where}: the feature spec has no normalisation statistics (mean/std)")


class ReflexPolicy:
    """A FastLoop stepped once per control tick (see the module doc)."""

    name = ACTOR

    def __init__(self, model, spec, version: str, action_bounds: tuple[float, float] | None = SIM_BOUNDS,
                 checkpoint_dir: Path | None = None):
        import torch  # lazy: loads torch

        self._torch = torch
        self.model = model.eval()
        self.spec = spec
        self.version = version
        self.checkpoint_dir = checkpoint_dir
        self.obs_dim, self.act_dim = spec.obs_dim, spec.act_dim
        obs_mean, obs_std, act_mean, act_std = spec.normalizer()
        # exactly the dataset cache's arithmetic: float32 x * inv_std - mean * inv_std
        self._inv_std = (1.0 / obs_std).astype(np.float32)
        self._shift = (obs_mean * self._inv_std).astype(np.float32)
        self._act_mean = np.asarray(act_mean, dtype=np.float64)
        self._act_std = np.asarray(act_std, dtype=np.float64)
        self.action_bounds = action_bounds
        # A camera reflex reads the frame at the spec's camera path of each observation (uint8 [H, W, 3]).
        self.frame = spec.frame if model.wants_frames else None
        self.render_style, self.render_from = RENDER_STYLE, "the default"  # how evaluate draws its frames
        self.ticks = 0
        self._state = None
        self.reset()

    # -- loading --------------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(cls, path: str | Path, *,
                        expect_observation: Sequence[tuple[str, int]] | None = SIM_OBSERVATION,
                        expect_action: Sequence[tuple[str, int]] | None = SIM_ACTION,
                        action_bounds: tuple[float, float] | None = SIM_BOUNDS) -> "ReflexPolicy":
        from hope_models.components.build import component_from_checkpoint  # lazy: loads safetensors, torch

        p = Path(path)
        if not p.exists():
            raise ReflexPolicyError(f"{p}: checkpoint not found (give a run dir or a checkpoints/<step> dir)")
        try:
            verified = open_checkpoint(p, keep=(CONFIG_FILE,))  # each file hashed once, the version from it
            version = version_name(verified.path, verified.sha256[MODEL_FILE], verified.json(CONFIG_FILE))
        except CheckpointError as exc:
            raise ReflexPolicyError(str(exc)) from None
        ckpt = verified.path
        try:
            comp = component_from_checkpoint(ckpt)
        except CheckpointError as exc:
            raise ReflexPolicyError(str(exc)) from None
        where = str(ckpt / CONFIG_FILE)
        if comp.name != ACTOR:
            raise ReflexPolicyError(f"{where}: component is {comp.name!r}; a reflex policy needs a {ACTOR} checkpoint")
        if comp.model.wants_frames and comp.spec.frame is None:
            raise ReflexPolicyError(f"{where}: this fast_loop reads camera frames but its feature spec names no "
                                    "camera (frame) to read them from")
        check_spec(comp.spec, where, expect_observation, expect_action)
        policy = cls(comp.model, comp.spec, version, action_bounds, ckpt)
        if policy.frame is not None:  # evaluated on frames drawn like the ones it learned from
            policy.render_style, policy.render_from = trained_render_style(verified.json(CONFIG_FILE))
        return policy

    # -- the tick -------------------------------------------------------------------------------
    def reset(self) -> None:
        """Start of an episode: every earlier point is masked (as the training windows do)."""
        self._state = self.model.init_state(1)
        self.ticks = 0

    def observation_vector(self, obs: Any) -> np.ndarray:
        """An observation dict (spec field paths) or a raw vector in spec order -> float64 [obs_dim]."""
        if isinstance(obs, dict):
            parts = []
            for f in self.spec.observation.fields:
                try:
                    v = _lookup(obs, f.path)
                except KeyError:
                    raise ReflexPolicyError(f"observation has no {f.path} (the policy's feature spec reads it)") from None
                a = np.asarray(v, dtype=np.float64).reshape(-1)
                if a.size != f.size:
                    raise ReflexPolicyError(f"observation {f.path} has {a.size} values, the policy needs {f.size}")
                parts.append(a)
            x = np.concatenate(parts) if parts else np.zeros(0)
        else:
            x = np.asarray(obs, dtype=np.float64).reshape(-1)
            if x.size != self.obs_dim:
                raise ReflexPolicyError(f"observation vector has {x.size} values, the policy needs {self.obs_dim} "
                                        f"({', '.join(self.spec.observation.dim_names())})")
        if not np.isfinite(x).all():
            raise ReflexPolicyError(f"observation has non-finite values: {x.tolist()}")
        return x

    @property
    def frame_size(self) -> int | None:
        """The side of the square camera frame each act() needs (None: no camera)."""
        return None if self.frame is None else int(self.frame.shape[0])

    def frame_of(self, obs: Any) -> np.ndarray:
        """The camera frame of an observation dict, checked against the spec's shape -> uint8 [H, W, 3]."""
        assert self.frame is not None
        if not isinstance(obs, dict):
            raise ReflexPolicyError(f"this policy reads the camera {self.frame.path}: give an observation dict")
        try:
            v = _lookup(obs, self.frame.path)
        except KeyError:
            raise ReflexPolicyError(f"observation has no {self.frame.path} (the policy's camera)") from None
        a = np.asarray(v)
        if a.shape != tuple(self.frame.shape) or a.dtype != np.uint8:
            raise ReflexPolicyError(f"observation {self.frame.path} is {a.dtype} {list(a.shape)}, the policy needs "
                                    f"uint8 {list(self.frame.shape)}")
        return a

    def normalise(self, x: np.ndarray) -> np.ndarray:
        x32 = np.asarray(x, dtype=np.float32) * self._inv_std
        x32 -= self._shift
        return x32

    def act(self, obs: Any) -> np.ndarray:
        """One control tick: observation -> action (denormalised, clipped to the bounds)."""
        torch = self._torch
        xn = torch.from_numpy(self.normalise(self.observation_vector(obs))[None, :])
        frame = None if self.frame is None else torch.from_numpy(np.ascontiguousarray(self.frame_of(obs))[None])
        with torch.inference_mode():
            a, self._state = self.model.step(xn, self._state, frame)
        self.ticks += 1
        action = a[0].double().numpy() * self._act_std + self._act_mean
        if self.action_bounds is not None:
            action = np.clip(action, self.action_bounds[0], self.action_bounds[1])
        return action

    def __repr__(self) -> str:
        return f"ReflexPolicy({self.version}, obs {self.obs_dim} -> act {self.act_dim})"


__all__ = ["ReflexPolicy", "ReflexPolicyError", "check_spec", "SIM_OBSERVATION", "SIM_ACTION", "SIM_BOUNDS"]
