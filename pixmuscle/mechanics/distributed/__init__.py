"""The distributed system: each MPI rank holds its own nodes plus a halo (:mod:`.system`), cut by
recursive coordinate bisection (:mod:`.partition`), with the exchanges of :mod:`.layout`."""

from .layout import Layout, PatchLayout
from .partition import bisection_partition, cell_depth, cover_margin, halo, halo_depth, needed, reach
from .system import DistributedState, DistributedSystem, build_distributed_system, submodel

__all__ = ["DistributedState", "DistributedSystem", "Layout", "PatchLayout",
           "bisection_partition", "build_distributed_system", "cell_depth", "cover_margin", "halo", "halo_depth",
           "needed", "reach", "submodel"]
