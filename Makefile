# Fresh machine: `make demo` runs the main job (the evaluation report), `make test` the test suite. Both build .venv first.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo example test venv clean

venv: $(STAMP)

# torch first, pinned to the CPU wheel: a bare `torch` requirement would pull GBs of CUDA packages.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m evaluate.report

example: $(STAMP)
	$(BIN)/python -m deepcharuco.detect deepcharuco/examples/board_320x240.png \
		--camera deepcharuco/examples/webcam_320x240.yaml --out demo_out

# DEEPCHARUCO_REQUIRE_ALL=1: a test that would skip for a dependency the dev extra installs (bpy, numba, ...) fails
# instead (tests/conftest.py); -ra lists every skip, and the summary line counts them. -n auto: one pytest-xdist
# worker per core (the tests use their own temporary folders; most of a test's time is one core's).
test: $(STAMP)
	DEEPCHARUCO_REQUIRE_ALL=1 $(BIN)/python -m pytest -q -ra -n auto

clean:
	rm -rf $(VENV) demo_out detect_out report .pytest_cache
