"""The tool as a user installs it: build the wheel, install it (not editable) into a fresh venv
outside the checkout, and from a directory that is not the checkout run `hope-trainer`: --version,
--help, and `serve` on a free port, which answers /api/health, the Robot Editor and its vendored
scripts, and trains a 20-step fast_loop queued through the API to `completed`.

Installing torch and the rest again would take minutes per run, so the wheel goes in with --no-deps
and the fresh venv sees the dev venv's site-packages through a .pth line. A directory added that
way does not have its own .pth files processed, so the checkout's editable install stays invisible:
the test checks that hope_trainer, webapp, registry and migrations all come from the new venv.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import time
import tomllib
import urllib.error
import urllib.request
import zipfile
from pathlib import Path

import psutil
import pytest

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
DIST_NAME = PYPROJECT["project"]["name"]
VERSION = PYPROJECT["project"]["version"]
VENDOR = sorted(p.name for p in (REPO / "webapp" / "static" / "vendor").glob("*.js"))

pytestmark = pytest.mark.slow


def _run(cmd: list, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{cmd}: exit {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def _clean_env(**extra: str) -> dict[str, str]:
    """This environment without what would point a child at the checkout or at another $HOPE_HOME."""
    dropped = ("VIRTUAL_ENV", "NOTIFY_SOCKET", "WATCHDOG_USEC")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("HOPE_", "PYTHON", "PIP_")) and k not in dropped}
    env.update({"PIP_DISABLE_PIP_VERSION_CHECK": "1", "PIP_NO_INPUT": "1", "PYTHONUNBUFFERED": "1"}, **extra)
    return env


def build_wheel(workdir: Path) -> Path:
    """The wheel of a copy of the packages pyproject.toml lists (a fresh tree: no build/ left over
    from an earlier build can add a module that moved since)."""
    if not VENDOR:
        pytest.fail("webapp/static/vendor/ holds no scripts: run `make assets` (npm ci + webapp/build_assets.py)")
    src = workdir / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    for pattern in PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]:
        package = pattern.rstrip("*")
        shutil.copytree(REPO / package, src / package, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
          "-w", workdir / "dist", src], cwd=workdir, env=_clean_env(), timeout=300)
    wheels = list((workdir / "dist").glob("*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def make_venv(workdir: Path, wheel: Path) -> Path:
    """A fresh venv with the wheel installed (no -e, no dependencies) and the dev venv's
    site-packages on its path for those; returns its bin/ directory."""
    venv = workdir / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], timeout=120)
    python = venv / "bin" / "python"
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--quiet", "--no-deps", "--no-index",
          wheel], cwd=workdir, env=_clean_env(), timeout=300)
    purelib = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        cwd=workdir, env=_clean_env()).stdout.strip())
    dev_site = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (purelib / "zz_dev_dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(dev_site)), encoding="utf-8")
    return venv / "bin"


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    work = tmp_path_factory.mktemp("installed-wheel")
    assert not work.resolve().is_relative_to(REPO)
    wheel = build_wheel(work)
    names = set(zipfile.ZipFile(wheel).namelist())
    return {"bin": make_venv(work, wheel), "wheel_files": names, "cwd": work}


def test_the_wheel_carries_the_files_the_tool_reads(installed):
    names = installed["wheel_files"]
    expected = {f"webapp/static/vendor/{n}" for n in VENDOR} | {"webapp/templates/editor.html",
                                                                "migrations/script.py.mako", "migrations/env.py",
                                                                "hope_trainer/__main__.py", "hope_trainer/cli.py"}
    expected |= {f"migrations/versions/{p.name}" for p in (REPO / "migrations" / "versions").glob("*.py")}
    expected |= {f"webapp/static/{p.relative_to(REPO / 'webapp' / 'static')}"
                 for p in (REPO / "webapp" / "static").rglob("*") if p.is_file() and not p.name.startswith(".")}
    assert expected <= names, sorted(expected - names)
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    assert entry_points.startswith(DIST_NAME.replace("-", "_") + "-")
    assert "run_trainer.py" not in names


def test_the_installed_packages_come_from_the_venv_not_the_checkout(installed):
    venv = installed["bin"].parent
    code = ("import hope_trainer, hope_models, registry, daemon, workers, webapp, migrations\n"
            "for m in (hope_trainer, hope_models, registry, daemon, workers, webapp, migrations): print(m.__file__)")
    proc = _run([installed["bin"] / "python", "-c", code], cwd=installed["cwd"], env=_clean_env())
    for line in proc.stdout.split():
        assert Path(line).resolve().is_relative_to(venv.resolve()), line
        assert not Path(line).resolve().is_relative_to(REPO), line


def test_version_and_help_list_every_verb(installed):
    from hope_trainer.cli import COMMANDS

    tool = installed["bin"] / "hope-trainer"
    assert _run([tool, "--version"], cwd=installed["cwd"], env=_clean_env()).stdout.strip() == \
        f"hope-trainer {VERSION}"
    text = _run([tool, "--help"], cwd=installed["cwd"], env=_clean_env(), timeout=120).stdout
    verbs = set(re.findall(r"^    (\S+)", text, re.M))
    assert set(COMMANDS) <= verbs, sorted(set(COMMANDS) - verbs)
    as_module = _run([installed["bin"] / "python", "-m", "hope_trainer", "--version"], cwd=installed["cwd"],
                     env=_clean_env())
    assert as_module.stdout.strip() == f"hope-trainer {VERSION}"


# -- serve from the installed tool -----------------------------------------------------------------

def _get(url: str, token: str | None = None, body: dict | None = None) -> tuple[int, bytes]:
    request = urllib.request.Request(url, data=None if body is None else json.dumps(body).encode(),
                                     method="GET" if body is None else "POST")
    if body is not None:
        request.add_header("Content-Type", "application/json")
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def _wait(predicate, timeout: float, what: str, log: Path):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.3)
    tails = [f"--- {p.name}\n" + p.read_text(errors="replace")[-4000:]
             for p in [log, *sorted((log.parent / "home" / "logs").glob("*.log"))] if p.exists()]
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}\n" + "\n".join(tails))


def _family(pid: int) -> list[tuple[psutil.Process, list[str]]]:
    """A process and its descendants, each with its command line (empty for a zombie)."""
    try:
        parent = psutil.Process(pid)
        procs = [parent, *parent.children(recursive=True)]
    except psutil.NoSuchProcess:
        return []
    out = []
    for p in procs:
        try:
            out.append((p, p.cmdline()))
        except psutil.Error:
            pass
    return out


def test_serve_trains_a_queued_run_from_outside_the_checkout(installed):
    from hope_models.data.synthetic import generate_dataset

    work = installed["cwd"] / "serve"
    home = work / "home"
    work.mkdir()
    data = home / "datasets" / "tiny"
    generate_dataset(data, 600, obs_dim=4, act_dim=2, episode_seconds=(3, 9), seed=3)
    env = _clean_env(HOPE_HOME=str(home), HOPE_AUTO_PROMOTE="0", HOPE_THERMAL_ZONE=str(home / "no-thermal-zone"),
                     HOPE_VCGENCMD="", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    log = work / "serve.log"
    with open(log, "ab") as out:
        proc = subprocess.Popen([str(installed["bin"] / "hope-trainer"), "serve", "--port", "0"], cwd=work, env=env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    seen: dict[int, tuple[psutil.Process, list[str]]] = {}
    try:
        def banner():
            assert proc.poll() is None, f"serve exited with {proc.returncode}:\n{log.read_text(errors='replace')}"
            return re.search(r"Robot Editor: (http://\S+)  token: (\S+)", log.read_text(errors="replace"))

        match = _wait(banner, 60, "serve to print its URL", log)
        url, token = match.group(1).rstrip("/"), match.group(2)
        assert _get(url + "/api/health")[0] == 200

        status, page = _get(url + "/")
        assert status == 200
        scripts = re.findall(r'<script src="([^"]+)"', page.decode())
        vendored = [s for s in scripts if "/vendor/" in s]
        assert sorted(s.rsplit("/", 1)[1] for s in vendored) == VENDOR, scripts
        for src in scripts + re.findall(r'<link[^>]+href="([^"]+\.css)"', page.decode()):
            assert _get(url + src)[0] == 200, src

        status, body = _get(url + "/api/runs", token, {
            "component": "fast_loop", "data": str(data), "steps": 20, "seed": 0, "batch_size": 8, "threads": 1,
            "warmup": 5, "log_every": 5})
        assert status == 201, body
        run_id = json.loads(body)["run"]["id"]

        def ended():
            for p, cmdline in _family(proc.pid):
                if cmdline:
                    seen.setdefault(p.pid, (p, cmdline))
            state = json.loads(_get(f"{url}/api/runs/{run_id}", token)[1])["run"]["state"]
            return state if state in ("completed", "failed", "cancelled") else None

        assert _wait(ended, 240, f"run {run_id} to end", log) == "completed"
        workers = [p for p, _ in seen.values() if p.pid != proc.pid]
        assert workers, "serve started no worker child"
        for _, cmdline in seen.values():  # the installed interpreter ran every one, not the dev venv's
            assert Path(cmdline[0]).parent == installed["bin"], cmdline

        proc.send_signal(signal.SIGINT)
        assert proc.wait(60) == 0, log.read_text(errors="replace")
        gone, alive = psutil.wait_procs(workers, timeout=10)
        assert not alive, f"left running after serve stopped: {[p.pid for p in alive]}"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
        for p, _ in seen.values():
            try:
                p.kill()
            except psutil.NoSuchProcess:
                pass
