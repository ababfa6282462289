"""What BrainService.status() says of a served component beyond its version and sessions."""
from __future__ import annotations

from typing import Any


def status_extra(model: Any, vq_model: Any) -> dict[str, Any]:
    """What status() adds for a component: its VQ-VAE's consistency with the promoted tokenizer
    (a component that carries one), and its shape of answer (its runtime's status_fields)."""
    out: dict[str, Any] = {}
    if model is None:
        return out
    if hasattr(model, "vqvae_sha256"):
        carried = model.vqvae_sha256
        out["vqvae_sha256"] = carried
        # True/False: whether the VQ-VAE it carries is the one promoted as the tokenizer (weights
        # sha256); None when it reads no VQ-VAE or no tokenizer is served
        out["vqvae_matches_promoted"] = (None if carried is None or vq_model is None else carried == vq_model.sha256)
    out.update(model.status_fields())
    return out
