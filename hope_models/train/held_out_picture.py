"""The picture a finished run leaves in its run dir for people to look at, drawn from the same
held-out episodes its validation figures are measured on.

A component that has something to show offers `held_out_picture(cache, episodes) -> uint8 [H, W, 3]
image | None`; the file is named for what it shows, by the component's role (`picture_name`):
- HELD_OUT_PICTURE, the frame VQ-VAE's: held-out frames over their reconstructions
  (components/vqvae/train.py);
- PREDICTED_PICTURE, the predictor's (spec.predicts; a grid Mid Loop): one held-out window a row,
  the frame now, then at each horizon (0.5 s, 1 s) the frame decoded from the predicted codes
  beside the recorded one (components/mid_loop/grid_picture.py).
The trainer calls `write_held_out_picture` after its validation (loop._Trainer._validate) and the
Robot Editor's run page shows the file (webapp/api/run_files.py lists both names as artifacts of
kind "picture"). The picture is made here, where torch already is, because the webapp never
imports torch. It is written atomically: a reader sees the previous picture or the new one, never
half a PNG.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hope_models.components import COMPONENTS
from hope_models.durable import atomic_write

HELD_OUT_PICTURE = "held_out_frames.png"
PREDICTED_PICTURE = "predicted_frames.png"


def picture_name(component: Any) -> str:
    """The file a component's picture goes to: a predictor's shows predictions, any other's reconstructions."""
    spec = COMPONENTS.get(getattr(component, "name", None))
    return PREDICTED_PICTURE if spec is not None and spec.predicts else HELD_OUT_PICTURE


def write_held_out_picture(component: Any, cache: Any, run_dir: Path, val_fraction: float) -> Path | None:
    """Write the component's picture of the cache's held-out episodes (the validation split of
    `val_fraction`, imagined episodes left out) to run_dir/picture_name(component); None, and nothing
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
    path = Path(run_dir) / picture_name(component)
    atomic_write(path, png(image))
    return path


__all__ = ["HELD_OUT_PICTURE", "PREDICTED_PICTURE", "picture_name", "write_held_out_picture"]
