"""What the training loop needs from a component, and what it accepts from outside while it runs.

The loop (loop.py) knows nothing about any model: a `Component` turns a window batch into a loss.
The worker, the CLI and the tests steer a running job only through a `Control`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

# Outcomes of a training job (TrainResult.outcome), and the CLI exit code for each.
OUTCOME_EXIT_CODES = {
    "completed": 0,
    "failed": 1,  # NaN/Inf loss, or an error during the job; the last good checkpoint is kept
    "paused_memory": 3,  # checkpointed at the memory soft limit; re-run to resume
    "paused_user": 4,  # checkpointed because Control asked for a pause; re-run to resume
    "cancelled": 5,  # stopped because Control asked; checkpoints are kept
    "paused_disk": 6,  # a write hit ENOSPC/EDQUOT; the last checkpoint is kept; free space, re-run to resume
}


class Component(Protocol):
    """A trainable HOPE component bound to one dataset's feature spec."""

    name: str  # one of hope_models.components.COMPONENTS

    @property
    def model(self) -> "Any":  # torch.nn.Module: its state_dict is what checkpoints hold
        ...

    @property
    def window(self) -> "Any":  # hope_models.data.windows.WindowSpec the sampler cuts for it
        ...

    @property
    def wants_frames(self) -> bool:  # make_windows(..., frames=True)
        ...

    def loss(self, batch: "Any") -> tuple["Any", dict[str, float]]:
        """Training loss (a scalar tensor with grad) and extra metrics (perplexity, accuracy, ...)
        for one hope_models.data.windows.WindowBatch."""

    def evaluate(self, batch: "Any") -> dict[str, float]:
        """Metrics without grad on a validation batch; must include "loss"."""

    def after_step(self, step: int) -> None:
        """Hook after the optimiser step (the VQ-VAE restarts dead codes here). Randomness must
        come from torch's global RNG, which checkpoints save, so resume stays bitwise exact."""

    def config(self) -> dict[str, Any]:
        """JSON for the checkpoint's config.json: component, model config (dims), window,
        feature spec, dataset fingerprint, and the VQ-VAE it reads codes from, if any."""


@dataclass(frozen=True)
class ControlCommand:
    desired: str = "run"  # "run" | "pause" | "cancel"
    throttle: float = 0.0  # fraction of each step to spend sleeping, 0 <= throttle < 1


class Control(Protocol):
    """Polled by the loop between steps (at most every few hundred ms; cheap to call)."""

    def poll(self, step: int) -> ControlCommand:
        ...


class NoControl:
    def poll(self, step: int) -> ControlCommand:
        return ControlCommand()


class TrainSetupError(ValueError):
    """The job cannot start: bad data, unknown component, a run dir that holds another job, or a
    configuration the memory budget cannot fit. The message names the parameter or path."""
