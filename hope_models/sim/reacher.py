"""The dm_control reacher (easy) as the reflex's simulator, and a "track" task on the same physics.

    env = make_env("reach", seed=7)          # or "track"
    obs = env.reset()                        # the RLDS observation block (below)
    obs, reward, done = env.step(action)     # action: [shoulder, wrist] in [-1, 1]

Both tasks run the reacher's physics with a 20 ms control period (CONTROL_PERIOD_S; one MuJoCo step
of 20 ms per control step) for EPISODE_STEPS = 1000 steps (20 s); `done` is True on the 1000th.
Reward is dm_control's reacher reward: 1 while the fingertip is within TOLERANCE_M (target radius
0.05 + finger radius 0.01) of the target centre, else 0, so a return is the number of steps spent
on the target (at most 1000).

- reach: dm_control's `reacher/easy` exactly (`suite.load("reacher", "easy", task_kwargs={"random":
  seed})`): random joint angles, a fixed target 0.05-0.20 m from the shoulder.
- track: the same start, then the target moves along a circle around the shoulder (radius
  TRACK_RADIUS_M drawn per episode, TRACK_OMEGA_RAD_S = 0.5 rad/s, i.e. at most 0.09 m/s, direction
  drawn per episode), always inside the arm's reach (0.04-0.24 m). Each control step, before the
  physics steps, the target geom is moved (physics.named.model.geom_pos) to where it will be at the
  end of the step, so the reward after the step sees the target's new position.
- a target jump (either task, `make_env(..., target_jump_s=T)`, eval-reflex --target-jump-at): at T s
  the target moves to a new position drawn from the seed alone (jump_position: 0.08-0.20 m from the
  shoulder, on the far side of where the target was), so the observation at step round(T / 20 ms) is
  the first to see it. On track the circle is re-fitted through the new position (same speed and
  direction), so the target keeps moving from there. It tests how a model reacts to the unexpected:
  the Mid Loop's surprise spikes (docs/reflex.md, "Reflex view: surprise").

Seeded: the same (task, seed) gives the same episode, bit for bit (the task's RandomState(seed)
draws everything). Evaluation uses seeds [S, S+N); demos are recorded from other seeds (see
recorder.DEFAULT_SEED_BASE).

Observation (the RLDS `observation` block a step holds, and what a policy reads):

    {"robot_state": {"joint_positions": [shoulder, wrist],        # rad; the shoulder is a continuous
                                                                   #  joint, wrapped to [-pi, pi)
                     "joint_velocities": [shoulder, wrist]},      # rad/s
     "target_offset": [dx, dy]}                                   # target centre minus fingertip, m,
                                                                   #  in the upper arm's frame

target_offset is dm_control's `to_target` (world frame) rotated by -shoulder, i.e. expressed in the
frame of the upper arm (x along the upper arm). The world-frame offset makes every useful action
depend on the shoulder angle, which a policy sees wrapped at +-pi: behaviour cloning then failed
around the wrap (2-5 of 100 held-out episodes stuck with the shoulder near +-pi). In the arm frame
the expert's action is a function of the wrist angle, the joint velocities and the offset alone, and
the cloned policy matches the expert (docs/reflex.md, "Why the arm frame"). to_arm_frame /
from_arm_frame convert.

A robot measures its joints, not where the target is: the camera observation (OBSERVATIONS,
`camera_observation`) keeps robot_state and replaces target_offset with the frame of the fixed
top-down camera, a reference {"uri": ..., "width", "height", "format"} under `camera`. Nothing
privileged (target_offset, to_target, the target's position) is in it; the simulator still scores
the episode from its own state.

OBS_FIELDS lists these paths in the order the feature spec infers them (sorted dotted paths), which
is the order of `observation_vector`. The action is `action.command` = [shoulder, wrist] motor
commands in [-1, 1] (gear 0.05 N m).

Rendering: MUJOCO_GL picks MuJoCo's GL backend and must be set before dm_control is first imported.
This module sets it (os.environ.setdefault, so a value the user exported wins) to "disabled" unless
frames are asked for, in which case it sets "egl" (headless GPU/Mesa rendering). Frames are 64x64
uint8 RGB from the fixed top-down camera, drawn "flat" by default (RENDER_STYLES). A process that imported dm_control with "disabled" cannot
render later: `make_env(..., frames=True)` then raises a RuntimeError saying so.
"""
from __future__ import annotations

import math
import os
import sys
from typing import Any

import numpy as np

CONTROL_PERIOD_S = 0.02
EPISODE_STEPS = 1000
TASKS = ("reach", "track")
ROBOT_MODEL = "dmc-reacher"
FRAME_SIZE = 64
FRAME_SIZES = (64, 96)  # what the camera observation renders (the cache's frame sizes 64 and 96)
OBSERVATIONS = ("state", "camera")  # the engineered state (with target_offset) / what a robot has
CAMERA_KEY = "camera"
CAMERA = "fixed"  # top-down camera of reacher.xml
# How frames are drawn. "flat" turns off the shadow map and the floor's reflection: under Mesa's
# software rasteriser they were ~90 % of a 64x64 frame's cost (25 ms against 3.5 ms, antialiasing
# kept), and a robot's own camera shows no mirror floor. "shaded": MuJoCo's defaults, what the
# recordings before 2026-12-07 hold (an episode's provenance.sim.render says which; none = shaded).
RENDER_STYLES = ("flat", "shaded")
RENDER_STYLE = "flat"

LINK_LENGTHS_M = (0.12, 0.12)  # shoulder->wrist, wrist->fingertip (reacher.xml)
TARGET_SIZE_M = 0.05  # reacher/easy target radius
FINGER_SIZE_M = 0.01
TOLERANCE_M = TARGET_SIZE_M + FINGER_SIZE_M  # reward 1 within this distance of the target centre

TRACK_RADIUS_M = (0.08, 0.18)  # circle radius range (drawn per episode), inside the 0.04-0.24 m annulus
TRACK_OMEGA_RAD_S = 0.5  # angular speed of the target on its circle
JUMP_RADIUS_M = (0.08, 0.20)  # where a target jump lands: well inside the arm's 0.04-0.24 m annulus
JUMP_SEED_SALT = 0x71  # the jump's own RandomState stream: it must not shift what the task draws
EPISODE_S = EPISODE_STEPS * CONTROL_PERIOD_S

OBS_FIELDS: tuple[tuple[str, int], ...] = (
    ("observation.robot_state.joint_positions", 2),
    ("observation.robot_state.joint_velocities", 2),
    ("observation.target_offset", 2),
)
OBS_DIM = sum(n for _, n in OBS_FIELDS)
ACTION_FIELD = ("action.command", 2)
ACT_DIM = 2
ACTION_LOW = -1.0
ACTION_HIGH = 1.0


# -- dm_control import with the right GL backend ------------------------------------------------

def _gl_backend(frames: bool) -> str:
    """Set MUJOCO_GL before dm_control is imported (a user's value wins); refuse frames without GL."""
    if "dm_control" not in sys.modules and "mujoco" not in sys.modules:
        os.environ.setdefault("MUJOCO_GL", "egl" if frames else "disabled")
    backend = os.environ.get("MUJOCO_GL", "")
    if frames and backend.lower() in ("disabled", ""):
        raise RuntimeError(
            f"frames need a GL backend but MUJOCO_GL={backend!r} in this process (dm_control was imported "
            "before frames were asked for); start a new process with MUJOCO_GL=egl, or ask for frames first")
    return backend


def _dm_control(frames: bool = False):
    _gl_backend(frames)
    from dm_control.rl import control  # lazy: loads dm_control
    from dm_control.suite import reacher  # lazy: loads dm_control

    return control, reacher


def wrap_angle(a: float | np.ndarray) -> Any:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def to_arm_frame(q1: float, v) -> np.ndarray:
    """A world-frame planar vector in the upper arm's frame (rotated by -q1)."""
    c, s = math.cos(q1), math.sin(q1)
    return np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1]])


def from_arm_frame(q1: float, v) -> np.ndarray:
    """An upper-arm-frame planar vector in the world frame (rotated by q1)."""
    c, s = math.cos(q1), math.sin(q1)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def observation_from_state(qpos, qvel, to_target) -> dict[str, Any]:
    """The RLDS observation block from joint angles, joint velocities and the world-frame
    target-minus-fingertip vector (dm_control's to_target), which is stored in the arm frame."""
    to_target = to_arm_frame(float(qpos[0]), to_target)
    return {
        "robot_state": {
            "joint_positions": [float(wrap_angle(qpos[0])), float(qpos[1])],
            "joint_velocities": [float(qvel[0]), float(qvel[1])],
        },
        "target_offset": [float(to_target[0]), float(to_target[1])],
    }


def camera_observation(obs: dict[str, Any], uri: str, size: int = FRAME_SIZE) -> dict[str, Any]:
    """What a robot has: the joints of the state observation `obs` and the camera frame stored at
    `uri` (relative to the episode dir), nothing about the target."""
    rs = obs["robot_state"]
    return {"robot_state": {"joint_positions": list(rs["joint_positions"]),
                            "joint_velocities": list(rs["joint_velocities"])},
            CAMERA_KEY: {"uri": uri, "width": size, "height": size, "format": "npy_uint8_hwc"}}


def observation_vector(obs: dict[str, Any]) -> np.ndarray:
    """The observation block as a float64 vector in OBS_FIELDS order (raw units, not normalised)."""
    rs = obs["robot_state"]
    return np.array([*rs["joint_positions"], *rs["joint_velocities"], *obs["target_offset"]], dtype=np.float64)


# -- the tasks ----------------------------------------------------------------------------------

def _track_task_class():
    _, reacher = _dm_control()

    class TrackReacher(reacher.Reacher):
        """reacher/easy's start, then a target moving along a circle around the shoulder."""

        def __init__(self, random=None):
            super().__init__(target_size=TARGET_SIZE_M, random=random)
            self.circle_radius = 0.0
            self.phase0 = 0.0
            self.direction = 1.0

        def initialize_episode(self, physics):
            super().initialize_episode(physics)  # joints + an initial target (we replace its position)
            self.circle_radius = float(self.random.uniform(*TRACK_RADIUS_M))
            self.phase0 = float(self.random.uniform(0, 2 * np.pi))
            self.direction = 1.0 if self.random.uniform() < 0.5 else -1.0
            self._place(physics, 0.0)

        def target_xy(self, t: float) -> tuple[float, float]:
            a = self.phase0 + self.direction * TRACK_OMEGA_RAD_S * t
            return self.circle_radius * math.cos(a), self.circle_radius * math.sin(a)

        def _place(self, physics, t: float) -> None:
            x, y = self.target_xy(t)
            physics.named.model.geom_pos["target", "x"] = x
            physics.named.model.geom_pos["target", "y"] = y

        def before_step(self, action, physics):
            # The target is where it will be at the end of this control step; the legacy step
            # recomputes positions after integrating, so the reward sees it there.
            self._place(physics, physics.data.time + CONTROL_PERIOD_S)
            super().before_step(action, physics)

    return TrackReacher


def jump_step(target_jump_s: float) -> int:
    """The step whose observation first sees a jump at target_jump_s; ValueError unless the jump
    falls within the episode (after its first step, before its last)."""
    t = float(target_jump_s)
    step = round(t / CONTROL_PERIOD_S) if math.isfinite(t) else -1
    if not 1 <= step < EPISODE_STEPS:
        raise ValueError(f"target_jump_s={target_jump_s!r} must be within the episode: "
                         f"{CONTROL_PERIOD_S:g}-{EPISODE_S - CONTROL_PERIOD_S:g} s")
    return step


def jump_position(seed: int, old_xy) -> tuple[float, float]:
    """Where a target jump lands on the episode of `seed`: drawn from the seed alone (its own stream),
    opposite the old position give or take 60 degrees, so the jump is a large one (>= 0.08 m)."""
    rng = np.random.RandomState([int(seed), JUMP_SEED_SALT])
    radius = rng.uniform(*JUMP_RADIUS_M)
    angle = math.atan2(float(old_xy[1]), float(old_xy[0])) + math.pi + rng.uniform(-math.pi / 3, math.pi / 3)
    return radius * math.cos(angle), radius * math.sin(angle)


class ReacherEnv:
    """One seeded episode source: reset() -> obs, step(action) -> (obs, reward, done)."""

    def __init__(self, task: str = "reach", seed: int = 0, frames: bool = False, target_jump_s: float | None = None,
                 render_style: str = RENDER_STYLE):
        if task not in TASKS:
            raise ValueError(f"task {task!r} is not one of {', '.join(TASKS)}")
        if render_style not in RENDER_STYLES:
            raise ValueError(f"render style {render_style!r} is not one of {', '.join(RENDER_STYLES)}")
        self.render_style = render_style
        self._cameras: dict[int, Any] = {}  # by frame size: one scene each, kept (a new one per frame costs ~2 ms)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed={seed!r} must be a non-negative integer")
        self.task_name, self.seed, self.frames = task, int(seed), frames
        self.jump_step = None if target_jump_s is None else jump_step(target_jump_s)
        self.jumped_to: tuple[float, float] | None = None  # where the target jumped to, once it has
        control, reacher = _dm_control(frames)
        physics = reacher.Physics.from_xml_string(*reacher.get_model_and_assets())
        if task == "reach":
            task_obj = reacher.Reacher(target_size=TARGET_SIZE_M, random=self.seed)
        else:
            task_obj = _track_task_class()(random=self.seed)
        # time_limit = 1000 steps; we count steps ourselves so float rounding cannot cut an episode short
        self._env = control.Environment(physics, task_obj, time_limit=float("inf"),
                                        control_timestep=CONTROL_PERIOD_S)
        if abs(self._env.control_timestep() - CONTROL_PERIOD_S) > 1e-12:
            raise RuntimeError(f"control timestep is {self._env.control_timestep()} s, expected {CONTROL_PERIOD_S}")
        self.t = 0
        self._obs: dict[str, Any] | None = None

    # -- access for the expert, the recorder and tests ------------------------------------------
    @property
    def physics(self):
        return self._env.physics

    @property
    def task(self):
        return self._env.task

    @property
    def action_low(self) -> np.ndarray:
        return np.full(ACT_DIM, ACTION_LOW)

    @property
    def action_high(self) -> np.ndarray:
        return np.full(ACT_DIM, ACTION_HIGH)

    def observation_dict(self, raw: dict[str, Any] | None = None) -> dict[str, Any]:
        """The RLDS observation block, from dm_control's raw observation (position, to_target,
        velocity) or, without one, from the current physics state."""
        if raw is None:
            p = self.physics
            return observation_from_state(p.data.qpos, p.data.qvel, p.finger_to_target())
        return observation_from_state(raw["position"], raw["velocity"], raw["to_target"])

    @property
    def observation(self) -> dict[str, Any]:
        if self._obs is None:
            raise RuntimeError("call reset() first")
        return self._obs

    def target_xy(self) -> np.ndarray:
        return np.array(self.physics.named.data.geom_xpos["target", :2], dtype=np.float64)

    def fingertip_xy(self) -> np.ndarray:
        return np.array(self.physics.named.data.geom_xpos["finger", :2], dtype=np.float64)

    def distance(self) -> float:
        return float(self.physics.finger_to_target_dist())

    # -- the episode ----------------------------------------------------------------------------
    def reset(self) -> dict[str, Any]:
        """Start an episode. The first reset() of an env is the episode of its seed; a second one
        draws the next start from the same RandomState (make a new env to replay a seed)."""
        ts = self._env.reset()
        self.t, self.jumped_to = 0, None
        self._obs = self.observation_dict(ts.observation)
        return self._obs

    def step(self, action) -> tuple[dict[str, Any], float, bool]:
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        if self.t >= EPISODE_STEPS:
            raise RuntimeError(f"the episode is over ({EPISODE_STEPS} steps); call reset()")
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (ACT_DIM,):
            raise ValueError(f"action must have {ACT_DIM} values, got shape {np.shape(action)}")
        if not np.isfinite(a).all():
            raise ValueError(f"action {a.tolist()} is not finite")
        if self.jump_step is not None and self.t + 1 == self.jump_step:
            self._jump_target()  # before the physics step: the observation after it sees the new target
        ts = self._env.step(np.clip(a, ACTION_LOW, ACTION_HIGH))
        self.t += 1
        self._obs = self.observation_dict(ts.observation)
        return self._obs, float(ts.reward or 0.0), self.t >= EPISODE_STEPS

    def _jump_target(self) -> None:
        x, y = jump_position(self.seed, self.target_xy())
        task = self.task
        if hasattr(task, "target_xy"):  # track: re-fit its circle through (x, y) at the jump's time
            t_jump = self.jump_step * CONTROL_PERIOD_S
            task.circle_radius = math.hypot(x, y)
            task.phase0 = math.atan2(y, x) - task.direction * TRACK_OMEGA_RAD_S * t_jump
        self.physics.named.model.geom_pos["target", "x"] = x
        self.physics.named.model.geom_pos["target", "y"] = y
        self.jumped_to = (x, y)

    def render(self, size: int = FRAME_SIZE) -> np.ndarray:
        """The current scene from the top-down camera, uint8 [size, size, 3]."""
        if not self.frames:
            raise RuntimeError("this env was made without frames=True (MUJOCO_GL must be a GL backend)")
        camera = self._cameras.get(size)
        if camera is None:
            camera = self._cameras[size] = self._camera(size)
        return np.ascontiguousarray(camera.render(), dtype=np.uint8)

    def _camera(self, size: int):
        from dm_control.mujoco.engine import Camera  # lazy: loads dm_control
        from dm_control.mujoco.wrapper.mjbindings import enums  # lazy: loads dm_control

        camera = Camera(self.physics, size, size, camera_id=CAMERA)
        if self.render_style == "flat":
            camera.scene.flags[enums.mjtRndFlag.mjRND_SHADOW] = 0
            camera.scene.flags[enums.mjtRndFlag.mjRND_REFLECTION] = 0
        return camera


def make_env(task: str = "reach", seed: int = 0, frames: bool = False,
             target_jump_s: float | None = None, render_style: str = RENDER_STYLE) -> ReacherEnv:
    """A seeded reacher env for `task` ("reach" or "track"); frames=True needs MUJOCO_GL=egl;
    target_jump_s: move the target at that time (the module docstring); render_style: RENDER_STYLES."""
    return ReacherEnv(task, seed, frames, target_jump_s, render_style)
