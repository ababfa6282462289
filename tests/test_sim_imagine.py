"""Imagined rollouts (hope_models/sim/imagine.py, `run_trainer.py imagine`): provenance and tag, the
train profile, start states outside the demos and the evaluation seeds, DART's corrective labels,
the CEM planner's simulator model, the CLI's JSON, determinism. Short episodes keep it fast."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MUJOCO_GL", "disabled")

from hope_models.rlds.discover import read_path  # noqa: E402
from hope_models.rlds.validation_report import episode_report  # noqa: E402
from hope_models.sim import imagine, seed_ranges  # noqa: E402
from hope_models.sim.expert import ExpertController  # noqa: E402
from hope_models.sim.reacher import make_env, observation_vector  # noqa: E402
from hope_models.sim.recorder import DEFAULT_SEED_BASE as DEMO_BASE  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
STEPS = 60


def _episodes(path: Path):
    eps = [ep for report in read_path(path) for ep in report.episodes]
    assert eps, f"no episode read from {path}"
    return sorted(eps, key=lambda e: e.episode_id)


@pytest.fixture(scope="module")
def imagined(tmp_path_factory):
    out = tmp_path_factory.mktemp("imag")
    dart = imagine.imagine_dataset(out / "dart", 2, method="dart", steps=STEPS)
    cem = imagine.imagine_dataset(out / "cem", 1, method="cem", task="track", steps=STEPS)
    return out, dart, cem


@pytest.mark.parametrize("method", imagine.METHODS)
def test_provenance_tag_and_train_profile(imagined, method):
    out, dart, cem = imagined
    result = dart if method == "dart" else cem
    assert len(result.paths) == len(result.episodes) >= 1
    for ep in _episodes(out / method):
        meta = ep.metadata
        assert meta["provenance"]["origin"] == f"imagined:{method}"
        assert "continuon.imagined" in meta["tags"]
        assert meta["schema_version"] == "1.1" and meta["robot_model"] == "dmc-reacher"
        assert ep.is_imagined
        report = episode_report(ep, "train")
        assert report["ok"], report["errors"]
        assert report["steps"] == STEPS
        # the recorder's observation/action layout (demos and imagined rollouts share one dataset)
        step = ep.steps[0]
        assert set(step.action) == {"command", "source", "executed_command"}  # label + what was executed
        assert set(step.observation) == {"robot_state", "target_offset"}
        assert [s.timestamp_ns for s in ep.steps[:3]] == [0, 20_000_000, 40_000_000]
        assert ep.steps[-1].is_terminal and not any(s.is_terminal for s in ep.steps[:-1])


def test_demos_and_imagined_share_one_feature_spec(tmp_path, imagined):
    from hope_models.data.cache import load_or_build

    out, dart, _ = imagined
    import shutil

    from hope_models.rlds.write_episode_dir import write_episode_dir
    from hope_models.sim.recorder import record_episode

    data = tmp_path / "mixed"
    ep, _ = record_episode("reach", DEMO_BASE, steps=STEPS)  # a demo as sim-demos writes it
    write_episode_dir(ep, data)
    for p in dart.paths:
        shutil.copytree(p, data / p.name)
    cache, _ = load_or_build(data, tmp_path / "cache")
    assert cache.n_episodes == 3  # nothing excluded
    assert int(cache.imagined.sum()) == 2
    assert [(f.path, f.size) for f in cache.spec.action.fields] == [("action.command", 2)]
    assert cache.spec.obs_dim == 6


def test_seed_ranges_are_disjoint():
    from hope_models.sim.seed_ranges import DEFAULT_SEED_BASE, DEMO_SEED_RANGE, EVAL_SEED_RANGE

    # the documented convention: eval [0, 100000), demos [100000, 200000), imagined [200000, ...)
    assert EVAL_SEED_RANGE[1] <= DEMO_SEED_RANGE[0] and DEMO_SEED_RANGE[1] <= DEFAULT_SEED_BASE
    # ... and it is what the other commands actually default to
    assert DEMO_SEED_RANGE[0] == DEMO_BASE
    eval_cli = pytest.importorskip("hope_models.cli.eval_reflex")
    import argparse

    parser = argparse.ArgumentParser()
    eval_cli.add_arguments(parser)
    eval_seed = parser.get_default("seed")
    assert EVAL_SEED_RANGE[0] <= eval_seed and eval_seed + 20 <= EVAL_SEED_RANGE[1]
    # default ranges of realistic sizes never meet
    for n in (1, 50, 10_000, 99_999):
        demos = set(range(DEMO_BASE, DEMO_BASE + n))
        evals = set(range(eval_seed, eval_seed + min(n, 1000)))
        imag = set(range(DEFAULT_SEED_BASE, DEFAULT_SEED_BASE + n))
        assert not (imag & demos) and not (imag & evals) and not (demos & evals)
    assert seed_ranges.reserved_overlaps(DEFAULT_SEED_BASE, 10_000) == []
    assert len(seed_ranges.reserved_overlaps(0, 1)) == 1
    assert len(seed_ranges.reserved_overlaps(DEMO_BASE - 1, 2)) == 2  # straddles both


def test_overlapping_seeds_are_refused(tmp_path):
    with pytest.raises(ValueError, match="evaluation"):
        imagine.imagine_dataset(tmp_path / "a", 2, seed=0, steps=5)
    with pytest.raises(ValueError, match="demonstrations"):
        imagine.imagine_dataset(tmp_path / "a", 2, seed=DEMO_BASE + 3, steps=5)
    assert not (tmp_path / "a").exists()  # refused before anything is written
    # demos recorded from a non-default seed are still caught when given with demos=
    demos = tmp_path / "demos"
    from hope_models.rlds.write_episode_dir import write_episode_dir
    from hope_models.sim.recorder import record_episode

    ep, _ = record_episode("reach", 300_001, steps=5)
    write_episode_dir(ep, demos)
    with pytest.raises(ValueError, match="demo start states"):
        imagine.imagine_dataset(tmp_path / "b", 3, seed=300_000, steps=5, demos=[demos])
    # the same seed for another task is another start state: allowed
    imagine.imagine_dataset(tmp_path / "c", 1, seed=300_001, task="track", steps=5, demos=[demos])


def test_start_states_differ_from_the_demos(imagined):
    from hope_models.sim.recorder import record_episode

    out, _, _ = imagined
    demo_starts = []
    for i in range(3):  # the recorder's default demo seeds
        ep, _ = record_episode("reach", DEMO_BASE + i, steps=2)
        demo_starts.append(observation_vector(ep.steps[0].observation))
    imag_eps = _episodes(out / "dart")
    for ep in imag_eps:
        assert ep.metadata["provenance"]["sim"]["seed"] >= imagine.DEFAULT_SEED_BASE
        start = observation_vector(ep.steps[0].observation)
        for d in demo_starts:
            assert not np.allclose(start, d, atol=1e-6)
    starts = [observation_vector(ep.steps[0].observation) for ep in imag_eps]
    assert not np.allclose(starts[0], starts[1])  # each imagined rollout has its own start


def test_dart_labels_are_the_experts_action_at_the_visited_state(imagined):
    out, _, _ = imagined
    expert = ExpertController()
    ep = _episodes(out / "dart")[0]
    seed = ep.metadata["provenance"]["sim"]["seed"]
    labels = np.array([s.action["command"] for s in ep.steps])
    executed = np.array([s.action["executed_command"] for s in ep.steps])
    # label = the expert's action at the observation recorded at that step (the visited state)
    expected = np.array([expert.act(s.observation) for s in ep.steps])
    np.testing.assert_allclose(labels, expected, rtol=0, atol=1e-12)
    # ... not the noisy command that was executed
    assert np.mean(np.any(np.abs(executed - labels) > 1e-3, axis=1)) > 0.8
    assert np.all(np.abs(executed) <= 1.0)
    # the executed commands are what drove the arm: replaying them visits the same states, while
    # replaying the labels does not
    for commands, same in ((executed, True), (labels, False)):
        env = make_env("reach", seed)
        obs = env.reset()
        visited = [observation_vector(obs)]
        for a in commands[:-1]:
            obs, _, _ = env.step(a)
            visited.append(observation_vector(obs))
        recorded = np.array([observation_vector(s.observation) for s in ep.steps])
        assert np.allclose(np.array(visited), recorded, atol=1e-9) is same


def test_cem_plans_with_the_simulator_as_its_model(imagined):
    # the planner's prediction of one step equals what the env then does
    env = make_env("reach", 200_123)
    env.reset()
    planner = imagine.CEMPlanner(env, 200_123, imagine.CEMConfig(horizon=4, population=8, iterations=1, elites=2))
    controls = np.random.default_rng(0).uniform(-1, 1, (1, 4, 2))
    tips = planner.predict(planner.state(), controls)
    for k in range(4):
        env.step(controls[0, k])
        np.testing.assert_allclose(tips[0, k], env.fingertip_xy(), atol=1e-9)
    # by default noise is injected (DART's rule applied to the planner): the label is the plan's
    # action at the visited state, the executed command, kept beside it, is what drove the arm
    out, _, cem = imagined
    ep = _episodes(out / "cem")[0]
    assert all(s.action["source"] == "sim_planner" and "plan_cost" in s.step_metadata for s in ep.steps)
    labels = np.array([s.action["command"] for s in ep.steps])
    executed = np.array([s.action["executed_command"] for s in ep.steps])
    assert np.mean(np.any(np.abs(executed - labels) > 1e-3, axis=1)) > 0.8
    env = make_env("track", ep.metadata["provenance"]["sim"]["seed"])
    env.reset()
    for a, s in zip(executed[:-1], ep.steps[1:]):
        obs, _, _ = env.step(a)
        np.testing.assert_allclose(observation_vector(obs), observation_vector(s.observation), atol=1e-9)
    # with noise 0 the labels are the executed actions, and the planner gets to the (moving) target
    ep, _ = imagine.imagine_episode("track", 200_124, "cem", noise=0.0, steps=STEPS)
    assert all("executed_command" not in s.action for s in ep.steps)
    d = [np.linalg.norm(s.observation["target_offset"]) for s in ep.steps]
    assert d[-1] < 0.5 * d[0]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "imagine", *args], capture_output=True,
                          text=True, cwd=REPO, env={**os.environ, "MUJOCO_GL": "disabled"}, timeout=120)


def test_cli_json(tmp_path):
    out = tmp_path / "cli"
    proc = _cli("--out", str(out), "--episodes", "2", "--steps", "30", "--seed", "250000", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    assert doc["outcome"] == "completed"
    assert doc["method"] == "dart" and doc["origin"] == "imagined:dart" and doc["tag"] == "continuon.imagined"
    assert doc["task"] == "reach" and doc["seeds"] == [250000, 250002] and doc["steps"] == 60
    assert doc["settings"]["noise_std"] == imagine.DEFAULT_NOISE["dart"]
    assert [e["seed"] for e in doc["episodes"]] == [250000, 250001]
    for e in doc["episodes"]:
        assert set(e) == {"episode_id", "path", "seed", "return", "steps", "status"}
        assert Path(e["path"]).is_dir() and e["steps"] == 30 and e["status"].startswith("accepted")
    assert isinstance(doc["mean_return"], float)
    # the written dataset passes `validate --profile train`
    val = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "validate", str(out), "--profile", "train",
                          "--json"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert val.returncode == 0, val.stdout[-2000:]
    assert json.loads(val.stdout)["summary"]["episodes"] == 2
    # usage errors: exit 2 with a message naming the problem
    bad = _cli("--out", str(tmp_path / "x"), "--episodes", "1", "--seed", "5", "--json")
    assert bad.returncode == 2
    assert json.loads(bad.stdout)["outcome"] == "error" and "evaluation" in bad.stderr
    again = _cli("--out", str(out), "--episodes", "1", "--steps", "30", "--seed", "250000")
    assert again.returncode == 2 and "already exists" in again.stderr
    bad_noise = _cli("--out", str(tmp_path / "y"), "--episodes", "1", "--noise", "-1")
    assert bad_noise.returncode == 2 and "--noise" in bad_noise.stderr


@pytest.mark.parametrize("method", imagine.METHODS)
def test_deterministic_for_a_seed(tmp_path, method):
    def files(d: Path) -> dict[str, bytes]:
        return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}

    a = imagine.imagine_dataset(tmp_path / "a", 1, seed=260_000, method=method, steps=40)
    b = imagine.imagine_dataset(tmp_path / "b", 1, seed=260_000, method=method, steps=40)
    c = imagine.imagine_dataset(tmp_path / "c", 1, seed=260_001, method=method, steps=40)
    fa, fb = files(tmp_path / "a"), files(tmp_path / "b")
    assert fa == fb and len(fa) == 2  # metadata.json + steps, byte for byte
    assert files(tmp_path / "c") != fa
    assert a.episodes[0].ret == b.episodes[0].ret


def test_cli_frames_are_blobs_the_cache_can_read(tmp_path):
    out = tmp_path / "frames"
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}  # the command picks egl for frames
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "imagine", "--out", str(out), "--episodes",
                           "1", "--steps", "3", "--frames", "--json"], capture_output=True, text=True, cwd=REPO,
                          env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    ep = _episodes(out)[0]
    report = episode_report(ep, "train")
    assert report["ok"] and not [w for w in report["warnings"] if "observation.media" in w], report["warnings"]
    for i, step in enumerate(ep.steps):
        rgb = step.observation["media"]["rgb"]
        assert rgb == {"uri": f"blobs/step_{i:06d}_rgb.npy", "width": 64, "height": 64, "format": "npy_uint8_hwc"}
        frame = np.load(Path(ep.blob_root) / rgb["uri"], allow_pickle=False)
        assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8 and frame.std() > 0
