"""Configuration of the ``segment`` stage (paper §4.1–4.2).

Intensity convention: every level-set model works on the MRI scaled robustly to [0, 255] and
on fibre channels ``255 * feature`` (see :mod:`pixmuscle.segmentation.features`); the paper's
``lambda = 0.02`` and ``mu = 1`` / ``100`` are meant on that scale.

Example (YAML)::

    segment:
      mri: data/leg_t1.nii.gz
      dti_tensor: data/leg_dti_tensor.nii.gz
      tensor_order: fsl
      imct_mask: data/leg_imct.nii.gz
      imat_mask: data/leg_imat.nii.gz
      seed_units: cm
      seeds:
        tibialis_anterior: [[0.5, 2.7, 13.0]]
        soleus: [[-0.3, -2.3, 13.0], [-0.3, -2.3, 16.0]]
      multiphase: {n_levelsets: 3, mu: [1.0], lambdas: [0.02], fiber_channels: outer}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pixmuscle.errors import InputError

__all__ = ["TwoPhaseConfig", "BoneConfig", "MultiphaseConfig", "DWIConfig", "SegmentConfig"]


@dataclass(frozen=True)
class DWIConfig:
    """A diffusion-weighted series as from the scanner: a 4-D NIfTI with FSL b-values / b-vectors, or
    a folder of DICOM files (gradients from the DICOM tags, :mod:`pixmuscle.io.dicom`); the tensor is
    fitted with dipy (:mod:`pixmuscle.imaging.dwi`, optional extra ``pixmuscle[dwi]``)."""

    image: Path = field(metadata={"must_exist": True, "doc": "4-D NIfTI, one volume per gradient, or a folder of "
                                                            "DICOM files (b-values and gradients from its tags)"})
    bvals: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "b-values file (FSL .bval, s/mm^2); with a NIfTI image only"})
    bvecs: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "b-vectors file (FSL .bvec, 3 rows); with a NIfTI image only"})
    series: str | int | None = field(default=None, metadata={
        "doc": "DICOM folder with several series: the diffusion series' SeriesNumber, SeriesDescription or "
               "SeriesInstanceUID"})
    bvecs_convention: Literal["fsl", "world"] = field(default="fsl", metadata={
        "doc": "fsl: voxel axes of the stored image, x negated for a positive-determinant affine "
               "(FSL, dcm2niix); world: scanner axes (NIfTI image only; DICOM is converted to fsl)"})
    b0_threshold: float = field(default=50.0, metadata={
        "range": (0.0, None), "doc": "b-values up to this (s/mm^2) are non-weighted volumes"})

    def __post_init__(self):
        if self.image.is_dir():
            for key in ("bvals", "bvecs"):
                if getattr(self, key) is not None:
                    raise InputError(f"segment.dwi.{key}: not used with a DICOM folder ({self.image}): "
                                     "the gradients come from its DICOM tags; remove the key")
        else:
            for key in ("bvals", "bvecs"):
                if getattr(self, key) is None:
                    raise InputError(f"segment.dwi.{key}: required key is missing (a NIfTI image, {self.image}, needs its "
                                     "b-values and b-vectors files; a DICOM folder carries them in its tags)")
            if self.series is not None:
                raise InputError(f"segment.dwi.series: only for a DICOM folder; {self.image} is a file")


@dataclass(frozen=True)
class TwoPhaseConfig:
    """Two-phase Chan–Vese (Chan & Vese 2001) settings, MRI on the [0, 255] scale."""

    mu: float = field(default=100.0, metadata={
        "range": (0.0, None), "doc": "contour length weight (paper: 1 or 100)"})
    nu: float = field(default=0.0, metadata={"doc": "area weight of the inside region"})
    lambda1: float = field(default=0.02, metadata={
        "range": (0.0, None), "doc": "data weight inside, per squared grey level (paper: 0.02)"})
    lambda2: float = field(default=0.02, metadata={
        "range": (0.0, None), "doc": "data weight outside, per squared grey level"})
    dt: float = field(default=0.5, metadata={"gt": 0.0, "doc": "time step of the scheme"})
    eps: float = field(default=1.0, metadata={
        "gt": 0.0, "doc": "width of the regularised Dirac (level-set units)"})
    tol: float = field(default=5e-4, metadata={
        "range": (0.0, 1.0), "doc": "stop when at most this fraction of voxels changes side "
                                    "over `window` iterations"})
    window: int = field(default=10, metadata={"range": (1, None),
                                              "doc": "iterations between convergence checks"})
    max_iter: int = field(default=500, metadata={"range": (1, None), "doc": "iteration limit"})
    reinit_every: int = field(default=5, metadata={
        "range": (0, None), "doc": "reinitialise to a signed distance every n iterations (0: never)"})


@dataclass(frozen=True)
class BoneConfig(TwoPhaseConfig):
    """Two-phase Chan–Vese settings for the bones (dark cortex inside the leg)."""

    mu: float = field(default=30.0, metadata={
        "range": (0.0, None), "doc": "contour length weight (a thin cortex needs less than the "
                                     "outer boundary)"})


@dataclass(frozen=True)
class MultiphaseConfig:
    """Multiphase multichannel Vese–Chan settings (paper eq. 21)."""

    n_levelsets: int = field(default=3, metadata={
        "range": (1, 6), "doc": "K level sets -> 2^K regions (paper: 3)"})
    mu: tuple[float, ...] = field(default=(1.0,), metadata={
        "range": (0.0, None), "doc": "length weight per level set (1 value or K; paper: 1)"})
    lambdas: tuple[float, ...] = field(default=(0.02,), metadata={
        "range": (0.0, None),
        "doc": "data weight per channel (1 value, or one per channel: MRI first, then fibre "
               "channels), per squared grey level (paper: 0.02)"})
    lambdas_per_region: list[list[float]] | None = field(default=None, metadata={
        "doc": "optional (2^K x channels) data weights; overrides `lambdas`"})
    fiber_channels: Literal["outer", "canonical", "abs", "none"] = field(default="outer", metadata={
        "doc": "fibre channels: outer = 6 components of v v^T (sign-free, continuous); "
               "canonical = e1, e2, e3 with v_z >= 0 (the paper's); none = MRI only"})
    use_mri: bool = field(default=True, metadata={"doc": "include the MRI as channel 0"})
    init: Literal["seeds", "kmeans", "checkerboard"] = field(default="seeds", metadata={
        "doc": "initial regions: nearest seed features (muscle m -> region m), k-means "
               "clusters of the channels, or Vese-Chan checkerboards (the last two in per-slice "
               "mode warm-start each slice from its finished neighbour)"})
    dt: float = field(default=0.5, metadata={"gt": 0.0, "doc": "time step"})
    eps: float = field(default=1.0, metadata={"gt": 0.0, "doc": "Dirac width (level-set units)"})
    tol: float = field(default=5e-4, metadata={
        "range": (0.0, 1.0), "doc": "stop when at most this fraction of voxels changes region "
                                    "over `window` iterations"})
    window: int = field(default=10, metadata={"range": (1, None),
                                              "doc": "iterations between convergence checks"})
    max_iter: int = field(default=300, metadata={"range": (1, None), "doc": "iteration limit"})
    reinit_every: int = field(default=5, metadata={
        "range": (0, None), "doc": "reinitialise every n iterations (0: never)"})


@dataclass(frozen=True)
class SegmentConfig:
    """``segment`` section: inputs, the level-set models and label assembly (paper §4.1–4.2)."""

    mri: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "anatomical MRI: a NIfTI file or a folder of DICOM files; defines the label grid"})
    series: str | int | None = field(default=None, metadata={
        "doc": "DICOM folder with several series: the anatomical series' SeriesNumber, SeriesDescription or "
               "SeriesInstanceUID"})
    bias_correction: Literal["none", "n4"] = field(default="none", metadata={
        "doc": "intensity inhomogeneity (receive-coil bias field) correction of the MRI before the level sets: "
               "n4 = SimpleITK's N4 (optional extra pixmuscle[scanner]); the field is written for QC"})
    dti_tensor: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "diffusion tensor image (NIfTI, 6 components)"})
    dti_v1: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "principal eigenvector image (NIfTI, 3 components), used "
                                   "when no tensor is given"})
    dwi: DWIConfig | None = field(default=None, metadata={
        "doc": "diffusion-weighted series {image, bvals, bvecs}: the tensor is fitted (dipy) "
               "instead of reading dti_tensor"})
    tensor_order: Literal["fsl", "dipy", "mrtrix"] = field(default="fsl", metadata={
        "doc": "component order of the tensor file"})
    dti_components: Literal["world", "voxel", "fsl"] = field(default="world", metadata={
        "doc": "axes of the DTI vector/tensor components in the files"})
    imct_mask: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "IMCT mask (NIfTI, any grid): labelled connective tissue"})
    imat_mask: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "IMAT mask (NIfTI, any grid): labelled fat"})
    aponeurosis_mask: Path | None = field(default=None, metadata={
        "must_exist": True, "doc": "aponeurosis mask (NIfTI, any grid): connective tissue that is not IMCT "
                                   "(paper Table 3); labelled connective tissue, kept as node set 'aponeurosis'"})
    seeds: dict[str, list[list[float]]] = field(default_factory=dict, metadata={
        "doc": "muscle name -> seed point [x, y, z] or list of points inside that muscle (order = ids)"})
    seed_units: Literal["cm", "mm", "voxel"] = field(default="cm", metadata={
        "doc": "seed coordinates: world cm or mm (scanner coordinates, as a viewer shows them), or voxel "
               "indices (i, j, k) of the MRI file as stored (as ITK-SNAP/FSLeyes show them)"})
    mode: Literal["slice", "3d"] = field(default="slice", metadata={
        "doc": "level sets per 2-D slice (the paper) or on the whole volume"})
    outer: TwoPhaseConfig = field(default_factory=TwoPhaseConfig, metadata={
        "doc": "Chan-Vese for the outer boundary (leg vs air)"})
    bone: BoneConfig = field(default_factory=BoneConfig, metadata={
        "doc": "Chan-Vese for the bones (inside the leg)"})
    multiphase: MultiphaseConfig = field(default_factory=MultiphaseConfig, metadata={
        "doc": "multiphase segmentation of the muscles"})
    fiber_min_fa: float = field(default=0.0, metadata={
        "range": (0.0, 1.0), "doc": "fibre data needs FA at least this"})
    fiber_min_trace: float = field(default=0.5, metadata={
        "range": (0.0, None), "doc": "fibre data needs trace(D) at least this fraction of the "
                                     "median trace of the non-zero tensors"})
    min_marrow_bright: float = field(default=0.5, metadata={
        "range": (0.0, 1.0), "doc": "a hole in the dark bone class is marrow if at least this "
                                    "fraction of it is in the bright (fat-like) class"})
    max_cortex_cm: float = field(default=0.6, metadata={
        "gt": 0.0, "doc": "thickest cortex (cm): dark voxels this close to marrow are bone"})
    qc_png: bool = field(default=True, metadata={"doc": "write per-slice overlay PNGs"})

    def dti_files(self) -> tuple[Path, ...]:
        """The files (or DICOM folder) the section's DTI is read from."""
        dwi = () if self.dwi is None else (self.dwi.image, self.dwi.bvals, self.dwi.bvecs)
        return tuple(p for p in (self.dti_tensor, self.dti_v1, *dwi) if p is not None)

    def __post_init__(self):
        if self.series is not None and self.mri is not None and not self.mri.is_dir():
            raise InputError(f"segment.series: only for a DICOM folder; segment.mri {self.mri} is a file")
        if self.dti_tensor is not None and self.dti_v1 is not None:
            raise InputError("segment.dti_v1: give either dti_tensor (preferred: tensors are interpolated "
                             "correctly) or dti_v1, not both")
        if self.dwi is not None and (self.dti_tensor is not None or self.dti_v1 is not None):
            raise InputError("segment.dwi: give either a DWI series (dwi) or a fitted DTI "
                             "(dti_tensor / dti_v1), not both")
        names = list(self.seeds)
        for name, pts in self.seeds.items():
            if not pts:
                raise InputError(f"segment.seeds.{name}: expected at least one point")
            for i, p in enumerate(pts):
                if len(p) != 3:
                    raise InputError(f"segment.seeds.{name}[{i}]: expected 3 coordinates "
                                     f"[x, y, z], got {list(p)}")
        k = self.multiphase.n_levelsets
        if len(names) > 2**k:
            raise InputError(f"segment.seeds: {len(names)} muscles but "
                             f"segment.multiphase.n_levelsets = {k} gives only {2**k} regions")
        if len(self.multiphase.mu) not in (1, k):
            raise InputError(f"segment.multiphase.mu: expected 1 or {k} values, got "
                             f"{len(self.multiphase.mu)}")
