"""The training configuration, spelled once: `TrainConfig`, one typed field per option.

Each field's metadata (an `Option`) says its kind, bounds, help text, flag, whether it defines
the math (a resumed run must repeat it) and at which doors it may be set. Everything else is
derived from here, so an option cannot drift between doors:

    TrainConfig  --add_flags(parser, "train")-->    `train` flags and --help (hope_models/cli/train.py)
                 --add_flags(parser, "request")-->  `enqueue` / `sequential` flags (daemon/cli/enqueue.py)
                 --REQUEST_FIELDS, check_value-->   POST /api/runs, /api/training/sequential (registry/run_request.py)
                 --check_value-->                   the worker's check of a run's stored config (workers/job.py)
                 --check()-->                       the trainer's check before anything is built (train/loop.py)
                 --identity()-->                    the resume comparison (train/loop.py)

Numbers follow hope_models/numbers.py at every door. Deployment defaults (the memory budget,
the thermal sources and limits) come from `Settings` only: a TrainConfig built without them
takes `Settings`' own defaults, and the commands fill them from the loaded settings.
Torch-free: the daemon, the webapp and the CLI parsers import it.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, Callable

from hope_models.numbers import NumberError, as_float, as_int, from_text, int_from_text, short
from hope_models.settings import Settings

MAX_STEPS = 100_000_000
DEFAULT_REQUEST_STEPS = 2000  # a run request that does not say how many steps
_DEPLOYMENT = Settings(home=None)  # type: ignore[arg-type]  # its defaults only: nothing is read or made


class ConfigValueError(ValueError):
    """A value an option cannot take; the message names the option."""


@dataclass(frozen=True)
class Option:
    """How one TrainConfig field is read, checked and shown."""
    kind: str  # "int" | "float" | "path" | "object" | "name"
    help: str
    minimum: float | None = None  # inclusive bounds
    maximum: float | None = None
    above: float | None = None  # exclusive bounds
    below: float | None = None
    math: bool = False  # defines the math of the run: a resume in the same run dir must repeat it
    doors: tuple[str, ...] = ("train", "request")  # "train": the train command; "request": enqueue/sequential/API
    flag: str | None = None  # the command-line flag, if not --<name-with-dashes>
    metavar: str | None = None

    def range_text(self) -> str:
        """The allowed range as a reader writes it: "1..65536", "[0, 1)", ">= 0"."""
        lo, hi = self.minimum if self.minimum is not None else self.above, \
            self.maximum if self.maximum is not None else self.below
        if lo is None or hi is None:
            return self.bounds_text()
        if self.minimum is not None and self.maximum is not None:
            return f"{lo:g}..{hi:g}"
        return f"{'[' if self.minimum is not None else '('}{lo:g}, {hi:g}{']' if self.maximum is not None else ')'}"

    def bounds_text(self) -> str:
        parts = []
        if self.minimum is not None:
            parts.append(f">= {self.minimum:g}")
        if self.above is not None:
            parts.append(f"> {self.above:g}")
        if self.maximum is not None:
            parts.append(f"<= {self.maximum:g}")
        if self.below is not None:
            parts.append(f"< {self.below:g}")
        return ", ".join(parts)


def option(default: Any = MISSING, *, factory: Callable[[], Any] | None = None, **meta: Any) -> Any:
    opt = Option(**meta)
    if factory is not None:
        return field(default_factory=factory, metadata={"option": opt})
    return field(default=default, metadata={"option": opt})


def _single_thread() -> int:
    # One: the seed models are small, so intra-op threads buy little even on idle cores, and on
    # shared cores (the Pi runs the robot's services beside the job) they stall each other. Measured
    # on the 2-core dev machine under load: mid_loop 200 steps took 54 s with 2 threads, 9.8 s with 1
    # (the same weights). `--threads N` for a big model on a quiet machine.
    return 1


@dataclass
class TrainConfig:
    component: str = option(kind="name", help="the component to train", math=True, doors=())
    data: str = option(kind="path", help="RLDS dataset dir, episode dir or episode file", metavar="PATH",
                       doors=())
    run_dir: str = option(kind="path", help="checkpoints and metrics go here; re-running with the same dir resumes",
                          metavar="DIR", doors=("train",))
    steps: int = option(kind="int", minimum=1, maximum=MAX_STEPS, doors=(),
                        help="total optimizer steps of the job (a re-run continues up to this)")
    seed: int = option(0, kind="int", minimum=0, maximum=2**32 - 1, math=True,  # what numpy's seed takes
                       help="seeds the init, the batches and every random draw")
    batch_size: int = option(64, kind="int", minimum=1, maximum=65536, math=True, help="windows per batch")
    lr: float = option(1e-3, kind="float", above=0, math=True, help="peak learning rate")
    warmup: int = option(100, kind="int", minimum=0, maximum=MAX_STEPS, math=True,
                         help="linear warmup steps, at most a tenth of --steps, then cosine decay")
    min_lr_ratio: float = option(0.1, kind="float", minimum=0, maximum=1, math=True,
                                 help="the cosine ends at lr x this")
    weight_decay: float = option(0.01, kind="float", minimum=0, math=True,
                                 help="AdamW weight decay, on matrices only")
    grad_clip: float = option(1.0, kind="float", minimum=0, math=True,
                              help="max global gradient norm; 0 disables clipping")
    threads: int = option(kind="int", minimum=1, maximum=256, factory=_single_thread,
                          help="torch threads (small models on shared cores: more rarely help)")
    checkpoint_every_steps: int = option(500, kind="int", minimum=1, maximum=MAX_STEPS, flag="--checkpoint-every",
                                         metavar="N", help="checkpoint every N steps")
    checkpoint_every_s: float = option(300.0, kind="float", above=0, flag="--checkpoint-seconds", metavar="T",
                                       help="and every T seconds")
    keep_last: int = option(3, kind="int", minimum=1, maximum=1000, flag="--keep", metavar="K",
                            help="keep the last K checkpoints")
    log_every: int = option(10, kind="int", minimum=1, maximum=MAX_STEPS, metavar="N",
                            help="metrics every N steps")
    memory_budget_mb: float = option(float(_DEPLOYMENT.memory_budget_mb), kind="float", above=0,
                                     help="the job's memory budget in MB (default: the settings' memory_budget_mb, "
                                          "HOPE_MEMORY_BUDGET_MB; a run may ask for less, never more)")
    memory_soft_fraction: float = option(0.9, kind="float", above=0, maximum=1, doors=(),
                                         help="checkpoint and pause at this fraction of the budget")
    thermal_zone: str | None = option(_DEPLOYMENT.thermal_zone_path, kind="path", doors=("train",), metavar="PATH",
                                      help="thermal zone file to watch (default: the settings' thermal_zone_path)")
    vcgencmd: str | None = option(_DEPLOYMENT.vcgencmd_path, kind="path", doors=(),
                                  help="the firmware's vcgencmd, for throttling flags")
    thermal_soft_c: float = option(_DEPLOYMENT.thermal_soft_c, kind="float", doors=(), help="slow down above")
    thermal_hard_c: float = option(_DEPLOYMENT.thermal_hard_c, kind="float", doors=(), help="checkpoint and wait above")
    thermal_resume_c: float = option(_DEPLOYMENT.thermal_resume_c, kind="float", doors=(), help="go on below")
    vqvae_dir: str | None = option(None, kind="path", flag="--vqvae", metavar="DIR",
                                   help="a trained VQ-VAE (checkpoint dir or run dir) whose codes fast_loop/mid_loop "
                                        "read")
    cache_dir: str | None = option(None, kind="path", doors=("train",), metavar="DIR",
                                   help="dataset cache root (default: $HOPE_HOME/cache)")
    spec_path: str | None = option(None, kind="path", doors=("train",), flag="--spec", metavar="FILE",
                                   help="feature spec JSON overriding the inferred one")
    imagined_ratio: float = option(0.0, kind="float", minimum=0, below=1, math=True,
                                   help="share of imagined episodes in a batch, in [0, 1)")
    val_fraction: float = option(0.1, kind="float", minimum=0, below=1, math=True,
                                 help="share of episodes held out for validation, in [0, 1)")
    model_config: dict[str, Any] = option(kind="object", factory=dict, math=True, metavar="JSON",
                                          help="model config overrides, e.g. '{\"d_model\": 64}'")
    control_interval_s: float = option(0.2, kind="float", minimum=0, doors=(),
                                       help="how often the control hook and the memory guard run (0: between every step)")
    val_batches: int = option(8, kind="int", minimum=1, maximum=1000, doors=(),
                              help="validation batches evaluated at the end of a completed job (and by the gate)")

    def to_json_obj(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def identity(self) -> dict[str, Any]:
        """The fields that define the math: a re-run in the same run dir must repeat them."""
        return {name: getattr(self, name) for name in IDENTITY}

    def check(self) -> None:
        """Every field against its option, each stored as checked (64.0 becomes 64);
        ConfigValueError names the first bad one."""
        for name, opt in OPTIONS.items():
            value = getattr(self, name)
            if name == "component" or (value is None and opt.kind == "path" and name not in ("data", "run_dir")):
                continue  # the component is the contract's to check; None: no such path (no VQ-VAE, no zone)
            try:
                setattr(self, name, check_value(name, value))
            except ConfigValueError as exc:
                rule = getattr(exc.__cause__ or exc.__context__, "rule", None)
                raise ConfigValueError(f"{name}={short(value)} {rule}" if rule else str(exc)) from None


_FIELDS = {f.name: f for f in fields(TrainConfig)}
OPTIONS: dict[str, Option] = {name: f.metadata["option"] for name, f in _FIELDS.items()}
IDENTITY = tuple(name for name, opt in OPTIONS.items() if opt.math)
REQUEST_FIELDS = tuple(name for name, opt in OPTIONS.items() if "request" in opt.doors)
TRAIN_FLAGS = tuple(name for name, opt in OPTIONS.items() if "train" in opt.doors)


def check_value(name: str, value: Any) -> Any:
    """`value` for option `name`, by the one rule for numbers (hope_models/numbers.py) and the
    option's bounds. Returns the value as the config holds it (an int for an int option)."""
    opt = OPTIONS[name]
    try:
        if opt.kind == "int":
            lo = None if opt.minimum is None else int(opt.minimum)
            hi = None if opt.maximum is None else int(opt.maximum)
            return as_int(name, value, minimum=lo, maximum=hi)
        if opt.kind == "float":
            return as_float(name, value, minimum=opt.minimum, maximum=opt.maximum, above=opt.above, below=opt.below)
    except NumberError as exc:
        raise ConfigValueError(str(exc)) from exc
    if opt.kind == "object":
        if not isinstance(value, dict):
            raise ConfigValueError(f"{name} must be a JSON object, e.g. {{\"d_model\": 64}}, got {short(value)}")
        return dict(value)
    if opt.kind in ("path", "name"):
        if not isinstance(value, str) or not value:
            raise ConfigValueError(f"{name}: expected a path, got {short(value)}")
        return value
    raise AssertionError(f"option {name}: unknown kind {opt.kind}")


def flag_of(name: str) -> str:
    return OPTIONS[name].flag or "--" + name.replace("_", "-")


def dest_of(name: str) -> str:
    """The argparse attribute of option `name` (its flag without dashes)."""
    return flag_of(name)[2:].replace("-", "_")


def _text_type(name: str) -> Callable[[str], Any]:
    """argparse `type=`: the flag's text read by the one rule, then the option's check."""
    opt = OPTIONS[name]

    def parse(text: str) -> Any:
        try:
            if opt.kind == "int":
                return check_value(name, int_from_text(name, text))
            if opt.kind == "float":
                return check_value(name, from_text(name, text))
            if opt.kind == "object":
                try:
                    obj = json.loads(text)
                except json.JSONDecodeError as exc:
                    raise ConfigValueError(f"{name}: not valid JSON: {exc}") from None
                return check_value(name, obj)
            return check_value(name, text)
        except (ConfigValueError, NumberError) as exc:
            reason = str(exc).split(": ", 1)[1] if ": " in str(exc) else str(exc)
            raise argparse.ArgumentTypeError(reason) from None

    parse.__name__ = OPTIONS[name].kind  # argparse names the type in "invalid <type> value"
    return parse


def add_flag(parser: Any, name: str, **overrides: Any) -> None:
    """The flag of option `name` with its help and check; `overrides` are argparse keywords
    (required=True, default=..., help=...)."""
    opt = OPTIONS[name]
    kw = {"dest": dest_of(name), "type": _text_type(name), "default": None, "metavar": opt.metavar,
          "help": opt.help + _default_text(name), **overrides}
    parser.add_argument(flag_of(name), **kw)


def _default_text(name: str) -> str:
    """" (default X)" from the field itself, so a help text never restates a default."""
    f = _FIELDS[name]
    default = f.default_factory() if f.default_factory is not MISSING else f.default
    if "default" in OPTIONS[name].help or default is MISSING or default is None or isinstance(default, dict):
        return ""
    return f" (default {default:g})" if isinstance(default, float) else f" (default {default})"


def add_flags(parser: argparse.ArgumentParser, door: str, *, skip: tuple[str, ...] = ()) -> None:
    """The flags of every option open at `door` ("train" or "request"), with their help.
    Each defaults to None (not given): the caller leaves those to TrainConfig and the settings."""
    for name, opt in OPTIONS.items():
        if door in opt.doors and name not in skip:
            add_flag(parser, name)


def values_from_args(args: argparse.Namespace, door: str) -> dict[str, Any]:
    """{option: value} of the flags given at `door` (the ones left unset are absent)."""
    out = {}
    for name, opt in OPTIONS.items():
        if door in opt.doors:
            value = getattr(args, dest_of(name), None)
            if value is not None:
                out[name] = value
    return out


def over_deployment_budget(budget: float, settings: Settings, whose: str = "this deployment's") -> str | None:
    """Why a run asking for `budget` MB may not have it (a run may ask for less than the
    deployment's memory_budget_mb, never for more), or None when it may."""
    limit = float(settings.memory_budget_mb)
    if budget <= limit:
        return None
    return (f"memory_budget_mb: {budget:g} MB is more than {whose} budget of {settings.memory_budget_mb} MB "
            "(HOPE_MEMORY_BUDGET_MB or memory_budget_mb in config.toml); a run may ask for less, never for more")


def deployment_values(settings: Settings) -> dict[str, Any]:
    """The fields the deployment decides, from loaded settings."""
    return {"memory_budget_mb": float(settings.memory_budget_mb), "thermal_zone": settings.thermal_zone_path,
            "vcgencmd": settings.vcgencmd_path, "thermal_soft_c": settings.thermal_soft_c,
            "thermal_hard_c": settings.thermal_hard_c, "thermal_resume_c": settings.thermal_resume_c,
            "cache_dir": str(settings.cache_dir)}


__all__ = ["ConfigValueError", "DEFAULT_REQUEST_STEPS", "IDENTITY", "MAX_STEPS", "OPTIONS", "Option",
           "REQUEST_FIELDS", "TRAIN_FLAGS", "TrainConfig", "add_flag", "add_flags", "check_value", "deployment_values",
           "dest_of", "flag_of", "over_deployment_budget", "values_from_args"]
