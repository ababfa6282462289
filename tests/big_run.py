"""A completed run with many metric records, for the run page's tests (API and browser).

    make_big_run(home_path, steps=100_000, run_id=None, component="vqvae", validation=None,
                 config=None) -> run id

writes $HOPE_HOME/runs/<id>/ with metrics.jsonl (one record per step, the format MetricsLog
writes: loss, lr, grad_norm, steps_per_s, rss_mb, temp_c, throttle_level, throttle and the
component's own figures: a vqvae's recon_loss, commit_loss, recon_nmse, perplexity, codes_used, or a
mid_loop's nll / copy-last / code-frequency / observation error per horizon; a noisy decaying loss,
the lr of a warmup + cosine schedule), events (checkpoints, the final state), result.json (its
summary.val = `validation`, the held-out figures), provenance.json and one small
checkpoint dir, the saved metric columns, and puts the run in that home's registry (migrated)
through the registry's own moves: created, dispatched, claimed, finished completed. 100k steps write in about 1 s.
"""
from __future__ import annotations

import json
import math
import os
import random
import time
from datetime import datetime, timezone
from pathlib import Path


def component_metrics(component: str, loss: float, frac: float, rng: random.Random) -> dict:
    """The component's own per-step figures, named as its trainer names them."""
    if component == "mid_loop":  # hope_models/components/mid_loop/metrics.py, per horizon
        out = {}
        for h, k in (("0.5s", 1.0), ("1s", 1.2)):
            out.update({f"nll_{h}": 14.0 * k * (0.8 + 0.2 * loss / 2.8), f"copy_last_nll_{h}": 19.0 * k,
                        f"code_freq_nll_{h}": 19.3 * k, f"accuracy_{h}": 0.6 * frac / k,
                        f"obs_mse_{h}": k * (0.4 + 0.6 * loss / 2.8), f"copy_last_obs_mse_{h}": 0.95 * k})
        return out
    return {"recon_loss": loss * 0.8, "commit_loss": loss * 0.2 * rng.random(), "recon_nmse": 0.02 + loss / 10,
            "perplexity": 40.0 + 20 * frac + rng.gauss(0, 1.0), "codes_used": float(min(64, 10 + int(54 * frac)))}


def _records(steps: int, t0: float, rng: random.Random, component: str):
    warmup = max(1, min(500, steps // 20))
    checkpoint_every = max(1, steps // 5)
    for s in range(1, steps + 1):
        frac = s / steps
        lr = 3e-3 * s / warmup if s <= warmup else 3e-3 * 0.5 * (1 + math.cos(math.pi * (s - warmup) / (steps - warmup)))
        base = 0.08 + 2.4 * math.exp(-6.0 * frac) + 0.3 * math.exp(-60.0 * frac)
        loss = base * math.exp(rng.gauss(0.0, 0.08))
        rec = {"type": "metric", "step": s, "wall_time": round(t0 + s * 0.05, 6), "loss": loss, "lr": lr,
               "grad_norm": abs(rng.gauss(1.0 + 3 * math.exp(-8 * frac), 0.3)),
               "steps_per_s": 20.0 + rng.gauss(0, 0.5), "rss_mb": 310.0 + 20 * frac + rng.random(),
               "temp_c": None, "throttle_level": "none", "throttle": False,
               **component_metrics(component, loss, frac, rng)}
        if component == "mid_loop":  # the Mid Loop's loss is a code nll, in nats
            rec["loss"] = 12.0 + 2.0 * loss
        yield rec
        if s % checkpoint_every == 0:
            yield {"type": "event", "kind": "checkpoint", "wall_time": rec["wall_time"],
                   "payload": {"step": s, "path": f"checkpoints/{s:08d}"}}


def make_big_run(home_path: Path, steps: int = 100_000, run_id: str | None = None, component: str = "vqvae",
                 validation: dict | None = None, config: dict | None = None) -> str:
    from hope_models.settings import load_settings
    from registry import runs
    from registry.db import Registry
    from registry.models import Run, new_run_id

    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env["HOPE_HOME"] = str(home_path)
    settings = load_settings(env=env)
    rid = run_id or new_run_id()
    run_dir = Path(settings.runs_dir) / rid
    run_dir.mkdir(parents=True)
    rng = random.Random(rid)
    t0 = time.time() - steps * 0.05
    dumps = json.JSONEncoder(separators=(",", ":"), allow_nan=False, ensure_ascii=False).encode
    last = None
    with open(run_dir / "metrics.jsonl", "w", encoding="utf-8") as f:
        batch = []
        for rec in _records(steps, t0, rng, component):
            batch.append(dumps(rec))
            if rec["type"] == "metric":
                last = rec
            if len(batch) >= 4096:
                f.write("\n".join(batch) + "\n")
                batch = []
        batch.append(dumps({"type": "event", "kind": "state", "wall_time": last["wall_time"],
                            "payload": {"state": "completed", "step": steps, "message": ""}}))
        f.write("\n".join(batch) + "\n")
    ckpt = run_dir / "checkpoints" / f"{steps:08d}"
    ckpt.mkdir(parents=True)
    (ckpt / "model.safetensors").write_bytes(b"\0" * 4096)
    (ckpt / "config.json").write_text(json.dumps({"component": component, "checkpoint": {"step": steps}}))
    (ckpt / "manifest.json").write_text(json.dumps({"files": {}}))
    (run_dir / "checkpoints" / "last").write_text(ckpt.name)
    config = {"data": str(Path(settings.home) / "datasets" / "big"), "steps": steps, "seed": 0, "batch_size": 32,
              **(config or {})}
    (run_dir / "provenance.json").write_text(json.dumps({
        "format": 1, "component": component, "config": {"component": component, **config},
        "dataset": {"path": config["data"], "fingerprint": "f" * 16, "episodes": 120, "steps": 60000,
                    "imagined_episodes": 20, "imagined_share": 20 / 120},
        "vqvae": None, "code": {"version": "0.1.0", "git_commit": None, "git_dirty": None}}))
    (run_dir / "result.json").write_text(json.dumps({
        "outcome": "completed", "component": component, "steps": steps, "total_steps": steps,
        "first_loss": 2.8, "final_loss": last["loss"], "checkpoint": str(ckpt), "peak_rss_mb": 331.0,
        "resumed_from": None, "summary": {"val": validation} if validation else {}, "message": "", "elapsed_s": steps * 0.05}))
    registry = Registry.open(settings, migrate=True)
    try:
        with registry.session() as s:
            run = runs.create_run(s, component=component, config=config, total_steps=steps, run_dir=str(run_dir),
                                  run_id=rid, dataset_fingerprint="f" * 16)
            runs.mark_dispatched(s, run, "big-run-task")
            runs.claim(s, rid, "big-run-task", run.attempt, "big-run-host", 4242)
            runs.finish(s, rid, 4242, "completed", "", step=steps, last_checkpoint=str(ckpt))
        with registry.session() as s:  # what the live progress reports would have left on the row
            run = s.get(Run, rid)
            run.loss = last["loss"]
            run.started_at = datetime.fromtimestamp(t0, timezone.utc)
            run.finished_at = datetime.fromtimestamp(last["wall_time"], timezone.utc)
    finally:
        registry.close()
    from hope_models.train.metric_series import write_columns

    write_columns(run_dir)  # what the trainer's metrics log leaves when a run ends
    return rid
