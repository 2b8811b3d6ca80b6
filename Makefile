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

# the solver-scale records (locking, accuracy and time against voxel FE, Newton, Krylov iterations against
# K/mu, patch-pressure stability and forces, the 74k sweep at the default tolerances); hours, not minutes
bench-scale: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/python benchmarks/bench_locking.py
	$(BIN)/python benchmarks/bench_vs_fe.py
	$(BIN)/python benchmarks/bench_newton.py
	$(BIN)/python benchmarks/bench_solve.py --conditioning 2k
	$(BIN)/python benchmarks/bench_solve.py --conditioning 5k
	$(BIN)/python benchmarks/bench_solve.py --conditioning 1.5k --variants projected:1,1,3:cg_amg projected:2,2,3:mixed_amg nodal:cg_amg
	for s in 1.5k 5k; do for p in "1,1,3 --held pressure" "2,2,3 --held pressure" "2,2,3 --held displacement"; do 	  $(BIN)/python benchmarks/bench_solve.py --infsup $$s --patch $$p || exit 1; done; done
	$(BIN)/python benchmarks/bench_solve.py --infsup 10k --patch 2,2,3 --held displacement --thresholds 0.01 0.05
	$(BIN)/python benchmarks/bench_patch.py
	$(BIN)/python benchmarks/bench_solve.py --append --cases 75k:cg_amg

lint: $(STAMP)
	$(BIN)/ruff check pixmuscle tests benchmarks

clean:
	rm -rf out .pytest_cache build *.egg-info
