"""What a request for a training run may say, checked once for every front door.

`run_trainer.py enqueue` / `sequential` and `POST /api/runs` / `/api/training/sequential` all
turn their input into a `RunRequest` (build_request: the fields), then queue_run() /
queue_sequence() run preflight() (what the disk says: a dataset with usable episodes, a
model_config that fits each component and the data, a memory estimate within a budget no larger
than the deployment's) and write the queued run(s). Checking here (not in the worker) means a bad
path, a typo in a field or a model that cannot fit is refused at the door with a message naming
the field, before a run exists, instead of becoming a failed run minutes later. Torch-free: the
CLI and the webapp import it.

The run's `config` column holds only TrainConfig overrides the request gave (plus `data`,
`steps` and `vqvae_run`); the worker fills the rest from TrainConfig's defaults and the settings
at the time the job starts.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hope_models import checkpoints as ckpt
from hope_models.components import COMPONENTS, TOKENIZER
from hope_models.components.chain import tokenizer_missing
from hope_models.numbers import NumberError, as_int, short
from hope_models.paths import PathError, confine_path
from hope_models.train.config import (
    DEFAULT_REQUEST_STEPS,
    REQUEST_FIELDS,
    ConfigValueError,
    TrainConfig,
    check_value,
    over_deployment_budget,
)

if TYPE_CHECKING:
    from hope_models.settings import Settings
    from registry.db import Registry

QUEUE_RE = re.compile(r"^[a-z0-9_-]{1,64}$")
DEFAULT_STEPS = DEFAULT_REQUEST_STEPS
RUN_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # registry.models.new_run_id: r-<time>-<hex>


class RunRequestError(ValueError):
    """A request that cannot become a run; the message names the field."""

    status = 400  # what the API answers with


class QueueFullError(RunRequestError):
    """The queue already holds settings.max_queued_runs runs waiting to start: try again later."""

    status = 429
    exit_code = 75  # sysexits' EX_TEMPFAIL: nothing wrong with the request, retry later
    retry_after_s = 30  # the HTTP answer's Retry-After: a queued run waits minutes, not seconds


def listed(names: list[str], at_most: int = 5) -> str:
    """Names for a message: a few, each bounded, and how many more (never the whole of a big body)."""
    shown = ", ".join(short(n) if len(n) > 40 else n for n in names[:at_most])
    return shown + (f" and {len(names) - at_most} more" if len(names) > at_most else "")


def check_int(field_name: str, value: Any, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer field of a request, by the one rule for numbers (hope_models/numbers.py)."""
    try:
        return as_int(field_name, value, minimum=minimum, maximum=maximum)
    except NumberError as exc:
        raise RunRequestError(str(exc)) from None


# The TrainConfig options a request may carry (train/config.py says which and how each is
# checked), except vqvae_dir, which a request names on its own: a path confined to the data
# roots, or vqvae_run.
CONFIG_FIELDS = tuple(name for name in REQUEST_FIELDS if name != "vqvae_dir")


def check_config_field(name: str, value: Any) -> Any:
    try:
        return check_value(name, value)
    except ConfigValueError as exc:
        raise RunRequestError(str(exc)) from None


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
    With `allowed_roots` (the webapp), the path must lie inside one of them (hope_models/paths.py:
    the one confinement rule, which the promotion gate applies to checkpoint configs too)."""
    try:
        return str(confine_path(field_name, value, base=base, allowed_roots=allowed_roots))
    except PathError as exc:
        raise RunRequestError(str(exc)) from None


def check_queue(value: Any) -> str:
    if not isinstance(value, str) or not QUEUE_RE.match(value):
        raise RunRequestError(f"queue: {short(value)} is not a queue name (1 to 64 lowercase letters, digits, "
                              "'_' and '-')")
    return value


def check_component(value: Any) -> str:
    if value not in COMPONENTS:
        raise RunRequestError(f"component: {short(value)} is not one of {', '.join(COMPONENTS)}")
    return value


def build_request(*, component: Any, data: Any, steps: Any = None, queue: Any = "pi", priority: Any = 0,
                  max_attempts: Any = 3, vqvae_dir: Any = None, vqvae_run: Any = None,
                  overrides: dict[str, Any] | None = None, base: Path | None = None,
                  allowed_roots: list[Path] | None = None) -> RunRequest:
    """Check every field; RunRequestError names the first bad one."""
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(CONFIG_FIELDS))
    if unknown:
        raise RunRequestError(f"unknown config field(s) {listed(unknown)} "
                              f"(known: {', '.join(sorted(CONFIG_FIELDS))})")
    checked = {k: check_config_field(k, v) for k, v in overrides.items() if v is not None}
    if vqvae_dir is not None and vqvae_run is not None:
        raise RunRequestError("vqvae_dir and vqvae_run: give one, not both")
    if vqvae_run is not None and (not isinstance(vqvae_run, str) or not RUN_ID_RE.fullmatch(vqvae_run.strip())):
        raise RunRequestError(f"vqvae_run: expected a run id, got {short(vqvae_run)}")
    return RunRequest(
        component=check_component(component),
        data=resolve_path("data", data, base=base, allowed_roots=allowed_roots),
        steps=DEFAULT_STEPS if steps is None else check_config_field("steps", steps),
        queue=check_queue(queue),
        priority=check_int("priority", priority, minimum=-1000, maximum=1000),
        max_attempts=check_int("max_attempts", max_attempts, minimum=1, maximum=100),
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
        raise RunRequestError(f"unknown field(s) {listed(unknown)} "
                              f"(known: {', '.join(sorted(REQUEST_KEYS | set(CONFIG_FIELDS)))})")
    for required in ("component", "data"):
        if required not in body:
            raise RunRequestError(f"{required}: required")
    main = {k: body[k] for k in REQUEST_KEYS if k in body}
    overrides = {k: body[k] for k in CONFIG_FIELDS if k in body}
    return build_request(**main, overrides=overrides, base=base, allowed_roots=allowed_roots)


def check_vqvae_run(session, run_id: str | None) -> str | None:
    """A vqvae_run must name a completed vqvae run of the registry: the worker reads its run dir
    when the job starts, and nothing orders two separate runs (a chain does: `sequential`).
    Returns that run dir."""
    from registry import runs  # lazy: loads sqlalchemy

    if run_id is None:
        return None
    try:
        source = runs.get_run(session, run_id)
    except runs.RunError as exc:
        raise RunRequestError(f"vqvae_run: {exc}") from None
    if source.component != TOKENIZER:
        raise RunRequestError(f"vqvae_run: run {source.id} trains {source.component}, not {TOKENIZER}")
    if source.state != "completed":
        raise RunRequestError(f"vqvae_run: run {source.id} is {source.state}, not completed; wait for it, or queue "
                              "the components as one chain with `run_trainer.py sequential`")
    return source.run_dir


def _check_vqvae_source(req: RunRequest, components: list[str], chain: bool) -> None:
    """Each member that predicts VQ-VAE codes has a VQ-VAE: given, or trained earlier in the chain."""
    name = tokenizer_missing(components, bool(req.vqvae_dir or req.vqvae_run))
    if name is None:
        return
    if chain:
        raise RunRequestError(f"components: {name} needs a trained VQ-VAE: put {TOKENIZER} before it in the chain, "
                              "or give vqvae_dir / vqvae_run")
    raise RunRequestError(f"{name} predicts VQ-VAE codes: give vqvae_dir (a trained VQ-VAE) or vqvae_run (a "
                          f"completed {TOKENIZER} run), or queue {TOKENIZER} first in one chain with "
                          f"`run_trainer.py sequential --components {TOKENIZER},{name}`")


def _model_config_error(exc: Exception, chain: bool) -> RunRequestError:
    text = str(exc) if str(exc).startswith("model_config") else f"model_config: {exc}"
    return RunRequestError(text + (" (the members of a chain share one model_config)" if chain else ""))


def preflight(settings: Settings, req: RunRequest, components: list[str] | None = None, *,
              vqvae_run_dir: str | None = None) -> list:
    """What the disk says about a request, before a run exists: the memory budget it asks for is
    within the deployment's, `data` holds usable episodes, the model_config fits every component
    (a chain's `components`, in order) and the data, and each model's estimated memory fits the
    budget (estimate.estimate_from_config: no model is built, torch is not imported). Returns
    the estimates (none when the dataset's files are too large to probe here: the job checks
    again before it builds anything). It reads files: call it outside a write transaction."""
    from hope_models.components.resolve import check_keys, read_vqvae_config, resolve  # lazy: loads numpy
    from hope_models.data.dataset_spec import probe_dataset_spec  # lazy: loads mcap, numpy
    from hope_models.data.features import FeatureSpecError  # lazy: loads numpy
    from hope_models.train.estimate import MemoryBudgetError, check_fits, estimate_from_config  # lazy: loads psutil

    names = components or [req.component]
    chain = components is not None
    budget = req.overrides.get("memory_budget_mb", float(settings.memory_budget_mb))
    too_much = over_deployment_budget(budget, settings)
    if too_much:
        raise RunRequestError(too_much)
    model_config = req.overrides.get("model_config", {})
    for name in names:
        try:
            check_keys(name, model_config)
        except ValueError as exc:
            raise _model_config_error(exc, chain) from None
    _check_vqvae_source(req, names, chain)
    try:
        spec = probe_dataset_spec(req.data)
    except FeatureSpecError as exc:
        raise RunRequestError(f"data: {exc}") from None
    vq = None  # the VQ-VAE a member reads codes from: given, then the chain's own once it is trained
    vq_source = req.vqvae_dir or vqvae_run_dir
    if vq_source:
        what = "vqvae_dir" if req.vqvae_dir else "vqvae_run"
        try:
            vq = read_vqvae_config(ckpt.resolve_checkpoint_dir(vq_source))
        except (ckpt.CheckpointError, ValueError) as exc:
            raise RunRequestError(f"{what}: {exc}") from None
    if spec is None:
        return []
    defaults: dict[str, Any] = {f.name: f.default for f in fields(TrainConfig)}  # these two have defaults
    batch_size = req.overrides.get("batch_size", defaults["batch_size"])
    estimates = []
    for name in names:
        try:
            resolved = resolve(name, spec, model_config, vq)  # ignored by a component that reads none
            est = estimate_from_config(resolved, batch_size, spec.obs_dim, spec.act_dim)
            estimates.append(check_fits(est, budget, defaults["memory_soft_fraction"]))
        except MemoryBudgetError as exc:
            raise RunRequestError(str(exc)) from None
        except ValueError as exc:
            raise _model_config_error(exc, chain) from None
        if name == TOKENIZER:
            vq = resolved.cfg  # the chain's later members read this one's codes
    return estimates


def queue_run(registry: Registry, settings: Settings, req: RunRequest, show=None):
    """preflight() then submit(): the one way a front door queues a run. Returns
    show(session, run) (default: Run.to_json_obj()), made while the run's session is open."""
    with registry.session(readonly=True) as s:
        vqvae_run_dir = check_vqvae_run(s, req.vqvae_run)
    preflight(settings, req, vqvae_run_dir=vqvae_run_dir)
    with registry.session() as s:
        check_queue_room(s, settings, req.queue)
        run = submit(s, settings, req)
        return show(s, run) if show is not None else run.to_json_obj()


def queue_sequence(registry: Registry, settings: Settings, names: list[str], req: RunRequest,
                   show=None) -> tuple[str, list]:
    """preflight() of every member, then registry.sequences.create_sequence: the chain's sequence id
    and show(session, run) of each member (default: Run.to_json_obj())."""
    from registry.sequences import create_sequence  # lazy: loads sqlalchemy

    with registry.session(readonly=True) as s:
        vqvae_run_dir = check_vqvae_run(s, req.vqvae_run)
    preflight(settings, req, list(names), vqvae_run_dir=vqvae_run_dir)
    with registry.session() as s:
        check_vqvae_run(s, req.vqvae_run)
        check_queue_room(s, settings, req.queue, len(names))
        members = create_sequence(s, names, req.config(), total_steps=req.steps, runs_dir=settings.runs_dir,
                                  queue=req.queue, priority=req.priority, max_attempts=req.max_attempts)
        assert members[0].sequence_id is not None  # create_sequence gives every member the chain's id
        return members[0].sequence_id, [show(s, r) if show is not None else r.to_json_obj() for r in members]


def check_queue_room(session, settings: Settings, queue: str, adding: int = 1) -> None:
    """QueueFullError unless `queue` has room for `adding` more runs waiting to start (queued or
    starting) under settings.max_queued_runs. Called in the write transaction that creates them
    (BEGIN IMMEDIATE), so two requests at once cannot both take the last place. The daemon's own
    auto chain does not come through here: it queues only on a queue with nothing waiting."""
    from sqlalchemy import func, select  # lazy: loads sqlalchemy

    from registry.models import Run  # lazy: loads sqlalchemy

    cap = int(settings.max_queued_runs)
    waiting = session.scalar(select(func.count()).select_from(Run).where(
        Run.queue == queue, Run.state.in_(("queued", "starting"))))
    if waiting + adding > cap:
        chain = f"; this chain adds {adding}" if adding > 1 else ""
        raise QueueFullError(f"queue {queue!r} is full: {waiting} runs are waiting to start (queued or starting), "
                             f"at most max_queued_runs={cap}{chain}; try again when some have started, cancel "
                             "some (`hope-trainer status`), or raise max_queued_runs")


def submit(session, settings: Settings, req: RunRequest, *, sequence_id: str | None = None,
           sequence_index: int | None = None):
    """Write `req` as a queued run (its run dir is $HOPE_HOME/runs/<id>); returns the Run."""
    from registry import runs  # lazy: loads sqlalchemy
    from registry.models import new_run_id  # lazy: loads sqlalchemy

    check_vqvae_run(session, req.vqvae_run)
    if sequence_id is None:  # refused here rather than failing in the worker minutes later
        _check_vqvae_source(req, [req.component], chain=False)
    run_id = new_run_id()
    run_dir = Path(settings.runs_dir) / run_id
    return runs.create_run(session, component=req.component, config=req.config(), total_steps=req.steps,
                           run_dir=str(run_dir), queue=req.queue, priority=req.priority,
                           max_attempts=req.max_attempts, sequence_id=sequence_id,
                           sequence_index=sequence_index, run_id=run_id)


__all__ = ["CONFIG_FIELDS", "DEFAULT_STEPS", "REQUEST_KEYS", "QueueFullError", "RunRequest", "RunRequestError",
           "build_request", "check_component", "check_int", "check_queue", "check_queue_room", "check_vqvae_run",
           "listed", "preflight", "queue_run", "queue_sequence", "request_from_json", "resolve_path", "submit"]
