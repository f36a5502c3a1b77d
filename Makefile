# Two entry points a newcomer needs: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# torch is pinned to the CPU build that lies on this machine's disk; a plain `torch`
# would pull a multi-GB CUDA build. A GPU user installs their own torch first.
TORCH  ?= torch==2.13.0

.PHONY: setup demo test lint bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip 2>&1 | grep -v "^WARNING: Location" || true
	$(BIN)/python -m pip install -q $(TORCH) 2>&1 | grep -v "^WARNING: Location" || true
	$(BIN)/python -m pip install -q -e '.[dev]' 2>&1 | grep -v "^WARNING: Location" || true
	$(BIN)/python -c "import torch, zoo, sdfzoo.cli.main"
	touch $@

setup: $(VENV)/.installed

demo: setup
	$(BIN)/zoo demo

test: setup
	$(BIN)/python -m pytest -q -x --durations=10

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/zoo bench --solvers

clean:
	rm -rf $(VENV) .pytest_cache
