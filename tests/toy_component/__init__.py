"""A toy fourth component, to prove a component is one unit: this folder plus one row of the table
(hope_models/components/__init__.py) make it trainable through the worker, gated, promoted and
answered by BrainService. tests/test_fourth_component.py copies the house, puts this folder at
hope_models/components/toy/ and adds the row; nothing else changes.

It maps the latest observation to the action through one linear layer (a "reflex" with no memory)
and has none of the roles (tokenizer, actor, predictor): BrainService answers it under `outputs`.
"""
from __future__ import annotations

from typing import Any

from hope_models.components.config_fields import make_config
from hope_models.components.spec import ComponentSpec, EpisodeFacts, on_a_clock
from hope_models.components.toy.config import ToyConfig
from hope_models.components.toy.layers import layers


def _check_window(window: Any) -> None:
    if window.horizons_s:
        raise ValueError("model_config.window.horizons_s: the toy predicts the current action, not horizons")


def _configure(spec: Any, window: Any, overrides: dict[str, Any], vq_cfg: None) -> ToyConfig:
    return make_config(ToyConfig, {"obs_dim": spec.obs_dim, "act_dim": spec.act_dim}, overrides, "toy")


def _cannot_train(facts: EpisodeFacts, tokenizer_reason: str | None) -> str | None:
    return on_a_clock(facts)


SPEC = ComponentSpec(
    name="toy",
    package=__name__,
    config_class=ToyConfig,
    window_scale="fast",
    window_defaults={"k": 1},
    check_window=_check_window,
    configure=_configure,
    layers=layers,
    cannot_train=_cannot_train,
)
