"""The Mid Loop predictor: a frozen VQ-VAE's codes and the actions over 2 s -> the codes 0.5 s and
1 s ahead, and (with a vector VQ-VAE) an action-conditioned world model imagination searches in.

    config.py      MidLoopConfig (torch-free)        model.py, metrics.py   the torch model, its losses
    layers.py      its layers, from a config         train.py       its loss as the loop sees it
    grid_model.py, grid_metrics.py  the model over a grid frame tokenizer (per-cell codes + joints), its loss
    grid_picture.py  its held-out picture: predicted frames at each horizon beside the recorded ones
    numpy_form.py  the NumPy predictor BrainService runs; checkpoint.py: what it accepts
    held_out.py    its held-out figures and the gate's baselines verdict
"""
from __future__ import annotations

from typing import Any

from hope_models.components.config_fields import horizon_steps, make_config
from hope_models.components.mid_loop import held_out, layers
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.spec import ComponentSpec, EpisodeFacts, on_a_clock

SPAN_S = 2.0 + 1.0  # the default window (2 s) and its furthest default horizon (1 s)


def _check_window(window: Any) -> None:
    if not window.horizons_s:
        raise ValueError("model_config.window.horizons_s: the mid_loop needs at least one horizon")


def _configure(spec: Any, window: Any, overrides: dict[str, Any], vq_cfg: Any) -> MidLoopConfig:
    derived = {"act_dim": spec.act_dim, "n_codes": vq_cfg.n_codes, "horizon_steps": horizon_steps(window)}
    if vq_cfg.input == "frame" and vq_cfg.layout == "grid":  # grid_model.py: the joints are read and predicted
        derived["obs_dim"] = spec.obs_dim
    return make_config(MidLoopConfig, derived, overrides, "mid_loop")


def _cannot_train(facts: EpisodeFacts, tokenizer_reason: str | None) -> str | None:
    if tokenizer_reason:
        return "it predicts VQ-VAE codes, and " + tokenizer_reason
    reason = on_a_clock(facts)
    if reason is None and facts.duration_s < SPAN_S:
        reason = f"{facts.duration_s:.2f} s long; its 2 s window and 1 s horizon need {SPAN_S:g} s"
    return reason


SPEC = ComponentSpec(
    name="mid_loop",
    package=__name__,
    config_class=MidLoopConfig,
    window_scale="mid",
    window_defaults={"horizons_s": (0.5, 1.0)},  # 2 s, K=20 (100 ms grid): 5 and 10 grid steps ahead
    check_window=_check_window,
    configure=_configure,
    layers=layers.layers,
    cannot_train=_cannot_train,
    reads_vqvae="required",
    predicts=True,
    held_out=held_out.held_out,
    held_out_line=held_out.held_out_line,
    baselines=held_out.baselines,
    stored_defaults={"grid_world_model": 0},  # grid checkpoints before it have no wm_* weights
)
