# pixmuscle — the two commands of the README (make demo, make test) set everything up themselves.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.pixmuscle-installed

.PHONY: venv demo test bench bench-scale lint clean

# (re)create the virtual environment and install pixmuscle with its extras when pyproject changes;
# .ci/install-petsc adds the optional PETSc/MPI backend where it can (Debian/Ubuntu as root) and says why not elsewhere
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,dev,fast,dwi]"
	.ci/install-petsc $(BIN)/python
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/pixmuscle run configs/demo.yaml

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

# the solver-scale records (issue 12's targets: locking, accuracy and time against voxel FE, Newton,
# Krylov iterations against K/mu, the 74k sweep at the default tolerances); hours, not minutes
bench-scale: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/python benchmarks/bench_locking.py
	$(BIN)/python benchmarks/bench_vs_fe.py
	$(BIN)/python benchmarks/bench_newton.py
	$(BIN)/python benchmarks/bench_solve.py --conditioning 2k
	$(BIN)/python benchmarks/bench_solve.py --conditioning 5k
	$(BIN)/python benchmarks/bench_solve.py --infsup 1.5k
	$(BIN)/python benchmarks/bench_solve.py --append --cases 75k:cg_amg

lint: $(STAMP)
	$(BIN)/ruff check pixmuscle tests benchmarks

clean:
	rm -rf out .pytest_cache build *.egg-info
