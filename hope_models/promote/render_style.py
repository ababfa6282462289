"""How the frames a camera reflex learned from were drawn, so that its evaluation draws the same.

    style, where = trained_render_style(config)   # a checkpoint's config.json -> ("flat", "<episode>/metadata.json")

A policy cloned from one picture and scored on another is scored on a shift it never saw: the
reacher's "shaded" frames (shadow map, reflecting floor) and its "flat" ones differ in every pixel of
the floor. The recorder writes the style into each episode's provenance.sim.render; an episode
with frames and no such key was recorded before there was a choice, i.e. shaded. The checkpoint's
config.json names the dataset it was trained on (train.data); when that dataset is gone or holds no
sim episode, the style is the recorder's default and `where` says so.
"""
from __future__ import annotations

import json
from itertools import islice
from pathlib import Path
from typing import Any

from hope_models.checkpoint_format import CONFIG_FILE
from hope_models.sim.reacher import RENDER_STYLE, RENDER_STYLES

BEFORE_STYLES = "shaded"  # what recordings with frames and no provenance.sim.render were drawn as
LOOK_AT = 8  # episode metadata files read at most: one dataset is recorded with one style


def trained_render_style(config: Any) -> tuple[str, str]:
    """(the style of the frames the training data of a checkpoint's parsed config.json holds, the file
    it was read from or why the default)."""
    train = config.get("train") if isinstance(config, dict) else None
    data = train.get("data") if isinstance(train, dict) else None
    if data is None:
        return RENDER_STYLE, f"the default ({CONFIG_FILE} names no training data)"
    root = Path(data) if isinstance(data, str) else None
    if root is None or not root.is_dir():
        return RENDER_STYLE, f"the default (the training data {data} is not here)"
    found = [*root.glob("*/metadata.json"), *root.glob("*/*/metadata.json")]
    for meta in islice(sorted(found), LOOK_AT):
        try:
            sim = json.loads(meta.read_text(encoding="utf-8"))["provenance"]["sim"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if not isinstance(sim, dict) or "frame_size" not in sim:
            continue  # no frames in it: says nothing about how they are drawn
        style = sim.get("render", BEFORE_STYLES)
        if style in RENDER_STYLES:
            return style, str(meta)
    return RENDER_STYLE, f"the default (no simulated episode with frames under {root})"
