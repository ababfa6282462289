"""The bench's one-call tick from raw values: FastLoopNumpyAct.act(values, state) -> action.

    model = FastLoopNumpyAct.from_checkpoint(ckpt)
    action, state = model.act(raw_observation, state)   # normalise, tick, denormalise, clip

The same arithmetic as tick() between normalise() and denormalise(), with the observation
normalisation folded into obs_in and the action denormalisation into out (float64, as denormalise
computes it), so a tick from raw values costs no more array operations than tick() itself.
bench/inference.py measures this floor of the NumPy form, and the tests take its answers as the
reference BrainService's must equal (an independent path to the same action); BrainService itself
serves through tick(), so this path serves nothing. Torch-free.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from hope_models.components.fast_loop.numpy_form import FastLoopNumpy, centred
from hope_models.components.numpy_layers import NumpyWindowState


class FastLoopNumpyAct(FastLoopNumpy):
    """FastLoopNumpy plus act() (see the module doc)."""

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        f64 = np.float64
        w_in, b_in = self._obs_in.w_t.astype(f64), self._obs_in.b.astype(f64)
        inv_std, shift = self._inv_std.astype(f64), self._shift.astype(f64)  # the float32 constants normalise uses
        self._e_w_raw, self._e_b_raw = centred(inv_std[:, None] * w_in, b_in - shift @ w_in)  # raw observation
        out_w, out_b = self._out.w_t.astype(f64), self._out.b.astype(f64)
        self._a_w_raw = np.ascontiguousarray(out_w * self._act_std[None, :])  # float64 [d, act]
        self._a_b_raw = out_b * self._act_std + self._act_mean

    def act(self, values: Any, state: NumpyWindowState,
            codes: np.ndarray | None = None) -> tuple[np.ndarray, NumpyWindowState]:
        """Raw observation (obs_dim numbers) + state -> (denormalised action float64 [act_dim], state).
        The values are checked as observation_vector checks them. codes: a camera reflex's frame codes."""
        x = np.asarray(values, dtype=np.float64)
        if x.shape != (self.obs_dim,):
            x = self.observation_vector(values)  # the exact message, or a [1, obs_dim] flattened
        if self.n_codes:  # the codes read the normalised observation itself (or the frame's, given)
            a, state = self.tick(self.normalise(self.observation_vector(x)), state, codes)
            return self.denormalise(a), state
        if state.h.shape[0] != 1:
            raise ValueError(f"act() steps one observation; this state holds a batch of {state.h.shape[0]}")
        e = x.astype(np.float32).dot(self._e_w_raw)
        e += self._e_b_raw
        ee = float(e.dot(e))
        if not math.isfinite(ee):  # a NaN/Inf observation (or one beyond float32): observation_vector decides
            self.observation_vector(x)
        y, r, state = self._core(e, ee, state)
        a = y.dot(self._a_w_raw)  # float64, as denormalise
        a *= r
        a += self._a_b_raw
        if self.action_bounds is not None:
            np.maximum(a, self.action_bounds[0], out=a)  # np.clip's values (NaN stays NaN) in half its time
            np.minimum(a, self.action_bounds[1], out=a)
        return a, state


__all__ = ["FastLoopNumpyAct"]
