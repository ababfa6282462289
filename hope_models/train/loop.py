"""The one training loop for every HOPE component: deterministic, resumable, guarded, logged.

    result = train(TrainConfig(component="fast_loop", data="ds/", run_dir="runs/r1", steps=2000))

What makes a re-run after a kill end with the same weights, bit for bit, as a run never stopped:
- the math depends only on (config, step): batch s is AnchorSampler.batch(s - 1), a pure function
  of (seed, s); the learning rate is lr_at(s), a pure function of the step (no scheduler object);
- a checkpoint holds everything else the next step reads: weights and buffers, AdamW's moments and
  step counts, torch's (and numpy's and python's) global RNG state, the sampler cursor;
- nothing that depends on wall time (checkpoints every T seconds, guards, throttling, metrics)
  touches the RNG or the tensors, and checkpoint writes only read them;
- threads are fixed, torch.use_deterministic_algorithms(True), subnormals flushed (job_setup).
A resumed job rebuilds the component (whose init consumes the RNG), then loads all of the above
over it, so the init draws do not matter.

Between steps: the control hook (pause / cancel / throttle, polled every control_interval_s), the
memory guard (checkpoint + "paused_memory" at the soft limit), the thermal governor (sleep a
fraction of the step when warm; checkpoint and wait when hot). A NaN/Inf loss or gradient stops
the job as "failed" before the optimizer step, so the last checkpoint on disk stays the last good one.
"""
from __future__ import annotations

import json
import math
import random
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from hope_models import checkpoints as ckpt
from hope_models import disk
from hope_models.components import COMPONENTS
from hope_models.durable import atomic_write
from hope_models.train import job_setup, rng_state, validation
from hope_models.train.config import ConfigValueError, TrainConfig
from hope_models.train.contract import Control, ControlCommand, NoControl, TrainSetupError
from hope_models.train.held_out_picture import write_held_out_picture
from hope_models.train.job_setup import LOADER_CHUNK
from hope_models.train.loss_history import LossHistory
from hope_models.train.provenance import write_provenance
from hope_models.train.result import TrainResult
from hope_models.train.run_dir_lock import RunDirBusy, RunDirLock
from hope_models.train.schedule import lr_at
from hope_models.train.thermal import ThermalGovernor
from hope_models.train.validation import NoValidationSplit, ValidationSetup, anchor_sampler, validation_metrics

Emit = Callable[[str, dict], None]


def _check_config(cfg: TrainConfig, custom_component: bool) -> None:
    if not custom_component and cfg.component not in COMPONENTS:
        raise TrainSetupError(f"--component {cfg.component!r} is not one of {', '.join(COMPONENTS)}")
    try:
        cfg.check()
    except ConfigValueError as exc:
        raise TrainSetupError(str(exc)) from None


# -- the loop ----------------------------------------------------------------------------------------

@dataclass
class _Pace:
    """What the loop carries from one step to the next besides the weights: the throttle the
    control hook set, when to poll it next, the last memory verdict and thermal action, the last
    step's duration, and where the steps/s measurement started."""
    verdict: Any
    log_t: float
    log_step: int
    throttle: float = 0.0
    next_poll: float = 0.0
    last_step_s: float = 0.0
    action: Any = None


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
    try:
        return trainer.run()
    except OSError as exc:  # a full disk in the cache build, the metrics' open/close or result.json
        if not disk.is_disk_full(exc):
            raise
        return trainer.disk_full(exc)


class _Trainer:
    def __init__(self, cfg: TrainConfig, control: Control, emit: Emit | None, factory):
        _check_config(cfg, factory is not None)
        self.cfg, self.control, self._emit_fn, self.factory = cfg, control, emit, factory
        self.run_dir = Path(cfg.run_dir)
        self.metrics, self.t_start = None, time.monotonic()
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
    def _build_component(self, spec, fingerprint: str):
        cfg = self.cfg
        factory = self.factory
        if factory is None:
            from hope_models.components.build import build_component as factory  # lazy: loads numpy, safetensors, torch
        try:
            return factory(cfg.component, spec, model_config=dict(cfg.model_config), vqvae_dir=self.vqvae_dir,
                           data_fingerprint=fingerprint)
        except (ValueError, KeyError, ckpt.CheckpointError) as exc:
            raise TrainSetupError(f"cannot build {cfg.component}: {exc}") from None

    def _sampler(self, cache, component, split: str):
        cfg = self.cfg
        return anchor_sampler(cache, component, split, batch_size=cfg.batch_size, seed=cfg.seed,
                              imagined_ratio=cfg.imagined_ratio, val_fraction=cfg.val_fraction)

    # -- checkpoint state ---------------------------------------------------------------------
    def _state(self, step: int) -> tuple[dict, dict]:
        opt_tensors, opt_meta = ckpt.flatten_optimizer(self.opt.state_dict())
        rng_tensors, rng = rng_state.capture()
        state = {
            "optimizer": opt_meta,
            "schedule": {"kind": "warmup_cosine", "lr": self.cfg.lr, "warmup": self.cfg.warmup,
                         "total": self.cfg.steps, "min_lr_ratio": self.cfg.min_lr_ratio,
                         "lr_at_step": lr_at(step, self.cfg) if step else 0.0},
            "sampler": self.sampler.state_dict(),
            "elapsed_s": self.elapsed_before + (time.monotonic() - self.t_start),
            "loss_history": self.history.to_json_obj(),
            "rng": rng,
        }
        return {**opt_tensors, **rng_tensors}, state

    def _restore(self, loaded: ckpt.LoadedCheckpoint) -> None:
        # training_state.json is as untrusted as config.json: any wrong shape or type in it is one
        # clear error naming the checkpoint, never a traceback half-way through the restore
        try:
            self.model.load_state_dict(loaded.model, strict=True)
            self.opt.load_state_dict(ckpt.unflatten_optimizer(loaded.tensors, loaded.state["optimizer"]))
            self.sampler.load_state_dict(loaded.state["sampler"])
            rng_state.restore(loaded.tensors, loaded.state["rng"])
            self.history = LossHistory.from_json_obj(loaded.state["loss_history"])
            self.elapsed_before = float(loaded.state.get("elapsed_s", 0.0))
        except (RuntimeError, ValueError, KeyError, TypeError, IndexError, AttributeError, OverflowError) as exc:
            raise TrainSetupError(f"{loaded.path}: cannot resume from it: {type(exc).__name__}: {exc}") from None

    def checkpoint(self, step: int) -> Path | None:
        """Write checkpoint `step` unless it is already the newest; refuses non-finite weights."""
        import torch  # lazy: loads torch

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
        from hope_models.train.adamw import adamw  # lazy: loads torch

        decay = [p for p in self.model.parameters() if p.requires_grad and p.dim() >= 2]
        no_decay = [p for p in self.model.parameters() if p.requires_grad and p.dim() < 2]
        self.params = decay + no_decay
        groups = [{"params": decay, "weight_decay": self.cfg.weight_decay},
                  {"params": no_decay, "weight_decay": 0.0}]
        return adamw([g for g in groups if g["params"]], lr=self.cfg.lr, betas=(0.9, 0.95), eps=1e-8)

    # -- run ---------------------------------------------------------------------------------
    def run(self) -> TrainResult:
        from hope_models.train.guards import MemoryGuard  # lazy: loads psutil

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
        self.vqvae_dir = job_setup.resolve_vqvae(cfg)
        cache, _info = job_setup.open_dataset(cfg, self.log)
        self.estimate = None if self.factory is not None else job_setup.estimate_from_config(cfg, cache, self.vqvae_dir)
        if self.estimate is not None:
            job_setup.check_budget(cfg, self.estimate)  # before torch is imported, and before the run dir exists
        self.run_dir.mkdir(parents=True, exist_ok=True)
        try:
            lock = RunDirLock(self.run_dir).acquire()
        except RunDirBusy as exc:
            raise TrainSetupError(str(exc)) from None
        with lock:
            return self._train(cache)

    def disk_full(self, exc: OSError) -> TrainResult:
        """paused_disk from the last checkpoint on disk, without a traceback; nothing more is written."""
        step = getattr(self, "last_ckpt_step", 0)
        path = getattr(self, "last_ckpt_path", None)
        message = disk.full_message(exc, self.run_dir) + f"; resumes from {path or 'the start'} (step {step})"
        self.log(message, "error")
        history = getattr(self, "history", None)
        first, last = (history.first(), history.last()) if history is not None else (None, None)
        return TrainResult("paused_disk", self.cfg.component, step, self.cfg.steps, first, last,
                           str(path) if path else None, self.mem.check().peak_mb if self.mem else 0.0, None, {},
                           message, time.monotonic() - self.t_start)

    def _train(self, cache) -> TrainResult:
        import numpy as np  # lazy: loads numpy
        import torch  # lazy: loads torch

        from hope_models.train.metrics import MetricsLog, convergence_summary  # lazy: loads mcap

        cfg = self.cfg
        job_setup.torch_settings(torch, cfg.threads)
        ckpt.clean_temp(self.run_dir)
        loaded = ckpt.load_latest(self.run_dir, warn=lambda m: self.log(m, "warning"))
        if loaded is not None:
            job_setup.check_resume_matches(cfg, loaded, self.run_dir, self.log)

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
            self.estimate = job_setup.estimate_built(cfg, self.component, cache)
            job_setup.check_budget(cfg, self.estimate)
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

        write_provenance(self.run_dir, cfg, cache, self.vqvae_dir)  # what this attempt is made from
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
        """Optimizer steps up to cfg.steps; (outcome, message, the last step done)."""
        from hope_models.data.windows import WindowLoader  # lazy: loads numpy

        cfg, comp = self.cfg, self.component
        if step >= cfg.steps:
            msg = f"already trained to step {step} (--steps {cfg.steps}); nothing to do"
            self.log(msg)
            return "completed", msg, step
        loader = WindowLoader(self.sampler.cache, self.sampler, comp.window, chunk=LOADER_CHUNK,
                              frames=bool(comp.wants_frames), codes=validation.code_table(comp, self.sampler.cache, self.log))
        self.model.train()
        pace = _Pace(verdict=self.mem.check(), log_t=time.monotonic(), log_step=step)
        try:
            while step < cfg.steps:
                stop = self._between_steps(step, pace)
                if stop is not None:
                    return stop
                t0 = time.monotonic()
                stepped = self._step(step + 1, next(loader))
                if isinstance(stepped, str):
                    return "failed", stepped, step
                step += 1
                pace.last_step_s = time.monotonic() - t0
                self._after_step(step, pace, *stepped)
        except _Stop as stop:
            return stop.outcome, stop.message, step
        except Exception as exc:  # an error inside the job: keep the last good checkpoint, say what happened
            if disk.is_disk_full(exc):  # not the job's fault: it resumes from the last checkpoint
                self.log(disk.full_message(exc, self.run_dir), "error")
                return "paused_disk", disk.full_message(exc, self.run_dir), self.last_ckpt_step
            self.log(traceback.format_exc(), "error")
            return "failed", f"error at step {step + 1}: {type(exc).__name__}: {exc}", step
        return "completed", f"trained {cfg.component} to step {step}", step

    def _between_steps(self, step: int, pace: "_Pace") -> tuple[str, str, int] | None:
        """Control, memory and thermal before step + 1; an (outcome, message, step) to stop with."""
        cfg = self.cfg
        now = time.monotonic()
        if now >= pace.next_poll:
            pace.next_poll = now + cfg.control_interval_s
            cmd = self._poll(step)
            if cmd.desired in ("pause", "cancel"):
                self.checkpoint(step)
                what = "paused" if cmd.desired == "pause" else "cancelled"
                return ("paused_user" if cmd.desired == "pause" else "cancelled",
                        f"{what} at step {step} by the control hook; checkpoint {self.last_ckpt_path}", step)
            pace.throttle = min(max(float(cmd.throttle), 0.0), 0.95)
            pace.verdict = self.mem.check()
            if pace.verdict.over_soft:
                self.checkpoint(step)
                self.metrics.event("memory", {"step": step, "rss_mb": round(pace.verdict.rss_mb, 1),
                                              "budget_mb": cfg.memory_budget_mb, "message": pace.verdict.message})
                return "paused_memory", f"step {step}: {pace.verdict.message}", step
        pace.action = action = self.thermal.before_step(pace.last_step_s)
        if action.level == "slow" and action.sleep_s > 0:
            time.sleep(action.sleep_s)
        elif action.level == "hot":
            why = self.thermal.wait_until_cool(lambda: self.checkpoint(step), lambda: self._poll(step))
            if why in ("pause", "cancel"):
                return ("paused_user" if why == "pause" else "cancelled",
                        f"{why} while waiting for the temperature to fall at step {step}", step)
        if pace.throttle > 0 and pace.last_step_s > 0:
            time.sleep(pace.last_step_s * pace.throttle / (1.0 - pace.throttle))
        return None

    def _step(self, s: int, batch) -> tuple[float, float, float, dict] | str:
        """Optimizer step `s`: (loss, lr, grad norm, the component's extra metrics), or why it
        stopped before the optimizer step (a non-finite loss or gradient)."""
        import torch  # lazy: loads torch

        lr = lr_at(s, self.cfg)
        for g in self.opt.param_groups:
            g["lr"] = lr
        loss, extra = self.component.loss(batch)
        loss_v = float(loss.detach())
        if not math.isfinite(loss_v):
            return (f"loss is {loss_v} at step {s}: stopped before the optimizer step; the last "
                    f"good checkpoint is {self.last_ckpt_path or 'none (no checkpoint yet)'}")
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        clip = self.cfg.grad_clip if self.cfg.grad_clip > 0 else float("inf")
        grad_norm = float(torch.nn.utils.clip_grad_norm_(self.params, clip))
        if not math.isfinite(grad_norm):
            return (f"gradient norm is {grad_norm} at step {s}: stopped before the optimizer "
                    f"step; the last good checkpoint is {self.last_ckpt_path or 'none'}")
        self.opt.step()
        self.component.after_step(s)
        self.history.add(s, loss_v)
        return loss_v, lr, grad_norm, extra

    def _after_step(self, step: int, pace: "_Pace", loss_v: float, lr: float, grad_norm: float,
                    extra: dict) -> None:
        """Checkpoints, metrics and progress after optimizer step `step`."""
        cfg = self.cfg
        now = time.monotonic()
        if step % cfg.checkpoint_every_steps == 0 or step == cfg.steps \
                or now - self.last_ckpt_time >= cfg.checkpoint_every_s:
            self.checkpoint(step)
        if step % cfg.log_every == 0 or step == cfg.steps:
            now = time.monotonic()
            sps = (step - pace.log_step) / max(now - pace.log_t, 1e-9)
            pace.log_t, pace.log_step = now, step
            action = pace.action
            record = {"loss": loss_v, "lr": lr, "grad_norm": grad_norm, "steps_per_s": sps,
                      "rss_mb": pace.verdict.rss_mb, "temp_c": action.temp_c, "throttle_level": action.level,
                      "throttle": pace.throttle, **{k: float(v) for k, v in extra.items()}}
            self.metrics.log(step, record)
            self.emit("progress", {"step": step, "total": cfg.steps, "loss": loss_v, "steps_per_s": sps,
                                   "eta_s": (cfg.steps - step) / sps if sps > 0 else None,
                                   "rss_mb": pace.verdict.rss_mb})

    def _validate(self, cache) -> dict[str, float]:
        """Mean evaluate() metrics over a few validation batches (the gate's function, validation.py),
        the RNG left as it was; and a frame run's held-out picture in the run dir (train/held_out_picture.py)."""
        try:
            val = validation_metrics(self.component, cache, ValidationSetup.from_train_config(self.cfg))
        except NoValidationSplit:
            return {}
        if (picture := write_held_out_picture(self.component, cache, self.run_dir, self.cfg.val_fraction)) is not None:
            self.log(f"held-out picture: {picture}")
        return val


def _write_json_atomic(path: Path, obj: Any) -> None:
    atomic_write(path, json.dumps(obj, indent=1, default=str))
