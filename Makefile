# Two commands on a fresh machine with Python 3.11 and make:
#   make serve   create .venv if missing, install the serving extra, serve the shipped policies
#                (holds its terminal; make serve PORT=8001, PUSHT_MODELS_DIR=runs/served make serve)
#   make test    create .venv if missing, install everything, run the test suite on every core (xdist)
#   make test-all  the same with the slow end-to-end tests too (what CI runs, with make lint)
#   make lint    ruff check and ruff format --check (configured in pyproject.toml)
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
HOST ?= 127.0.0.1
PORT ?= 8000

.PHONY: serve test test-all lint bench clean

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip

$(VENV)/.serve-installed: pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install --quiet -e ".[serve,client]"
	touch $@

$(VENV)/.test-installed: pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install --quiet -e ".[test]"
	touch $@ $(VENV)/.serve-installed

serve: $(VENV)/.serve-installed
	@echo "serving $${PUSHT_MODELS_DIR:-models} on http://$(HOST):$(PORT) until Ctrl-C; talk to it from another terminal"
	$(PY) -m service --host $(HOST) --port $(PORT)

test: $(VENV)/.test-installed
	$(PY) -m pytest -q -n auto -m "not slow"

test-all: $(VENV)/.test-installed
	$(PY) -m pytest -q -n auto

lint: $(VENV)/.test-installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

bench: $(VENV)/.test-installed
	$(PY) bench/env_speed.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
