# The two commands the README shows. Both set the environment up first
# (Debian packages, the venv, torch, fempdl) and are safe to run repeatedly.
# STACK=debian (the default): Debian's DOLFINx 0.5.2 in .venv.
# STACK=pypi: DOLFINx 0.11 from PyPI on the machine's Python 3.12, in .venv-pypi.
STACK ?= debian
ifeq ($(STACK),debian)
VENV ?= .venv
SETUP := tools/setup_env.sh
else ifeq ($(STACK),pypi)
VENV ?= .venv-pypi
SETUP := tools/setup_env_pypi.sh
else
$(error STACK must be debian or pypi, got '$(STACK)')
endif
PYTHON := $(VENV)/bin/python
PYTEST_ARGS ?=

.PHONY: setup run test lint bench clean

setup:
	@bash $(SETUP) $(VENV)

run: setup
	$(VENV)/bin/fempdl run --overwrite

test: setup
	$(PYTHON) -m pytest -q $(PYTEST_ARGS)

# The linter's rules are pyproject.toml's [tool.ruff]; CI runs this before the tests.
lint: setup
	$(VENV)/bin/ruff check .

bench: setup
	$(PYTHON) benchmarks/bench_layer.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
