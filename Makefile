# Set-up and everyday commands. `make demo` and `make test` work on a fresh machine: they create
# .venv and install the package with its test extra first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint bench clean

$(STAMP): pyproject.toml requirements-nodeps.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[test]"
	# TrackEval declares opencv-python (GUI build, needs libGL) which would overwrite the headless
	# OpenCV in cv2/; it never imports cv2 for the metrics we use, so install it without deps.
	$(BIN)/pip install --quiet --no-deps -r requirements-nodeps.txt
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(BIN)/uavmm demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadfile

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/uavmm bench

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .mypy_cache
