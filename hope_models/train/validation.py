"""Validation metrics of a component on a dataset's validation split: one function, two users.

The trainer reports them at the end of a completed job (loop._Trainer._validate) and the promotion
gate compares a candidate with the promoted model on them (hope_models/promote/gate.py). Both call
`validation_metrics`, so a gate's "val loss" is the number the run reported, measured on the same
episodes and the same batches:

- the split is by episode (sampler.is_validation_episode: the hash of the episode id against
  val_fraction), so it depends only on the data and val_fraction;
- the batches are AnchorSampler(split="val").batch(0 .. batches-1), a pure function of
  (seed, batch_size, imagined_ratio, val_fraction) and the component's window (its history and
  horizon decide which anchors are eligible);
- the metrics are the mean of component.evaluate() over those batches, with torch's RNG restored
  afterwards and the model back in the mode it was in.

`ValidationSetup.from_train_config` reads those numbers from a TrainConfig, or from the "train"
block a checkpoint's config.json holds, so the gate re-creates a finished run's split exactly.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

from hope_models.numbers import short
from hope_models.train.config import OPTIONS, ConfigValueError, TrainConfig, check_value


class NoValidationSplit(ValueError):
    """The dataset has no anchors in the validation split (too few episodes for val_fraction)."""


@dataclass(frozen=True)
class ValidationSetup:
    batch_size: int
    seed: int = 0
    imagined_ratio: float = 0.0
    val_fraction: float = 0.1
    batches: int = 8  # TrainConfig.val_batches: 512 anchors at batch 64, enough for the gate to decide

    @classmethod
    def from_train_config(cls, cfg: Any, where: str = "the training config") -> "ValidationSetup":
        """From a TrainConfig or a checkpoint's config.json "train" dict (TrainConfig.to_json_obj).
        The dict is untrusted (the gate reads it from a candidate's checkpoint): each value must be
        of its type and within TrainConfig's bounds, else ValueError naming `where` and the field."""
        get = cfg.get if isinstance(cfg, Mapping) else (lambda k, d=None: getattr(cfg, k, d))
        values = {}
        for name in VALIDATION_FIELDS:
            v = get(name, _DEFAULTS.get(name))
            kind = OPTIONS[name].kind
            if isinstance(v, bool) or not isinstance(v, (int, float) if kind == "float" else int):
                raise ValueError(f"{where}: {name}={short(v)} is not {'a number' if kind == 'float' else 'an integer'}")
            try:
                values[name] = check_value(name, v)  # TrainConfig's own bounds (train/config.py)
            except ConfigValueError:
                raise ValueError(f"{where}: {name}={short(v)} is outside {OPTIONS[name].range_text()}") from None
        return cls(batch_size=values["batch_size"], seed=values["seed"], imagined_ratio=values["imagined_ratio"],
                   val_fraction=values["val_fraction"], batches=values["val_batches"])


# The TrainConfig fields validation reads. The bounds are TrainConfig's: far above any real run,
# they keep a hostile config from asking the gate for a batch or a number of batches that would
# take the Pi's memory or days. batch_size has no default: a training config always has one.
VALIDATION_FIELDS = ("batch_size", "seed", "imagined_ratio", "val_fraction", "val_batches")
_DEFAULTS = {f.name: f.default for f in fields(TrainConfig) if f.name in VALIDATION_FIELDS and f.name != "batch_size"}


def anchor_sampler(cache, component, split: str, *, batch_size: int, seed: int, imagined_ratio: float,
                   val_fraction: float):
    """The AnchorSampler the trainer draws `split` ("train", "val", "all") from for this component.
    A component that clones the recorded actions (`clones_actions`, the fast_loop) never draws
    from play episodes: their actions are exploration, not labels."""
    from hope_models.data.sampler import AnchorSampler  # lazy: loads numpy

    win = component.window
    horizon = getattr(component, "horizon_s", max(win.horizons_s, default=0.0))
    return AnchorSampler(cache, batch_size, seed=seed, imagined_ratio=imagined_ratio, split=split,
                         val_fraction=val_fraction, min_history_s=float(getattr(component, "min_history_s", 0.0)),
                         horizon_s=float(horizon), exclude_play=bool(getattr(component, "clones_actions", False)))


def validation_metrics(component, cache, setup: ValidationSetup, *, anchors_from=None) -> dict[str, float]:
    """Mean component.evaluate() metrics over setup.batches validation batches.

    `anchors_from` (default: `component`) is the component whose window picks the anchors: the
    gate passes the candidate's, so a promoted model is scored on exactly the candidate's batches.
    `cache` may be a view of the dataset with another model's normalisation (gate.py); the anchors
    do not depend on it. Raises NoValidationSplit when the split has no anchors.
    """
    import torch  # lazy: loads torch

    from hope_models.data.windows import make_windows  # lazy: loads numpy

    if setup.batches < 1:
        raise ValueError(f"val_batches={setup.batches} must be >= 1")
    try:
        val = anchor_sampler(cache, anchors_from or component, "val", batch_size=setup.batch_size, seed=setup.seed,
                             imagined_ratio=setup.imagined_ratio, val_fraction=setup.val_fraction)
    except ValueError as exc:
        raise NoValidationSplit(str(exc)) from None
    rng = torch.get_rng_state()
    model = component.model
    was_training = model.training
    sums: dict[str, float] = {}
    codes = code_table(component, cache)  # before eval(): it keeps the model's mode as it found it
    model.eval()
    try:
        with torch.no_grad():
            for b in range(setup.batches):
                batch = make_windows(cache, val.batch(b), component.window, frames=bool(component.wants_frames),
                                     codes=codes)
                for k, v in component.evaluate(batch).items():
                    sums[k] = sums.get(k, 0.0) + float(v)
    finally:
        model.train(was_training)
        torch.set_rng_state(rng)
    return {k: v / setup.batches for k, v in sums.items()}


def code_table(component, cache, log=None):
    """The component's precomputed tokenizer codes of `cache` (TrainingComponent.code_table), or
    None: for a component that reads no frames, or one outside hope_models.components (a test's
    stand-in that only keeps train/contract.Component) that has no table to offer."""
    table = getattr(component, "code_table", None)
    return None if table is None else table(cache, log)


__all__ = ["ValidationSetup", "NoValidationSplit", "anchor_sampler", "code_table", "validation_metrics"]
