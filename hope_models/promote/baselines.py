"""The gate's baselines check: a component whose spec names baselines (the tokenizer, the
predictor) is promoted only if it beats the trivial answer on held-out episodes, measured on the
validation batches the val_loss check scored. Each component's verdict is in its folder's
held_out.py (vqvae: the variance its reconstruction keeps; mid_loop: copy-last and the code
frequencies at every horizon, and its world model). The verdict's detail carries every figure, so
a refusal says by how much.
"""
from __future__ import annotations

from typing import Any

from hope_models.components import spec_of
from hope_models.components.verdict import FAILED


def baselines_check(gate, metrics: dict[str, Any], cand, val: dict[str, Any] | None) -> None:
    """Record the baselines check of a candidate whose component has baselines (others have none)."""
    verdict = spec_of(cand.name).baselines
    if verdict is None:
        return
    if val is None:
        gate.record("baselines", FAILED, "baselines: not measured: no held-out validation figures, so the "
                                         f"{cand.name} cannot show it beats its baselines")
        return
    status, detail = verdict(val, cand, gate.settings)
    metrics["baselines"] = {"status": status, "detail": detail}
    gate.record("baselines", status, detail)
