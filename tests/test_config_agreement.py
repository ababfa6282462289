"""Every training option is accepted and refused alike at every door that takes it.

The doors: the `train` flags, the `enqueue` and `sequential` flags, the JSON of POST /api/runs
(registry/run_request.request_from_json), the worker's check of a run's stored config
(workers/job.build_train_config) and the trainer's own check (TrainConfig.check). The values
walk each option's bounds (at, just past, and for integers a fraction) and the type confusions
the one rule for numbers refuses (hope_models/numbers.py). A new option, a changed bound or a
door that checks its own way fails here."""
from __future__ import annotations

import argparse
import json
import math
from types import SimpleNamespace

import pytest

from hope_models.settings import load_settings
from hope_models.train.config import OPTIONS, REQUEST_FIELDS, TRAIN_FLAGS, TrainConfig, dest_of, flag_of

def probes(name: str) -> list:
    """Values around option `name`'s bounds, plus values no number field takes."""
    opt = OPTIONS[name]
    values: list = [True, False, None, "5", [], {}, math.nan, math.inf, -math.inf, 0, 1, 7, 0.5, 2.0, -1, 10**6]
    for bound in (opt.minimum, opt.maximum, opt.above, opt.below):
        if bound is not None:
            values += [bound, bound - 1, bound + 1, bound - 0.5, bound + 0.5, float(bound)]
    return [v for i, v in enumerate(values) if not any(v is w or (type(v) is type(w) and v == w)
                                                          for w in values[:i])]


def cli_text(name: str, value) -> str | None:
    """What a user types on a command line for `value` of option `name` (None: no text means
    it). As text an integer is decimal digits, so 2.0 is typed 2 for an integer option."""
    if isinstance(value, bool):
        return json.dumps(value)
    if isinstance(value, float) and not math.isfinite(value):
        return {math.inf: "1e999", -math.inf: "-1e999"}.get(value, "nan")
    if isinstance(value, float) and value.is_integer() and OPTIONS[name].kind == "int":
        return str(int(value))
    if isinstance(value, (int, float)):
        return json.dumps(value)
    return None


def by_loop(name, value):
    cfg = TrainConfig(component="fast_loop", data="/d", run_dir="/r", steps=10, **{name: value})
    cfg.check()
    return getattr(cfg, name)


def by_parser(module_name: str):
    import importlib

    parser = argparse.ArgumentParser(exit_on_error=False)
    importlib.import_module(module_name).add_arguments(parser)
    return parser


@pytest.fixture(scope="module")
def doors(tmp_path_factory):
    home = tmp_path_factory.mktemp("agree")
    data = home / "ds"
    data.mkdir()
    settings = load_settings(home / "home", env={"HOPE_MEMORY_BUDGET_MB": str(10**7)})
    parsers = {m: by_parser(m) for m in ("hope_models.cli.train", "daemon.cli.enqueue", "daemon.cli.sequential")}
    return SimpleNamespace(data=str(data), settings=settings, parsers=parsers)


def accepted(fn, *args):
    """(True, value) or (False, the error's text)."""
    try:
        return True, fn(*args)
    except (ValueError, SystemExit, argparse.ArgumentError) as exc:  # every refusal of a door
        return False, str(exc)


def by_cli(doors, module_name: str, name: str, text: str):
    fixed = {"hope_models.cli.train": ["--component", "fast_loop", "--run-dir", "/r", "--steps", "10"],
             "daemon.cli.enqueue": ["--component", "fast_loop"],
             "daemon.cli.sequential": ["--components", "vqvae,fast_loop"]}[module_name]
    args = doors.parsers[module_name].parse_args([*fixed, "--data", doors.data, flag_of(name), text])
    return getattr(args, dest_of(name))


def by_api(doors, name, value):
    from registry.run_request import request_from_json

    req = request_from_json({"component": "fast_loop", "data": doors.data, "steps": 10, name: value},
                            allowed_roots=None)
    return req.overrides[name]


def by_worker(doors, name, value):
    from workers.job import build_train_config

    run = SimpleNamespace(id="r-1", component="fast_loop", total_steps=10, run_dir="/r",
                          config={"data": doors.data, name: value})
    return getattr(build_train_config(doors.settings, run, lambda r: r), name)


@pytest.mark.parametrize("name", [n for n in REQUEST_FIELDS if OPTIONS[n].kind != "path"])
def test_request_doors_agree_value_by_value(doors, name):
    """enqueue, sequential, the API, the worker and the trainer: the same verdict and value."""
    for value in probes(name):
        if value is None:
            continue  # "not given" at every door
        loop_ok, loop_v = accepted(by_loop, name, value)
        api_ok, api_v = accepted(by_api, doors, name, value)
        worker_ok, worker_v = accepted(by_worker, doors, name, value)
        assert api_ok == worker_ok == loop_ok, (name, value, api_v, worker_v, loop_v)
        if loop_ok:
            assert api_v == worker_v == loop_v and type(api_v) is type(loop_v), (name, value)
        text = cli_text(name, value)
        if text is None:
            continue
        for module in ("daemon.cli.enqueue", "daemon.cli.sequential", "hope_models.cli.train"):
            cli_ok, cli_v = accepted(by_cli, doors, module, name, text)
            assert cli_ok == loop_ok, (module, name, text, cli_v, loop_v)
            if cli_ok:
                assert cli_v == loop_v and type(cli_v) is type(loop_v), (module, name, text)


@pytest.mark.parametrize("name", [n for n in TRAIN_FLAGS if OPTIONS[n].kind in ("int", "float")])
def test_train_flags_agree_with_the_trainer(doors, name):
    """The `train` flags that no request may set (e.g. none today, or deployment ones) still
    check as the trainer does."""
    for value in probes(name):
        text = cli_text(name, value)
        if text is None:
            continue
        loop_ok, loop_v = accepted(by_loop, name, value)
        cli_ok, cli_v = accepted(by_cli, doors, "hope_models.cli.train", name, text)
        assert cli_ok == loop_ok, (name, text, cli_v, loop_v)


def test_every_option_open_at_a_door_has_its_flag_and_its_key():
    from daemon.cli.enqueue import OVERRIDE_ARGS
    from registry.run_request import CONFIG_FIELDS, REQUEST_KEYS
    from workers.job import RUN_CONFIG_KEYS

    for module_name, door in (("hope_models.cli.train", "train"), ("daemon.cli.enqueue", "request"),
                              ("daemon.cli.sequential", "request")):
        help_text = by_parser(module_name).format_help()
        for name, opt in OPTIONS.items():
            if door in opt.doors:
                assert flag_of(name) in help_text, (module_name, name)
                if opt.kind != "path":  # a path's help may say more at a door (sequential's --vqvae)
                    assert opt.help[:30] in " ".join(help_text.split()), (module_name, name)
    assert set(CONFIG_FIELDS) | {"vqvae_dir"} == set(REQUEST_FIELDS)
    assert set(OVERRIDE_ARGS) == set(CONFIG_FIELDS)
    assert set(REQUEST_FIELDS) | {"data", "steps"} <= RUN_CONFIG_KEYS
    assert not (set(CONFIG_FIELDS) & REQUEST_KEYS)


def test_the_one_rule_for_numbers():
    from hope_models.numbers import NumberError, as_float, as_int, float_from_text, from_text, int_from_text

    assert as_int("n", 2000) == as_int("n", 2000.0) == int_from_text("n", "2000") == 2000
    assert as_float("x", from_text("x", "1e-3")) == float_from_text("x", "0.001") == float_from_text("x", "1e-3")
    for text in ("2e3", "2000.0", "+5", " 5"):  # as text, an integer is decimal digits
        with pytest.raises(NumberError, match="expected an integer"):
            int_from_text("n", text)
    for bad in (2000.5, True, "2000", None, math.nan, math.inf, [2000]):
        with pytest.raises(NumberError, match="^n: "):
            as_int("n", bad)
    for text in ("0x10", "1_000", "nan", "inf", " ", "", "2000.", ".5", "+5", "5 5", " 5", "5\n"):
        with pytest.raises(NumberError, match="expected a number"):
            from_text("n", text)
    with pytest.raises(NumberError, match="must be >= 1"):
        as_int("steps", 0, minimum=1)


def test_settings_follow_the_one_rule(tmp_path):
    from hope_models.settings import SettingsError

    assert load_settings(tmp_path / "a", env={"HOPE_PORT": "8765"}).port == 8765
    assert load_settings(tmp_path / "b", env={"HOPE_GATE_VAL_TOLERANCE": "5e-2"}).gate_val_tolerance == 0.05
    for env in ({"HOPE_PORT": "8765.5"}, {"HOPE_PORT": "8765.0"}, {"HOPE_PORT": "true"}, {"HOPE_PORT": "0x10"},
                {"HOPE_GATE_VAL_TOLERANCE": "nan"}):
        with pytest.raises(SettingsError, match=next(iter(env))):
            load_settings(tmp_path / "c", env=env)
    home = tmp_path / "d"
    home.mkdir()
    (home / "config.toml").write_text('port = "8765"\n')
    with pytest.raises(SettingsError, match="port.*expected an integer"):  # TOML has numbers: a string is not one
        load_settings(home, env={})
    (home / "config.toml").write_text("port = 8765.5\n")
    with pytest.raises(SettingsError, match="port.*expected an integer"):
        load_settings(home, env={})


def test_train_refuses_a_budget_above_the_deployments(tmp_path):
    import subprocess
    import sys

    env = {"HOPE_HOME": str(tmp_path / "h"), "HOPE_MEMORY_BUDGET_MB": "500", "PATH": "/usr/bin:/bin"}
    proc = subprocess.run([sys.executable, "-m", "hope_trainer", "train", "--component", "fast_loop", "--data",
                           str(tmp_path), "--run-dir", str(tmp_path / "r"), "--steps", "5", "--memory-budget-mb", "501"],
                          capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 2 and "memory_budget_mb: 501 MB is more than this deployment's budget of 500 MB" \
        in proc.stderr, proc.stderr
