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

Within a phase the same holds for arrays below glibc's mmap threshold, which glibc raises
(dynamically, up to 32 MB) to the size of every mapped block freed: after the first few frees,
the per-node arrays of a large model (N × 9 float64 is 21 MB at 295k nodes) come from the heap,
and the holes they leave when freed stay resident until the next trim. :func:`map_large_allocations`
fixes the threshold instead (glibc's ``mallopt(M_MMAP_THRESHOLD)``, which also turns the dynamic
raise off), so that a block of at least 1 MiB that needs new memory gets a mapping of its own and
goes back to the system when it is freed. The threshold does not apply to a request that a free
chunk of the heap can serve: glibc takes that chunk, whatever the size, faults its trimmed pages
in again, and keeps them resident once the block is freed. So the heap's free space left by the
build takes the per-node arrays of every Newton iteration; on the 295k leg that held 0.7 GB
resident from the first line search on (sampled RSS of the solving process; tracemalloc showed
the live numpy memory unchanged). The solve therefore trims once per Newton iteration too.

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

#: glibc's mallopt parameter number of the mmap threshold (malloc.h)
M_MMAP_THRESHOLD = -3
#: the size from which a block has a mapping of its own (:func:`map_large_allocations`), bytes
LARGE_BYTES = 1 << 20


@functools.cache
def _libc_function(name: str, argtypes: tuple):
    """The C library's function ``name`` (int result), or None where the library or the function is missing."""
    lib = ctypes.util.find_library("c")
    if lib is None:
        return None
    try:
        fn = getattr(ctypes.CDLL(lib), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes = list(argtypes)
    fn.restype = ctypes.c_int
    return fn


def _trim():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    return _libc_function("malloc_trim", (ctypes.c_size_t,))


def map_large_allocations(threshold: int = LARGE_BYTES) -> bool:
    """Give every C-heap block of at least ``threshold`` bytes its own memory mapping, returned to
    the operating system when it is freed (glibc's ``mallopt(M_MMAP_THRESHOLD, threshold)``; the
    setting holds for the whole process and every thread).

    Returns
    -------
    bool
        True where glibc took the setting; False where the C library has no ``mallopt``.
    """
    fn = _libc_function("mallopt", (ctypes.c_int, ctypes.c_int))
    return bool(fn(M_MMAP_THRESHOLD, int(threshold))) if fn is not None else False


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
