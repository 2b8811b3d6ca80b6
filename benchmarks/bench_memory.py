"""Where the memory of a solve goes: the first Newton system of the SYNTHETIC leg at the shipped defaults,
phase by phase and owner by owner, each size in a process of its own.

Phases, in the order a solve runs them: the model (labels → nodes), the system (RK shape functions, SCNI
and stabilisation operators, penalty, pressure patches: ``build_system``, its freed heap pages then given
back as the solve does), the first state (deformation,
stress and material moduli at α = 0.095), the linear solver's set-up (the multigrid stand-in, BoomerAMG,
region factors, the Schur probe: ``prepare``) and one mixed solve (its Krylov vectors). For each phase:
the resident memory after it and its own peak (the kernel's high-water mark, reset before the phase through
``/proc/self/clear_refs``), both of this process; and the BoomerAMG worker processes' peaks.

Owners: after the solve, every numpy array and sparse matrix reachable from the model, the system, the
state and the solver is counted once (the first owner reached keeps a shared array), under the attribute
path that holds it (``system.scni.G`` …). Memory that numpy does not own — MKL PARDISO's factors, hypre's
hierarchy, Python objects, the allocator's free pages — is the difference between the resident memory and
the owners' sum (``not_numpy_GB``); of it, what PARDISO reports holding for the region factors (its
analysis, factors and solve work space, and its peak, iparm[14..16]) is listed per region
(``region_factors_pardiso``).

Run: ``python benchmarks/bench_memory.py 75k 295k``; writes ``benchmarks/results/bench_memory.json`` (one
row per size, GB per phase and per owner; a size measured again replaces its row, which ``--keep-before``
adds to the record's ``before`` list, the size's history, for a before/after comparison). A smaller leg
(``5k``, ``10k``, ``20k``: the sizes of :mod:`bench_solve`) measures the same owners in under a minute;
``--out PATH`` writes such a trial elsewhere and ``--depth`` lists the owners deeper down their paths
(``solver._M.regions.parts[0].asm.g`` at depth 6).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
from pathlib import Path

import numpy as np
import scipy.sparse as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run, status_kb  # noqa: E402
from bench_solve import SIZES, leg_case  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "bench_memory.json"
GB = 1024.0**3


def _reset_peak() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")       # resets VmHWM (Linux ≥ 4.0)
    except OSError:
        pass


def _root(a: np.ndarray) -> np.ndarray:
    """The array that owns ``a``'s memory (``a`` itself unless it is a view of another array)."""
    while isinstance(a.base, np.ndarray):
        a = a.base
    return a


def _nbytes(x, seen: set) -> int:
    """Bytes of an array or sparse matrix not counted yet (views and shared buffers once, by their owner)."""
    if isinstance(x, np.ndarray):
        arrays = [x]
    elif sp.issparse(x):
        arrays = [getattr(x, a) for a in ("data", "indices", "indptr", "row", "col", "offsets")
                  if isinstance(getattr(x, a, None), np.ndarray)]
    else:
        return 0
    total = 0
    for a in arrays:
        r = _root(a)
        if id(r) not in seen:
            seen.add(id(r))
            total += r.nbytes
    return total


def owners(roots: dict, depth: int = 4) -> dict[str, int]:
    """Bytes of the arrays reachable from ``roots`` (name → object), by attribute path, each array once."""
    seen: set[int] = set()
    out: dict[str, int] = {}

    def walk(obj, path: str, level: int) -> int:
        if id(obj) in seen or obj is None or isinstance(obj, (str, bytes, int, float, bool, type, types.ModuleType,
                                                             types.FunctionType)):
            return 0
        if isinstance(obj, np.ndarray) or sp.issparse(obj):
            return _nbytes(obj, seen)
        seen.add(id(obj))
        if isinstance(obj, dict):
            items = list(obj.items())
        elif isinstance(obj, (list, tuple, set, frozenset)):
            items = list(enumerate(obj))
        elif hasattr(obj, "__dict__") or hasattr(obj, "__slots__"):
            names = list(getattr(obj, "__dict__", {}))
            names += [s for s in getattr(type(obj), "__slots__", ()) if isinstance(s, str) and hasattr(obj, s)]
            items = [(n, getattr(obj, n, None)) for n in names]
        else:
            return 0
        total = 0
        for key, child in items:
            sub = f"{path}.{key}" if not isinstance(key, int) else f"{path}[{key}]"
            b = walk(child, sub, level + 1)
            if b and level < depth:
                out[sub] = out.get(sub, 0) + b
            total += b
        return total

    for name, obj in roots.items():
        out[name] = walk(obj, name, 1)
    return out


def measure(size: str, depth: int = 4) -> dict:
    from pixmuscle.mechanics.heap import release_free_heap
    from pixmuscle.mechanics.linsolve import make_solver
    from pixmuscle.mechanics.linsolve.amg_processes import workers_peak_rss_kb
    from pixmuscle.mechanics.solve import build_system

    def build(model, cfg):  # as the solve builds it: the build's freed heap pages go back to the system
        out = build_system(model, cfg)
        release_free_heap()
        return out

    run = Run(defaults=True)
    phases = []

    def phase(name, fn):
        _reset_peak()
        t = time.perf_counter()
        out = fn()
        phases.append({"phase": name, "wall_s": round(time.perf_counter() - t, 1),
                       "rss_after_GB": round(status_kb("self", "VmRSS") / 1024**2, 3),
                       "peak_GB": round(status_kb("self", "VmHWM") / 1024**2, 3)})
        print(json.dumps({"size": size, **phases[-1]}), flush=True)
        return out

    model, cfg = phase("model", lambda: leg_case(size, None))
    system, _ = phase("system", lambda: build(model, cfg))
    state = phase("first state", lambda: system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095))
    width = 2 * np.floor(np.asarray(cfg.support.a_over_h) + 0.5).astype(int)
    solver = make_solver(cfg.solver, model.X, ijk=model.ijk, width=width)
    phase("solver set-up", lambda: solver.prepare(system, state))
    if hasattr(solver, "solve_mixed") and getattr(solver, "_mixed", None) is not None:
        phase("mixed solve", lambda: solver.solve_mixed(state.r.ravel(), np.zeros(system.volumetric.n_patches)))
    else:
        phase("solve", lambda: solver.solve(state.r.ravel()))
    iterations = int(solver.info["iterations"])
    by_owner = owners({"model": model, "system": system, "state": state, "solver": solver}, depth=depth)
    rss = status_kb("self", "VmRSS") * 1024.0
    top = {k: v for k, v in by_owner.items() if "." not in k and "[" not in k}
    floor = min(0.01 * GB, 0.002 * sum(top.values()))  # 10 MB, or 0.2 % of the owners on a small leg
    detail = {k: round(v / GB, 4) for k, v in sorted(by_owner.items(), key=lambda kv: -kv[1]) if v >= floor}
    workers = [kb / 1024**2 for kb in workers_peak_rss_kb()]
    regions = getattr(solver, "_regions", None)  # PARDISO's own memory of the region factors (MKL, not numpy)
    parts = [] if regions is None else [p.factor.info for p in regions.parts]
    pardiso = {"region_nodes": [int(p.nodes.size) for p in ([] if regions is None else regions.parts)],
               "held_GB": [round(i.get("memory_kB", 0) / 1024**2, 3) for i in parts],
               "peak_GB": [round(i.get("peak_memory_kB", 0) / 1024**2, 3) for i in parts],
               "factor_nnz": [int(i.get("factor_nnz", 0)) for i in parts]}
    dofs = 3 * model.n_nodes
    peak = max(p["peak_GB"] for p in phases)
    return {"size": size, "nodes": int(model.n_nodes), "displacement_dofs": dofs, "pixel_cm": list(SIZES[size][2:] or [None])[0],
            "backend": solver.name, "krylov_iterations": iterations, "phases": phases,
            "owners_GB": {k: round(v / GB, 3) for k, v in top.items()}, "owners_detail_GB": detail,
            "not_numpy_GB": round((rss - sum(top.values())) / GB, 3), "region_factors_pardiso": pardiso,
            "amg_workers_peak_GB": [round(w, 3) for w in workers],
            "process_peak_GB": round(peak, 3),
            "kB_per_dof": {"process_peak": round(peak * 1024**2 / dofs, 2),
                           "with_workers": round((peak + sum(workers)) * 1024**2 / dofs, 2),
                           "numpy_owned": round(sum(top.values()) / 1024 / dofs, 2)},
            **run.fields(peak_rss_GB=round(peak + sum(workers), 2))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sizes", nargs="+", choices=sorted(SIZES))
    ap.add_argument("--out", type=Path, default=OUT, help="results file (default: the records' %(default)s)")
    ap.add_argument("--depth", type=int, default=4, help="deepest attribute path listed per owner (default 4)")
    ap.add_argument("--keep-before", action="store_true",
                    help="add the row a size replaces to the record's before list (the size's history: a before/after comparison)")
    a = ap.parse_args(argv)
    if len(a.sizes) > 1:  # each size in a process of its own: what one leaves on the heap is not the next one's
        import subprocess

        flags = (["--out", str(a.out)] if a.out != OUT else []) + (["--depth", str(a.depth)] if a.depth != 4 else [])
        flags += ["--keep-before"] if a.keep_before else []
        for size in a.sizes:
            subprocess.run([sys.executable, __file__, size, *flags], check=True)
        return 0
    data = json.loads(a.out.read_text()) if a.out.exists() else {}
    old = data.get("cases", [])
    for size in a.sizes:
        row = measure(size, a.depth)
        if a.keep_before:  # the row it replaces joins ``before``, the size's history (the docs' before/after table)
            data["before"] = data.get("before", []) + [r for r in old if r["size"] == size]
        old = [r for r in old if r["size"] != size] + [row]
        data["cases"] = old
        a.out.write_text(json.dumps(data, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
