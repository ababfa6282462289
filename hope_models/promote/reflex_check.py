"""The gate's reflex check: a sim-reacher fast_loop run in closed loop on held-out seeds against
the promoted one, before serving (gate.py) or after it (reflex_verdict, registry/gating.py)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hope_models.components import ACTOR
from hope_models.promote.checks import (
    FAILED,
    PASSED,
    SKIPPED,
    Gate,
    GateError,
    GateResult,
    load_component,
    resolve_candidate,
    use_threads,
)
from hope_models.promote.reflex_policy import SIM_ACTION, SIM_OBSERVATION, ReflexPolicy, ReflexPolicyError, check_spec
from hope_models.sim.evaluate import evaluate_policy
from hope_models.sim.reacher import ROBOT_MODEL, TASKS

# The first episodes' metadata read to decide the sim task (metadata.environment_id).
_TASK_PROBE_EPISODES = 3


def sim_task(cache) -> str | None:
    """The reacher task ("reach", "track") the dataset was recorded on, from its episodes'
    metadata (robot_model dmc-reacher, environment_id dm_control/reacher-<task>); None if not sim."""
    for ep in cache.episodes[:_TASK_PROBE_EPISODES]:
        src = Path(str(ep.get("source", "")))
        meta_file = src / "metadata.json" if src.is_dir() else src.parent / "metadata.json"
        try:
            meta = json.loads(meta_file.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if not isinstance(meta, dict) or meta.get("robot_model") != ROBOT_MODEL:
            continue
        env_id = str(meta.get("environment_id", ""))
        task = env_id.rsplit("-", 1)[-1] if env_id.startswith("dm_control/reacher-") else None
        if task in TASKS:
            return task
    return None


def reflex_verdict(candidate_ckpt: str | Path, promoted_ckpt: str | Path | None, *, settings: Any,
                   task: str, threads: int | None = None) -> GateResult:
    """The deferred reflex check of a served candidate against the model it replaced (None: none
    to compare with, the candidate's return is only measured); GateError when the candidate cannot be read.
    threads: torch's thread count for the check (None: as it is)."""
    use_threads(threads)
    gate = Gate(settings)
    cand_dir = resolve_candidate(candidate_ckpt)
    cand = load_component(cand_dir)
    metrics: dict[str, Any] = {"reflex": None}
    prom = prom_dir = None
    prom_problem = "nothing was promoted before it"
    if promoted_ckpt is not None:
        try:
            prom_dir = resolve_candidate(promoted_ckpt)
            prom = load_component(prom_dir)
        except GateError as exc:
            prom_problem = f"the model it replaced cannot be loaded: {exc}"
    if has_reflex(gate, cand, cand_dir):
        reflex_check(gate, metrics, cand, cand_dir, prom, prom_dir, prom_problem, task if task in TASKS else "reach")
    return gate.result(metrics)


def has_reflex(gate: Gate, cand, cand_dir: Path) -> bool:
    """Whether the reflex check applies: a fast_loop trained on the sim reacher's observation that
    reads no camera (a camera one is recorded as not measured)."""
    if cand.name != ACTOR:
        return False
    try:
        check_spec(cand.spec, str(cand_dir), SIM_OBSERVATION, SIM_ACTION)
    except ReflexPolicyError:
        return False  # not trained on the sim reacher: no reflex to check
    if cand.wants_frames:
        gate.record("reflex", SKIPPED, "reflex: not measured: this fast_loop reads camera frames")
        return False
    return True


def reflex_check(gate: Gate, metrics: dict[str, Any], cand, cand_dir: Path, prom, prom_dir, prom_problem, task: str):
    settings = gate.settings
    n = int(settings.gate_reflex_episodes)
    tol = float(settings.gate_reflex_tolerance)
    seeds = list(range(n))
    reflex: dict[str, Any] = {"task": task, "seeds": [seeds[0], seeds[-1]], "episodes": n, "tolerance": tol,
                              "candidate_mean_return": None, "promoted_mean_return": None}
    metrics["reflex"] = reflex
    try:
        res = evaluate_policy(ReflexPolicy.from_checkpoint(cand_dir), seeds, task)
    except (ReflexPolicyError, ValueError) as exc:
        gate.record("reflex", FAILED, f"reflex: the candidate cannot run the {task} task: {exc}")
        return
    reflex["candidate_mean_return"] = res.mean_return
    reflex["candidate_success_rate"] = res.success_rate
    where = f"{task}, seeds {seeds[0]}-{seeds[-1]}"
    if prom is None:
        gate.record("reflex", SKIPPED, f"reflex: mean return {res.mean_return:.1f} ({where}); not compared: "
                                       f"{prom_problem}")
        return
    try:
        p_res = evaluate_policy(ReflexPolicy.from_checkpoint(prom_dir), seeds, task)
    except (ReflexPolicyError, ValueError) as exc:
        gate.record("reflex", SKIPPED, f"reflex: not compared: the promoted model cannot run the {task} task: {exc}")
        return
    reflex["promoted_mean_return"] = p_res.mean_return
    reflex["promoted_success_rate"] = p_res.success_rate
    text = (f"reflex mean return {res.mean_return:.1f} vs the promoted model's {p_res.mean_return:.1f} ({where}, "
            f"tolerance {tol:g})")
    if res.mean_return < p_res.mean_return - tol:
        gate.record("reflex", FAILED, f"{text}: worse by more than the tolerance")
    else:
        gate.record("reflex", PASSED, text)


__all__ = ["reflex_check", "has_reflex", "reflex_verdict", "sim_task"]
