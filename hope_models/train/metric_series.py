"""A run's metric records as columns, one per metric name, for plotting (the Robot Editor's run page).

    series_columns(run_dir) -> MetricColumns   cached per run dir, read incrementally while it grows

`MetricColumns` holds, for each metric name that has at least one finite number in the run's
metric records (not type/step/wall_time; strings, booleans and nulls are skipped), the records
that have a finite number for it: `step`, `wall_time` and `value`, steps ascending. The records
are metrics.jsonl's (`read_jsonl`'s rules: a damaged line is skipped, a last line without its
newline is not read yet) with the steps a resume trained again counted once (`latest_timeline`'s
rule: after a "resume" event at step N, the earlier records of steps > N are dropped).

Cost: parsing a 100k-record metrics.jsonl takes 1-1.5 s on the dev box's x86 core (json.loads
is most of it; several times that on a Pi), so the parsed
columns are kept per run dir (at most CACHE_RUNS of them, least recently used dropped), keyed on
the file's identity (device, inode) and how far it was read. A file that only grew (a live run
appending) is read from where the last read stopped; one that shrank or was replaced is read
again from the start. Thread-safe: one lock around the cache and the reads.

A run that ended for good also leaves its columns beside the file (`write_columns`, called when
its metrics log closes: metrics.columns, a JSON header line then the arrays' raw bytes), so the
first look at a finished run after a restart loads them in milliseconds instead of parsing. They
are used only while metrics.jsonl has exactly the size and mtime they were made from; anything
else (a retry appended, a damaged or foreign file) falls back to parsing.
"""
from __future__ import annotations

import json
import logging
import os
import sys
import threading
from array import array
from bisect import bisect_right
from collections import OrderedDict
from math import fsum, isfinite
from pathlib import Path

from hope_models.durable import atomic_open
from hope_models.train.metrics_files import JSONL_NAME, RESERVED

log = logging.getLogger(__name__)

CACHE_RUNS = 4
COLUMNS_NAME = "metrics.columns"
COLUMNS_FORMAT = 1
NAN = float("nan")
_NUMBERS = frozenset((float, int))
_RESERVED = frozenset(RESERVED)
_STEP_LIMIT = 1 << 62  # an int64 array holds the steps
_READ_BLOCK = 8 << 20


class Column:
    """One name's points: parallel arrays of step, wall time and value (24 bytes a point: a
    100k-step run's ten series keep ~24 MB, not the ~50 MB lists of floats would)."""

    __slots__ = ("step", "wall_time", "value", "missing_wall")

    def __init__(self, step=None, wall_time=None, value=None, missing_wall: bool = False):
        self.step = step if step is not None else array("q")
        self.wall_time = wall_time if wall_time is not None else array("d")  # NaN: no wall_time
        self.value = value if value is not None else array("d")
        self.missing_wall = missing_wall

    def copy(self) -> "Column":
        return Column(array("q", self.step), array("d", self.wall_time), array("d", self.value), self.missing_wall)

    def lists(self, floor: int | None = None) -> dict[str, list]:
        """{"step", "wall_time", "value"} of the points with step > floor (all when None)."""
        i = 0 if floor is None else bisect_right(self.step, floor)
        walls = self.wall_time[i:].tolist()
        if self.missing_wall:
            walls = [None if w != w else w for w in walls]
        return {"step": self.step[i:].tolist(), "wall_time": walls, "value": self.value[i:].tolist()}

    def drop_after(self, step: int) -> None:
        keep = [i for i, s in enumerate(self.step) if s <= step]
        if len(keep) != len(self.step):
            self.step = array("q", (self.step[i] for i in keep))
            self.wall_time = array("d", (self.wall_time[i] for i in keep))
            self.value = array("d", (self.value[i] for i in keep))


class MetricColumns:
    def __init__(self, identity: tuple[int, int] | None = None):
        self.columns: dict[str, Column] = {}
        self.record_steps = array("q")  # every metric record's step, in order
        self.offset = 0  # bytes of metrics.jsonl read (up to the end of the last complete line)
        self.identity = identity  # (st_dev, st_ino) of the file read

    def copy(self) -> "MetricColumns":
        other = MetricColumns(self.identity)
        other.columns = {n: c.copy() for n, c in self.columns.items()}
        other.record_steps = array("q", self.record_steps)
        other.offset = self.offset
        return other

    @property
    def records(self) -> int:
        return len(self.record_steps)

    @property
    def last_step(self) -> int | None:
        return self.record_steps[-1] if self.record_steps else None

    def names(self) -> list[str]:
        """The metric names, "loss" first, then sorted."""
        return sorted(self.columns, key=lambda n: (n != "loss", n))

    def column(self, name: str) -> Column:
        return self.columns.get(name) or Column()

    def _resume(self, step: int) -> None:
        self.record_steps = array("q", (s for s in self.record_steps if s <= step))
        for col in self.columns.values():
            col.drop_after(step)
        for name in [n for n, c in self.columns.items() if not c.step]:
            del self.columns[name]

    def add(self, records: list) -> None:
        """Decoded lines of metrics.jsonl, in file order: metric records column by column (a
        comprehension per name is several times faster than a loop over each record's items),
        a "resume" event dropping what it supersedes in between."""
        batch: list[dict] = []
        for rec in records:
            if type(rec) is not dict:
                continue
            kind = rec.get("type")
            if kind == "metric":
                step = rec.get("step")
                if type(step) is int and -_STEP_LIMIT < step < _STEP_LIMIT:  # bool is not int to type()
                    batch.append(rec)
            elif kind == "event" and rec.get("kind") == "resume":
                payload = rec.get("payload")
                resumed = payload.get("step") if isinstance(payload, dict) else None
                if type(resumed) is int:
                    self._add_metrics(batch)
                    batch = []
                    self._resume(resumed)
        self._add_metrics(batch)

    def _add_metrics(self, batch: list[dict]) -> None:
        if not batch:
            return
        steps = array("q", [r["step"] for r in batch])
        walls = array("d", [w if type(w) is float or type(w) is int else NAN for w in
                            [r.get("wall_time") for r in batch]])
        walls_missing = any(w != w for w in walls)
        self.record_steps.extend(steps)
        for name in set().union(*batch).difference(_RESERVED):
            values = [r.get(name) for r in batch]
            types = set(map(type, values))
            if types.isdisjoint(_NUMBERS):
                continue  # strings, booleans, nulls: not a series
            whole = array("d", values) if types <= _NUMBERS and _all_finite(values) else None
            col = self.columns.get(name)
            if col is None:
                col = self.columns[name] = Column()
            if whole is not None:  # the common case: a number in every record
                col.step.extend(steps)
                col.wall_time.extend(walls)
                col.value.extend(whole)
                col.missing_wall = col.missing_wall or walls_missing
                continue
            # finite numbers only: v - v is 0 for those, NaN for NaN and the infinities
            keep = [i for i, v in enumerate(values) if (type(v) is float or type(v) is int) and v - v == 0]
            picked = array("d", [walls[i] for i in keep])
            col.step.extend(array("q", [steps[i] for i in keep]))
            col.wall_time.extend(picked)
            col.value.extend(array("d", [values[i] for i in keep]))
            col.missing_wall = col.missing_wall or any(w != w for w in picked)
        for name in [n for n, c in self.columns.items() if not c.step]:
            del self.columns[name]


def _all_finite(values: list) -> bool:
    try:
        return isfinite(fsum(values))
    except (OverflowError, ValueError):  # an infinity or a sum past 1e308: take the careful path
        return False


def _read_from(path: Path, cols: MetricColumns) -> None:
    """Add the complete lines after cols.offset (read_jsonl's rules: a damaged line is skipped)."""
    loads = json.loads
    with open(path, "rb") as f:
        f.seek(cols.offset)
        rest = b""
        while True:
            block = f.read(_READ_BLOCK)
            if not block:
                break
            data = rest + block
            end = data.rfind(b"\n")
            if end < 0:
                rest = data
                continue
            records = []
            for line in data[:end].decode("utf-8", "replace").split("\n"):
                if line:
                    try:
                        records.append(loads(line))
                    except ValueError:
                        continue
            cols.add(records)
            cols.offset += end + 1
            rest = data[end + 1:]


_cache: OrderedDict[str, MetricColumns] = OrderedDict()
_lock = threading.Lock()


def series_columns(run_dir: str | os.PathLike) -> MetricColumns:
    """The run's metric columns, up to date with its metrics.jsonl (empty when it has none).

    Callers must not change what they get: it is shared with other threads and later calls."""
    path = Path(run_dir) / JSONL_NAME
    key = str(Path(run_dir).resolve())
    with _lock:
        try:
            st = os.stat(path)
        except FileNotFoundError:
            _cache.pop(key, None)
            return MetricColumns()
        cols = _cache.get(key)
        identity = (st.st_dev, st.st_ino)
        if cols is None or cols.identity != identity or st.st_size < cols.offset:
            cols = load_columns(Path(run_dir), st) or MetricColumns(identity=identity)
        if st.st_size > cols.offset:
            # a copy, so a reader holding the cached object never sees it half updated
            cols = _extend(path, cols)
        _cache[key] = cols
        _cache.move_to_end(key)
        while len(_cache) > CACHE_RUNS:
            _cache.popitem(last=False)
        return cols


def _extend(path: Path, cols: MetricColumns) -> MetricColumns:
    fresh = cols if cols.offset == 0 else cols.copy()
    _read_from(path, fresh)
    return fresh


def clear_cache() -> None:
    with _lock:
        _cache.clear()


# -- the columns of a finished run, saved beside its metrics.jsonl ------------------------------

def _stamp(st: os.stat_result) -> dict:
    return {"jsonl_size": st.st_size, "jsonl_mtime_ns": st.st_mtime_ns}


def write_columns(run_dir: str | os.PathLike) -> Path | None:
    """Parse metrics.jsonl and save its columns as metrics.columns (durable.atomic_open: a crash
    leaves the old file or none). Returns the path, or None when there is no
    metrics.jsonl or writing failed (logged; the file is then parsed when first read)."""
    run = Path(run_dir)
    path = run / JSONL_NAME
    try:
        st = os.stat(path)
        cols = MetricColumns(identity=(st.st_dev, st.st_ino))
        _read_from(path, cols)
        names = cols.names()
        header = {"format": COLUMNS_FORMAT, "byteorder": sys.byteorder, **_stamp(st), "offset": cols.offset,
                  "records": cols.records,
                  "columns": [{"name": n, "points": len(cols.columns[n].step),
                               "missing_wall": cols.columns[n].missing_wall} for n in names]}
        out = run / COLUMNS_NAME
        with atomic_open(out, "wb") as f:
            f.write(json.dumps(header, separators=(",", ":")).encode() + b"\n")
            f.write(cols.record_steps.tobytes())
            for n in names:
                c = cols.columns[n]
                f.write(c.step.tobytes() + c.wall_time.tobytes() + c.value.tobytes())
        return out
    except (OSError, ValueError) as exc:
        log.warning("%s: metric columns not saved (%s); the run page parses metrics.jsonl instead", run, exc)
        return None


def load_columns(run_dir: Path, st: os.stat_result) -> MetricColumns | None:
    """The saved columns when they were made from metrics.jsonl exactly as it is now (`st`);
    None otherwise (missing, stale, damaged, another machine's byte order)."""
    try:
        with open(run_dir / COLUMNS_NAME, "rb") as f:
            header = json.loads(f.readline())
            if (not isinstance(header, dict) or header.get("format") != COLUMNS_FORMAT
                    or header.get("byteorder") != sys.byteorder
                    or {k: header.get(k) for k in _stamp(st)} != _stamp(st)):
                return None
            cols = MetricColumns(identity=(st.st_dev, st.st_ino))
            cols.offset = int(header["offset"])
            cols.record_steps = _array("q", f, int(header["records"]))
            for spec in header["columns"]:
                n = int(spec["points"])
                cols.columns[str(spec["name"])] = Column(_array("q", f, n), _array("d", f, n), _array("d", f, n),
                                                         bool(spec["missing_wall"]))
            if f.read(1):
                return None  # more bytes than the header says: not what write_columns wrote
            return cols
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("%s: saved metric columns unreadable (%s); parsing metrics.jsonl", run_dir, exc)
        return None


def _array(typecode: str, f, n: int) -> array:
    a = array(typecode)
    data = f.read(n * a.itemsize)
    if len(data) != n * a.itemsize:
        raise ValueError(f"{COLUMNS_NAME} is shorter than its header says")
    a.frombytes(data)
    return a
