"""The feature spec of a dataset on disk, read as the cache build reads it.

`infer_dataset_spec` is the build's first pass (an even sample of the sources votes on the
fields); `probe_dataset_spec` is the bounded look at a path's first usable episodes that a run
request is checked with before any cache exists, in a process that must stay small (the webapp).
"""
from __future__ import annotations

import os
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
    if data.is_dir():
        sources = iter_sources(data)
    elif data.is_file() and kind_from_name(data.name) is not None and not is_manifest(data.name):
        sources = iter([data])
    else:
        raise FeatureSpecError(f"{data}: not a dataset (an RLDS dataset dir, an episode dir, or an episode file: "
                               ".json, .jsonl, TFRecord or .mcap)")
    problems: list[str] = []
    signatures: list[EpisodeSignature] = []
    looked = too_big = 0
    try:
        for src in sources:
            if looked >= PROBE_MAX_SOURCES or len(signatures) >= PROBE_EPISODES:
                break
            looked += 1
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


def _source_bytes(src: Path) -> int:
    """What reading `src` parses: its episode files, not the frame blobs it loads one at a time."""
    if not src.is_dir():
        return src.stat().st_size
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(src) for f in files
               if kind_from_name(f) is not None)
