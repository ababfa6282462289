"""`run_trainer.py eval-reflex`: a fast_loop in closed loop in the reacher, against the expert and random.

    run_trainer.py eval-reflex --checkpoint runs/reach [--episodes 20] [--seed 0] [--task reach|track] [--json]
    run_trainer.py eval-reflex --checkpoint promoted ... [--stream-frames FPS] [--stream-surprise] [--target-jump-at S]

The policy is stepped one tick per 20 ms control step with its recurrent state (ReflexPolicy), on
seeds S .. S+N-1; the expert and a uniform-random policy run on the same seeds. With --json one
object is printed:

    {"mean_return", "success_rate", "time_to_reach_s", "expert_mean_return", "random_mean_return",
     "episodes": N, "task", "seeds": [S, S+N-1], "checkpoint", "version", "expert_success_rate",
     "random_success_rate", "reached", "per_episode": [{"seed", "return", "success", "time_to_reach_s",
     "expert_return", "random_return"}], "elapsed_s"}

and, for a camera reflex, "render": {"style", "from"}: how its frames were drawn (`--render`, or by
default as in the episodes it was trained on: hope_models/promote/render_style.py).

`--checkpoint promoted` reads the promotion pointer $HOPE_HOME/promoted/fast_loop.json, a JSON object
whose "checkpoint" names the checkpoint dir (absolute, or relative to $HOPE_HOME). Until a fast_loop
has been promoted there is none, and the command says so (exit 2).
Exit 0 after an evaluation, 2 for a usage error (no such checkpoint, not a fast_loop, a spec that
does not read the reacher's observation).

Frames: `--stream-frames FPS [--stream-size 128] [--stream-speed 1.0]` renders the policy's first
episode and writes one JSON line per frame on stdout while it runs, before the result (which stays
the last line; hope_models/sim/frames.py has the format):

    {"frame": {"episode": 0, "seed", "step", "image": "data:image/png;base64,...", "return_so_far", "done"}}

FPS frames per simulated second, the episode paced at --stream-speed x real time (1.0: 20 s for the
1000 steps; 0: as fast as it runs). MUJOCO_GL is set to "egl" before dm_control is imported (unless it
names another GL backend). If the frames cannot be rendered, a {"frame_error": "..."} line says why,
the evaluation goes on, and the result's "frames" {"fps", "size", "speed", "sent", "error"} reports
sent = 0 and the error; if dm_control cannot even be imported with that backend, the command fails
(exit 2) with the reason. The expert and random episodes are never rendered.

Surprise: `--stream-surprise` shows the policy's first episode to the mid_loop promoted in $HOPE_HOME
(hope_models/components/mid_loop/surprise_stream.py: BrainService's session and surprise, fed the sim's
observations and the actions the reflex takes), and writes one line per Mid Loop grid point (every 5
control steps, rendered or not; with --stream-frames, among the frames) after a header line:

    {"surprise_stream": {"mid_loop": version | null, "reason": null | "no mid_loop promoted" | why not,
                         "horizons", "horizons_s", "grid_step_s", "every_steps", "window_k", "target_jump_s"}}
    {"surprise": {"step", "t", "grid_point", "surprise", "surprise_by_horizon"}}

The result's "surprise" {"mid_loop", "reason", "records", "non_finite"} sums it up. A mid_loop that
cannot read the reacher's observation is a reason, not a failure: the reflex is still evaluated.

Target jump: `--target-jump-at SECONDS` moves the target at that time in every episode (the policy's,
the expert's and random's; reacher.py's jump_position, drawn from the seed), to see the reflex and
the Mid Loop react to the unexpected.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from hope_models.child_result import add_result_argument, write_result
from hope_models.cli.argtypes import non_negative_int, positive_int
from hope_models.components import PREDICTOR
from hope_models.numbers import NumberError, float_from_text
from hope_models.settings import SettingsError, load_settings

PROMOTED = "promoted"
POINTER_DIR = "promoted"
POINTER_FILE = "fast_loop.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hope_models.sim.reacher import RENDER_STYLES, TASKS  # lazy: loads numpy

    parser.add_argument("--checkpoint", required=True, metavar="PATH|promoted",
                        help="a fast_loop run dir or checkpoints/<step> dir, or 'promoted' for the promoted one")
    parser.add_argument("--episodes", type=positive_int, default=20, help="episodes (seeds) to evaluate (default 20)")
    parser.add_argument("--seed", type=non_negative_int, default=0,
                        help="first seed (default 0); seeds S..S+N-1, held out from sim-demos' default 100000+")
    parser.add_argument("--task", choices=TASKS, default="reach", help="reach or track (default reach)")
    parser.add_argument("--render", choices=RENDER_STYLES, default=None,
                        help="how a camera reflex's frames are drawn (default: as in the episodes it was trained on, "
                             "provenance.sim.render; flat when they are not here)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1: one tick is tiny)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    add_result_argument(parser)
    parser.add_argument("--stream-frames", type=_fps, default=None, metavar="FPS",
                        help="stream the first episode's frames as JSON lines on stdout, FPS per simulated second")
    parser.add_argument("--stream-size", type=positive_int, default=128, metavar="PX",
                        help="streamed frame size, square (default 128)")
    parser.add_argument("--stream-speed", type=_speed, default=1.0, metavar="X",
                        help="pace the streamed episode at X times real time (default 1; 0: as fast as it runs)")
    parser.add_argument("--stream-surprise", action="store_true",
                        help="stream the promoted mid_loop's surprise at each grid point of the first episode as "
                             "JSON lines on stdout (a header says when no mid_loop is promoted)")
    parser.add_argument("--target-jump-at", type=_jump, default=None, metavar="SECONDS",
                        help="move the target to a new position (drawn from the seed, inside the arm's reach) at "
                             "SECONDS into every episode (0.02-19.98; default: it never moves on reach)")


def _fps(text: str) -> float:
    from hope_models.sim.frames import MAX_FPS  # lazy: loads numpy

    try:  # the one rule for numbers (hope_models/numbers.py)
        return float_from_text("--fps", text, above=0.0, maximum=MAX_FPS)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason) from None


def _speed(text: str) -> float:
    try:
        return float_from_text("--stream-speed", text, minimum=0.0)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason) from None


def _jump(text: str) -> float:
    from hope_models.sim.reacher import jump_step  # lazy: loads numpy

    try:
        value = float_from_text("--target-jump-at", text)
        jump_step(value)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason) from None
    except ValueError as exc:  # outside the episode
        raise argparse.ArgumentTypeError(f"--target-jump-at {text}: {exc}") from None
    return value


def _surprise_tick(args, out):
    """(on_tick for the streamed episode, the result's "surprise" summary) for the promoted mid_loop;
    the header line is written at once, so a reader knows whether records will follow."""
    from hope_models.components.mid_loop.surprise_stream import SurpriseStream  # lazy: loads numpy
    from hope_models.sim.reacher import CONTROL_PERIOD_S  # lazy: loads numpy

    try:
        stream, reason = SurpriseStream.promoted(load_settings().home, CONTROL_PERIOD_S)
    except SettingsError as exc:
        stream, reason = None, f"no $HOPE_HOME to read the mid_loop pointer from: {exc}"
    summary = {PREDICTOR: stream.mid.version if stream else None, "reason": reason, "records": 0, "non_finite": 0}
    header = {**(stream.describe() if stream else {PREDICTOR: None}), "reason": reason,
              "target_jump_s": args.target_jump_at}

    def write(obj) -> None:
        out.write(json.dumps(obj, allow_nan=False) + "\n")
        out.flush()

    write({"surprise_stream": header})
    if stream is None:
        return None, summary

    def on_tick(step, observation, action) -> None:
        if summary["reason"] is not None:
            return
        if step == 0:
            try:
                stream.check_fits(observation, len(action))
            except ValueError as exc:  # a mid_loop of another robot: say so once, keep evaluating
                summary["reason"] = f"the promoted mid_loop cannot read this episode: {exc}"
                write({"surprise_stream": {**header, "reason": summary["reason"]}})
                return
        record = stream.tick(step, observation, action)
        if record is not None:
            write({"surprise": record})
            summary["records"] += 1
            summary["non_finite"] = stream.non_finite

    return on_tick, summary


def _prepare_gl(why: str = "--stream-frames") -> str | None:
    """Choose EGL before dm_control is imported (a GL backend the user exported wins; "disabled",
    which a parent that ran the sim without frames may pass down, does not) and import it; the
    reason when that fails."""
    if "dm_control" not in sys.modules and os.environ.get("MUJOCO_GL", "").strip().lower() in ("", "disabled"):
        os.environ["MUJOCO_GL"] = "egl"
    try:
        from hope_models.sim.reacher import _dm_control  # lazy: loads numpy

        _dm_control(frames=True)
    except Exception as exc:  # noqa: BLE001 - ImportError, RuntimeError, OpenGL errors: all mean "no frames"
        instead = "run without --stream-frames, or " if why == "--stream-frames" else ""
        return (f"cannot render the reacher for {why} (MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r}): "
                f"{type(exc).__name__}: {exc}; {instead}make that backend work (MUJOCO_GL=egl needs libEGL, "
                "e.g. Mesa's libegl1)")
    return None


def _camera_gl(policy, args: argparse.Namespace) -> str | None:
    """A camera reflex sees rendered frames: EGL, unless --stream-frames chose it already."""
    if policy.frame is None or args.stream_frames is not None:
        return None
    return _prepare_gl(f"the policy's camera ({policy.frame.path})")


def resolve_promoted(home: Path) -> Path:
    """The checkpoint the fast_loop promotion pointer names; FileNotFoundError/ValueError with the reason."""
    pointer = home / POINTER_DIR / POINTER_FILE
    if not pointer.is_file():
        raise FileNotFoundError(f"no promoted fast_loop exists yet ({pointer} not found); promote a checkpoint first "
                                "or pass --checkpoint PATH (a fast_loop run dir or checkpoint dir)")
    try:
        obj = json.loads(pointer.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{pointer}: not readable JSON: {exc}") from None
    ckpt = obj.get("checkpoint") if isinstance(obj, dict) else None
    if not isinstance(ckpt, str) or not ckpt:
        raise ValueError(f"{pointer}: must be a JSON object with a 'checkpoint' path")
    path = Path(ckpt)
    return path if path.is_absolute() else home / path


def _fail(args, message: str) -> int:
    write_result(args.result_file, {"ok": False, "error": message})
    if args.json:
        print(json.dumps({"ok": False, "error": message}))
    print(f"error: {message}", file=sys.stderr)
    return 2


def _result(policy, args: argparse.Namespace, seeds: list[int], res, expert, rand, started: float) -> dict:
    """The result object (module doc) of the policy's, the expert's and random's evaluations."""
    from hope_models.sim.evaluate import json_number  # lazy: loads numpy

    return {
        "ok": True,
        "mean_return": json_number(res.mean_return),
        "success_rate": json_number(res.success_rate),
        "time_to_reach_s": json_number(res.time_to_reach_s),
        "expert_mean_return": json_number(expert.mean_return),
        "random_mean_return": json_number(rand.mean_return),
        "episodes": len(res.episodes),
        "task": args.task,
        "seeds": [seeds[0], seeds[-1]],
        "checkpoint": str(policy.checkpoint_dir),
        "version": policy.version,
        "reached": res.reached,
        "expert_success_rate": json_number(expert.success_rate),
        "random_success_rate": json_number(rand.success_rate),
        "per_episode": [
            {"seed": p.seed, "return": p.ret, "success": p.success, "time_to_reach_s": p.time_to_reach_s,
             "expert_return": e.ret, "random_return": r.ret}
            for p, e, r in zip(res.episodes, expert.episodes, rand.episodes, strict=True)],
        "elapsed_s": round(time.perf_counter() - started, 2),
    }


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    ckpt_arg = args.checkpoint
    if ckpt_arg == PROMOTED:
        try:
            ckpt_arg = str(resolve_promoted(load_settings().home))
        except (FileNotFoundError, ValueError, SettingsError) as exc:
            return _fail(args, str(exc))

    if args.stream_frames is not None:
        from hope_models.sim.frames import MAX_SIZE, MIN_SIZE  # lazy: loads numpy

        if not MIN_SIZE <= args.stream_size <= MAX_SIZE:
            return _fail(args, f"--stream-size {args.stream_size} must be within {MIN_SIZE}-{MAX_SIZE}")
        problem = _prepare_gl()  # before torch and anything else that could import dm_control
        if problem is not None:
            return _fail(args, problem)

    import torch  # lazy: loads torch

    from hope_models.promote.reflex_policy import ReflexPolicy, ReflexPolicyError  # lazy: loads numpy

    # lazy: loads numpy
    from hope_models.sim.evaluate import evaluate_policy, expert_factory, random_factory

    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)  # as training does (job_setup.torch_settings): subnormals only cost time
    try:
        policy = ReflexPolicy.from_checkpoint(ckpt_arg)
    except ReflexPolicyError as exc:
        return _fail(args, str(exc))
    if (problem := _camera_gl(policy, args)) is not None:
        return _fail(args, problem)
    if args.render is not None:
        policy.render_style, policy.render_from = args.render, "--render"
    seeds = list(range(args.seed, args.seed + args.episodes))
    stream = on_tick = surprise = None
    if args.stream_frames is not None:
        from hope_models.sim.frames import FrameStream  # lazy: loads numpy

        stream = FrameStream(sys.stdout, fps=args.stream_frames, size=args.stream_size, speed=args.stream_speed)
    if args.stream_surprise:
        on_tick, surprise = _surprise_tick(args, sys.stdout)
    jump = args.target_jump_at
    res = evaluate_policy(policy, seeds, args.task, frames=stream, target_jump_s=jump, on_tick=on_tick)
    if stream is not None and stream.error is not None:
        print(f"warning: no frames were streamed: {stream.error}", file=sys.stderr)
    expert = evaluate_policy(expert_factory, seeds, args.task, target_jump_s=jump)
    rand = evaluate_policy(random_factory, seeds, args.task, target_jump_s=jump)
    out = _result(policy, args, seeds, res, expert, rand, started)
    camera = {"style": policy.render_style, "from": policy.render_from} if policy.frame is not None else None
    extras = {"render": camera, "target_jump_s": jump, "frames": None if stream is None else stream.summary(),
              "surprise": surprise}
    out.update({k: v for k, v in extras.items() if v is not None})
    write_result(args.result_file, out)
    if args.json:
        print(json.dumps(out))
    else:
        ttr = "n/a" if res.time_to_reach_s is None else f"{res.time_to_reach_s:.2f} s"
        print(f"{policy.version} on {args.task}, seeds {seeds[0]}-{seeds[-1]}: mean return {res.mean_return:.1f} "
              f"(expert {expert.mean_return:.1f}, random {rand.mean_return:.1f}), success {res.success_rate:.0%}, "
              f"time to reach {ttr} ({res.reached}/{len(seeds)} reached)")
    return 0
