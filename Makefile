# Two entry points for a fresh machine: `make demo` and `make test` (see README.md).
# Everything a test needs is installed from here; nothing is expected to be on the machine by hand.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# pytest options for `make test`; e.g. make test PYTEST_ARGS="-k rlds"
PYTEST_ARGS ?=

.PHONY: setup test demo bench clean system-deps

setup: $(STAMP)

# The daemon tests start a real redis-server on a loopback port (the production broker).
system-deps:
	@command -v redis-server >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get install -y -q redis-server >/dev/null || \
	    { apt-get update -q >/dev/null && apt-get install -y -q redis-server >/dev/null; }; \
	  else sudo apt-get install -y -q redis-server >/dev/null; fi; }
	@command -v redis-server >/dev/null 2>&1 || { echo "redis-server is needed by the tests: apt-get install redis-server" >&2; exit 1; }

# Plain pip into a venv: uv/poetry would skip the local CPU torch wheel and pull CUDA.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -e '.[dev,sim]'
	@touch $@

test: setup system-deps
	$(PY) -m pytest -q $(PYTEST_ARGS)

demo: setup
	$(PY) run_trainer.py demo

bench: setup
	$(PY) bench/data_pipeline.py

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache
