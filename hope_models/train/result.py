"""What a training job ends with: `TrainResult` (result.json, the CLI's summary, the worker's report)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from hope_models.train.contract import OUTCOME_EXIT_CODES


@dataclass
class TrainResult:
    outcome: str  # a key of contract.OUTCOME_EXIT_CODES
    component: str
    steps: int  # optimizer steps done (all attempts together)
    total_steps: int
    first_loss: float | None
    final_loss: float | None
    checkpoint: str | None  # the newest good checkpoint dir
    peak_rss_mb: float
    resumed_from: int | None  # the step this attempt resumed at, None for a fresh start
    summary: dict[str, Any] = field(default_factory=dict)  # convergence summary (+ "val" metrics)
    message: str = ""
    elapsed_s: float = 0.0  # training wall time of all attempts

    @property
    def exit_code(self) -> int:
        return OUTCOME_EXIT_CODES[self.outcome]

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)

    def cli_json(self) -> dict[str, Any]:
        keys = ("component", "steps", "first_loss", "final_loss", "checkpoint", "peak_rss_mb", "resumed_from",
                "outcome")
        out = {k: getattr(self, k) for k in keys}
        out["peak_rss_mb"] = round(self.peak_rss_mb, 1)
        if self.message:
            out["message"] = self.message
        return out
