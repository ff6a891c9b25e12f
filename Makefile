# Two entry points: `make demo` and `make test`. Each creates .venv if missing.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP_RUN := $(VENV)/.stamp-run
STAMP_TEST := $(VENV)/.stamp-test
# test processes (pytest-xdist): the suite is mostly XLA compiles, which use one core each
TEST_WORKERS ?= 2

.PHONY: demo test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# every dependency at the version in requirements.lock (pip constraints), the project itself editable
$(STAMP_RUN): pyproject.toml requirements.lock | $(BIN)/python
	$(BIN)/python -m pip install -q -c requirements.lock -e .
	touch $@

$(STAMP_TEST): pyproject.toml requirements.lock | $(BIN)/python
	$(BIN)/python -m pip install -q -c requirements.lock -e '.[test]'
	touch $@ $(STAMP_RUN)

# The whole pipeline on a smaller synthetic scene (a smoke run of a few minutes); `fgjax demo`
# without --quick runs it at full size.
demo: $(STAMP_RUN)
	$(BIN)/fgjax demo --quick --overwrite

test: $(STAMP_TEST)
	$(BIN)/python -m ruff check -q fgjax tests
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS)

bench: $(STAMP_RUN)
	$(BIN)/fgjax bench raster

clean:
	rm -rf $(VENV) outputs .cache
