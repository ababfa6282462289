"""The canonical episode every reader produces and every writer consumes.

Canonical means the documented Continuon v1.1 shape: snake_case keys, `schema_version` "1.1",
`metadata.provenance.origin` set, and one integer `timestamp_ns` per step derived from whichever
clock the producer wrote (see `timestamps.py`). Unknown keys are kept as they came, so nothing a
producer wrote is lost on the way through.

Readers never raise for bad data: they record `Problem`s on the episode (or on a `SourceReport`
when no episode could be built at all) so that `validate` and `ingest` can report every file.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

SCHEMA_VERSION = "1.1"

ERROR = "error"
WARNING = "warning"


@dataclass(frozen=True)
class Problem:
    """One finding about a source file, precise enough to go and look at the byte that caused it."""

    severity: str  # ERROR or WARNING
    source: str  # the file (or file + member) the finding is about
    message: str
    step: int | None = None  # step index within the episode, when it applies
    field: str | None = None  # dotted field path, e.g. "observation.robot_state.joint_positions"

    def __str__(self) -> str:
        where = self.source
        if self.step is not None:
            where += f": step {self.step}"
        if self.field:
            where += f": {self.field}"
        return f"{where}: {self.message}"

    def as_dict(self) -> dict[str, Any]:
        return {"severity": self.severity, "source": self.source, "step": self.step,
                "field": self.field, "message": self.message}


@dataclass
class Step:
    observation: dict[str, Any]
    action: dict[str, Any]
    reward: float = 0.0
    is_terminal: bool = False
    step_metadata: dict[str, Any] = field(default_factory=dict)
    timestamp_ns: int | None = None  # filled by timestamps.assign_timestamps
    extras: dict[str, Any] = field(default_factory=dict)  # other step keys, e.g. language_instruction

    def to_json_obj(self, index: int) -> dict[str, Any]:
        obj: dict[str, Any] = {
            "step_index": index,
            "timestamp_ns": self.timestamp_ns,
            "observation": self.observation,
            "action": self.action,
            "reward": self.reward,
            "is_terminal": self.is_terminal,
            "step_metadata": self.step_metadata,
        }
        for k, v in self.extras.items():
            obj.setdefault(k, v)
        return obj


@dataclass
class Episode:
    episode_id: str
    metadata: dict[str, Any]
    steps: list[Step]
    source: str  # where it was read from (path, or path#episode_id for multi-episode files)
    layout: str  # "episode_dir", "single_json", "steps_jsonl", "tfrecord", "mcap", "canonical_dir"
    problems: list[Problem] = field(default_factory=list)
    steps_lost: int = 0  # steps that could not be recovered (corrupt TFRecord records, bad lines)
    blob_root: str | None = None  # directory that relative blob URIs resolve against

    # -- findings -------------------------------------------------------------------------
    def error(self, message: str, step: int | None = None, field: str | None = None,
              source: str | None = None) -> None:
        self.problems.append(Problem(ERROR, source or self.source, message, step, field))

    def warn(self, message: str, step: int | None = None, field: str | None = None,
             source: str | None = None) -> None:
        self.problems.append(Problem(WARNING, source or self.source, message, step, field))

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == ERROR]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == WARNING]

    @property
    def is_imagined(self) -> bool:
        provenance = self.metadata.get("provenance")
        origin = str(provenance.get("origin", "")) if isinstance(provenance, dict) else ""
        tags = self.metadata.get("tags")
        return origin.startswith("imagined:") or (isinstance(tags, list) and "continuon.imagined" in tags)

    @property
    def duration_s(self) -> float:
        ts = [s.timestamp_ns for s in self.steps if s.timestamp_ns is not None]
        return (ts[-1] - ts[0]) / 1e9 if len(ts) >= 2 else 0.0


@dataclass
class SourceReport:
    """What a reader found in one file or directory: the episodes, plus problems with no episode."""

    source: str
    episodes: list[Episode] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)  # e.g. unreadable file, no records
    skipped: bool = False  # a metadata-only dir, a zero-record TFRecord: nothing to train on
    skip_reason: str | None = None
