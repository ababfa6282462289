"""The Mid Loop's held-out figures per horizon, the line a report gives them, and the gate's
baselines verdict on them: at each horizon the code log-likelihood beats copy-last and the code
frequencies (nll below both; metrics.py defines them), and with a vector VQ-VAE the decoded
predicted observation's error is lower than copy-last's by at least
settings.gate_mid_loop_min_gain (0.30); over a grid frame VQ-VAE (grid_model.py) its predicted
joints' error is lower than copy-last's by as much. Its world model (the action-conditioned wm_ heads, when
it has them) must predict the next grid steps better than copy-last (wm_obs_mse below
wm_copy_obs_mse): imagination searches in it."""
from __future__ import annotations

from typing import Any

from hope_models.components.verdict import FAILED, PASSED, fmt, num

KEYS = ("obs_mse", "copy_last_obs_mse", "nll", "copy_last_nll", "code_freq_nll", "joint_mse", "copy_last_joint_mse")


def held_out(val: dict[str, Any]) -> dict[str, Any] | None:
    labels = sorted({k[len("nll_"):] for k in val if k.startswith("nll_")}, key=lambda x: float(x.rstrip("s")))
    return {label: {k: val.get(f"{k}_{label}") for k in KEYS} for label in labels}


def _than(mse: Any, copy: Any) -> str:
    gain = (1 - mse / copy) if isinstance(mse, (int, float)) and isinstance(copy, (int, float)) and copy else None
    return "-" if gain is None else f"{abs(100 * gain):.0f} % {'lower' if gain >= 0 else 'higher'}"


def held_out_line(h: dict[str, Any]) -> str | None:
    parts = []
    for label, f in h.items():
        mse, copy = f.get("obs_mse"), f.get("copy_last_obs_mse")
        what = "observation"
        if mse is None and f.get("joint_mse") is not None:  # a grid Mid Loop predicts the joints themselves
            mse, copy, what = f.get("joint_mse"), f.get("copy_last_joint_mse"), "joint"
        parts.append(f"{label}: {what} error {fmt(mse, '.3f')} vs copy-last {fmt(copy, '.3f')} "
                     f"({_than(mse, copy)}), nll {fmt(f.get('nll'), '.2f')} "
                     f"vs copy-last {fmt(f.get('copy_last_nll'), '.2f')}, code frequency {fmt(f.get('code_freq_nll'), '.2f')}")
    return "mid_loop (held-out episodes): " + "; ".join(parts)


def _gain_check(val: dict[str, Any], label: str, what: tuple[str, str], keys: tuple[str, str], min_gain: float,
                parts: list[str], short: list[str]) -> None:
    """what: (its name, its possessive), e.g. ("joint", "joints'")."""
    name, whose = what
    mse, copy_mse = num(val, f"{keys[0]}_{label}"), num(val, f"{keys[1]}_{label}")
    if mse is None or copy_mse is None or copy_mse <= 0:
        short.append(f"{label}: the predicted {whose} error was not measured")
        return
    gain = 1.0 - mse / copy_mse
    than = f"{abs(gain):.0%} {'lower' if gain >= 0 else 'higher'}"
    parts[-1] += f"; {name} error {mse:.4f} vs copy-last {copy_mse:.4f} ({than}, needs {min_gain:.0%} lower)"
    if gain < min_gain:
        short.append(f"{label}: its predicted {whose} error is {than} than copy-last's")


def mid_loop_verdict(val: dict[str, Any], labels: list[str], vector: bool, min_gain: float,
                     joints: bool = False) -> tuple[str, str]:
    """vector: the decoded observation must beat copy-last by min_gain; joints (a grid Mid Loop):
    its predicted joints must."""
    parts, short = [], []
    for label in labels:
        nll, copy, freq = (num(val, f"{k}_{label}") for k in ("nll", "copy_last_nll", "code_freq_nll"))
        if nll is None or copy is None or freq is None:
            short.append(f"{label}: the log-likelihoods were not measured")
            continue
        text = f"{label}: nll {nll:.3f} vs copy-last {copy:.3f}, code frequency {freq:.3f}"
        if not (nll < copy and nll < freq):
            short.append(f"{label}: its code log-likelihood does not beat both baselines")
        parts.append(text)
        if vector:
            _gain_check(val, label, ("observation", "observation's"), ("obs_mse", "copy_last_obs_mse"), min_gain, parts, short)
        if joints:
            _gain_check(val, label, ("joint", "joints'"), ("joint_mse", "copy_last_joint_mse"), min_gain, parts, short)
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
    grid = bool(getattr(cand.model, "grid", False))  # grid_model.GridMidLoop: it predicts the joints
    return mid_loop_verdict(val, labels, not cand.wants_frames, float(settings.gate_mid_loop_min_gain), joints=grid)
