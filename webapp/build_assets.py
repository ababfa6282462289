"""Copy the Robot Editor's browser libraries from node_modules/ into webapp/static/vendor/.

    npm ci && python webapp/build_assets.py      (what `make setup` runs)

No CDN: a robot is often offline, so the pages load only files this server has. npm installs the
pinned versions (package.json / package-lock.json at the repo root); this script copies the one
prebuilt browser file each package ships, so there is no bundler and no build step beyond a copy.
The copies in webapp/static/vendor/ are committed, so a clean checkout (the robot's `make install`)
needs no npm; `make assets` refreshes them from the pinned packages and tests/test_vendor_assets.py
checks they are the bytes npm installs. webapp/pages.py names the same files and the page says
what to run when one is missing.
"""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
VENDOR_DIR = Path(__file__).resolve().parent / "static" / "vendor"

# vendor file name -> the file inside node_modules/ (UMD builds: plain <script> globals `io`, `Chart`,
# `Hammer`, `ChartZoom`). The page loads them in this order: the zoom plugin needs Chart and Hammer
# (touch pan and pinch) before it, and registers itself with Chart when it loads.
VENDOR_FILES = {
    "socket.io.min.js": "socket.io-client/dist/socket.io.min.js",
    "chart.umd.min.js": "chart.js/dist/chart.umd.min.js",
    "hammer.min.js": "hammerjs/hammer.min.js",
    "chartjs-plugin-zoom.min.js": "chartjs-plugin-zoom/dist/chartjs-plugin-zoom.min.js",
}


def missing_vendor_files(vendor_dir: Path = VENDOR_DIR) -> list[str]:
    return [name for name in VENDOR_FILES if not (vendor_dir / name).is_file()]


def build(node_modules: Path, vendor_dir: Path = VENDOR_DIR) -> list[Path]:
    """Copy every VENDOR_FILES entry; FileNotFoundError names the first missing source."""
    missing = [src for src in VENDOR_FILES.values() if not (node_modules / src).is_file()]
    if missing:
        raise FileNotFoundError(f"{node_modules / missing[0]} is missing: run `npm ci` in {REPO_ROOT} first")
    vendor_dir.mkdir(parents=True, exist_ok=True)
    out = []
    for name, src in VENDOR_FILES.items():
        dest = vendor_dir / name
        shutil.copyfile(node_modules / src, dest)
        out.append(dest)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--node-modules", type=Path, default=REPO_ROOT / "node_modules")
    parser.add_argument("--vendor-dir", type=Path, default=VENDOR_DIR)
    args = parser.parse_args(argv)
    try:
        copied = build(args.node_modules, args.vendor_dir)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for path in copied:
        print(f"copied {path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
