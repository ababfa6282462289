"""The learning-rate schedule: linear warmup, then cosine decay, a pure function of the step (no
scheduler object to save, so a resumed job's rate is the uninterrupted job's rate)."""
from __future__ import annotations

import math

from hope_models.train.config import TrainConfig


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Learning rate of optimizer step `step` (1-based): linear warmup, then cosine to min_lr_ratio."""
    total = cfg.steps
    warmup = min(cfg.warmup, max(1, total // 10))
    if step <= warmup:
        return cfg.lr * step / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1.0 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress)))
