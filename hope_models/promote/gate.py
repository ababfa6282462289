"""The promotion gate: may this candidate checkpoint replace the promoted one of its component?

    result = gate_candidate("runs/r2/checkpoints/00002000", "runs/r1/checkpoints/00002000",
                            data=None, settings=settings)
    result.passed, result.reasons, result.metrics

Checks, in order (the later ones only when the earlier ones could run):
1. finite: every floating tensor of model.safetensors is finite (a NaN anywhere refuses).
2. val_loss: the candidate's validation loss on its own run's validation split (the same episodes
   and batches the trainer reported: hope_models/train/validation.py), against the promoted
   model's loss on that SAME split and batches; refused when candidate > promoted x (1 +
   gate_val_tolerance). Skipped, with the reason, when nothing is promoted, when the promoted
   model cannot read this data (other component, fields, frame or window: "does not fit"), or when
   the data has no validation split.
3. baselines: a vqvae or mid_loop must beat its trivial baselines on the same held-out batches
   (hope_models/promote/baselines.py: the tokenizer's variance kept, the predictor against copy-last
   and code frequencies), with every figure in the verdict.
4. reflex: a fast_loop trained on the sim reacher (its feature spec reads the reacher's observation
   and writes its action) is run in closed loop on gate_reflex_episodes held-out seeds (0..N-1;
   demos are recorded from seed 100000 up), and so is the promoted one; refused when the
   candidate's mean return is below the promoted one's minus gate_reflex_tolerance. With
   reflex_after_serving (settings.gate_reflex_after_serving, the default for promotions) the
   check is recorded as deferred and run by reflex_verdict() once the candidate is served;
   registry/gating.py rolls it back when it fails.

The dataset (train_source): the promotion's own when it has one (`promote RUN` passes the run's
from the registry), else the one the candidate's config.json names, with its cache dir and spec
override. config.json is untrusted input: those paths are followed only inside the data roots
($HOPE_HOME and settings.data_roots, the rule POST /api/runs applies), and a value of the wrong
type or out of range is a failed val_loss check naming the field and the file, before anything is
read or created.

Each model sees the data normalised with its own feature spec's statistics (what it was trained
with; the anchors do not depend on it). When the two specs' statistics differ, the losses are in
each model's own normalised units and a note says so; likewise when two mid_loops predict the codes
of different frozen VQ-VAEs.

`passed` is True only if no check failed. `reasons` holds the failures when refused, otherwise the
notes about skipped checks; `checks` has every check with its status and detail. Needs torch; it
runs in its own process (`run_trainer.py promote`), never in the daemon or the webapp.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.checkpoint_format import CONFIG_FILE
from hope_models.data.features import FeatureSpecError
from hope_models.paths import PathError, confine_path, data_roots
from hope_models.promote.baselines import baselines_check
from hope_models.promote.checks import (
    DEFERRED,
    FAILED,
    PASSED,
    SKIPPED,
    Gate,
    GateError,
    GateResult,
    load_component,
    non_finite_tensors,
    read_config,
    resolve_candidate,
    use_threads,
)
from hope_models.promote.reflex_check import has_reflex, reflex_check, reflex_verdict, sim_task
from hope_models.train.contract import TrainSetupError
from hope_models.train.dataset_dir import dataset_dir_for
from hope_models.train.validation import NoValidationSplit, ValidationSetup, validation_metrics

# -- data ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TrainSource:
    """What the val_loss check reads: the dataset, the cache root it is compiled under, the
    feature spec override (None: inferred, as the trainer does without one)."""
    data: str
    cache_root: Path
    spec_path: Path | None


def train_source(cand_cfg: dict[str, Any], where: Path, data: str | Path | None, settings: Any) -> TrainSource | None:
    """The candidate's training data. With `data` (the promotion's own dataset: `promote RUN`
    passes the run's, from the registry), config.json's paths are not followed at all: the cache
    is compiled under settings.cache_dir with the inferred spec, as a run the worker trained.
    Otherwise train.data, train.cache_dir and train.spec_path come from config.json, which is
    untrusted (anyone who can write a checkpoint dir under a data root can ask for its promotion):
    each must lie inside the data roots (hope_models/paths.py, the rule POST /api/runs applies),
    because the gate reads the spec, walks the dataset and creates the cache dir. ValueError names
    the field and the file; None when config.json names no dataset."""
    if data is not None:
        return TrainSource(str(data), Path(settings.cache_dir), None)
    train = cand_cfg.get("train", {})
    if not isinstance(train, dict):
        raise ValueError(f"{where}: 'train' must be an object, got {type(train).__name__}")
    roots = data_roots(settings)

    def confined(name: str, must_exist: bool) -> Path | None:
        value = train.get(name)
        if value is None:
            return None
        try:
            return confine_path(f"train.{name}", value, allowed_roots=roots, must_exist=must_exist)
        except PathError as exc:
            raise ValueError(f"{where}: {exc}") from None

    # all three checked before anything is read or created
    dataset, cache_root, spec_path = confined("data", True), confined("cache_dir", False), confined("spec_path", True)
    if dataset is None:
        return None
    return TrainSource(str(dataset), cache_root or Path(settings.cache_dir), spec_path)


def _open_data(source: TrainSource):
    """The candidate run's dataset cache (built like the trainer builds it); ValueError with the reason."""
    from hope_models.data.cache import CacheError, load_or_build  # lazy: loads mcap

    data, cache_root = source.data, source.cache_root
    try:
        data_dir = dataset_dir_for(data, cache_root)
        cache, _info = load_or_build(data_dir, cache_root, None if source.spec_path is None else str(source.spec_path))
    except (TrainSetupError, CacheError, FeatureSpecError) as exc:
        raise ValueError(str(exc)) from None
    except OSError as exc:
        raise ValueError(f"{exc.filename or data}: {exc.strerror or exc}") from None
    return cache


def _fields(group) -> list[tuple[str, int]]:
    return [(f.path, f.size) for f in group.fields]


def fit_problem(component, cache_spec, candidate) -> str | None:
    """Why `component` cannot be scored on the candidate's batches of this data (None: it can)."""
    spec = component.spec
    if component.name != candidate.name:
        return f"it is a {component.name}, the candidate a {candidate.name}"
    if _fields(spec.observation) != _fields(cache_spec.observation):
        return f"it reads observation {_fields(spec.observation)}, the data has {_fields(cache_spec.observation)}"
    if _fields(spec.action) != _fields(cache_spec.action):
        return f"its action is {_fields(spec.action)}, the data's is {_fields(cache_spec.action)}"
    frame = None if spec.frame is None else spec.frame.to_json_obj()
    data_frame = None if cache_spec.frame is None else cache_spec.frame.to_json_obj()
    if component.wants_frames and frame != data_frame:
        return f"it reads frames {frame}, the data has {data_frame}"
    if component.window.to_json_obj() != candidate.window.to_json_obj():
        return f"its window is {component.window.to_json_obj()}, the candidate's {candidate.window.to_json_obj()}"
    return None


def normalised_view(cache, spec):
    """The same cache read with another spec's normalisation statistics (a shallow copy: the
    mapped arrays are shared; only the two per-column vectors make_windows applies differ)."""
    view = copy.copy(cache)
    obs_mean, obs_std, act_mean, act_std = spec.normalizer()
    view.spec = spec
    view.x_inv_std = (1.0 / np.concatenate([obs_std, act_std])).astype(np.float32)
    view.x_shift = (np.concatenate([obs_mean, act_mean]) * view.x_inv_std).astype(np.float32)
    return view


def _same_stats(a, b) -> bool:
    return a.to_json_obj(with_notes=False) == b.to_json_obj(with_notes=False)


def _vqvae_weights(component) -> str | None:
    ref = getattr(component, "vqvae_ref", None)
    return ref.get("weights_sha256") if isinstance(ref, dict) else None


# -- the gate -------------------------------------------------------------------------------------

def gate_candidate(candidate_ckpt: str | Path, promoted_ckpt: str | Path | None, *, data: str | Path | None = None,
                   settings: Any, reflex_after_serving: bool = False, threads: int | None = None) -> GateResult:
    """Run the checks of the module doc. `data` is the promotion's own dataset, which replaces
    what the candidate's config.json names (train_source). Raises GateError only when the
    candidate itself cannot be read; every other problem is a failed or skipped check in the result.
    reflex_after_serving: the reflex check is not run here but recorded as deferred, its task in
    metrics["reflex"]; the caller serves the candidate, then runs reflex_verdict(). threads: torch's
    thread count for the gate (None: as it is)."""
    use_threads(threads)
    gate = Gate(settings)
    cand_dir = resolve_candidate(candidate_ckpt)
    cand_cfg = read_config(cand_dir)
    metrics: dict[str, Any] = {"candidate": str(cand_dir), "promoted": None, "candidate_val_loss": None,
                               "promoted_val_loss": None, "ratio": None,
                               "val_tolerance": float(settings.gate_val_tolerance), "finite": None, "reflex": None}

    # 1. finite weights
    bad = non_finite_tensors(cand_dir)
    metrics["finite"] = not bad
    if bad:
        gate.record("finite", FAILED, f"non-finite weights (NaN or Inf) in {len(bad)} tensor(s): "
                                      f"{', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}")
        for check in ("val_loss", "reflex"):
            gate.record(check, SKIPPED, f"{check}: not measured (the weights are not finite)")
        return gate.result(metrics)
    gate.record("finite", PASSED, "every weight is finite")
    cand = load_component(cand_dir)

    prom = prom_dir = prom_problem = None
    if promoted_ckpt is not None:
        metrics["promoted"] = str(promoted_ckpt)
        try:
            prom_dir = resolve_candidate(promoted_ckpt)
            prom = load_component(prom_dir)
        except GateError as exc:
            prom_problem = f"the promoted model cannot be loaded: {exc}"
    else:
        prom_problem = "nothing promoted yet to compare with"

    # 2. validation loss on the candidate's split, 3. the sim reflex (fast_loop on reacher data)
    cache = _val_check(gate, metrics, cand, cand_dir, prom, prom_problem, cand_cfg, data)
    if not has_reflex(gate, cand, cand_dir):
        return gate.result(metrics)
    task = (sim_task(cache) if cache is not None else None) or "reach"
    if reflex_after_serving:
        n = int(settings.gate_reflex_episodes)
        metrics["reflex"] = {"task": task, "after_serving": True, "episodes": n}
        gate.record("reflex", DEFERRED, f"reflex: checked after serving ({task}, seeds 0-{n - 1}); rolled back "
                                        f"when worse than the promoted model's by more than "
                                        f"{float(settings.gate_reflex_tolerance):g}")
        return gate.result(metrics)
    reflex_check(gate, metrics, cand, cand_dir, prom, prom_dir, prom_problem, task)
    return gate.result(metrics)


def _val_check(gate: Gate, metrics: dict[str, Any], cand, cand_dir: Path, prom, prom_problem: str | None,
               cand_cfg: dict[str, Any], data: str | Path | None):
    """The val_loss check; returns the candidate's dataset cache (None when it cannot be opened)."""
    tol = float(gate.settings.gate_val_tolerance)
    where = cand_dir / CONFIG_FILE
    try:
        source = train_source(cand_cfg, where, data, gate.settings)
        train_cfg = cand_cfg.get("train") or {"batch_size": 64}
        if not isinstance(train_cfg, dict):
            raise ValueError(f"{where}: 'train' must be an object, got {type(train_cfg).__name__}")
        setup = ValidationSetup.from_train_config(train_cfg, where=f"{where}: train")
    except ValueError as exc:
        gate.record("val_loss", FAILED, f"the validation loss was not measured: {exc}")
        return None
    if source is None:
        gate.record("val_loss", FAILED, f"{where} names no training data ('train'.'data'); "
                                        "the validation loss cannot be measured (pass data=)")
        return None
    data = source.data
    try:
        cache = _open_data(source)
    except ValueError as exc:
        gate.record("val_loss", FAILED, f"cannot measure the validation loss on {data}: {exc}")
        return None
    problem = fit_problem(cand, cache.spec, cand)
    if problem is not None:
        gate.record("val_loss", FAILED, f"the candidate cannot be scored on {data} any more: {problem}")
        return cache
    metrics["val_batches"], metrics["val_data"] = setup.batches, data
    try:
        cand_val = validation_metrics(cand, normalised_view(cache, cand.spec), setup)
    except NoValidationSplit as exc:
        gate.record("val_loss", SKIPPED, f"val_loss: not compared: {data} has no validation split ({exc})")
        baselines_check(gate, metrics, cand, None)
        return cache
    metrics["candidate_val"] = cand_val
    baselines_check(gate, metrics, cand, cand_val)
    c_loss = metrics["candidate_val_loss"] = cand_val.get("loss")
    if c_loss is None or not math.isfinite(c_loss):
        gate.record("val_loss", FAILED, f"the candidate's validation loss is {c_loss}")
        return cache
    if prom is None:
        gate.record("val_loss", SKIPPED, f"val_loss: {c_loss:.6g}; not compared: {prom_problem}")
        return cache
    problem = fit_problem(prom, cache.spec, cand)
    if problem is not None:
        gate.record("val_loss", SKIPPED,
                    f"val_loss: not compared: the promoted model does not fit this data: {problem}")
        return cache
    if not _same_stats(prom.spec, cand.spec):
        gate.notes.append("the promoted model normalises with other statistics than the candidate; each loss is "
                          "in its own model's normalised units")
    if _vqvae_weights(prom) != _vqvae_weights(cand):
        gate.notes.append("the two models read codes of different frozen VQ-VAEs; for a mid_loop each loss is "
                          "measured against its own VQ-VAE's codes")
    p_val = validation_metrics(prom, normalised_view(cache, prom.spec), setup, anchors_from=cand)
    metrics["promoted_val"] = p_val
    p_loss = metrics["promoted_val_loss"] = p_val.get("loss")
    if p_loss is None or not math.isfinite(p_loss):
        gate.record("val_loss", SKIPPED, f"val_loss: not compared: the promoted model's loss is {p_loss}")
        return cache
    ratio = c_loss / p_loss if p_loss > 0 else (1.0 if c_loss <= 0 else math.inf)
    metrics["ratio"] = ratio
    text = (f"validation loss {c_loss:.6g} vs the promoted model's {p_loss:.6g} on the same {setup.batches} "
            f"batches (ratio {ratio:.4g}, limit {1.0 + tol:.4g})")
    if c_loss > p_loss * (1.0 + tol) + 1e-12:
        gate.record("val_loss", FAILED, f"{text}: worse by more than {tol:.0%}")
    else:
        gate.record("val_loss", PASSED, text)
    return cache


__all__ = ["GateResult", "GateError", "TrainSource", "gate_candidate", "reflex_verdict", "resolve_candidate", "non_finite_tensors",
           "fit_problem", "normalised_view", "sim_task", "train_source"]
