"""The toy's one layer, from its configuration."""
from __future__ import annotations

from typing import Any

from hope_models.components.layers import Layer, linear


def layers(cfg: Any, vq_cfg: None = None) -> list[Layer]:
    return [linear(cfg.obs_dim, cfg.act_dim, True)]
