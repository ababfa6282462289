"""The production locks (requirements/*.txt, written by requirements/lock.py, installed by
`make install`): they agree with pyproject.toml, every aarch64 pin has a binary wheel on PyPI for
its Python whose sha256 the lock holds, and dm_control.suite works without labmaze (the py313 lock
leaves it out: it has no cp313 aarch64 wheel).

The wheel check reads PyPI's JSON simple API (PEP 691: file names and hashes, a few MB in all)
instead of `pip download --platform ...`, which would fetch hundreds of MB of torch and friends.
It matches file names against the tags pip accepts for `--platform manylinux_2_28_aarch64
--python-version 3.x --only-binary=:all:`, the target lock.py resolved for.
"""
from __future__ import annotations

import functools
import json
import os
import re
import subprocess
import sys
import textwrap
import tomllib
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.tags import compatible_tags, cpython_tags
from packaging.utils import canonicalize_name, parse_wheel_filename
from packaging.version import Version

REPO = Path(__file__).resolve().parents[1]
LOCKS = {  # lock -> (platform_machine, python version)
    "pi-aarch64-py311": ("aarch64", (3, 11)),
    "pi-aarch64-py313": ("aarch64", (3, 13)),
    "x86_64-py311": ("x86_64", (3, 11)),
}
PYPI_SIMPLE = "https://pypi.org/simple"
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)")
_HASH = re.compile(r"--hash=sha256:([0-9a-f]{64})")


def read_lock(name: str) -> dict[str, tuple[str, set[str]]]:
    """canonical name -> (version, sha256 set) of a lock file."""
    pins: dict[str, tuple[str, set[str]]] = {}
    current = None
    for line in (REPO / "requirements" / f"{name}.txt").read_text(encoding="utf-8").splitlines():
        match = _PIN.match(line)
        if match:
            current = canonicalize_name(match.group(1))
            assert current not in pins, f"{name}: {current} pinned twice"
            pins[current] = (match.group(2), set())
        elif current and _HASH.search(line):
            pins[current][1].update(_HASH.findall(line))
        elif line.strip() and not line.lstrip().startswith("#"):
            pytest.fail(f"{name}: unexpected line {line!r} (only name==version and --hash lines)")
    return pins


def runtime_requirements(machine: str, python: tuple[int, int]) -> list[Requirement]:
    """pyproject's dependencies + [sim] that apply on this machine and Python."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    env = {"platform_machine": machine, "python_version": "%d.%d" % python,
           "python_full_version": "%d.%d.0" % python, "sys_platform": "linux", "extra": ""}
    reqs = [Requirement(r) for r in project["dependencies"] + project["optional-dependencies"]["sim"]]
    return [r for r in reqs if r.marker is None or r.marker.evaluate(env)]


@pytest.mark.parametrize("lock", sorted(LOCKS))
def test_lock_pins_what_pyproject_asks(lock):
    machine, python = LOCKS[lock]
    pins = read_lock(lock)
    for req in runtime_requirements(machine, python):
        name = canonicalize_name(req.name)
        assert name in pins, f"{lock} does not pin {req}: run `make lock`"
        assert req.specifier.contains(pins[name][0], prereleases=True), \
            f"{lock} pins {name}=={pins[name][0]}, pyproject.toml asks {req}: run `make lock`"
    for name, (version, hashes) in pins.items():
        assert hashes, f"{lock}: {name}=={version} has no --hash (make install uses --require-hashes)"
    # the robot's venv holds no test tools
    assert not {"pytest", "pytest-xdist", "playwright", "fakeredis"} & set(pins), lock
    if machine == "aarch64":
        # PyPI's aarch64 torch 2.11+ drags CUDA packages onto the Pi
        assert Version(pins["torch"][0]) < Version("2.11"), pins["torch"]
        assert not [n for n in pins if n.startswith("nvidia-") or n == "triton"], lock


def test_py313_lock_leaves_labmaze_out():
    """labmaze has no cp313 aarch64 wheel and its sdist needs Bazel; py311 has a wheel and keeps it."""
    assert "labmaze" not in read_lock("pi-aarch64-py313")
    assert "labmaze" in read_lock("pi-aarch64-py311")
    assert "dm-control" in read_lock("pi-aarch64-py313")


def _accepted_tags(python: tuple[int, int]) -> set:
    """What pip accepts for --platform manylinux_2_28_aarch64 --python-version 3.x: manylinux
    2_28 down to 2_17, the manylinux2014 alias of 2_17, CPython's ABIs, abi3 and pure wheels."""
    platforms = [f"manylinux_2_{minor}_aarch64" for minor in range(28, 16, -1)] + ["manylinux2014_aarch64"]
    tags = set(cpython_tags(python, platforms=platforms))
    tags.update(compatible_tags(python, interpreter=f"cp{python[0]}{python[1]}", platforms=platforms))
    return tags


@functools.lru_cache(maxsize=None)  # both aarch64 locks share most names: one fetch each
def _pypi_files(name: str) -> list[dict]:
    request = urllib.request.Request(f"{PYPI_SIMPLE}/{name}/",
                                     headers={"Accept": "application/vnd.pypi.simple.v1+json"})
    with urllib.request.urlopen(request, timeout=60) as response:
        return json.load(response)["files"]


def _missing_wheel(name: str, version: str, hashes: set[str], accepted: set, files: list[dict]) -> str | None:
    """None when a file of name==version is an accepted wheel whose sha256 is in the lock."""
    wheels = []
    for entry in files:
        if not entry["filename"].endswith(".whl") or entry.get("yanked"):
            continue
        _, wheel_version, _, tags = parse_wheel_filename(entry["filename"])
        if wheel_version == Version(version) and tags & accepted:
            wheels.append(entry)
    if not wheels:
        return f"{name}=={version}: no wheel for these tags on PyPI"
    if not any(entry["hashes"].get("sha256") in hashes for entry in wheels):
        return f"{name}=={version}: the lock's hashes match none of {[w['filename'] for w in wheels]}"
    return None


@pytest.mark.parametrize("lock", ["pi-aarch64-py311", "pi-aarch64-py313"])
def test_aarch64_lock_has_a_wheel_for_every_pin(lock):
    machine, python = LOCKS[lock]
    pins = read_lock(lock)
    accepted = _accepted_tags(python)
    with ThreadPoolExecutor(max_workers=8) as pool:
        listings = dict(zip(pins, pool.map(_pypi_files, pins)))
    missing = [problem for name, (version, hashes) in sorted(pins.items())
               if (problem := _missing_wheel(name, version, hashes, accepted, listings[name]))]
    assert not missing, f"{lock} (cp{python[0]}{python[1]} manylinux_2_28_aarch64):\n" + "\n".join(missing)
    # the check can fail: labmaze, left out of py313 for this reason, has no such wheel
    if python == (3, 13):
        labmaze = _missing_wheel("labmaze", "1.0.6", set(), accepted, _pypi_files("labmaze"))
        assert labmaze and "no wheel" in labmaze, labmaze


# A meta-path finder first in line makes every `import labmaze` fail, as on the py313 Pi.
NO_LABMAZE = textwrap.dedent("""
    import sys
    class NoLabmaze:
        def find_spec(self, name, path=None, target=None):
            if name == "labmaze" or name.startswith("labmaze."):
                raise ImportError("labmaze is not installed (py313 lock)")
            return None
    sys.meta_path.insert(0, NoLabmaze())
    try:
        import labmaze  # noqa: F401
        raise SystemExit("the finder did not hide labmaze")
    except ImportError:
        pass
    import numpy as np
    from dm_control import suite
    env = suite.load("reacher", "easy", task_kwargs={"random": 0})
    spec = env.action_spec()
    step = env.reset()
    total = 0.0
    for i in range(20):
        step = env.step(np.full(spec.shape, 0.5, dtype=spec.dtype))
        total += step.reward or 0.0
    obs = np.concatenate([np.ravel(v) for v in step.observation.values()])
    assert np.all(np.isfinite(obs)) and obs.size > 0, obs
    assert not [m for m in sys.modules if m.split(".")[0] == "labmaze"]
    print("reacher ok", obs.size, round(total, 3))
""")


def test_reacher_loads_and_steps_without_labmaze():
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env.setdefault("MUJOCO_GL", "egl")
    proc = subprocess.run([sys.executable, "-c", NO_LABMAZE], capture_output=True, text=True, timeout=120,
                          env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    assert proc.stdout.startswith("reacher ok"), proc.stdout


def test_make_install_uses_the_lock_and_no_dev_tools():
    """`make -n install` (what it would run, nothing is created): this machine's lock with hashes,
    no npm, no [dev]. The venv path must not itself contain a word searched for (pytest's tmp_path does)."""
    proc = subprocess.run(["make", "-n", "install", "INSTALL_VENV=/srv/hope-venv"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    machine = os.uname().machine
    tag = ("pi-aarch64" if machine in ("aarch64", "arm64") else machine) + "-py%d%d" % sys.version_info[:2]
    assert f"--require-hashes --no-deps --only-binary=:all: -r \"requirements/{tag}.txt\"" in proc.stdout, proc.stdout
    assert "libopengl0" in proc.stdout
    assert not re.search(r"\bnpm\s+(ci|install|run)\b|build_assets", proc.stdout), proc.stdout
    for word in ("[dev", "playwright", "chromium", "pytest", ".venv/"):
        assert word not in proc.stdout, f"make install would run {word!r}:\n{proc.stdout}"


def test_pip_agrees_with_the_tag_check(tmp_path):
    """The tag set above is what pip itself accepts: pip downloads the locked crc32c (a small
    compiled wheel) for cp313 manylinux_2_28_aarch64 and refuses labmaze (no such wheel)."""
    version = read_lock("pi-aarch64-py313")["crc32c"][0]

    def download(spec: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [sys.executable, "-m", "pip", "download", "--isolated", "--index-url", PYPI_SIMPLE, "--quiet",
             "--only-binary=:all:", "--no-deps", "--platform", "manylinux_2_28_aarch64",
             "--python-version", "3.13", "-d", str(tmp_path), spec],
            capture_output=True, text=True, timeout=120)

    ok = download(f"crc32c=={version}")
    assert ok.returncode == 0, ok.stderr[-2000:]
    [wheel] = tmp_path.glob("crc32c-*.whl")
    assert parse_wheel_filename(wheel.name)[3] & _accepted_tags((3, 13)), wheel.name
    refused = download("labmaze==1.0.6")
    assert refused.returncode != 0 and "labmaze" in refused.stderr, refused.stderr[-2000:]
