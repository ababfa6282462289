"""A component is one unit: a fourth one is a folder and a row of the table, nothing else.

The house's packages are copied as they are; tests/toy_component/ goes in as
hope_models/components/toy/ and one line ("toy",) is added to the table
(hope_models/components/__init__.py). Then, with only that copy on the path, a real `serve`
(daemon, Celery worker, webapp) trains a toy run the way a user queues one (`enqueue`), the
`promote` command gates and promotes it, and BrainService answers it over the API: what the toy's
NumPy form answers is what its torch model computes from the checkpoint.
"""
from __future__ import annotations

import filecmp
import json
import math
import os
import re
import shutil
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from daemon_fixtures import REPO, Home, Proc, tiny_dataset_path, wait_until

pytestmark = pytest.mark.slow

PACKAGES = ("daemon", "workers", "hope_models", "webapp", "registry", "hope_trainer", "migrations")
TOP_FILES = ("run_trainer.py", "alembic.ini", "pyproject.toml")
TABLE = "hope_models/components/__init__.py"
ROW = '    "mid_loop",\n'
OBS = [0.3, -0.2, 0.1, 0.5]  # the tiny dataset: obs 4, act 2

TORCH_ANSWER = """
import json, sys
import numpy as np, torch
from hope_models.components.build import component_from_checkpoint
comp = component_from_checkpoint(sys.argv[1])
o, a = comp.spec.observation, comp.spec.action
x = (np.asarray(json.loads(sys.argv[2])) - np.asarray(o.mean)) / np.asarray(o.std)
with torch.no_grad():
    y = comp.model(torch.tensor(x, dtype=torch.float32)[None])[0].double().numpy()
print(json.dumps(list(y * np.asarray(a.std) + np.asarray(a.mean))))
"""


def _copy_house(dest: Path) -> None:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "node_modules")
    for pkg in PACKAGES:
        shutil.copytree(REPO / pkg, dest / pkg, ignore=ignore)
    for name in TOP_FILES:
        if (REPO / name).is_file():
            shutil.copy2(REPO / name, dest / name)
    shutil.copytree(REPO / "tests" / "toy_component", dest / "hope_models" / "components" / "toy", ignore=ignore)
    table = (dest / TABLE).read_text()
    assert table.count(ROW) == 1, f"{TABLE}: the table's last row is not {ROW.strip()}"
    (dest / TABLE).write_text(table.replace(ROW, ROW + '    "toy",\n'))


def _changed(dest: Path) -> list[str]:
    """The house's files the copy differs in (the toy's own folder aside)."""
    changed = []
    for pkg in PACKAGES:
        for path in (REPO / pkg).rglob("*"):
            if path.is_file() and "__pycache__" not in path.parts and "node_modules" not in path.parts:
                rel = path.relative_to(REPO)
                if not filecmp.cmp(path, dest / rel, shallow=False):
                    changed.append(rel.as_posix())
    return changed


def _cli(house: Path, home: Home, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(house / "run_trainer.py"), *args], cwd=house, env=home.env,
                          capture_output=True, text=True, timeout=timeout)


def test_a_fourth_component_from_one_folder_trains_is_gated_promoted_and_served(tmp_path, tmp_path_factory):
    house = tmp_path / "house"
    _copy_house(house)
    assert _changed(house) == [TABLE]
    added = [line for line in (house / TABLE).read_text().splitlines()
             if line not in (REPO / TABLE).read_text().splitlines()]
    assert added == ['    "toy",']

    home = Home(tmp_path / "home", extra_env={"PYTHONPATH": str(house)})
    shutil.copytree(tiny_dataset_path(tmp_path_factory), home.settings.datasets_dir / "ds")
    log = home.path / "serve.log"
    home.logs += [log, home.path / "logs" / "worker.log"]
    serve = Proc("serve", [sys.executable, str(house / "run_trainer.py"), "serve", "--port", "0"], home.env, log,
                 cwd=house)
    try:
        def banner():
            assert serve.alive(), log.read_text()
            return ("Robot Editor: " in log.read_text()) and log.read_text()
        text = wait_until(banner, 30, "serve to print its URL", home)
        url, token = re.search(r"Robot Editor: (http://\S+)  token: (\S+)", text).groups()

        # queued the way a user does: the copy's own CLI, which knows the toy from its table
        out = _cli(house, home, "enqueue", "--component", "toy", "--data", str(home.settings.datasets_dir / "ds"),
                   "--steps", "120",
                   "--batch-size", "16", "--threads", "1", "--log-every", "10", "--json")
        assert out.returncode == 0, out.stdout + out.stderr
        run_id = json.loads(out.stdout)["id"]
        wait_until(lambda: home.run(run_id)["state"] in ("completed", "failed", "cancelled"), 180,
                   f"the toy run {run_id} to finish", home)
        run = home.run(run_id)
        assert run["state"] == "completed" and run["component"] == "toy", home.describe()
        losses = [json.loads(line) for line in (Path(run["run_dir"]) / "metrics.jsonl").read_text().splitlines()]
        train = [r["loss"] for r in losses if r.get("type") == "metric" and r.get("loss") is not None]
        assert len(train) >= 5 and train[-1] < train[0], train  # it learned something

        # gated and promoted by the promote command (the gate runs as a child)
        out = _cli(house, home, "promote", run_id, "--component", "toy", "--json")
        assert out.returncode == 0, out.stdout + out.stderr
        outcome = json.loads(out.stdout.strip().splitlines()[-1])
        assert outcome.get("promoted") is True, outcome
        version = outcome["version"]

        # BrainService (in serve) follows the pointer and answers the toy under `outputs`
        def answer():
            req = urllib.request.Request(url.rstrip("/") + "/api/brain/infer", method="POST",
                                         data=json.dumps({"component": "toy", "observation": OBS}).encode(),
                                         headers={"Authorization": f"Bearer {token}",
                                                  "Content-Type": "application/json"})
            try:
                with urllib.request.urlopen(req, timeout=10) as r:
                    return json.load(r)
            except urllib.error.HTTPError as exc:
                assert exc.code == 503, exc.read()  # not served yet
                return None

        got = wait_until(answer, 30, "BrainService to serve the promoted toy", home)
        assert got["versions"]["toy"] == version and got["model_version"] == version, got
        assert got["action"] is None and set(got["outputs"]) == {"toy"}, got
        served = got["outputs"]["toy"]
        assert len(served) == 2 and all(math.isfinite(v) for v in served), served

        ckpt = Path(run["run_dir"]) / "checkpoints"
        env = dict(home.env, PYTHONPATH=str(house))
        torch_out = subprocess.run([sys.executable, "-c", TORCH_ANSWER, str(ckpt / (ckpt / "last").read_text().strip()),
                                    json.dumps(OBS)], cwd=house, env=env, capture_output=True, text=True, timeout=120)
        assert torch_out.returncode == 0, torch_out.stderr
        assert served == pytest.approx(json.loads(torch_out.stdout), abs=1e-5)
    finally:
        serve.signal(2)
        try:
            serve.popen.wait(60)
        finally:
            serve.stop()
            home.close()
    assert not os.environ.get("PYTHONPATH", "").startswith(str(house))
