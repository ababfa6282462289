"""What a run was made from and what it left, over HTTP (bearer token): the Robot Editor's run page.

    GET /api/runs/<id>/provenance
        -> {"run_id", "component", "config": <the full resolved configuration>, "config_source",
            "dataset": {"path", "fingerprint", "episodes", "steps", "imagined_episodes", "imagined_share", ...},
            "vqvae": {"dir", "run_id", "version"} | null,
            "code": {"version", "git_commit", "git_dirty"},
            "gate": [{"model_id", "version", "verdict", "checks", "at", "reasons", "promoted"}, ...],
            "recorded_at": unix s | null}
    GET /api/runs/<id>/artifacts
        -> {"run_id", "artifacts": [{"name", "kind", "size", "url", "media_type", "description"
                                     (, "step" for a checkpoint)}, ...]}
    GET /api/runs/<id>/artifacts/<name>   the file, as an attachment (Content-Disposition names it)

Provenance: where each field comes from is webapp/api/run_provenance.py's docstring; a field no
record holds is null, never made up (a run trained before provenance.json existed has no dataset
counts and no code version).

Artifacts, in this order, those that exist: "metrics.jsonl" (kind "metrics"), "metrics.mcap",
"metrics.1.mcap", ... (kind "mcap": open in Foxglove), "result.json" (kind "result", once the run
ended), "provenance.json" (kind "provenance"), "gate.json" (kind "gate", when a gate report was
written into the run dir; the gate today records into the registry, shown by /provenance),
"held_out_frames.png" (kind "picture", media type image/png: a frame VQ-VAE run's held-out frames
over their reconstructions, train/held_out_picture.py; the run page shows it), "predicted_frames.png"
(kind "picture", image/png: a grid Mid Loop run's held-out windows, one a row, the frame now and at
each horizon the frame decoded from its predicted codes beside the recorded one; shown likewise), then
"checkpoint-<step>.tar" per checkpoint dir, oldest first (kind "checkpoint", "step"; size is the
sum of its files). `url` is the download's path. A file is sent with Content-Length (its size
when the request opened it; Range and conditional requests work); a checkpoint as an uncompressed tar streamed from the dir, members named
"checkpoint-<step>/<file>". A name must be one the listing has: anything else, a path included,
is 404; a file or checkpoint that resolves outside the run dir (a symlink) is 404 too, with the
reason (webapp/api/run_files.py). Errors: 404 unknown run or artifact.
"""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

from flask import Blueprint, Response, current_app, jsonify, request

from webapp.api.run_files import (
    UnsafeFile,
    artifact_size,
    candidates,
    is_safe,
    list_artifacts,
    open_checkpoint_tar,
    open_confined,
)
from webapp.api.run_provenance import gate_records
from webapp.api.run_provenance import provenance as assemble
from webapp.api.runs import run_dir_of, run_or_404
from webapp.api.validation import query_args
from webapp.errors import ApiError

bp = Blueprint("run_artifacts", __name__, url_prefix="/api")


@bp.get("/runs/<run_id>/provenance")
def provenance(run_id: str):
    query_args()
    with current_app.extensions["hope"].registry.session(readonly=True) as s:
        obj = assemble(run_or_404(s, run_id), gate_records(s, run_id))
    return jsonify(obj)


@bp.get("/runs/<run_id>/artifacts")
def artifacts(run_id: str):
    query_args()
    run_dir = Path(run_dir_of(run_id))
    out = []
    for art in list_artifacts(run_dir):
        try:
            size = artifact_size(run_dir, art)
        except (OSError, UnsafeFile):
            continue  # gone (pruned) or changed since it was listed
        item = {"name": art.name, "kind": art.kind, "size": size, "url": f"/api/runs/{run_id}/artifacts/{art.name}",
                "media_type": art.media_type, "description": art.description}
        if art.step is not None:
            item["step"] = art.step
        out.append(item)
    return jsonify({"run_id": run_id, "artifacts": out})


@bp.get("/runs/<run_id>/artifacts/<path:name>")
def download(run_id: str, name: str):
    query_args()
    run_dir = Path(run_dir_of(run_id))
    art = {a.name: a for a in candidates(run_dir)}.get(name)
    if art is None:
        raise ApiError(f"run {run_id} has no artifact {name[:100]!r} (GET /api/runs/{run_id}/artifacts lists them)", 404)
    if not is_safe(run_dir, art):
        # the listing leaves it out: say why rather than "no such"
        raise ApiError(f"artifact {name}: resolves outside the run dir; refused", 404)
    try:
        if art.kind == "checkpoint":
            blocks, length = open_checkpoint_tar(run_dir, art)
            response = Response(blocks, mimetype=art.media_type, direct_passthrough=True)
            response.headers["Content-Length"] = str(length)
            response.headers["Content-Disposition"] = f"attachment; filename={art.name}"
            return response
        f, st = open_confined(run_dir, art.path)
    except UnsafeFile as exc:
        raise ApiError(f"artifact {name}: {exc}; refused", 404) from None
    except FileNotFoundError:
        raise ApiError(f"artifact {name}: gone (pruned or replaced since it was listed)", 404) from None
    rv = Response(_limited(f, st.st_size), mimetype=art.media_type, direct_passthrough=True)
    rv.content_length = st.st_size
    rv.last_modified = datetime.fromtimestamp(st.st_mtime, timezone.utc)  # the same header as the float gave
    rv.set_etag(f"{st.st_ino}-{st.st_size}-{st.st_mtime_ns}")
    rv.cache_control.no_cache = True
    rv.headers["Content-Disposition"] = f"attachment; filename={art.name}"
    return rv.make_conditional(request.environ, accept_ranges=True, complete_length=st.st_size)


def _limited(f, size: int, chunk: int = 256 * 1024):
    """The file's first `size` bytes (its size when it was opened: a live run's metrics.jsonl
    grows while it is sent, and the answer must match its Content-Length)."""
    try:
        left = size
        while left > 0:
            data = f.read(min(chunk, left))
            if not data:
                break
            left -= len(data)
            yield data
    finally:
        f.close()
