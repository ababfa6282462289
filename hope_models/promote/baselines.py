"""The gate's baselines check: a tokenizer or a predictor is promoted only if it beats the trivial
answer on held-out episodes, measured on the validation batches the val_loss check scored.

- vqvae (vector input): the held-out reconstruction's normalised MSE (validation recon_nmse: the
  squared error over the data's variance, 1 - the share of variance kept) must be at most
  settings.gate_vqvae_max_nmse (0.05: keeps >= 95 %). A frame VQ-VAE must beat the mean frame
  (recon_nmse < 1); its PSNR is reported.
- mid_loop, at each horizon: the code log-likelihood beats copy-last and the code frequencies
  (nll below both; mid_loop_metrics.py defines them), and with a vector VQ-VAE the decoded predicted
  observation's error is lower than copy-last's by at least settings.gate_mid_loop_min_gain (0.30).
  Its world model (the action-conditioned wm_ heads, when it has them) must predict the next grid
  steps better than copy-last (wm_obs_mse below wm_copy_obs_mse): imagination searches in it.

The verdict's detail carries every figure, so a refusal says by how much.
"""
from __future__ import annotations

import math
from typing import Any

PASSED, FAILED = "passed", "failed"


def _num(metrics: dict[str, Any], key: str) -> float | None:
    v = metrics.get(key)
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def vqvae_verdict(val: dict[str, Any], frames: bool, max_nmse: float) -> tuple[str, str]:
    nmse = _num(val, "recon_nmse")
    usage = f"perplexity {val.get('perplexity', float('nan')):.1f} per group, code usage {val.get('code_usage', float('nan')):.0%}"
    if nmse is None:
        return FAILED, "baselines: the held-out reconstruction error (recon_nmse) was not measured"
    if frames:
        psnr = _num(val, "psnr_db")
        text = (f"held-out frames: normalised MSE {nmse:.4f} (the mean frame: 1), PSNR {psnr or float('nan'):.1f} dB; "
                f"{usage}")
        return (PASSED, text) if nmse < 1.0 else (FAILED, f"{text}: no better than the mean frame")
    text = (f"held-out reconstruction keeps {1 - nmse:.1%} of the variance (normalised MSE {nmse:.4f}, limit "
            f"{max_nmse:g}); {usage}")
    return (PASSED, text) if nmse <= max_nmse else (FAILED, f"{text}: the tokenizer loses too much")


def mid_loop_verdict(val: dict[str, Any], labels: list[str], vector: bool, min_gain: float) -> tuple[str, str]:
    parts, short = [], []
    for label in labels:
        nll, copy, freq = (_num(val, f"{k}_{label}") for k in ("nll", "copy_last_nll", "code_freq_nll"))
        if nll is None or copy is None or freq is None:
            short.append(f"{label}: the log-likelihoods were not measured")
            continue
        text = f"{label}: nll {nll:.3f} vs copy-last {copy:.3f}, code frequency {freq:.3f}"
        if not (nll < copy and nll < freq):
            short.append(f"{label}: its code log-likelihood does not beat both baselines")
        if vector:
            mse, copy_mse = _num(val, f"obs_mse_{label}"), _num(val, f"copy_last_obs_mse_{label}")
            if mse is None or copy_mse is None or copy_mse <= 0:
                short.append(f"{label}: the predicted observation's error was not measured")
            else:
                gain = 1.0 - mse / copy_mse
                than = f"{abs(gain):.0%} {'lower' if gain >= 0 else 'higher'}"
                text += f"; observation error {mse:.4f} vs copy-last {copy_mse:.4f} ({than}, needs {min_gain:.0%} lower)"
                if gain < min_gain:
                    short.append(f"{label}: its predicted observation's error is {than} than copy-last's")
        parts.append(text)
    wm, wm_copy = _num(val, "wm_obs_mse"), _num(val, "wm_copy_obs_mse")
    if wm is not None and wm_copy is not None:
        parts.append(f"world model: observation error {wm:.4f} vs copy-last {wm_copy:.4f}")
        if not wm < wm_copy:
            short.append("its world model predicts no better than copy-last")
    detail = "held-out " + "; ".join(parts) if parts else "no held-out figures"
    if short:
        return FAILED, f"{detail}: {'; '.join(short)}"
    return PASSED, detail


def baselines_check(gate, metrics: dict[str, Any], cand, val: dict[str, Any] | None) -> None:
    """Record the baselines check of a vqvae or mid_loop candidate (others have none)."""
    if cand.name not in ("vqvae", "mid_loop"):
        return
    if val is None:
        gate.record("baselines", FAILED, "baselines: not measured: no held-out validation figures, so the "
                                         f"{cand.name} cannot show it beats its baselines")
        return
    s = gate.settings
    if cand.name == "vqvae":
        status, detail = vqvae_verdict(val, bool(cand.wants_frames), float(s.gate_vqvae_max_nmse))
    else:
        labels = [f"{h:g}s" for h in cand.window.horizons_s]
        status, detail = mid_loop_verdict(val, labels, not cand.wants_frames, float(s.gate_mid_loop_min_gain))
    metrics["baselines"] = {"status": status, "detail": detail}
    gate.record("baselines", status, detail)
