"""The picture a finished run leaves in its run dir for people to look at (HELD_OUT_PICTURE), drawn
from the same held-out episodes its validation figures are measured on.

A component that has something to show offers `held_out_picture(cache, episodes) -> uint8 [H, W, 3]
image | None` (the frame VQ-VAE: held-out frames over their reconstructions,
components/vqvae/train.py); the trainer calls `write_held_out_picture` after its validation
(loop._Trainer._validate) and the Robot Editor's run page shows the file
(webapp/api/run_files.py lists it as the artifact of kind "picture"). The picture is made here,
where torch already is, because the webapp never imports torch. It is written atomically: a reader
sees the previous picture or the new one, never half a PNG.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hope_models.durable import atomic_write

HELD_OUT_PICTURE = "held_out_frames.png"


def write_held_out_picture(component: Any, cache: Any, run_dir: Path, val_fraction: float) -> Path | None:
    """Write the component's picture of the cache's held-out episodes (the validation split of
    `val_fraction`, imagined episodes left out) to run_dir/HELD_OUT_PICTURE; None, and nothing
    written, for a component that reads no frames or has no picture, or a split without steps."""
    draw = getattr(component, "held_out_picture", None)
    if draw is None or not getattr(component, "wants_frames", False):
        return None
    from hope_models.components.picture import png  # lazy: loads numpy and Pillow
    from hope_models.data.sampler import split_episodes

    episodes = split_episodes(cache, "val", val_fraction)
    episodes = episodes[~cache.imagined[episodes]]
    image = draw(cache, episodes) if len(episodes) else None
    if image is None:
        return None
    path = Path(run_dir) / HELD_OUT_PICTURE
    atomic_write(path, png(image))
    return path


__all__ = ["HELD_OUT_PICTURE", "write_held_out_picture"]
