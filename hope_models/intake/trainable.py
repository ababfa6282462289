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
  as many steps as its window has points (K=5 over 100 ms: its spec's window);
* `mid_loop`: the same over at least its window (2 s) plus its furthest horizon (1 s): its target
  is the code that far ahead.
Each rule is the component's spec's (cannot_train, in its folder's __init__.py); this module reads
the facts they are judged on off the episode.
An episode called trainable here can still be left out of a dataset whose other episodes choose
different fields (the 90 % coverage rule); that is the dataset's verdict, not the episode's.
"""
from __future__ import annotations

import math
from typing import Any

from hope_models.components import COMPONENTS, TOKENIZER
from hope_models.components.spec import EpisodeFacts
from hope_models.data.features import FRAME_FIELD, FRAME_SHAPE, MAX_VECTOR
from hope_models.data.spec_inference import episode_signature
from hope_models.rlds.episode import Episode


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
    """(components `ep` can train, {component: why not} for the others), each component's reason
    from its spec (components/<name>/__init__.py, cannot_train)."""
    if not ep.steps:
        return [], {c: "the episode has no steps" for c in COMPONENTS}
    sig = episode_signature(ep.episode_id, ep.steps, ep.blob_root)
    obs = _vectors(sig.leaves, "observation")
    act = _vectors(sig.leaves, "action")
    has_frame, frame_why = _frame(sig.leaves, sig.frame_blobs)
    missing = []
    if not obs:
        missing.append("no numeric observation field (a feature spec needs one, frames or not)")
    if not act:
        empty = [p for p, n in sig.leaves.items() if p.startswith("action.") and n == 0]
        missing.append(f"{empty[0]} is always empty" if empty else "no numeric action field")
    clocked = [s.timestamp_ns for s in ep.steps if s.timestamp_ns is not None]
    facts = EpisodeFacts(steps=len(ep.steps), duration_s=ep.duration_s, clocked=len(clocked) == len(ep.steps),
                         missing="; ".join(missing), has_frame=has_frame, has_obs=bool(obs),
                         frame_note=frame_why or _media_note(ep) or "")
    why: dict[str, str] = {}
    tokenizer_reason = COMPONENTS[TOKENIZER].cannot_train(facts, None)
    for name, spec in COMPONENTS.items():
        reason = tokenizer_reason if spec.tokenizer else spec.cannot_train(facts, tokenizer_reason)
        if reason:
            why[name] = reason
    return [c for c in COMPONENTS if c not in why], why


def trainable_json(ep: Episode) -> dict[str, Any]:
    can, cannot = trainable(ep)
    return {"trainable": can, "not_trainable": cannot}
