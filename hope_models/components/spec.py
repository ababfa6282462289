"""What the house asks of a component, declared once in its folder's __init__.py.

The trainer, the gate, BrainService, the inbox, the registry, the daemon, the webapp and the CLI
read a component through its ComponentSpec (the table is hope_models/components/__init__.py):
whether it reads a VQ-VAE's codes, its window, how its configuration follows from a dataset's
feature spec, its layers (the memory estimate), which episodes it cannot train on, its held-out
figures and the gate's baselines. Torch-free: the service processes import it. What needs torch
(the model, its loss) is in the folder's model.py and train.py, imported by `torch_module` only
inside a job's child process.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Callable

READS_VQVAE = ("never", "optional", "required")


@dataclass(frozen=True)
class EpisodeFacts:
    """What an episode offers a component (intake/trainable.py reads them off the episode)."""
    steps: int
    duration_s: float
    clocked: bool  # every step has a timestamp_ns (windows are placed in time)
    missing: str  # why it has no feature spec ("" when it has a numeric observation)
    has_frame: bool
    has_obs: bool
    frame_note: str  # why its frames are not usable, "" if they are or there are none
    no_action: str = ""  # why it has no numeric action ("" when it has one): only the tokenizer trains without


# The fewest points a window has on the clock (the Fast Loop's K over 100 ms): an episode with fewer
# steps trains neither loop.
MIN_WINDOW_POINTS = 5


def on_a_clock(facts: EpisodeFacts) -> str | None:
    """Why an episode cannot train a loop, whose windows are placed in time: no feature spec, steps
    without a timestamp, or fewer steps than a window's points; None if it can."""
    if facts.missing or facts.no_action:
        return "; ".join(r for r in (facts.missing, facts.no_action) if r)
    if not facts.clocked:
        return "steps without a clock (timestamp_ns): windows are placed in time"
    if facts.steps < MIN_WINDOW_POINTS:
        return f"{facts.steps} steps; its window needs {MIN_WINDOW_POINTS}"
    return None


def _no_held_out(val: dict[str, Any]) -> dict[str, Any] | None:
    return None


def _no_line(held_out: dict[str, Any]) -> str | None:
    return None


@dataclass(frozen=True)
class ComponentSpec:
    name: str
    package: str  # the folder's module path: <package>.train builds it (torch), <package>.numpy_form serves it
    config_class: type  # its torch-free config dataclass
    window_scale: str  # "fast" | "mid" (data/windows.py)
    window_defaults: dict[str, Any]  # window_spec() keyword arguments
    check_window: Callable[[Any], None]  # a WindowSpec it cannot train on -> ValueError naming model_config.window
    configure: Callable[..., Any]  # (feature_spec, window, overrides, vq_cfg) -> its validated config
    layers: Callable[[Any, Any], list]  # (cfg, vq_cfg) -> components.layers.Layer list, the model's own order
    # (facts, why the tokenizer cannot train on it or None) -> why it cannot, or None
    cannot_train: Callable[[EpisodeFacts, str | None], str | None]
    reads_vqvae: str = "never"  # one of READS_VQVAE: a frozen VQ-VAE's codes as inputs
    tokenizer: bool = False  # its codes are what a reads_vqvae component reads (one component is)
    acts: bool = False  # it outputs the robot's action (reflex rollouts; the app's action figures)
    predicts: bool = False  # it predicts codes ahead (imagination, surprise)
    held_out: Callable[[dict[str, Any]], dict[str, Any] | None] = _no_held_out  # result.json summary.val -> figures
    held_out_line: Callable[[dict[str, Any]], str | None] = _no_line  # those figures in one report line
    # (validation figures, candidate, settings) -> (status, detail) of the gate's "baselines" check, or
    # None when it has no baselines to beat
    baselines: Callable[..., tuple[str, str]] | None = None
    # model_config values a stored checkpoint made before the field existed was trained with (where
    # the field's default for a new run differs): filled in when the checkpoint is loaded
    stored_defaults: dict[str, Any] = field(default_factory=dict)

    def stored_config(self, model_config: dict[str, Any]) -> dict[str, Any]:
        """A stored checkpoint's model_config with the fields it predates filled in (stored_defaults)."""
        return {**self.stored_defaults, **model_config}

    def __post_init__(self) -> None:
        if self.reads_vqvae not in READS_VQVAE:
            raise ValueError(f"component {self.name}: reads_vqvae={self.reads_vqvae!r} is not one of {READS_VQVAE}")
        if self.tokenizer and self.reads_codes:
            raise ValueError(f"component {self.name}: the tokenizer reads no other VQ-VAE")

    @property
    def reads_codes(self) -> bool:
        """Whether it reads a frozen VQ-VAE's codes at all (optionally or necessarily)."""
        return self.reads_vqvae != "never"

    def part(self, name: str) -> ModuleType:
        """A module of the component's folder by name: "train" (its loss and build(); imports torch,
        so only a job's child asks for it), "numpy_form" (its serving form). The table stays
        torch-free because nothing imports these until asked."""
        return importlib.import_module(f"{self.package}.{name}")
