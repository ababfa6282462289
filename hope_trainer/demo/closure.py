"""Step 4 of the demo: the loop closure. Auto-promotion gates each completed run; as soon as
BrainService serves the new fast_loop, one inference goes through the HTTP API with the token, on
the inference port as a robot's would (that first answer closes the loop, and its run's
loop-closure time is recorded).

`ClosureSteps` is a part of `Demo` (hope_trainer/demo/session.py): it reads the session's `serve`,
`settings`, `inference_url`, `token`, `first_observation` and sets `inference`, and waits with its `sleep`.
"""
from __future__ import annotations

import base64
import json
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hope_models.components import ACTOR
from hope_models.media import decode_still
from hope_trainer.demo.report import gate_outcome
from hope_trainer.demo.shared import CLOSURE_WAIT_S, COMPONENTS, GATE_WAIT_S, SERVE_WAIT_S, DemoError, say

if TYPE_CHECKING:
    from hope_models.settings import Settings

BRAIN_TICKS = 75  # 1.5 s of 20 ms ticks: past the Mid Loop's 1 s horizon, so a surprise is due


def raw_frame(path: Path, height: int, width: int) -> dict[str, Any]:
    """A recorded camera frame at the size it was recorded (the served model's) as a request's raw
    `frame` (hope_models/runtime/brain_frame.py): uint8 RGB bytes, base64."""
    pixels = decode_still(path, (height, width))
    return {"encoding": "raw", "shape": list(pixels.shape), "data": base64.b64encode(pixels.tobytes()).decode()}


def _not_serving_yet(answer: dict[str, Any]) -> bool:
    """The robot's port answered that it serves no promoted model yet (HTTP 503): it may a moment later."""
    return str(answer.get("error", "")).startswith("HTTP 503")


class ClosureSteps:
    # what Demo (session.py) provides; annotations only, nothing is set here
    serve: Any
    settings: Settings
    inference_url: str | None
    token: str | None
    first_observation: tuple[dict[str, Any], list[float]] | None
    inference: dict[str, Any] | None
    door_answer: dict[str, Any] | None

    if TYPE_CHECKING:
        def sleep(self, seconds: float) -> None: ...
        def _runs(self, ids: list[str]) -> list[dict[str, Any]]: ...
        def loop_closed(self) -> None: ...

    def _gating_idle(self) -> bool:
        """Auto-promotion has nothing running and nothing left to gate: waiting longer is useless."""
        promoter = getattr(self.serve.daemon, "autopromoter", None)
        return promoter is not None and not promoter.busy and promoter.next_run() is None

    def _gate(self, run_id: str) -> dict[str, Any] | None:
        with self.serve.registry.session(readonly=True) as s:
            return gate_outcome(s, run_id)

    def _try_close_loop(self, fast_id: str, display: Any = None) -> bool:
        """One look: if the fast_loop run was promoted and BrainService serves it, infer once."""
        gate = self._gate(fast_id)
        if gate is None or gate["state"] != "promoted":
            return False
        status = (self.serve.brain.status().get(ACTOR) or {})
        if status.get("version") != gate["version"]:
            return False
        # The robot's port is another process with its own BrainService: it follows the pointer on
        # its own poll, so it may answer with nothing or the previous version for a moment.
        inf = self.infer_over_http()
        if _not_serving_yet(inf) or (not inf.get("error") and inf.get("model_version") != gate["version"]):
            self.door_answer = inf
            return False
        if display is not None:
            display.close()
        say(f"4. promoted and served: fast_loop {gate['version']}")
        self.inference = inf
        if inf.get("error"):
            say(f"   inference failed: {inf['error']}")
        else:
            say(f"   POST /api/brain/infer -> action [{', '.join(f'{v:+.3f}' for v in inf['action'])}] "
                f"(expert [{', '.join(f'{v:+.3f}' for v in inf['expert_action'])}]), {inf['model_version']}, "
                f"{inf['latency_ms']:.2f} ms")
        self.loop_closed()
        return True

    def close_loop(self, fast_id: str) -> dict[str, Any] | None:
        """After the chain: wait for the fast_loop's gate and BrainService (when not done already)."""
        deadline = time.monotonic() + GATE_WAIT_S
        promoted_at: float | None = None
        while self.inference is None:
            gate = self._gate(fast_id)
            if gate is not None and gate["state"] != "promoted":
                return gate  # refused or failed: the summary says why
            now = time.monotonic()
            if gate is None and (now > deadline or self._gating_idle()):
                self.sleep(1.0)  # the daemon's next tick may just not have spawned the child yet
                if self._gate(fast_id) is None and self._gating_idle():
                    return None  # nothing will gate it (the summary says "not gated")
            if gate is None and now > deadline:
                raise DemoError(f"the fast_loop run {fast_id} was not gated within {GATE_WAIT_S:.0f} s "
                                f"(see {Path(self.settings.home) / 'logs' / 'promote.log'})")
            if gate is not None:
                promoted_at = promoted_at or now
                if now - promoted_at > SERVE_WAIT_S:
                    status = self.serve.brain.status().get(ACTOR) or {}
                    door = self.door_answer or {}
                    raise DemoError(f"BrainService does not serve {gate['version']} {SERVE_WAIT_S:.0f} s after its "
                                    f"promotion (serving {status.get('version')}; last error: "
                                    f"{status.get('last_error')}; the robot's port answered: "
                                    f"{door.get('error') or door.get('model_version')})")
            self._try_close_loop(fast_id)
            self.sleep(0.3)
        return self._gate(fast_id)

    def brain_inference(self, gates: dict[str, Any], ids: list[str], data: Path) -> dict[str, Any] | None:
        """Once the gate promoted the chain's vqvae and mid_loop and BrainService serves them: one
        session ticked through the first 1.5 s of the first demonstration (a Mid Loop prediction
        made one horizon ago is then due), and its last answer: action, code, prediction, surprise."""
        wanted = {c: (gates.get(i) or {}) for c, i in zip(COMPONENTS, ids, strict=False)}
        if any(g.get("state") != "promoted" for g in wanted.values()):
            return None  # the summary already says which one the gate refused
        deadline = time.monotonic() + SERVE_WAIT_S
        while any((self.serve.brain.status().get(c) or {}).get("version") != g["version"] for c, g in wanted.items()):
            refused = self._refused_by_brain(wanted)
            if refused:
                return {"error": refused}
            if time.monotonic() > deadline:
                return {"error": f"BrainService does not serve the promoted {', '.join(wanted)} after {SERVE_WAIT_S:.0f} s"}
            self.sleep(0.2)
        observations = list(self._observations(data, BRAIN_TICKS))
        want = {c: g["version"] for c, g in wanted.items()}
        while True:  # the robot's port follows the pointers on its own poll (_try_close_loop)
            answer = self._post_infer({"component": ACTOR, **observations[0][0], "session": "demo-brain", "reset": True})
            if not answer.get("error") and all((answer.get("versions") or {}).get(c) == v for c, v in want.items()):
                break
            if answer.get("error") and not _not_serving_yet(answer):
                return answer
            if time.monotonic() > deadline:
                return {"error": f"the robot's port does not answer with the promoted {want} after {SERVE_WAIT_S:.0f} s: "
                                 f"{answer.get('error') or answer.get('versions')}"}
            self.sleep(0.2)
        for seen, _expert in observations[1:]:
            answer = self._post_infer({"component": ACTOR, **seen, "session": "demo-brain", "reset": False})
            if answer.get("error"):
                return answer
        return {**answer, "ticks": BRAIN_TICKS}

    def _refused_by_brain(self, wanted: dict[str, dict[str, Any]]) -> str | None:
        """Why BrainService will not serve a promoted version (it read that pointer and refused the
        checkpoint), or None: then waiting may still see it served."""
        status = self.serve.brain.status()
        for name, gate in wanted.items():
            st = status.get(name) or {}
            if st.get("pointer_version") == gate["version"] and st.get("version") != gate["version"] \
                    and st.get("last_error"):
                return f"BrainService does not serve the promoted {name} {gate['version']}: {st['last_error']}"
        return None

    def _observations(self, data: Path, n: int) -> list[tuple[dict[str, Any], list[float]]]:
        """The first n steps of the first demonstration: (what a request carries of it, the expert's
        command), the request's part being the observation vector in the spec's order (joint
        positions, joint velocities, the target offset when recorded) and, for a camera
        observation, its frame."""
        episode = sorted(p for p in data.iterdir() if p.is_dir())[0]
        out = []
        with open(episode / "steps" / "000000.jsonl", encoding="utf-8") as f:
            for line in f:
                step = json.loads(line)
                o = step["observation"]
                obs = [*o["robot_state"]["joint_positions"], *o["robot_state"]["joint_velocities"],
                       *o.get("target_offset", [])]
                seen: dict[str, Any] = {"observation": [float(v) for v in obs]}
                if "camera" in o:
                    cam = o["camera"]
                    seen["frame"] = raw_frame(episode / cam["uri"], int(cam["height"]), int(cam["width"]))
                out.append((seen, [float(v) for v in step["action"]["command"]]))
                if len(out) == n:
                    break
        return out

    def _observation(self, data: Path) -> tuple[dict[str, Any], list[float]]:
        """The first step of the first demonstration (_observations)."""
        return self._observations(data, 1)[0]

    def infer_over_http(self) -> dict[str, Any]:
        assert self.first_observation is not None, "the demo reads its first observation before it infers"
        seen, expert = self.first_observation
        answer = self._post_infer({"component": ACTOR, **seen, "session": "demo", "reset": True})
        return answer if answer.get("error") else {**answer, "observation": seen["observation"],
                                                   "expert_action": expert}

    def _post_infer(self, request: dict[str, Any]) -> dict[str, Any]:
        body = json.dumps(request).encode()
        assert self.inference_url is not None, "the demo starts the server before it infers"
        req = urllib.request.Request(self.inference_url.rstrip("/") + "/api/brain/infer", data=body, method="POST",
                                     headers={"Content-Type": "application/json",
                                              "Authorization": f"Bearer {self.token}"})
        try:
            with urllib.request.urlopen(req, timeout=10) as resp:
                answer = json.loads(resp.read())
        except urllib.error.HTTPError as exc:
            return {"error": f"HTTP {exc.code}: {exc.read().decode('utf-8', 'replace')[:300]}"}
        except (urllib.error.URLError, OSError, ValueError) as exc:
            return {"error": str(exc)}
        return answer

    def loop_closure(self, fast_id: str) -> float | None:
        from registry import runs  # lazy: loads sqlalchemy

        deadline = time.monotonic() + CLOSURE_WAIT_S
        while True:
            with self.serve.registry.session(readonly=True) as s:
                value = runs.get_run(s, fast_id).loop_closure_s
            if value is not None or time.monotonic() > deadline:
                return value
            self.sleep(0.2)

    def wait_gates(self, ids: list[str]) -> dict[str, dict[str, Any] | None]:
        """Every completed member's gate outcome (the mid_loop's gate runs after the chain ends)."""
        objs = {o["id"]: o for o in self._runs(ids)}
        deadline = time.monotonic() + GATE_WAIT_S
        while True:
            gates = {i: self._gate(i) for i in ids}
            pending = [i for i in ids if objs[i]["state"] == "completed" and gates[i] is None]
            if not pending or time.monotonic() > deadline:
                return gates
            if self._gating_idle():
                self.sleep(1.0)  # one more tick: a run that just completed is picked up then
                if self._gating_idle():
                    return {i: self._gate(i) for i in ids}
            self.sleep(0.5)
