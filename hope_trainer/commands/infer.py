"""`hope-trainer infer`: one tick of the promoted models, from the shell.

    hope-trainer infer --observation '[0.1, -0.2, 0.3, 0.05, -0.4, 0.2]' [--component fast_loop]
                         [--session S] [--reset] [--action '[0.2, -0.1]'] [--frame camera.png] [--json]
                         [--local] [--timeout 5]

By default it asks the running service (`hope-trainer serve` or `webapp`): POST /api/brain/infer
on the configured host and inference port (the robot's door, 8766, HOPE_INFERENCE_PORT; the
editor's port when that setting is 0, "any free port", which a second process cannot know) with the
token from $HOPE_HOME/token, so the answer comes from the BrainService the robot uses, through the
robot's own door (and a --session there keeps its recurrent state between calls).
When nothing answers it says so and suggests `serve`, or --local, which loads BrainService in this
process from the promotion pointer and answers one tick (torch-free, like the service; a --session
then lasts only this command, so every --local call is an episode's first tick).

Prints the action, the model version that produced it and the latency, and, when a vqvae and a
mid_loop are promoted, the observation's code, the Mid Loop's prediction at each horizon and the
surprise (hope_models/components/mid_loop/serving.py defines it; it needs a --session ticked for one horizon
on the service). --action is the action the robot actually took on the previous tick (the Mid
Loop's input; default: the fast_loop's previous answer). --frame: a JPEG or PNG file sent as the
request's camera frame, for a served model that reads the camera (resized by the service to its
frame size). --json: the service's answer ("action",
"model_version", "latency_ms", "session", "code", "prediction", "surprise", ...) plus "via":
"http" | "local".
Exit 0 answered; 1 nothing could answer (no service running, no promoted model yet, or the model
computed a non-finite action: a 500); 2 bad input (the message says what is wrong: wrong length,
NaN, a value beyond +-1e6, not a list of numbers, unknown component, a frame that is not an image,
no frame for a model that reads the camera or one for a model that does not).
"""
from __future__ import annotations

import argparse
import base64
import json
import sys
import urllib.error
import urllib.request
from typing import TYPE_CHECKING, Any

from hope_models.components import ACTOR
from hope_models.numbers import NumberError, float_from_text
from hope_models.settings import SettingsError, load_settings

if TYPE_CHECKING:
    from hope_models.settings import Settings

NOT_ANSWERED_EXIT = 1
USAGE_EXIT = 2


class InferFailure(Exception):
    def __init__(self, message: str, code: int):
        super().__init__(message)
        self.code = code


def _timeout_s(text: str) -> float:
    try:  # the one rule for numbers (hope_models/numbers.py)
        return float_from_text("--timeout", text, above=0.0, maximum=600.0)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason + " (seconds)") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--component", default=ACTOR, metavar="C",
                        help=f"the component whose answer is needed (default {ACTOR}; every other promoted "
                             "component with the same observation layout answers too)")
    parser.add_argument("--observation", required=True, metavar="JSON",
                        help="the observation as a JSON list of numbers, in the model's feature order "
                             "(GET /api/brain or `infer --json` of a wrong length lists the fields)")
    parser.add_argument("--session", default=None, metavar="S",
                        help="keep recurrent state under this name between calls (on the service)")
    parser.add_argument("--reset", action="store_true", help="start the session's episode again with this tick")
    parser.add_argument("--action", default=None, metavar="JSON",
                        help="the action taken on the previous tick, a JSON list (the Mid Loop's input)")
    parser.add_argument("--frame", default=None, metavar="FILE",
                        help="a camera frame (JPEG or PNG file) sent with the joints, for a model that reads the camera")
    parser.add_argument("--local", action="store_true",
                        help="answer in this process from the promoted pointer instead of asking the service")
    parser.add_argument("--timeout", type=_timeout_s, default=5.0, help="HTTP timeout in seconds (default 5)")
    parser.add_argument("--json", action="store_true", help="print the answer as JSON on stdout")


def _observation(text: str, flag: str = "--observation") -> list[float]:
    from hope_models.runtime.brain_service import BrainError, observation_values  # lazy: loads numpy

    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InferFailure(f"{flag} is not valid JSON ({exc}); give a list like '[0.1, -0.2]'",
                           USAGE_EXIT) from None
    try:
        return observation_values(obj)
    except BrainError as exc:
        raise InferFailure(f"{flag}: {exc}", USAGE_EXIT) from None


def _frame(path: str) -> str:
    """The file's bytes as the request's `frame` (base64; the service decodes and checks the image)."""
    from hope_models.runtime.brain_frame import MAX_FRAME_CHARS  # lazy: loads numpy

    limit = MAX_FRAME_CHARS * 3 // 4
    try:
        with open(path, "rb") as fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise InferFailure(f"--frame {path}: cannot read: {exc.strerror or exc}", USAGE_EXIT) from None
    if len(data) > limit:
        raise InferFailure(f"--frame {path}: more than {limit} bytes; send the camera's frame, not a large photo",
                           USAGE_EXIT)
    return base64.b64encode(data).decode("ascii")


def _base_url(settings: Settings) -> str:
    port = settings.inference_port or settings.port
    host = settings.host
    if host in ("", "0.0.0.0", "::"):  # bound to every interface: this machine answers on loopback
        host = "127.0.0.1"
    if ":" in host:
        host = f"[{host}]"
    return f"http://{host}:{port}"


def _via_http(settings: Settings, body: dict[str, Any], timeout: float) -> dict[str, Any]:
    from webapp.auth import TokenError, read_token, token_path  # lazy: loads flask

    base = _base_url(settings)
    hint = ("start the service with `python run_trainer.py serve`, or answer in this process with --local")
    path = token_path(settings)
    if not path.exists():
        raise InferFailure(f"no API token at {path}: the service has never run with HOPE_HOME={settings.home}; "
                           f"{hint}", NOT_ANSWERED_EXIT)
    try:
        token = read_token(path)
    except TokenError as exc:
        raise InferFailure(str(exc), USAGE_EXIT) from None
    req = urllib.request.Request(f"{base}/api/brain/infer", data=json.dumps(body).encode("utf-8"), method="POST",
                                 headers={"Content-Type": "application/json", "Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            return json.loads(resp.read().decode("utf-8"))
    except urllib.error.HTTPError as exc:
        try:
            message = json.loads(exc.read().decode("utf-8")).get("error") or exc.reason
        except (ValueError, AttributeError, UnicodeDecodeError):
            message = exc.reason
        if exc.code == 401:
            raise InferFailure(f"{base} refused the token in {path} (is that service running with another "
                               "HOPE_HOME?)", USAGE_EXIT) from None
        # 5xx: the service could not answer (no model yet, or the model computed a non-finite action)
        code = NOT_ANSWERED_EXIT if (exc.code == 404 and "component" not in str(message)) or exc.code >= 500 \
            else USAGE_EXIT
        if exc.code == 404 and "component" not in str(message):
            message = f"{message} (is the service at {base} a HOPE serve/webapp with the brain API?)"
        raise InferFailure(f"{base}: {exc.code}: {message}", code) from None
    except (urllib.error.URLError, ConnectionError, TimeoutError, OSError) as exc:
        reason = getattr(exc, "reason", exc)
        raise InferFailure(f"nothing answers at {base} ({reason}); {hint}", NOT_ANSWERED_EXIT) from None
    except ValueError as exc:
        raise InferFailure(f"{base}: the answer is not JSON ({exc})", NOT_ANSWERED_EXIT) from None


def _record_first_inference(settings: Settings):
    """on_first_inference for --local: the loop-closure time goes into the registry as with serve."""
    def record(component: str, version: str, checkpoint: str, when) -> None:
        from registry import promotion  # lazy: loads sqlalchemy
        from registry.db import Registry  # lazy: loads sqlalchemy

        with Registry.open(settings) as registry, registry.session() as s:
            promotion.record_first_inference(s, checkpoint, when)

    return record


def _via_local(settings: Settings, body: dict[str, Any]) -> dict[str, Any]:
    from hope_models.runtime.brain_service import BrainError, BrainService  # lazy: loads numpy

    try:
        brain = BrainService(settings.home, on_first_inference=_record_first_inference(settings))
    except ValueError as exc:
        raise InferFailure(str(exc), USAGE_EXIT) from None
    brain.check_now()  # load the promoted model once; no watcher thread for one answer
    try:
        return brain.infer(body["component"], body["observation"], body.get("session"), body.get("reset", False),
                           action=body.get("action"), frame=body.get("frame"))
    except BrainError as exc:
        raise InferFailure(str(exc), NOT_ANSWERED_EXIT if exc.status >= 500 else USAGE_EXIT) from None
    finally:
        brain.stop()  # runs the queued first-inference record before the process exits


def run(args: argparse.Namespace) -> int:
    try:
        settings = load_settings()
        body: dict[str, Any] = {"component": args.component, "observation": _observation(args.observation)}
        if args.session is not None:
            body["session"] = args.session
        if args.reset:
            body["reset"] = True
        if args.action is not None:
            body["action"] = _observation(args.action, "--action")
        if args.frame is not None:
            body["frame"] = _frame(args.frame)
        via = "local" if args.local else "http"
        out = _via_local(settings, body) if args.local else _via_http(settings, body, args.timeout)
    except SettingsError as exc:
        return _fail(args, str(exc), USAGE_EXIT)
    except InferFailure as exc:
        return _fail(args, str(exc), exc.code)
    out = {**out, "via": via}
    if args.json:
        print(json.dumps(out), flush=True)
    else:
        print(_text(out, via))
    return 0


def _text(out: dict[str, Any], via: str) -> str:
    action = "none (no fast_loop answered)" if out.get("action") is None else \
        "[" + ", ".join(f"{v:.6g}" for v in out["action"]) + "]"
    lines = [f"action {action}  version {out.get('model_version')}  latency {out.get('latency_ms') or 0:.3f} ms"
             f"  ({'in this process' if via == 'local' else 'from the service'})"]
    if out.get("code") is not None:
        lines.append(f"code {out['code']}")
    for label, obs in (out.get("prediction") or {}).items():
        lines.append(f"prediction +{label}: [{', '.join(f'{v:.6g}' for v in obs)}]")
    if out.get("prediction") is not None:
        s = out.get("surprise")
        lines.append("surprise: none yet (tick a --session for one horizon)" if s is None else f"surprise {s:.4g} nats")
    return "\n".join(lines)


def _fail(args: argparse.Namespace, message: str, code: int) -> int:
    if args.json:
        print(json.dumps({"error": message}), flush=True)
    print(f"error: {message}", file=sys.stderr)
    return code
