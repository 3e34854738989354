# `make demo` and `make test` work on a machine that has only python3 (>= 3.11) and make:
# each creates .venv and installs what it needs on first use.
#   make demo              the interactive viewer on the default liver (Ctrl-C stops it)
#   make demo HEADLESS=1   the scripted session instead (static poke, modal dynamics, 1 kHz loop)
#   make test              the whole suite (the browser test needs Debian's chromium: see README)
#   make pictures          the README's pictures, into docs/img
#   make docs              the manual (Sphinx), warnings as errors, into docs/_build/html
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
PORT   ?= 8080
HEADLESS ?=

.PHONY: demo test bench pictures docs clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info < (3, 11))' || \
	  { echo "rtfem needs Python >= 3.11; found $$($(PYTHON) --version 2>&1). Set PYTHON=python3.11 (or newer)."; exit 1; }
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV) || \
	  { rm -rf $(VENV); echo "could not create a virtual environment: on Debian/Ubuntu run 'apt-get install python3-venv'"; exit 1; }
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --upgrade pip
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e ".[viewer,plots,video,test,fast,mesh,docs,igtl,cluster,segmentation]"
	@touch $(STAMP)

ifeq ($(HEADLESS),)
demo: $(STAMP)
	@echo "rtfem: starting the viewer on the default liver; open the address below in a browser."
	@echo "rtfem: press Ctrl-C here to stop it (make demo HEADLESS=1 runs the scripted session instead)."
	$(BIN)/rtfem view --port $(PORT)
else
demo: $(STAMP)
	$(BIN)/python -m rtfem.cli.demo
endif

test: $(STAMP)
	$(BIN)/python -m pytest

docs: $(STAMP)
	$(BIN)/python -m sphinx -W --keep-going -q -b html docs docs/_build/html
	@echo "rtfem: the manual is in docs/_build/html/index.html"

pictures: $(STAMP)
	$(BIN)/rtfem pictures --out docs/img

# all benchmark tables (about an hour with the 40,962-vertex liver; BENCH_LEVELS="4 5" is quicker)
BENCH_LEVELS ?= 4 5 6
bench: $(STAMP)
	$(BIN)/python benchmarks/assembly.py --levels $(BENCH_LEVELS)
	$(BIN)/python benchmarks/eigen.py --levels $(BENCH_LEVELS)
	$(BIN)/python benchmarks/dynamics.py --levels $(BENCH_LEVELS)
	$(BIN)/python benchmarks/sldm.py --levels $(BENCH_LEVELS)
	$(BIN)/python benchmarks/haptics.py --levels $(BENCH_LEVELS)
	$(BIN)/python benchmarks/haptic_step.py
	$(BIN)/python benchmarks/haptic_loop.py
	$(BIN)/python benchmarks/solid.py --organs
	$(BIN)/python benchmarks/large_deformation.py
	$(BIN)/python benchmarks/contact.py

clean:
	rm -rf $(VENV) out .pytest_cache test-artifacts
