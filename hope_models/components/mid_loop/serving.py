"""The Mid Loop's part of BrainService's answer (the predictor's): its prediction and surprise, per
session, at its grid points; the tokenizer's code is BrainService's own.

One request is one control tick of a session (the fast_loop's grid step, 20 ms for the reacher).
Besides the fast_loop's action it answers:

- `code`: the promoted vqvae's codes of the observation (its own normalisation), G ints, every tick.
- Mid Loop fields, computed only at the mid_loop's grid points: a grid point falls every
  round(mid grid step / control period) ticks of the session (5 at 0.1 s / 0.02 s), starting at its
  first tick. At grid point k the Mid Loop reads what its OWN VQ-VAE (the one it was trained with,
  under vqvae.* in its checkpoint) makes of the tick: a vector Mid Loop the observation's codes
  (its own normalisation), a grid Mid Loop (numpy_grid.py) the cell codes of the request's camera
  frame (BrainService encodes the frame once per encoder: brain_seen.py) and the joints. The
  point's action input is the action taken on the previous tick (the request's `action` when
  given, else the fast_loop's answer of the previous tick, else zeros). The prediction is computed
  from the session's last K grid points as a training window (a zero state at its first point,
  whose action input is zeros, as previous_actions makes it), not from a state stepped since the
  start, and only at the window's last point.
  - `prediction`: {horizon: in raw units (mid_loop feature spec, spec order)}: the expected
    observation (a vector Mid Loop), or the predicted joints (a grid Mid Loop).
  - `surprise_by_horizon[h]` at grid point k: -sum_g log P_{k - s_h, h, g}(c_g(k)), nats, where
    c(k) is the observed code at k (G groups; a grid Mid Loop: G cells, summed over the cells)
    and P_{j, h} the distribution the Mid Loop predicted at grid point j of this session for
    horizon h (s_h grid steps ahead; a grid Mid Loop's each cell's decoder mixed with copy-last
    as its metrics read it, decoded only now, for the cells of that one horizon); null until grid
    point s_h of the session. `surprise` is the one of the shortest horizon.
  Between grid points the latest values are answered again, with `mid_tick` (the session tick)
  and `mid_grid_point` (k) they were computed at. A request without a session is a fresh one-point
  window: its prediction, never a surprise.

The model's part is its form's point() (what the window keeps of a grid point), predict() (the
window's last point: the prediction, and what a later surprise reads) and surprises(); its
prepare() and window_ahead() are called on the ticks between grid points (a grid Mid Loop's
prepare(), numpy_grid.py: the newest prediction's per-cell normalisers and the decoder of the
predictions the next grid point scores; a vector one has nothing to prepare), then
window_ahead() and ahead_step(): the next window's states but its last point, a block's SSM or
its MLP a tick.
So a grid point's work is spread over the ticks between grid points and the grid point runs its
own point alone (what a tick did not finish, the grid point does: the same figures).

Sessions are the mid_loop slot's own LRU (BrainService._session's rule); a mid_loop version change
clears them, a reset starts them again. A non-finite prediction (the model's fault) is logged and
counted, answered as null, and kept out of the surprise history. Torch-free.
"""
from __future__ import annotations

import logging
import math
import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

EMPTY = {"prediction": None, "surprise": None, "surprise_by_horizon": None, "mid_tick": None, "mid_grid_point": None}

DEFAULT_CONTROL_PERIOD_S = 0.02  # without a fast_loop (or one whose window names no grid step): 50 Hz
MAX_ABS_ACTION = 1e6  # as MAX_ABS_OBSERVATION: a unit or encoding error of the client beyond it


@dataclass(eq=False)
class MidSession:
    version: str
    horizons: int  # the longest horizon in grid steps: how many past predictions surprise reads
    k: int
    lock: threading.Lock = field(default_factory=threading.Lock)
    ticks: int = 0
    points: int = 0
    window: deque = field(default=None)  # (the form's point, previous action normalised [A]) of the last K points
    logp: deque = field(default=None)  # what each recent point predicted, for surprise (None: not finite)
    last_action: np.ndarray | None = None  # the action answered on the previous tick (raw)
    answer: dict[str, Any] | None = None
    ahead: tuple[int, Any] | None = None  # (grid point, the form's window_ahead for it)

    def __post_init__(self) -> None:
        self.reset(self.version)

    def reset(self, version: str) -> None:
        self.version, self.ticks, self.points, self.last_action, self.answer = version, 0, 0, None, None
        self.ahead = None
        self.window, self.logp = deque(maxlen=self.k), deque(maxlen=self.horizons)


def action_values(action: Any, act_dim: int) -> np.ndarray:
    """The request's `action` (the action taken on the previous tick) -> float64 [act_dim]; ValueError naming
    what is wrong otherwise."""
    if not isinstance(action, (list, tuple)) or len(action) != act_dim:
        raise ValueError(f"action must be a list of {act_dim} numbers (the action taken on the previous tick)")
    out = []
    for i, v in enumerate(action):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"action[{i}] = {v!r} is not a number")
        f = float(v)
        if not math.isfinite(f) or abs(f) > MAX_ABS_ACTION:
            raise ValueError(f"action[{i}] = {f:g} is not finite or outside [-{MAX_ABS_ACTION:g}, {MAX_ABS_ACTION:g}]")
        out.append(f)
    return np.asarray(out, dtype=np.float64)


def ticks_per_point(mid: Any, control_period_s: float | None) -> int:
    period = control_period_s or DEFAULT_CONTROL_PERIOD_S
    return max(1, round(mid.grid_step_s / period))


def new_session(mid: Any) -> MidSession:
    return MidSession(mid.version, max(mid.horizon_steps), mid.window_k)


def stateless(mid: Any, values: np.ndarray, codes: np.ndarray | None = None) -> tuple[dict[str, Any], bool]:
    """A fresh one-point window (grid point 0, action input zeros) -> (the mid fields, finite).
    codes: the frame's cell codes by the Mid Loop's VQ-VAE (a grid Mid Loop), else None."""
    pred, _, finite = mid.predict([mid.point(values, codes)], np.zeros((1, mid.act_dim), np.float32))
    return _fields(mid, pred if finite else None, {n: None for n in mid.horizon_names}, 0, 0), finite


def tick(mid: Any, sess: MidSession, values: np.ndarray, prev_action: np.ndarray | None,
         answered: np.ndarray | None, every: int, codes: np.ndarray | None = None) -> bool:
    """One tick of a session (under its lock): at a grid point, encode, predict and score the point
    (sess.answer updated). prev_action: the action the client says it took on the previous tick
    (None: the fast_loop's answer of the previous tick, else zeros); answered: this tick's action
    (the next tick's default); codes: the tick's frame codes by the Mid Loop's own VQ-VAE (a grid
    Mid Loop). False when the Mid Loop computed a non-finite prediction."""
    finite = True
    if sess.ticks % every == 0:
        finite = _grid_point(mid, sess, mid.point(values, codes),
                             prev_action if prev_action is not None else sess.last_action)
    elif sess.ahead is not None:
        mid.ahead_step(sess.ahead[1])  # the next stage of the next window's states (nothing once complete)
    elif sess.logp and sess.logp[-1] is not None:
        # part of the next grid point's work, one step a tick (nothing is left of prepare() once ahead
        # is made: what it reads changes only at a grid point, which clears ahead)
        if not mid.prepare(sess.logp[-1], _due(mid, sess)):
            earlier = list(sess.window)[max(0, len(sess.window) + 1 - sess.k):]  # the next window but its last
            acts = np.stack([a for _, a in earlier]) if earlier else np.zeros((0, mid.act_dim), np.float32)
            acts[:1] = 0.0  # the next window's first point (previous_actions)
            sess.ahead = (sess.points, mid.window_ahead([p for p, _ in earlier], acts))
    sess.last_action = answered
    sess.ticks += 1
    return finite


def _grid_point(mid: Any, sess: MidSession, point: Any, prev: np.ndarray | None) -> bool:
    act_n = np.zeros(mid.act_dim, np.float32) if prev is None else mid.norm.act(prev)
    sess.window.append((point, act_n))
    scored = mid.surprises(_due(mid, sess), point)
    by_h = {name: scored.get(h) for h, name in enumerate(mid.horizon_names)}
    ahead = sess.ahead[1] if sess.ahead is not None and sess.ahead[0] == sess.points else None
    sess.ahead = None
    if ahead is None:
        acts = np.stack([a for _, a in sess.window])
        acts[0] = 0.0  # a window's first point has no earlier action (previous_actions, as in training)
        pred, memo, finite = mid.predict([p for p, _ in sess.window], acts)
    else:  # the points before hold their states in ahead: only the last point (never a window's first) is read
        pred, memo, finite = mid.predict([point], act_n[None], ahead)
    sess.logp.append(memo if finite else None)
    sess.answer = _fields(mid, pred if finite else None, by_h, sess.ticks, sess.points)
    sess.points += 1
    return finite


def _due(mid: Any, sess: MidSession) -> dict[int, Any]:
    """{horizon index: the prediction the session's next grid point k scores}: made at k - s_h."""
    return {h: sess.logp[-s] for h, s in enumerate(mid.horizon_steps) if len(sess.logp) >= s and sess.logp[-s] is not None}


def answer(slot: Any, served: Any, x: np.ndarray, session: str | None, reset: bool, given: np.ndarray | None,
           answered: np.ndarray | None, fast: Any, max_sessions: int, codes: np.ndarray | None = None) -> dict[str, Any]:
    """The Mid Loop fields of one request: slot = BrainService's mid_loop slot (its sessions LRU and
    counters), served = the version read for this request, x = the raw observation, given = the
    request's `action`, answered = this tick's fast_loop action, fast = the served fast_loop model,
    codes = the frame's codes by the Mid Loop's own VQ-VAE (a grid Mid Loop; None otherwise)."""
    mid = served.model
    if session is None:
        fields, finite = stateless(mid, x, codes)
    else:
        with slot.lock:
            sess = slot.sessions.get(session)
            if sess is None:
                sess = slot.sessions[session] = new_session(mid)
                while len(slot.sessions) > max_sessions:
                    slot.sessions.popitem(last=False)  # least recently used
            slot.sessions.move_to_end(session)
        with sess.lock:
            if reset or sess.version != served.version:  # a swap since: the history was other weights'
                sess.reset(served.version)
            every = ticks_per_point(mid, fast.control_period_s if fast is not None else None)
            finite = tick(mid, sess, x, given, answered, every, codes)
            fields = dict(sess.answer or EMPTY)
    if not finite:  # the model's fault: counted and logged; the robot's action is still answered
        with slot.lock:
            slot.non_finite += 1
        log.error("BrainService: mid_loop %s computed a non-finite prediction (session %r)", served.version, session)
    return fields


def _fields(mid: Any, pred: np.ndarray | None, by_h: dict[str, float | None], tick_no: int,
            point: int) -> dict[str, Any]:
    shortest = mid.horizon_names[int(np.argmin(mid.horizon_steps))]
    return {"prediction": None if pred is None else {n: np.asarray(p, np.float64).tolist()
                                                     for n, p in zip(mid.horizon_names, pred, strict=False)},
            "surprise": by_h[shortest], "surprise_by_horizon": by_h, "mid_tick": tick_no, "mid_grid_point": point}


__all__ = ["MidSession", "DEFAULT_CONTROL_PERIOD_S", "EMPTY", "action_values", "answer", "new_session", "stateless", "tick",
           "ticks_per_point"]
