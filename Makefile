# Two entry points for a fresh machine: `make demo` and `make test` (see README.md).
# Everything a test needs is installed from here; nothing is expected to be on the machine by hand.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# pytest options for `make test`; e.g. make test PYTEST_ARGS="-k rlds"
PYTEST_ARGS ?=
# pytest-xdist workers for `make test`: most tests wait on servers and child processes, so two
# workers on CI's two cores overlap those waits (PYTEST_WORKERS=0 runs everything in one process).
# worksteal keeps each worker on a contiguous run of files (module fixtures built once) and lets an
# idle worker take tests from the busy one.
PYTEST_WORKERS ?= 2
PYTEST_XDIST := $(if $(filter 0,$(PYTEST_WORKERS)),-p no:xdist,-n $(PYTEST_WORKERS) --dist worksteal)

.PHONY: setup lint test demo bench clean system-deps gl-deps assets install lock

ASSETS := webapp/static/vendor/.stamp

setup: $(STAMP) $(ASSETS)

# ruff (pyflakes, import order, bugbear) on the packages, bench/ and run_trainer.py (not tests/), then
# mypy on the service packages ([tool.mypy] in pyproject.toml); `make test` runs it first.
LINT_PATHS := daemon workers hope_models webapp registry hope_trainer migrations run_trainer.py bench
# mypy's cache lives with the user's caches, not in the clone: a fresh clone (CI) then checks in
# ~1 s instead of ~16 s; mypy re-checks every file whose contents differ from the cached ones.
MYPY_CACHE ?= $(or $(XDG_CACHE_HOME),$(HOME)/.cache)/hope-seed-trainer/mypy
lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINT_PATHS)
	MYPY_CACHE_DIR=$(MYPY_CACHE) $(VENV)/bin/mypy

# The daemon tests start a real redis-server on a loopback port (the production broker); the browser
# tests drive Debian's chromium (never `playwright install`: no browser downloads); npm installs the
# Robot Editor's JS (socket.io-client, chart.js) from package-lock.json.
APT_DEPS := redis-server:redis-server chromium:chromium npm:npm
# tests/test_systemd_units.py checks the units with systemd-analyze (verify, security --offline=true)
APT_DEPS += systemd-analyze:systemd
# libopengl0 (libOpenGL.so.0): without it PyOpenGL's EGL platform cannot load GL on a minimal
# Raspberry Pi OS and `import mujoco` under MUJOCO_GL=egl fails.
GL_DEPS := libegl1 libgl1-mesa-dri libopengl0
system-deps: gl-deps
	@for dep in $(APT_DEPS); do cmd=$${dep%%:*}; pkg=$${dep#*:}; \
	  command -v $$cmd >/dev/null 2>&1 && continue; \
	  if [ "$$(id -u)" = 0 ]; then apt-get install -y -q $$pkg >/dev/null || \
	    { apt-get update -q >/dev/null && apt-get install -y -q $$pkg >/dev/null; }; \
	  else sudo apt-get install -y -q $$pkg >/dev/null; fi; \
	  command -v $$cmd >/dev/null 2>&1 || { echo "$$cmd is needed by the tests: apt-get install $$pkg" >&2; exit 1; }; \
	done

# MUJOCO_GL=egl (frames for the VQ-VAE and the reflex view) needs the EGL and Mesa drivers.
gl-deps:
	@dpkg -s $(GL_DEPS) >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get install -y -q $(GL_DEPS) >/dev/null || \
	    { apt-get update -q >/dev/null && apt-get install -y -q $(GL_DEPS) >/dev/null; }; \
	  else sudo apt-get install -y -q $(GL_DEPS) >/dev/null; fi; }

# The Robot Editor's browser libraries: npm (pinned by package-lock.json), copied into
# webapp/static/vendor/ (generated, gitignored) by webapp/build_assets.py.
assets: $(ASSETS)
$(ASSETS): package.json package-lock.json webapp/build_assets.py | system-deps
	npm ci --no-audit --no-fund --loglevel=error
	$(PYTHON) webapp/build_assets.py
	@touch $@

# Plain pip into a venv: uv/poetry would skip the local CPU torch wheel and pull CUDA.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -e '.[dev,sim]'
	@touch $@

test: setup system-deps lint
	$(PY) -m pytest -q $(PYTEST_XDIST) --durations=15 -m "not heavy" $(PYTEST_ARGS)

# The tests marked heavy (tests/conftest.py): minutes each, outside the suite's budget (e.g. the
# camera demo end to end, tests/test_demo_camera_e2e.py).
.PHONY: test-heavy
test-heavy: setup system-deps
	$(PY) -m pytest -q -p no:xdist --durations=15 -m heavy $(PYTEST_ARGS)

demo: setup
	$(PY) run_trainer.py demo

# The same loop on the camera observation (joints + a 64x64 frame rendered with EGL): ~21 minutes
# on 2 idle cores (hope_trainer/demo/camera.py, docs/reflex.md "demo --camera").
.PHONY: demo-camera
demo-camera: setup
	$(PY) run_trainer.py demo --camera

bench: setup
	$(PY) bench/data_pipeline.py

# The wheel, into dist/: the `hope-trainer` console script, the Robot Editor's static files (with the
# npm-built vendor/ JS, hence $(ASSETS)), its templates and the Alembic migrations. Install it with
# `pip install dist/hope_seed_trainer-*.whl`. build/ goes first: setuptools would otherwise carry a
# module that moved or was deleted over from an earlier build.
.PHONY: dist
dist: $(STAMP) $(ASSETS)
	rm -rf build
	$(PY) -m pip wheel --quiet --no-deps --no-build-isolation -w dist .

# arm64 under qemu-user: a cached Debian bookworm arm64 root (debootstrap), a venv from
# requirements/pi-aarch64-py311.txt, then sim-demos -> ingest -> train fast_loop -> promote ->
# infer --local, each timed (bench/pi_smoke.sh; docs/pi.md has a recorded run). Needs root and the
# network; slow under emulation, so not part of `make test`.
PI_SMOKE_CACHE ?= /var/cache/hope-pi-smoke
.PHONY: pi-smoke
pi-smoke:
	PI_SMOKE_CACHE=$(PI_SMOKE_CACHE) nice -n 19 bash bench/pi_smoke.sh

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache node_modules webapp/static/vendor test-artifacts

# The robot's install: runtime + [sim] from the lock of this machine's arch and Python (exact pins,
# sha256 of every file, --no-deps: nothing unpinned), then the project itself without deps. No
# pytest/playwright/fakeredis, no chromium, no npm: the Robot Editor's vendored JS is committed in
# webapp/static/vendor/ (or comes in a wheel from `make dist`: WHEEL=dist/hope_seed_trainer-....whl).
# Its own venv, so the developer .venv is never touched.
#   sudo make install                                    # /opt/hope-trainer/venv
#   make install INSTALL_VENV=/tmp/hope/venv WHEEL=dist/hope_seed_trainer-0.1.0-py3-none-any.whl
INSTALL_VENV ?= /opt/hope-trainer/venv
INSTALL_PYTHON ?= $(PYTHON)
WHEEL ?=
# recursive (=): evaluated only when a target uses it. The Python is the venv's when it exists (a
# venv left from an older OS release keeps its Python), else the one that will create it.
INSTALL_PY_TAG = $(shell p="$(INSTALL_VENV)/bin/python"; [ -x "$$p" ] || p="$(INSTALL_PYTHON)"; \
  "$$p" -c 'import sys; print("py%d%d" % sys.version_info[:2])')
LOCK_TAG = $(if $(filter aarch64 arm64,$(shell uname -m)),pi-aarch64,$(shell uname -m))-$(INSTALL_PY_TAG)
LOCK ?= requirements/$(LOCK_TAG).txt
VENDOR_JS = $(wildcard webapp/static/vendor/*.js)
install: gl-deps
	@test -f "$(LOCK)" || { echo "no lock $(LOCK) for this machine: $$(ls requirements/*.txt)" >&2; exit 1; }
	@test -n "$(WHEEL)$(VENDOR_JS)" || { echo "webapp/static/vendor/ is empty and no WHEEL=: build the wheel" \
	  "on a dev machine (make dist) and pass WHEEL=dist/hope_seed_trainer-*.whl (no JS is built here)" >&2; exit 1; }
	test -x "$(INSTALL_VENV)/bin/python" || $(INSTALL_PYTHON) -m venv "$(INSTALL_VENV)"
	"$(INSTALL_VENV)/bin/python" -m pip install --quiet --require-hashes --no-deps --only-binary=:all: -r "$(LOCK)"
	@# build/ goes first, as for `make dist`: a stale one would carry deleted modules into the install
	$(if $(WHEEL),"$(INSTALL_VENV)/bin/python" -m pip install --quiet --no-deps --force-reinstall "$(WHEEL)",\
	  rm -rf build && "$(INSTALL_VENV)/bin/python" -m pip install --quiet --no-deps --no-build-isolation --force-reinstall .)
	@rm -rf build
	@echo "installed into $(INSTALL_VENV) from $(LOCK): $(INSTALL_VENV)/bin/hope-trainer"

# Rewrites requirements/*.txt from pyproject.toml (uv resolves for the Pi's platforms from here).
lock:
	$(PYTHON) requirements/lock.py
