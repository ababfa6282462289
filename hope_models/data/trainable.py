"""Which components an episode can train, and for each one it cannot, why.

The rules are the ones a training run applies, read off the same signature the feature-spec
inference uses (`spec_inference.episode_signature`: the numeric leaves present with one length at
the first and the last step, and the `.npy` frames that load):

* every component's dataset needs a feature spec, and a spec has a numeric observation group and
  a numeric action group (`infer_spec`; empty lists and lists longer than MAX_VECTOR are left out),
  so an episode without both trains nothing, whatever its frames;
* `vqvae`: that observation vector, or a loadable 64x64x3 frame (inline `image_rgb` or a `.npy`
  blob, data/frames.py); a JPEG or video file is not a frame the cache can read;
* `fast_loop`: the numeric observation and a non-empty numeric action, on a clock, with at least
  as many steps as its window has points (K=5 over 100 ms: train/model_config.DEFAULT_WINDOWS);
* `mid_loop`: the same over at least its window (2 s) plus its furthest horizon (1 s): its target
  is the code that far ahead.
An episode called trainable here can still be left out of a dataset whose other episodes choose
different fields (the 90 % coverage rule); that is the dataset's verdict, not the episode's.
"""
from __future__ import annotations

import math
from typing import Any

from hope_models.data.features import FRAME_FIELD, FRAME_SHAPE, MAX_VECTOR
from hope_models.data.spec_inference import episode_signature
from hope_models.rlds.episode import Episode

COMPONENTS = ("vqvae", "fast_loop", "mid_loop")
FAST_WINDOW_POINTS = 5  # the fast window's K (model_config.DEFAULT_WINDOWS, data/windows.py)
MID_SPAN_S = 2.0 + 1.0  # the mid window (2 s) and its furthest default horizon (1 s)


def _usable(size: int) -> bool:
    return 0 < size <= MAX_VECTOR


def _vectors(leaves: dict[str, int], root: str) -> dict[str, int]:
    return {p: n for p, n in leaves.items()
            if p.startswith(root + ".") and p.split(".")[-1] != FRAME_FIELD and _usable(n)}


def _frame(leaves: dict[str, int], frame_blobs: dict[str, str]) -> tuple[bool, str | None]:
    """(has a loadable frame, why a frame-like reference is not one)."""
    inline = [p for p, n in leaves.items() if p.split(".")[-1] == FRAME_FIELD and n == math.prod(FRAME_SHAPE)]
    if inline or any(status == "ok" for status in frame_blobs.values()):
        return True, None
    if frame_blobs:
        path, status = sorted(frame_blobs.items())[0]
        return False, f"{path}: {status}"
    return False, None


def _media_note(ep: Episode) -> str | None:
    """A frame the app recorded as a picture file: said, so nobody wonders why it is not used."""
    for step in ep.steps[:1]:
        for key, value in step.observation.items():
            uri = value.get("uri") if isinstance(value, dict) else None
            if isinstance(uri, str) and uri and not uri.lower().endswith(".npy") and "video" in key:
                return (f"observation.{key} is a {uri.rsplit('.', 1)[-1][:8]} file; training reads frames "
                        f"as {list(FRAME_SHAPE)} .npy blobs")
    return None


def trainable(ep: Episode) -> tuple[list[str], dict[str, str]]:
    """(components `ep` can train, {component: why not} for the others)."""
    if not ep.steps:
        return [], {c: "the episode has no steps" for c in COMPONENTS}
    sig = episode_signature(ep.episode_id, ep.steps, ep.blob_root)
    obs = _vectors(sig.leaves, "observation")
    act = _vectors(sig.leaves, "action")
    has_frame, frame_why = _frame(sig.leaves, sig.frame_blobs)
    why: dict[str, str] = {}
    missing = []
    if not obs:
        missing.append("no numeric observation field (a feature spec needs one, frames or not)")
    if not act:
        empty = [p for p, n in sig.leaves.items() if p.startswith("action.") and n == 0]
        missing.append(f"{empty[0]} is always empty" if empty else "no numeric action field")
    base = "; ".join(missing)
    note = frame_why or _media_note(ep)
    if base:
        why["vqvae"] = base + (f"; {note}" if note and not has_frame else "")
    elif not (has_frame or obs):
        why["vqvae"] = "no frame and no numeric observation vector"
    clocked = [s.timestamp_ns for s in ep.steps if s.timestamp_ns is not None]
    if base:
        why["fast_loop"] = base
    elif len(clocked) < len(ep.steps):
        why["fast_loop"] = "steps without a clock (timestamp_ns): windows are placed in time"
    elif len(ep.steps) < FAST_WINDOW_POINTS:
        why["fast_loop"] = f"{len(ep.steps)} steps; its window needs {FAST_WINDOW_POINTS}"
    if "vqvae" in why:
        why["mid_loop"] = "it predicts VQ-VAE codes, and " + why["vqvae"]
    elif "fast_loop" in why:
        why["mid_loop"] = why["fast_loop"]
    elif ep.duration_s < MID_SPAN_S:
        why["mid_loop"] = (f"{ep.duration_s:.2f} s long; its 2 s window and 1 s horizon need "
                           f"{MID_SPAN_S:g} s")
    return [c for c in COMPONENTS if c not in why], why


def trainable_json(ep: Episode) -> dict[str, Any]:
    can, cannot = trainable(ep)
    return {"trainable": can, "not_trainable": cannot}
