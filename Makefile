# Two entry points for a fresh machine: `make run` and `make test` (see README).
VENV ?= .venv
PY := $(VENV)/bin/python
ARGS ?=
PYTEST_ARGS ?=
# PyTorch's CPU wheels; on a GPU machine, the CUDA index pytorch.org gives for its driver
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu

.PHONY: setup run test bench mutation

setup: $(VENV)/.installed

# CPU torch first, from TORCH_INDEX: a bare torch requirement would pull a multi-GB CUDA build.
$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0 --index-url $(TORCH_INDEX)
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

run: setup
	$(VENV)/bin/hvc-run $(ARGS)

test: setup
	$(PY) -m pytest $(PYTEST_ARGS)

bench: setup
	$(VENV)/bin/hvc-bench

# Mutation testing (issue 21): mutmut over the paper's maths and the resume path, each group
# against its fast test files; writes docs/results/mutation/. Long (README: Tests); not in CI.
# MUTATION_GROUPS="vtrace retrace" runs some groups (scripts/mutation.py --list names them).
MUTATION_GROUPS ?=
MUTATION_ARGS ?=

$(VENV)/.mutation-installed: $(VENV)/.installed pyproject.toml
	$(PY) -m pip install --quiet -e '.[mutation]'
	touch $@

mutation: $(VENV)/.mutation-installed
	nice -n 19 $(PY) scripts/mutation.py $(MUTATION_ARGS) $(MUTATION_GROUPS)
