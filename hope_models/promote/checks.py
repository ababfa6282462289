"""What every check of the promotion gate shares: the statuses, the verdict a gate builds check
by check, loading a candidate checkpoint (hope_models/promote/gate.py runs the checks)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hope_models.checkpoint_format import CONFIG_FILE, MODEL_FILE, CheckpointError, read_json_object
from hope_models.checkpoints import load_tensors, resolve_checkpoint_dir
from hope_models.json_finite import finite

PASSED, FAILED, SKIPPED = "passed", "failed", "skipped"
# a check that runs after the candidate is served (the reflex in simulation), which rolls it back
# when it fails: registry/gating.py
DEFERRED = "deferred"


def use_threads(threads: int | None) -> None:
    """torch's thread count for a check (None: as it is)."""
    if threads is not None:
        import torch  # lazy: loads torch

        torch.set_num_threads(threads)


class GateError(ValueError):
    """The candidate cannot be gated at all (not a complete checkpoint, an unreadable config);
    the message names the path. A gate that ran and said no is a GateResult, not this."""


@dataclass
class GateResult:
    passed: bool
    reasons: list[str]
    metrics: dict[str, Any]
    checks: list[dict[str, str]] = field(default_factory=list)

    def to_json_obj(self) -> dict[str, Any]:
        return finite(asdict(self))


class Gate:
    def __init__(self, settings: Any):
        self.settings = settings
        self.checks: list[dict[str, str]] = []
        self.notes: list[str] = []

    def record(self, check: str, status: str, detail: str) -> None:
        self.checks.append({"check": check, "status": status, "detail": detail})

    def result(self, metrics: dict[str, Any]) -> GateResult:
        failed = [c["detail"] for c in self.checks if c["status"] == FAILED]
        skipped = [c["detail"] for c in self.checks if c["status"] in (SKIPPED, DEFERRED)]
        reasons = (failed if failed else skipped) + self.notes
        return GateResult(not failed, reasons, metrics, self.checks)


# -- loading -------------------------------------------------------------------------------------

def read_config(ckpt: Path) -> dict[str, Any]:
    try:
        return read_json_object(ckpt / CONFIG_FILE)
    except FileNotFoundError:
        raise GateError(f"{ckpt / CONFIG_FILE}: not found") from None
    except CheckpointError as exc:
        raise GateError(str(exc)) from None


def resolve_candidate(path: str | Path) -> Path:
    """A complete checkpoint dir from a checkpoint dir or a run dir; GateError otherwise."""
    p = Path(path)
    if not p.exists():
        raise GateError(f"{p}: no such checkpoint or run dir")
    try:
        return resolve_checkpoint_dir(p).resolve()
    except CheckpointError as exc:
        raise GateError(str(exc)) from None


def non_finite_tensors(ckpt: Path) -> list[str]:
    """Names of the floating tensors of model.safetensors holding NaN or Inf (safetensors only)."""
    import torch  # lazy: loads torch


    try:
        tensors = load_tensors(ckpt / MODEL_FILE)
    except CheckpointError as exc:
        raise GateError(str(exc)) from None
    return sorted(name for name, t in tensors.items()
                  if t.is_floating_point() and not bool(torch.isfinite(t).all()))


def load_component(ckpt: Path):
    from hope_models.components.build import component_from_checkpoint  # lazy: loads safetensors, torch

    try:
        return component_from_checkpoint(ckpt)
    except CheckpointError as exc:
        raise GateError(str(exc)) from None
