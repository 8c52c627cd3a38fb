# Two entry points for a fresh clone: `make demo` and `make test`.
# Both create .venv with python3 (>= 3.11) and install afmctl into it.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast fuzz bench clean

# First run: say what is happening, show pip's progress, then compile numba's kernels into
# their cache once, with a progress bar (python -m afmctl.kernels), instead of a silent first demo.
$(STAMP): pyproject.toml
	@echo "afmctl: setting up $(VENV): installing afmctl and its dependencies, then compiling its numba kernels (first time only, a few minutes)"
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install --progress-bar on -e ".[test]"
	$(BIN)/python -m afmctl.kernels
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/afmctl demo --out demo-out

test: $(STAMP)
	$(BIN)/python -m pytest -q

# The inner loop: everything but the tests marked `slow` (tests/conftest.py), on two worker
# processes (pytest-xdist): under a minute on 2 cores (docs/ARCHITECTURE.md, "Working on afmctl").
test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow" -n 2

# Long random runs of the property tests (hypothesis's `fuzz` profile, tests/conftest.py): 20x each
# test's examples, failures kept in .hypothesis/examples and replayed first by the next run.
# `make test` uses the derandomised `ci` profile, so it gives the same answer every time.
FUZZ_ARGS ?=
fuzz: $(STAMP)
	@echo "afmctl: fuzzing the property tests (hypothesis profile 'fuzz'; HYPOTHESIS_FUZZ_FACTOR=$${HYPOTHESIS_FUZZ_FACTOR:-20})"
	HYPOTHESIS_PROFILE=fuzz $(BIN)/python -m pytest -q -m hypothesis -p no:cacheprovider $(FUZZ_ARGS) \
	  || { status=$$?; \
	       echo "afmctl fuzz: a property failed. To replay it: rerun 'make fuzz FUZZ_ARGS=\"-k NAME\"' (the failing"; \
	       echo "  example is stored in .hypothesis/examples and tried first), or paste the printed"; \
	       echo "  @reproduce_failure(...) line above the test's @given and run that test with pytest."; \
	       exit $$status; }

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) .venv-nv200 demo-out .pytest_cache
