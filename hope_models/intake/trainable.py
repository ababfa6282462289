"""Which components an episode can train, and for each one it cannot, why.

The rules are the ones a training run applies, read off the same signature the feature-spec
inference uses (`spec_inference.episode_signature`: the numeric leaves present with one length at
the first and the last step, and the `.npy` frames that load):

* every component's dataset needs a feature spec, and a spec has a numeric observation group
  (`infer_spec`; empty lists and lists longer than MAX_VECTOR are left out) and a numeric action
  group, which may be empty when the dataset has a camera: then only the tokenizer trains (the app's
  record screen sends an empty command);
* `vqvae`: that observation vector, or a colour camera whose frames decode at every step (inline
  `image_rgb`, or a frame file: .npy, JPEG, PNG or video, data/cameras.py); the verdict says per
  camera what will be used ("egocentric_video: 12/12 frames, JPEG 480x640 -> 64x64") or why not,
  and `reads` what the tokenizer will read, so a camera it cannot use is never passed over in silence;
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
from hope_models.data.cameras import CameraCheck
from hope_models.data.features import DEFAULT_FRAME_SIZE, FRAME_FIELD, FRAME_SHAPE, MAX_VECTOR
from hope_models.data.spec_inference import episode_signature
from hope_models.rlds.episode import Episode


def _usable(size: int) -> bool:
    return 0 < size <= MAX_VECTOR


def _vectors(leaves: dict[str, int], root: str) -> dict[str, int]:
    return {p: n for p, n in leaves.items()
            if p.startswith(root + ".") and p.split(".")[-1] != FRAME_FIELD and _usable(n)}


def _inline_frame(leaves: dict[str, int]) -> str | None:
    return next((p for p, n in leaves.items() if p.split(".")[-1] == FRAME_FIELD and n == math.prod(FRAME_SHAPE)),
                None)


def _reads(inline: str | None, checks: list[CameraCheck], obs: dict[str, int]) -> str:
    """What the tokenizer will read from this episode, and which cameras it passes over and why."""
    usable = [c for c in checks if c.ok and c.kind == "rgb"]
    if inline:
        what = f"frame {inline} (inline floats, 64x64)"
    elif usable:
        what = f"frame {usable[0].path} ({usable[0].source(DEFAULT_FRAME_SIZE)})"
    else:
        what = f"the observation vector ({sum(obs.values())} values)"
    unused = [c for c in checks if not c.ok]
    if unused:
        what += "; not usable: " + "; ".join(c.describe(DEFAULT_FRAME_SIZE) for c in unused)
    return what


def trainable(ep: Episode) -> tuple[list[str], dict[str, str]]:
    """(components `ep` can train, {component: why not} for the others), each component's reason
    from its spec (components/<name>/__init__.py, cannot_train)."""
    can, cannot, _checks, _reads_line = _verdict(ep)
    return can, cannot


def _verdict(ep: Episode) -> tuple[list[str], dict[str, str], list[CameraCheck], str]:
    if not ep.steps:
        return [], {c: "the episode has no steps" for c in COMPONENTS}, [], ""
    sig = episode_signature(ep.episode_id, ep.steps, ep.blob_root, every_step=True)
    obs = _vectors(sig.leaves, "observation")
    act = _vectors(sig.leaves, "action")
    checks = list(sig.cameras.values())
    inline = _inline_frame(sig.leaves)
    has_frame = inline is not None or any(c.ok and c.kind == "rgb" for c in checks)
    colour = [c for c in checks if c.kind == "rgb"]
    frame_why = None if has_frame or not colour else colour[0].describe(DEFAULT_FRAME_SIZE)
    missing = "" if obs else "no numeric observation field (a feature spec needs one, frames or not)"
    no_action = ""
    if not act:
        empty = [p for p, n in sig.leaves.items() if p.startswith("action.") and n == 0]
        no_action = f"{empty[0]} is always empty" if empty else "no numeric action field"
    clocked = [s.timestamp_ns for s in ep.steps if s.timestamp_ns is not None]
    facts = EpisodeFacts(steps=len(ep.steps), duration_s=ep.duration_s, clocked=len(clocked) == len(ep.steps),
                         missing=missing, no_action=no_action, has_frame=has_frame, has_obs=bool(obs),
                         frame_note=frame_why or "")
    why: dict[str, str] = {}
    tokenizer_reason = COMPONENTS[TOKENIZER].cannot_train(facts, None)
    for name, spec in COMPONENTS.items():
        reason = tokenizer_reason if spec.tokenizer else spec.cannot_train(facts, tokenizer_reason)
        if reason:
            why[name] = reason
    return [c for c in COMPONENTS if c not in why], why, checks, _reads(inline, checks, obs)


VERDICT_EXTRAS = ("cameras", "reads")  # verdict keys beside trainable / not_trainable


def verdict_fields(entry: dict[str, Any]) -> dict[str, Any]:
    """The verdict of an inbox entry as the API answers it: trainable, not_trainable, cameras and,
    when the tokenizer can train, what it reads."""
    out = {"trainable": list(entry.get("trainable", [])), "not_trainable": dict(entry.get("not_trainable", {})),
           "cameras": list(entry.get("cameras", []))}
    if "reads" in entry:
        out["reads"] = entry["reads"]
    return out


def trainable_json(ep: Episode) -> dict[str, Any]:
    """The verdict: what `ep` can train, why not the rest, each camera's line, what the tokenizer reads."""
    can, cannot, checks, reads = _verdict(ep)
    out: dict[str, Any] = {"trainable": can, "not_trainable": cannot,
                           "cameras": [c.describe(DEFAULT_FRAME_SIZE) for c in checks]}
    if TOKENIZER in can:
        out["reads"] = {TOKENIZER: reads}
    return out
