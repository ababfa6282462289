"""The VQ-VAE observation tokenizer: an observation vector or a camera frame -> one code per group
(product quantisation); the codes the Fast Loop may and the Mid Loop must read.

    config.py      VQVAEConfig (torch-free)          model.py       the torch model
    layers.py      its layers, from a config         train.py       its loss as the loop sees it
    numpy_form.py  the NumPy encoder BrainService runs, and what it accepts as a checkpoint
    held_out.py    its held-out figures and the gate's baselines verdict
"""
from __future__ import annotations

from typing import Any

from hope_models.components.config_fields import make_config
from hope_models.components.spec import ComponentSpec, EpisodeFacts
from hope_models.components.vqvae import held_out, layers
from hope_models.components.vqvae.config import GRID_CELL_DIM, VQVAEConfig


def _check_window(window: Any) -> None:
    if window.k != 1 or window.horizons_s:
        raise ValueError("model_config.window: the vqvae reads one frame (k=1, no horizons)")


def _configure(spec: Any, window: Any, overrides: dict[str, Any], vq_cfg: None) -> VQVAEConfig:
    frame = spec.frame
    derived: dict[str, Any] = {"obs_dim": spec.obs_dim}
    want = overrides.get("input", "frame" if frame is not None else "vector")
    if want == "frame":
        if frame is None:
            raise ValueError("model_config.input='frame' but the feature spec has no frame feature")
        derived["frame_shape"] = tuple(frame.shape)
        if overrides.get("layout") == "grid":  # the grid fixes the groups: one per cell
            h, w, _ = derived["frame_shape"]
            patch = overrides.get("patch", VQVAEConfig.patch)
            if isinstance(patch, int) and not isinstance(patch, bool) and patch > 0:
                derived["groups"] = (h // patch) * (w // patch)
                if "code_dim" not in overrides:
                    derived["code_dim"] = derived["groups"] * GRID_CELL_DIM
    return make_config(VQVAEConfig, {"input": want, **derived}, overrides, "vqvae")


def _cannot_train(facts: EpisodeFacts, tokenizer_reason: str | None) -> str | None:
    # A dataset without actions still has a feature spec when it has a camera: its frames are
    # what the tokenizer learns (the app's record screen sends an empty command).
    missing = "; ".join(r for r in (facts.missing, "" if facts.has_frame else facts.no_action) if r)
    if missing:
        return missing + (f"; {facts.frame_note}" if facts.frame_note and not facts.has_frame else "")
    if not (facts.has_frame or facts.has_obs):
        return "no frame and no numeric observation vector"
    return None


SPEC = ComponentSpec(
    name="vqvae",
    package=__name__,
    config_class=VQVAEConfig,
    window_scale="fast",
    window_defaults={"k": 1},  # one point: the anchor's own frame / observation
    check_window=_check_window,
    configure=_configure,
    layers=layers.layers,
    cannot_train=_cannot_train,
    tokenizer=True,
    held_out=held_out.held_out,
    held_out_line=held_out.held_out_line,
    baselines=held_out.baselines,
)
