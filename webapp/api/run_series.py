"""A run's metrics as plottable series over HTTP (bearer token): the Robot Editor's run page.

    GET /api/runs/<id>/series
        -> {"run_id", "records": <metric record count>,
            "series": [{"name", "points", "first_step", "last_step", "last"}, ...]}
    GET /api/runs/<id>/series?names=loss,lr[&after=STEP]
        -> {"run_id", "last_step": <newest metric step or null>,
            "series": {"loss": {"step": [...], "wall_time": [...], "value": [...]}, ...}}

Without `names`: every metric name that has at least one finite number in the run's metric
records (not type/step/wall_time; strings and booleans are not series), "loss" first, then sorted
by name; `points` is how many records have a finite number for it, `last` the newest of them.

With `names` (comma-separated, at most 12, each [A-Za-z0-9_.:/-]{1,100}): per name only the
records with a finite number for it, steps ascending, step > `after` when given (an integer >= 0;
only with names),
the steps a resume trained again counted once (the rule of GET /api/runs/<id>/metrics). A name the
run has not recorded (yet) has empty arrays. A client polling a live run asks again with
after=<the last step it has>; `last_step` is the newest metric step of any name.

The records are metrics.jsonl's (docs/training.md), read into columns once per run and then only
as far as the file grew (hope_models/train/metric_series.py). Errors: 400 a bad parameter (named),
404 unknown run.
"""
from __future__ import annotations

import json
import re

from flask import Blueprint, Response, jsonify, request

from hope_models.train.metric_series import series_columns
from webapp.api.runs import run_dir_of
from webapp.api.validation import query_args, query_int
from webapp.errors import ApiError

bp = Blueprint("run_series", __name__, url_prefix="/api")

MAX_NAMES = 12
NAME_RE = re.compile(r"[A-Za-z0-9_.:/-]{1,100}")


def _names() -> list[str] | None:
    if "names" not in request.args:
        return None
    raw = request.args.get("names", "")
    names = [n.strip() for n in raw.split(",") if n.strip()]
    if not names:
        raise ApiError("names: give at least one metric name (comma-separated)", 400)
    if len(names) > MAX_NAMES:
        raise ApiError(f"names: at most {MAX_NAMES} names, got {len(names)}", 400)
    bad = [n for n in names if not NAME_RE.fullmatch(n)]
    if bad:
        raise ApiError(f"names: {bad[0][:40]!r} is not a metric name ([A-Za-z0-9_.:/-], 1 to 100 characters)", 400)
    return list(dict.fromkeys(names))


@bp.get("/runs/<run_id>/series")
def series(run_id: str):
    query_args("names", "after")
    names = _names()
    after = query_int("after", default=None, minimum=0)
    if after is not None and names is None:
        raise ApiError("after: only with names=", 400)
    cols = series_columns(run_dir_of(run_id))
    if names is None:
        out = []
        for name in cols.names():
            col = cols.columns[name]
            out.append({"name": name, "points": len(col.step), "first_step": col.step[0],
                        "last_step": col.step[-1], "last": col.value[-1]})
        return jsonify({"run_id": run_id, "records": cols.records, "series": out})
    picked = {}
    for name in names:
        picked[name] = cols.column(name).lists(after)
    # Every value is a finite number and every name matched NAME_RE: plain json.dumps is safe and
    # skips the provider's walk over (up to) hundreds of thousands of numbers.
    body = json.dumps({"run_id": run_id, "last_step": cols.last_step, "series": picked},
                      separators=(",", ":"), allow_nan=False)
    return Response(body, mimetype="application/json")
