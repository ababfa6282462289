"""What a request for a training run may say, checked once for every front door.

`run_trainer.py enqueue` / `sequential` and `POST /api/runs` all turn their input into a
`RunRequest`, then `submit()` writes the queued run. Checking here (not in the worker) means a bad
path or a typo in a field is refused at the door with a message naming the field, instead of
becoming a failed run minutes later. Torch-free: the CLI and the webapp import it.

The run's `config` column holds only TrainConfig overrides the request gave (plus `data`,
`steps` and `vqvae_run`); the worker fills the rest from TrainConfig's defaults and the settings
at the time the job starts.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hope_models.train.contract import COMPONENTS

QUEUE_RE = re.compile(r"^[a-z0-9_-]+$")
DEFAULT_STEPS = 2000
MAX_STEPS = 100_000_000


class RunRequestError(ValueError):
    """A request that cannot become a run; the message names the field."""


def _int(field_name: str, value: Any, *, minimum: int | None = None, maximum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, str)):
        raise RunRequestError(f"{field_name}: expected an integer, got {value!r}")
    try:
        v = int(value)
    except ValueError:
        raise RunRequestError(f"{field_name}: expected an integer, got {value!r}") from None
    if minimum is not None and v < minimum:
        raise RunRequestError(f"{field_name}: {v} must be >= {minimum}")
    if maximum is not None and v > maximum:
        raise RunRequestError(f"{field_name}: {v} must be <= {maximum}")
    return v


def _float(field_name: str, value: Any, *, positive: bool = False, lo: float | None = None,
           hi_exclusive: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise RunRequestError(f"{field_name}: expected a number, got {value!r}")
    try:
        v = float(value)
    except ValueError:
        raise RunRequestError(f"{field_name}: expected a number, got {value!r}") from None
    if not math.isfinite(v):
        raise RunRequestError(f"{field_name}: {value!r} is not a finite number")
    if positive and v <= 0:
        raise RunRequestError(f"{field_name}: {v} must be > 0")
    if lo is not None and v < lo:
        raise RunRequestError(f"{field_name}: {v} must be >= {lo}")
    if hi_exclusive is not None and v >= hi_exclusive:
        raise RunRequestError(f"{field_name}: {v} must be < {hi_exclusive}")
    return v


def _model_config(field_name: str, value: Any) -> dict:
    if not isinstance(value, dict):
        raise RunRequestError(f"{field_name}: expected a JSON object, e.g. {{\"d_model\": 64}}, got {value!r}")
    return dict(value)


# TrainConfig overrides a request may carry: name -> checker. Names are TrainConfig fields
# (tests/test_cli_daemon.py checks that), except vqvae_run (the worker maps it to a run dir).
CONFIG_FIELDS = {
    "seed": lambda n, v: _int(n, v, minimum=0),
    "batch_size": lambda n, v: _int(n, v, minimum=1, maximum=65536),
    "lr": lambda n, v: _float(n, v, positive=True),
    "warmup": lambda n, v: _int(n, v, minimum=0),
    "threads": lambda n, v: _int(n, v, minimum=1, maximum=256),
    "checkpoint_every_steps": lambda n, v: _int(n, v, minimum=1),
    "checkpoint_every_s": lambda n, v: _float(n, v, positive=True),
    "keep_last": lambda n, v: _int(n, v, minimum=1),
    "log_every": lambda n, v: _int(n, v, minimum=1),
    "memory_budget_mb": lambda n, v: _float(n, v, positive=True),
    "imagined_ratio": lambda n, v: _float(n, v, lo=0.0, hi_exclusive=1.0),
    "model_config": _model_config,
}


@dataclass
class RunRequest:
    component: str
    data: str  # absolute path of the dataset (checked to exist)
    steps: int = DEFAULT_STEPS
    queue: str = "pi"
    priority: int = 0
    max_attempts: int = 3
    vqvae_dir: str | None = None  # a trained VQ-VAE checkpoint or run dir (absolute)
    vqvae_run: str | None = None  # or the run id of one (checked at submit)
    overrides: dict[str, Any] = field(default_factory=dict)  # checked CONFIG_FIELDS values

    def config(self) -> dict[str, Any]:
        """The run's `config` column."""
        cfg: dict[str, Any] = {"data": self.data, "steps": self.steps, **self.overrides}
        if self.vqvae_dir:
            cfg["vqvae_dir"] = self.vqvae_dir
        if self.vqvae_run:
            cfg["vqvae_run"] = self.vqvae_run
        return cfg


def resolve_path(field_name: str, value: Any, *, base: Path | None = None,
                 allowed_roots: list[Path] | None = None) -> str:
    """An existing path, made absolute (relative to `base`, default the working directory).
    With `allowed_roots` (the webapp), the path must lie inside one of them."""
    if not isinstance(value, str) or not value.strip():
        raise RunRequestError(f"{field_name}: expected a path, got {value!r}")
    path = Path(value).expanduser()
    if not path.is_absolute():
        path = (base or Path.cwd()) / path
    path = path.resolve()
    if allowed_roots is not None:
        roots = [Path(r).expanduser().resolve() for r in allowed_roots]
        if not any(path == r or r in path.parents for r in roots):
            raise RunRequestError(f"{field_name}: {value} is outside the allowed data roots "
                                  f"({', '.join(str(r) for r in roots)}; add one with data_roots in config.toml)")
    if not path.exists():
        raise RunRequestError(f"{field_name}: {path} does not exist")
    return str(path)


def check_queue(value: Any) -> str:
    if not isinstance(value, str) or not QUEUE_RE.match(value):
        raise RunRequestError(f"queue: {value!r} is not a queue name (lowercase letters, digits, '_' and '-')")
    return value


def check_component(value: Any) -> str:
    if value not in COMPONENTS:
        raise RunRequestError(f"component: {value!r} is not one of {', '.join(COMPONENTS)}")
    return value


def build_request(*, component: Any, data: Any, steps: Any = None, queue: Any = "pi", priority: Any = 0,
                  max_attempts: Any = 3, vqvae_dir: Any = None, vqvae_run: Any = None,
                  overrides: dict[str, Any] | None = None, base: Path | None = None,
                  allowed_roots: list[Path] | None = None) -> RunRequest:
    """Check every field; RunRequestError names the first bad one."""
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(CONFIG_FIELDS))
    if unknown:
        raise RunRequestError(f"unknown config field(s) {', '.join(unknown)} "
                              f"(known: {', '.join(sorted(CONFIG_FIELDS))})")
    checked = {k: CONFIG_FIELDS[k](k, v) for k, v in overrides.items() if v is not None}
    if vqvae_dir is not None and vqvae_run is not None:
        raise RunRequestError("vqvae_dir and vqvae_run: give one, not both")
    if vqvae_run is not None and (not isinstance(vqvae_run, str) or not vqvae_run.strip()):
        raise RunRequestError(f"vqvae_run: expected a run id, got {vqvae_run!r}")
    return RunRequest(
        component=check_component(component),
        data=resolve_path("data", data, base=base, allowed_roots=allowed_roots),
        steps=DEFAULT_STEPS if steps is None else _int("steps", steps, minimum=1, maximum=MAX_STEPS),
        queue=check_queue(queue),
        priority=_int("priority", priority, minimum=-1000, maximum=1000),
        max_attempts=_int("max_attempts", max_attempts, minimum=1, maximum=100),
        vqvae_dir=None if vqvae_dir is None else resolve_path("vqvae_dir", vqvae_dir, base=base,
                                                              allowed_roots=allowed_roots),
        vqvae_run=vqvae_run.strip() if isinstance(vqvae_run, str) else None,
        overrides=checked,
    )


# JSON body of POST /api/runs: these keys, plus any CONFIG_FIELDS key at the top level.
REQUEST_KEYS = {"component", "data", "steps", "queue", "priority", "max_attempts", "vqvae_dir", "vqvae_run"}


def request_from_json(body: Any, *, allowed_roots: list[Path] | None, base: Path | None = None) -> RunRequest:
    if not isinstance(body, dict):
        raise RunRequestError("the request body must be a JSON object")
    unknown = sorted(set(body) - REQUEST_KEYS - set(CONFIG_FIELDS))
    if unknown:
        raise RunRequestError(f"unknown field(s) {', '.join(unknown)} "
                              f"(known: {', '.join(sorted(REQUEST_KEYS | set(CONFIG_FIELDS)))})")
    for required in ("component", "data"):
        if required not in body:
            raise RunRequestError(f"{required}: required")
    main = {k: body[k] for k in REQUEST_KEYS if k in body}
    overrides = {k: body[k] for k in CONFIG_FIELDS if k in body}
    return build_request(**main, overrides=overrides, base=base, allowed_roots=allowed_roots)


def check_vqvae_run(session, run_id: str | None) -> None:
    """A vqvae_run must name a completed vqvae run of the registry: the worker reads its run dir
    when the job starts, and nothing orders two separate runs (a chain does: `sequential`)."""
    from daemon import runs

    if run_id is None:
        return
    try:
        source = runs.get_run(session, run_id)
    except runs.RunError as exc:
        raise RunRequestError(f"vqvae_run: {exc}") from None
    if source.component != "vqvae":
        raise RunRequestError(f"vqvae_run: run {source.id} trains {source.component}, not vqvae")
    if source.state != "completed":
        raise RunRequestError(f"vqvae_run: run {source.id} is {source.state}, not completed; wait for it, or queue "
                              "the components as one chain with `run_trainer.py sequential`")


def submit(session, settings, req: RunRequest, *, sequence_id: str | None = None,
           sequence_index: int | None = None):
    """Write `req` as a queued run (its run dir is $HOPE_HOME/runs/<id>); returns the Run."""
    from daemon import runs
    from daemon.models import new_run_id

    from hope_models.train.sequential import NEEDS_VQVAE  # torch-free

    check_vqvae_run(session, req.vqvae_run)
    if req.component in NEEDS_VQVAE and sequence_id is None and not (req.vqvae_dir or req.vqvae_run):
        # Refused here rather than failing in the worker minutes later.
        raise RunRequestError(f"{req.component} predicts VQ-VAE codes: give vqvae_dir (a trained VQ-VAE) or "
                              "vqvae_run (a completed vqvae run), or queue vqvae first in one chain with "
                              "`run_trainer.py sequential --components vqvae," + req.component + "`")
    run_id = new_run_id()
    run_dir = Path(settings.runs_dir) / run_id
    return runs.create_run(session, component=req.component, config=req.config(), total_steps=req.steps,
                           run_dir=str(run_dir), queue=req.queue, priority=req.priority,
                           max_attempts=req.max_attempts, sequence_id=sequence_id,
                           sequence_index=sequence_index, run_id=run_id)


__all__ = ["CONFIG_FIELDS", "DEFAULT_STEPS", "REQUEST_KEYS", "RunRequest", "RunRequestError", "build_request",
           "check_component", "check_vqvae_run", "check_queue", "request_from_json", "resolve_path", "submit"]
