"""A finished run's metric columns saved beside its metrics.jsonl (hope_models/train/metric_series.py
write_columns / load_columns): written when the metrics log of a run that ended for good closes,
loaded instead of parsed on the first look after a restart, and never used once they no longer
describe the file (a retry appended to it, the saved file damaged)."""
from __future__ import annotations

import logging
import time

from big_run import make_big_run
from hope_models.train.metric_series import COLUMNS_NAME, clear_cache, series_columns, write_columns
from hope_models.train.metrics import MetricsLog


def _as_lists(cols) -> dict:
    return {"records": cols.records, "last_step": cols.last_step, "offset": cols.offset,
            "columns": {n: cols.column(n).lists() for n in cols.names()}}


def _parsed(run) -> dict:
    """What parsing metrics.jsonl gives (the saved columns moved out of the way)."""
    saved = run / COLUMNS_NAME
    aside = run / "columns.aside"
    saved.rename(aside)
    try:
        clear_cache()
        return _as_lists(series_columns(run))
    finally:
        aside.rename(saved)
        clear_cache()


def test_a_run_that_ends_saves_its_columns_and_a_pause_does_not(tmp_path):
    run = tmp_path / "run"
    log = MetricsLog(run)
    for s in range(1, 51):
        log.log(s, {"loss": 1.0 / s, "lr": 1e-3, "note": "text is not a series"})
    log.event("state", {"state": "paused_user", "step": 50})
    log.close()
    assert not (run / COLUMNS_NAME).exists()  # a paused run goes on appending
    log = MetricsLog(run)
    log.event("resume", {"step": 40})
    for s in range(41, 81):
        log.log(s, {"loss": 2.0 / s, "lr": 1e-3})
    log.event("state", {"state": "completed", "step": 80})
    log.close()
    assert (run / COLUMNS_NAME).is_file()
    clear_cache()
    loaded = _as_lists(series_columns(run))
    assert loaded == _parsed(run)
    assert loaded["columns"]["loss"]["step"] == list(range(1, 81)) and "note" not in loaded["columns"]
    assert loaded["columns"]["loss"]["value"][45] == 2.0 / 46  # the resumed attempt's, not the first's


def test_saved_columns_load_instead_of_parse_and_are_dropped_when_stale_or_damaged(tmp_path, caplog):
    home = tmp_path / "home"
    rid = make_big_run(home, steps=30_000)
    run = home / "runs" / rid
    parsed = _parsed(run)
    t0 = time.perf_counter()
    clear_cache()
    loaded = _as_lists(series_columns(run))
    load_s = time.perf_counter() - t0
    assert loaded == parsed and loaded["records"] == 30_000
    clear_cache()
    t0 = time.perf_counter()
    write_columns(run)  # a parse, like the first look without saved columns
    parse_s = time.perf_counter() - t0
    assert load_s < parse_s / 3, (load_s, parse_s)

    # a retry appended: the saved columns describe an older file, so it is parsed again
    with open(run / "metrics.jsonl", "a", encoding="utf-8") as f:
        f.write('{"type":"metric","step":30001,"wall_time":1.0,"loss":0.5}\n')
    clear_cache()
    grown = series_columns(run)
    assert grown.last_step == 30_001 and grown.column("loss").lists(30_000)["value"] == [0.5]

    # damaged saved columns (cut short) with a matching header: parsed instead, and said
    write_columns(run)
    data = (run / COLUMNS_NAME).read_bytes()
    (run / COLUMNS_NAME).write_bytes(data[: len(data) - 100])
    clear_cache()
    with caplog.at_level(logging.WARNING, logger="hope_models.train.metric_series"):
        again = _as_lists(series_columns(run))
    assert again["records"] == 30_001 and again["columns"]["loss"]["value"][-1] == 0.5
    assert any("unreadable" in r.getMessage() for r in caplog.records), caplog.text
    clear_cache()
