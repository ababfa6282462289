"""The one training loop for every HOPE component: deterministic, resumable, guarded, logged.

    result = train(TrainConfig(component="fast_loop", data="ds/", run_dir="runs/r1", steps=2000))

What makes a re-run after a kill end with the same weights, bit for bit, as a run never stopped:
- the math depends only on (config, step): batch s is AnchorSampler.batch(s - 1), a pure function
  of (seed, s); the learning rate is lr_at(s), a pure function of the step (no scheduler object);
- a checkpoint holds everything else the next step reads: weights and buffers, AdamW's moments and
  step counts, torch's (and numpy's and python's) global RNG state, the sampler cursor;
- nothing that depends on wall time (checkpoints every T seconds, guards, throttling, metrics)
  touches the RNG or the tensors, and checkpoint writes only read them;
- threads are fixed and torch.use_deterministic_algorithms(True).
A resumed job rebuilds the component (whose init consumes the RNG), then loads all of the above
over it, so the init draws do not matter.

Between steps: the control hook (pause / cancel / throttle, polled every control_interval_s), the
memory guard (checkpoint + "paused_memory" at the soft limit), the thermal governor (sleep a
fraction of the step when warm; checkpoint and wait when hot). A NaN/Inf loss or gradient stops
the job as "failed" before the optimizer step, so the last checkpoint on disk stays the last good one.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import random
import time
import traceback
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Callable

from hope_models.durable import atomic_write
from hope_models.train import checkpoint as ckpt
from hope_models.train.contract import COMPONENTS, OUTCOME_EXIT_CODES, Control, ControlCommand, NoControl
from hope_models.train.run_dir_lock import RunDirBusy, RunDirLock

Emit = Callable[[str, dict], None]
LOADER_CHUNK = 8  # window batches built per vectorised call (the pre-flight estimate counts them)


class TrainSetupError(ValueError):
    """The job cannot start: bad data, unknown component, a run dir that holds another job, or a
    configuration the memory budget cannot fit. The message names the parameter or path."""


def _default_threads() -> int:
    # One: the seed models are small, so intra-op threads buy little even on idle cores, and on
    # shared cores (the Pi runs the robot's services beside the job) they stall each other. Measured
    # on the 2-core dev machine under load: mid_loop 200 steps took 54 s with 2 threads, 9.8 s with 1
    # (the same weights). `--threads N` for a big model on a quiet machine.
    return 1


@dataclass
class TrainConfig:
    component: str  # one of contract.COMPONENTS
    data: str  # an RLDS dataset dir, episode dir or episode file
    run_dir: str  # checkpoints/, metrics.jsonl, metrics.mcap, result.json live here
    steps: int  # total optimizer steps of the job (a re-run continues up to this)
    seed: int = 0
    batch_size: int = 64
    lr: float = 1e-3
    warmup: int = 100  # linear warmup steps (at most a tenth of `steps`), then cosine decay
    min_lr_ratio: float = 0.1  # the cosine ends at lr x this
    weight_decay: float = 0.01  # AdamW, on matrices only (not biases, norms, embeddings' 1-D params)
    grad_clip: float = 1.0  # max global grad norm; 0 disables clipping (the norm is still logged)
    threads: int = field(default_factory=_default_threads)
    checkpoint_every_steps: int = 500
    checkpoint_every_s: float = 300.0
    keep_last: int = 3
    log_every: int = 10
    memory_budget_mb: float = 3072.0
    memory_soft_fraction: float = 0.9
    thermal_zone: str | None = "/sys/class/thermal/thermal_zone0/temp"
    vcgencmd: str | None = "vcgencmd"
    thermal_soft_c: float = 75.0
    thermal_hard_c: float = 82.0
    thermal_resume_c: float = 70.0
    vqvae_dir: str | None = None  # a VQ-VAE checkpoint (or run) dir; mid_loop needs one
    cache_dir: str | None = None  # dataset cache root (default: $HOPE_HOME/cache)
    spec_path: str | None = None  # feature spec override JSON
    imagined_ratio: float = 0.0
    val_fraction: float = 0.1
    model_config: dict[str, Any] = field(default_factory=dict)
    control_interval_s: float = 0.2  # how often Control.poll and the memory guard run
    val_batches: int = 4  # validation batches evaluated at the end of a completed job

    # Fields that define the math of the run: a re-run in the same run dir must repeat them.
    IDENTITY = ("component", "seed", "batch_size", "lr", "warmup", "min_lr_ratio", "weight_decay", "grad_clip",
                "imagined_ratio", "val_fraction", "model_config")

    def to_json_obj(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def identity(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.IDENTITY}


@dataclass
class TrainResult:
    outcome: str  # a key of contract.OUTCOME_EXIT_CODES
    component: str
    steps: int  # optimizer steps done (all attempts together)
    total_steps: int
    first_loss: float | None
    final_loss: float | None
    checkpoint: str | None  # the newest good checkpoint dir
    peak_rss_mb: float
    resumed_from: int | None  # the step this attempt resumed at, None for a fresh start
    summary: dict[str, Any] = field(default_factory=dict)  # convergence summary (+ "val" metrics)
    message: str = ""
    elapsed_s: float = 0.0  # training wall time of all attempts

    @property
    def exit_code(self) -> int:
        return OUTCOME_EXIT_CODES[self.outcome]

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)

    def cli_json(self) -> dict[str, Any]:
        keys = ("component", "steps", "first_loss", "final_loss", "checkpoint", "peak_rss_mb", "resumed_from",
                "outcome")
        out = {k: getattr(self, k) for k in keys}
        out["peak_rss_mb"] = round(self.peak_rss_mb, 1)
        if self.message:
            out["message"] = self.message
        return out


# -- pure pieces ----------------------------------------------------------------------------------

def lr_at(step: int, cfg: TrainConfig) -> float:
    """Learning rate of optimizer step `step` (1-based): linear warmup, then cosine to min_lr_ratio."""
    total = cfg.steps
    warmup = min(cfg.warmup, max(1, total // 10))
    if step <= warmup:
        return cfg.lr * step / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1.0 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress)))


class LossHistory:
    """The losses the convergence summary needs, small enough to ride in every checkpoint: the
    first `head` steps, the last `tail` steps, and one point every `stride` steps in between (the
    stride doubles whenever the curve passes max_points, so a week-long job stays a few KB)."""

    def __init__(self, stride: int, head: int = 10, tail: int = 10, max_points: int = 2048):
        self.stride, self.head, self.tail, self.max_points = max(1, stride), head, tail, max_points
        self.points: list[tuple[int, float]] = []

    def add(self, step: int, loss: float) -> None:
        self.points.append((step, loss))
        if len(self.points) > self.tail:
            s = self.points[-self.tail - 1][0]
            if s > self.head and s % self.stride:
                del self.points[-self.tail - 1]
        if len(self.points) > self.max_points:
            self.stride *= 2
            keep_from = len(self.points) - self.tail
            self.points = [p for i, p in enumerate(self.points)
                           if p[0] <= self.head or p[0] % self.stride == 0 or i >= keep_from]

    def first(self) -> float | None:
        return self.points[0][1] if self.points else None

    def last(self) -> float | None:
        return self.points[-1][1] if self.points else None

    def to_json_obj(self) -> dict[str, Any]:
        return {"stride": self.stride, "points": [[s, v] for s, v in self.points]}

    @classmethod
    def from_json_obj(cls, obj: dict[str, Any]) -> "LossHistory":
        h = cls(int(obj["stride"]))
        h.points = [(int(s), float(v)) for s, v in obj["points"]]
        return h


def dataset_dir_for(data: str | os.PathLike, cache_root: Path) -> Path:
    """The dir load_or_build reads. A single episode file (JSON, JSONL, TFRecord, MCAP) gets a dir
    of its own holding a symlink to it, so the cache (which walks dirs) reads it through discover."""
    p = Path(data).expanduser()
    if not p.exists():
        raise TrainSetupError(f"--data {data}: no such file or directory")
    if p.is_dir():
        return p
    p = p.resolve()
    link_dir = cache_root / "sources" / hashlib.sha256(str(p).encode("utf-8")).hexdigest()[:16]
    link = link_dir / p.name
    link_dir.mkdir(parents=True, exist_ok=True)
    if not (link.is_symlink() and Path(os.readlink(link)) == p):
        # a symlink, not file data: durable.atomic_write does not apply; symlink + rename is atomic
        tmp = link_dir / f".{p.name}.{os.getpid()}.tmp"
        tmp.unlink(missing_ok=True)
        os.symlink(p, tmp)
        os.replace(tmp, link)
    return link_dir


def _check_config(cfg: TrainConfig, custom_component: bool) -> None:
    if not custom_component and cfg.component not in COMPONENTS:
        raise TrainSetupError(f"--component {cfg.component!r} is not one of {', '.join(COMPONENTS)}")
    for name in ("steps", "batch_size", "threads", "checkpoint_every_steps", "keep_last", "log_every"):
        v = getattr(cfg, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise TrainSetupError(f"{name}={v!r} must be a positive integer")
    if isinstance(cfg.seed, bool) or not isinstance(cfg.seed, int) or cfg.seed < 0:
        raise TrainSetupError(f"seed={cfg.seed!r} must be a non-negative integer")
    for name in ("lr", "checkpoint_every_s", "memory_budget_mb"):
        v = getattr(cfg, name)
        if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise TrainSetupError(f"{name}={v!r} must be a positive number")
    if not 0 <= cfg.min_lr_ratio <= 1:
        raise TrainSetupError(f"min_lr_ratio={cfg.min_lr_ratio!r} must be within [0, 1]")
    if not 0 <= cfg.imagined_ratio <= 1:
        raise TrainSetupError(f"imagined_ratio={cfg.imagined_ratio!r} must be within [0, 1]")
    if not 0 <= cfg.val_fraction < 1:
        raise TrainSetupError(f"val_fraction={cfg.val_fraction!r} must be within [0, 1)")
    if cfg.warmup < 0 or cfg.weight_decay < 0 or cfg.grad_clip < 0:
        raise TrainSetupError("warmup, weight_decay and grad_clip must be >= 0")


# -- the loop ----------------------------------------------------------------------------------------

class _Stop(Exception):
    def __init__(self, outcome: str, message: str):
        super().__init__(message)
        self.outcome, self.message = outcome, message


def train(cfg: TrainConfig, control: Control | None = None, emit: Emit | None = None, *,
          component_factory: Callable[..., Any] | None = None, memory_guard: Any = None,
          thermal: Any = None) -> TrainResult:
    """Train cfg.component up to cfg.steps, resuming from the newest good checkpoint in cfg.run_dir.

    Returns a TrainResult whose outcome is one of contract.OUTCOME_EXIT_CODES. Raises
    TrainSetupError before the first step when the job cannot start (the message says why).
    `component_factory(name, spec, model_config=, vqvae_dir=, data_fingerprint=)` replaces
    components.build_component (tests use it for stand-in components); `memory_guard` (a
    guards.MemoryGuard) and `thermal` (a thermal.ThermalGovernor) replace the ones built from cfg,
    e.g. with a scripted RSS or a fake thermal file.
    """
    trainer = _Trainer(cfg, control or NoControl(), emit, component_factory)
    trainer.mem, trainer.thermal = memory_guard, thermal
    return trainer.run()


class _Trainer:
    def __init__(self, cfg: TrainConfig, control: Control, emit: Emit | None, factory):
        _check_config(cfg, factory is not None)
        self.cfg, self.control, self._emit_fn, self.factory = cfg, control, emit, factory
        self.run_dir = Path(cfg.run_dir)
        self.metrics = None
        self.mem = self.thermal = None

    # -- events ------------------------------------------------------------------------------
    def emit(self, kind: str, payload: dict) -> None:
        if self._emit_fn is not None:
            self._emit_fn(kind, payload)

    def log(self, message: str, level: str = "info") -> None:
        self.emit("log", {"level": level, "message": message})

    def _thermal_event(self, kind: str, payload: dict) -> None:
        if self.metrics is not None:  # into metrics.jsonl/.mcap as well; MetricsLog passes it on to emit
            self.metrics.event(kind, payload)
        else:
            self.emit(kind, payload)

    # -- setup -------------------------------------------------------------------------------
    def _open_data(self):
        from hope_models.data.cache import CacheError, load_or_build
        from hope_models.data.features import FeatureSpecError

        cfg = self.cfg
        if cfg.cache_dir:
            cache_root = Path(cfg.cache_dir)
        else:
            from hope_models.settings import load_settings
            cache_root = load_settings().cache_dir
        data_dir = dataset_dir_for(cfg.data, cache_root)
        try:
            cache, info = load_or_build(data_dir, cache_root, cfg.spec_path)
        except (CacheError, FeatureSpecError) as exc:
            raise TrainSetupError(f"--data {cfg.data}: {exc}") from None
        except OSError as exc:
            raise TrainSetupError(f"--data {cfg.data}: {exc.filename or ''} {exc.strerror or exc}") from None
        if cache.n_episodes == 0 or cache.n_steps == 0:
            excluded = cache.manifest.get("excluded", [])
            why = f" ({len(excluded)} excluded, e.g. {excluded[0]['reason']})" if excluded else ""
            raise TrainSetupError(f"--data {cfg.data}: no usable episodes{why}")
        for note in info.notes:
            self.log(f"dataset cache: {note}", "warning")
        return cache, info

    def _resolve_vqvae(self) -> Path | None:
        if not self.cfg.vqvae_dir:
            return None
        try:
            return ckpt.resolve_checkpoint_dir(self.cfg.vqvae_dir)
        except ckpt.CheckpointError as exc:
            raise TrainSetupError(f"--vqvae {self.cfg.vqvae_dir}: {exc}") from None

    def _build_component(self, spec, fingerprint: str):
        cfg = self.cfg
        factory = self.factory
        if factory is None:
            from hope_models.train.components import build_component as factory
        try:
            return factory(cfg.component, spec, model_config=dict(cfg.model_config), vqvae_dir=self.vqvae_dir,
                           data_fingerprint=fingerprint)
        except (ValueError, KeyError, ckpt.CheckpointError) as exc:
            raise TrainSetupError(f"cannot build {cfg.component}: {exc}") from None

    def _sampler(self, cache, component, split: str):
        from hope_models.train.validation import anchor_sampler

        cfg = self.cfg
        return anchor_sampler(cache, component, split, batch_size=cfg.batch_size, seed=cfg.seed,
                              imagined_ratio=cfg.imagined_ratio, val_fraction=cfg.val_fraction)

    def _check_resume_matches(self, loaded: ckpt.LoadedCheckpoint) -> None:
        saved = loaded.config.get("train", {})
        if not isinstance(saved, dict):  # config.json is read as untrusted: a clear error, not a traceback
            raise TrainSetupError(f"{loaded.path / ckpt.CONFIG_FILE}: 'train' must be an object, got "
                                  f"{type(saved).__name__}; choose a new --run-dir")
        mine = json.loads(json.dumps(self.cfg.identity()))  # tuples -> lists, as saved
        diffs = [f"{k}: {saved.get(k)!r} in the run dir, {v!r} now" for k, v in mine.items() if saved.get(k) != v]
        if diffs:
            raise TrainSetupError(
                f"{self.run_dir} holds a run with other settings ({'; '.join(diffs)}); re-run with the same "
                "arguments to resume it, or choose a new --run-dir")
        if saved.get("threads") != self.cfg.threads:
            self.log(f"resuming with threads={self.cfg.threads} (the run started with {saved.get('threads')}); "
                     "the weights may differ in the last bits from an uninterrupted run", "warning")
        if saved.get("steps") != self.cfg.steps:
            self.log(f"--steps changed from {saved.get('steps')} to {self.cfg.steps}: the cosine schedule "
                     "follows the new total from here", "warning")

    # -- checkpoint state ---------------------------------------------------------------------
    def _state(self, step: int) -> tuple[dict, dict]:
        import numpy as np
        import torch

        opt_tensors, opt_meta = ckpt.flatten_optimizer(self.opt.state_dict())
        np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
        tensors = {**opt_tensors, "rng.torch": torch.get_rng_state(),
                   "rng.numpy_keys": torch.from_numpy(np.ascontiguousarray(np_keys).view(np.int32).copy())}
        py_version, py_internal, py_gauss = random.getstate()
        state = {
            "optimizer": opt_meta,
            "schedule": {"kind": "warmup_cosine", "lr": self.cfg.lr, "warmup": self.cfg.warmup,
                         "total": self.cfg.steps, "min_lr_ratio": self.cfg.min_lr_ratio,
                         "lr_at_step": lr_at(step, self.cfg) if step else 0.0},
            "sampler": self.sampler.state_dict(),
            "elapsed_s": self.elapsed_before + (time.monotonic() - self.t_start),
            "loss_history": self.history.to_json_obj(),
            "rng": {"numpy": {"name": np_name, "pos": int(np_pos), "has_gauss": int(np_has_gauss),
                              "cached_gaussian": float(np_gauss)},
                    "python": {"version": py_version, "internal": list(py_internal), "gauss_next": py_gauss}},
        }
        return tensors, state

    def _restore(self, loaded: ckpt.LoadedCheckpoint) -> None:
        import numpy as np
        import torch

        # training_state.json is as untrusted as config.json: any wrong shape or type in it is one
        # clear error naming the checkpoint, never a traceback half-way through the restore
        try:
            self.model.load_state_dict(loaded.model, strict=True)
            self.opt.load_state_dict(ckpt.unflatten_optimizer(loaded.tensors, loaded.state["optimizer"]))
            self.sampler.load_state_dict(loaded.state["sampler"])
            torch.set_rng_state(loaded.tensors["rng.torch"])
            rng = loaded.state["rng"]
            keys = loaded.tensors["rng.numpy_keys"].numpy().view(np.uint32)
            n = rng["numpy"]
            np.random.set_state((n["name"], keys, n["pos"], n["has_gauss"], n["cached_gaussian"]))
            p = rng["python"]
            random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))
            self.history = LossHistory.from_json_obj(loaded.state["loss_history"])
            self.elapsed_before = float(loaded.state.get("elapsed_s", 0.0))
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError, AttributeError, OverflowError) as exc:
            raise TrainSetupError(f"{loaded.path}: cannot resume from it: {type(exc).__name__}: {exc}") from None

    def checkpoint(self, step: int) -> Path | None:
        """Write checkpoint `step` unless it is already the newest; refuses non-finite weights."""
        import torch

        if step == self.last_ckpt_step or step == 0:
            return self.last_ckpt_path
        t0 = time.monotonic()
        model_state = self.model.state_dict()
        bad = [k for k, v in model_state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
        if bad:
            raise _Stop("failed", f"non-finite values in {', '.join(bad[:3])} at step {step}: not checkpointed; "
                                  f"the last good checkpoint is {self.last_ckpt_path}")
        tensors, state = self._state(step)
        config = {**self.component.config(), "train": json.loads(json.dumps(self.cfg.to_json_obj()))}
        path = ckpt.save_checkpoint(self.run_dir, step, model_state=model_state, config=config,
                                    state_tensors=tensors, state=state, keep_last=self.cfg.keep_last)
        self.last_ckpt_step, self.last_ckpt_path = step, path
        self.last_ckpt_time = time.monotonic()
        payload = {"step": step, "path": str(path), "seconds": round(self.last_ckpt_time - t0, 4)}
        if self.metrics is not None:
            self.metrics.event("checkpoint", payload)  # MetricsLog also passes it to emit
            self.metrics.sync()  # the metrics up to a checkpoint survive a power cut too
        else:
            self.emit("checkpoint", payload)
        return path

    def _optimizer(self):
        """AdamW; weight decay on matrices only (biases, norms and other vectors are left alone)."""
        import torch

        decay = [p for p in self.model.parameters() if p.requires_grad and p.dim() >= 2]
        no_decay = [p for p in self.model.parameters() if p.requires_grad and p.dim() < 2]
        self.params = decay + no_decay
        groups = [{"params": decay, "weight_decay": self.cfg.weight_decay},
                  {"params": no_decay, "weight_decay": 0.0}]
        return torch.optim.AdamW([g for g in groups if g["params"]], lr=self.cfg.lr, betas=(0.9, 0.95), eps=1e-8)

    def _estimate_from_config(self, cache):
        """The memory estimate of the component cfg describes, from its configuration: nothing is
        built, so a model too big for the budget is refused before it can take the memory."""
        from hope_models.train.estimate import cache_resident_mb, estimate_from_config
        from hope_models.train.model_config import read_vqvae_config, resolve

        cfg = self.cfg
        try:
            vq = read_vqvae_config(self.vqvae_dir) if self.vqvae_dir is not None and cfg.component != "vqvae" else None
            resolved = resolve(cfg.component, cache.spec, dict(cfg.model_config), vq)
        except ValueError as exc:
            raise TrainSetupError(f"cannot build {cfg.component}: {exc}") from None
        return estimate_from_config(resolved, cfg.batch_size, cache.spec.obs_dim, cache.spec.act_dim,
                                    cache_mb=cache_resident_mb(cache), loader_chunk=LOADER_CHUNK)

    def _estimate_built(self, cache):
        """A stand-in factory's component is known only once built: its estimate from the model."""
        from hope_models.train.estimate import cache_resident_mb, estimate_memory

        cfg, win = self.cfg, self.component.window
        return estimate_memory(cfg.component, self.model, cfg.batch_size, win.k, cache.spec.obs_dim,
                               cache.spec.act_dim, bool(self.component.wants_frames), horizons=len(win.horizons_s),
                               cache_mb=cache_resident_mb(cache), loader_chunk=LOADER_CHUNK)

    def _preflight(self, est) -> None:
        """Refuse, before the first step, a configuration whose estimated memory cannot fit the budget."""
        from hope_models.train.estimate import MemoryBudgetError, check_fits

        try:
            check_fits(est, self.cfg.memory_budget_mb, self.cfg.memory_soft_fraction)
        except MemoryBudgetError as exc:
            raise TrainSetupError(str(exc)) from None

    # -- run ---------------------------------------------------------------------------------
    def run(self) -> TrainResult:
        from hope_models.train.guards import MemoryGuard
        from hope_models.train.thermal import ThermalGovernor

        cfg = self.cfg
        self.t_start = time.monotonic()
        # Everything a user can get wrong is checked before torch is imported (seconds on a Pi).
        try:
            if self.mem is None:
                self.mem = MemoryGuard(cfg.memory_budget_mb, cfg.memory_soft_fraction)
            if self.thermal is None:
                self.thermal = ThermalGovernor(cfg.thermal_zone, cfg.vcgencmd, cfg.thermal_soft_c, cfg.thermal_hard_c,
                                               cfg.thermal_resume_c, emit=self._thermal_event)
        except ValueError as exc:
            raise TrainSetupError(str(exc)) from None
        self.vqvae_dir = self._resolve_vqvae()
        cache, _info = self._open_data()
        self.estimate = None if self.factory is not None else self._estimate_from_config(cache)
        if self.estimate is not None:
            self._preflight(self.estimate)  # before torch is imported, and before the run dir exists
        self.run_dir.mkdir(parents=True, exist_ok=True)
        try:
            lock = RunDirLock(self.run_dir).acquire()
        except RunDirBusy as exc:
            raise TrainSetupError(str(exc)) from None
        with lock:
            return self._train(cache)

    def _train(self, cache) -> TrainResult:
        import numpy as np
        import torch

        from hope_models.train.metrics import MetricsLog, convergence_summary

        cfg = self.cfg
        torch.set_num_threads(cfg.threads)
        torch.use_deterministic_algorithms(True)
        ckpt.clean_temp(self.run_dir)
        loaded = ckpt.load_latest(self.run_dir, warn=lambda m: self.log(m, "warning"))
        if loaded is not None:
            self._check_resume_matches(loaded)

        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        self.component = self._build_component(cache.spec, cache.fingerprint)
        self.model = self.component.model
        try:
            self.sampler = self._sampler(cache, self.component, "train")
            split = "train"
        except ValueError as exc:  # e.g. every episode hashed into the validation split
            try:
                self.sampler = self._sampler(cache, self.component, "all")
            except ValueError as exc_all:
                raise TrainSetupError(f"--data {cfg.data}: no batches to train on: {exc_all}") from None
            split = "all"
            self.log(f"training on all episodes (no validation split): {exc}", "warning")
        self.opt = self._optimizer()
        if self.estimate is None:
            self.estimate = self._estimate_built(cache)
            self._preflight(self.estimate)
        self.log(f"{cfg.component}: {sum(p.numel() for p in self.params):,} trainable parameters, "
                 f"{self.estimate.describe()} of the {cfg.memory_budget_mb:.0f} MB budget")

        self.history = LossHistory(cfg.log_every)
        self.elapsed_before = 0.0
        self.last_ckpt_step, self.last_ckpt_path = 0, None
        resumed_from = None
        if loaded is not None:
            self._restore(loaded)
            resumed_from = loaded.step
            self.last_ckpt_step, self.last_ckpt_path = loaded.step, loaded.path
            del loaded  # the tensors were copied into the model and optimizer
        self.last_ckpt_time = time.monotonic()
        start_step = self.last_ckpt_step

        self.metrics = MetricsLog(self.run_dir, emit=self._emit_fn)
        try:
            if resumed_from is not None:
                self.metrics.event("resume", {"step": resumed_from, "path": str(self.last_ckpt_path)})
            outcome, message, step = self._loop(start_step)
            summary = convergence_summary(self.history.points) if self.history.points else {}
            if outcome == "completed" and split == "train":
                val = self._validate(cache)
                if val:
                    summary["val"] = val
            self.metrics.event("state", {"state": outcome, "step": step, "message": message})
        finally:
            self.metrics.close()
        peak = self.mem.check().peak_mb
        result = TrainResult(outcome, cfg.component, step, cfg.steps, self.history.first(), self.history.last(),
                             str(self.last_ckpt_path) if self.last_ckpt_path else None, peak, resumed_from,
                             summary, message, self.elapsed_before + time.monotonic() - self.t_start)
        _write_json_atomic(self.run_dir / "result.json", result.to_json_obj())
        return result

    def _poll(self, step: int) -> ControlCommand:
        cmd = self.control.poll(step)
        if cmd.desired not in ("run", "pause", "cancel"):
            raise ValueError(f"Control.poll returned desired={cmd.desired!r}")
        return cmd

    def _loop(self, step: int) -> tuple[str, str, int]:
        import torch

        from hope_models.data.windows import WindowLoader

        cfg, model, opt, comp = self.cfg, self.model, self.opt, self.component
        loader = WindowLoader(self.sampler.cache, self.sampler, comp.window, chunk=LOADER_CHUNK,
                              frames=bool(comp.wants_frames))
        model.train()
        clip = cfg.grad_clip if cfg.grad_clip > 0 else float("inf")
        throttle = 0.0
        next_poll = 0.0
        verdict = self.mem.check()
        last_step_s = 0.0
        log_t, log_step = time.monotonic(), step
        sps = 0.0
        if step >= cfg.steps:
            msg = f"already trained to step {step} (--steps {cfg.steps}); nothing to do"
            self.log(msg)
            return "completed", msg, step
        try:
            while step < cfg.steps:
                # -- between steps: control, memory, thermal ---------------------------------
                now = time.monotonic()
                if now >= next_poll:
                    next_poll = now + cfg.control_interval_s
                    cmd = self._poll(step)
                    if cmd.desired in ("pause", "cancel"):
                        self.checkpoint(step)
                        what = "paused" if cmd.desired == "pause" else "cancelled"
                        return ("paused_user" if cmd.desired == "pause" else "cancelled",
                                f"{what} at step {step} by the control hook; checkpoint {self.last_ckpt_path}", step)
                    throttle = min(max(float(cmd.throttle), 0.0), 0.95)
                    verdict = self.mem.check()
                    if verdict.over_soft:
                        self.checkpoint(step)
                        self.metrics.event("memory", {"step": step, "rss_mb": round(verdict.rss_mb, 1),
                                                      "budget_mb": cfg.memory_budget_mb, "message": verdict.message})
                        return "paused_memory", f"step {step}: {verdict.message}", step
                action = self.thermal.before_step(last_step_s)
                if action.level == "slow" and action.sleep_s > 0:
                    time.sleep(action.sleep_s)
                elif action.level == "hot":
                    why = self.thermal.wait_until_cool(lambda: self.checkpoint(step), lambda: self._poll(step))
                    if why in ("pause", "cancel"):
                        return ("paused_user" if why == "pause" else "cancelled",
                                f"{why} while waiting for the temperature to fall at step {step}", step)
                if throttle > 0 and last_step_s > 0:
                    time.sleep(last_step_s * throttle / (1.0 - throttle))

                # -- one optimizer step ---------------------------------------------------------
                t0 = time.monotonic()
                s = step + 1
                batch = next(loader)
                lr = lr_at(s, cfg)
                for g in opt.param_groups:
                    g["lr"] = lr
                loss, extra = comp.loss(batch)
                loss_v = float(loss.detach())
                if not math.isfinite(loss_v):
                    return "failed", (f"loss is {loss_v} at step {s}: stopped before the optimizer step; the last "
                                      f"good checkpoint is {self.last_ckpt_path or 'none (no checkpoint yet)'}"), step
                opt.zero_grad(set_to_none=True)
                loss.backward()
                grad_norm = float(torch.nn.utils.clip_grad_norm_(self.params, clip))
                if not math.isfinite(grad_norm):
                    return "failed", (f"gradient norm is {grad_norm} at step {s}: stopped before the optimizer "
                                      f"step; the last good checkpoint is {self.last_ckpt_path or 'none'}"), step
                opt.step()
                comp.after_step(s)
                step = s
                self.history.add(step, loss_v)
                last_step_s = time.monotonic() - t0

                # -- checkpoints, metrics, progress ---------------------------------------------
                now = time.monotonic()
                if step % cfg.checkpoint_every_steps == 0 or step == cfg.steps \
                        or now - self.last_ckpt_time >= cfg.checkpoint_every_s:
                    self.checkpoint(step)
                if step % cfg.log_every == 0 or step == cfg.steps:
                    now = time.monotonic()
                    sps = (step - log_step) / max(now - log_t, 1e-9)
                    log_t, log_step = now, step
                    temp = action.temp_c
                    record = {"loss": loss_v, "lr": lr, "grad_norm": grad_norm, "steps_per_s": sps,
                              "rss_mb": verdict.rss_mb, "temp_c": temp, "throttle_level": action.level,
                              "throttle": throttle, **{k: float(v) for k, v in extra.items()}}
                    self.metrics.log(step, record)
                    self.emit("progress", {"step": step, "total": cfg.steps, "loss": loss_v, "steps_per_s": sps,
                                           "eta_s": (cfg.steps - step) / sps if sps > 0 else None,
                                           "rss_mb": verdict.rss_mb})
        except _Stop as stop:
            return stop.outcome, stop.message, step
        except Exception as exc:  # an error inside the job: keep the last good checkpoint, say what happened
            tb = traceback.format_exc()
            self.log(tb, "error")
            return "failed", f"error at step {step + 1}: {type(exc).__name__}: {exc}", step
        return "completed", f"trained {cfg.component} to step {step}", step

    def _validate(self, cache) -> dict[str, float]:
        """Mean evaluate() metrics over a few validation batches; the RNG is left as it was. The
        promotion gate computes the same numbers with the same function (train/validation.py)."""
        from hope_models.train.validation import NoValidationSplit, ValidationSetup, validation_metrics

        try:
            return validation_metrics(self.component, cache, ValidationSetup.from_train_config(self.cfg))
        except NoValidationSplit:
            return {}


def _write_json_atomic(path: Path, obj: Any) -> None:
    atomic_write(path, json.dumps(obj, indent=1, default=str))
