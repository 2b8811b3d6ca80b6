"""The segment section as a user writes it: seed units (cm, mm, voxels of the file's own grid), one
point where a list is expected, scalar weights, case-insensitive choices, conflicting inputs."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError
from pixmuscle.imaging.nifti import load_volume
from pixmuscle.segmentation.config import SegmentConfig
from pixmuscle.segmentation.volume import _check_distinct_seeds, seeds_to_voxels
from pixmuscle.stages.segment import seeds_in_cm


def _parse(raw, base_dir="."):
    return parse_section(SegmentConfig, raw, "segment", base_dir)


def test_single_point_scalar_weights_and_case_insensitive_choices():
    c = _parse({"seeds": {"soleus": [1.0, 2.0, 3.0], "tibialis": [[1, 2, 4], [1, 2, 5]]}, "seed_units": "CM",
                "tensor_order": "FSL", "multiphase": {"mu": 1, "lambdas": 0.02, "fiber_channels": "Outer"}})
    assert c.seeds == {"soleus": [[1.0, 2.0, 3.0]], "tibialis": [[1.0, 2.0, 4.0], [1.0, 2.0, 5.0]]}
    assert c.seed_units == "cm" and c.tensor_order == "fsl" and c.multiphase.fiber_channels == "outer"
    assert c.multiphase.mu == (1.0,) and c.multiphase.lambdas == (0.02,)
    with pytest.raises(InputError, match=r"segment.seed_units: .*did you mean 'voxel'"):
        _parse({"seed_units": "voxels"})
    with pytest.raises(InputError, match=r"segment.seeds.soleus\[0\]: expected 3 coordinates"):
        _parse({"seeds": {"soleus": [1.0, 2.0]}})


def test_both_dti_inputs_is_an_error(tmp_path):
    for name in ("t.nii.gz", "v.nii.gz"):
        (tmp_path / name).write_bytes(b"x")
    with pytest.raises(InputError, match="either dti_tensor .* or dti_v1, not both"):
        _parse({"dti_tensor": "t.nii.gz", "dti_v1": "v.nii.gz"}, tmp_path)


def test_two_muscles_sharing_a_seed_voxel_is_an_error():
    names, pts = seeds_to_voxels({"a": [[1.0, 1.0, 1.0]], "b": [[1.2, 0.9, 1.1]]}, "voxel", np.eye(4), (4, 4, 4))
    with pytest.raises(InputError, match="'a' and 'b' have a seed in the same voxel"):
        _check_distinct_seeds(names, pts)


@pytest.mark.parametrize("flip", [(-1, -1, 1), (1, 1, 1), (1, -1, -1)])
def test_voxel_seeds_are_voxels_of_the_file_as_stored(tmp_path, flip):
    """An LPS (or other) file: a seed given as (i, j, k) of the file lands on that very voxel of the
    reoriented grid the segmentation works on (checked on the voxel values, read independently)."""
    rng = np.random.default_rng(0)
    data = rng.uniform(1, 2, (7, 6, 5)).astype(np.float32)
    aff = np.diag([0.8 * flip[0], 0.9 * flip[1], 2.5 * flip[2], 1.0])
    aff[:3, 3] = [10.0, -20.0, 30.0]
    img = nib.Nifti1Image(data, aff)
    img.header.set_xyzt_units("mm")
    path = tmp_path / "mri.nii.gz"
    nib.save(img, path)
    vol = load_volume(path, kind="image")
    file_ijk = [[1, 2, 3], [6, 0, 4], [0, 5, 0]]
    cfg = SegmentConfig(mri=path, seeds={"m": file_ijk}, seed_units="voxel")
    names, ijk = seeds_to_voxels(seeds_in_cm(cfg), "cm", vol.affine, vol.data.shape)
    got = vol.data[tuple(ijk[0].T)]
    expect = data[tuple(np.array(file_ijk).T)]
    np.testing.assert_array_equal(got, expect)
    # the same points in world mm and in cm
    cm = seeds_in_cm(cfg)["m"]
    mm = SegmentConfig(mri=path, seeds={"m": (np.array(cm) * 10).tolist()}, seed_units="mm")
    np.testing.assert_array_equal(seeds_to_voxels(seeds_in_cm(mm), "cm", vol.affine, vol.data.shape)[1][0], ijk[0])
