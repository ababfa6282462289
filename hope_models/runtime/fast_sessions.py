"""The actor's part of a BrainService request: one tick of the fast_loop for a session, its
window-exact recurrent state kept per session (an LRU of max_sessions in the component's slot) and
committed only when the tick is finite. Torch-free.

    action = tick(slot, served, values, session, reset, codes, max_sessions)

Without a session the call is stateless (a fresh state: a 1-point window). A session whose state
was made by another version starts afresh on the served weights; `reset` starts its episode again.
If the fast_loop computes NaN or Inf from a valid observation, that is the model's fault: a
BrainError 500 naming the version, logged and counted (the slot's `non_finite`), the session's
state left as it was (one bad tick must not leave NaN in the state every later tick reads).
"""
from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hope_models.components.numpy_layers import NumpyWindowState
from hope_models.runtime.brain_input import BrainError

log = logging.getLogger(__name__)


@dataclass(eq=False)
class FastSession:
    version: str
    state: NumpyWindowState
    lock: threading.Lock = field(default_factory=threading.Lock)
    ticks: int = 0  # ticks committed to the state


def tick(slot: Any, served: Any, values: list[float], session: str | None, reset: bool,
         codes: np.ndarray | None, max_sessions: int) -> np.ndarray:
    """The fast_loop's action for this tick (raw units). slot: BrainService's slot of the actor
    (its sessions and counters); served: the version read for this request; codes: a camera
    reflex's frame codes (None for one that reads no camera)."""
    model = served.model
    xn = model.normalise(np.asarray(values, dtype=np.float64))
    if session is None:
        a, state = model.tick(xn, model.init_state(), codes)
        action = model.denormalise(a)
        if not finite(action, state):
            non_finite(slot, served, session, values)
        return action
    sess = session_of(slot, session, served.version, model, reset, max_sessions)
    with sess.lock:
        if sess.version != served.version:  # a swap happened since: start afresh on these weights
            sess.version, sess.state, sess.ticks = served.version, model.init_state(), 0
        a, state = model.tick(xn, sess.state, codes)
        action = model.denormalise(a)
        # Committed only when finite: one bad tick must not leave NaN in the recurrent state,
        # which every later tick of the session would read (K ticks of NaN answers).
        if not finite(action, state):
            non_finite(slot, served, session, values)
        sess.state = state
        sess.ticks += 1
    return action


def non_finite(slot: Any, served: Any, session: str | None, values: list[float]) -> None:
    """A valid observation gave NaN/Inf: the served weights' fault, not the request's, so a
    500 (the robot should fall back to its safe behaviour and the operator look at the model),
    logged, and never the NaN itself (JSON has none)."""
    with slot.lock:
        slot.non_finite += 1
    log.error("BrainService: %s %s computed a non-finite action or state (session %r, observation range "
              "[%.3g, %.3g]); answered 500, the session's state left as it was", slot.component, served.version,
              session, min(values), max(values))
    raise BrainError(f"{served.version} computed a non-finite action for this observation (a fault of the served "
                     "model, not of the request); no action is given, and a session's recurrent state is left "
                     "as it was before this tick", 500)


def session_of(slot: Any, name: str, version: str, model: Any, reset: bool, max_sessions: int) -> FastSession:
    with slot.lock:
        sess = slot.sessions.get(name)
        if sess is None:
            sess = FastSession(version, model.init_state())
            slot.sessions[name] = sess
            while len(slot.sessions) > max_sessions:
                slot.sessions.popitem(last=False)  # least recently used
        else:
            slot.sessions.move_to_end(name)
    if reset:
        with sess.lock:
            sess.version, sess.state, sess.ticks = version, model.init_state(), 0
    return sess


def finite(action: np.ndarray, state: NumpyWindowState) -> bool:
    # The state, not only the action: a NaN can sit in the ring for K ticks before it reaches an
    # action. h is enough: the tick's one new ring entry v is added into h with weight 1 (h = a h +
    # v - a^K v_old, or the recompute from the ring), so a NaN or Inf in v makes h non-finite, and
    # the ring's other entries were finite when their ticks were committed (or zeros of a fresh state).
    return bool(np.isfinite(action).all() and np.isfinite(state.h).all())


__all__ = ["FastSession", "finite", "non_finite", "session_of", "tick"]
