"""The end-to-end demo's figures and its summary table (`hope-trainer demo`, hope_trainer/demo/session.py).

Everything here reads what the services already recorded, so the demo prints what a user could
check by hand: the registry (runs, their events, the models table) and each run's
`result.json` (written by the training loop: first and final loss, peak RSS, elapsed time).
Torch-free, and no I/O beyond those reads, so tests can feed it plain dicts.

    figures = component_figures(run_obj, gate)      # one row of the table
    text = format_summary(summary)                  # the table and the lines under it
    problems = verdict(summary, target_return=900)  # [] when the demo did what it promises
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hope_models.components import COMPONENTS
from hope_models.components.verdict import fmt

AUTO_PROMOTE_SOURCE = "auto-promote"
GATING_PREFIX = "auto-promote: gating"


def read_result(run_dir: str | Path) -> dict[str, Any] | None:
    """The training loop's result.json of a run dir, or None (not finished, unreadable)."""
    try:
        obj = json.loads((Path(run_dir) / "result.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def gate_outcome(session: Any, run_id: str) -> dict[str, Any] | None:
    """What auto-promotion did with a completed run, or None while it has not finished.

    {"state": "promoted", "version", "model_id"} | {"state": "refused", "version", "model_id",
    "reasons"} | {"state": "error", "message"} (the promote child could not gate, or skipped it)."""
    from sqlalchemy import select  # lazy: loads sqlalchemy

    from registry import runs  # lazy: loads sqlalchemy
    from registry.models import Model  # lazy: loads sqlalchemy

    model = session.scalars(select(Model).where(Model.run_id == run_id).order_by(Model.id.desc())).first()
    if model is not None:
        gate = model.gate_result or {}
        if model.promoted_at is not None or model.demoted_at is not None:
            return {"state": "promoted", "version": model.version, "model_id": model.id,
                    "notes": list(gate.get("reasons") or [])}
        return {"state": "refused", "version": model.version, "model_id": model.id,
                "reasons": list(gate.get("reasons") or [])}
    # No row: the child may still run, or it ended without recording (skipped, could not gate).
    for event in reversed(runs.run_events(session, run_id, kinds=("log",))):
        payload = event.payload or {}
        if payload.get("source") != AUTO_PROMOTE_SOURCE:
            continue
        message = str(payload.get("message", ""))
        if message.startswith(GATING_PREFIX):
            return None  # the newest word is "gating": still running
        return {"state": "error", "message": message}
    return None


def component_figures(run: dict[str, Any], gate: dict[str, Any] | None) -> dict[str, Any]:
    """One row: a run's JSON object (Run.to_json_obj) plus its result.json and gate outcome."""
    result = read_result(run["run_dir"]) or {}
    return {
        "component": run["component"],
        "run_id": run["id"],
        "state": run["state"],
        "steps": run["step"],
        "total_steps": run["total_steps"],
        "first_loss": result.get("first_loss"),
        "final_loss": result.get("final_loss"),
        "peak_rss_mb": result.get("peak_rss_mb"),
        "train_s": result.get("elapsed_s"),
        "error": run.get("error"),
        "gate": gate,
        "loop_closure_s": run.get("loop_closure_s"),
        "held_out": held_out(run["component"], result),
    }


def held_out(component: str, result: dict[str, Any]) -> dict[str, Any] | None:
    """The validation figures a component is judged by (result.json summary.val), as its spec
    selects them (the VQ-VAE's reconstruction and codebook, the Mid Loop's per-horizon figures
    against its baselines; None for one without)."""
    summary = result.get("summary")
    val = summary.get("val") if isinstance(summary, dict) else None
    if not isinstance(val, dict) or component not in COMPONENTS:
        return None
    return COMPONENTS[component].held_out(val)


def held_out_lines(rows: list[dict[str, Any]]) -> list[str]:
    lines = []
    for r in rows:
        h = r.get("held_out")
        spec = COMPONENTS.get(r["component"])
        if not h or spec is None:
            continue
        line = spec.held_out_line(h)
        if line:
            psnr = h.get("psnr_db")  # a frame tokenizer's: the line speaks of the variance only
            lines.append(line + (f", PSNR {fmt(psnr, '.1f')} dB" if isinstance(psnr, (int, float)) else ""))
    return lines


def split_range(total: int, parts: int) -> list[tuple[int, int]]:
    """`total` items cut into at most `parts` consecutive runs as even as can be: (first, count) each."""
    parts = max(1, min(parts, total))
    return [(i * total // parts, (i + 1) * total // parts - i * total // parts) for i in range(parts)]


EVAL_KEEP = ("mean_return", "success_rate", "time_to_reach_s", "expert_mean_return", "random_mean_return",
             "episodes", "seeds", "version", "checkpoint", "elapsed_s")


def merge_evaluations(results: list[dict[str, Any]]) -> dict[str, Any]:
    """eval-reflex results over consecutive seed ranges (in order) as one over all of them: the means
    weighted by each range's episodes, time to reach by the episodes that reached, the seeds end to
    end; one result is kept as it is."""
    if len(results) == 1:
        return {k: results[0].get(k) for k in EVAL_KEEP}
    versions = {r.get("version") for r in results}
    if len(versions) > 1:
        return {"error": f"the evaluations ran different checkpoints: {', '.join(sorted(map(str, versions)))}"}
    n = sum(r["episodes"] for r in results)

    def mean(key: str, weight: str = "episodes") -> float | None:
        pairs = [(r.get(key), r.get(weight) or 0) for r in results]
        total = sum(w for v, w in pairs if isinstance(v, (int, float)))
        return sum(v * w for v, w in pairs if isinstance(v, (int, float))) / total if total else None

    return {"mean_return": mean("mean_return"), "success_rate": mean("success_rate"),
            "time_to_reach_s": mean("time_to_reach_s", "reached"), "expert_mean_return": mean("expert_mean_return"),
            "random_mean_return": mean("random_mean_return"), "episodes": n,
            "seeds": [results[0]["seeds"][0], results[-1]["seeds"][-1]], "version": results[0].get("version"),
            "checkpoint": results[0].get("checkpoint"), "elapsed_s": max(r.get("elapsed_s") or 0 for r in results),
            "processes": len(results)}


def _gate_text(gate: dict[str, Any] | None) -> str:
    if gate is None:
        return "not gated"
    if gate["state"] == "promoted":
        return f"promoted {gate.get('version')}"
    if gate["state"] == "refused":
        return "refused by the gate"
    return "gate error"


def format_summary(summary: dict[str, Any]) -> str:
    """The table (per component: steps, loss first -> last, peak RSS, time, gate) and the lines
    under it: inference through the API, the reflex against the expert and random, the loop closure."""
    rows = summary.get("components") or []
    lines = ["", "Summary", "",
             f"{'component':<10} {'steps':>11}  {'loss first -> last':<21} {'peak RSS':>9} {'time':>7}  gate",
             "-" * 96]
    for r in rows:
        steps = f"{r['steps']}/{r['total_steps']}"
        loss = f"{fmt(r['first_loss'], '.4g')} -> {fmt(r['final_loss'], '.4g')}"
        rss = f"{fmt(r['peak_rss_mb'], '.0f')} MB" if r.get("peak_rss_mb") is not None else "-"
        took = f"{fmt(r['train_s'], '.0f')} s" if r.get("train_s") is not None else "-"
        state = "" if r["state"] == "completed" else f"  [{r['state']}]"
        lines.append(f"{r['component']:<10} {steps:>11}  {loss:<21} {rss:>9} {took:>7}  {_gate_text(r['gate'])}{state}")
    lines.append("")
    lines.extend(held_out_lines(rows))
    inference = summary.get("inference")
    if inference and inference.get("action") is not None:
        action = ", ".join(f"{a:+.3f}" for a in inference["action"])
        expert = inference.get("expert_action")
        lines.append(f"inference (POST /api/brain/infer): action [{action}]"
                     + (f" (the expert: [{', '.join(f'{a:+.3f}' for a in expert)}])" if expert else "")
                     + f", {inference.get('model_version')}, {fmt(inference.get('latency_ms'), '.2f')} ms")
    brain = summary.get("brain")
    if brain and brain.get("error"):
        lines.append(f"whole brain: {brain['error']}")
    elif brain:
        lines.append(f"whole brain (session ticked through {brain.get('ticks')} steps of a demonstration): action "
                     f"[{', '.join(fmt(a, '+.3f') for a in brain.get('action') or [])}], versions {brain.get('versions')}")
        lines.extend(_whole_brain_lines(brain))
    elif inference and inference.get("error"):
        lines.append(f"inference: {inference['error']}")
    reflex = summary.get("reflex")
    if reflex and reflex.get("mean_return") is not None:
        seeds = reflex.get("seeds") or ["?", "?"]
        lines.append(f"reflex (reach, held-out seeds {seeds[0]}-{seeds[-1]}): mean return "
                     f"{fmt(reflex['mean_return'], '.1f')}, success {fmt(100 * reflex['success_rate'], '.0f')} %"
                     f"  | expert {fmt(reflex.get('expert_mean_return'), '.1f')}"
                     f"  | random {fmt(reflex.get('random_mean_return'), '.1f')}"
                     f"  (target >= {fmt(summary.get('target_return'), 'g')})")
    elif reflex:
        lines.append(f"reflex: {reflex.get('error')}")
    closure = summary.get("loop_closure_s")
    lines.append("loop closure: " + (f"{closure:.1f} s from the fast_loop run finishing to its first served "
                                     "inference (gate + load)" if isinstance(closure, (int, float))
                                     else "not measured"))
    timings = summary.get("timings") or {}
    if timings:
        lines.append("time: " + ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()))
    return "\n".join(lines)


def _whole_brain_lines(inference: dict[str, Any]) -> list[str]:
    """The answer's code, prediction and surprise (BrainService serving all three components)."""
    out = []
    if inference.get("code") is not None:
        out.append(f"  code {inference['code']}")
    pred = inference.get("prediction")
    if isinstance(pred, dict):
        for label, obs in pred.items():
            out.append(f"  prediction at +{label}: [{', '.join(fmt(v, '+.3f') for v in obs)}]")
    if "surprise" in inference:
        value = inference.get("surprise")
        out.append("  surprise: none yet (no prediction made one horizon ago in this session)" if value is None
                   else f"  surprise {fmt(value, '.2f')} nats")
    return out


def verdict(summary: dict[str, Any], target_return: float) -> list[str]:
    """What the demo promised and did not do; [] when all is well."""
    problems = []
    for r in summary.get("components") or []:
        if r["state"] != "completed":
            problems.append(f"{r['component']} run {r['run_id']} ended {r['state']}"
                            + (f": {r['error']}" if r.get("error") else ""))
    for r in summary.get("components") or []:
        # every member must earn its place: the gate checks the vqvae's and mid_loop's baselines too
        if r["state"] != "completed":
            continue
        gate, name = r.get("gate"), r["component"]
        if gate is None:
            problems.append(f"the {name} run was not gated (auto-promotion did not finish)")
        elif gate["state"] == "refused":
            problems.append(f"the gate refused the {name}: {'; '.join(gate.get('reasons') or [])}")
        elif gate["state"] == "error":
            problems.append(f"auto-promotion of the {name} failed: {gate.get('message')}")
    inference = summary.get("inference") or {}
    if inference.get("error"):
        problems.append(f"inference through the API failed: {inference['error']}")
    brain = summary.get("brain") or {}
    if brain.get("error"):
        problems.append(f"the whole-brain inference failed: {brain['error']}")
    reflex = summary.get("reflex") or {}
    mean = reflex.get("mean_return")
    if reflex.get("error"):
        problems.append(f"the reflex evaluation failed: {reflex['error']}")
    elif not isinstance(mean, (int, float)):
        problems.append("the reflex evaluation did not run")
    elif mean < target_return:
        problems.append(f"the promoted fast_loop's mean return {mean:.1f} is below the target {target_return:g}")
    return problems


__all__ = ["component_figures", "format_summary", "gate_outcome", "merge_evaluations", "read_result", "split_range",
           "verdict"]
