"""The daemon's side of a full disk: the free-space floor before dispatch, and retention.

Floor. A job on a local queue writes under $HOPE_HOME; the daemon does not start one while the
free space there is below the floor (settings.disk_floor_mb, or by default the job's checkpoint
size x (keep_last + 2) + 200 MB, hope_models/disk.py). The run stays queued, and its `waiting`
text (Run.waiting_text) says why: the text is kept in the queued run's error_message, which a
queued run has no other use for (run_states.transition clears it when the run leaves queued). A
run paused for disk (outcome paused_disk) is requeued once the free space is above its floor.

The checkpoint size comes from disk, torch-free and exact where it can be: the newest checkpoint
in the run's own dir (a resumed job writes the same size again), else the newest checkpoint of the
last run of the same component that has one, else an estimate from the run's configuration (the
weights and AdamW's two moments of the model it describes: estimate.checkpoint_mb_from_config, as
the door's pre-flight resolves it), else 0 (the 200 MB margin alone).

Retention (settings.keep_runs, 0 = keep all): after a run finishes (the daemon's tick sees the
number of finished runs change) the run dirs of finished runs are deleted, except the newest
keep_runs finished ones that produced something (a checkpoint or metrics on disk: a run cancelled
or failed before it started takes no place, so a burst of created-and-cancelled runs cannot push
a trained run out), the newest completed run of each component, those of models that were ever
promoted (served now or a rollback target), the VQ-VAE runs those and the unfinished runs read
codes from, and any run dir holding a file named PINNED (`touch <run_dir>/PINNED`). Only dirs
under $HOPE_HOME/runs are ever deleted; the run rows stay, each deletion a `log` event on its run
(payload `retention`: the dir, keep_runs, why) and a log line.
"""
from __future__ import annotations

import itertools
import logging
import os
import shutil
from pathlib import Path
from typing import Any

from sqlalchemy import func, or_, select

from hope_models import disk
from hope_models.checkpoints import list_step_dirs, resolve_checkpoint_dir
from hope_models.components import spec_of
from hope_models.train.config import TrainConfig
from hope_models.train.metrics import JSONL_NAME
from registry import runs
from registry.models import Model, Run

log = logging.getLogger(__name__)

PIN_FILE = "PINNED"
MB = 1024 * 1024


def _estimated_checkpoint_mb(run: Run) -> float:
    """The checkpoint size the run's configuration describes (0 when it cannot be told: the floor
    is then the margin alone, and the job's own ENOSPC handling still stands)."""
    from hope_models.components.resolve import resolve  # lazy: loads numpy
    from hope_models.data.dataset_spec import probe_dataset_spec  # lazy: loads numpy
    from hope_models.train.estimate import checkpoint_mb_from_config  # lazy: loads psutil

    cfg = run.config or {}
    try:
        spec = probe_dataset_spec(cfg["data"])
        reads = spec_of(run.component).reads_codes
        if spec is None or reads and cfg.get("vqvae_dir") is None and cfg.get("vqvae_run") is not None:
            return 0.0  # too large to probe here, or codes from a VQ-VAE not trained yet
        vq = None
        if reads and cfg.get("vqvae_dir"):
            from hope_models.components.resolve import read_vqvae_config  # lazy: loads numpy
            vq = read_vqvae_config(resolve_checkpoint_dir(cfg["vqvae_dir"]))
        resolved = resolve(run.component, spec, dict(cfg.get("model_config") or {}), vq)
        return checkpoint_mb_from_config(resolved, spec.obs_dim, spec.act_dim)
    except Exception as exc:  # a run the door checked; anything odd here only loses the estimate
        log.info("run %s: no checkpoint size estimate (%s: %s)", run.id, type(exc).__name__, exc)
        return 0.0


def _dir_mb(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / MB


def newest_checkpoint_mb(run_dir: str | Path) -> float | None:
    try:
        steps = list_step_dirs(run_dir)
        return _dir_mb(steps[0][1]) if steps else None
    except OSError:
        return None


class DiskGuard:
    def __init__(self, registry: Any, settings: Any):
        self.registry, self.settings = registry, settings
        self._finished_seen: int | None = None
        self._estimated: dict[str, float] = {}

    # -- the floor ---------------------------------------------------------------------------

    def checkpoint_mb(self, s: Any, run: Run) -> float:
        own = newest_checkpoint_mb(run.run_dir)
        if own is not None:
            return own
        for other in s.scalars(select(Run).where(Run.component == run.component, Run.id != run.id,
                                                 Run.last_checkpoint.is_not(None))
                               .order_by(Run.updated_at.desc()).limit(5)):
            size = newest_checkpoint_mb(other.run_dir)
            if size is not None:
                return size
        if run.id not in self._estimated:  # probing the dataset reads files: once per run
            self._estimated[run.id] = _estimated_checkpoint_mb(run)
        return self._estimated[run.id]

    def floor_mb(self, s: Any, run: Run) -> float:
        keep = int((run.config or {}).get("keep_last") or TrainConfig.keep_last)
        return disk.dispatch_floor_mb(self.checkpoint_mb(s, run), keep, self.settings.disk_floor_mb)

    def refusal(self, s: Any, run: Run) -> str | None:
        """Why `run` must not start on this host now (too little free space), or None."""
        free = disk.free_mb(self.settings.home)
        floor = self.floor_mb(s, run)
        if free is None or free >= floor:
            return None
        how = ("disk_floor_mb" if self.settings.disk_floor_mb > 0
               else "its checkpoint size x (keep_last + 2) + 200 MB; set disk_floor_mb to override")
        return (f"waiting for disk space: {free:.0f} MB free under {self.settings.home}, below the floor of "
                f"{floor:.0f} MB ({how}); free some space (or lower keep_runs) and it starts")

    def hold(self, s: Any, run: Run, why: str) -> None:
        """Keep `run` queued with `why` as its waiting text; logged on the run once per reason."""
        if run.error_message != why:
            first = run.error_message is None
            run.error_message = why
            if first:
                runs.add_event(s, run.id, "log", {"level": "warning", "message": why})
                log.warning("run %s: %s", run.id, why)

    # -- retention ---------------------------------------------------------------------------

    def maybe_prune(self) -> list[str]:
        """prune() when the number of finished runs changed since the last call (cheap otherwise)."""
        with self.registry.session(readonly=True) as s:
            n = s.scalar(select(func.count()).select_from(Run).where(Run.state.in_(runs.TERMINAL)))
        if n == self._finished_seen:
            return []
        self._finished_seen = n
        return self.prune()

    def _kept(self, s: Any, finished: list[Run]) -> set[str]:
        keep_n = int(self.settings.keep_runs)
        kept = {r.id for r in itertools.islice((r for r in finished if produced(r.run_dir)), keep_n)}
        newest: dict[str, str] = {}
        for r in finished:  # newest first: a component's last trained model is never the one pruned
            if r.state == "completed":
                newest.setdefault(r.component, r.id)
        kept |= set(newest.values())
        kept |= set(s.scalars(select(Model.run_id).where(Model.run_id.is_not(None), or_(
            Model.promoted_at.is_not(None), Model.demoted_at.is_not(None)))))
        unfinished = s.scalars(select(Run).where(Run.state.not_in(runs.TERMINAL))).all()
        readers = [r for r in [*finished, *unfinished] if r.id in kept or r.state not in runs.TERMINAL]
        kept |= {str((r.config or {}).get("vqvae_run")) for r in readers if (r.config or {}).get("vqvae_run")}
        return kept

    def prune(self) -> list[str]:
        """Delete the run dirs retention does not keep (see the module doc); the run ids pruned."""
        if int(self.settings.keep_runs) <= 0:
            return []
        root = Path(self.settings.runs_dir).resolve()
        with self.registry.session(readonly=True) as s:
            finished = s.scalars(select(Run).where(Run.state.in_(runs.TERMINAL))
                                 .order_by(Run.finished_at.desc(), Run.created_at.desc())).all()
            kept = self._kept(s, finished)
            doomed = [(r.id, r.component, r.state, Path(r.run_dir)) for r in finished if r.id not in kept]
        pruned = []
        for run_id, component, state, run_dir in doomed:
            if not run_dir.is_dir():
                continue  # gone already (most of them, on a robot with a long history): one stat, no resolve
            target = run_dir.resolve()
            if not target.is_dir() or target.parent != root or (target / PIN_FILE).exists():
                continue  # gone already, not ours to delete (outside $HOPE_HOME/runs), or pinned
            trash = root / f".pruned-{target.name}-{os.urandom(3).hex()}"
            os.rename(target, trash)  # out of sight at once; a crash mid-delete leaves only a dot dir
            shutil.rmtree(trash, ignore_errors=True)
            why = (f"older than the newest keep_runs={self.settings.keep_runs} finished runs that produced a "
                   "checkpoint or metrics, not the newest completed " + component + ", never promoted, not pinned")
            message = (f"run dir {run_dir} of {state} {component} run {run_id} pruned by retention: {why} "
                       f"(pin a run with `touch <run_dir>/{PIN_FILE}`)")
            with self.registry.session() as s:
                runs.add_event(s, run_id, "log", {"level": "info", "message": message, "retention": {
                    "run_dir": str(run_dir), "keep_runs": int(self.settings.keep_runs), "why": why}})
            log.info("retention: %s", message)
            pruned.append(run_id)
        return pruned


def produced(run_dir: str | Path) -> bool:
    """Whether a run left anything worth keeping: a checkpoint or a metrics file."""
    try:
        return bool(list_step_dirs(run_dir)) or (Path(run_dir) / JSONL_NAME).is_file()
    except OSError:
        return False

__all__ = ["PIN_FILE", "DiskGuard", "newest_checkpoint_mb", "produced"]
