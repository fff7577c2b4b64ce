# roslab developer entry points. `make demo` and `make test` are the README's two commands.
VENV ?= .venv
BIN := $(VENV)/bin
PYTHON ?= python3

.PHONY: setup demo demo-down test typecheck unit e2e bench clean

# bash, so that a pipe fails when its first command does (pip's output is filtered below).
SHELL := /bin/bash
.SHELLFLAGS := -o pipefail -c

# The virtualenv is rebuilt when the project's dependencies change. Each step says what it
# does before it starts, and pip names each package as it comes (no silent half minute).
$(VENV)/.installed: pyproject.toml
	@echo "make setup: creating the virtualenv $(VENV) ($(PYTHON) -m venv)"
	$(PYTHON) -m venv $(VENV)
	@echo "make setup: upgrading pip in $(VENV)"
	$(BIN)/pip install --quiet --upgrade pip
	@echo "make setup: installing roslab (editable) and its dependencies: pyinfra, paramiko, PyYAML, jinja2, pytest..."
	@$(BIN)/pip install --progress-bar off -e '.[test]' 2>&1 \
		| grep --line-buffered -E '^(Collecting|Building|Installing|Successfully|ERROR|error)' \
		| sed -u 's/^/    /'
	touch $@

setup: $(VENV)/.installed
	@echo "make setup: checking this machine's tools for the sandbox (scripts/install-host-tools)"
	scripts/install-host-tools
	@# pyinfra's CLI writes no .pyc files (sys.dont_write_bytecode): without these, every run
	@# would compile roslab's modules again, about 0.1 CPU-s per run (bench/noop_rerun.py).
	@echo "make setup: byte-compiling roslab, deploy and inventories (skips what is up to date)"
	$(BIN)/python -m compileall -q roslab deploy inventories > /dev/null

# Boot the sandbox classroom (2 teams, emulated Ubuntu 24.04 and 22.04) and provision it.
demo: setup
	$(BIN)/roslab sandbox up
	$(BIN)/pyinfra -y inventories/sandbox.py deploy.py

demo-down: setup
	@echo "make demo-down: taking the sandbox classroom down (roslab sandbox down)"
	$(BIN)/roslab sandbox down

# The type check of roslab/ and deploy/ ([tool.mypy] in pyproject.toml, docs/testing.md):
# any error fails it, and with it `make test`. Its cache is .mypy_cache (about 1 s warm).
typecheck: $(VENV)/.installed
	@echo "make typecheck: mypy on roslab/ and deploy/"
	$(BIN)/mypy

# Test modules run two at a time (pytest-xdist; tests/conftest.py keeps each module, and every
# module on the session's sandbox, on one worker and sends the longest first): an end-to-end
# module waits on boots and SSH much of its time, and the other uses the cores meanwhile.
# TEST_WORKERS=1 runs them one at a time, in the order collected.
TEST_WORKERS ?= 2
PARALLEL = $(if $(filter 1,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadgroup --no-loadscope-reorder)

# The type check first, then unit and end-to-end tests on sandbox hosts, in one pytest run;
# every module's seconds and the 25 slowest tests are printed at the end and kept in
# test-durations.md (tests/durations.py), so a test that grew slow shows and stays readable.
test: setup typecheck
	ROSLAB_TEST_DURATIONS=$(CURDIR)/test-durations.md $(BIN)/pytest $(PARALLEL) tests/unit tests/e2e

unit: $(VENV)/.installed
	$(BIN)/pytest tests/unit

e2e: setup
	$(BIN)/pytest tests/e2e

bench: setup
	$(BIN)/python bench/noop_rerun.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache
