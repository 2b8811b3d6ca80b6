"""PROTOTYPE — linear-solver research for the SCNI/RKPM tangent (not production code).

This script is a measurement harness, not part of the package. It rebuilds, in a few dozen
lines, a minimal copy of the SCNI smoothed-gradient operators, the NSNI stabilisation and the
penalty stiffness of ``pixmuscle.mechanics`` (paper §3, eqs. 16–20) on a SYNTHETIC leg-like voxel
model (``pixmuscle.synth.leg.LegAnatomy`` sampled at voxel centres: muscle, connective tissue,
fat, tibia and fibula holes), and measures linear solvers on the Newton system K Δd = r:

* tangent build: scipy SpGEMM Bᵀ D B versus the team's compiled fill (``mechanics.assembly``);
* direct: SuperLU (``scipy.sparse.linalg.splu``) with COLAMD / MMD orderings;
* CG + smoothed-aggregation AMG (pyamg, 6 rigid-body modes) on the assembled K;
* MATRIX-FREE K (G_k operators + per-node 9×9 contraction, K never formed) with CG/MINRES,
  preconditioned by AMG on a sparse AUXILIARY matrix: trilinear-hex (Q1) stiffness on the dual
  voxel grid with the same reference moduli (full, selectively reduced ["B-bar"] or deviatoric
  volumetric part), or the SCNI stiffness with a smaller support; block-Jacobi for reference;
* a Newton activation sweep with a stale (reused) preconditioner.

Sizes are set by ``--size`` (leg scale and number of slices at the paper's coarse spacing
0.156 × 0.156 × 0.5 cm). Each case runs in its own process (``all`` spawns them with a time and
memory limit) so that peak RSS is per case.

Run one case:   .venv/bin/python benchmarks/proto_linsolve.py case --size 5k --what mf --aux q1_sri
Run the study:  .venv/bin/python benchmarks/proto_linsolve.py all   (writes benchmarks/results/proto_linsolve.json)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

from pixmuscle.mechanics.materials import CONNECTIVE_TISSUE, FAT, MUSCLE  # noqa: E402
from pixmuscle.rk import shape_functions  # noqa: E402

HERE = Path(__file__).resolve().parent
H = np.array([0.156, 0.156, 0.5])  # cm, coarse model spacing (paper §5, Example 2)
A_OVER_H = 1.65
# size name -> (leg scale, number of slices); ~2950 nodes per slice at scale 1
SIZES = {"2k": (0.40, 5), "5k": (0.50, 8), "10k": (0.62, 11), "20k": (0.72, 15), "40k": (0.86, 20), "75k": (1.04, 25)}


def rss_gb() -> float:
    """Peak resident set size of this process so far, GB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


_T0 = time.perf_counter()


def log(msg):
    print(f"[{time.perf_counter() - _T0:7.1f} s, {rss_gb():.2f} GB] {msg}", file=sys.stderr, flush=True)


class Timer:
    def __init__(self):
        self.t = {}

    def __call__(self, name):
        timer = self

        class _T:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *a):
                timer.t[name] = round(timer.t.get(name, 0.0) + time.perf_counter() - self.t0, 3)

        return _T()


# ---------------------------------------------------------------------------------------------
# model


@dataclasses.dataclass
class LegModel:
    X: np.ndarray  # (N, 3) cm
    ijk: np.ndarray  # (N, 3)
    tissue: np.ndarray  # (N,) 1 muscle, 2 connective tissue, 3 fat
    fiber: np.ndarray  # (N, 3)
    index: np.ndarray  # (I, J, K) node id or -1
    bone: np.ndarray  # (I, J, K) bool
    z_min: np.ndarray
    z_max: np.ndarray
    bone_surface: np.ndarray


def leg_model(scale: float, n_slices: int, seed: int = 0) -> LegModel:
    """SYNTHETIC leg-like pixel model: LegAnatomy sampled at the voxel centres of a 0.156/0.5 cm grid."""
    from pixmuscle.synth import phantom as ph
    from pixmuscle.synth.leg import LegAnatomy

    rng = np.random.default_rng(seed)
    anat = LegAnatomy((0.0, 0.0), (0.0, (n_slices - 1) * H[2]), rng, leg_scale=scale, fat_cm=0.6 * scale)
    lo, hi = anat.bounding_box()
    nx, ny = (np.ceil((hi - lo) / H[:2]).astype(int) + 3)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(n_slices), indexing="ij")
    ijk = np.column_stack([i.ravel(), j.ravel(), k.ravel()])
    pts = np.column_stack([lo[0] - H[0] + ijk[:, 0] * H[0], lo[1] - H[1] + ijk[:, 1] * H[1], ijk[:, 2] * H[2]])
    s = anat(pts, want_fiber=True)
    code = np.zeros(len(pts), np.int8)
    code[s.cls == ph.MUSCLE] = 1
    code[(s.cls == ph.CT) | (s.cls == ph.SKIN)] = 2
    code[s.cls == ph.FAT] = 3
    is_bone = (s.cls == ph.CORTEX) | (s.cls == ph.MARROW)
    keep = clean_mask((code > 0).reshape(nx, ny, n_slices)).ravel()
    code[~keep] = 0
    index = np.full(len(pts), -1, np.int64)
    index[keep] = np.arange(keep.sum())
    index = index.reshape(nx, ny, n_slices)
    bone = is_bone.reshape(nx, ny, n_slices)
    ijk_n = ijk[keep]
    near_bone = np.zeros(keep.sum(), bool)
    for ax in range(3):
        for sgn in (-1, 1):
            q = ijk_n.copy()
            q[:, ax] += sgn
            ok = np.all((q >= 0) & (q < np.array(bone.shape)), axis=1)
            near_bone[ok] |= bone[q[ok, 0], q[ok, 1], q[ok, 2]]
    fiber = s.fiber[keep]
    return LegModel(X=pts[keep], ijk=ijk_n, tissue=code[keep], fiber=fiber, index=index, bone=bone,
                    z_min=np.flatnonzero(ijk_n[:, 2] == 0), z_max=np.flatnonzero(ijk_n[:, 2] == n_slices - 1),
                    bone_surface=np.flatnonzero(near_bone))


def clean_mask(mask):
    """Drop voxels that are one voxel thin along x or y (their RK moment matrix at a = 1.65 h is
    singular: all support nodes lie in one plane), repeat until stable, keep the largest component."""
    from scipy import ndimage

    m = mask.copy()
    while True:
        thin = np.zeros_like(m)
        for ax in (0, 1):
            lo = np.zeros_like(m)
            hi = np.zeros_like(m)
            sl = [slice(None)] * 3
            sl2 = [slice(None)] * 3
            sl[ax], sl2[ax] = slice(1, None), slice(None, -1)
            lo[tuple(sl)] = m[tuple(sl2)]
            hi[tuple(sl2)] = m[tuple(sl)]
            thin |= m & ~lo & ~hi
        if not thin.any():
            break
        m &= ~thin
    lab, nlab = ndimage.label(m)
    if nlab > 1:
        m = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    return m


def neighbour(model: LegModel, axis: int, sgn: int) -> np.ndarray:
    """Node id of the face neighbour along ±axis, −1 where none."""
    q = model.ijk.copy()
    q[:, axis] += sgn
    ok = np.all((q >= 0) & (q < np.array(model.index.shape)), axis=1)
    out = np.full(len(q), -1, np.int64)
    out[ok] = model.index[q[ok, 0], q[ok, 1], q[ok, 2]]
    return out


# ---------------------------------------------------------------------------------------------
# minimal SCNI (prototype copy of the idea in pixmuscle.mechanics.scni)


@dataclasses.dataclass
class Operators:
    G: list  # 3 CSR (N, N): G[J][L, I] = b̃_IJ(X_L), cm⁻¹
    S: sp.csr_matrix  # (N, N) scalar NSNI stabilisation, K_stab = I3 ⊗ S, N/cm
    Kpen: list  # 3 CSR (N, N) penalty stiffness per component, N/cm
    volume: float
    beta: float
    info: dict
    pattern: sp.csr_matrix = None  # (N, N) structural cell–node support incidence (all faces of the cell)


def faces_of(model: LegModel):
    """Unique cell faces: centres (F, 3), and per axis the + and − face index of every cell (3, N)."""
    n = len(model.X)
    centres, plus, minus, start = [], np.empty((3, n), np.int64), np.empty((3, n), np.int64), 0
    for ax in range(3):
        down = neighbour(model, ax, -1)
        own = np.arange(n)
        plus[ax] = start + own  # every cell owns its + face
        low_b = np.flatnonzero(down < 0)
        minus[ax] = np.where(down >= 0, start + np.maximum(down, 0), 0)
        minus[ax, low_b] = start + n + np.arange(len(low_b))
        e = np.zeros(3)
        e[ax] = H[ax] / 2
        centres += [model.X + e, model.X[low_b] - e]
        start += n + len(low_b)
    return np.concatenate(centres), plus, minus


def reference_moduli(model, alpha, kscale=1.0, F=None):
    """P (N,3,3) and A (N,3,3,3,3) of every node at F (default I), activation α; K of all tissues × kscale."""
    n = len(model.X)
    F = np.broadcast_to(np.eye(3), (n, 3, 3)).copy() if F is None else F
    P = np.empty((n, 3, 3))
    A = np.empty((n, 3, 3, 3, 3))
    mats = {1: dataclasses.replace(MUSCLE, K=MUSCLE.K * kscale),
            2: dataclasses.replace(CONNECTIVE_TISSUE, K=CONNECTIVE_TISSUE.K * kscale),
            3: dataclasses.replace(FAT, K=FAT.K * kscale)}
    for code, mat in mats.items():
        idx = np.flatnonzero(model.tissue == code)
        kw = {"fiber": model.fiber[idx], "activation": alpha} if code == 1 else {}
        P[idx], A[idx] = mat.stress_tangent(F[idx], **kw)
    return P, A, mats


def build_operators(model: LegModel, a_over_h=A_OVER_H, penalty_factor=1e3, A0=None, mu=None) -> Operators:
    """G_k, NSNI stabilisation S (shear modulus, coefficient 1), penalty stiffness (ends: xyz, bone: xy)."""
    info = {}
    n = len(model.X)
    vol = float(np.prod(H))
    support = a_over_h * H
    t0 = time.perf_counter()
    centres, plus, minus = faces_of(model)
    psi, dpsi = shape_functions(model.X, centres, support, kernel="cubic", order=1, gradient=True)
    info["shape_s"] = round(time.perf_counter() - t0, 3)
    t0 = time.perf_counter()
    area = vol / H
    G = []
    rows = np.arange(n)
    for ax in range(3):
        D = sp.csr_matrix((np.r_[np.full(n, area[ax] / vol), np.full(n, -area[ax] / vol)],
                           (np.r_[rows, rows], np.r_[plus[ax], minus[ax]])), shape=(n, len(centres)))
        G.append((D @ psi).tocsr())
    cells = np.repeat(rows, 6)
    fcs = np.stack([plus[0], minus[0], plus[1], minus[1], plus[2], minus[2]], axis=1).ravel()
    Ds = sp.csr_matrix((np.ones(6 * n), (cells, fcs)), shape=(n, len(centres)))
    Ps = psi.copy()
    Ps.data[:] = 1.0
    pattern = (Ds @ Ps).tocsr()
    pattern.data[:] = 1.0
    info["cell_support_nodes"] = round(pattern.nnz / n, 1)
    info["G_s"] = round(time.perf_counter() - t0, 3)
    info["G_nnz_per_row"] = round(sum(g.nnz for g in G) / 3 / n, 1)
    t0 = time.perf_counter()
    # NSNI (Hillman & Chen 2016) as in mechanics.stabilization, modulus 2μ I, M_Lk = V h_k²/12
    S = sp.csr_matrix((n, n))
    for k in range(3):
        wk = sp.diags(2.0 * mu * vol * H[k] ** 2 / 12.0)
        for J in range(3):
            Hk = ((dpsi[J][plus[k]] - dpsi[J][minus[k]]) / H[k]).tocsr()
            S = S + Hk.T @ wk @ Hk
    S = S.tocsr()
    info["stab_s"] = round(time.perf_counter() - t0, 3)
    info["S_nnz_per_row"] = round(S.nnz / n, 1)
    t0 = time.perf_counter()
    Mmax = max(float(np.max(A0[:, i, J, i, J])) for i in range(3) for J in range(3))
    beta = penalty_factor * Mmax / H.min()
    e = np.array([0, 0, H[2] / 2])
    pts = np.concatenate([model.X[model.z_min] - e, model.X[model.z_max] + e, model.X[model.bone_surface]])
    w = np.r_[np.full(len(model.z_min) + len(model.z_max), H[0] * H[1]),
              np.full(len(model.bone_surface), H[0] * H[2])]
    mask = np.ones((len(pts), 3))
    mask[len(model.z_min) + len(model.z_max):, 2] = 0.0  # bone: in-plane only
    Pc = sp.csr_matrix(shape_functions(model.X, pts, support, kernel="cubic", order=1))
    Kpen = [(Pc.T @ sp.diags(beta * w * mask[:, j]) @ Pc).tocsr() for j in range(3)]
    info["penalty_s"] = round(time.perf_counter() - t0, 3)
    nz = len(model.z_min)
    zmax = slice(nz, nz + len(model.z_max))
    ops = Operators(G=G, S=S, Kpen=Kpen, volume=vol, beta=beta, info=info, pattern=pattern)
    ops.Pc_zmax, ops.w_zmax = Pc[zmax], w[zmax]
    return ops


def reaction_zmax(ops, d):
    """z-force (N) the support at z_max exerts on the body, R = −β Σ_c w_c u^h_z(x_c) (load factor 0)."""
    u = ops.Pc_zmax @ d.reshape(-1, 3)[:, 2]
    return float(-ops.beta * np.sum(ops.w_zmax * u))


def tangent9(A):
    """(N,3,3,3,3) → (N,9,9) with index 3i+J (row) and 3k+L (column)."""
    return np.ascontiguousarray(A.reshape(len(A), 9, 9))


# ---------------------------------------------------------------------------------------------
# assembled tangent


def assemble_spgemm(ops: Operators, A9) -> sp.csr_matrix:
    """K = Bᵀ (V A) B + I3⊗S + Kpen by scipy sparse products (B: 9N × 3N)."""
    n = A9.shape[0]
    rows, cols, vals = [], [], []
    for J in range(3):
        C = ops.G[J].tocoo()
        for i in range(3):
            rows.append(9 * C.row + 3 * i + J)
            cols.append(3 * C.col + i)
            vals.append(C.data)
    B = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(9 * n, 3 * n))
    D = sp.bsr_matrix((ops.volume * A9, np.arange(n), np.arange(n + 1)), shape=(9 * n, 9 * n))
    K = (B.T @ (D @ B).tocsr()).tocsr()
    return K + extra_stiffness(ops, n)


def extra_stiffness(ops, n):
    E = sp.kron(ops.S, sp.eye(3), format="csr")
    for j in range(3):
        P = ops.Kpen[j].tocoo()
        E = E + sp.csr_matrix((P.data, (3 * P.row + j, 3 * P.col + j)), shape=(3 * n, 3 * n))
    return E.tocsr()


def assemble_numba(ops: Operators, A) -> sp.bsr_matrix:
    """Same K with the team's compiled fill on the fixed block pattern (pixmuscle.mechanics.assembly)."""
    from pixmuscle.mechanics.assembly import Assembler

    n = A.shape[0]
    asm = Assembler(ops.pattern)
    g = asm.on_support(ops.G)
    data = asm.fill(g, A, np.full(n, ops.volume))
    for i in range(3):
        asm.align_scalar(ops.S, i, i, data)
        asm.align_scalar(ops.Kpen[i], i, i, data)
    return asm.matrix(data), asm


# ---------------------------------------------------------------------------------------------
# matrix-free tangent


class MatrixFreeK(spla.LinearOperator):
    """K v = Σ_L V_L B̃_Lᵀ A_L B̃_L v + (I3⊗S) v + Kpen v without forming K.

    Per product: one SpMM with the stacked (3N × N) G and 3 columns, a batched 9×9 contraction,
    one SpMM with its transpose, one SpMM with S (3 columns) and 3 penalty SpMVs.
    """

    def __init__(self, ops: Operators, A9):
        n = A9.shape[0]
        super().__init__(np.float64, (3 * n, 3 * n))
        self.n = n
        self.Gs = sp.vstack(ops.G).tocsr()
        self.GsT = self.Gs.T.tocsr()
        self.S = ops.S
        self.Kpen = ops.Kpen
        self.set_moduli(ops.volume * A9)

    def set_moduli(self, VA9):
        self.VA = np.ascontiguousarray(VA9)

    def _matvec(self, v):
        n = self.n
        V = np.asarray(v, float).reshape(n, 3)
        g = (self.Gs @ V).reshape(3, n, 3)  # g[J, L, i] = ∂v_i/∂X_J at cell L
        grad = np.ascontiguousarray(g.transpose(1, 2, 0)).reshape(n, 9, 1)
        t = np.matmul(self.VA, grad).reshape(n, 3, 3)  # t[L, i, J] = V_L (A : ∇v)_iJ
        y = self.GsT @ np.ascontiguousarray(t.transpose(2, 0, 1)).reshape(3 * n, 3)
        y += self.S @ V
        for j in range(3):
            y[:, j] += self.Kpen[j] @ V[:, j]
        return y.ravel()

    def block_diagonal(self, ops: Operators, VA9):
        """3×3 diagonal blocks of K (N, 3, 3) computed from the operators (for Jacobi and aux fixes)."""
        n = self.n
        pat = (abs(ops.G[0]) + abs(ops.G[1]) + abs(ops.G[2])).tocoo()
        g = np.stack([np.asarray(ops.G[J][pat.row, pat.col]).ravel() for J in range(3)], axis=1)  # (m, 3)
        VA = VA9.reshape(n, 3, 3, 3, 3)
        blk = np.einsum("mJ,miJkL,mL->mik", g, VA[pat.row], g, optimize=True)
        D = np.zeros((n, 3, 3))
        np.add.at(D, pat.col, blk)
        d = ops.S.diagonal()
        for i in range(3):
            D[:, i, i] += d + ops.Kpen[i].diagonal()
        return D


class SplitSystem(spla.LinearOperator):
    """Displacement–pressure form of the same system (volumetric term taken out as a constraint).

    With A = A_rest + κ_L cof⊗cof per node (κ_L the bulk modulus, cof = J F⁻ᵀ, = I at F = I) the
    SCNI tangent is K = K_rest + Dᵀ diag(V κ) D with (D v)_L = cof_L : ∇̃v(X_L). Introducing
    p = diag(V κ) D u gives the equivalent symmetric saddle-point system

        [K_rest  Dᵀ        ] [u]   [b]
        [D       −diag(1/Vκ)] [p] = [0]

    whose block-diagonal preconditioner diag(AMG(K_rest-aux), Ŝ⁻¹), Ŝ_L = 1/(Vκ) + c/(V μ), makes
    MINRES iteration counts (ideally) independent of κ/μ. (4N unknowns.)
    """

    def __init__(self, ops: Operators, A9, kvol, cof9=None):
        n = A9.shape[0]
        super().__init__(np.float64, (4 * n, 4 * n))
        self.n = n
        self.cof9 = np.tile(np.eye(3).ravel(), (n, 1)) if cof9 is None else cof9
        self.wk = ops.volume * kvol
        A9r = A9 - kvol[:, None, None] * self.cof9[:, :, None] * self.cof9[:, None, :]
        self.A9_rest = A9r
        self.mf = MatrixFreeK(ops, A9r)

    def _matvec(self, z):
        n, mf = self.n, self.mf
        U = np.asarray(z[:3 * n], float).reshape(n, 3)
        pr = z[3 * n:]
        g = (mf.Gs @ U).reshape(3, n, 3)
        grad = np.ascontiguousarray(g.transpose(1, 2, 0)).reshape(n, 9)
        t = np.matmul(mf.VA, grad[:, :, None])[:, :, 0] + self.cof9 * pr[:, None]
        t = t.reshape(n, 3, 3)
        y = mf.GsT @ np.ascontiguousarray(t.transpose(2, 0, 1)).reshape(3 * n, 3)
        y += mf.S @ U
        for j in range(3):
            y[:, j] += mf.Kpen[j] @ U[:, j]
        yp = np.sum(grad * self.cof9, axis=1) - pr / self.wk
        return np.concatenate([y.ravel(), yp])


class BlockDiagPrec(spla.LinearOperator):
    def __init__(self, Mu, s_inv):
        n3 = Mu.shape[0]
        super().__init__(np.float64, (n3 + len(s_inv), n3 + len(s_inv)))
        self.Mu, self.s_inv, self.n3 = Mu, s_inv, n3

    def _matvec(self, z):
        return np.concatenate([self.Mu @ z[:self.n3], self.s_inv * z[self.n3:]])


def spd_clamp(A9, floor=0.0):
    """Symmetric part of each 9×9 tangent with eigenvalues below ``floor`` raised to |λ| (SPD surrogate)."""
    Ss = 0.5 * (A9 + A9.transpose(0, 2, 1))
    lam, Q = np.linalg.eigh(Ss)
    lam = np.maximum(np.abs(lam), floor)
    return np.einsum("nab,nb,ncb->nac", Q, lam, Q)


def deformation_gradient(mf: MatrixFreeK, d):
    n = mf.n
    g = (mf.Gs @ d.reshape(n, 3)).reshape(3, n, 3)
    return np.eye(3)[None] + g.transpose(1, 2, 0)


def internal_force(mf: MatrixFreeK, P, vol):
    n = mf.n
    y = mf.GsT @ np.ascontiguousarray(np.transpose(P, (2, 0, 1))).reshape(3 * n, 3) * vol
    return y.ravel()


# ---------------------------------------------------------------------------------------------
# auxiliary matrices for the preconditioner


def q1_aux(model: LegModel, A, kvol, mode="sri", Kpen=None, diag_fix=None, dev_bulk=None):
    """Trilinear hexahedra on the dual voxel grid (node = hex corner), 2×2×2 Gauss, same moduli.

    mode "full": A at all 8 Gauss points; "sri": A − K δ_iJ δ_kL at 8 points, K δ_iJ δ_kL at the
    centre (selective reduced integration = B-bar for a linear problem); "dev": like "sri" but
    the volumetric modulus replaced by ``dev_bulk`` (N/cm²).
    Nodes outside every hex get the diagonal block ``diag_fix`` of the true K.
    """
    n = len(model.X)
    idx = model.index
    shp = np.array(idx.shape)
    corners = np.array(list(np.ndindex(2, 2, 2)))
    base = model.ijk[np.all(model.ijk + 1 < shp, axis=1)]
    cn = np.stack([idx[base[:, 0] + a, base[:, 1] + b, base[:, 2] + c] for a, b, c in corners], axis=1)
    conn = cn[np.all(cn >= 0, axis=1)]  # (E, 8)
    E = len(conn)
    # shape-function gradients at the Gauss points of the box [0,h]
    gp = np.array([0.5 - 0.5 / np.sqrt(3), 0.5 + 0.5 / np.sqrt(3)])
    xi = np.array(list(np.ndindex(2, 2, 2)), float)
    xi = gp[xi.astype(int)]  # (8 gauss, 3) in [0,1]

    def dN(p):  # (8 nodes, 3) gradients at local point p in [0,1]^3, cm⁻¹
        out = np.empty((8, 3))
        for a, c in enumerate(corners):
            f = np.where(c == 1, p, 1 - p)
            s = np.where(c == 1, 1.0, -1.0)
            for J in range(3):
                out[a, J] = s[J] / H[J] * np.prod(np.delete(f, J))
        return out

    vol = float(np.prod(H))
    W8 = sum(np.einsum("aJ,bL->aJbL", dN(p), dN(p)) for p in xi) * vol / 8.0
    d0 = dN(np.full(3, 0.5))
    W1 = np.einsum("aJ,bL->aJbL", d0, d0) * vol
    Ae = A[conn].mean(axis=1)  # (E,3,3,3,3)
    ke = kvol[conn].mean(axis=1)  # (E,)
    dd = np.einsum("iJ,kL->iJkL", np.eye(3), np.eye(3))
    if mode == "full":
        Ke = np.einsum("aJbL,eiJkL->eaibk", W8, Ae, optimize=True)
    else:
        Adev = Ae - ke[:, None, None, None, None] * dd
        kv = ke if mode == "sri" else np.full(E, dev_bulk)
        Ke = np.einsum("aJbL,eiJkL->eaibk", W8, Adev, optimize=True) + \
            np.einsum("e,aJbL,iJkL->eaibk", kv, W1, dd, optimize=True)
    rows = np.repeat(conn, 8, axis=1).ravel()  # a-major
    cols = np.tile(conn, (1, 8)).ravel()
    keys = rows * n + cols
    uk, inv = np.unique(keys, return_inverse=True)
    blocks = np.zeros((len(uk), 3, 3))
    Kb = Ke.transpose(0, 1, 3, 2, 4).reshape(-1, 3, 3)  # (E*64, 3, 3) in (a, b) order
    for i in range(3):
        for k in range(3):
            blocks[:, i, k] = np.bincount(inv, weights=Kb[:, i, k], minlength=len(uk))
    br, bc = uk // n, uk % n
    indptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(br, minlength=n), out=indptr[1:])
    K = sp.bsr_matrix((blocks, bc, indptr), shape=(3 * n, 3 * n)).tocsr()
    covered = np.zeros(n, bool)
    covered[conn.ravel()] = True
    if diag_fix is not None and (~covered).any():
        m = np.flatnonzero(~covered)
        K = K + block_diag_matrix(diag_fix, m, n)
    if Kpen is not None:
        K = K + penalty_scalar_to_dofs(Kpen, n)
    return K.tocsr(), {"elements": int(E), "uncovered_nodes": int((~covered).sum()),
                       "aux_nnz_per_row": round(K.nnz / (3 * n), 1)}


def filtered_aux(K, ijk, reach=1, lump=True):
    """Keep the 3×3 blocks of K between nodes at most ``reach`` voxels apart (per axis); add each
    dropped block to the diagonal block of its row when ``lump`` (keeps K·t for translations t)."""
    Kb = sp.bsr_matrix(K, blocksize=(3, 3))
    n = Kb.shape[0] // 3
    rows = np.repeat(np.arange(n), np.diff(Kb.indptr))
    far = np.abs(ijk[rows] - ijk[Kb.indices]).max(axis=1) > reach
    data = Kb.data.copy()
    if lump:
        diag_pos = np.flatnonzero(rows == Kb.indices)
        lumped = np.zeros((n, 3, 3))
        np.add.at(lumped, rows[far], data[far])
        data[diag_pos] += lumped[rows[diag_pos]]
    keep = ~far
    indptr = np.r_[0, np.cumsum(np.bincount(rows[keep], minlength=n))]
    return sp.bsr_matrix((data[keep], Kb.indices[keep], indptr), shape=Kb.shape).tocsr()


def block_diag_matrix(D, nodes, n):
    r = (3 * nodes[:, None, None] + np.arange(3)[None, :, None]) + 0 * np.arange(3)[None, None, :]
    c = (3 * nodes[:, None, None] + np.arange(3)[None, None, :]) + 0 * np.arange(3)[None, :, None]
    return sp.csr_matrix((D[nodes].ravel(), (r.ravel(), c.ravel())), shape=(3 * n, 3 * n))


def penalty_scalar_to_dofs(Kpen, n):
    out = sp.csr_matrix((3 * n, 3 * n))
    for j in range(3):
        P = Kpen[j].tocoo()
        out = out + sp.csr_matrix((P.data, (3 * P.row + j, 3 * P.col + j)), shape=(3 * n, 3 * n))
    return out


from pixmuscle.mechanics.linsolve import rigid_body_modes  # noqa: E402  (same modes as the solver)


def geometric_aggregates(ijk, block=(3, 3, 1)):
    """Aggregation operator (N × N_agg CSR, 0/1) grouping nodes in voxel blocks of ``block``."""
    key = ijk // np.asarray(block)
    _, agg = np.unique(key, axis=0, return_inverse=True)
    agg = agg.ravel()
    n = len(ijk)
    return sp.csr_matrix((np.ones(n), (np.arange(n), agg)), shape=(n, agg.max() + 1))


def amg(K, X, theta=0.0, max_coarse=300, smoother="gs", agg=None):
    import pyamg

    Kb = sp.bsr_matrix(K, blocksize=(3, 3))
    kw = {}
    if agg is not None:
        kw["aggregate"] = [("predefined", {"AggOp": agg})] + ["standard"] * 8
    if smoother == "jacobi":
        kw = dict(presmoother=("block_jacobi", {"omega": 0.5, "iterations": 2}),
                  postsmoother=("block_jacobi", {"omega": 0.5, "iterations": 2}))
    ml = pyamg.smoothed_aggregation_solver(
        Kb, B=rigid_body_modes(X), symmetry="symmetric", strength=("symmetric", {"theta": theta}),
        smooth=("jacobi", {"omega": 4.0 / 3.0, "degree": 1}), max_coarse=max_coarse, keep=False, **kw)
    return ml


def pcg(Aop, b, M, rtol=1e-8, maxiter=3000, x0=None):
    """Preconditioned CG; returns x, relative residual history (true recurrence ‖r‖/‖b‖), status."""
    x = np.zeros_like(b) if x0 is None else x0.copy()
    r = b - Aop @ x if x0 is not None else b.copy()
    nb = np.linalg.norm(b)
    hist = [np.linalg.norm(r) / nb]
    z = M @ r
    p = z.copy()
    rz = r @ z
    status = "maxiter"
    for it in range(maxiter):
        if it % 100 == 0 and it:
            log(f"  cg it {it}: {hist[-1]:.2e}")
        q = Aop @ p
        pq = p @ q
        if pq <= 0:
            status = "breakdown (p·Kp ≤ 0)"
            break
        a = rz / pq
        x += a * p
        r -= a * q
        hist.append(np.linalg.norm(r) / nb)
        if hist[-1] <= rtol:
            status = "ok"
            break
        z = M @ r
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, hist, status


def iters_to(hist, tol):
    for i, h in enumerate(hist):
        if h <= tol:
            return i
    return None


class BlockJacobi(spla.LinearOperator):
    def __init__(self, D):
        n = len(D)
        super().__init__(np.float64, (3 * n, 3 * n))
        self.Dinv = np.linalg.inv(D)

    def _matvec(self, v):
        return np.matmul(self.Dinv, v.reshape(-1, 3, 1)).ravel()


# ---------------------------------------------------------------------------------------------
# one case


def setup(args, T):
    scale, slices = SIZES[args.size]
    with T("model_s"):
        model = leg_model(scale, slices)
    n = len(model.X)
    with T("moduli_s"):
        P, A, mats = reference_moduli(model, args.alpha, args.kscale)
        P0, A0, _ = reference_moduli(model, 0.0, args.kscale)
    mu = np.where(model.tissue == 1, mats[1].shear_modulus, np.where(model.tissue == 2, mats[2].shear_modulus,
                                                                    mats[3].shear_modulus))
    kvol = np.where(model.tissue == 1, mats[1].K, np.where(model.tissue == 2, mats[2].K, mats[3].K))
    with T("operators_s"):
        ops = build_operators(model, args.a_over_h, args.penalty, A0=A0, mu=mu)
    # right-hand side: minus the internal force of the activation step at d = 0 (residual)
    vol = ops.volume
    Gs = sp.vstack(ops.G).tocsr()
    f = (Gs.T @ np.ascontiguousarray(np.transpose(P, (2, 0, 1))).reshape(3 * n, 3) * vol).ravel()
    b = -f if np.linalg.norm(f) > 0 else rigid_body_modes(model.X)[:, 2].copy()
    return model, P, A, mats, mu, kvol, ops, b


def run_case(args) -> dict:
    T = Timer()
    out = {"size": args.size, "what": args.what, "alpha": args.alpha, "kscale": args.kscale, "penalty": args.penalty,
           "a_over_h": args.a_over_h}
    model, P, A, mats, mu, kvol, ops, b = setup(args, T)
    n = len(model.X)
    out.update(n_nodes=n, n_dof=3 * n, n_end_nodes=int(len(model.z_min) + len(model.z_max)),
               n_bone_surface=int(len(model.bone_surface)), tissue_counts=np.bincount(model.tissue, minlength=4)[1:].tolist(),
               K_over_mu_muscle=round(mats[1].K / mats[1].shear_modulus, 1), beta=ops.beta, **ops.info)
    A9 = tangent9(A)
    ev = np.linalg.eigvalsh(0.5 * (A9 + A9.transpose(0, 2, 1)))
    out["A9_min_eig"] = float(ev[:, 0].min())
    out["rss_after_setup_gb"] = round(rss_gb(), 3)
    w = args.what

    def amg_preconditioner(Kp):
        """pyamg SA V-cycle of Kp with this run's aggregation and θ; records levels and complexity."""
        agg = geometric_aggregates(model.ijk, (3, 3, 1)) if args.agg == "geo" else None
        with T("amg_setup_s"):
            ml = amg(Kp, model.X, theta=args.theta, agg=agg)
        log(f"amg set up: {ml}")
        out["levels"] = len(ml.levels)
        out["operator_complexity"] = round(ml.operator_complexity(), 3)
        return ml.aspreconditioner(cycle="V")

    if w == "build":
        with T("spgemm_s"):
            K1 = assemble_spgemm(ops, A9) if args.spgemm else None
        rss1 = rss_gb()
        with T("numba_first_s"):
            K2, asm = assemble_numba(ops, A)
        with T("numba_refill_s"):
            asm.fill(asm.on_support(ops.G), A, np.full(n, ops.volume))
        out["nnz"] = int(K2.nnz)
        out["nnz_per_dof_row"] = round(K2.nnz / (3 * n), 1)
        out["K_bsr_gb"] = round((K2.data.nbytes + K2.indices.nbytes + K2.indptr.nbytes) / 1e9, 3)
        out["K_csr_int32_gb"] = round(K2.nnz * 12 / 1e9, 3)
        mf = MatrixFreeK(ops, A9)
        x = np.random.default_rng(1).standard_normal(3 * n)
        y2 = K2 @ x
        with T("mf_matvec_s"):
            for _ in range(5):
                ymf = mf @ x
        T.t["mf_matvec_s"] = round(T.t["mf_matvec_s"] / 5, 4)
        with T("assembled_matvec_s"):
            for _ in range(5):
                y2 = K2 @ x
        T.t["assembled_matvec_s"] = round(T.t["assembled_matvec_s"] / 5, 4)
        Kc = K2.tocsr()
        with T("assembled_csr_matvec_s"):
            for _ in range(5):
                Kc @ x
        T.t["assembled_csr_matvec_s"] = round(T.t["assembled_csr_matvec_s"] / 5, 4)
        out["mf_vs_assembled_rel_diff"] = float(np.linalg.norm(ymf - y2) / np.linalg.norm(y2))
        if K1 is not None:
            out["spgemm_vs_numba_rel_diff"] = float(abs(K1 - Kc).max() / abs(Kc).max())
            out["rss_after_spgemm_gb"] = round(rss1, 3)
        # rigid translation / rotation energy without penalty and stab (checks of the operators)
        rb = rigid_body_modes(model.X)
        Kmat = K2 - extra_stiffness(ops, n)
        out["rigid_mode_rel_residual"] = float(max(np.linalg.norm(Kmat @ rb[:, j]) for j in range(3)) / np.linalg.norm(Kmat @ x))
        out["mf_memory_gb"] = round((mf.Gs.data.nbytes + mf.Gs.indices.nbytes) * 2 / 1e9 + mf.VA.nbytes / 1e9
                                    + (ops.S.data.nbytes + ops.S.indices.nbytes) / 1e9, 3)
        out["symmetry_rel"] = float(abs(Kc - Kc.T).max() / abs(Kc).max())
    elif w == "direct":
        K2, _ = assemble_numba(ops, A)
        Kc = sp.csc_matrix(K2)
        del K2
        out["nnz"] = int(Kc.nnz)
        with T("factor_s"):
            lu = spla.splu(Kc, permc_spec=args.ordering)
        out["fill_nnz"] = int(lu.L.nnz + lu.U.nnz)
        out["fill_gb"] = round(out["fill_nnz"] * 12 / 1e9, 3)
        with T("solve_s"):
            x = lu.solve(b)
        out["rel_residual"] = float(np.linalg.norm(Kc @ x - b) / np.linalg.norm(b))
        out["ordering"] = args.ordering
    elif w == "pardiso":
        # optional: MKL PARDISO via pypardiso (not a project dependency; see docs/linsolve-research.md)
        import pypardiso

        K2, _ = assemble_numba(ops, A)
        Ku = sp.triu(K2.tocsr(), format="csr")
        del K2
        Ku.sort_indices()
        slv = pypardiso.PyPardisoSolver(mtype=-2)
        slv.set_iparm(18, -1)
        z = np.zeros((3 * n, 1))
        with T("analyse_s"):
            slv.set_phase(11)
            slv._check_A(Ku)
            slv._call_pardiso(Ku, z)
        with T("factor_s"):
            slv.set_phase(22)
            slv._call_pardiso(Ku, z)
        out["factor_nnz"] = int(slv.get_iparm(18))
        out["factor_mem_mb"] = round(slv.get_iparm(17) / 1024, 1)
        out["negative_eigenvalues"] = int(slv.get_iparm(23))
        with T("solve_s"):
            slv.set_phase(33)
            x = slv._call_pardiso(Ku, b.reshape(-1, 1).copy()).ravel()
        Kfull = Ku + sp.triu(Ku, k=1).T
        out["rel_residual"] = float(np.linalg.norm(Kfull @ x - b) / np.linalg.norm(b))
        out["reaction_zmax_N"] = reaction_zmax(ops, x)
    elif w == "amg_full":
        K2, _ = assemble_numba(ops, A)
        K = K2.tocsr()
        del K2
        out["nnz_per_dof_row"] = round(K.nnz / (3 * n), 1)
        log("assembled")
        M = amg_preconditioner(K)
        with T("solve_s"):
            x, hist, st = pcg(K, b, M, rtol=args.rtol, maxiter=args.maxiter)
        out.update(cg_status=st, iterations=len(hist) - 1, it_1e3=iters_to(hist, 1e-3), it_1e6=iters_to(hist, 1e-6))
        out["rel_residual"] = float(np.linalg.norm(K @ x - b) / np.linalg.norm(b))
    elif w in ("mf", "mf_minres"):
        mf = MatrixFreeK(ops, A9)
        if args.aux == "jacobi":
            with T("aux_s"):
                M = BlockJacobi(mf.block_diagonal(ops, ops.volume * A9))
        else:
            with T("aux_s"):
                if args.aux.startswith("q1"):
                    D = mf.block_diagonal(ops, ops.volume * A9)
                    # volumetric modulus as seen by the tangent: K (muscle/fat) or K (CT)
                    Kaux, ainfo = q1_aux(model, A, kvol, mode=args.aux[3:], Kpen=ops.Kpen, diag_fix=D,
                                         dev_bulk=args.dev_bulk)
                elif args.aux.startswith("scni"):
                    small = float(args.aux[4:])
                    ops_s = build_operators(model, small, args.penalty, A0=A0_of(model, args), mu=mu)
                    Ks, _ = assemble_numba(ops_s, A)
                    Kaux = Ks.tocsr()
                    ainfo = {"aux_nnz_per_row": round(Kaux.nnz / (3 * n), 1), "aux_a_over_h": small}
                elif args.aux == "filt2":
                    Ks, _ = assemble_numba(ops, A)
                    Kaux = filtered_aux(Ks.tocsr(), model.ijk, 2, False)
                    del Ks
                    ainfo = {"aux_nnz_per_row": round(Kaux.nnz / (3 * n), 1), "aux_filter_reach": 2}
                elif args.aux == "full":
                    Ks, _ = assemble_numba(ops, A)
                    Kaux = Ks.tocsr()
                    ainfo = {"aux_nnz_per_row": round(Kaux.nnz / (3 * n), 1)}
                else:
                    raise SystemExit(f"unknown aux {args.aux}")
            out.update(ainfo)
            log(f"aux built {ainfo}")
            M = amg_preconditioner(Kaux)
            with T("vcycle_s"):
                for _ in range(3):
                    M @ b
            T.t["vcycle_s"] = round(T.t["vcycle_s"] / 3, 4)
        with T("mf_matvec_s"):
            for _ in range(3):
                mf @ b
        T.t["mf_matvec_s"] = round(T.t["mf_matvec_s"] / 3, 4)
        out["aux"] = args.aux
        if w == "mf":
            with T("solve_s"):
                x, hist, st = pcg(mf, b, M, rtol=args.rtol, maxiter=args.maxiter)
            out.update(cg_status=st, iterations=len(hist) - 1, it_1e3=iters_to(hist, 1e-3), it_1e6=iters_to(hist, 1e-6))
        else:
            cnt = [0]
            with T("solve_s"):
                x, flag = spla.minres(mf, b, M=M, rtol=args.rtol, maxiter=args.maxiter, callback=lambda _: cnt.__setitem__(0, cnt[0] + 1))
            out.update(minres_flag=int(flag), iterations=cnt[0])
        out["rel_residual"] = float(np.linalg.norm(mf @ x - b) / np.linalg.norm(b))
    elif w == "newton":
        out.update(newton_sweep(model, ops, mats, mu, kvol, args, T))
    out["timings"] = T.t
    out["peak_rss_gb"] = round(rss_gb(), 3)
    return out


def A0_of(model, args):
    return reference_moduli(model, 0.0, args.kscale)[1]


def newton_sweep(model, ops, mats, mu, kvol, args, T):
    """Activation sweep α: 0 → α_end in ``steps`` steps, exact (matrix-free) tangent, inexact CG.

    Preconditioner (AMG on the Q1-SRI auxiliary matrix) rebuilt according to ``--reuse``:
    "iter" (every Newton iteration, with the current moduli), "step" (at the start of each step),
    "once" (reference state only).
    """
    n = len(model.X)
    d = np.zeros(3 * n)
    F = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    P, A, _ = reference_moduli(model, 0.0, args.kscale)
    mf = MatrixFreeK(ops, tangent9(A))
    Kpen_dofs = penalty_scalar_to_dofs(ops.Kpen, n)
    Sd = sp.kron(ops.S, sp.eye(3), format="csr")
    rows, M, n_setup = [], None, 0
    alphas = np.linspace(0.0, args.alpha_end, args.steps + 1)[1:]

    def residual(d, alpha):
        F = deformation_gradient(mf, d)
        P, A, _ = reference_moduli(model, alpha, args.kscale, F=F)
        r = internal_force(mf, P, ops.volume) + Sd @ d + Kpen_dofs @ d
        return r, F, A

    agg = geometric_aggregates(model.ijk, (3, 3, 1))

    def build_M(A):
        # SPD surrogate of the current tangent (clamped 9×9 moduli), assembled, filtered to reach 2
        Ac = spd_clamp(tangent9(A)).reshape(n, 3, 3, 3, 3)
        Kb, _ = assemble_numba(ops, Ac)
        Kaux = filtered_aux(Kb.tocsr(), model.ijk, 2, False)
        del Kb
        return amg(Kaux, model.X, theta=0.1, agg=agg).aspreconditioner(cycle="V")

    t_setup = t_cg = t_res = 0.0
    total_cg = 0
    scale0 = None
    for s, alpha in enumerate(alphas):
        t0 = time.perf_counter()
        r, F, A = residual(d, alpha)
        t_res += time.perf_counter() - t0
        nr0 = np.linalg.norm(r)
        scale0 = scale0 or nr0
        for it in range(args.newton_max):
            nr = np.linalg.norm(r)
            if nr <= args.newton_tol * max(scale0, 1e-300) and it > 0:
                break
            mf.set_moduli(ops.volume * tangent9(A))
            if M is None or args.reuse == "iter" or (args.reuse == "step" and it == 0):
                t0 = time.perf_counter()
                M = build_M(A)
                t_setup += time.perf_counter() - t0
                n_setup += 1
            # Eisenstat–Walker-like forcing: loose early, tighter near convergence
            eta = min(1e-2, max(1e-6, (nr / nr0) ** 0.5 * 1e-2)) if it > 0 else 1e-2
            t0 = time.perf_counter()
            dx, hist, st = pcg(mf, -r, M, rtol=eta, maxiter=args.maxiter)
            t_cg += time.perf_counter() - t0
            total_cg += len(hist) - 1
            d += dx
            t0 = time.perf_counter()
            r, F, A = residual(d, alpha)
            t_res += time.perf_counter() - t0
            rows.append([s + 1, it + 1, float(alpha), float(np.linalg.norm(r) / scale0), len(hist) - 1, st])
            log(f"step {s + 1} it {it + 1} alpha {alpha:.3f} |r|/|r0| {rows[-1][3]:.2e} cg {len(hist) - 1} {st}")
        else:
            pass
    force = float(np.sum((ops.Kpen[2] @ d.reshape(n, 3)[:, 2])[model.z_max]))
    return {"newton_rows": rows, "newton_iterations": len(rows), "cg_iterations_total": total_cg,
            "preconditioner_setups": n_setup, "setup_total_s": round(t_setup, 2), "cg_total_s": round(t_cg, 2),
            "residual_eval_s": round(t_res, 2), "steps": args.steps, "alpha_end": args.alpha_end, "reuse": args.reuse,
            "max_abs_u_cm": float(np.abs(d).max()), "penalty_force_zmax_proxy_N": force}


# ---------------------------------------------------------------------------------------------
# driver


def case_parser(p):
    p.add_argument("--size", default="5k", choices=list(SIZES))
    p.add_argument("--what", default="build", choices=["build", "direct", "pardiso", "amg_full", "mf", "mf_minres", "newton"])
    p.add_argument("--alpha", type=float, default=0.5)
    p.add_argument("--kscale", type=float, default=1.0, help="scale every bulk modulus K")
    p.add_argument("--penalty", type=float, default=1e3, help="penalty factor (β = factor · max modulus / h_min)")
    p.add_argument("--a-over-h", dest="a_over_h", type=float, default=A_OVER_H)
    p.add_argument("--ordering", default="COLAMD")
    p.add_argument("--aux", default="q1_sri", help="jacobi | q1_full | q1_sri | q1_dev | filt2 | full")
    p.add_argument("--dev-bulk", dest="dev_bulk", type=float, default=50.0)
    p.add_argument("--theta", type=float, default=0.0)
    p.add_argument("--agg", default="standard", choices=["standard", "geo"], help="AMG first-level aggregation: "
                   "pyamg standard, or geometric 3×3×1 voxel blocks")
    p.add_argument("--rtol", type=float, default=1e-8)
    p.add_argument("--maxiter", type=int, default=3000)
    p.add_argument("--spgemm", action="store_true")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--alpha-end", dest="alpha_end", type=float, default=0.95)
    p.add_argument("--reuse", default="step", choices=["iter", "step", "once"])
    p.add_argument("--newton-max", dest="newton_max", type=int, default=12)
    p.add_argument("--newton-tol", dest="newton_tol", type=float, default=1e-6)
    p.add_argument("--json", default=None)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    case_parser(sub.add_parser("case", help="run one case in this process"))
    pa = sub.add_parser("all", help="run the study (each case in a subprocess with limits)")
    pa.add_argument("--out", default=str(HERE / "results" / "proto_linsolve.json"))
    pa.add_argument("--timeout", type=int, default=200)
    pa.add_argument("--mem-gb", type=float, default=8.0)
    pa.add_argument("--only", default=None, help="substring filter on case labels")
    args = ap.parse_args(argv)
    if args.cmd == "case":
        res = run_case(args)
        text = json.dumps(res, indent=1, default=str)
        if args.json:
            Path(args.json).write_text(text)
        print(text)
        return 0
    return run_all(args)


STUDY = [
    # label, argv  (each reproduces one record of benchmarks/results/proto_linsolve.json)
    ("build 5k", ["--size", "5k", "--what", "build", "--spgemm"]),
    ("build 10k", ["--size", "10k", "--what", "build", "--spgemm"]),
    ("direct 2k colamd", ["--size", "2k", "--what", "direct"]),
    ("direct 2k mmd", ["--size", "2k", "--what", "direct", "--ordering", "MMD_AT_PLUS_A"]),
    ("direct 5k colamd", ["--size", "5k", "--what", "direct"]),
    ("amg_full 2k pen1e3", ["--size", "2k", "--what", "amg_full"]),
    ("amg_full 5k pen1 th0.1", ["--size", "5k", "--what", "amg_full", "--penalty", "1", "--theta", "0.1"]),
    ("amg_full geo 5k pen1", ["--size", "5k", "--what", "amg_full", "--penalty", "1", "--theta", "0.1", "--agg", "geo"]),
    ("mf filt2 geo 2k pen1", ["--size", "2k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1", "--penalty", "1"]),
    ("mf filt2 geo 5k pen1", ["--size", "5k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1", "--penalty", "1"]),
    ("mf filt2 geo 10k pen1", ["--size", "10k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1", "--penalty", "1"]),
    ("mf filt2 geo 20k pen1 (30 it timing)", ["--size", "20k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1",
                                               "--penalty", "1", "--maxiter", "30"]),
    ("mf filt2 geo 5k pen1e3", ["--size", "5k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1", "--maxiter", "800"]),
    ("mf filt2 geo 5k pen1 K/mu~10", ["--size", "5k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1", "--penalty", "1",
                                       "--kscale", "0.01"]),
    ("mf filt2 geo 5k pen1 K/mu~100", ["--size", "5k", "--what", "mf", "--aux", "filt2", "--agg", "geo", "--theta", "0.1", "--penalty", "1",
                                        "--kscale", "0.1"]),
    ("mf q1_sri 2k pen1", ["--size", "2k", "--what", "mf", "--aux", "q1_sri", "--penalty", "1", "--maxiter", "400"]),
    ("mf jacobi 2k pen10", ["--size", "2k", "--what", "mf", "--aux", "jacobi", "--penalty", "10", "--maxiter", "600"]),
    ("newton 2k pen1 reuse=step", ["--size", "2k", "--what", "newton", "--penalty", "1", "--reuse", "step"]),
    ("newton 2k pen1 reuse=once", ["--size", "2k", "--what", "newton", "--penalty", "1", "--reuse", "once"]),
    ("pardiso 5k", ["--size", "5k", "--what", "pardiso"]),
    ("pardiso 20k", ["--size", "20k", "--what", "pardiso"]),
]


def run_all(args):
    out_path = Path(args.out)
    results = json.loads(out_path.read_text()) if out_path.exists() else {"cases": {}}
    for label, argv in STUDY:
        if args.only and args.only not in label:
            continue
        print(f"== {label}", flush=True)
        tmp = Path(f"/tmp/proto_linsolve_{os.getpid()}.json")
        lim = int(args.mem_gb * 1024**3)

        def limits(lim=lim):
            resource.setrlimit(resource.RLIMIT_AS, (lim, lim))

        t0 = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, __file__, "case", *argv, "--json", str(tmp)], cwd=HERE.parent,
                                  preexec_fn=limits, timeout=args.timeout, capture_output=True, text=True)
            if proc.returncode == 0:
                rec = json.loads(tmp.read_text())
            else:
                rec = {"failed": f"exit {proc.returncode}", "stderr_tail": proc.stderr[-1500:]}
        except subprocess.TimeoutExpired:
            rec = {"failed": f"timeout after {args.timeout} s"}
        rec["wall_s"] = round(time.perf_counter() - t0, 1)
        rec["argv"] = argv
        results["cases"][label] = rec
        results["machine"] = {"python": sys.version.split()[0], "numpy": np.__version__, "platform": platform.platform(),
                              "cpus": os.cpu_count(), "threads": os.environ.get("OMP_NUM_THREADS")}
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(results, indent=1, default=str))
        print(json.dumps({k: rec.get(k) for k in ("failed", "wall_s", "peak_rss_gb", "iterations", "timings")}, default=str), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
