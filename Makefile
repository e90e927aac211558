# The two commands the README shows. Both set the environment up first
# (Debian packages, the venv, torch, fempdl) and are safe to run repeatedly.
VENV ?= .venv
PYTHON := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: setup run test bench clean

setup:
	@bash scripts/setup_env.sh $(VENV)

run: setup
	$(VENV)/bin/fempdl run --overwrite

test: setup
	$(PYTHON) -m pytest -q $(PYTEST_ARGS)

bench: setup
	$(PYTHON) scripts/bench_layer.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
