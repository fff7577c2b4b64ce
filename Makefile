# roslab developer entry points. `make demo` and `make test` are the README's two commands.
VENV ?= .venv
BIN := $(VENV)/bin
PYTHON ?= python3

.PHONY: setup demo demo-down test unit e2e bench clean

# The virtualenv is rebuilt when the project's dependencies change.
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

setup: $(VENV)/.installed
	scripts/install-host-tools

# Boot the sandbox classroom (2 teams, emulated Ubuntu 24.04 and 22.04) and provision it.
demo: setup
	$(BIN)/roslab sandbox up
	$(BIN)/pyinfra -y inventories/sandbox.py deploy.py

demo-down: setup
	$(BIN)/roslab sandbox down

# Unit tests first (seconds), then end-to-end tests on sandbox hosts, in one pytest run;
# the 25 slowest are listed at the end, so a test that grew slow shows in CI's log.
test: setup
	$(BIN)/pytest --durations=25 tests/unit tests/e2e

unit: $(VENV)/.installed
	$(BIN)/pytest tests/unit

e2e: setup
	$(BIN)/pytest tests/e2e

bench: setup
	$(BIN)/python bench/noop_rerun.py

clean:
	rm -rf $(VENV) .pytest_cache
