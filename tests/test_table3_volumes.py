"""Table 3 volumes (IMAT, IMCT without the aponeurosis) against the MG phantom's truth, at the
paper's two resolutions: the fine model (0.078 cm, one node per pixel) and the coarse model
(every second pixel, 0.156 cm), built and coarsened by the pipeline's own functions."""

from __future__ import annotations

import numpy as np
import pytest

from pixmuscle.model.build import model_from_labels
from pixmuscle.model.coarsen import coarsen_model
from pixmuscle.report.tables import tissue_table
from pixmuscle.synth.mg import make_mg_phantom, tissue_volumes


def _volumes(model, with_aponeurosis=True):
    apo = None
    if with_aponeurosis:
        apo = np.zeros(model.n_nodes, bool)
        apo[model.sets["aponeurosis"]] = True
    t = tissue_table(model.ijk, model.tissue, model.muscle_id, model.shape, model.spacing, model.muscle_names,
                     aponeurosis=apo)
    return t["volumes_cm3"]


@pytest.fixture(scope="module", params=["young", "old"])
def models(request):
    ph = make_mg_phantom(request.param, shape=(96, 64, 4), seed=3, supersample=2, supersample_z=1)
    fine = model_from_labels(ph.labels, ph.affine, tissue_map={0: "background", 1: "muscle", 2: "connective_tissue",
                                                               3: "fat", 4: "bone"},
                             fibers=ph.fiber_true, masks={"aponeurosis": ph.outer_ct_mask},
                             muscle_ids=ph.muscle_id, muscle_names=ph.muscle_names)
    return tissue_volumes(ph), fine, coarsen_model(fine, 2)


def test_imat_and_imct_match_the_phantom_truth_at_two_resolutions(models):
    truth, fine, coarse = models
    for model in (fine, coarse):
        v = _volumes(model)
        assert v["imat"] == pytest.approx(truth["imat"], rel=0.05)
        assert v["imct"] == pytest.approx(truth["imct"], rel=0.05)
        assert v["muscle"] == pytest.approx(truth["muscle"], rel=0.05)
    assert _volumes(fine)["imct"] == pytest.approx(truth["imct"], rel=1e-12)  # one node per pixel: exact
    assert _volumes(fine)["imat"] == pytest.approx(truth["imat"], rel=1e-12)


def test_without_the_aponeurosis_mask_the_aponeurosis_counts_as_imct(models):
    truth, fine, _ = models
    v = _volumes(fine, with_aponeurosis=False)
    assert v["imct"] > 1.5 * truth["imct"]
    assert v["imat"] == pytest.approx(truth["imat"], rel=1e-12)  # the IMAT rule does not need the mask


def test_aponeurosis_mask_travels_from_segment_to_the_report(tmp_path):
    """segment.aponeurosis_mask → segmentation.h5 /masks/aponeurosis → node set 'aponeurosis' →
    IMCT of the tissue table without it (checked against the mask itself, node by node)."""
    import h5py
    import yaml
    from fixtures_results import write_mg_phantom

    from pixmuscle.io.model import load_model
    from pixmuscle.pipeline import run_pipeline
    from pixmuscle.report.tables import tissue_classes

    d, seed = write_mg_phantom(tmp_path / "data")
    cfg = {"synthetic": True, "output_dir": "out", "models": ["fine"],
           "segment": {"mri": str(d / "mg_mri.nii.gz"), "dti_tensor": str(d / "mg_dti_tensor.nii.gz"),
                       "imct_mask": str(d / "mg_imct.nii.gz"), "imat_mask": str(d / "mg_imat.nii.gz"),
                       "aponeurosis_mask": str(d / "mg_aponeurosis.nii.gz"),
                       "seeds": {"medial_gastrocnemius": [seed]}}, "build_model": {}}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    assert run_pipeline(tmp_path / "c.yaml", until="build-model")
    with h5py.File(tmp_path / "out" / "segmentation.h5", "r") as f:
        seg_apo = f["masks/aponeurosis"][()] != 0
        labels = f["labels"][()]
    assert seg_apo.any() and np.all(labels[seg_apo] == 2)
    m = load_model(tmp_path / "out" / "model.h5")
    in_set = np.zeros(m.n_nodes, bool)
    in_set[m.sets["aponeurosis"]] = True
    np.testing.assert_array_equal(in_set, seg_apo[tuple(np.asarray(m.ijk).T)])  # same grid, no reorientation
    c = tissue_classes(m.ijk, m.tissue, m.muscle_id, m.shape, spacing=m.spacing, aponeurosis=in_set)
    assert not (c["imct"] & in_set).any() and c["imct"].sum() + c["aponeurosis"].sum() + c["skin"].sum() == (m.tissue == 2).sum()
