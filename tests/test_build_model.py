"""build-model: label volume → pixel-point model, checked against nibabel and hand-made truths."""

import logging
import re

import h5py
import nibabel as nib
import numpy as np
import pytest
from nibabel.affines import apply_affine

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError, SchemaError
from pixmuscle.model.build import model_from_labels, parse_tissue_map, principal_directions
from pixmuscle.model.config import BuildModelConfig, CoarsenConfig
from pixmuscle.model.tissues import NODE_TISSUES

# 0.8 × 0.8 × 4 mm voxels, x axis flipped (LAS storage), arbitrary origin — in mm
AFFINE_MM = np.array([[-0.8, 0.0, 0.0, 41.3],
                      [0.0, 0.8, 0.0, -12.7],
                      [0.0, 0.0, 4.0, 55.0],
                      [0.0, 0.0, 0.0, 1.0]])


def mm_to_cm(aff):
    out = aff.copy()
    out[:3] /= 10.0
    return out


def random_labels(shape=(12, 9, 5), seed=0):
    rng = np.random.default_rng(seed)
    return rng.choice([0, 1, 2, 3, 4], p=[0.2, 0.4, 0.15, 0.15, 0.1], size=shape).astype(np.int16)


def sort_rows(a):
    a = np.asarray(a)
    return a[np.lexsort(a.T[::-1])]


def test_nodes_coordinates_and_volume_against_nibabel():
    labels = random_labels()
    model = model_from_labels(labels, mm_to_cm(AFFINE_MM), muscle_fibers={"muscle": [0, 0, 1]})
    is_node = np.isin(labels, NODE_TISSUES)
    assert model.n_nodes == int(is_node.sum())
    # every node tissue voxel, mapped to the scanner frame by nibabel (mm) then cm: same point set
    world = apply_affine(AFFINE_MM, np.argwhere(is_node)) / 10.0
    np.testing.assert_allclose(sort_rows(model.X), sort_rows(world), atol=1e-12)
    # the model grid is nibabel's closest canonical grid: ijk, tissue and X = canonical affine @ ijk
    canon = nib.as_closest_canonical(nib.Nifti1Image(labels, AFFINE_MM))
    cdata = np.asarray(canon.dataobj)
    np.testing.assert_array_equal(model.ijk, np.argwhere(np.isin(cdata, NODE_TISSUES)))
    np.testing.assert_array_equal(model.tissue, cdata[tuple(model.ijk.T)])
    np.testing.assert_allclose(model.X, apply_affine(canon.affine, model.ijk) / 10.0, atol=1e-12)
    np.testing.assert_array_equal(model.shape, cdata.shape)
    np.testing.assert_allclose(model.spacing, [0.08, 0.08, 0.4])
    np.testing.assert_allclose(model.rotation, np.eye(3), atol=1e-15)
    # cell volumes sum to the node voxels' volume
    assert model.n_nodes * model.cell_volume == pytest.approx(is_node.sum() * abs(np.linalg.det(AFFINE_MM[:3, :3])) / 1e3)
    # bone voxels kept in canonical indices
    np.testing.assert_array_equal(sort_rows(model.bone_ijk), sort_rows(np.argwhere(cdata == 4)))
    assert model.fiber[model.tissue != 1].any() is np.False_
    np.testing.assert_allclose(model.fiber[model.tissue == 1], np.tile([0, 0, 1.0], ((model.tissue == 1).sum(), 1)))


def test_spacing_only_and_node_sets_present():
    labels = np.zeros((4, 4, 3), int)
    labels[1:3, 1:3, :] = 3
    model = model_from_labels(labels, [0.1, 0.2, 0.5])
    np.testing.assert_allclose(model.X, model.ijk * [0.1, 0.2, 0.5])
    assert model.muscle_names == ["muscle"] and not model.fiber.any()
    assert {"z_min", "z_max", "x_min", "x_max", "y_min", "y_max", "bone_surface", "outer_surface"} <= set(model.sets)
    assert len(model.sets["z_min"]) == 4 and len(model.sets["outer_surface"]) == 12


def test_oblique_scan_rotation_and_fibres(caplog):
    t = np.radians(10.0)
    R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    spacing = np.array([0.1, 0.1, 0.5])
    aff = np.eye(4)
    aff[:3, :3] = R * spacing
    aff[:3, 3] = [1.0, 2.0, 3.0]
    labels = random_labels((6, 5, 3), seed=3)
    f_world = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    with caplog.at_level(logging.WARNING):
        model = model_from_labels(labels, aff, muscle_fibers={"muscle": f_world})
    assert "oblique" in caplog.text
    np.testing.assert_allclose(model.rotation, R, atol=1e-12)
    # model frame → scanner frame: rotate about the origin, then equals nibabel's mapping
    world = (model.X - model.origin) @ model.rotation.T + model.origin
    np.testing.assert_allclose(world, apply_affine(aff, model.ijk), atol=1e-12)
    # fibres rotate with the frame: R f_model is parallel to the scanner-frame direction
    fm = model.fiber[model.tissue == 1]
    np.testing.assert_allclose(np.abs(fm @ R.T @ f_world), 1.0, atol=1e-12)


def test_named_muscles_and_per_muscle_fibres():
    rng = np.random.default_rng(1)
    labels = rng.choice([0, 5, 6, 7, 9], size=(6, 6, 4)).astype(np.int32)
    tissue_map = {0: "background", 5: {"muscle": "soleus", "fiber": [0, 0.2, 1]},
                  6: {"muscle": "gastrocnemius"}, 7: "fat", 9: "bone"}
    model = model_from_labels(labels, [0.1, 0.1, 0.4], tissue_map=tissue_map,
                              muscle_fibers={"gastrocnemius": [1, 0, -1]})
    assert model.muscle_names == ["soleus", "gastrocnemius"]
    lab = labels[tuple(model.ijk.T)]
    np.testing.assert_array_equal(model.muscle_id, np.select([lab == 5, lab == 6], [1, 2], 0))
    np.testing.assert_array_equal(model.tissue, np.select([lab == 7], [3], 1))
    sol = np.array([0, 0.2, 1]) / np.linalg.norm([0, 0.2, 1])
    gas = np.array([-1, 0, 1]) / np.sqrt(2)       # canonical sign: z ≥ 0
    np.testing.assert_allclose(model.fiber[lab == 5], np.tile(sol, ((lab == 5).sum(), 1)))
    np.testing.assert_allclose(model.fiber[lab == 6], np.tile(gas, ((lab == 6).sum(), 1)))
    assert not model.fiber[lab == 7].any()
    np.testing.assert_array_equal(sort_rows(model.bone_ijk), sort_rows(np.argwhere(labels == 9)))


def test_plain_muscle_names():
    labels = np.array([1, 8, 2, 0]).reshape(2, 2, 1)
    model = model_from_labels(labels, [1, 1, 1], tissue_map={0: "background", 1: "muscle", 8: "muscle",
                                                             2: "fat"}, muscle_fibers={"muscle_1": [0, 0, 1],
                                                                                       "muscle_8": [0, 1, 0]})
    assert model.muscle_names == ["muscle_1", "muscle_8"]


def test_missing_fibre_names_count_and_location():
    labels = np.zeros((5, 5, 3), np.int16)
    labels[1:4, 1:4, :] = 1
    fib = np.zeros((5, 5, 3, 3))
    fib[labels == 1] = [0.0, 0.0, 1.0]
    holes = [(1, 2, 0), (3, 3, 2), (2, 2, 1)]
    for h in holes:
        fib[h] = 0.0
    fib[2, 2, 1] = np.nan
    spacing = [0.1, 0.1, 0.5]
    with pytest.raises(InputError) as exc:
        model_from_labels(labels, spacing, fibers=fib)
    msg = str(exc.value)
    assert msg.startswith("3 muscle nodes have no usable fibre direction")
    assert "'muscle': 3 nodes" in msg and "fiber_fallback" in msg
    listed = [tuple(map(int, m)) for m in re.findall(r"ijk \((\d+), (\d+), (\d+)\)", msg)]
    assert listed and set(listed) <= set(holes)
    xyz = [tuple(map(float, m)) for m in re.findall(r"at \(([-\d.]+), ([-\d.]+), ([-\d.]+)\) cm", msg)]
    np.testing.assert_allclose(xyz, np.array(listed) * spacing, atol=5e-3)
    # no fibre at all
    with pytest.raises(InputError, match="no fibre image"):
        model_from_labels(labels, spacing)


def test_muscle_mean_fallback_recovers_direction(caplog):
    rng = np.random.default_rng(5)
    labels = np.ones((8, 8, 6), np.int16)
    d = np.array([0.3, -0.5, 0.8])
    d /= np.linalg.norm(d)
    v = d + 0.05 * rng.standard_normal(labels.shape + (3,))
    v *= rng.choice([-1.0, 1.0], size=labels.shape)[..., None]      # random signs
    v *= rng.uniform(0.5, 2.0, size=labels.shape)[..., None]        # any length
    missing = rng.random(labels.shape) < 0.2
    v[missing] = 0.0
    with caplog.at_level(logging.WARNING):
        model = model_from_labels(labels, [0.1, 0.1, 0.3], fibers=v, fiber_fallback="muscle_mean")
    miss = missing[tuple(model.ijk.T)]
    assert f"{int(missing.sum())} of {labels.size} nodes" in caplog.text
    fill = model.fiber[miss]
    assert np.allclose(fill, fill[0])
    angle = np.degrees(np.arccos(abs(fill[0] @ d)))
    assert angle < 1.0, angle
    assert fill[0, 2] >= 0                                             # canonical sign
    # nodes with a vector keep it (unit, canonical sign)
    own = v[tuple(model.ijk[~miss].T)]
    own = own / np.linalg.norm(own, axis=1, keepdims=True) * np.sign(own[:, 2:3])
    np.testing.assert_allclose(model.fiber[~miss], own, atol=1e-12)


def test_principal_directions_sign_invariant():
    rng = np.random.default_rng(2)
    dirs = rng.standard_normal((3, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    g = rng.integers(0, 3, 300)
    v = dirs[g] * rng.choice([-1, 1], size=(300, 1))
    got, counts = principal_directions(v, g, 4)
    np.testing.assert_allclose(np.abs(np.sum(got[:3] * dirs, axis=1)), 1.0, atol=1e-12)
    assert counts[3] == 0 and not got[3].any()


def test_unknown_labels_and_bad_maps():
    labels = np.array([0, 1, 7, 7, 12]).reshape(5, 1, 1)
    with pytest.raises(InputError, match=r"values 7 \(2 voxels\), 12 \(1 voxels\) are not in the tissue map"):
        model_from_labels(labels, [1, 1, 1])
    with pytest.raises(InputError, match="did you mean 'muscle'"):
        parse_tissue_map({1: "muscel"})
    with pytest.raises(InputError, match=r"tissue_map\[2\]\.fiber"):
        parse_tissue_map({2: {"muscle": "a", "fiber": [0, 0, 0]}})
    with pytest.raises(InputError, match="no voxel of a node tissue"):
        model_from_labels(np.zeros((2, 2, 2), int), [1, 1, 1])
    with pytest.raises(InputError, match="expected shape"):
        model_from_labels(np.ones((2, 2, 2), int), [1, 1, 1], fibers=np.ones((2, 2, 3, 3)))
    with pytest.raises(InputError, match="unknown muscle 'soleus'"):
        model_from_labels(np.ones((2, 2, 2), int), [1, 1, 1], muscle_fibers={"soleus": [0, 0, 1]})


def test_muscle_id_volume_with_names_and_masks(caplog):
    labels = np.ones((4, 4, 2), np.int16)
    labels[0] = 3
    mid = np.zeros_like(labels)
    mid[1:3] = 1
    mid[3, :2] = 2
    fib = np.zeros(labels.shape + (3,))
    fib[..., 2] = -1.0
    mask = np.zeros(labels.shape, bool)
    mask[:, :, 1] = True
    with caplog.at_level(logging.WARNING):
        model = model_from_labels(labels, [1, 1, 1], fibers=fib, muscle_ids=mid, muscle_names=["a", "b"],
                                  masks={"top": mask})
    assert model.muscle_names == ["a", "b", "unassigned"]
    assert "4 muscle voxels have muscle_id 0" in caplog.text
    expect = np.where(labels[tuple(model.ijk.T)] == 1, np.where(mid[tuple(model.ijk.T)] == 0, 3, mid[tuple(model.ijk.T)]), 0)
    np.testing.assert_array_equal(model.muscle_id, expect)
    np.testing.assert_allclose(model.fiber[model.tissue == 1], np.tile([0, 0, 1.0], ((model.tissue == 1).sum(), 1)))
    np.testing.assert_array_equal(model.sets["top"], np.flatnonzero(model.ijk[:, 2] == 1))
    with pytest.raises(InputError, match="may only name tissues"):
        model_from_labels(labels, [1, 1, 1], muscle_ids=mid, muscle_names=["a", "b"],
                          tissue_map={1: {"muscle": "x"}, 3: "fat"})


# ------------------------------------------------------------------------------------------ config
def test_config_validation(tmp_path):
    lab = tmp_path / "labels.nii.gz"
    lab.write_bytes(b"")
    cfg = parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "tissue_map": {1: {"muscle": "sol"}, 0: "background"},
                                           "fiber_fallback": "muscle_mean"}, "build_model", tmp_path)
    assert cfg.labels == lab and cfg.require_input() == lab
    both = parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "segmentation": "labels.nii.gz"}, "build_model", tmp_path)
    assert both.require_input() == lab           # a corrected label map with the segmentation it corrects
    with pytest.raises(InputError, match="not both"):
        parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "tissue_map": {1: "muscle"},
                                         "label_names": {"a": "fat"}}, "build_model", tmp_path)
    with pytest.raises(InputError, match="file not found"):
        parse_section(BuildModelConfig, {"segmentation": "nope.h5"}, "build_model", tmp_path)
    with pytest.raises(InputError, match=r"build_model.tissue_map\[1\]: unknown tissue 'bon'"):
        parse_section(BuildModelConfig, {"tissue_map": {1: "bon"}}, "build_model", tmp_path)
    with pytest.raises(InputError, match="build_model.muscle_fibers.sol"):
        parse_section(BuildModelConfig, {"muscle_fibers": {"sol": [1, 2]}}, "build_model", tmp_path)
    with pytest.raises(InputError, match="build_model.fiber_fallback"):
        parse_section(BuildModelConfig, {"fiber_fallback": "mean"}, "build_model", tmp_path)
    with pytest.raises(InputError, match="no input"):
        parse_section(BuildModelConfig, {}, "build_model", tmp_path).require_input()
    assert parse_section(CoarsenConfig, None, "coarsen", tmp_path).factor == 2
    with pytest.raises(InputError, match="coarsen.factor"):
        parse_section(CoarsenConfig, {"factor": 0}, "coarsen", tmp_path)


# ------------------------------------------------------------------------------------------ stages
def write_nifti(path, data, affine_mm):
    img = nib.Nifti1Image(data, affine_mm)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(path))
    return path


def test_stage_nifti_round_trip(tmp_path):
    from pixmuscle.io.model import load_model
    from pixmuscle.stages.build_model import run_build_model
    from pixmuscle.store import read_meta

    labels = random_labels(seed=4)
    write_nifti(tmp_path / "labels.nii.gz", labels, AFFINE_MM)
    mask = np.zeros(labels.shape, np.uint8)
    mask[:, :, -1] = 1                                      # last stored slice = highest z
    write_nifti(tmp_path / "top.nii.gz", mask, AFFINE_MM)
    cfg = parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "muscle_fibers": {"muscle": [0, 1, 1]},
                                           "masks": {"top": "top.nii.gz"}}, "build_model", tmp_path)
    out = run_build_model(cfg, tmp_path / "out" / "model.h5")
    model = load_model(out)
    is_node = np.isin(labels, NODE_TISSUES)
    assert model.n_nodes == is_node.sum()
    np.testing.assert_allclose(sort_rows(model.X), sort_rows(apply_affine(AFFINE_MM, np.argwhere(is_node)) / 10), atol=1e-6)
    np.testing.assert_allclose(model.spacing, [0.08, 0.08, 0.4], rtol=1e-6)
    np.testing.assert_array_equal(model.sets["top"], model.sets["z_max"])
    meta = read_meta(out)
    assert meta["schema"] == "pixmuscle.model"
    assert str(tmp_path / "labels.nii.gz") in meta["provenance"]["inputs"]
    assert "muscle_fibers" in meta["config"]


def test_stage_fibre_grid_mismatch(tmp_path):
    from pixmuscle.stages.build_model import run_build_model

    labels = random_labels(seed=4)
    write_nifti(tmp_path / "labels.nii.gz", labels, AFFINE_MM)
    write_nifti(tmp_path / "fib.nii.gz", np.ones((*labels.shape[:2], 3, 3), np.float32), AFFINE_MM)
    cfg = parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "fibers": "fib.nii.gz"}, "build_model", tmp_path)
    with pytest.raises(InputError, match=r"fib\.nii\.gz is not on the label grid of .*labels\.nii\.gz: shape"):
        run_build_model(cfg, tmp_path / "model.h5")


def write_segmentation(path, labels, muscle_id, names, fiber, affine_cm):
    from pixmuscle.store import write_dataset, write_stage

    def fill(f):
        write_dataset(f, "labels", labels.astype(np.int16))
        write_dataset(f, "muscle_id", muscle_id.astype(np.int16))
        write_dataset(f, "muscle_names", np.array(names, dtype=str))
        write_dataset(f, "fiber", fiber.astype(np.float32))
        write_dataset(f, "affine", affine_cm, units="cm")

    return write_stage(path, schema="pixmuscle.segmentation", version=1, write=fill)


def test_stage_segmentation_round_trip_and_wrong_schema(tmp_path):
    from pixmuscle.io.model import load_model
    from pixmuscle.stages.build_model import run_build_model
    from pixmuscle.stages.coarsen import run_coarsen

    labels = np.ones((6, 5, 3), np.int16)
    labels[0] = 3
    labels[:, 0] = 4
    mid = np.where(labels == 1, 1, 0)
    mid[4:] = np.where(labels[4:] == 1, 2, 0)
    fib = np.zeros(labels.shape + (3,))
    fib[mid == 1] = [0, 0, 1]
    fib[mid == 2] = [0, 1, 1]
    aff = np.diag([0.1, 0.1, 0.5, 1.0])
    seg = write_segmentation(tmp_path / "segmentation.h5", labels, mid, ["soleus", "tibialis"], fib, aff)
    cfg = parse_section(BuildModelConfig, {"segmentation": str(seg)}, "build_model", tmp_path)
    model = load_model(run_build_model(cfg, tmp_path / "model.h5"))
    assert model.muscle_names == ["soleus", "tibialis"]
    np.testing.assert_array_equal(model.muscle_id, mid[tuple(model.ijk.T)])
    np.testing.assert_allclose(model.fiber[model.muscle_id == 2], np.tile([0, 1, 1] / np.sqrt(2), ((model.muscle_id == 2).sum(), 1)))
    np.testing.assert_array_equal(sort_rows(model.bone_ijk), sort_rows(np.argwhere(labels == 4)))
    np.testing.assert_array_equal(model.sets["bone_surface"], np.flatnonzero(model.ijk[:, 1] == 1))  # j = 1 row
    # coarsen stage on the file
    coarse = load_model(run_coarsen(tmp_path / "model.h5", 2, tmp_path / "model_coarse.h5"))
    assert coarse.coarsen_factor == 2
    np.testing.assert_allclose(coarse.spacing, [0.2, 0.2, 0.5])
    # a model file given as segmentation: wrong schema
    bad = parse_section(BuildModelConfig, {"segmentation": str(tmp_path / "model.h5")}, "build_model", tmp_path)
    with pytest.raises(SchemaError, match="schema 'pixmuscle.model' v1, expected 'pixmuscle.segmentation' v1"):
        run_build_model(bad, tmp_path / "x.h5")
    plain = tmp_path / "plain.h5"
    with h5py.File(plain, "w") as f:
        f["labels"] = labels
    bad = parse_section(BuildModelConfig, {"segmentation": str(plain)}, "build_model", tmp_path)
    with pytest.raises(SchemaError, match="not a pixmuscle stage file"):
        run_build_model(bad, tmp_path / "x.h5")
    with pytest.raises(SchemaError, match="expected 'pixmuscle.model' v1"):
        run_coarsen(seg, 2, tmp_path / "y.h5")


@pytest.mark.parametrize("components", ["world", "voxel"])
def test_stage_fibre_image_components(tmp_path, components):
    from pixmuscle.io.model import load_model
    from pixmuscle.stages.build_model import run_build_model

    labels = np.ones((4, 3, 2), np.int16)
    v = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    write_nifti(tmp_path / "labels.nii.gz", labels, AFFINE_MM)
    write_nifti(tmp_path / "fib.nii.gz", np.tile(v, (*labels.shape, 1)).astype(np.float32), AFFINE_MM)
    cfg = parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "fibers": "fib.nii.gz",
                                           "fiber_components": components}, "build_model", tmp_path)
    model = load_model(run_build_model(cfg, tmp_path / "model.h5"))
    # world components are kept; voxel components are along the stored axes, whose x is flipped
    expect = v if components == "world" else np.array([-1.0, 0.0, 1.0]) / np.sqrt(2)
    np.testing.assert_allclose(model.fiber, np.tile(expect, (model.n_nodes, 1)), atol=1e-6)


def test_stage_fibre_affine_mismatch(tmp_path):
    from pixmuscle.stages.build_model import run_build_model

    labels = np.ones((4, 3, 2), np.int16)
    write_nifti(tmp_path / "labels.nii.gz", labels, AFFINE_MM)
    shifted = AFFINE_MM.copy()
    shifted[0, 3] += 1.0
    write_nifti(tmp_path / "fib.nii.gz", np.ones((4, 3, 2, 3), np.float32), shifted)
    cfg = parse_section(BuildModelConfig, {"labels": "labels.nii.gz", "fibers": "fib.nii.gz"}, "build_model", tmp_path)
    with pytest.raises(InputError, match="voxel → cm affine"):
        run_build_model(cfg, tmp_path / "model.h5")
