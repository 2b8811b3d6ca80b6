# pixmuscle — the two commands of the README (make demo, make test) set up what they need themselves.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.pixmuscle-installed
DEMO_STAMP := $(VENV)/.pixmuscle-demo

.PHONY: venv demo test bench bench-scale examples examples-small docs-tables lint clean

# `make demo` installs what the demo needs (pixmuscle and the interactive 3-D view: about a minute on a
# fresh machine); `make test` adds everything the tests use: the test and dev tools, MKL PARDISO, dipy,
# the scanner-data readers (pydicom, dcm2niix, pynrrd, SimpleITK),
# the optional PETSc/MPI backend (.ci/install-petsc: Debian/Ubuntu as root, else it says why not) and
# headless Chromium for the report's browser test (.ci/install-browser, same rule). Both redo their
# install when pyproject.toml changes.
$(DEMO_STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[view]"
	touch $(DEMO_STAMP)

$(STAMP): $(DEMO_STAMP)
	$(BIN)/python -m pip install --quiet -e ".[view,test,dev,fast,dwi,scanner]"
	.ci/install-petsc $(BIN)/python
	.ci/install-browser
	touch $(STAMP)

venv: $(STAMP)

demo: $(DEMO_STAMP)
	$(BIN)/pixmuscle run configs/demo.yaml

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

# the solver-scale records (locking, accuracy and time against voxel FE, Newton, Krylov iterations against
# K/mu, patch-pressure stability and forces, the multigrids, the sweeps at the defaults up to 295k), then the
# time estimate's fit against them and the docs' tables; hours, not minutes
bench-scale: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[bench]"
	$(BIN)/python benchmarks/bench_locking.py
	$(BIN)/python benchmarks/bench_vs_fe.py
	$(BIN)/python benchmarks/bench_vs_fe.py --append --cases leg5k:pixmuscle leg5k:felupe:1x1x1 leg5k:felupe:1x1x2 leg5k:felupe:2x2x2 --threads 1
	$(BIN)/python benchmarks/bench_newton.py
	$(BIN)/python benchmarks/bench_solve.py --conditioning 2k
	$(BIN)/python benchmarks/bench_solve.py --conditioning 5k
	$(BIN)/python benchmarks/bench_solve.py --conditioning 1.5k --variants projected:1,1,3:cg_amg projected:2,2,3:mixed_amg projected:2,2,3:mixed_amg:patch nodal:cg_amg
	for s in 1.5k 5k; do for p in "1,1,3 --held pressure" "2,2,3 --held pressure" "2,2,3 --held displacement" "2,2,3 --held patch"; do 	  $(BIN)/python benchmarks/bench_solve.py --infsup $$s --patch $$p || exit 1; done; done
	$(BIN)/python benchmarks/bench_solve.py --infsup 10k --patch 2,2,3 --held displacement --thresholds 0.01 0.05
	$(BIN)/python benchmarks/bench_solve.py --infsup 20k --patch 2,2,3 --held patch
	$(BIN)/python benchmarks/bench_solve.py --conditioning 5k --append --variants projected:2,2,3:mixed_amg:own
	$(BIN)/python benchmarks/bench_solve.py --conditioning 20k --append --variants projected:2,2,3:mixed_amg:own
	$(BIN)/python benchmarks/bench_solve.py --conditioning 75k --append --variants projected:2,2,3:mixed_amg:own --scales 1
	$(BIN)/python benchmarks/bench_solve.py --inertia 5k
	$(BIN)/python benchmarks/bench_solve.py --inertia 20k
	$(BIN)/python benchmarks/bench_tolerance.py --size 5k --tols 1e-6 1e-4 1e-4:1e-5 1e-4:1e-4 1e-3 1e-2
	$(BIN)/python benchmarks/bench_tolerance.py --size 20k --tols 1e-4
	$(BIN)/python benchmarks/bench_petsc_mixed.py
	$(BIN)/python benchmarks/bench_patch.py
	for s in 5k 20k 75k; do for a in pyamg hypre; do $(BIN)/python benchmarks/bench_solve.py --multigrid $$s --amg $$a || exit 1; done; done
	$(BIN)/python benchmarks/bench_solve.py --append --cases 5k:auto 5k:mixed_amg 20k:auto 75k:auto
	for s in 20k-fine 75k-fine 295k; do $(BIN)/python benchmarks/bench_solve.py --conditioning $$s --append --variants projected:2,2,3:mixed_amg:own --scales 1 || exit 1; done
	$(BIN)/python benchmarks/bench_solve.py --append --cases 295k:auto --checkpoint .bench-checkpoints
	$(BIN)/python benchmarks/bench_solve.py --append --cases 295k:auto_1p --checkpoint .bench-checkpoints
	$(BIN)/python benchmarks/bench_solve.py --append --cases 75k:auto_1p 20k:auto_2p
	$(BIN)/python benchmarks/bench_solve.py --append --cases 295k:auto_rebuild100 --checkpoint .bench-checkpoints
	$(BIN)/python benchmarks/bench_solve.py --probe-direct 75k
	$(BIN)/python benchmarks/bench_memory.py 75k
	$(BIN)/python benchmarks/bench_backends.py
	$(BIN)/python benchmarks/bench_scaling.py --solve-record --cases 37k:1 75k:2 295k:2 150k:4
	$(BIN)/python benchmarks/bench_scaling.py --model
	$(BIN)/python benchmarks/fit_time_estimate.py
	$(BIN)/python benchmarks/docs_tables.py

# the paper's Examples 3 and 2 at the paper's resolution, each timed stage by stage (wall time, peak memory,
# load average; per model nodes, Newton iterations, F_max: benchmarks/results/bench_examples.json) and the
# figures of docs/examples.md drawn from its results; hours on 2 cores (Example 2: coarse and fine model).
# A run made by hand is recorded with `benchmarks/bench_examples.py EXAMPLE --from-run DIR` (no solve).
examples: $(STAMP)
	$(BIN)/python benchmarks/bench_examples.py uncertainty
	$(BIN)/python benchmarks/bench_examples.py mg_young_old
	$(BIN)/python benchmarks/fig_examples.py mg_young_old
	$(BIN)/python benchmarks/bench_examples.py lower_leg
	$(BIN)/python benchmarks/fig_examples.py lower_leg

# the same for the small variants (minutes); their Example 2 figures go to out/lower_leg_small/figures
examples-small: $(STAMP)
	$(BIN)/python benchmarks/bench_examples.py mg_young_old_small
	$(BIN)/python benchmarks/bench_examples.py lower_leg_small
	$(BIN)/python benchmarks/fig_examples.py lower_leg_small --out-dir out/lower_leg_small/figures

# the README's two commands on a fresh clone of HEAD, timed with their installs (benchmarks/results/bench_make.json)
bench-make:
	$(PYTHON) benchmarks/bench_make.py

# the tables of measured figures in README.md and docs/*.md, rewritten from benchmarks/results/*.json
# (the blocks between <!-- records:NAME --> and <!-- /records:NAME -->; no solve, seconds)
docs-tables: $(STAMP)
	$(BIN)/python benchmarks/docs_tables.py

lint: $(STAMP)
	$(BIN)/ruff check pixmuscle tests benchmarks

clean:
	rm -rf out .pytest_cache build *.egg-info
