"""What every benchmark record carries (benchmarks/_record.py), and the records' state: the solve-time
estimate is the fit to today's default sweeps, and no default row older than the defaults is unmarked."""

import importlib.util
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module(name):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_record_carries_every_field():
    record = _module("_record")
    fields = record.Run(defaults=True, command="x").fields()
    assert set(fields) == {"command", "commit", "utc", "machine", "load_average", "defaults", "peak_rss_GB"}
    assert fields["command"] == "x" and fields["defaults"] is True and fields["peak_rss_GB"] > 0
    assert set(fields["load_average"]) == {"before", "after"} and len(fields["load_average"]["before"]) == 3
    assert "cpus" in fields["machine"] and "memory_GB" in fields["machine"]
    assert fields["utc"].endswith("+00:00")


_TREE = """
import os, sys, time
import numpy as np
held = np.ones(300 * 2**20 // 8)                 # 300 MiB in the child, touched
pid = os.fork()
if pid == 0:
    if sys.argv[1] == "own":
        mine = np.ones(200 * 2**20 // 8)         # 200 MiB more in the grandchild
    time.sleep(1.5)                              # "shared": only the child's pages, shared after the fork
    os._exit(0)
os.waitpid(pid, 0)
sys.exit(3)
"""


def test_a_child_tree_is_measured_with_its_descendants_and_shared_pages_once():
    """The child of a large process is measured as itself (``ru_maxrss`` would report the parent's
    size, which the fork copied until ``exec``), with its descendants, and a fork's shared pages once."""
    import numpy as np

    record = _module("_record")
    large = np.ones(600 * 2**20 // 8)  # this process is large when it starts the child
    code, usage, own = record.run_child(["-c", _TREE, "own"])
    del large
    assert code == 3 and usage.ru_maxrss > 0
    assert 0.48 < own / 2**20 < 0.75  # 300 + 200 MiB (+ numpy's import in both) and no more
    code, _, shared = record.run_child(["-c", _TREE, "shared"])
    assert code == 3
    assert 0.29 < shared / 2**20 < 0.45  # the forked pages are counted once, not twice


def test_the_estimate_is_the_fit_to_todays_default_sweeps():
    fit = _module("fit_time_estimate")
    from pixmuscle.preflight import NODES_REF, SETUP_SECONDS, STEP_SECONDS

    rows = fit.current_default_sweeps()
    assert len(rows) >= 3 and not any(r.get("superseded") for r in rows)
    assert fit.fit(rows, NODES_REF) == tuple(STEP_SECONDS)
    assert fit.fit_setup(rows, NODES_REF) == tuple(SETUP_SECONDS)


def test_default_rows_made_before_the_last_change_are_marked():
    record = _module("_record")
    last = record.DEFAULTS_CHANGES[-1][1]
    cases = json.loads((ROOT / "benchmarks" / "results" / "bench_solve.json").read_text())["cases"]
    for c in cases:
        if c.get("utc") and c["utc"] < last:
            assert c.get("superseded"), c.get("case")
