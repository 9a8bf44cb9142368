# diffsolids: two commands do everything on a fresh machine.
#   make demo   create .venv when missing, install, run the flagship demo (the paper's 3D bunny
#               throw on its data, ~6-8 min on 2 cores; `make demo-2d`: the 2D throw, ~20 s)
#   make test   same setup, then ruff, the serial tests and the MPI tests (2 ranks)
#   make docs   the HTML documentation in docs/_build/html (Sphinx, fails on any warning)
# PYTHON=/path/to/python3.12 overrides the interpreter used to create the venv.

VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.diffsolids-installed
NPROC ?= 2
DEMO_ARGS ?=
export PYTHON

.PHONY: setup demo demo-2d demos docs test test-serial test-mpi lint bench clean

$(STAMP): pyproject.toml
	@set -e; \
	if [ ! -x "$(PY)" ]; then \
	  interp=$$(.ci/find-python); \
	  echo "creating $(VENV) with $$interp"; \
	  "$$interp" -m venv "$(VENV)"; \
	fi
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dolfinx,test,docs]"
	$(PY) -m diffsolids_mpi_first --install
	@touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(PY) demos/paper_throw_bunnies.py --check $(DEMO_ARGS)

demo-2d: $(STAMP)
	$(PY) demos/throw.py

demos: $(STAMP)
	$(PY) demos/run_all.py

docs: $(STAMP)
	$(VENV)/bin/sphinx-build -W --keep-going -q -b html docs docs/_build/html
	@echo "open docs/_build/html/index.html"

lint: $(STAMP)
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports --no-cache

test-serial: $(STAMP)
	$(PY) -m pytest -n $(NPROC) --dist loadfile --max-worker-restart 0 tests

# tests/mpi in three processes: objects of finished test modules stay alive in the process
# (test caches, references held on the PETSc side) with their communicator duplicates, and one
# process running every file reached MPICH's 2048 communicators per rank (MPI_Comm_dup aborts).
MPI_GROUPS := a-c d-g h-z

test-mpi: $(STAMP)
	@set -e; for g in $(MPI_GROUPS); do \
	  echo "== tests/mpi/test_[$$g]*.py"; \
	  $(VENV)/bin/mpiexec -n 2 $(PY) -m pytest -p no:cacheprovider tests/mpi/test_[$$g]*.py; \
	done

test: lint test-serial test-mpi

bench: $(STAMP)
	@set -e; for f in tests/benchmarks/bench_*.py; do echo "== $$f"; $(PY) $$f; done

clean:
	rm -rf output .pytest_cache build src/*.egg-info docs/_build docs/api
