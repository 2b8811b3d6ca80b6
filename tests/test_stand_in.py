"""The multigrid's filtered stand-in of the tangent: positive definite by construction (its factors cut
near their cells, :func:`pixmuscle.mechanics.assembly.local_rows`), where leaving out far node pairs
of the full stiffness is not."""

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from pixmuscle.mechanics.assembly import local_operator, local_rows
from pixmuscle.mechanics.solve import build_system
from pixmuscle.verify.mechanics import _cfg, mask_model

CLAMPED = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]


def test_local_rows_keep_row_sums_and_only_near_nodes():
    rng = np.random.default_rng(0)
    ijk = np.argwhere(np.ones((6, 6, 4), bool))
    n = len(ijk)
    own = rng.integers(0, n, 40)
    rows = np.repeat(np.arange(40), 25)
    cols = np.concatenate([np.r_[o, rng.choice(np.delete(np.arange(n), o), 24, replace=False)] for o in own])
    vals = rng.standard_normal((rows.size, 3))
    cut = local_rows(rows, cols, vals, own, ijk, 1)
    for r in range(40):
        sel = rows == r
        np.testing.assert_allclose(cut[sel].sum(axis=0), vals[sel].sum(axis=0), atol=1e-12)
    far = np.abs(ijk[own[rows]] - ijk[cols]).max(axis=1) > 1
    assert far.any() and np.all(cut[far] == 0.0)
    np.testing.assert_array_equal(cut[~far & (cols != own[rows])], vals[~far & (cols != own[rows])])
    M = sp.csr_matrix((vals[:, 0], (rows, cols)), shape=(40, n))
    Mc = local_operator(M, own, ijk, 1)
    np.testing.assert_allclose(np.asarray(Mc.sum(axis=1)).ravel(), np.asarray(M.sum(axis=1)).ravel(), atol=1e-12)


def test_filtered_stand_in_is_positive_definite_where_dropping_far_pairs_is_not():
    """On pixels 6.4 times finer in-plane than the slices, the full stiffness with its node pairs more
    than 2 voxels apart left out has negative eigenvalues; the stand-in within the same pattern does
    not, and it is spectrally close to the full stiffness (K v = λ S v with λ in [0.3, 8])."""
    mask = np.ones((9, 9, 6), bool)
    mask[6:, 6:, :] = False
    model = mask_model(mask, (0.078, 0.078, 0.5), tissue=2)
    cfg = _cfg(boundary_conditions=CLAMPED, volumetric={"method": "projected", "patch": [2, 2, 3]})
    system = build_system(model, cfg)[0]
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.0)
    stand_in = system.preconditioner_matrix(state, 2, volumetric="held")
    full = system.preconditioner_matrix(state, None, volumetric="held").tocoo()
    ijk = np.asarray(model.ijk)
    near = np.abs(ijk[full.row // 3] - ijk[full.col // 3]).max(axis=1) <= 2
    dropped = sp.coo_matrix((full.data[near], (full.row[near], full.col[near])), shape=full.shape)
    assert stand_in.nnz < np.count_nonzero(near)  # within the same pattern, thinner
    rows = np.repeat(np.arange(model.n_nodes), np.diff(stand_in.indptr))
    assert np.abs(ijk[rows] - ijk[stand_in.indices]).max() <= 2
    assert np.linalg.eigvalsh(dropped.toarray())[0] < 0.0
    assert np.linalg.eigvalsh(stand_in.toarray())[0] > 0.0
    lam = scipy.linalg.eigh(full.toarray(), stand_in.toarray(), eigvals_only=True)
    assert 0.3 < lam[0] and lam[-1] < 8.0
