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
    Peak memory of the benchmark's process tree, :func:`peak_rss_GB`: the largest sum over the
    process and all its descendants (the BoomerAMG workers and children included) of each one's
    proportional set size, sampled by :class:`TreeMemory` (every :data:`SAMPLE_S` seconds, less often
    where reading a large tree would take more than :data:`SAMPLER_SHARE` of a core), or the largest
    own high-water mark of a process of the tree where that is larger.

Rows made before the shipped defaults last changed are marked afterwards by
``benchmarks/mark_superseded.py`` (``"superseded"``), from :data:`DEFAULTS_CHANGES`.
"""

from __future__ import annotations

import datetime as dt
import os
import platform
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"

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
    ("9f2cf06", "2026-12-07T13:53:48+00:00", "region solves factorise each displacement component's block (region_coupling: auto)"),
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


#: seconds between two samples of the process tree's memory (:class:`TreeMemory`), at least
SAMPLE_S = 0.25
#: the largest share of one core the sampling may take: reading a process's proportional set size walks
#: its page tables (50 ms for a 13 GB process), so after a sample that took t seconds the sampler waits
#: max(SAMPLE_S, t / SAMPLER_SHARE). Sampling a 13 GB solve every 0.25 s took 73 % of a core on this
#: 2-core machine, and the solve it measured ran that much slower.
SAMPLER_SHARE = 0.02


def _children() -> dict[int, list[int]]:
    """Each process's children (by its parent's pid), from ``/proc/*/stat``."""
    out: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        out.setdefault(ppid, []).append(int(name))
    return out


def status_kb(pid: int | str, key: str) -> int:
    """A ``/proc/PID/status`` entry in kB (``VmRSS``, ``VmHWM``); 0 where it cannot be read."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def _pss_kb(pid: int) -> int:
    """Proportional set size of ``pid``, kB: its resident pages, each page shared by k processes
    counted 1/k (``/proc/PID/smaps_rollup``); its resident size where that is not readable."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return status_kb(pid, "VmRSS")


def own_peak_kb(pid: int | str = "self") -> int:
    """The high-water mark of a process's resident memory since it started its program, kB
    (``VmHWM``). Not ``ru_maxrss``: Linux keeps in that the size of the forked copy of the parent
    that ran until ``exec``, so a small child of a large process reports the parent's size."""
    return status_kb(pid, "VmHWM")


def tree_kb(root: int | None = None) -> tuple[int, int]:
    """Memory of the process ``root`` (this one by default) and all its descendants now, kB: the sum
    of their proportional set sizes (:func:`_pss_kb`), so that pages a fork shares are counted once,
    and the largest own high-water mark among them (:func:`own_peak_kb`, a lower bound of the tree's
    peak that no sampling interval can miss). The BoomerAMG workers that ``amg_processes`` spawns are
    descendants (of Open MPI's daemon, a child of the run)."""
    root = os.getpid() if root is None else root
    children, total, largest, todo = _children(), 0, 0, [root]
    while todo:
        pid = todo.pop()
        total += _pss_kb(pid)
        largest = max(largest, own_peak_kb(pid))
        todo.extend(children.get(pid, ()))
    return total, largest


class TreeMemory:
    """The peak memory of a process tree (``root`` and its descendants; default this process), kB,
    sampled by a daemon thread from :meth:`start` until :meth:`stop`: the larger of the largest sampled
    :func:`tree_kb` sum and the largest own high-water mark of a process of the tree.

    The samples are :data:`SAMPLE_S` seconds apart, or further where reading the tree is slow, so that
    the sampling takes at most :data:`SAMPLER_SHARE` of a core. A sample can miss a peak of the sum
    shorter than the interval; the high-water marks cannot miss a process's own peak.
    """

    def __init__(self, root: int | None = None):
        self.root = root
        self.peak_kb = 0
        self._thread = None
        self._stop = threading.Event()

    def start(self) -> TreeMemory:
        if self._thread is None:
            self.sample()
            self._thread = threading.Thread(target=self._run, name="tree-memory", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> int:
        """End the sampling (after one last sample) and return the peak, kB."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        return self.sample()

    def sample(self) -> int:
        self.peak_kb = max(self.peak_kb, *tree_kb(self.root))
        return self.peak_kb

    def _run(self) -> None:
        wait = SAMPLE_S
        while not self._stop.wait(wait):
            t0 = time.perf_counter()
            self.sample()
            wait = max(SAMPLE_S, (time.perf_counter() - t0) / SAMPLER_SHARE)


_sampler = TreeMemory().start()


def peak_rss_GB() -> float:
    """Peak memory of this process's tree, GB: the largest sampled sum of the proportional set sizes
    of this process and all its descendants (:class:`TreeMemory`: BoomerAMG workers, children and
    MPI ranks started by a child ``mpiexec`` included; pages shared after a fork counted once), or
    the largest own high-water mark of a process of the tree (:func:`own_peak_kb`) where that is larger."""
    return round(_sampler.sample() / 1024**2, 2)


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


def run_child(argv: list[str], **popen) -> tuple[int, object, int]:
    """Run ``python ARGV`` (a script, ``-m module`` or ``-c code``) and wait for it, sampling the
    memory of its process tree (:class:`TreeMemory` of the child) as it runs.

    Returns
    -------
    exit_code : int
    usage : resource.struct_rusage
        ``wait4``'s usage of the child (its ``ru_maxrss`` is not its peak: :func:`own_peak_kb`).
    peak_kb : int
        The largest sampled memory of the child's tree (its BoomerAMG workers and Dask workers
        included), or the largest own high-water mark of a process of that tree where that is
        larger, kB.
    """
    proc = subprocess.Popen([sys.executable, *argv], **popen)
    sampler = TreeMemory(proc.pid).start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        peak = sampler.stop()
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage, peak
