"""BrainService: serves every promoted component of the table (hope_models/components) through its
NumPy form (its folder's numpy_form.RUNTIME) and follows promotions without a restart.

    brain = BrainService(settings.home, on_swap=..., on_first_inference=..., on_error=...)
    brain.start()                                   # loads what is promoted now, then watches
    brain.infer("fast_loop", [0.1, ...], session="arm-1")     # + frame="data:image/png;base64,..." for a camera
        -> {"action": [...], "model_version": "reach@2500:1a2b3c4d5e6f", "latency_ms": 0.08, "session": "arm-1",
            "code": [3, 11], "prediction": {"0.5s": [...], "1s": [...]}, "surprise": 2.1,
            "surprise_by_horizon": {"0.5s": 2.1, "1s": 3.0}, "mid_tick": 35, "mid_grid_point": 7,
            "versions": {"vqvae": ..., "fast_loop": ..., "mid_loop": ...}}
    brain.status()["mid_loop"]                      # version, checkpoint, loaded_at, last_error, sessions, ...
    brain.stop()

The answer is composed by role from the promoted components that read the request's observation
layout: the actor's `action`, the tokenizer's `code`, the predictor's `prediction` and `surprise`
(mid_serving.py), and `outputs` {component: its form's answer(values)} for any other component.

Each component's promoted model is named by its pointer file $HOPE_HOME/promoted/<component>.json
(hope_models.promoted). A watcher thread reads the pointers every poll_s (0.2 s) and compares
their bytes with the last seen, so a promotion or a rollback is noticed within a poll. A new
checkpoint is loaded on the watcher thread, off the request path: its manifest verified (each file
read and hashed once, the weights loaded from the bytes that were hashed), their sha256 checked
against the pointer's, its config checked to fit (a checkpoint this runtime can run, reading the
same layout as the model being served: fit_fields), warmed, and only then swapped in by assigning
one reference. A request reads that reference once and finishes on the object it read, so
requests in flight complete on the old weights and none fail. A checkpoint that does not fit is
refused: the old model keeps serving, the reason is in status()["<component>"]["last_error"] and
passed to on_error. Each component follows its own pointer.

Hooks (plain attributes, read each time they are called, so the webapp can wire them after
construction): on_swap(component, version, checkpoint) and on_error(component, message) run on the
watcher thread (or in start()/check_now()); on_first_inference(component, version, checkpoint, when)
fires once per loaded version on a hook thread of its own, so the request that triggered it never
waits for the webapp's registry write (`wait_hooks()` waits for it; `stop()` runs what is queued).
A hook that raises is logged, never propagated. A refused pointer is not retried until it changes.

Torch-free (the `serve` process's memory budget has no room for torch): each NumPy form is tested
equal to its torch model. Construction puts NumPy's OpenBLAS on one thread for the whole process
(blas_threads.py, no environment variable a child would inherit; `self.blas_threads` says what was
done): its default of a thread per core made the frame answer ~15x slower on busy cores.

A request is one control tick of a session and answers from every served component that reads the
observation's layout; `component` names the one the caller needs (503 while it is not served).
The fast_loop's recurrent state (window-exact: FastLoop.forward over the session's last K
observations; fast_sessions.py) and the Mid Loop's grid points (mid_serving.py: when it runs,
`prediction` and `surprise`) are per session; without one the call is stateless (a 1-point window). Sessions are
kept per component in an LRU of `max_sessions`; `reset=True` starts the session's episode again,
and a version change resets that component's sessions (a state computed by other weights means
nothing to the new ones); a vqvae change changes only `code`.

The camera: a component whose model reads a frame (a frame VQ-VAE as the tokenizer, a fast_loop over
one: `frame_shape` not None) needs the request's `frame` (brain_frame.py: a base64 JPEG/PNG or data
URL, resized as the training cache resized; a raw uint8 array of the model's size; nested lists).
It is decoded once per size and encoded once per frame encoder (brain_seen.py: the tokenizer and the
reflex carrying the same VQ-VAE share the codes), before any session moves. No frame when one is
read, or a frame when no served component of the answer reads one, is a 400 saying so (never
ignored: a robot sending its camera to a model that cannot see should hear it). A replacement must
read the same frame size as the served model (fit_fields). A grid Mid Loop (mid_loop/numpy_grid.py)
reads the frame's cells by its own VQ-VAE from the same SeenFrame (frame_codes[PREDICTOR]: one
encode when its VQ-VAE's weights are the reflex's or the tokenizer's) with the joints; a request
without a frame to it is the same 400.

Every answer is finite. An observation value beyond +-MAX_ABS_OBSERVATION (1e6) is refused (400).
If the fast_loop computes NaN or Inf from a valid observation, that is the model's fault: BrainError
500 naming the version, logged and counted (status()["fast_loop"]["non_finite"]), and the session's
state is committed only when the tick's action and state are finite. A non-finite Mid Loop
prediction is answered as null (counted the same way) and the action is still given.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from hope_models.components import ACTOR, COMPONENTS, PREDICTOR, TOKENIZER
from hope_models.components.checkpoint_checks import CheckpointRefused
from hope_models.components.mid_loop import serving as mid_serving
from hope_models.promoted import PointerError, pointer_path, read_pointer
from hope_models.runtime import blas_threads, brain_input, fast_sessions
from hope_models.runtime.brain_input import MAX_ABS_OBSERVATION, MAX_SESSIONS, BrainError, observation_values
from hope_models.runtime.brain_seen import check_frame, describe_shape, frame_shape
from hope_models.runtime.brain_status import status_extra
from hope_models.runtime.hook_thread import HookThread

log = logging.getLogger(__name__)

# component -> its torch-free inference runtime (its folder's numpy_form.RUNTIME)
RUNTIMES = {name: spec.part("numpy_form").RUNTIME for name, spec in COMPONENTS.items()}


def _utcnow() -> datetime:
    return datetime.now(timezone.utc)


@dataclass(eq=False)
class _Served:
    """One loaded version of a component: never mutated after it is swapped in (apart from the
    once-only first-inference flag)."""
    model: Any  # one of RUNTIMES' classes
    checkpoint: Path
    pointer: dict[str, Any]
    loaded_at: datetime
    first_inference_done: bool = False

    @property
    def version(self) -> str:
        return self.model.version


@dataclass(eq=False)
class _Slot:
    """Per component: the served model (one reference, swapped whole), its sessions, the watcher's view."""
    component: str
    served: _Served | None = None
    last_error: str | None = None
    pointer_bytes: bytes | None = None  # what the pointer file held when last looked at
    pointer_version: str | None = None
    sessions: "OrderedDict[str, Any]" = field(default_factory=OrderedDict)  # fast_sessions.FastSession (actor)
    lock: threading.Lock = field(default_factory=threading.Lock)  # sessions and first-inference flag
    non_finite: int = 0  # answers refused because the served model computed NaN/Inf (status())


class BrainService:
    def __init__(self, home: str | Path, *, components: Iterable[str] = tuple(RUNTIMES), poll_s: float = 0.2,
                 on_swap: Callable[[str, str, str], Any] | None = None,
                 on_first_inference: Callable[[str, str, str, datetime], Any] | None = None,
                 on_error: Callable[[str, str], Any] | None = None, max_sessions: int = MAX_SESSIONS):
        comps = tuple(components)
        unknown = [c for c in comps if c not in RUNTIMES]
        if unknown or not comps:
            raise ValueError(f"BrainService: no inference runtime for {unknown or 'no component'}; it serves "
                             f"{', '.join(RUNTIMES)}")
        if not (isinstance(poll_s, (int, float)) and 0 < poll_s <= 1.0):
            raise ValueError(f"BrainService: poll_s={poll_s!r} must be within (0, 1] (changes are noticed within 1 s)")
        if max_sessions < 1:
            raise ValueError(f"BrainService: max_sessions={max_sessions} must be >= 1")
        # every serving process builds one before it answers: NumPy's BLAS on one thread for this
        # process only (blas_threads.py; children keep their own defaults)
        self.blas_threads = blas_threads.limit_numpy_blas_threads()
        self.home = Path(home)
        self.poll_s = float(poll_s)
        self.max_sessions = int(max_sessions)
        self.on_swap, self.on_first_inference, self.on_error = on_swap, on_first_inference, on_error
        self._slots = {c: _Slot(c) for c in comps}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._check_lock = threading.Lock()  # one pointer check at a time (watcher vs check_now)
        # on_first_inference runs on its own thread: the webapp's hook writes to SQLite, which may
        # wait for the daemon's write lock, and a robot's request must never wait for that.
        self._hooks = HookThread("brain-hooks")

    @property
    def components(self) -> tuple[str, ...]:
        return tuple(self._slots)

    # -- lifecycle ------------------------------------------------------------------------------
    def start(self) -> "BrainService":
        """Load what is promoted now (so infer answers right after start), then watch in a thread."""
        if self._thread is not None:
            return self
        self._stop.clear()
        self.check_now()
        self._thread = threading.Thread(target=self._watch, name="brain-watcher", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop watching; hooks already queued (first-inference records) still run, within timeout."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout)
        self._hooks.stop(timeout)

    def __enter__(self) -> "BrainService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _watch(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.check_now()
            except Exception:  # never let the watcher die: the next poll tries again
                log.exception("BrainService: pointer check failed")

    # -- following the pointers -----------------------------------------------------------------
    def check_now(self) -> None:
        """Look at every pointer once and load what changed (the watcher calls this each poll)."""
        with self._check_lock:
            for slot in self._slots.values():
                self._check(slot)

    def _check(self, slot: _Slot) -> None:
        path = pointer_path(self.home, slot.component)
        try:
            raw = path.read_bytes()
        except FileNotFoundError:
            raw = None
        except OSError as exc:
            self._fail(slot, f"{path}: cannot read the pointer: {exc.strerror or exc}")
            return
        if raw == slot.pointer_bytes:
            return
        slot.pointer_bytes = raw
        if raw is None:
            if slot.served is not None:
                # Keep the robot's reflex running: a missing pointer is not a reason to stop serving.
                self._fail(slot, f"{path} was removed; still serving {slot.served.version}")
            return
        try:
            pointer = read_pointer(self.home, slot.component)
        except PointerError as exc:
            self._fail(slot, str(exc))
            return
        if pointer is None:  # removed between our read and read_pointer's: the next poll sees it
            slot.pointer_bytes = None
            return
        slot.pointer_version = pointer.get("version") if isinstance(pointer.get("version"), str) else None
        try:
            served = self._load(slot, pointer, path)
        except (CheckpointRefused, BrainError) as exc:
            self._fail(slot, str(exc))
            return
        if served is None:  # the same weights as served now (e.g. the pointer rewritten): nothing to do
            slot.last_error = None
            return
        self._swap(slot, served)

    def _load(self, slot: _Slot, pointer: dict[str, Any], path: Path) -> _Served | None:
        target = pointer.get("checkpoint")
        if not isinstance(target, str) or not target:
            raise BrainError(f"{path}: 'checkpoint' is missing or not a path")
        ckpt = Path(target) if Path(target).is_absolute() else self.home / target
        sha = pointer.get("sha256")
        if sha is not None and not isinstance(sha, str):
            raise BrainError(f"{path}: 'sha256' must be a hex string")
        current = slot.served
        if current is not None and current.checkpoint == ckpt and sha == current.model.sha256:
            return None
        # verify_manifest: a torn or altered checkpoint is refused; each file is hashed once
        model = RUNTIMES[slot.component].from_checkpoint(ckpt, expected_sha256=sha, verify_manifest=True)
        ckpt = model.checkpoint  # a run dir named by hand resolves to its newest complete checkpoint
        if current is not None:
            self._check_fits(slot, current.model, model)
        model.warm()  # so the first real request after the swap pays no first-call costs
        return _Served(model=model, checkpoint=ckpt, pointer=dict(pointer), loaded_at=_utcnow())

    @staticmethod
    def _check_fits(slot: _Slot, old: Any, new: Any) -> None:
        """The robot sends what the served model reads: a model with another observation or action
        layout (the vqvae: observation) would fail every request, so it is refused while the old one
        keeps serving."""
        if new.fit_fields != old.fit_fields:
            def fmt(m):
                shape = frame_shape(m)
                camera = "" if shape is None else f" + a {describe_shape(shape)} camera frame"
                fields = ", ".join(f"{p}[{n}]" for p, n in m.observation_fields)
                return f"{fields}{camera} -> " + ", ".join(f"{p}[{n}]" for p, n in m.action_fields)

            raise BrainError(
                f"{new.checkpoint}: does not fit the {slot.component} being served ({old.version}): it reads "
                f"{fmt(new)}, the served model reads {fmt(old)}; still serving {old.version} "
                "(restart the service to switch to a robot with another layout)")

    def _swap(self, slot: _Slot, served: _Served) -> None:
        old = slot.served
        slot.served = served  # the swap: one reference; in-flight requests keep the object they read
        with slot.lock:
            slot.sessions.clear()  # a state made by other weights means nothing to these
        slot.last_error = None
        log.info("BrainService: %s now serves %s (was %s)", slot.component, served.version,
                 old.version if old else "nothing")
        self._callback(self.on_swap, slot.component, served.version, str(served.checkpoint))

    def _fail(self, slot: _Slot, message: str) -> None:
        if slot.served is not None and "still serving" not in message:
            message = f"{message} (still serving {slot.served.version})"
        if message == slot.last_error:  # a read error that persists: say it once
            return
        slot.last_error = message
        log.warning("BrainService: %s: %s", slot.component, message)
        self._callback(self.on_error, slot.component, message)

    @staticmethod
    def _callback(fn: Callable | None, *args) -> None:
        if fn is None:
            return
        try:
            fn(*args)
        except Exception:  # a hook must never fail a request or kill the watcher
            log.exception("BrainService: callback %r failed", fn)

    # -- inference ------------------------------------------------------------------------------
    def infer(self, component: Any, observation: Any, session: Any = None, reset: Any = False,
              action: Any = None, frame: Any = None) -> dict[str, Any]:
        """One tick of a session: every served component whose observation layout is `component`'s, on
        `observation` (a list of finite numbers, the spec order). `component` is the one the caller
        needs (503 while it is not served). `action`: the action taken on the previous tick (the Mid
        Loop's input; by default the fast_loop's previous answer). mid_serving: the predictor's fields.
        `frame`: the camera frame (brain_frame's forms), required when a served component of the
        answer reads the camera and refused (400) when none does; decoded and encoded before any
        session moves, so a bad image changes no state."""
        started = time.perf_counter()
        slot = self._slots.get(component) if isinstance(component, str) else None
        if slot is None:
            raise BrainError(f"unknown component {component!r}; BrainService serves {', '.join(self._slots)}", 404)
        values = observation_values(observation)
        brain_input.check_session(session)
        if not isinstance(reset, bool):
            raise BrainError(f"reset must be true or false, got {reset!r}")
        served = slot.served  # read once: this request finishes on this object, whatever swaps meanwhile
        if served is None:
            why = f" (the promoted checkpoint was refused: {slot.last_error})" if slot.last_error else ""
            raise BrainError(f"no promoted {component} to serve yet{why}; promote a checkpoint first "
                             f"(run_trainer.py promote RUN)", 503)
        model = served.model
        if len(values) != model.obs_dim:
            raise BrainError(f"observation has {len(values)} values, {served.version} needs {model.obs_dim} "
                             f"({model.describe_observation()})")
        peers = {name: served if name == component else self._peer(name, model.observation_fields)
                 for name in self._slots}
        fast, vq, mid = peers.get(ACTOR), peers.get(TOKENIZER), peers.get(PREDICTOR)
        # the camera: a frame VQ-VAE's codes for each component that reads one, one encode per encoder
        readers = {name: p.model for name, p in peers.items() if p is not None and frame_shape(p.model) is not None}
        seen = check_frame(frame, readers, component, model)
        frame_codes = {} if seen is None else {name: seen.codes(m.frame_vq) for name, m in readers.items()}
        given = None
        if action is not None:  # checked before any state moves: a refused request changes no session
            try:
                given = mid_serving.action_values(action, (mid or served).model.act_dim)
            except ValueError as exc:
                raise BrainError(str(exc)) from None
        answered = None if fast is None else fast_sessions.tick(self._slots[fast.model.name], fast, values, session,
                                                                reset, frame_codes.get(ACTOR), self.max_sessions)
        code = None if vq is None else frame_codes.get(TOKENIZER)
        if vq is not None and code is None:
            code = vq.model.codes_of(np.asarray(values))
        out = {"action": None if answered is None else answered.tolist(),  # float64 -> the same Python floats
               "model_version": served.version, "latency_ms": 0.0, "session": session,
               "code": None if code is None else np.asarray(code).tolist()}
        mid_codes = frame_codes.get(PREDICTOR)
        if mid is not None and mid_codes is None and code is not None and hasattr(mid.model, "same_codes") \
                and mid.model.same_codes(vq.model):  # the tokenizer's codes are the Mid Loop's: encoded once
            mid_codes = code
        out.update(mid_serving.EMPTY if mid is None else
                   mid_serving.answer(self._slots[mid.model.name], mid, np.asarray(values), session, reset, given, answered,
                                      fast.model if fast else None, self.max_sessions, mid_codes))
        # a component with none of the roles above answers with its NumPy form's own output
        others = {name: p.model.answer(np.asarray(values)) for name, p in peers.items()
                  if p is not None and name not in (ACTOR, TOKENIZER, PREDICTOR)}
        if others:
            out["outputs"] = others
        out["versions"] = {name: p.version if p is not None else None for name, p in peers.items()}
        out["latency_ms"] = round((time.perf_counter() - started) * 1000.0, 4)
        for name, p in peers.items():
            if p is not None and not p.first_inference_done:
                self._first_inference(self._slots[name], p)
        return out

    def _peer(self, name: str, fields: list) -> _Served | None:
        """The served model of `name` when it reads the observation layout `fields`, else None."""
        p = self._slots[name].served
        return p if p is not None and p.model.observation_fields == fields else None

    def _first_inference(self, slot: _Slot, served: _Served) -> None:
        with slot.lock:
            if served.first_inference_done:
                return
            served.first_inference_done = True
        # Once per loaded version; `when` is now (the answer exists), the hook runs on the hook thread
        # and reads the attribute as it is then (the webapp rewires it).
        self._hooks.post(lambda *args: self._callback(self.on_first_inference, *args),
                         slot.component, served.version, str(served.checkpoint), _utcnow())

    def wait_hooks(self, timeout: float = 5.0) -> bool:
        """Wait until every queued hook has run (tests; `infer --local` before it exits). True if so."""
        return self._hooks.wait(timeout)

    # -- status ---------------------------------------------------------------------------------
    def status(self) -> dict[str, dict[str, Any]]:
        out = {}
        vq = self._slots[TOKENIZER].served if TOKENIZER in self._slots else None
        for name, slot in self._slots.items():
            served = slot.served
            model = served.model if served else None
            out[name] = {
                "version": served.version if served else None,
                "checkpoint": str(served.checkpoint) if served else None,
                "loaded_at": served.loaded_at.isoformat() if served else None,
                "last_error": slot.last_error,
                "sessions": len(slot.sessions),
                "non_finite": slot.non_finite,
                "pointer_version": slot.pointer_version,
                "obs_dim": model.obs_dim if model else None,
                "act_dim": model.act_dim if model else None,
                "observation_fields": model.spec.observation.dim_names() if model else None,
                "frame_shape": list(shape) if (shape := frame_shape(model)) is not None else None,
                "action_fields": model.spec.action.dim_names() if model else None,
                **status_extra(model, vq.model if vq else None),
            }
        return out

    def version(self, component: str) -> str | None:
        slot = self._slots.get(component)
        return slot.served.version if slot and slot.served else None


__all__ = ["BrainService", "BrainError", "RUNTIMES", "MAX_ABS_OBSERVATION", "MAX_SESSIONS", "observation_values"]
