# `make demo` sets up .venv and runs the main job; `make test` runs the fast test suite.
PYTHON ?= python3.12
VENV := .venv
BIN := $(VENV)/bin
export MUJOCO_GL ?= egl

.PHONY: install demo test test-integration test-slow bench lint clean

# uv installs the ~3 GB of torch and CUDA wheels in half of pip's time (88 s against 186 s,
# back to back on a 2-core machine with empty caches). Byte code is compiled at install: where
# PYTHONDONTWRITEBYTECODE is set, nothing would ever cache it, and every process would compile
# torch again on import.
$(BIN)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet "uv==0.13.9"
	$(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e ".[dev]"
	touch $@

install: $(BIN)/.installed

demo: install
	$(BIN)/ccdata generate --suite PnPBoxClose

# One worker per core; a test file stays on one worker (its module fixtures run once).
test: install
	$(BIN)/ruff check . && $(BIN)/ruff format --check .
	$(BIN)/python -m pytest -q -n auto --dist loadfile --durations=20

# The whole runs `make test` leaves out (marked `integration`); CI runs them after it.
test-integration: install
	$(BIN)/python -m pytest -q -n auto --dist loadfile --durations=20 -m integration

test-slow: install
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m slow

bench: install
	@for script in bench/*.py; do echo "== $$script"; $(BIN)/python $$script; done

lint: install
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info
