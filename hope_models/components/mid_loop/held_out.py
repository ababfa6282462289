"""The Mid Loop's held-out figures per horizon, the line a report gives them, and the gate's
baselines verdict on them: at each horizon the code log-likelihood beats copy-last and the code
frequencies (nll below both; metrics.py defines them), and with a vector VQ-VAE the decoded
predicted observation's error is lower than copy-last's by at least
settings.gate_mid_loop_min_gain (0.30). Its world model (the action-conditioned wm_ heads, when
it has them) must predict the next grid steps better than copy-last (wm_obs_mse below
wm_copy_obs_mse): imagination searches in it."""
from __future__ import annotations

from typing import Any

from hope_models.components.verdict import FAILED, PASSED, fmt, num

KEYS = ("obs_mse", "copy_last_obs_mse", "nll", "copy_last_nll", "code_freq_nll")


def held_out(val: dict[str, Any]) -> dict[str, Any] | None:
    labels = sorted({k[len("nll_"):] for k in val if k.startswith("nll_")}, key=lambda x: float(x.rstrip("s")))
    return {label: {k: val.get(f"{k}_{label}") for k in KEYS} for label in labels}


def held_out_line(h: dict[str, Any]) -> str | None:
    parts = []
    for label, f in h.items():
        mse, copy = f.get("obs_mse"), f.get("copy_last_obs_mse")
        gain = (1 - mse / copy) if isinstance(mse, (int, float)) and isinstance(copy, (int, float)) and copy else None
        than = "-" if gain is None else f"{abs(100 * gain):.0f} % {'lower' if gain >= 0 else 'higher'}"
        parts.append(f"{label}: observation error {fmt(mse, '.3f')} vs copy-last {fmt(copy, '.3f')} "
                     f"({than}), nll {fmt(f.get('nll'), '.2f')} "
                     f"vs copy-last {fmt(f.get('copy_last_nll'), '.2f')}, code frequency {fmt(f.get('code_freq_nll'), '.2f')}")
    return "mid_loop (held-out episodes): " + "; ".join(parts)


def mid_loop_verdict(val: dict[str, Any], labels: list[str], vector: bool, min_gain: float) -> tuple[str, str]:
    parts, short = [], []
    for label in labels:
        nll, copy, freq = (num(val, f"{k}_{label}") for k in ("nll", "copy_last_nll", "code_freq_nll"))
        if nll is None or copy is None or freq is None:
            short.append(f"{label}: the log-likelihoods were not measured")
            continue
        text = f"{label}: nll {nll:.3f} vs copy-last {copy:.3f}, code frequency {freq:.3f}"
        if not (nll < copy and nll < freq):
            short.append(f"{label}: its code log-likelihood does not beat both baselines")
        if vector:
            mse, copy_mse = num(val, f"obs_mse_{label}"), num(val, f"copy_last_obs_mse_{label}")
            if mse is None or copy_mse is None or copy_mse <= 0:
                short.append(f"{label}: the predicted observation's error was not measured")
            else:
                gain = 1.0 - mse / copy_mse
                than = f"{abs(gain):.0%} {'lower' if gain >= 0 else 'higher'}"
                text += f"; observation error {mse:.4f} vs copy-last {copy_mse:.4f} ({than}, needs {min_gain:.0%} lower)"
                if gain < min_gain:
                    short.append(f"{label}: its predicted observation's error is {than} than copy-last's")
        parts.append(text)
    wm, wm_copy = num(val, "wm_obs_mse"), num(val, "wm_copy_obs_mse")
    if wm is not None and wm_copy is not None:
        parts.append(f"world model: observation error {wm:.4f} vs copy-last {wm_copy:.4f}")
        if not wm < wm_copy:
            short.append("its world model predicts no better than copy-last")
    detail = "held-out " + "; ".join(parts) if parts else "no held-out figures"
    if short:
        return FAILED, f"{detail}: {'; '.join(short)}"
    return PASSED, detail


def baselines(val: dict[str, Any], cand: Any, settings: Any) -> tuple[str, str]:
    labels = [f"{h:g}s" for h in cand.window.horizons_s]
    return mid_loop_verdict(val, labels, not cand.wants_frames, float(settings.gate_mid_loop_min_gain))
