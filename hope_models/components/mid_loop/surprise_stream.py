"""The promoted Mid Loop's surprise over one episode's control ticks, as BrainService defines it.

    stream, reason = SurpriseStream.promoted(home, control_period_s=0.02)  # (None, why) without one
    record = stream.tick(step, observation, action)   # a dict at the Mid Loop's grid points, else None

eval-reflex --stream-frames uses it to plot the Mid Loop's surprise beside the reflex's frames
(docs/reflex.md, "Reflex view: surprise"). The definition is serving.py's (its module docstring), not
re-implemented here: the episode is one serving.MidSession ticked with serving.tick, exactly as
BrainService ticks a session whose client sends, with each observation, the action it took on the
previous tick (here: the action the reflex answered to the previous observation, as the sim applied
it). So a grid point falls every ticks_per_point(mid, control period) ticks from tick 0, its action
input is the previous tick's action, and surprise_by_horizon[h] scores the observed code against
the distribution predicted s_h grid points earlier (null until then).

A record: {"step": control step, "t": step x control period (s), "grid_point": k, "surprise": nats |
null (the shortest horizon's), "surprise_by_horizon": {"0.5s": nats | null, ...}}.

The observation is an RLDS observation block (a dict); the values the Mid Loop reads are taken from
it by the dotted paths of its feature spec ("observation.robot_state.joint_positions"), in spec
order, so a Mid Loop trained on the sim's demos reads the sim's observation as recorded. Torch-free.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components import PREDICTOR
from hope_models.components.checkpoint_checks import CheckpointRefused
from hope_models.components.mid_loop import serving
from hope_models.components.mid_loop.numpy_form import MidLoopNumpy
from hope_models.promoted import PointerError, read_pointer

NO_MID_LOOP = "no mid_loop promoted"


def observation_values(fields: list[tuple[str, int]], observation: dict[str, Any]) -> np.ndarray:
    """The values at `fields` ((dotted path, size) in spec order) of an RLDS observation block, float64;
    ValueError naming the first path it does not hold (or holds with another size)."""
    out: list[float] = []
    for path, size in fields:
        node: Any = {"observation": observation}
        for part in path.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        values = np.atleast_1d(np.asarray(node, dtype=np.float64)) if node is not None else None
        if values is None or values.shape != (size,):
            raise ValueError(f"the observation has no {path} of {size} value(s) (the mid_loop reads it)")
        out.extend(values.tolist())
    return np.asarray(out, dtype=np.float64)


class SurpriseStream:
    """One episode of ticks through one Mid Loop session (not thread-safe: one episode, one caller)."""

    def __init__(self, mid: MidLoopNumpy, control_period_s: float):
        self.mid = mid
        self.control_period_s = float(control_period_s)
        self.every = serving.ticks_per_point(mid, self.control_period_s)
        self.session = serving.new_session(mid)
        self.non_finite = 0  # grid points whose prediction was non-finite (kept out of surprise, as served)
        self._previous: np.ndarray | None = None

    @classmethod
    def promoted(cls, home: str | Path, control_period_s: float) -> tuple["SurpriseStream | None", str | None]:
        """The stream of the mid_loop promoted in `home` (the pointer BrainService follows, its sha256 and
        manifest verified the same way), or (None, the reason there is none)."""
        try:
            pointer = read_pointer(home, PREDICTOR)
        except PointerError as exc:
            return None, f"the mid_loop promotion pointer is unusable: {exc}"
        if pointer is None:
            return None, NO_MID_LOOP
        ckpt = Path(pointer["checkpoint"])
        ckpt = ckpt if ckpt.is_absolute() else Path(home) / ckpt
        try:
            mid = MidLoopNumpy.from_checkpoint(ckpt, expected_sha256=pointer["sha256"], verify_manifest=True)
        except (CheckpointRefused, OSError, ValueError) as exc:
            return None, f"the promoted mid_loop cannot be loaded: {exc}"
        return cls(mid, control_period_s), None

    def describe(self) -> dict[str, Any]:
        """What the records will hold: the version, its horizons and grid (the stream's header)."""
        m = self.mid
        return {PREDICTOR: m.version, "horizons": list(m.horizon_names), "horizons_s": list(m.horizons_s),
                "grid_step_s": m.grid_step_s, "every_steps": self.every, "window_k": m.window_k}

    def check_fits(self, observation: dict[str, Any], act_dim: int) -> None:
        """ValueError when this Mid Loop cannot read the episode's observation or action."""
        observation_values(self.mid.observation_fields, observation)
        if act_dim != self.mid.act_dim:
            raise ValueError(f"the mid_loop reads {self.mid.act_dim} action values; the episode's actions have {act_dim}")

    def tick(self, step: int, observation: dict[str, Any], action: np.ndarray) -> dict[str, Any] | None:
        """Control step `step`'s observation and the action answered to it -> the grid point's record,
        or None between grid points."""
        values = observation_values(self.mid.observation_fields, observation)
        sess = self.session
        point = sess.points
        # given = the previous tick's action (None on the first tick: zeros, serving.py's default)
        if not serving.tick(self.mid, sess, values, self._previous, None, self.every):
            self.non_finite += 1
        self._previous = np.asarray(action, dtype=np.float64)
        if sess.points == point:  # not a grid point
            return None
        a = sess.answer
        return {"step": int(step), "t": round(step * self.control_period_s, 6), "grid_point": a["mid_grid_point"],
                "surprise": a["surprise"], "surprise_by_horizon": dict(a["surprise_by_horizon"])}


__all__ = ["NO_MID_LOOP", "SurpriseStream", "observation_values"]
