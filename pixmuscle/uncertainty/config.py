"""Configuration of the uncertainty study (YAML section ``uncertainty``).

Example (YAML)::

    uncertainty:
      realisations: 8          # noisy realisations; the noise-free case is run too
      seed: 0                  # realisation r is drawn from (seed, r): reproducible from the config alone
      dti_snr: 20              # S0 / sigma of the b = 0 signal (null: no DTI noise)
      dti_bvalue: 500          # s/mm^2, the acquisition the noise is simulated for
      dti_directions: 12
      dti_b0_volumes: 1
      boundary_voxels: 1.0     # boundaries moved in-plane by up to this many voxels (0: off)
      boundary_length_cm: 1.0  # correlation length of the boundary displacement, cm
"""

from __future__ import annotations

import dataclasses
from dataclasses import field

from pixmuscle.errors import InputError

__all__ = ["UncertaintyConfig", "MAX_REALISATIONS"]

#: most realisations of one run (each is a whole solve)
MAX_REALISATIONS = 999


@dataclasses.dataclass(frozen=True)
class UncertaintyConfig:
    """Realisations of the scan's noise: DTI noise and the segmentation's boundaries (docs/uncertainty.md)."""

    realisations: int = field(default=8, metadata={
        "range": (2, MAX_REALISATIONS),
        "doc": "noisy realisations (cases <output_dir>/uncertainty/r01 ...); the noise-free case is run as well"})
    seed: int = field(default=0, metadata={
        "range": (0, None), "doc": "random seed: realisation r is drawn from (seed, r) alone, so the same config "
                                   "gives the same realisations on any machine and runner"})
    dti_snr: float | None = field(default=20.0, metadata={
        "gt": 0, "doc": "SNR of the DTI: S0 / sigma of the non-weighted (b = 0) signal, Rician noise on the "
                        "simulated signals of each DTI voxel, tensor fitted again (null: no DTI noise)"})
    dti_bvalue: float = field(default=500.0, metadata={
        "gt": 0, "doc": "b-value of the diffusion-weighted volumes the noise is simulated for, s/mm^2"})
    dti_directions: int = field(default=12, metadata={
        "range": (6, 1000), "doc": "gradient directions of the simulated acquisition"})
    dti_b0_volumes: int = field(default=1, metadata={
        "range": (1, 100), "doc": "non-weighted (b = 0) volumes of the simulated acquisition"})
    boundary_voxels: float = field(default=0.0, metadata={
        "range": (0.0, 10.0), "doc": "segmentation boundaries moved in-plane by up to this many voxels by a "
                                     "smooth random field (0: off, the default: it shifts F_max systematically, "
                                     "docs/uncertainty.md; 0 < value ≤ 0.5 moves no voxel centre)"})
    boundary_length_cm: float = field(default=1.0, metadata={
        "gt": 0, "doc": "correlation length of the boundary displacement field, cm"})

    def __post_init__(self):
        if 0 < self.boundary_voxels <= 0.5:
            raise InputError(f"uncertainty.boundary_voxels: {self.boundary_voxels} moves no voxel: a boundary lies on "
                             "the faces between voxels, half a voxel from their centres, so a voxel changes label only "
                             "when the boundary moves by more than 0.5 voxels; use 0 (off) or a value > 0.5, e.g. 1 "
                             "(the boundary anywhere within the boundary voxels)")
        if self.dti_snr is None and self.boundary_voxels == 0:
            raise InputError("uncertainty: nothing is perturbed (dti_snr is null and boundary_voxels is 0); "
                             "set dti_snr and/or boundary_voxels")
