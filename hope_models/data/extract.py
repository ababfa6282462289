"""Reading a feature spec's fields out of an episode's steps as arrays.

An episode that does not fit the spec (a field missing at some step, a length that changes, a
NaN, a frame file that does not load) raises EpisodeMismatch naming the step and the field; the
cache build then excludes the episode with that reason, never pads it.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from hope_models.data.features import FeatureField, FeatureGroup, FrameFeature, is_number


class EpisodeMismatch(ValueError):
    """An episode does not fit the spec; str() is the reason shown in the excluded list."""

    def __init__(self, reason: str, step: int | None = None, field: str | None = None):
        where = "".join([f"step {step}: " if step is not None else "", f"{field}: " if field else ""])
        super().__init__(where + reason)
        self.step, self.field = step, field


def _get(step_obj: dict, parts: tuple[str, ...]) -> Any:
    v: Any = step_obj
    for part in parts:
        if not isinstance(v, dict) or part not in v:
            return _MISSING
        v = v[part]
    return v


_MISSING = object()


def field_matrix(steps: list, f: FeatureField | FrameFeature, dtype=np.float64) -> np.ndarray:
    """The field's values over the episode as an [n, size] array, or EpisodeMismatch naming the step."""
    root, *rest = f.path.split(".")
    parts = tuple(rest)
    attr = "observation" if root == "observation" else "action"
    values = [_get(getattr(s, attr), parts) for s in steps]
    size = f.size
    arr = None
    try:
        arr = np.asarray(values)  # no dtype: numpy would quietly turn "0.5" strings into floats
    except (ValueError, TypeError):
        pass  # ragged or mixed: diagnosed below
    if arr is not None and arr.dtype.kind in "fiub":
        if arr.ndim == 1 and size == 1:
            arr = arr[:, None]
        if arr.ndim == 2 and arr.shape[1] == size:
            arr = arr.astype(dtype, copy=False)
            if not np.isfinite(arr).all():
                bad = int(np.argwhere(~np.isfinite(arr))[0][0])
                raise EpisodeMismatch("value is NaN or infinite", bad, f.path)
            return arr
    for i, v in enumerate(values):  # slow path: name the first step that does not fit
        if v is _MISSING or v is None:
            raise EpisodeMismatch("missing", i, f.path)
        if isinstance(v, dict) and "uri" in v:
            raise EpisodeMismatch("is a blob reference, not numbers (a frame file needs \"source\": \"blob\" "
                                  "in the spec's frame)", i, f.path)
        if is_number(v):
            n = 1
        elif isinstance(v, list) and all(is_number(x) for x in v):
            n = len(v)
        else:
            raise EpisodeMismatch(f"not numeric ({type(v).__name__})", i, f.path)
        if n != size:
            raise EpisodeMismatch(f"has {n} values, the spec needs {size}", i, f.path)
    raise EpisodeMismatch("values do not form a numeric matrix", None, f.path)


def group_matrix(steps: list, group: FeatureGroup) -> np.ndarray:
    if not group.fields:  # the empty action group of a camera dataset without actions
        return np.zeros((len(steps), 0))
    parts = [field_matrix(steps, f) for f in group.fields]
    return np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]
