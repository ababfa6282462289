"""sim-demos --policy play: unlabeled exploration the cache marks and the fast_loop never clones."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hope_models.data.cache import load_or_build
from hope_models.data.dataset_cache import is_play_episode
from hope_models.data.sampler import AnchorSampler
from hope_models.rlds.discover import read_path
from hope_models.rlds.episode import Step
from hope_models.sim.recorder import record_dataset, record_episode

REPO = Path(__file__).resolve().parents[1]
STEPS = 150  # long enough for the expert to park on the target, short enough to stay fast


def _episodes(path: Path):
    return sorted((ep for report in read_path(path) for ep in report.episodes), key=lambda e: e.episode_id)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "run_trainer.py", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory) -> Path:
    """6 expert demos and 6 play episodes of the same seeds in one dataset."""
    ds = tmp_path_factory.mktemp("play") / "ds"
    record_dataset(ds, 6, seed=100_000, steps=60)
    record_dataset(ds, 6, seed=100_000, steps=60, policy="play")
    return ds


@pytest.fixture(scope="module")
def mixed_cache(mixed, tmp_path_factory):
    cache, _ = load_or_build(mixed, tmp_path_factory.mktemp("cache"))
    return cache


@pytest.fixture(scope="module")
def components(mixed_cache, tmp_path_factory):
    """Untrained fast_loop, vqvae and mid_loop (on that vqvae's codes) for the cache's spec."""
    import torch
    from safetensors.torch import save_file

    from hope_models.components.build import build_component

    from hope_models.data.windows import make_windows
    from hope_models.train.validation import anchor_sampler

    spec = mixed_cache.spec
    vq = build_component("vqvae", spec)
    sampler = anchor_sampler(mixed_cache, vq, "all", batch_size=32, seed=0, imagined_ratio=0.0, val_fraction=0.0)
    with torch.no_grad():  # the first batch initialises the codebook; nothing to learn here
        vq.loss(make_windows(mixed_cache, sampler.batch(0), vq.window))
    d = tmp_path_factory.mktemp("vq")
    save_file(vq.model.state_dict(), str(d / "model.safetensors"))
    (d / "config.json").write_text(json.dumps(vq.config()), encoding="utf-8")
    return {"fast_loop": build_component("fast_loop", spec), "vqvae": vq,
            "mid_loop": build_component("mid_loop", spec, vqvae_dir=d)}


def _positions(ep) -> np.ndarray:
    """Joint angles with the shoulder's wrap at +-pi undone (a wrap is not a sweep)."""
    return np.unwrap(np.array([s.observation["robot_state"]["joint_positions"] for s in ep.steps]), axis=0)


def test_play_is_deterministic_per_seed_and_differs_from_the_expert():
    a, ret_a = record_episode("reach", 100_003, "play", steps=80)
    b, ret_b = record_episode("reach", 100_003, "play", steps=80)
    assert [s.action for s in a.steps] == [s.action for s in b.steps] and ret_a == ret_b
    assert [s.observation for s in a.steps] == [s.observation for s in b.steps]
    other, _ = record_episode("reach", 100_004, "play", steps=80)
    assert [s.action for s in other.steps] != [s.action for s in a.steps]
    expert, _ = record_episode("reach", 100_003, steps=80)
    assert a.steps[0].observation == expert.steps[0].observation  # same start state
    assert [s.action["command"] for s in a.steps] != [s.action["command"] for s in expert.steps]


def test_play_metadata_provenance_tags_and_source(mixed):
    eps = _episodes(mixed)
    play = [e for e in eps if "-play-" in e.episode_id]
    demos = [e for e in eps if "-play-" not in e.episode_id]
    assert len(play) == 6 and len(demos) == 6
    ep = play[0]
    assert ep.episode_id == "dmc-reacher-reach-play-s100000"
    meta = ep.metadata
    assert meta["provenance"]["sim"]["policy"] == "play" and meta["provenance"]["sim"]["noise_std"] == 0.0
    assert meta["provenance"]["sim"]["policy_config"]["tau_s"] > 0
    assert "play" in meta["tags"] and meta["control_role"] == "sim_play" and meta["action_source"] == "sim_play"
    assert all(s.action["source"] == "sim_play" and "executed_command" not in s.action for s in ep.steps)
    assert all(max(abs(v) for v in s.action["command"]) <= 1.0 for s in ep.steps)
    assert all("play" not in d.metadata["tags"] and d.metadata["provenance"]["sim"]["policy"] == "expert"
               for d in demos)


def test_the_recorded_command_is_what_was_executed():
    """Replaying the recorded commands in the same env reproduces the recorded observations."""
    from hope_models.sim.reacher import make_env

    ep, _ = record_episode("reach", 100_007, "play", steps=40)
    env = make_env("reach", 100_007)
    obs = env.reset()
    for step in ep.steps:
        assert obs == step.observation
        obs, _, _ = env.step(np.asarray(step.action["command"]))


def test_play_explores_the_workspace_far_more_than_the_expert():
    spread = {"play": [], "expert": []}
    travel = {"play": [], "expert": []}
    for seed in range(100_000, 100_006):
        for name, policy in (("play", "play"), ("expert", None)):
            ep, _ = record_episode("reach", seed, policy, steps=STEPS)
            q = _positions(ep)
            spread[name].append(q.std(axis=0).mean())
            travel[name].append(np.abs(np.diff(q, axis=0)).sum(axis=0).mean())  # rad swept per joint
    assert np.mean(spread["play"]) > 3 * np.mean(spread["expert"])
    assert np.mean(travel["play"]) > 3 * np.mean(travel["expert"])
    assert min(travel["play"]) > 1.5  # every play episode sweeps, not just a lucky one


def test_play_with_noise_is_a_usage_error_naming_noise(tmp_path):
    proc = _cli("sim-demos", "--policy", "play", "--noise", "1", "--episodes", "1", "--steps", "3",
                "--out", str(tmp_path / "x"))
    assert proc.returncode == 2 and "--noise" in proc.stderr
    assert not (tmp_path / "x").exists()
    with pytest.raises(ValueError, match="noise"):
        record_dataset(tmp_path / "y", 1, policy="play", noise=1.0, steps=3)


def test_sim_demos_cli_records_play(tmp_path):
    proc = _cli("sim-demos", "--policy", "play", "--episodes", "2", "--steps", "5", "--out", str(tmp_path / "p"),
                "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out["policy"] == "play" and out["seeds"] == [100_000, 100_001]
    assert [e["episode_id"] for e in out["episodes"]] == ["dmc-reacher-reach-play-s100000",
                                                        "dmc-reacher-reach-play-s100001"]


def test_the_cache_marks_play_episodes(mixed_cache):
    c = mixed_cache
    by_id = dict(zip(c.episode_ids, c.play.tolist()))
    assert by_id == {i: "-play-" in i for i in c.episode_ids}
    assert [e["play"] for e in c.episodes] == c.play.tolist()
    assert c.manifest["play_episodes"] == 6 and not c.imagined.any()


def test_play_detection_rule():
    assert is_play_episode({"tags": ["teleop", "Play"]})
    assert is_play_episode({"provenance": {"origin": "sim:x", "sim": {"policy": "play"}}})
    steps = [Step(observation={}, action={"command": [0.0], "source": "sim_play"}) for _ in range(3)]
    assert is_play_episode({}, steps)
    mixed = steps + [Step(observation={}, action={"command": [0.0], "source": "sim_expert"})]
    assert not is_play_episode({"tags": ["sim", "dart_noise"]}, mixed)
    assert not is_play_episode({"tags": "play"}, [])  # tags must be a list


def test_exclude_play_never_draws_a_play_anchor(mixed_cache):
    c = mixed_cache
    play_step = c.play[c.episode_of(np.arange(c.n_steps))]
    for split in ("train", "val", "all"):
        try:
            s = AnchorSampler(c, 32, seed=1, split=split, val_fraction=0.3, exclude_play=True)
        except ValueError:
            continue  # a split may hold no demos at this size
        assert not any(play_step[s.batch(b)].any() for b in range(20))
    every = AnchorSampler(c, 32, seed=1, split="all", exclude_play=False)
    assert any(play_step[every.batch(b)].any() for b in range(20))


def test_fast_loop_excludes_play_and_mid_loop_and_vqvae_use_it(mixed_cache, components):
    from hope_models.train.validation import anchor_sampler

    c = mixed_cache
    play_step = c.play[c.episode_of(np.arange(c.n_steps))]
    kw = dict(batch_size=32, seed=0, imagined_ratio=0.0, val_fraction=0.0)
    fast, mid, vq = (anchor_sampler(c, components[n], "all", **kw) for n in ("fast_loop", "mid_loop", "vqvae"))
    assert fast.exclude_play and not mid.exclude_play and not vq.exclude_play
    assert not any(play_step[fast.batch(b)].any() for b in range(20))
    assert any(play_step[mid.batch(b)].any() for b in range(20))
    assert any(play_step[vq.batch(b)].any() for b in range(20))
    assert vq.real.size > fast.real.size > 0  # same window lengths (no horizon): only play is missing


def test_only_play_data_gives_a_clear_fast_loop_error(tmp_path):
    from hope_models.train.loop import TrainConfig, TrainSetupError, train

    ds = tmp_path / "play_only"
    record_dataset(ds, 3, steps=40, policy="play")
    cfg = TrainConfig(component="fast_loop", data=str(ds), run_dir=str(tmp_path / "run"), steps=2, seed=0,
                      batch_size=8, threads=1, cache_dir=str(tmp_path / "cache"), thermal_zone=None, vcgencmd=None,
                      control_interval_s=0.0)
    with pytest.raises(TrainSetupError, match=r"all 3 episodes are play \(unlabeled exploration\); the fast_loop "
                                              r"clones expert actions") as info:
        train(cfg)
    assert str(ds) in str(info.value)
    cache, _ = load_or_build(ds, tmp_path / "cache")
    assert cache.play.all()
    from hope_models.components.build import build_component
    from hope_models.train.validation import anchor_sampler

    vq = anchor_sampler(cache, build_component("vqvae", cache.spec), "all", batch_size=8, seed=0,
                        imagined_ratio=0.0, val_fraction=0.0)
    assert vq.real.size == cache.n_steps  # the vqvae trains on play alone
