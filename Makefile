# Entry points (README): `make demo`, `make test` and `make lint`. Each creates/refreshes .venv first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.requirements.stamp

.PHONY: demo test lint venv clean-venv

venv: $(STAMP)

$(STAMP): requirements.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements.txt
	@touch $(STAMP)

# Train the built-in demo capture with the fast preset, score it, render a bullet-time orbit.
demo: $(STAMP)
	$(PY) -m engine demo --out runs/demo

# Every test, the slow ones (marked @pytest.mark.slow) included; `-m "not slow"` skips them.
test: $(STAMP)
	$(PY) -m pytest -q tests

# Style (ruff, configured in pyproject.toml) and the engine's import graph (no cycles, no
# upward arrows between its packages, no bpy, no module over ~500 lines).
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m tools import-graph

clean-venv:
	rm -rf $(VENV)
