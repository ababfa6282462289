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

.PHONY: setup test demo bench clean system-deps assets

ASSETS := webapp/static/vendor/.stamp

setup: $(STAMP) $(ASSETS)

# The daemon tests start a real redis-server on a loopback port (the production broker); the browser
# tests drive Debian's chromium (never `playwright install`: no browser downloads); npm installs the
# Robot Editor's JS (socket.io-client, chart.js) from package-lock.json.
APT_DEPS := redis-server:redis-server chromium:chromium npm:npm
GL_DEPS := libegl1 libgl1-mesa-dri
system-deps:
	@for dep in $(APT_DEPS); do cmd=$${dep%%:*}; pkg=$${dep#*:}; \
	  command -v $$cmd >/dev/null 2>&1 && continue; \
	  if [ "$$(id -u)" = 0 ]; then apt-get install -y -q $$pkg >/dev/null || \
	    { apt-get update -q >/dev/null && apt-get install -y -q $$pkg >/dev/null; }; \
	  else sudo apt-get install -y -q $$pkg >/dev/null; fi; \
	  command -v $$cmd >/dev/null 2>&1 || { echo "$$cmd is needed by the tests: apt-get install $$pkg" >&2; exit 1; }; \
	done
	@# MUJOCO_GL=egl (frames for the VQ-VAE and the reflex view) needs the EGL and Mesa drivers.
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

test: setup system-deps
	$(PY) -m pytest -q $(PYTEST_XDIST) --durations=15 $(PYTEST_ARGS)

demo: setup
	$(PY) run_trainer.py demo

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

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache node_modules webapp/static/vendor test-artifacts
