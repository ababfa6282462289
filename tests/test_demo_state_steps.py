"""The state demo's chain (`hope-trainer demo`, hope_trainer/demo/chain.py): each member's own step
count and threads down to the TrainConfig its job builds (the Mid Loop 1000 steps, its held-out
figures' best: docs/training.md, "How many steps"; on the machine's cores, up to 2), and --steps
giving every member one count."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from hope_models.components import ACTOR, PREDICTOR, TOKENIZER
from hope_trainer.demo.chain import MAX_MID_THREADS, STATE_STEPS, mid_loop_threads
from hope_trainer.demo.session import Demo
from hope_trainer.demo.shared import COMPONENTS


def _demo(tmp_path: Path, **kw) -> Demo:
    from hope_models.settings import load_settings

    base = {"episodes": 50, "noise": 1.0, "steps": None, "seed": 0, "eval_episodes": 20, "target_return": 900.0,
            "queue": "pi", "camera": False}
    return Demo(load_settings(tmp_path / "home", env={}), argparse.Namespace(**{**base, **kw}))


def test_each_member_trains_its_own_steps_down_to_the_job(tmp_path):
    from registry.db import Registry
    from registry.report_channel import snapshot_of
    from registry.sequences import create_sequence
    from workers.job import build_train_config

    assert STATE_STEPS == {TOKENIZER: 4000, ACTOR: 4000, PREDICTOR: 1000} and set(STATE_STEPS) == set(COMPONENTS)
    data = tmp_path / "data"
    data.mkdir()
    configs = _demo(tmp_path).member_configs(data)
    settings = _demo(tmp_path).settings
    with Registry.open(settings) as registry, registry.session() as s:
        first = configs[COMPONENTS[0]]
        runs = create_sequence(s, COMPONENTS, first, total_steps=first["steps"], runs_dir=tmp_path / "runs",
                               member_configs=configs)
        assert [r.total_steps for r in runs] == [STATE_STEPS[c] for c in COMPONENTS]
        cfgs = {r.component: build_train_config(settings, snapshot_of(s, r), lambda _rid: str(tmp_path / "vq"))
                for r in runs}
    assert {c: cfg.steps for c, cfg in cfgs.items()} == STATE_STEPS
    assert all(cfg.lr == 1e-3 and cfg.seed == 0 for cfg in cfgs.values())
    # the Mid Loop on the machine's cores, up to 2; the others on the loop's one thread
    assert cfgs[PREDICTOR].threads == min(2, len(os.sched_getaffinity(0)))
    assert cfgs[TOKENIZER].threads == cfgs[ACTOR].threads == 1
    # --steps replaces every member's count (a short run)
    short = _demo(tmp_path, steps=30).member_configs(data)
    assert {c["steps"] for c in short.values()} == {30}


def test_the_mid_loop_threads_follow_the_cores(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: {0})
    assert mid_loop_threads() == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(8)))
    assert mid_loop_threads() == MAX_MID_THREADS == 2
