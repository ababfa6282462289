"""The Robot Editor's browser libraries are committed in webapp/static/vendor/ (a robot's clean
checkout installs without npm): they must be exactly the files the pinned npm packages ship
(package-lock.json; `make setup` runs `npm ci`), so a committed copy cannot drift from the lock."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

from webapp.build_assets import VENDOR_DIR, VENDOR_FILES

REPO = Path(__file__).resolve().parent.parent


def test_the_committed_vendor_files_are_the_locked_packages_files():
    node_modules = REPO / "node_modules"
    lock = json.loads((REPO / "package-lock.json").read_text(encoding="utf-8"))["packages"]
    for name, src in VENDOR_FILES.items():
        package = src.split("/")[0]  # no scoped (@org/...) package is vendored
        shipped = node_modules / src
        assert shipped.is_file(), f"{shipped}: missing; `make setup` runs npm ci"
        installed = json.loads((node_modules / package / "package.json").read_text(encoding="utf-8"))["version"]
        assert installed == lock[f"node_modules/{package}"]["version"], package
        assert (VENDOR_DIR / name).read_bytes() == shipped.read_bytes(), f"{name} differs from {shipped}: make assets"


def test_the_vendor_files_are_tracked_by_git():
    tracked = subprocess.run(["git", "ls-files", "webapp/static/vendor"], cwd=REPO, capture_output=True, text=True,
                             check=True).stdout.split()
    assert sorted(tracked) == sorted(f"webapp/static/vendor/{name}" for name in VENDOR_FILES)
