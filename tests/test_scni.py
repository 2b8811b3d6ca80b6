"""SCNI operators, NSNI stabilisation and tangent assembly: checks against analytic truths,
the divergence theorem and finite differences."""

import numpy as np
import pytest

from pixmuscle.config import parse_section
from pixmuscle.mechanics.assembly import Assembler, support_pattern
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.scni import build_scni, cell_faces, face_incidence, neighbour_index, support_radius
from pixmuscle.mechanics.solve import build_system
from pixmuscle.mechanics.stabilization import gradient_differences, second_moments
from pixmuscle.model.tissues import CONNECTIVE_TISSUE, FAT, MUSCLE
from pixmuscle.verify.mechanics import irregular_mask, linear_stiffness, mask_model, patch_test, stabilization_check


@pytest.fixture(scope="module")
def lshape():
    return mask_model(irregular_mask(), (0.1, 0.12, 0.25))


def test_neighbour_index_and_faces_tile_cells(lshape):
    m = lshape
    up = neighbour_index(m.ijk, (1, 0, 0))
    has = up >= 0
    assert np.all(m.ijk[up[has]] - m.ijk[has] == [1, 0, 0])
    mask = irregular_mask()
    expect_missing = (~np.pad(mask, ((0, 1), (0, 0), (0, 0)))[1:])[tuple(m.ijk.T)]
    assert np.array_equal(~has, expect_missing)
    f = cell_faces(m.X, m.ijk, m.spacing)
    n = m.n_nodes
    # every cell has exactly one face per side and axis, interior faces are shared by two cells
    assert f.plus.shape == (3, n) and f.minus.shape == (3, n)
    for k in range(3):
        assert np.all(f.low[f.plus[k]] == np.arange(n))
        assert np.all(f.high[f.minus[k]] == np.arange(n))
        assert np.allclose(f.centre[f.plus[k]] - m.X, np.eye(3)[k] * m.spacing[k] / 2)
    n_bnd = int(f.boundary.sum())
    assert len(f.axis) == (6 * n + n_bnd) // 2
    # the boundary of the voxel body: total boundary-face area per axis equals twice the projected area
    for k in range(3):
        proj = mask.any(axis=k).sum() * np.prod(m.spacing) / m.spacing[k]
        on = f.boundary & (f.axis == k)
        assert f.area[on].sum() >= 2 * proj - 1e-12
    # closed surface: Σ A n = 0 over the boundary faces
    sgn = f.normal_sign
    for k in range(3):
        on = f.boundary & (f.axis == k)
        assert abs(np.sum(f.area[on] * sgn[on])) < 1e-12


def test_linear_patch_test_irregular_domain():
    """Gradients of u = A X + c reproduce A; Dirichlet and traction patch tests reproduce u (L-shape with a cavity)."""
    for stab in ("nsni",):
        r = patch_test(stabilization=stab)
        assert r["n_free_dirichlet"] > 50
        assert r["gradient_error"] < 1e-10
        assert r["integration_error"] < 1e-10
        assert r["dirichlet_error"] < 1e-8
        assert r["traction_error"] < 1e-8


def test_smoothed_gradient_is_cell_average_of_rk_gradient():
    """For u = x² the smoothed gradient is (u(face+) − u(face−))/h of the RK interpolant: compare with
    the exact cell average of ∂u^h/∂x computed by 1-D Gauss quadrature of the RK derivative."""
    from pixmuscle.rk import shape_functions

    m = mask_model(np.ones((5, 4, 4), bool), (0.1, 0.1, 0.2))
    sup = support_radius(m.spacing, (1.65, 1.65, 1.65))
    s = build_scni(m.X, m.ijk, m.spacing, sup)
    d = m.X[:, 0] ** 2 + 0.3 * m.X[:, 1] * m.X[:, 2]
    L = 7  # an interior-ish cell
    xg, wg = np.polynomial.legendre.leggauss(6)
    pts = []
    wts = []
    for a, wa in zip(xg, wg, strict=True):
        for b, wb in zip(xg, wg, strict=True):
            for c, wc in zip(xg, wg, strict=True):
                pts.append(m.X[L] + 0.5 * m.spacing * np.array([a, b, c]))
                wts.append(wa * wb * wc / 8)
    _, grads = shape_functions(m.X, np.array(pts), sup, gradient=True)
    for k in range(3):
        avg = float(np.dot(wts, grads[k] @ d))
        # the RK interpolant is C2 in the cell (cubic B-spline kernel): Gauss converges to the exact
        # average, and the divergence theorem on the box with face-centre values is exact only for
        # linear fields, so compare with a tolerance of the face-quadrature error O(h²)
        assert abs((s.G[k] @ d)[L] - avg) < 2e-3 * max(1.0, abs(avg))


def _mixed_model():
    m = mask_model(np.ones((4, 3, 5), bool), (0.15, 0.2, 0.3), tissue=MUSCLE, fiber=(0.3, 0.2, 0.9))
    rng = np.random.default_rng(3)
    m.tissue[:] = rng.choice([MUSCLE, CONNECTIVE_TISSUE, FAT], m.n_nodes)
    m.fiber[m.tissue != MUSCLE] = 0.0
    m.muscle_id[:] = (m.tissue == MUSCLE).astype(np.int16)
    return m


def test_internal_force_and_tangent_match_finite_differences():
    """f_int (eq. 19) is the gradient of the discrete energy and K (eq. 18) the Jacobian of the residual."""
    m = _mixed_model()
    cfg = parse_section(SolveConfig, {"boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                                              {"nodes": "z_max", "displace": {"z": 0.1}}]}, "solve")
    system, _ = build_system(m, cfg)
    rng = np.random.default_rng(0)
    d = 0.01 * rng.standard_normal((m.n_nodes, 3))
    t, alpha = 0.7, 0.6
    st = system.evaluate(d, t, alpha)
    K = system.stiffness(st).toarray()
    assert np.abs(K - K.T).max() < 1e-9 * np.abs(K).max()
    v = rng.standard_normal(d.shape)
    eps = 1e-6
    rp = system.evaluate(d + eps * v, t, alpha)
    rm = system.evaluate(d - eps * v, t, alpha)
    fd = -(rp.r - rm.r).ravel() / (2 * eps)
    assert np.linalg.norm(K @ v.ravel() - fd) < 1e-6 * np.linalg.norm(fd)
    # residual = −∂Π/∂d (energy includes material, stabilisation and penalty terms)
    dE = (system.energy(rp) - system.energy(rm)) / (2 * eps)
    assert abs(dE + np.vdot(st.r, v)) < 1e-6 * abs(dE)


def test_deformation_gradient_exact_for_homogeneous_map():
    m = mask_model(irregular_mask(8, 5), (0.1, 0.1, 0.3))
    sup = support_radius(m.spacing, (1.65, 1.65, 1.65))
    s = build_scni(m.X, m.ijk, m.spacing, sup)
    F0 = np.array([[1.1, 0.2, -0.05], [0.03, 0.95, 0.1], [0.0, -0.2, 1.3]])
    F = s.deformation_gradient(m.X @ (F0 - np.eye(3)).T)
    assert np.abs(F - F0).max() < 1e-12
    # uniform P: internal forces vanish on nodes whose support misses the boundary, and sum to zero
    P = np.broadcast_to(np.arange(9.0).reshape(3, 3), (m.n_nodes, 3, 3))
    f = s.internal_force(np.ascontiguousarray(P))
    assert np.abs(f.sum(axis=0)).max() < 1e-10 * np.abs(f).max()


def test_stabilization_zero_modes_and_hourglass():
    r = stabilization_check(free_shape=(4, 4, 5), clamped_n=9, n_modes=3)
    # exactly the six rigid-body modes with NSNI; on these small free blocks plain SCNI also has six
    # (the boundary cells break the symmetry that makes oscillating modes energy-free)
    assert r["free_zero_modes_nsni"] == 6
    assert r["free_zero_modes_none"] == 6
    # interior cells: SCNI's smoothed gradient cannot see the (−1)^(i+j+k) field, NSNI's term can
    assert r["checker_interior_gradient"] < 1e-10
    assert r["checker_interior_nsni"] > 1.0
    # clamped block: the lowest modes are oscillating (spurious) without stabilisation, and NSNI
    # raises the lowest eigenvalue by a large factor (on larger blocks the lowest NSNI modes are
    # smooth: see verify_mechanics, 12³ nodes)
    assert min(r["clamped_oscillation_none"]) > 1.5
    assert r["clamped_eigenvalues_nsni"][0] > 3 * r["clamped_eigenvalues_none"][0]


def test_stabilization_vanishes_for_linear_fields():
    m = mask_model(irregular_mask(8, 5), (0.1, 0.1, 0.3))
    K0, _ = linear_stiffness(m, stabilization="none")
    K1, scni = linear_stiffness(m, stabilization="nsni")
    Ks = K1 - K0
    rng = np.random.default_rng(1)
    A = rng.standard_normal((3, 3))
    u = (m.X @ A.T + rng.standard_normal(3)).ravel()
    assert np.abs(Ks @ u).max() < 1e-9 * abs(Ks).max() * np.abs(u).max()
    # exact ∂²u/∂x² = 2 for u = x² at cells whose face supports see a complete uniform neighbourhood
    box = mask_model(np.ones((9, 8, 8), bool), (0.1, 0.1, 0.3))
    _, sbox = linear_stiffness(box, stabilization="none")
    H = gradient_differences(sbox)
    ijk = box.ijk
    inner = np.all((ijk >= 3) & (ijk <= ijk.max(axis=0) - 3), axis=1)
    assert inner.sum() > 0
    x2 = box.X[:, 0] ** 2
    assert np.allclose((H[0][0] @ x2)[inner], 2.0, rtol=1e-9)
    assert np.allclose((H[1][0] @ x2)[inner], 0.0, atol=1e-9)
    M = second_moments(scni.volume, m.spacing)
    assert np.allclose(M, np.prod(m.spacing) * m.spacing ** 2 / 12)


def test_assembler_matches_sparse_product():
    """The compiled fill equals Σ_L V_L B̃_Lᵀ A_L B̃_L built with scipy sparse products."""
    import scipy.sparse as sp

    m = mask_model(irregular_mask(8, 5), (0.1, 0.1, 0.2))
    sup = support_radius(m.spacing, (1.65, 1.65, 1.65))
    s = build_scni(m.X, m.ijk, m.spacing, sup)
    asm = Assembler(support_pattern(face_incidence(s.faces, s.volume), s.psi_faces))
    rng = np.random.default_rng(2)
    A = rng.standard_normal((m.n_nodes, 3, 3, 3, 3))
    K = asm.matrix(asm.fill(asm.on_support(s.G), A, s.volume)).toarray()
    n = m.n_nodes
    # B: rows (L, i, J) → value G_J[L, I] at column 3I + i
    rows, cols, vals = [], [], []
    for J in range(3):
        C = s.G[J].tocoo()
        for i in range(3):
            rows.append(C.row * 9 + 3 * i + J)
            cols.append(3 * C.col + i)
            vals.append(C.data)
    B = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(9 * n, 3 * n))
    D = sp.block_diag([s.volume[L] * A[L].reshape(9, 9) for L in range(n)])
    K_ref = (B.T @ D @ B).toarray()
    assert np.allclose(K, K_ref, atol=1e-10 * np.abs(K_ref).max())


def test_end_faces_by_the_vertex_rule_keep_the_patch_test_and_equal_the_penalty_rows():
    """End faces held at their vertices (``penalty.at`` auto / vertices) are integrated by SCNI with the
    same trapezoidal rule: their face value is the mean of Ψ at the four vertices (checked against Ψ
    evaluated here), the smoothed gradient still reproduces a homogeneous map exactly, and the boundary
    rows of an end, Σ_f A_f Ψ̄(f), equal the penalty rows Σ_c w_c Ψ(x_c) of its constraint points, an
    independent enumeration (:func:`pixmuscle.mechanics.boundary.face_vertices`). With the centre rule
    on those faces they differ (here by up to 17 % of the largest row): a homogeneous stretch is then
    reproduced only to ~0.5 %, whatever β."""
    from pixmuscle.mechanics.boundary import build_constraints, vertex_rule_faces
    from pixmuscle.mechanics.solve import node_supports
    from pixmuscle.rk import shape_functions

    m = mask_model(irregular_mask(8, 5), (0.1, 0.12, 0.25))
    cfg = parse_section(SolveConfig, {"boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                                              {"nodes": "z_max", "fix": ["z"]}]}, "solve")
    bcs = cfg.boundary_conditions
    sup, _ = node_supports(m, cfg)                                       # covers the cell corners
    faces = cell_faces(m.X, m.ijk, m.spacing)
    vf = vertex_rule_faces(m, list(bcs), faces, at="auto")
    assert vf.size == 2 * np.unique(m.ijk[:, :2], axis=0).shape[0]       # every end face of both ends, once
    assert vertex_rule_faces(m, list(bcs), faces, at="centres").size == 0
    s = build_scni(m.X, m.ijk, m.spacing, sup, faces=faces, vertex_faces=vf, face_gradients=True)
    centre = build_scni(m.X, m.ijk, m.spacing, sup, face_gradients=True)
    f = vf[::7]
    h = np.asarray(m.spacing)
    corners = faces.centre[f][:, None, :] + np.array([[a, b, 0.0] for a in (-0.5, 0.5) for b in (-0.5, 0.5)]) * h
    psi, dpsi = shape_functions(m.X, corners.reshape(-1, 3), sup, gradient=True)
    np.testing.assert_allclose(s.psi_faces[f].toarray(), psi.toarray().reshape(len(f), 4, -1).mean(axis=1), atol=1e-14)
    np.testing.assert_allclose(s.dpsi_faces[1][f].toarray(), dpsi[1].toarray().reshape(len(f), 4, -1).mean(axis=1),
                               atol=1e-12)
    rest = np.setdiff1d(np.arange(len(faces.axis)), vf)
    assert abs(s.psi_faces[rest] - centre.psi_faces[rest]).max() == 0
    F0 = np.array([[1.1, 0.2, -0.05], [0.03, 0.95, 0.1], [0.0, -0.2, 1.3]])
    assert np.abs(s.deformation_gradient(m.X @ (F0 - np.eye(3)).T) - F0).max() < 1e-12
    con = build_constraints(m, list(bcs), faces, sup, 1.0, at="auto")
    for b, end in enumerate(("z_min", "z_max")):
        rows = con.psi[con.group == b].T @ con.weight[con.group == b]
        on = vf[(faces.axis[vf] == 2) & (faces.normal_sign[vf] == (-1 if end == "z_min" else 1))]
        np.testing.assert_allclose(s.psi_faces[on].T @ faces.area[on], rows, atol=1e-14)
        assert np.abs(centre.psi_faces[on].T @ faces.area[on] - rows).max() > 1e-3 * np.abs(rows).max()


@pytest.mark.parametrize("modulus", ["shear", "tangent"])
def test_constant_stiffness_product_equals_the_assembled_nsni_stiffness(modulus):
    """K_s V by :class:`ConstantStiffness` — the scalar operator L ⊗ I₃ for the shear modulus, the
    matrix-free product form for the full tangent — against the NSNI stiffness assembled block by
    block with the compiled fill (an independent path), with a random anisotropic reference tangent."""
    from pixmuscle.mechanics.stabilization import stabilization_operators, stabilization_stiffness
    from pixmuscle.mechanics.tangent import ConstantStiffness

    m = mask_model(irregular_mask(8, 5), (0.1, 0.12, 0.25))
    sup = support_radius(m.spacing, (1.65, 1.65, 1.65))
    s = build_scni(m.X, m.ijk, m.spacing, sup, face_gradients=True)
    asm = Assembler(support_pattern(face_incidence(s.faces, s.volume), s.psi_faces))
    rng = np.random.default_rng(3)
    A0 = rng.standard_normal((m.n_nodes, 9, 9))
    A0 = (A0 @ A0.transpose(0, 2, 1)).reshape(m.n_nodes, 3, 3, 3, 3)
    Ks = asm.matrix(stabilization_stiffness(s, asm, A0, coefficient=0.7, modulus=modulus)).tocsr()
    H, C = stabilization_operators(s, A0, coefficient=0.7, modulus=modulus)
    op = ConstantStiffness(H, C)
    assert op.scalar == (modulus == "shear")
    V = rng.standard_normal((m.n_nodes, 3))
    ref = (Ks @ V.ravel()).reshape(-1, 3)
    assert np.abs(op.apply(V) - ref).max() < 1e-12 * np.abs(ref).max()


def test_threaded_csr_product_is_the_serial_product_bit_for_bit():
    """Vectors on row blocks in a thread pool and three columns by the compiled row kernel give
    SciPy's serial product exactly, whatever the number of threads, with unequal rows (the blocks
    are cut by non-zeros)."""
    import numba
    import scipy.sparse as sp

    from pixmuscle.mechanics.threaded import ThreadedCSR

    rng = np.random.default_rng(4)
    n = 3000
    per_row = rng.integers(0, 200, n)
    rows = np.repeat(np.arange(n), per_row)
    A = sp.csr_matrix((rng.standard_normal(rows.size), (rows, rng.integers(0, n, rows.size))), shape=(n, n))
    x, X = rng.standard_normal(n), rng.standard_normal((n, 3))
    for threads in (2, 3, 7):
        T = ThreadedCSR(A, threads=threads)
        assert T.threads == threads
        assert np.array_equal(T @ x, A @ x)
        for _, _, blk in T._blocks:  # the row blocks hold no second copy of the matrix
            assert np.shares_memory(blk.data, A.data) and np.shares_memory(blk.indices, A.indices)
    saved = numba.get_num_threads()
    try:
        for k in sorted({1, saved}):
            numba.set_num_threads(k)
            assert np.array_equal(ThreadedCSR(A) @ X, A @ X)
            assert np.array_equal(ThreadedCSR(A) @ X[::2].repeat(2, axis=0), A @ X[::2].repeat(2, axis=0))
    finally:
        numba.set_num_threads(saved)
    assert ThreadedCSR(A[:10], threads=4).threads == 1  # too small to split


def test_unstored_operators_equal_the_stored_ones_whatever_the_threads():
    """Operators that store less than the matrix they apply — Bᵀ on B's arrays (:class:`TransposedCSR`),
    a symmetric matrix by its upper triangle (:class:`SymmetricCSR`: products, rows, the whole matrix),
    rows of a CSR matrix without their copy (:class:`RowSubset`), the SCNI gradients as row views of
    their stack — equal the stored matrices' products to 1e-13, bit for bit on one thread and on all."""
    import numba
    import scipy.sparse as sp

    from pixmuscle.mechanics.scni import StackedRows
    from pixmuscle.mechanics.tangent import RowSubset, SymmetricCSR, TransposedCSR

    rng = np.random.default_rng(5)
    n = 2000
    per_row = rng.integers(0, 120, n)
    rows = np.repeat(np.arange(n), per_row)
    A = sp.csr_matrix((rng.standard_normal(rows.size), (rows, rng.integers(0, n, rows.size))), shape=(n, n))
    L = (A + A.T + sp.identity(n)).tocsr()
    X, x = rng.standard_normal((n, 3)), rng.standard_normal(n)
    nodes = np.sort(rng.choice(n, 300, replace=False))
    S = SymmetricCSR(L)
    assert S.nnz < 0.6 * L.nnz and abs(S.matrix - L).max() == 0.0 and abs(S.rows_matrix(nodes)[nodes] - L[nodes]).max() == 0.0
    saved = numba.get_num_threads()
    got = []
    try:
        for k in sorted({1, saved}):
            numba.set_num_threads(k)
            out = [TransposedCSR(A) @ X, S @ X, S @ x, S.rows(nodes)(X), RowSubset(L, nodes) @ X, RowSubset(L, nodes) @ x]
            for y, ref in zip(out, [A.T @ X, L @ X, L @ x, L[nodes] @ X, L[nodes] @ X, L[nodes] @ x], strict=True):
                assert np.abs(y - ref).max() <= 1e-13 * np.abs(ref).max()
            got.append(out)
    finally:
        numba.set_num_threads(saved)
    assert all(np.array_equal(a, b) for a, b in zip(got[0], got[-1], strict=True))
    G = StackedRows([A[:700], A[700:], A[:5]])
    assert all(np.shares_memory(M.data, G.stacked.data) for M in G)
    assert abs(sp.vstack(list(G)) - G.stacked).max() == 0.0 and abs(G[1] - A[700:]).max() == 0.0


def test_transposed_and_symmetric_products_of_a_banded_matrix_sum_over_windows():
    """In the slice-by-slice node order a block of rows reaches a band around its own: the transposed
    and symmetric products sum each block over that window only (empty rows and blocks included), and
    equal SciPy's products of the stored matrices for one, two and three columns."""
    import scipy.sparse as sp

    from pixmuscle.mechanics.tangent import TRANSPOSE_PARTS, SymmetricCSR, TransposedCSR

    rng = np.random.default_rng(7)
    n, band = 3000, 40
    rows = np.repeat(np.arange(n), 30)
    cols = np.clip(rows + rng.integers(-band, band + 1, rows.size), 0, n - 1)
    keep = (rows >= 400) & (rows < 2600)  # empty rows at both ends: whole blocks without entries
    A = sp.csr_matrix((rng.standard_normal(keep.sum()), (rows[keep], cols[keep])), shape=(n, n))
    L = (A + A.T + sp.identity(n)).tocsr()
    T, S = TransposedCSR(A), SymmetricCSR(L)
    # each block's own rows and a band beyond them, not n rows per block
    assert np.sum(S._hi - S._lo) <= n + TRANSPOSE_PARTS * (band + 1)
    assert np.sum(T._hi - T._lo) <= n + TRANSPOSE_PARTS * (2 * band + 1)
    for k in (1, 2, 3):
        X = rng.standard_normal((n, k))
        ref = L @ X
        assert np.abs(S @ X - ref).max() <= 1e-13 * np.abs(ref).max()
    X = rng.standard_normal((n, 3))
    assert np.abs(T @ X - A.T @ X).max() <= 1e-13 * np.abs(A.T @ X).max()


def test_gram_upper_is_the_upper_triangle_of_the_weighted_gram_sum_whatever_the_threads():
    """gram_upper(terms) = triu(Σ_t B_tᵀ diag(w_t) B_t) with signed weights, its row blocks made on one
    thread or on several, bit for bit the same."""
    import scipy.sparse as sp

    from pixmuscle.mechanics.tangent import gram_upper

    rng = np.random.default_rng(11)
    n, m = 500, 700
    terms = [(sp.random(m, n, density=0.02, format="csr", random_state=k), rng.standard_normal(m)) for k in range(3)]
    ref = sp.triu(sum(B.T @ sp.diags(w) @ B for B, w in terms), format="csr")
    out = [gram_upper(iter(terms), n, blocks=7) for _ in range(2)]
    assert abs(out[0] - ref).max() <= 1e-13 * abs(ref).max()
    import numba

    saved = numba.get_num_threads()
    try:
        numba.set_num_threads(1)  # the thread count of pixmuscle's pools (threaded.thread_count)
        one = gram_upper(iter(terms), n, blocks=7)
    finally:
        numba.set_num_threads(saved)
    assert all((U != one).nnz == 0 for U in out)


def test_threaded_fill_adds_the_same_blocks_as_one_thread():
    """The fills split the block rows among threads (each adds to its own rows only): the tangent
    comes out bit for bit as on one thread, for the whole pattern and for the square block of a
    node subset."""
    import numba

    m = mask_model(np.ones((10, 10, 8), bool), (0.1, 0.1, 0.25))
    sup = support_radius(m.spacing, (1.65, 1.65, 1.65))
    s = build_scni(m.X, m.ijk, m.spacing, sup)
    S = support_pattern(face_incidence(s.faces, s.volume), s.psi_faces)
    rng = np.random.default_rng(5)
    A = rng.standard_normal((m.n_nodes, 3, 3, 3, 3))
    sub = np.flatnonzero(m.ijk[:, 2] < 4)
    saved = numba.get_num_threads()
    out = {}
    try:
        for k in sorted({1, saved, 2} & set(range(1, saved + 1))):
            numba.set_num_threads(k)
            for name, asm in (("whole", Assembler(S)), ("square", Assembler(S, rows=sub, square=True))):
                assert 9 * asm.nnzb >= 200_000 or name == "square"
                data = asm.fill(asm.on_support(s.G), A, s.volume)
                out.setdefault(name, []).append((len(asm._row_parts()), data))
    finally:
        numba.set_num_threads(saved)
    for name, runs in out.items():
        for _, data in runs[1:]:
            assert np.array_equal(data, runs[0][1]), name
    if saved > 1:
        assert out["whole"][-1][0] > 1  # the fill did run on several threads


def test_identity_blocks_merge_a_scalar_operator_into_full_and_filtered_patterns():
    """``Assembler.add_identity_blocks``: M ⊗ I₃ on the pattern, entries outside it dropped — checked
    dense, entry by entry, on the full pattern (every entry kept) and on a filtered one (reach 1:
    only the pairs at most one voxel apart per axis)."""
    import scipy.sparse as sp

    m = mask_model(irregular_mask(8, 5), (0.1, 0.12, 0.25))
    sup = support_radius(m.spacing, (1.65, 1.65, 1.65))
    s = build_scni(m.X, m.ijk, m.spacing, sup, face_gradients=False)
    S = support_pattern(face_incidence(s.faces, s.volume), s.psi_faces)
    rng = np.random.default_rng(5)
    M = (S.T @ sp.diags(rng.random(S.shape[0])) @ S).tocsr()  # a symmetric scalar operator on the support pairs
    M.sort_indices()
    dense = M.toarray()
    for reach in (None, 1):
        asm = Assembler(S, ijk=m.ijk, reach=reach)
        K = asm.matrix(asm.add_identity_blocks(M, asm.zeros())).toarray()
        near = np.ones_like(dense, bool) if reach is None else \
            np.all(np.abs(m.ijk[:, None, :] - m.ijk[None, :, :]) <= reach, axis=2)
        np.testing.assert_array_equal(K, np.kron(np.where(near, dense, 0.0), np.eye(3)))
        assert reach is None or np.any(dense[~near] != 0)  # the filter did drop entries


def test_bone_faces_by_the_vertex_rule_equal_the_penalty_rows_and_cover_the_contact_area():
    """``bone_surface`` held at the vertices of the faces it shares with bone (``penalty.at`` auto):
    the faces are exactly the node–bone face contacts of the label volume (counted here voxel by
    voxel), SCNI integrates them by the same trapezoidal rule (the patch test stays exact), the
    penalty weights sum to the contact area and the penalty rows Σ_c w_c Ψ(x_c) equal SCNI's
    boundary rows Σ_f A_f Ψ̄(f) on those faces. ``nodes`` holds the set at its nodes instead."""
    from pixmuscle.mechanics.boundary import bone_faces, build_constraints, vertex_rule_faces
    from pixmuscle.mechanics.solve import node_supports
    from pixmuscle.model.build import model_from_labels

    labels = np.full((7, 6, 6), MUSCLE)
    labels[0, :, :] = 0
    labels[2:4, 2:4, :] = 4                                              # a bone through the body
    labels[5, 4, 1:3] = 4                                                # and a small one at its side
    h = np.array([0.1, 0.12, 0.25])
    m = model_from_labels(labels, h, fibers=np.broadcast_to([0.0, 0.0, 1.0], labels.shape + (3,)))
    contacts, area = 0, 0.0
    for i, j, k in np.argwhere(labels == MUSCLE):
        for axis in range(3):
            for s in (-1, 1):
                q = [i, j, k]
                q[axis] += s
                if 0 <= q[axis] < labels.shape[axis] and labels[tuple(q)] == 4:
                    contacts += 1
                    area += np.prod(np.delete(h, axis))
    cfg = parse_section(SolveConfig, {"boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                                              {"nodes": "bone_surface", "fix": ["x", "y"]}]}, "solve")
    bcs = list(cfg.boundary_conditions)
    faces = cell_faces(m.X, m.ijk, m.spacing)
    bf = bone_faces(m, faces, m.sets["bone_surface"])
    assert bf.size == contacts
    vf = vertex_rule_faces(m, bcs, faces, at="auto")
    assert np.isin(bf, vf).all() and vertex_rule_faces(m, bcs, faces, at="nodes").size == 0
    sup, _ = node_supports(m, cfg)
    s = build_scni(m.X, m.ijk, m.spacing, sup, faces=faces, vertex_faces=vf, face_gradients=True)
    F0 = np.array([[1.1, 0.2, -0.05], [0.03, 0.95, 0.1], [0.0, -0.2, 1.3]])
    assert np.abs(s.deformation_gradient(m.X @ (F0 - np.eye(3)).T) - F0).max() < 1e-10
    con = build_constraints(m, bcs, faces, sup, 1.0, at="auto")
    on_bone = con.group == 1
    assert np.isclose(con.weight[on_bone].sum(), area, rtol=1e-12)
    rows = con.psi[on_bone].T @ con.weight[on_bone]
    np.testing.assert_allclose(s.psi_faces[bf].T @ faces.area[bf], rows, atol=1e-14)
    at_nodes = build_constraints(m, bcs, faces, sup, 1.0, at="nodes")
    np.testing.assert_array_equal(np.sort(at_nodes.node[at_nodes.group == 1]), m.sets["bone_surface"])
