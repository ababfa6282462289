"""Regenerates the lock files in requirements/ from pyproject.toml (runtime + [sim], no [dev]).

    python requirements/lock.py            # all three locks
    python requirements/lock.py x86_64-py311

`make lock` runs it. Each lock pins every package the robot runs, with the sha256 of every file of
that release, for one machine and Python: `make install` installs one with
`pip install --require-hashes --no-deps -r`, so nothing unpinned or unhashed reaches the robot.

uv resolves for a platform other than this machine's (pip can only install for it); it is used
only to write the locks, never to install (it would skip this machine's local CPU torch wheel).
"""
from __future__ import annotations

import argparse
import configparser
import glob
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
UV_VERSION = "0.13.9"
PYPI = "https://pypi.org/simple"

# name -> (uv's --python-platform, Python version, overrides). labmaze has no cp313 aarch64 wheel
# and its sdist needs Bazel; dm_control.suite never imports it (tests/test_locks.py proves the
# reacher steps without it), so the py313 lock leaves it out and `make install` installs the lock
# with --no-deps.
NO_LABMAZE = "labmaze ; python_version < '0'"
TARGETS = {
    "pi-aarch64-py311": ("aarch64-manylinux_2_28", "3.11", []),
    "pi-aarch64-py313": ("aarch64-manylinux_2_28", "3.13", [NO_LABMAZE]),
    "x86_64-py311": ("x86_64-manylinux_2_28", "3.11", []),
}


def pip_find_links() -> list[str]:
    """The find-links of pip's configuration: where this machine keeps its CPU torch wheel."""
    links = os.environ.get("PIP_FIND_LINKS", "").split()
    for conf in ("/etc/pip.conf", "/etc/xdg/pip/pip.conf", os.path.expanduser("~/.config/pip/pip.conf"),
                 os.path.expanduser("~/.pip/pip.conf")):
        parser = configparser.ConfigParser()
        try:
            parser.read(conf)
        except configparser.Error:
            continue
        links += parser.get("global", "find-links", fallback="").split()
    return list(dict.fromkeys(link for link in links if os.path.isdir(link)))


def x86_torch_override(find_links: list[str]) -> list[str]:
    """PyPI's x86_64 torch pulls GBs of CUDA: pin the local +cpu wheel when there is one."""
    for link in find_links:
        wheels = sorted(glob.glob(os.path.join(link, "torch-*+cpu-*x86_64.whl")))
        if wheels:
            return [f"torch=={Path(wheels[-1]).name.split('-')[1]}"]
    print("lock.py: no local torch +cpu wheel in pip's find-links; x86_64 torch comes from PyPI",
          file=sys.stderr)
    return []


def uv_command() -> list[str]:
    """uv from PATH, or a pinned uv in a cache venv of its own (never the project's venvs)."""
    found = shutil.which("uv")
    if found:
        return [found]
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "hope-trainer" / "uv"
    uv = cache / "bin" / "uv"
    if not uv.exists():
        subprocess.run([sys.executable, "-m", "venv", str(cache)], check=True)
        subprocess.run([str(cache / "bin" / "pip"), "install", "--quiet", f"uv=={UV_VERSION}"], check=True)
    return [str(uv)]


def compile_lock(name: str) -> Path:
    platform, python, overrides = TARGETS[name]
    out = HERE / f"{name}.txt"
    cmd = uv_command() + [
        "pip", "compile", str(ROOT / "pyproject.toml"), "--extra", "sim",
        "--python-platform", platform, "--python-version", python,
        "--index-url", PYPI, "--generate-hashes", "--no-annotate", "--quiet",
        "--custom-compile-command", f"python requirements/lock.py {name}",
        "-o", str(out),
    ]
    if name.startswith("x86_64"):
        links = pip_find_links()
        overrides = overrides + x86_torch_override(links)
        for link in links:
            cmd += ["--find-links", link]
    with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as fh:
        fh.write("\n".join(overrides) + "\n")
    try:
        if overrides:
            cmd += ["--override", fh.name]
        # a stale lock would be read as preferences: resolve afresh
        out.unlink(missing_ok=True)
        subprocess.run(cmd, check=True, cwd=ROOT)
    finally:
        os.unlink(fh.name)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("targets", nargs="*", metavar="LOCK", help=f"any of {', '.join(TARGETS)} (default: all)")
    args = parser.parse_args(argv)
    unknown = set(args.targets) - set(TARGETS)
    if unknown:
        parser.error(f"unknown lock {', '.join(sorted(unknown))}: choose from {', '.join(TARGETS)}")
    for name in args.targets or list(TARGETS):
        print(f"wrote {compile_lock(name).relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
