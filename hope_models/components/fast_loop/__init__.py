"""The Fast Loop reflex policy: the last 100 ms of observations (+ a frozen VQ-VAE's codes, when it
has one) -> the action, window-exact over its K grid points.

    config.py      FastLoopConfig (torch-free)       model.py       the torch model
    layers.py      its layers, from a config         train.py       its loss as the loop sees it
    numpy_form.py  the NumPy policy BrainService runs; numpy_act.py: it as a session's action
    checkpoint.py  what the NumPy form accepts as a checkpoint
"""
from __future__ import annotations

from typing import Any

from hope_models.components.config_fields import make_config
from hope_models.components.fast_loop import layers
from hope_models.components.fast_loop.config import FastLoopConfig
from hope_models.components.spec import ComponentSpec, EpisodeFacts, on_a_clock


def _check_window(window: Any) -> None:
    if window.horizons_s:
        raise ValueError("model_config.window.horizons_s: the fast_loop predicts the current action, not horizons")


def view_joint(spec: Any, vq_cfg: Any) -> dict[str, Any]:
    """The observation's first joint angle, for a policy reading a grid of frame codes: the index of
    the first value of a `joint_positions` field and its statistics (none: index -1)."""
    if vq_cfg is None or vq_cfg.input != "frame" or vq_cfg.layout != "grid" or not spec.observation.has_stats:
        return {"view_joint": -1}
    start = 0
    for f in spec.observation.fields:
        if f.path.rsplit(".", 1)[-1] == "joint_positions":
            return {"view_joint": start, "view_joint_mean": float(spec.observation.mean[start]),
                    "view_joint_std": float(spec.observation.std[start])}
        start += f.size
    return {"view_joint": -1}


def _configure(spec: Any, window: Any, overrides: dict[str, Any], vq_cfg: Any) -> FastLoopConfig:
    # window_k follows the window: the policy is window-exact over the K points it is trained on.
    # view_joint follows the spec, unless turned off (-1: by the request, or a checkpoint from before it)
    view = {} if overrides.get("view_joint") == -1 else view_joint(spec, vq_cfg)
    return make_config(FastLoopConfig, {"obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "window_k": window.k,
                                        "n_codes": 0 if vq_cfg is None else vq_cfg.n_codes, **view},
                       overrides, "fast_loop")


def _cannot_train(facts: EpisodeFacts, tokenizer_reason: str | None) -> str | None:
    return on_a_clock(facts)


SPEC = ComponentSpec(
    name="fast_loop",
    package=__name__,
    config_class=FastLoopConfig,
    window_scale="fast",
    window_defaults={},  # 100 ms, K=5
    check_window=_check_window,
    configure=_configure,
    layers=layers.layers,
    cannot_train=_cannot_train,
    reads_vqvae="optional",
    acts=True,
    # a camera policy from before the frames reader: keypoints placed by its loss, read unturned;
    # from before the vector drawing: its points drew codes
    stored_defaults={"keypoint_reader": "policy", "view_joint": -1, "keypoint_draw": "codes"},
)
