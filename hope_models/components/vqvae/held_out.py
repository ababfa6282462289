"""The VQ-VAE's held-out figures (validation on held-out episodes), the line a report gives them,
and the gate's baselines verdict on them: a vector VQ-VAE's reconstruction must keep at least
1 - settings.gate_vqvae_max_nmse (0.95) of the variance (recon_nmse: the squared error over the
data's variance); a frame VQ-VAE must beat the mean frame (recon_nmse < 1), its PSNR reported."""
from __future__ import annotations

import math
from typing import Any

from hope_models.components.verdict import FAILED, PASSED, fmt, num

KEYS = ("recon_nmse", "perplexity", "code_usage", "psnr_db")


def held_out(val: dict[str, Any]) -> dict[str, Any] | None:
    return {k: val[k] for k in KEYS if k in val}


def held_out_line(h: dict[str, Any]) -> str | None:
    if "recon_nmse" not in h:
        return None
    nmse = h["recon_nmse"]
    return (f"vqvae (held-out episodes): keeps {fmt(100 * (1 - nmse), '.1f')} % of the variance "
            f"(normalised MSE {fmt(nmse, '.4f')}, target <= 0.05), perplexity "
            f"{fmt(h.get('perplexity'), '.0f')} per group, code usage {fmt(100 * h.get('code_usage', math.nan), '.0f')} %")


def vqvae_verdict(val: dict[str, Any], frames: bool, max_nmse: float) -> tuple[str, str]:
    nmse = num(val, "recon_nmse")
    usage = f"perplexity {val.get('perplexity', float('nan')):.1f} per group, code usage {val.get('code_usage', float('nan')):.0%}"
    if nmse is None:
        return FAILED, "baselines: the held-out reconstruction error (recon_nmse) was not measured"
    if frames:
        psnr = num(val, "psnr_db")
        text = (f"held-out frames: normalised MSE {nmse:.4f} (the mean frame: 1), PSNR {psnr or float('nan'):.1f} dB; "
                f"{usage}")
        return (PASSED, text) if nmse < 1.0 else (FAILED, f"{text}: no better than the mean frame")
    text = (f"held-out reconstruction keeps {1 - nmse:.1%} of the variance (normalised MSE {nmse:.4f}, limit "
            f"{max_nmse:g}); {usage}")
    return (PASSED, text) if nmse <= max_nmse else (FAILED, f"{text}: the tokenizer loses too much")


def baselines(val: dict[str, Any], cand: Any, settings: Any) -> tuple[str, str]:
    return vqvae_verdict(val, bool(cand.wants_frames), float(settings.gate_vqvae_max_nmse))
