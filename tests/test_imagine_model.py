"""`imagine --method model`: episodes imagined in the Mid Loop's learned world model, with no simulator.

One tiny world model (a few train steps: the test checks the plumbing; what the episodes are worth
is bench/imagination.py) on 2 demos + 2 play episodes; the CLI runs in a subprocess whose import
system refuses dm_control, mujoco and hope_models.sim outright.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hope_models.cli import imagine as imagine_cli
from hope_models.data.dataset_cache import is_play_episode
from hope_models.imagine.model_imagine import imagine_model_dataset
from hope_models.imagine.planner import PlanConfig
from hope_models.imagine.recorded import Goal, Recorded, grid_history
from hope_models.rlds.discover import read_path
from hope_models.sim.recorder import record_dataset

REPO = Path(__file__).resolve().parent.parent
FORBIDDEN = ("dm_control", "mujoco", "hope_models.sim")
# Runs run_trainer.py with a meta-path hook that makes importing any FORBIDDEN module an error,
# and reports at exit every module loaded (a C extension could sneak past the hook: belt and braces).
NO_SIM = """
import atexit, importlib.abc, json, os, runpy, sys
FORBIDDEN = {forbidden!r}
def bad(name):
    return any(name == f or name.startswith(f + ".") for f in FORBIDDEN)
class NoSim(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if bad(name):
            raise ImportError("the simulator is not available here: " + name)
        return None
sys.meta_path.insert(0, NoSim())
atexit.register(lambda: open(os.environ["LOADED_OUT"], "w").write(json.dumps(sorted(sys.modules))))
sys.argv = ["run_trainer.py"] + sys.argv[1:]
runpy.run_path("run_trainer.py", run_name="__main__")
""".format(forbidden=FORBIDDEN)


def _run(args: list[str], env: dict, tmp: Path, hook: bool = False) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-c", NO_SIM, *args] if hook else [sys.executable, "run_trainer.py", *args]
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**env, "LOADED_OUT": str(tmp / "loaded.json")})


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("wm")
    record_dataset(root / "demos", 2, seed=100_000, steps=120, noise=1.0)
    record_dataset(root / "play", 2, seed=100_000, steps=120, policy="play")
    env = {**os.environ, "HOPE_HOME": str(root / "home"), "MUJOCO_GL": "disabled"}
    ds = root / "ds"
    for src in ("demos", "play"):
        assert _run(["ingest", str(root / src), "--into", str(ds)], env, root).returncode == 0
    proc = _run(["train", "--sequential", "vqvae,mid_loop", "--data", str(ds), "--run-dir", str(root / "wm"),
                 "--steps", "15", "--checkpoint-every", "15", "--json"], env, root)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return root, env


def test_cli_imagines_train_episodes_without_importing_the_simulator(world):
    root, env = world
    out = root / "imagined"
    proc = _run(["imagine", "--method", "model", "--model", str(root / "wm"), "--demos", str(root / "demos"),
                 "--play", str(root / "play"), "--episodes", "3", "--steps", "12", "--seed", "7",
                 "--population", "8", "--elites", "3", "--out", str(out), "--json"], env, root, hook=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    loaded = json.loads((root / "loaded.json").read_text())
    assert not [m for m in loaded if any(m == f or m.startswith(f + ".") for f in FORBIDDEN)]
    assert "hope_models.imagine.model_imagine" in loaded and "torch" in loaded
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    assert doc["outcome"] == "completed" and doc["origin"] == "imagined:model" and doc["tag"] == "continuon.imagined"
    assert doc["steps"] == 36 and doc["settings"]["control_period_s"] == pytest.approx(0.02)
    assert doc["settings"]["start_episodes"] == 4 and doc["settings"]["play_episodes"] == 2
    eps = sorted((e for r in read_path(out) for e in r.episodes), key=lambda e: e.episode_id)
    demo = next(e for r in read_path(root / "demos") for e in r.episodes)
    assert len(eps) == 3
    for ep in eps:
        assert ep.is_imagined and not is_play_episode(ep.metadata, ep.steps)
        prov = ep.metadata["provenance"]
        assert prov["origin"] == "imagined:model" and "sim" not in prov
        assert ep.metadata["robot_model"] == demo.metadata["robot_model"]
        assert [s.timestamp_ns for s in ep.steps] == [i * 20_000_000 for i in range(12)]
        assert ep.steps[-1].is_terminal and not ep.steps[0].is_terminal
        for s in ep.steps:
            assert set(s.observation) == set(demo.steps[0].observation)
            assert np.all(np.abs(s.action["command"]) <= 1.0) and len(s.action["executed_command"]) == 2
            assert s.action["source"] == "model_planner"
        # five 20 ms steps per 100 ms grid step hold one executed command, each with its own label
        assert ep.steps[0].action["executed_command"] == ep.steps[4].action["executed_command"]
    assert all(e["status"].startswith("accepted") for e in doc["episodes"])  # train-profile verdicts
    # the same model, data, seed and settings: the same bytes (in-process: the CLI's function)
    imagine_model_dataset(root / "again", 3, model=root / "wm", demos=[root / "demos"], play=[root / "play"],
                          seed=7, steps=12, plan=PlanConfig(population=8, elites=3))
    for ep in eps:
        a = sorted((out / ep.episode_id).rglob("*.jsonl"))
        b = sorted((root / "again" / ep.episode_id).rglob("*.jsonl"))
        assert a and [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    # without --play: the play episodes of the dataset the world model was trained on
    auto = imagine_model_dataset(root / "auto", 1, model=root / "wm", demos=[root / "demos"], seed=7, steps=5,
                                 plan=PlanConfig(population=8, elites=3)).settings
    assert auto["play_episodes"] == 2 and auto["start_episodes"] == 4 and "training data" in auto["play_from"][0]
    _refusals(root, out)


def _refusals(root: Path, out: Path) -> None:
    """Usage errors exit 2 with the reason (in-process, through the CLI's own parser and run())."""
    cases = [(["--method", "model", "--demos", str(root / "demos")], "--model"),
             (["--method", "model", "--model", str(root / "wm")], "--demos"),
             (["--method", "model", "--model", str(root / "wm" / "vqvae"), "--demos", str(root / "demos")],
              "not a mid_loop"),
             (["--method", "dart", "--model", str(root / "wm")], "--method model"),
             (["--method", "model", "--model", str(root / "wm"), "--demos", str(root / "demos"), "--seed", "7"],
              "already exists")]
    for args, needle in cases:
        parser = argparse.ArgumentParser()
        imagine_cli.add_arguments(parser)
        buf = io.StringIO()
        with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
            code = imagine_cli.run(parser.parse_args([*args, "--episodes", "1", "--out", str(out), "--json"]))
        assert code == 2, args
        assert needle in json.loads(buf.getvalue().strip().splitlines()[-1])["message"], (args, buf.getvalue())


def _recorded(obs, reward, play=False, dt=0.02):
    obs = np.asarray(obs, dtype=np.float32)
    return Recorded("e", {}, obs, np.zeros((len(obs), 1), np.float32), np.asarray(reward, float),
                    np.arange(len(obs)) * dt, play)


def test_goal_weights_what_the_rewarded_steps_hold_still():
    rng = np.random.default_rng(0)
    n = 400
    obs = np.stack([rng.normal(0, 1, n), rng.normal(0, 0.01, n) + 0.5], 1)  # dim 1 all but constant when rewarded
    goal = Goal.from_rewarded([_recorded(obs, np.ones(n)), _recorded(obs + 9, np.ones(n), play=True)])
    assert goal.steps == n  # play is not a demonstration of the goal
    assert goal.weight[1] == 1.0 and goal.weight[0] < 0.02 and goal.mean[1] == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="rewarded"):
        Goal.from_rewarded([_recorded(obs, np.zeros(n))])


def test_grid_history_holds_the_latest_step_and_masks_before_the_episode():
    ep = _recorded(np.arange(12)[:, None], np.zeros(12))
    obs, _, mask = grid_history(ep, 7, k=4, grid_s=0.04)  # grid times 0.02 .. 0.14 s: steps 1, 3, 5, 7
    assert obs[:, 0].tolist() == [1, 3, 5, 7] and mask.all()
    obs, _, mask = grid_history(ep, 3, k=4, grid_s=0.04)  # -0.06, -0.02: before the episode
    assert mask.tolist() == [False, False, True, True] and obs[:, 0].tolist() == [0, 0, 1, 3]
