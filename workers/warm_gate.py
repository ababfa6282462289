"""The gate of a run in the worker child that has just trained it, before the child exits.

    gate = WarmGate(settings, channel, threads)   # wanted: auto-promotion on, the registry on this host
    with gate.held():                             # takes the promote lock when nobody else has it
        final = channel.finish(...)               # the run becomes "completed" while the lock is held
        gate.run(run_id, final)                   # gates, records and promotes like `promote RUN --auto`

Why here: this child has torch loaded and the dataset's pages in memory. A `promote` child that
auto-promotion spawns first spends seconds importing torch and opening the dataset (4-5 s of
imports alone on a loaded Pi-class machine) before the gate starts, and the new model answers that
much later. The procedure is registry/gating.py's, the one `promote` runs.

The lock is taken before the run is reported completed, so the daemon's auto-promotion (which
skips a tick while the lock is held: daemon/autopromote.py) finds the run already recorded and
spawns nothing. When the lock is busy (another gate runs) or the gate fails, nothing is lost:
the run has no candidate record, and auto-promotion gates it in a child as before. A worker on
another host (reporting through Redis) has no registry here and never gates.
"""
from __future__ import annotations

import logging
import os
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

from hope_models.log_limits import rotate_if_over
from registry import runs
from registry.gating import PROMOTE_LOG, PromoteRequest, UsageError, describe_outcome, promote_candidate, promote_lock
from registry.models import utcnow
from registry.promotion import PromotionError

if TYPE_CHECKING:
    from hope_models.settings import Settings

log = logging.getLogger(__name__)


class WarmGate:
    def __init__(self, settings: Settings, channel: Any, threads: int = 1):
        self.settings, self.channel, self.threads = settings, channel, max(1, int(threads))
        self.registry: Any = getattr(channel, "registry", None)  # "db" channels only
        self.wanted = bool(settings.auto_promote) and channel.mode == "db" and self.registry is not None
        self._held = False
        self.outcome: dict[str, Any] | None = None  # what the gate said (tests, the job's summary)

    @contextmanager
    def held(self) -> Iterator[bool]:
        if not self.wanted:
            yield False
            return
        with promote_lock(Path(self.settings.home), wait=False) as mine:
            self._held = mine
            try:
                yield mine
            finally:
                self._held = False

    def run(self, run_id: str, final: str | None) -> dict[str, Any] | None:
        """Gate `run_id` when it completed and the lock is held; never raises (the daemon gates it
        later when this does not)."""
        if not self._held or final != "completed":
            return None
        try:
            code, out = promote_candidate(self.settings, self.registry,
                                          PromoteRequest(run=run_id, auto=True, threads=self.threads))
        except (UsageError, PromotionError) as exc:
            code, out = 2, {"promoted": False, "error": str(exc)}
        except Exception:  # a bug must not lose the run's outcome: auto-promotion retries in a child
            log.exception("run %s: the gate in the worker child failed; auto-promotion gates it instead", run_id)
            return None
        level, message = describe_outcome(code, out, who="auto-promote (in the worker that trained it)")
        self.outcome = {"exit_code": code, **out}
        self._record(run_id, level, message)
        return self.outcome

    def _record(self, run_id: str, level: str, message: str) -> None:
        logs = Path(self.settings.home) / "logs"
        try:
            logs.mkdir(parents=True, exist_ok=True)
            rotate_if_over(logs / PROMOTE_LOG, self.settings)
            with open(logs / PROMOTE_LOG, "a", encoding="utf-8") as f:
                f.write(f"{utcnow().isoformat(timespec='seconds')} run {run_id}: {message} (pid {os.getpid()})\n")
        except OSError as exc:
            log.warning("run %s: %s not written: %s", run_id, logs / PROMOTE_LOG, exc)
        try:
            with self.registry.session() as s:
                runs.add_event(s, run_id, "log", {"level": level, "message": message, "source": "auto-promote"})
        except runs.RunError as exc:
            log.warning("run %s: the gate's outcome is not recorded as an event: %s", run_id, exc)
        log.info("run %s: %s", run_id, message)


__all__ = ["WarmGate"]
