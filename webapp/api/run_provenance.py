"""A run's provenance, assembled from what was recorded (GET /api/runs/<id>/provenance in
webapp/api/run_artifacts.py). Nothing is guessed: a figure no record holds is null.

Where each part comes from, first found wins:
  config   provenance.json's (the attempt's full TrainConfig, written at run start:
           hope_models/train/provenance.py), else the newest checkpoint's config.json "train"
           (the same object, saved with every checkpoint), else the registry row's config (what
           the request said; the rest were defaults). `config_source` says which.
  dataset  provenance.json's (path, fingerprint, episodes, steps, imagined episodes and share);
           else path from the run's config and fingerprint from the registry row, the rest null.
  vqvae    provenance.json's; else, for a component that reads one, the newest checkpoint's
           config.json "vqvae" reference (dir) and the request's vqvae_run; null for a vqvae run.
  code     provenance.json's (package version, git commit, dirty); else nulls.
  gate     every registry Model row of this run, oldest first: its gate_result's verdict
           ("promoted", "forced", "passed" (not promoted), "refused") and checks.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from hope_models.checkpoint_format import CONFIG_FILE, VQVAE_REF, CheckpointError, read_json_object
from hope_models.checkpoints import list_step_dirs
from hope_models.components import spec_of
from hope_models.train.provenance import read_provenance

CODE_NULL = {"version": None, "git_commit": None, "git_dirty": None}
DATASET_KEYS = ("path", "fingerprint", "episodes", "steps", "imagined_episodes", "imagined_share")


def _checkpoint_config(run_dir: Path) -> dict[str, Any] | None:
    for _, ckdir in list_step_dirs(run_dir):
        try:
            return read_json_object(ckdir / CONFIG_FILE)
        except (OSError, CheckpointError):
            continue
    return None


def _verdict(gate: Any) -> str | None:
    if not isinstance(gate, dict):
        return None
    if gate.get("promoted"):
        return "forced" if gate.get("forced") else "promoted"
    return "passed" if gate.get("passed") else "refused"


def gate_records(s, run_id: str) -> list[dict[str, Any]]:
    from sqlalchemy import select  # lazy: loads sqlalchemy

    from registry.models import Model, iso  # lazy: loads sqlalchemy

    rows = s.scalars(select(Model).where(Model.run_id == run_id).order_by(Model.created_at, Model.id)).all()
    out = []
    for m in rows:
        gate = m.gate_result if isinstance(m.gate_result, dict) else None
        out.append({"model_id": m.id, "version": m.version, "verdict": _verdict(gate),
                    "checks": gate.get("checks") if gate else None, "at": iso(m.created_at),
                    "reasons": gate.get("reasons") if gate else None, "promoted": m.promoted_at is not None})
    return out


_UNRECORDED = object()


def provenance(run, gate: list[dict[str, Any]]) -> dict[str, Any]:
    """The answer for a registry Run row (read inside its session) and its gate records."""
    run_dir = Path(run.run_dir)
    rec = read_provenance(run_dir) or {}
    request_config = run.config if isinstance(run.config, dict) else {}
    ck = None
    recorded_vq = rec.get(VQVAE_REF, _UNRECORDED)  # the provenance's reference to the VQ-VAE read, if it has one
    if not isinstance(rec.get("config"), dict) or recorded_vq is _UNRECORDED:
        ck = _checkpoint_config(run_dir)
    if isinstance(rec.get("config"), dict):
        config, source = rec["config"], "provenance"
    elif ck is not None and isinstance(ck.get("train"), dict):
        config, source = ck["train"], "checkpoint"
    else:
        config, source = request_config, "request"

    recorded_dataset = rec.get("dataset")
    recorded = recorded_dataset if isinstance(recorded_dataset, dict) else {}
    dataset = {k: recorded.get(k) for k in DATASET_KEYS}
    dataset.update({k: v for k, v in recorded.items() if k not in dataset})
    if dataset["path"] is None:
        data = config.get("data") or request_config.get("data")
        dataset["path"] = data if isinstance(data, str) else None
    if dataset["fingerprint"] is None:
        dataset["fingerprint"] = run.dataset_fingerprint or (ck or {}).get("data_fingerprint")

    if recorded_vq is not _UNRECORDED:
        vqvae = recorded_vq if isinstance(recorded_vq, dict) else None
    elif not spec_of(run.component).reads_codes:
        vqvae = None
    else:
        ref = (ck or {}).get(VQVAE_REF)
        path = ref.get("path") if isinstance(ref, dict) else None
        path = path if isinstance(path, str) else request_config.get("vqvae_dir")
        run_ref = request_config.get("vqvae_run")
        if path is None and run_ref is None:
            vqvae = None
        else:
            derived = Path(path).parent.parent.name if path and Path(path).parent.name == "checkpoints" else None
            vqvae = {"dir": path, "run_id": run_ref or derived, "version": None}

    recorded_code = rec.get("code")
    code = recorded_code if isinstance(recorded_code, dict) else {}
    return {"run_id": run.id, "component": run.component, "config": config, "config_source": source,
            "dataset": dataset, VQVAE_REF: vqvae, "code": {**CODE_NULL, **code}, "gate": gate,
            "recorded_at": rec.get("written_at")}
