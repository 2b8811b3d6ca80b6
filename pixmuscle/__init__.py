"""pixmuscle: pixel-based meshfree (RKPM) modelling of skeletal muscle from MRI and DTI.

Pipeline stages (one sub-package each): imaging/segmentation → model → rk → mechanics → report.
Units inside the package: cm, N, N/cm².
"""

__version__ = "0.1.0"

from .parallel import share_cores as _share_cores

_share_cores()  # under mpiexec, before numba starts its threads
