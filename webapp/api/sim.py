"""The sim reflex over HTTP: the promoted fast_loop driving the dm_control reacher, in the background.

    POST /api/sim/reflex  {"episodes": 1..5 (default 1), "seed": int >= 0 (default 0),
                           "task": "reach" | "track" (default "reach"),
                           "target_jump_s": seconds within the episode (0.02-19.98) | null (default: none)}
         -> 202 {"job": {...}}  (Location: /api/sim/reflex/<job>); 409 while another one runs or
            when no fast_loop has been promoted yet
    GET  /api/sim/reflex/<job>  -> {"job": {"id", "state": running|completed|failed, "episodes",
                                   "seed", "task", "created_at", "finished_at", "elapsed_s",
                                   "result": eval-reflex's JSON | null, "error": str | null,
                                   "frames": {"emitted": int, "error": str | null},
                                   "target_jump_s": number | null,
                                   "surprise": {"mid_loop": version | null, "reason": str | null,
                                                "horizons", "grid_step_s", "records": [...]} | null}}

Each job is `run_trainer.py eval-reflex --checkpoint promoted --json --stream-frames 10 --stream-surprise
[--target-jump-at S]` in a child process (torch and MuJoCo stay out of the webapp), one at a time: the reflex is a demonstration, and
two would only halve each other's speed on the Pi. The last KEEP_JOBS jobs are remembered in memory
(a restart forgets them; their results are not training state).

Frames: the child renders its first episode (at FRAME_FPS frames per simulated second, paced at
`stream_speed` x real time, so the episode plays as it happens) and writes them as JSON lines on
stdout; each is pushed to browsers as Socket.IO `sim.frame` {job_id, episode, seed, step, image (a
data:image/png URL, 128x128), return_so_far, done}, at most MAX_EMITS_PER_S a second (the last frame
of the episode always goes out, so the final return is shown). If the child cannot render, the job
still completes with its result, and "frames": {"error"} says why there were none.

Surprise (docs/reflex.md, "Reflex view: surprise"): with the frames, the child (--stream-surprise) streams the promoted
mid_loop's surprise at every Mid Loop grid point of that episode (eval-reflex's module doc); every
record is kept in the job's "surprise" (none is dropped: 200 small records for 20 s), the page polls
them and plots them. "mid_loop": null with "reason" ("no mid_loop promoted", or why it could not read
the episode) when there are none. `target_jump_s` moves the target at that time
(eval-reflex --target-jump-at) so the surprise has something to react to.
"""
from __future__ import annotations

import itertools
import json
import logging
import math
import secrets
import threading
import time
from datetime import datetime, timezone
from typing import Any

from flask import Blueprint, current_app, jsonify

from hope_models.components import ACTOR, PREDICTOR
from hope_models.promoted import PointerError, read_pointer
from webapp.api.validation import get_int, get_str, json_body
from webapp.errors import ApiError

log = logging.getLogger(__name__)

bp = Blueprint("sim", __name__, url_prefix="/api/sim")

TASKS = ("reach", "track")  # hope_models.sim.reacher.TASKS (not imported: it loads MuJoCo); a test compares
MAX_EPISODES = 5
MAX_SEED = 2**31 - 1
KEEP_JOBS = 20
JOB_TIMEOUT_S = 900.0
FRAME_EVENT = "sim.frame"
FRAME_FPS = 10  # frames per simulated second the child renders
FRAME_SIZE = 128
MAX_EMITS_PER_S = 10.0
STREAM_SPEED = 1.0  # the streamed episode plays in real time (20 s); 0: as fast as the child runs
# A jump must land on a control step inside the episode (reacher.jump_step; MuJoCo stays out of the webapp)
JUMP_MIN_S, JUMP_MAX_S = 0.02, 19.98
MAX_SURPRISE_RECORDS = 1000  # one per grid point of the 1000-step episode at most (a grid point per step)


def _now() -> str:
    return datetime.now(timezone.utc).isoformat()


class ReflexBusy(RuntimeError):
    pass


class ReflexJobs:
    """Background eval-reflex children, one at a time, and the results of the last KEEP_JOBS."""

    def __init__(self, children, *, timeout_s: float = JOB_TIMEOUT_S, socketio: Any = None,
                 stream_speed: float = STREAM_SPEED):
        self.children = children  # webapp.commands.ChildProcesses
        self.timeout_s = timeout_s
        self.socketio = socketio  # where sim.frame goes (create_app sets it); None: frames are not streamed
        self.stream_speed = stream_speed
        self._jobs: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        self._counter = itertools.count(1)
        self._running: str | None = None

    def start(self, *, episodes: int, seed: int, task: str, target_jump_s: float | None = None) -> dict[str, Any]:
        with self._lock:
            if self._running is not None:
                raise ReflexBusy(f"sim reflex job {self._running} is still running; wait for it "
                                 f"(GET /api/sim/reflex/{self._running})")
            job_id = f"reflex-{next(self._counter)}-{secrets.token_hex(3)}"
            job = {"id": job_id, "state": "running", "episodes": episodes, "seed": seed, "task": task,
                   "created_at": _now(), "finished_at": None, "elapsed_s": None, "result": None, "error": None,
                   "frames": {"emitted": 0, "error": None}, "target_jump_s": target_jump_s, "surprise": None}
            self._jobs[job_id] = job
            self._running = job_id
            for old in list(self._jobs)[:-KEEP_JOBS]:
                del self._jobs[old]
            snapshot = _copy(job)
        args = ["eval-reflex", "--checkpoint", "promoted", "--json", "--episodes", str(episodes), "--seed", str(seed),
                "--task", task]
        if target_jump_s is not None:
            args += ["--target-jump-at", repr(float(target_jump_s))]
        if self.socketio is not None:
            args += ["--stream-frames", str(FRAME_FPS), "--stream-size", str(FRAME_SIZE),
                     "--stream-speed", f"{self.stream_speed:g}", "--stream-surprise"]
        threading.Thread(target=self._run, args=(job_id, args), name=f"sim-{job_id}", daemon=True).start()
        return snapshot

    def _frame_consumer(self, job_id: str):
        """on_line for the child's stdout: frame lines become sim.frame events (throttled)."""
        last_emit = [float("-inf")]

        def on_line(line: str) -> bool:
            if line.startswith('{"surprise'):
                return self._surprise_line(job_id, json.loads(line))
            if line.startswith('{"frame_error"'):
                message = str(json.loads(line).get("frame_error"))
                log.warning("sim reflex job %s: no frames: %s", job_id, message)
                self._update_frames(job_id, error=message)
                return True
            if not line.startswith('{"frame"'):
                return False
            frame = json.loads(line).get("frame")
            if not isinstance(frame, dict):
                return False
            now = time.monotonic()
            if now - last_emit[0] < 1.0 / MAX_EMITS_PER_S and not frame.get("done"):
                return True  # dropped: the browser gets at most MAX_EMITS_PER_S
            last_emit[0] = now
            payload = {"job_id": job_id, **{k: frame.get(k) for k in
                                            ("episode", "seed", "step", "image", "return_so_far", "done")}}
            try:
                self.socketio.emit(FRAME_EVENT, payload)
            except Exception:  # noqa: BLE001 - a browser push must not stop the evaluation
                log.exception("could not push %s", FRAME_EVENT)
                return True
            self._update_frames(job_id, emitted=1)
            return True

        return on_line

    def _surprise_line(self, job_id: str, obj: dict[str, Any]) -> bool:
        """A surprise_stream header (again, when the child found the mid_loop cannot read the episode)
        or one grid point's record, into the job."""
        with self._lock:
            job = self._jobs.get(job_id)
            if job is None:
                return True
            if isinstance(obj.get("surprise_stream"), dict):
                header = obj["surprise_stream"]
                records = (job["surprise"] or {}).get("records", [])
                job["surprise"] = {k: header.get(k) for k in (PREDICTOR, "reason", "horizons", "grid_step_s",
                                                               "every_steps")}
                job["surprise"]["records"] = records
            elif isinstance(obj.get("surprise"), dict) and job["surprise"] is not None:
                records = job["surprise"]["records"]
                if len(records) < MAX_SURPRISE_RECORDS:
                    records.append({k: obj["surprise"].get(k) for k in
                                    ("step", "t", "grid_point", "surprise", "surprise_by_horizon")})
        return True

    def _update_frames(self, job_id: str, *, emitted: int = 0, error: str | None = None) -> None:
        with self._lock:
            job = self._jobs.get(job_id)
            if job is not None:
                job["frames"]["emitted"] += emitted
                if error is not None:
                    job["frames"]["error"] = error

    def _run(self, job_id: str, args: list[str]) -> None:
        try:
            on_line = self._frame_consumer(job_id) if "--stream-frames" in args else None
            res = self.children.run(args, timeout_s=self.timeout_s, on_line=on_line)
            if res.code == 0 and isinstance(res.output, dict) and res.output.get("ok", True):
                update = {"state": "completed", "result": res.output}
                frames = res.output.get("frames")
                if on_line is not None and isinstance(frames, dict) and frames.get("error"):
                    self._update_frames(job_id, error=str(frames["error"]))
            elif res.timed_out:
                update = {"state": "failed", "error": f"eval-reflex did not finish within {self.timeout_s:.0f} s"}
            else:
                update = {"state": "failed", "error": res.error()}
            update["elapsed_s"] = res.elapsed_s
        except Exception as exc:  # noqa: BLE001 - a job that cannot start is a failed job, not a dead thread
            log.exception("sim reflex job %s could not run", job_id)
            update = {"state": "failed", "error": f"could not run eval-reflex: {exc}"}
        with self._lock:
            job = self._jobs.get(job_id)
            if job is not None:
                job.update(update, finished_at=_now())
            self._running = None

    def get(self, job_id: str) -> dict[str, Any] | None:
        with self._lock:
            job = self._jobs.get(job_id)
            return _copy(job) if job is not None else None

    def running(self) -> str | None:
        return self._running


def _copy(job: dict[str, Any]) -> dict[str, Any]:
    surprise = job.get("surprise")
    if surprise is not None:
        surprise = {**surprise, "records": list(surprise["records"])}
    return {**job, "frames": dict(job["frames"]), "surprise": surprise}


def _jump_seconds(body: dict[str, Any]) -> float | None:
    """target_jump_s: null/absent, or a number of seconds within the episode; 400 naming it otherwise."""
    value = body.get("target_jump_s")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ApiError(f"target_jump_s: expected a number of seconds, got {json.dumps(value)[:60]}", 400)
    if not JUMP_MIN_S <= value <= JUMP_MAX_S:
        raise ApiError(f"target_jump_s: {value:g} s is not within the episode ({JUMP_MIN_S:g}-{JUMP_MAX_S:g} s)", 400)
    return float(value)


def _state():
    return current_app.extensions["hope"]


@bp.post("/reflex")
def start_reflex():
    body = json_body(allowed=("episodes", "seed", "task", "target_jump_s"))
    episodes = get_int(body, "episodes", default=1, minimum=1, maximum=MAX_EPISODES)
    seed = get_int(body, "seed", default=0, minimum=0, maximum=MAX_SEED)
    task = get_str(body, "task", default="reach", choices=TASKS)
    target_jump_s = _jump_seconds(body)
    state = _state()
    try:
        pointer = read_pointer(state.settings.home, ACTOR)
    except PointerError as exc:
        raise ApiError(f"the {ACTOR} promotion pointer is unusable: {exc}", 409) from None
    if pointer is None:
        raise ApiError("no fast_loop has been promoted yet: promote one first (POST /api/brain/promote or "
                       "`run_trainer.py promote RUN`)", 409)
    try:
        job = state.reflex_jobs.start(episodes=episodes, seed=seed, task=task, target_jump_s=target_jump_s)
    except ReflexBusy as exc:
        raise ApiError(str(exc), 409) from None
    response = jsonify({"job": job})
    response.status_code = 202
    response.headers["Location"] = f"/api/sim/reflex/{job['id']}"
    return response


@bp.get("/reflex/<job_id>")
def get_reflex(job_id: str):
    job = _state().reflex_jobs.get(job_id)
    if job is None:
        raise ApiError(f"no sim reflex job {job_id} (jobs are kept in memory: the last {KEEP_JOBS} since the "
                       "webapp started)", 404)
    return jsonify({"job": job})
