"""Give the C heap's free pages back to the operating system at the solve's phase boundaries.

Most of what a solve allocates outside numpy — hypre's hierarchies, the assemblers' work arrays
below glibc's mmap threshold, Python objects — comes from glibc's heap, and glibc returns freed
heap memory to the system only from the top of the heap. Pages freed in the middle stay resident
and are counted in the process's memory until they are reused. The solve frees such memory in
large amounts at a few points: after the system build (its temporaries), and when a preconditioner
is rebuilt (the old hierarchy and region factors). Allocations after those points that do not fit
the freed holes take new pages: on the 74k leg the first rebuild of the AMG hierarchy and region
factors left 0.5 GB of free heap resident (2.68 GB live, 3.18 GB resident). Released at those
points, the resident set between the phases is what is live; the peak of a whole sweep moves
less, since most of the freed memory is taken again by the next build (docs/performance.md,
"Where the memory goes").

:func:`release_free_heap` calls glibc's ``malloc_trim(0)``, which releases every whole free page
of every arena (``madvise(MADV_DONTNEED)``): a few milliseconds. Where the C library is not glibc
(macOS, musl) it does nothing.

References
----------
The GNU C Library Reference Manual, "Memory Allocation Tunables" and ``malloc_trim(3)``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _trim():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        fn = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


def release_free_heap() -> bool:
    """Return the C heap's whole free pages to the operating system.

    Returns
    -------
    bool
        True where glibc's ``malloc_trim`` ran and released memory, False where it released none
        or the C library has no such call.
    """
    fn = _trim()
    return bool(fn(0)) if fn is not None else False
