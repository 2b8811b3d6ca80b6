"""The multigrid's filtered stand-in of the tangent: positive definite by construction (its factors cut
near their cells, :func:`pixmuscle.mechanics.assembly.local_rows`), where leaving out far node pairs
of the full stiffness is not."""

import numpy as np
import scipy.linalg
import scipy.sparse as sp

from pixmuscle.mechanics.assembly import local_operator, local_rows, local_rows_csr
from pixmuscle.mechanics.solve import build_system
from pixmuscle.verify.mechanics import _cfg, mask_model

CLAMPED = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]


def _l_shaped_leg(shape, corner, spacing):
    """An L-shaped block of connective tissue (the corner from ``corner`` on cut out of x and y),
    clamped at both ends, with the projected volumetric energy: (model, cfg, system, state at rest)."""
    mask = np.ones(shape, bool)
    mask[corner:, corner:, :] = False
    model = mask_model(mask, spacing, tissue=2)
    cfg = _cfg(boundary_conditions=CLAMPED, volumetric={"method": "projected", "patch": [2, 2, 3]})
    system = build_system(model, cfg)[0]
    return model, cfg, system, system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.0)


def test_local_rows_keep_row_sums_and_first_moments_on_near_nodes_only():
    """Each cut row acts on every linear field as the whole row does, and holds no far entry; a row
    with nothing to cut is left as it was."""
    rng = np.random.default_rng(0)
    shape = (8, 8, 6)
    ijk = np.argwhere(np.ones(shape, bool))
    n = len(ijk)
    index = lambda p: np.ravel_multi_index(tuple(np.asarray(p).T), shape)  # noqa: E731
    inner = np.flatnonzero(np.all((ijk >= 1) & (ijk <= np.array(shape) - 2), axis=1))
    own = rng.choice(inner, 30, replace=False)
    box = np.argwhere(np.ones((3, 3, 3), bool)) - 1
    cols, rows = [], []
    for r, o in enumerate(own):
        near = index(ijk[o] + box)
        far = rng.choice(np.setdiff1d(np.arange(n), near), 0 if r == 0 else 12, replace=False)
        cols.append(np.r_[near, far])
        rows.append(np.full(len(near) + len(far), r))
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    vals = rng.standard_normal((rows.size, 3))
    cut = local_rows(rows, cols, vals, own, ijk, 1)
    far = np.abs(ijk[own[rows]] - ijk[cols]).max(axis=1) > 1
    assert far.any() and np.all(cut[far] == 0.0)
    np.testing.assert_array_equal(cut[rows == 0], vals[rows == 0])
    for lin in (np.ones(n), *ijk.T.astype(float)):  # a constant and the three linear fields
        before = np.zeros((len(own), 3))
        after = np.zeros((len(own), 3))
        np.add.at(before, rows, vals * lin[cols, None])
        np.add.at(after, rows, cut * lin[cols, None])
        np.testing.assert_allclose(after, before, atol=1e-11)
    M = sp.csr_matrix((vals[:, 0], (rows, cols)), shape=(len(own), n))
    Mc = local_operator(M, own, ijk, 1)
    np.testing.assert_allclose(Mc @ ijk[:, 2].astype(float), M @ ijk[:, 2].astype(float), atol=1e-11)
    np.testing.assert_allclose(np.asarray(Mc.sum(axis=1)).ravel(), np.asarray(M.sum(axis=1)).ravel(), atol=1e-12)



def test_rows_cut_a_few_at_a_time_are_cut_as_all_at_once():
    rng = np.random.default_rng(1)
    ijk = np.argwhere(np.ones((6, 6, 5), bool))
    n = len(ijk)
    counts = rng.integers(5, 40, n)
    ptr = np.r_[0, np.cumsum(counts)]
    cols = np.concatenate([np.r_[r, rng.choice(np.delete(np.arange(n), r), c - 1, replace=False)]
                           for r, c in enumerate(counts)])
    vals = rng.standard_normal((cols.size, 3))
    rows = np.repeat(np.arange(n), counts)
    whole = local_rows(rows, cols, vals, np.arange(n), ijk, 1, tol=0.1)
    for chunk in (1, 50, 1000, 10**9):
        np.testing.assert_array_equal(local_rows_csr(ptr, cols, vals, ijk, 1, tol=0.1, chunk=chunk), whole)


def test_filtered_stand_in_is_positive_definite_where_dropping_far_pairs_is_not():
    """On pixels 6.4 times finer in-plane than the slices, the full stiffness with its node pairs more
    than 2 voxels apart left out has negative eigenvalues; the stand-in within the same pattern does
    not, and it is spectrally close to the full stiffness: K v = λ S v with λ in [0.32, 2.5], a ratio
    of 7.9 (15.6, [0.40, 6.2], when the cut rows kept only their sums, not their first moments)."""
    model, cfg, system, state = _l_shaped_leg((9, 9, 6), 6, (0.078, 0.078, 0.5))
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
    assert 0.25 < lam[0] and lam[-1] < 3.0 and lam[-1] / lam[0] < 10.0


def test_stand_in_filled_by_blocks_of_cells_is_the_one_filled_at_once(monkeypatch):
    """The stand-in, its pattern and a region's block made one block of cells at a time (the
    gradients of each block only, :meth:`MechanicalSystem._support_gradients` with ``cells``) equal
    what the whole support layout's gradients give: the same pattern, and values equal to round-off
    (the blocks add the cells in the same order)."""
    from pixmuscle.mechanics import assembly
    from pixmuscle.mechanics.rows import RowAssembler

    model, cfg, system, state = _l_shaped_leg((7, 6, 5), 4, (0.1, 0.1, 0.25))
    S = system.support
    whole = system._support_gradients()
    cells = np.array([5, 0, 17, 3])  # any cells, in any order: their rows one after the other
    rows = np.concatenate([np.arange(S.indptr[c], S.indptr[c + 1]) for c in cells])
    np.testing.assert_array_equal(system._support_gradients(cells), whole[rows])
    np.testing.assert_array_equal(system._support_gradients((4, 9)), whole[S.indptr[4]:S.indptr[9]])
    nodes = np.arange(0, model.n_nodes, 3)
    once = system.preconditioner_matrix(state, 2, volumetric="held")
    block_once = RowAssembler(system, nodes, square=True).block(state, pressure_free=True)
    fresh = build_system(model, cfg)[0]
    monkeypatch.setattr(assembly, "FILL_BLOCK", 97)  # many blocks of a few cells
    assert len(fresh.assembler(2).cell_blocks()) > 20
    blocks = fresh.preconditioner_matrix(state, 2, volumetric="held")
    for a, b in ((once, blocks), (block_once, RowAssembler(fresh, nodes, square=True).block(state, pressure_free=True))):
        np.testing.assert_array_equal(a.indptr, b.indptr)
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_allclose(b.data, a.data, rtol=0, atol=1e-12 * np.abs(a.data).max())
