"""The feature spec of a dataset on disk, read as the cache build reads it.

`infer_dataset_spec` is the build's first pass (an even sample of the sources votes on the
fields); `probe_dataset_spec` is the bounded look at a path's first usable episodes that a run
request is checked with before any cache exists, in a process that must stay small (the webapp).
A probe is remembered (by the path, the files it read, their sizes and times) so that asking about
the same dataset again, as every run request does, costs a directory listing and a few stats, not
a parse: a client may ask as often as it likes.
"""
from __future__ import annotations

import copy
import itertools
import os
import threading
import time
from collections import OrderedDict
from pathlib import Path

from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.source import iter_sources, read_source
from hope_models.data.spec_inference import EpisodeSignature, episode_signature, infer_spec
from hope_models.data.spec_request import SpecRequest
from hope_models.rlds.discover import is_manifest, kind_from_name
from hope_models.rlds.episode import ERROR

# Spec inference reads an even sample of sources beyond this many: choosing fields is a vote that a
# few hundred episodes settle, and the build pass then checks every step of every episode anyway.
INFER_MAX_SOURCES = 200
# probe_dataset_spec reads at most this much, in a process that must stay small (the webapp)
PROBE_MAX_SOURCES = 20
PROBE_EPISODES = 8
PROBE_MAX_SOURCE_BYTES = 16 << 20  # parsed JSON takes several times its size


def _signatures(reports, problems: list[str] | None = None) -> list[EpisodeSignature]:
    """Signatures of the usable episodes of these source reports (`problems` collects why the
    others are not)."""
    signatures: list[EpisodeSignature] = []
    for report in reports:
        for ep in report.episodes:
            if not ep.errors and ep.steps:
                signatures.append(episode_signature(ep.episode_id, ep.steps, ep.blob_root))
            elif problems is not None:
                problems.append(str(ep.errors[0]) if ep.errors else f"{report.source}: episode {ep.episode_id} "
                                                                    "has no steps")
        if problems is not None:
            problems.extend(str(x) for x in report.problems if x.severity == ERROR)
    return signatures


def infer_dataset_spec(dataset: Path, request: SpecRequest, skip: Path | None = None) -> FeatureSpec:
    """Pass 1: episode signatures (first/last step) from the sources, then choose fields."""
    sources = list(iter_sources(dataset, skip))
    sample = sources
    if len(sources) > INFER_MAX_SOURCES:
        stride = len(sources) / INFER_MAX_SOURCES
        sample = [sources[int(i * stride)] for i in range(INFER_MAX_SOURCES)]
    signatures = _signatures(report for src in sample for report in read_source(src))
    try:
        spec = infer_spec(signatures, request)
    except FeatureSpecError as exc:
        raise FeatureSpecError(f"{dataset}: {exc}") from None
    if sample is not sources:
        spec.notes.append(f"fields inferred from an even sample of {len(sample)} of {len(sources)} sources")
    return spec


def probe_dataset_spec(data: str | Path, request: SpecRequest | None = None) -> FeatureSpec | None:
    """The feature spec of the first few usable episodes of `data` (a dataset dir, an episode dir
    or an episode file), read as the cache build reads them, torch-free and in bounded time.

    It lets a run request be refused at the door (registry/run_request.py) when its path holds no
    usable episode, and its memory be estimated from the dims the build will most likely infer (the
    build votes over up to INFER_MAX_SOURCES sources). FeatureSpecError names the path and why; None
    when every source it looked at is larger than PROBE_MAX_SOURCE_BYTES (not read here: the
    training job's own checks still apply)."""
    data = Path(data)
    key = (str(data), repr(request))
    remembered = _PROBES.get(key, data)
    if remembered is not None:
        return remembered.answer()
    probe = _Probe(time.time_ns())
    try:
        probe.spec = _probe(data, request, probe.looked)
    except FeatureSpecError as exc:
        probe.error = str(exc)
    if probe.stamp(data):
        _PROBES.put(key, probe)
    return probe.answer()


def _sources(data: Path):
    if data.is_dir():
        return iter_sources(data)
    if data.is_file() and kind_from_name(data.name) is not None and not is_manifest(data.name):
        return iter([data])
    raise FeatureSpecError(f"{data}: not a dataset (an RLDS dataset dir, an episode dir, or an episode file: "
                           ".json, .jsonl, TFRecord or .mcap)")


def _probe(data: Path, request: SpecRequest | None, looked_at: list[Path]) -> FeatureSpec | None:
    sources = _sources(data)
    problems: list[str] = []
    signatures: list[EpisodeSignature] = []
    looked = too_big = 0
    try:
        for src in sources:
            if looked >= PROBE_MAX_SOURCES or len(signatures) >= PROBE_EPISODES:
                break
            looked += 1
            looked_at.append(src)
            if _source_bytes(src) > PROBE_MAX_SOURCE_BYTES:
                too_big += 1
                continue
            signatures += _signatures(read_source(src), problems)
    except OSError as exc:
        raise FeatureSpecError(f"{data}: cannot read it: {exc.strerror or exc}") from None
    if not signatures:
        if looked and too_big == looked:
            return None
        if not looked:
            raise FeatureSpecError(f"{data}: no episode files in it (.json, .jsonl, TFRecord or .mcap)")
        why = f": {problems[0]}" if problems else ""
        raise FeatureSpecError(f"{data}: no usable episode in the first {looked} source(s){why}")
    try:
        return infer_spec(signatures, request)
    except FeatureSpecError as exc:
        raise FeatureSpecError(f"{data}: {exc}") from None

class _Probe:
    """One probe's answer (a spec, None, or the refusal's text), the sources it read in order, and
    the size and time of every file under them when it was made."""

    def __init__(self, started_ns: int):
        self.started_ns = started_ns
        self.spec: FeatureSpec | None = None
        self.error: str | None = None
        self.looked: list[Path] = []
        self.files: tuple = ()
        self.exhausted = False

    def answer(self) -> FeatureSpec | None:
        if self.error is not None:
            raise FeatureSpecError(self.error)
        return copy.deepcopy(self.spec)  # callers add notes to theirs

    def _now(self, data: Path) -> tuple[list[Path], bool, tuple] | None:
        """(the first sources of data now, whether there are no more, their files' stamps); None
        when the path cannot be listed (no answer is remembered for it)."""
        try:
            first = list(itertools.islice(_sources(data), len(self.looked) + 1))
            stamps = []
            for src in first[:len(self.looked)]:
                walk = [(d, f) for d, _, files in os.walk(src) for f in files] if src.is_dir() else [("", str(src))]
                for d, f in sorted(walk):
                    st = os.stat(os.path.join(d, f))
                    stamps.append((d, f, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino))
            return first[:len(self.looked)], len(first) <= len(self.looked), tuple(stamps)
        except (OSError, FeatureSpecError):
            return None

    def stamp(self, data: Path) -> bool:
        """Take the stamps the answer is remembered by; False (not remembered) when the sources
        moved or a file changed so recently that the parse may have seen it half-written (within
        CHANGED_LATELY_NS of the probe's start: coarse clocks on some cards)."""
        now = self._now(data)
        if now is None or now[0] != self.looked:
            return False
        if any(max(st[3], st[4]) >= self.started_ns - CHANGED_LATELY_NS for st in now[2]):
            return False
        _, self.exhausted, self.files = now
        return True

    def still_holds(self, data: Path) -> bool:
        """The same sources in the same order (and no new one, when the probe read them all), and
        not one of their files changed in size, time or inode."""
        now = self._now(data)
        return now is not None and now[0] == self.looked and now[2] == self.files and (
            now[1] or not self.exhausted)


class _ProbeMemory:
    """The last PROBES_REMEMBERED probes, each answered again only while its files are unchanged."""

    def __init__(self, size: int):
        self.size = size
        self.lock = threading.Lock()
        self.probes: OrderedDict[tuple, _Probe] = OrderedDict()

    def get(self, key: tuple, data: Path) -> _Probe | None:
        with self.lock:
            probe = self.probes.get(key)
        if probe is None or not probe.still_holds(data):
            return None
        with self.lock:
            if key in self.probes:
                self.probes.move_to_end(key)
        return probe

    def put(self, key: tuple, probe: _Probe) -> None:
        with self.lock:
            self.probes[key] = probe
            self.probes.move_to_end(key)
            while len(self.probes) > self.size:
                self.probes.popitem(last=False)


PROBES_REMEMBERED = 32
CHANGED_LATELY_NS = 2_000_000_000
_PROBES = _ProbeMemory(PROBES_REMEMBERED)


def _source_bytes(src: Path) -> int:
    """What reading `src` parses: its episode files, not the frame blobs it loads one at a time."""
    if not src.is_dir():
        return src.stat().st_size
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(src) for f in files
               if kind_from_name(f) is not None)
