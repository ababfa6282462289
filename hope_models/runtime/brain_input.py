"""What BrainService accepts in a request, and the error it answers with. Torch-free."""
from __future__ import annotations

import math
from typing import Any

MAX_SESSIONS = 256
MAX_SESSION_CHARS = 128
MAX_OBSERVATION = 4096  # longer lists are refused before any conversion
# The largest |value| an observation may hold. Robot observations are joint angles (rad),
# velocities, positions (m), forces: none comes within orders of magnitude of this, so a larger
# value is a unit or encoding error of the client. The bound also keeps the float32 arithmetic of
# the tick finite: normalised by a std of at least the default floor (1e-3), a value of 1e6 is
# 1e9, and its squares stay far below float32's 3.4e38 (values near that limit overflowed to Inf
# and answered NaN, poisoning the session's recurrent state).
MAX_ABS_OBSERVATION = 1e6


class BrainError(ValueError):
    """A request BrainService cannot answer; `.status` is the HTTP status that fits (400 bad input,
    404 unknown component, 503 no model to serve yet, 500 the served model computed a non-finite
    answer from a valid observation)."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


def observation_values(observation: Any) -> list[float]:
    """A JSON list of finite numbers within +-MAX_ABS_OBSERVATION -> floats; BrainError(400)
    naming what is wrong otherwise."""
    if not isinstance(observation, (list, tuple)):
        raise BrainError(f"observation must be a list of numbers, got {type(observation).__name__}")
    if not observation:
        raise BrainError("observation is empty; it must be a list of numbers")
    if len(observation) > MAX_OBSERVATION:
        raise BrainError(f"observation has {len(observation)} values; at most {MAX_OBSERVATION} are accepted")
    values = []
    for i, v in enumerate(observation):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise BrainError(f"observation[{i}] = {v!r} is not a number")
        try:
            f = float(v)
        except OverflowError:  # a huge JSON integer
            raise BrainError(f"observation[{i}] is too large for a float") from None
        if not math.isfinite(f):
            raise BrainError(f"observation[{i}] = {f} is not finite (NaN and Inf are refused)")
        if abs(f) > MAX_ABS_OBSERVATION:
            raise BrainError(f"observation[{i}] = {f:g} is outside the accepted range [-{MAX_ABS_OBSERVATION:g}, "
                             f"{MAX_ABS_OBSERVATION:g}] (robot observations are far smaller: check the units)")
        values.append(f)
    return values


def check_session(session: Any) -> None:
    """BrainError(400) unless `session` is None (no session) or a string of 1 to MAX_SESSION_CHARS characters."""
    if session is not None and (not isinstance(session, str) or not 0 < len(session) <= MAX_SESSION_CHARS):
        raise BrainError(f"session must be a string of 1 to {MAX_SESSION_CHARS} characters (or omitted)")


__all__ = ["BrainError", "MAX_ABS_OBSERVATION", "MAX_OBSERVATION", "MAX_SESSIONS", "MAX_SESSION_CHARS",
           "check_session", "observation_values"]
