"""The doctor's checks that must run in a child process: torch's build and an EGL frame.

A torch wheel built for the wrong CPU dies with SIGILL, and a GL driver that is missing a library
can hang or abort: in a child (with a timeout) that is a fail line with the child's last words,
not a crash of the doctor, and the doctor's own process never pays for importing torch.
"""
from __future__ import annotations

import importlib.metadata
import json
import os
import signal
import subprocess
import sys
from typing import Any

from hope_trainer.doctor.check import FAIL, OK, SKIP, WARN, Check

TORCH_TIMEOUT_S = 180.0  # importing torch on a Pi 5 from an SD card takes several seconds cold
RENDER_TIMEOUT_S = 120.0
INSTALL_FIX = "reinstall from the lock: sudo make install (docs/pi.md, 'Install')"

_TORCH_CODE = """
import json, platform, torch
x = torch.ones(8, 8)
print(json.dumps({"version": torch.__version__, "cuda": torch.version.cuda, "machine": platform.machine(),
                  "threads": torch.get_num_threads(), "mkldnn": torch.backends.mkldnn.is_available(),
                  "matmul_ok": float((x @ x).sum()) == 512.0}))
"""
# The same path the recorder and the reflex stream take (sim/reacher.py): MUJOCO_GL=egl, a 64x64 frame.
_RENDER_CODE = """
import json
import numpy as np
from hope_models.sim.reacher import make_env
frame = make_env(frames=True).render(64)
print(json.dumps({"shape": list(frame.shape), "nonblank": bool(np.asarray(frame).std() > 0)}))
"""


def _child(code: str, timeout: float, env: dict[str, str] | None = None) -> tuple[dict | None, str]:
    """(the child's JSON line, or None; why not) for `python -c code`."""
    try:
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout,
                              check=False, env=env, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return None, f"the child did not finish in {timeout:g} s"
    except OSError as exc:
        return None, f"could not start {sys.executable}: {exc.strerror or exc}"
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1][:300]
        if proc.returncode < 0:
            name = signal.Signals(-proc.returncode).name if -proc.returncode in signal.valid_signals() else "?"
            return None, f"the child died of signal {-proc.returncode} ({name}): {last}"
        return None, f"the child exited {proc.returncode}: {last}"
    try:
        return json.loads(proc.stdout.strip().splitlines()[-1]), ""
    except (ValueError, IndexError):
        return None, f"the child printed no result: {proc.stdout.strip()[-200:]!r}"


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def check_torch(_settings: Any) -> Check:
    installed = _version("torch")
    if installed is None:
        return Check("torch", FAIL, "torch is not installed in this environment", INSTALL_FIX)
    got, why = _child(_TORCH_CODE, TORCH_TIMEOUT_S)
    if got is None:
        return Check("torch", FAIL, f"torch {installed} is installed but does not import: {why}",
                     f"{INSTALL_FIX}; a SIGILL means a wheel built for another CPU")
    build = "CPU" if got.get("cuda") is None else f"CUDA {got['cuda']}"
    detail = (f"{got['version']} ({build} build for {got['machine']}, {got['threads']} threads, "
              f"oneDNN {'on' if got.get('mkldnn') else 'off'})")
    if not got.get("matmul_ok"):
        return Check("torch", FAIL, f"{detail}: an 8x8 matmul gave a wrong answer", INSTALL_FIX)
    if got["version"].split("+")[0] != installed.split("+")[0]:
        return Check("torch", WARN, f"{detail}: the package metadata says {installed}", INSTALL_FIX)
    return Check("torch", OK, detail)


def check_render(_settings: Any) -> Check:
    missing = [d for d in ("mujoco", "dm-control") if _version(d) is None]
    if missing:
        return Check("render", SKIP, f"{', '.join(missing)} not installed (the [sim] extra): no simulator here")
    env = {**os.environ, "MUJOCO_GL": "egl"}
    got, why = _child(_RENDER_CODE, RENDER_TIMEOUT_S, env=env)
    if got is None:
        return Check("render", FAIL, f"a 64x64 frame under MUJOCO_GL=egl did not render: {why}",
                     "sudo apt install libegl1 libgl1-mesa-dri libopengl0 (a minimal Raspberry Pi OS lacks "
                     "libopengl0); sim-demos --frames and eval-reflex --stream-frames need it")
    if got.get("shape") != [64, 64, 3] or not got.get("nonblank"):
        return Check("render", WARN, f"the frame came back as {got.get('shape')}, blank={not got.get('nonblank')}",
                     "check the Mesa driver: sudo apt install --reinstall libgl1-mesa-dri")
    return Check("render", OK, "a 64x64 frame rendered under MUJOCO_GL=egl")
