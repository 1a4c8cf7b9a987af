# `make demo` runs the whole pipeline on the built-in synthetic dive; `make test` runs the tests.
# Both create or update the local virtual environment .venv from the pinned requirements first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CORES ?= 2

.PHONY: demo test test-fast report install clean-results

install: $(STAMP)

$(STAMP): pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --constraint requirements.lock --editable '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES)
	PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/snakemake --cores $(CORES) --report report.html
	@echo "Report: results/report/summary.html and report.html"

# The tests run in $(CORES) processes, a test file to a process (its module fixtures run once),
# the files in the order tests/conftest.py puts them (slow first): most tests leave a core idle,
# and the SLURM test mostly waits on the queue.
PYTEST := PATH="$(CURDIR)/$(BIN):$$PATH" $(BIN)/python -m pytest -n $(CORES) --dist loadfile \
	--no-loadscope-reorder

test: $(STAMP)
	$(PYTEST)

test-fast: $(STAMP)
	$(PYTEST) -m "not slow"

clean-results:
	rm -rf results/*/ logs .snakemake report.html
