"""What every benchmark record carries, made one way for every script in ``benchmarks/``.

A record (a row of ``benchmarks/results/*.json``, or a whole file's ``meta`` where a file is one
measurement) gets these fields from :class:`Run`:

``command``
    The command that made it, as run from the repository root (``.venv/bin/python benchmarks/…``).
``commit``
    ``git rev-parse HEAD`` at the start, with ``-dirty`` when tracked files other than the records
    themselves (``benchmarks/results/``) differ from it; ``unknown`` outside a git checkout.
``utc``
    ISO date and time (UTC, seconds) at the start.
``machine``
    CPUs (all, and usable by this process), memory (GB), processor model, OS and Python: no host name.
``load_average``
    ``{"before": [1, 5, 15 min], "after": [...]}`` around the measurement.
``defaults``
    True when what is measured ran at the shipped defaults (every setting the pipeline ships left as
    it is); the script says so.
``peak_rss_GB``
    Peak resident memory of the benchmark's process tree, :func:`peak_rss_GB`.

Rows made before the shipped defaults last changed are marked afterwards by
``benchmarks/mark_superseded.py`` (``"superseded"``), from :data:`DEFAULTS_CHANGES`.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import resource
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
#: environment variable naming the file a child run through :func:`child_command` writes its BoomerAMG
#: workers' peaks to (kB, one JSON list)
WORKERS_FILE_ENV = "PIXMUSCLE_BENCH_WORKERS_FILE"

#: Commits that changed the shipped defaults of the solve (oldest first): (commit, date, what changed).
#: A record made before the last of them is not at today's defaults; ``mark_superseded.py`` names,
#: for each such record, the first change made after it. Add a line here whenever a default changes.
DEFAULTS_CHANGES: list[tuple[str, str, str]] = [
    ("5e68f86", "2026-12-02T10:13:16+00:00", "2 x 2 x 3 pressure patches; auto takes mixed_amg above the direct limit"),
    ("ad330bd", "2026-12-02T19:19:56+00:00", "Newton's residual tolerance 1e-4 (energy 1e-6) instead of 1e-8"),
    ("78d766e", "2026-12-03T06:17:24+00:00", "a cutback holds for the rest of the ramp (newton.hold_cutback)"),
    ("ef4dffc", "2026-12-03T09:54:44+00:00", "Newton on the mixed form (newton.pressure_update: mixed)"),
    ("52fa48a", "2026-12-03T13:40:01+00:00", "mixed_amg's stand-in without its weak node blocks (drop_tol 0.005)"),
    ("07d812d", "2026-12-03T20:06:36+00:00", "BoomerAMG coarsens each displacement component on its own"),
    ("310200e", "2026-12-04T14:29:54+00:00", "amg_processes: auto (BoomerAMG on two processes from 50,000 nodes)"),
    ("545e8cf", "2026-12-04T17:35:05+00:00", "the multigrid's stand-in made positive definite by construction"),
    ("e046e17", "2026-12-04T19:59:35+00:00", "bone_surface held at the vertices of its bone faces"),
    ("4451d67", "2026-12-04T22:28:40+00:00", "held nodes keep their own pressure patch (volumetric.held: own)"),
    ("4075b12", "2026-12-05T00:53:30+00:00", "mixed_amg's region solves take every node of a constraint point's support"),
    ("bb27ce9", "2026-12-05T02:37:37+00:00", "the multigrid stand-in's cut rows keep their first moments"),
    ("f038e9d", "2026-12-05T05:15:59+00:00", "BoomerAMG strength threshold 0.25 instead of 0.5"),
    ("a1f5054", "2026-12-05T15:33:57+00:00", "mixed_amg rebuilds its hierarchy at 40 FGMRES iterations of excess (was 100)"),
]


def git_commit() -> str:
    """``HEAD`` of the checkout, ``-dirty`` appended when tracked files outside the records differ."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                 ":(exclude)benchmarks/results"], cwd=ROOT, capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("-dirty" if status.stdout.strip() else "")


def utc_now() -> str:
    """The time now, ISO 8601 in UTC to the second."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def load_average() -> list[float]:
    """The 1, 5 and 15 min load averages."""
    return [round(x, 2) for x in os.getloadavg()]


def machine() -> dict:
    """The machine without its name: CPUs, memory (GB), processor model, OS and Python."""
    cpus_usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    memory_gb = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1024**3
    processor = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            processor = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), processor)
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "cpus_usable": cpus_usable, "memory_GB": round(memory_gb, 1),
            "processor": processor, "os": f"{platform.system()} {platform.release()}", "python": platform.python_version()}


def workers_peak_kb() -> int:
    """Summed peaks (kB) of the BoomerAMG worker processes of this process (``amg_processes``, only
    while they run) and of those the children run by :func:`child_command` reported."""
    total = 0
    if "pixmuscle.mechanics.linsolve.amg_processes" in sys.modules:  # never import MPI just to ask
        total += sum(sys.modules["pixmuscle.mechanics.linsolve.amg_processes"].workers_peak_rss_kb())
    return total + _reported_kb


_reported_kb = 0


def peak_rss_GB() -> float:
    """Peak resident memory of this process's tree, GB: the sum of this process's peak
    (``RUSAGE_SELF``), the largest peak among its finished children together with their own waited-for
    children (``RUSAGE_CHILDREN``), and the peaks of the BoomerAMG workers (:func:`workers_peak_kb`),
    which MPI starts outside this tree. Summing peaks bounds the peak of the sum from above; children
    run one after another count as the largest of them."""
    kb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss + resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
          + workers_peak_kb())
    return round(kb / 1024**2, 2)  # Linux: ru_maxrss in kB


def command_line(argv: list[str] | None = None, script: str | None = None) -> str:
    """The command that made a record, from the repository root: ``.venv/bin/python SCRIPT ARGS``
    (``script`` defaults to the running script, ``argv`` to its arguments)."""
    script = script or sys.argv[0]
    path = Path(script).resolve()
    script = str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else script
    return shlex.join([".venv/bin/python", script, *(sys.argv[1:] if argv is None else argv)])


class Run:
    """One measurement: what is known at its start (commit, time, machine, load) and, from
    :meth:`fields`, the record's fields once it has ended.

    Parameters
    ----------
    defaults : bool
        Whether the measurement runs at the shipped defaults (can be overridden in :meth:`fields`).
    command : str, optional
        The command that makes it; :func:`command_line` when not given.
    """

    def __init__(self, defaults: bool = False, command: str | None = None):
        self.defaults = defaults
        self.command = command or command_line()
        self.commit = git_commit()
        self.utc = utc_now()
        self.machine = machine()
        self.load_before = load_average()

    def fields(self, defaults: bool | None = None, command: str | None = None,
               peak_rss_GB: float | None = None) -> dict:
        """The record's fields at the end of the measurement (``peak_rss_GB``: this process tree's
        unless given, e.g. by a child that measured its own)."""
        return {"command": command or self.command, "commit": self.commit, "utc": self.utc, "machine": self.machine,
                "load_average": {"before": self.load_before, "after": load_average()},
                "defaults": self.defaults if defaults is None else bool(defaults),
                "peak_rss_GB": globals()["peak_rss_GB"]() if peak_rss_GB is None else peak_rss_GB}


def child_command(argv: list[str]) -> list[str]:
    """``[python, _record.py, --child, *argv]``: runs ``python ARGV`` (a script, ``-m module`` or ``-c code``) in a
    child that, before its BoomerAMG workers stop, writes their peaks to the file named by
    :data:`WORKERS_FILE_ENV`; :func:`run_child` adds them to this process's :func:`peak_rss_GB`."""
    return [sys.executable, str(Path(__file__).resolve()), "--child", *argv]


def run_child(argv: list[str], **popen) -> tuple[int, object, int]:
    """Run ``python ARGV`` through :func:`child_command` and wait for it.

    Returns
    -------
    exit_code : int
    usage : resource.struct_rusage
        ``wait4``'s usage of the child (``ru_maxrss``: the largest process of its tree, kB).
    workers_kb : int
        The summed peaks of the BoomerAMG workers the child started (0 without).
    """
    global _reported_kb
    import tempfile

    with tempfile.NamedTemporaryFile("r", suffix=".json") as f:
        env = {**os.environ, **popen.pop("env", {}), WORKERS_FILE_ENV: f.name}
        proc = subprocess.Popen(child_command(argv), env=env, **popen)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        text = Path(f.name).read_text()
    workers = sum(json.loads(text)) if text.strip() else 0
    _reported_kb = max(_reported_kb, workers)
    return proc.returncode, usage, workers


def _child(argv: list[str]) -> None:
    """Run ``python ARGV`` in this process, reporting its BoomerAMG workers' peaks when they stop."""
    import runpy

    sys.path.insert(0, os.getcwd())
    try:
        from pixmuscle.mechanics.linsolve import amg_processes
    except ImportError:
        amg_processes = None
    if amg_processes is not None and os.environ.get(WORKERS_FILE_ENV):
        close, seen = amg_processes.WorkerGroup.close, {}

        def close_reporting(self):
            if self.open and not self.busy:
                seen[id(self)] = self.peak_rss_kb()
                Path(os.environ[WORKERS_FILE_ENV]).write_text(json.dumps([kb for v in seen.values() for kb in v]))
            close(self)

        amg_processes.WorkerGroup.close = close_reporting
    if argv[0] == "-c":
        sys.argv = ["-c", *argv[2:]]
        exec(compile(argv[1], "<string>", "exec"), {"__name__": "__main__"})
    elif argv[0] == "-m":
        sys.argv = [argv[1], *argv[2:]]
        runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
    else:
        sys.argv = list(argv)
        runpy.run_path(argv[0], run_name="__main__")


if __name__ == "__main__" and len(sys.argv) > 1 and sys.argv[1] == "--child":
    _child(sys.argv[2:])
