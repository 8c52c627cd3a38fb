# Two entry points for a fresh clone: `make demo` and `make test`.
# Both create .venv with python3 (>= 3.11) and install afmctl into it, editable:
# `make demo` with its runtime dependencies only, `make test` adds the `test` extra (pytest,
# hypothesis, playwright, mypy, the vendors' client libraries, Gwyddion's converter) on top.
# Two stamps, so a demo environment never receives the test tools.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
RUNTIME_STAMP := $(VENV)/.installed-runtime
TEST_STAMP := $(VENV)/.installed-test

# setuptools prints one notice with every editable install whose packages come from several
# folders (package-dir maps drivers/, compensators/, sim_backend/ into afmctl): "Editable
# installation ... folders in your working directory with the same name as your package may
# take precedence during imports". The only such folder is afmctl/ itself, the package's own
# source, so the notice is filtered; every other setuptools warning still shows.
PIP := PYTHONWARNINGS="ignore:Editable installation:UserWarning" $(BIN)/python -m pip

.PHONY: demo test test-fast typecheck fuzz bench clean

# First run: say what is happening, show pip's progress, then compile numba's kernels into
# their cache once, with a progress bar (python -m afmctl.kernels), instead of a silent first demo.
$(RUNTIME_STAMP): pyproject.toml
	@echo "afmctl: setting up $(VENV): installing afmctl and its dependencies, then compiling its numba kernels (first time only, a few minutes)"
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(PIP) install --progress-bar on -e .
	$(BIN)/python -m afmctl.kernels
	touch $(RUNTIME_STAMP)

$(TEST_STAMP): $(RUNTIME_STAMP)
	@echo "afmctl: adding the test tools to $(VENV)"
	$(PIP) install --progress-bar on -e ".[test]"
	touch $(TEST_STAMP)

demo: $(RUNTIME_STAMP)
	$(BIN)/afmctl demo --out demo-out

# mypy first (tools/typecheck.py: the whole package as it installs, zero errors), then pytest on
# two worker processes (pytest-xdist): the suite is half numerics, half waiting on wall-clock
# devices, so two workers share 2 cores well (7 min vs 11.5 min in one process, measured on a
# quiet 2-core machine; docs/ARCHITECTURE.md "Working on afmctl"). A file's tests stay on one worker
# (--dist loadfile: module fixtures built once; the longest files start first, tests/conftest.py).
# One BLAS thread per worker: two workers with two OpenBLAS threads each oversubscribed the 2 cores
# (the unseen-plant and image-dynamics fixtures side by side: 71 s with, 47 s without).
# For the same reason afmctl calibrate fits in one process here (AFMCTL_FIT_JOBS=1; two by
# default): tests/test_fit_pool.py and tests/test_identify_worker.py ask for two themselves.
# PYTEST_WORKERS=0: one process.
PYTEST_WORKERS ?= 2
test: $(TEST_STAMP)
	$(BIN)/python tools/typecheck.py
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 AFMCTL_FIT_JOBS=1 $(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --dist loadfile

typecheck: $(TEST_STAMP)
	$(BIN)/python tools/typecheck.py

# The inner loop: everything but the tests marked `slow` (tests/conftest.py), on two worker
# processes (pytest-xdist): under a minute on 2 cores (docs/ARCHITECTURE.md, "Working on afmctl").
test-fast: $(TEST_STAMP)
	$(BIN)/python -m pytest -q -m "not slow" -n 2

# Long random runs of the property tests (hypothesis's `fuzz` profile, tests/conftest.py): 20x each
# test's examples, failures kept in .hypothesis/examples and replayed first by the next run.
# `make test` uses the derandomised `ci` profile, so it gives the same answer every time.
FUZZ_ARGS ?=
fuzz: $(TEST_STAMP)
	@echo "afmctl: fuzzing the property tests (hypothesis profile 'fuzz'; HYPOTHESIS_FUZZ_FACTOR=$${HYPOTHESIS_FUZZ_FACTOR:-20})"
	HYPOTHESIS_PROFILE=fuzz $(BIN)/python -m pytest -q -m hypothesis -p no:cacheprovider $(FUZZ_ARGS) \
	  || { status=$$?; \
	       echo "afmctl fuzz: a property failed. To replay it: rerun 'make fuzz FUZZ_ARGS=\"-k NAME\"' (the failing"; \
	       echo "  example is stored in .hypothesis/examples and tried first), or paste the printed"; \
	       echo "  @reproduce_failure(...) line above the test's @given and run that test with pytest."; \
	       exit $$status; }

bench: $(TEST_STAMP)
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) .venv-nv200 demo-out .pytest_cache
