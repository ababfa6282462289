# Two entry points for a fresh machine: `make demo` and `make test` (see README.md).
# Everything a test needs is installed from here; nothing is expected to be on the machine by hand.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
# pytest options for `make test`; e.g. make test PYTEST_ARGS="-k rlds"
PYTEST_ARGS ?=

.PHONY: setup test demo bench clean

setup: $(STAMP)

# Plain pip into a venv: uv/poetry would skip the local CPU torch wheel and pull CUDA.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet -e '.[dev,sim]'
	@touch $@

test: setup
	$(PY) -m pytest -q $(PYTEST_ARGS)

demo: setup
	$(PY) run_trainer.py demo

bench: setup
	$(PY) bench/data_pipeline.py

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache
