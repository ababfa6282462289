"""`hope-trainer demo --camera`: the whole loop on the camera observation, what a robot has (the
joints and a 64x64 top-down frame, nothing about the target), through the same services as `demo`.

1. records the expert's DART demonstrations with `sim-demos --observation camera`, the episodes
   split over CAMERA.record_processes children (~5-10 s an episode on a core with flat frames);
2. starts the services (session.py);
3. queues one chain whose members train with their own recipe (CAMERA.members): the grid frame
   VQ-VAE, the Fast Loop reading its codes through the code table, the grid Mid Loop;
4. as soon as the gate promoted the fast_loop and BrainService serves it, one inference goes
   through the HTTP API with the first demonstration's joints and frame (the loop closure), and
   the reflex's evaluation starts at once, beside the Mid Loop's training: eval-reflex renders
   the frames (EGL) on held-out seeds 0..N-1 (CAMERA.eval_processes children, each a seed range);
5. the summary: demo's table and figures (the VQ-VAE's and the Mid Loop's held-out figures, the
   reflex against the expert and random, the loop closure), each stage's wall time, written to
   $HOPE_HOME/demo/camera/summary.json.

Unlike `demo`, a stage that fails stops it with a message naming the stage: nothing after it
could be measured. CAMERA is the one place its numbers live.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from hope_models.components import ACTOR, PREDICTOR, TOKENIZER
from hope_models.promoted import PointerError, read_pointer
from hope_trainer.demo.children import ChildGroup
from hope_trainer.demo.report import split_range
from hope_trainer.demo.session import Demo
from hope_trainer.demo.shared import COMPONENTS, DEMO_SEED, DemoError
from registry.run_request import build_request

# The grid frame tokenizer measured in docs/training.md: 16x16 cells of 4 px, 256 codes, a decoder
# twice as wide as the encoder (the robot's encode costs the same), the arm and target weighed 10x.
GRID_TOKENIZER = {"layout": "grid", "patch": 4, "n_codes": 256, "channels": 16, "decoder_channels": 32,
                  "fg_weight": 10}


@dataclass(frozen=True)
class Member:
    steps: int
    overrides: dict[str, Any] = field(default_factory=dict)  # run request fields (train/config.py)


@dataclass(frozen=True)
class CameraRecipe:
    members: dict[str, Member]  # by role (TOKENIZER, ACTOR, PREDICTOR)
    frame_size: int = 64
    record_processes: int = 2  # sim-demos children (one per core)
    # eval-reflex children, each a range of the held-out seeds. One: it runs beside the Mid Loop's
    # one-thread training and ends first (20 held-out episodes took 235 s with flat frames, against
    # 3000 grid Mid Loop steps at ~7.5 steps/s); a second would only take the Mid Loop's core.
    eval_processes: int = 1


CAMERA = CameraRecipe(members={
    TOKENIZER: Member(2500, {"lr": 2e-3, "threads": 2, "model_config": GRID_TOKENIZER}),
    ACTOR: Member(12000),  # the Fast Loop's own defaults; 12 000 steps: docs/reflex.md, "A reflex from pixels"
    PREDICTOR: Member(3000, {"lr": 2e-3}),  # the grid Mid Loop's documented rate
})
MIN_EPISODES = 3  # the validation split keeps at least one episode from 3 on (data/sampler.py)


def camera_problem(args: Any) -> str | None:
    """What makes `demo --camera` refuse these arguments before it starts anything, or None."""
    if args.episodes < MIN_EPISODES:
        return (f"--episodes {args.episodes}: the camera demo reports held-out figures, and the chain holds "
                f"episodes out only from {MIN_EPISODES} on; record at least {MIN_EPISODES}")
    if args.noise < 0:
        return f"--noise {args.noise:g}: the DART noise is a standard deviation, >= 0"
    return None


def served_layout_problem(home: Path) -> str | None:
    """A promoted model here that reads no camera (a `demo` ran in this $HOPE_HOME): BrainService
    keeps the layout it serves and would refuse the camera models, so say it before recording."""
    for name in COMPONENTS:
        try:
            pointer = read_pointer(home, name)
            if pointer is None:
                continue
            ckpt = Path(pointer["checkpoint"])
            config = json.loads(((ckpt if ckpt.is_absolute() else home / ckpt) / "config.json").read_text())
        except (PointerError, OSError, ValueError) as exc:
            return f"the promoted {name} cannot be read: {exc}"
        frame = (config.get("feature_spec") or {}).get("frame") if isinstance(config, dict) else None
        if frame is None:
            return (f"{home} serves the {name} {pointer['version']}, which reads no camera; BrainService keeps the "
                    "observation layout it serves and would refuse the camera demo's models. Run the camera demo "
                    "with a HOPE_HOME of its own, e.g. HOPE_HOME=~/.local/share/hope-trainer-camera")
    return None


def stage_seconds(run: dict[str, Any]) -> float | None:
    """A member's wall time in the chain: dispatched to the worker until it finished."""
    try:
        start = datetime.fromisoformat(run["dispatched_at"] or run["started_at"])
        return (datetime.fromisoformat(run["finished_at"]) - start).total_seconds()
    except (KeyError, TypeError, ValueError):
        return None


class CameraDemo(Demo):
    recorded = "expert episodes of the reacher seen by its top-down camera"

    def __init__(self, settings: Any, args: Any, recipe: CameraRecipe = CAMERA):
        super().__init__(settings, args)
        self.recipe = recipe
        self.eval_processes = recipe.eval_processes
        self.eval_group: ChildGroup | None = None  # started as soon as the fast_loop is served

    def data_dir(self) -> Path:
        a = self.args
        return Path(self.settings.home) / "demo" / "camera" / f"reach-{a.episodes}-dart{a.noise:g}"

    def summary_path(self) -> Path:
        return Path(self.settings.home) / "demo" / "camera" / "summary.json"

    def recording_argvs(self, out: Path) -> list[list[str]]:
        a = self.args
        return [["sim-demos", "--episodes", str(count), "--out", str(out), "--task", "reach", "--noise", str(a.noise),
                 "--seed", str(DEMO_SEED + first), "--observation", "camera",
                 "--frame-size", str(self.recipe.frame_size), "--json"]
                for first, count in split_range(a.episodes, self.recipe.record_processes)]

    def member_configs(self, data: Path) -> dict[str, dict[str, Any]]:
        """The recipe's member, or --steps for every member when given (a short run)."""
        a = self.args
        out = {}
        for name in COMPONENTS:
            member = self.recipe.members[name]
            out[name] = build_request(component=name, data=str(data), steps=a.steps or member.steps, queue=a.queue,
                                      overrides={"seed": a.seed, **member.overrides}).config()
        return out

    # -- a failed stage stops the demo ------------------------------------------------------------

    def record_demos(self) -> Path:
        try:
            return super().record_demos()
        except DemoError as exc:
            raise DemoError(f"the camera demo stopped at step 1 (demonstrations): {exc}") from None

    def check_chain(self, objs: list[dict[str, Any]]) -> None:
        for o in objs:
            seconds = stage_seconds(o)
            if seconds is not None:
                self.timings[o["component"]] = seconds
        for o in objs:
            if o["state"] != "completed":
                error = f": {o['error']}" if o.get("error") else ""
                raise DemoError(f"the camera demo stopped at step 3 (training the {o['component']}): run {o['id']} "
                                f"ended {o['state']}{error}")

    def loop_closed(self) -> None:
        if self.inference and not self.inference.get("error") and self.eval_group is None:
            self.eval_group = self.start_evaluation()  # beside the Mid Loop's training

    def evaluate(self) -> dict[str, Any]:
        group, self.eval_group = self.eval_group or self.start_evaluation(), None
        reflex = self.finish_evaluation(group)
        if isinstance(reflex.get("elapsed_s"), (int, float)):
            # its own time: it ended while the chain went on, and was read only after the chain
            self.timings["reflex"] = reflex["elapsed_s"]
        return reflex

    def check_reflex(self, fast_gate: dict[str, Any] | None, reflex: dict[str, Any]) -> None:
        if fast_gate is None or fast_gate.get("state") != "promoted":
            why = ("; ".join(fast_gate.get("reasons") or []) or fast_gate.get("message", "")) if fast_gate else \
                "it was not gated"
            raise DemoError(f"the camera demo stopped at step 4 (promotion): the {ACTOR} was not promoted: {why}")
        inference = self.inference or {"error": f"BrainService never served the promoted {ACTOR}"}
        if inference.get("error"):
            raise DemoError(f"the camera demo stopped at step 4 (inference through the API): {inference['error']}")
        if reflex.get("error"):
            raise DemoError(f"the camera demo stopped at step 5 (reflex): {reflex['error']}")


__all__ = ["CAMERA", "CameraDemo", "CameraRecipe", "GRID_TOKENIZER", "Member", "camera_problem",
           "served_layout_problem"]
