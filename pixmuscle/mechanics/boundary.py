"""Essential boundary conditions by the penalty method (paper eqs. 9–11, 19) and reaction forces.

RK shape functions are not interpolating (Ψ_J(X_I) ≠ δ_IJ), so a prescribed displacement g acts on
the RK-interpolated displacement u^h(x_c) = Σ_J Ψ_J(x_c) d_J at constraint points x_c through the
penalty energy (the last term of eq. 9, integrated by a quadrature rule on the constrained boundary)

    Π_pen = (β/2) Σ_c w_c Σ_{j constrained} (u^h_j(x_c) − t g_cj)²,

t ∈ [0, 1] the load factor of the step. Its gradient and Hessian are the penalty parts of f_ext
and K in eq. (19): f_pen = β Ψ_cᵀ W (u^h − t g), K_pen = β Ψ_cᵀ W Ψ_c (per component).

Constraint points and quadrature weights w_c (cm²):

* end sets ``x_min, x_max, y_min, y_max, z_min, z_max`` with ``penalty.at = auto`` (default) or
  ``vertices``: the vertices of the nodes' boundary faces on that end, each once with the quarter
  areas of the faces that share it summed (:func:`face_vertices`) — the trapezoidal rule for the
  boundary integral of eq. (9) on the actual end surface of the voxel body. SCNI integrates the
  boundary term of the smoothed gradient on those faces by the same rule
  (:func:`vertex_rule_faces`, :func:`pixmuscle.mechanics.scni.build_scni`), so the penalty rows
  Σ_v w_v Ψ(x_v) are SCNI's own boundary rows and a homogeneous deformation is reproduced exactly
  (the patch test: a roller stretch to round-off, its end gap ∝ 1/β). The field is held on the
  whole face, outer edge included: on a clamped, activated 4 × 4 × 8 block every end-face point
  moves 0.83 % of the largest point displacement at factor 1 (0.01 % at 10³); on the demo 1.12 %.
  The rule has fewer points than the two node layers whose shape functions reach the face, so it
  does not over-constrain (its gap falls as 1/β for large β).
* the same sets with ``penalty.at = centres``: the centre of each of those faces (X_I ± h_k/2 e_k),
  weight = the face area h_i h_j (the midpoint rule, SCNI's rule on every face). It too passes the
  patch test, but it holds the field only at the centres: on the outer edge of the face (half a
  voxel beyond the outermost centres, where the RK field extrapolates the end layer's steep
  gradient) the block moves 7.8 % of the largest point displacement, still 7.4 % with a 10³ times
  stiffer penalty, and the demo 23 %: the constraint leaves the edge free, it is not a penalty
  error. Face centres *and* vertices together, or a 2 × 2 Gauss rule per face, have more points
  than those node layers (over-constrained: the block's reaction rises 2.3–2.4 % from factor 1
  to 10, the Gauss rule leaves the edge at 3.7 %).
* ``bone_surface`` with ``penalty.at = auto`` or ``vertices``: the vertices of the faces its nodes
  share with a bone voxel (:func:`bone_faces`, the tissue–bone interface of the label volume), each
  once with the quarter areas of the faces that share it summed; SCNI integrates those faces by the
  same rule. This is where a voxel finite-element model holds the bone (its element vertices on the
  bone); the nodes themselves lie half a voxel inside the tissue. On the 5k leg the force falls
  from 104.66 N (held at the nodes) to 103.89 N (hex8 on the same voxels: 104.12 N). With
  ``penalty.at = centres``: the centres of those faces, weight = face area.
* any other node set, ``penalty.at = nodes``, and ``point`` conditions: the node itself,
  u^h(X_I); weight = the area of the cell's boundary faces (cm²), or V^(2/3) for a node with none
  (an interior node or a point constraint).

Penalty number (N/cm³): β = factor · M / h_min by default, with M the largest reference
longitudinal tangent modulus max_L,i,J A_L[i, J, i, J] (N/cm², ≈ K + 4μ/3 for an isotropic
material) and h_min the smallest spacing; ``penalty.beta`` sets it directly. Constraint error:
linearised, K d + β Ψᵀ W (Ψ d − g) = f gives for the gap e = Ψ d − g

    e = (I + β S W)⁻¹ e₀,   S = Ψ K⁻¹ Ψᵀ (the flexibility of the body at the constraint points),

e₀ the gap without penalty: a mode of S W with eigenvalue s shrinks by 1 / (1 + β s), so the gap
falls as 1/β only once β s ≫ 1 for every mode it contains, and tenfold β reduces it by a factor
between 1 and 10 before that. At equilibrium
the penalty traction is t_c = −β (u^h − g), so |u^h − g| / h_min ≈ |t_c| / (factor · M): the
traction-to-modulus ratio (a strain measure) divided by the factor. With the default factor 1
the gap is a fraction of the strain times the cell size; on a clamped, activated 4 × 4 × 8 block
the reaction changes by 1.6 % between factor 1 and 10³ at the vertices (gap ratios 4.6, 7.1, 9.5
per tenfold β), 0.1 % at the face centres (ratio 10.0; their constrained limit is 2.4 % softer:
the edges are free), and the iterative solver needs the small factor.

Reaction (sign convention of docs/architecture.md): the force the support exerts on the body,

    R = −β Σ_{c in the set} w_c (u^h(x_c) − t g_c)    (constrained components only), N.

The force a curve reports is R · n_out with n_out the outward normal of the end (+z for z_max,
−z for z_min): positive when the body pulls on the support (tension).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from .config import BoundaryCondition, bc_name
from .scni import Faces, face_vertex_rule

_LOG = logging.getLogger(__name__)

#: node sets whose constraint sits on the end face: name → (axis, outward sign)
END_SETS = {"x_min": (0, -1), "x_max": (0, 1), "y_min": (1, -1), "y_max": (1, 1), "z_min": (2, -1), "z_max": (2, 1)}

SIGN_CONVENTION = (
    "reaction/<set> is the force (N) the support exerts on the body, R = -beta * sum_c w_c (u(x_c) - g_c) "
    "over the constrained components; the force of an end is R . n_out (n_out outward normal, +z for z_max, "
    "-z for z_min): positive = the body pulls on the support (tension)."
)


@dataclasses.dataclass
class Constraints:
    """Penalty constraint points of all boundary conditions.

    Attributes
    ----------
    names : list of str
        Reaction names, one per boundary condition (repeated names are summed).
    points : (C, 3) float
        Constraint points x_c, cm.
    node : (C,) int
        Constrained node of each point.
    weight : (C,) float
        Quadrature weight w_c, cm².
    mask : (C, 3) bool
        Constrained components.
    target : (C, 3) float
        Final prescribed displacement g_c (0 on fixed and free components), cm.
    group : (C,) int
        Index of the boundary condition of each point.
    psi : CSR (C, N)
        Ψ_J(x_c).
    beta : float
        Penalty number, N/cm³.
    """

    names: list
    points: np.ndarray
    node: np.ndarray
    weight: np.ndarray
    mask: np.ndarray
    target: np.ndarray
    group: np.ndarray
    psi: sp.csr_matrix
    beta: float

    @property
    def reaction_names(self) -> list[str]:
        """Unique reaction names in order of first appearance."""
        return list(dict.fromkeys(self.names))

    def displacement(self, d: np.ndarray) -> np.ndarray:
        """u^h(x_c), cm, shape (C, 3)."""
        return self.psi @ d

    def gap(self, d: np.ndarray, t: float) -> np.ndarray:
        """(u^h(x_c) − t g_c) on constrained components, 0 elsewhere; cm, shape (C, 3)."""
        return np.where(self.mask, self.displacement(d) - t * self.target, 0.0)

    def force(self, d: np.ndarray, t: float) -> np.ndarray:
        """Penalty force on the coefficients, f_pen = β Ψᵀ W (u^h − t g), N, shape (N, 3)."""
        return self.psi.T @ (self.beta * self.weight[:, None] * self.gap(d, t))

    def energy(self, d: np.ndarray, t: float) -> float:
        """Π_pen = (β/2) Σ w_c |u^h − t g|², N·cm."""
        gap = self.gap(d, t)
        return 0.5 * self.beta * float(np.sum(self.weight[:, None] * gap**2))

    def _chosen(self, points: np.ndarray | None) -> np.ndarray:
        return np.ones(self.group.size, bool) if points is None else np.asarray(points, bool)

    def reactions(self, d: np.ndarray, t: float, points: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Reaction per name: force (N, shape (3,)) that the support exerts on the body (summed over
        the constraint points, or over those chosen by ``points`` (C,) bool: a rank's own)."""
        per_point = -self.beta * self.weight[:, None] * self.gap(d, t)
        chosen = self._chosen(points)
        out = {name: np.zeros(3) for name in self.reaction_names}
        for b, name in enumerate(self.names):
            out[name] += per_point[(self.group == b) & chosen].sum(axis=0)
        return out

    def prescribed(self, t: float, points: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Prescribed displacement per name at load factor t (cm, (3,); 0 for free components, and
        for a name without constraint points among ``points``)."""
        chosen = self._chosen(points)
        out = {name: np.zeros(3) for name in self.reaction_names}
        for b, name in enumerate(self.names):
            sel = (self.group == b) & chosen
            if np.any(sel):
                out[name] = np.where(self.mask[sel][0], t * self.target[sel][0], out[name])
        return out

    def present(self, points: np.ndarray | None = None) -> dict[str, bool]:
        """Whether each name has constraint points (among ``points``)."""
        chosen = self._chosen(points)
        out = {name: False for name in self.reaction_names}
        for b, name in enumerate(self.names):
            out[name] = out[name] or bool(np.any((self.group == b) & chosen))
        return out

    def gaps(self, d: np.ndarray, t: float, u_nodes: np.ndarray,
             points: np.ndarray | None = None) -> dict[str, dict[str, float]]:
        """How far each boundary condition is from holding exactly, per reaction name (cm).

        ``point_cm``: largest |u^h(x_c) − t g_c| over the constrained components at the
        constraint points (where the penalty acts: end faces or nodes); ``node_cm``: the same at
        the constrained nodes themselves, |u(X_I) − t g| (what a viewer of nodal fields sees).

        Parameters
        ----------
        d : (N, 3) float
            RK coefficients, cm.
        t : float
            Load factor.
        u_nodes : (N, 3) float
            Nodal displacements u(X_I), cm.
        points : (C,) bool, optional
            The constraint points to take (default all; a rank's own).
        """
        at_points = np.abs(self.gap(d, t))
        at_nodes = np.where(self.mask, np.abs(u_nodes[self.node] - t * self.target), 0.0)
        chosen = self._chosen(points)
        out = {name: {"point_cm": 0.0, "node_cm": 0.0} for name in self.reaction_names}
        for b, name in enumerate(self.names):
            sel = (self.group == b) & chosen
            if np.any(sel):
                out[name]["point_cm"] = max(out[name]["point_cm"], float(at_points[sel].max()))
                out[name]["node_cm"] = max(out[name]["node_cm"], float(at_nodes[sel].max()))
        return out

    def constrained_components(self) -> dict[str, np.ndarray]:
        """Constrained components per name, (3,) bool."""
        out = {name: np.zeros(3, bool) for name in self.reaction_names}
        for b, name in enumerate(self.names):
            sel = self.group == b
            if np.any(sel):
                out[name] |= self.mask[sel].any(axis=0)
        return out

    def stiffness(self, n_nodes: int) -> list[sp.csr_matrix]:
        """Penalty stiffness per component j: β Ψᵀ diag(w m_j) Ψ (N × N), N/cm. Components held at
        the same points (equal mask columns: x and y of ends and bone surfaces) share one matrix
        object (read only)."""
        return shared_by_mask(self.mask, lambda j: (self.psi.T @ sp.diags(self.beta * self.weight * self.mask[:, j])
                                                    @ self.psi).tocsr())


def shared_by_mask(mask: np.ndarray, make) -> list:
    """``[make(j) for j in range(3)]``, calling ``make`` once per distinct column of ``mask`` (n, 3)
    bool: components with equal columns get the same object."""
    out = []
    for j in range(3):
        same = next((i for i in range(j) if np.array_equal(mask[:, i], mask[:, j])), None)
        out.append(make(j) if same is None else out[same])
    return out


def penalty_number(A0: np.ndarray, spacing, factor: float) -> float:
    """Default penalty number β = factor · max_L,i,J A0[L, i, J, i, J] / min(spacing), N/cm³."""
    M = max(float(np.max(A0[:, i, J, i, J])) for i in range(3) for J in range(3))
    return float(factor) * M / float(np.min(spacing))


def _boundary_area(faces: Faces, n_nodes: int) -> np.ndarray:
    """Total area of the boundary faces of each cell, cm², shape (N,)."""
    area = np.zeros(n_nodes)
    b = faces.boundary
    cell = faces.cell_of(np.flatnonzero(b))
    np.add.at(area, cell, faces.area[b])
    return area


def check_boundary_conditions(model, bcs: list[BoundaryCondition]) -> None:
    """Check the boundary conditions against a model before any assembly.

    Raises
    ------
    InputError
        A node set the model does not have, or a ``point`` farther than one cell diagonal
        (‖spacing‖) from every node (outside the body, or given in mm instead of cm).
    """
    X = np.asarray(model.X, float)
    h = np.asarray(model.spacing, float)
    for b, bc in enumerate(bcs):
        if bc.nodes is not None and bc.nodes not in model.sets:
            avail = ", ".join(sorted(model.sets)) or "none"
            raise InputError(f"solve.boundary_conditions[{b}].nodes: node set {bc.nodes!r} is not in the model (available: {avail})")
        if bc.point is not None and X.shape[0]:
            p = np.asarray(bc.point, float)
            dist = float(np.sqrt(np.min(np.sum((X - p) ** 2, axis=1))))
            if dist > float(np.linalg.norm(h)):
                raise InputError(f"solve.boundary_conditions[{b}].point: {p.tolist()} cm is {dist:.3g} cm from the nearest "
                                 f"node, more than one cell ({float(np.linalg.norm(h)):.3g} cm) from the body; "
                                 "give a point on or inside the body (cm, model frame)")


def face_vertices(centre: np.ndarray, node: np.ndarray, spacing, axis: int):
    """Trapezoidal-rule points of axis-normal cell faces: their vertices, each once, with the
    quarter areas of the faces that share it summed.

    Parameters
    ----------
    centre : (F, 3) float
        Face centres, cm (faces normal to ``axis``, all in one plane).
    node : (F,) int
        Node of each face.
    spacing : (3,) float
        Cell edge lengths h, cm.
    axis : int
        Normal axis k of the faces.

    Returns
    -------
    points : (V, 3) float
        Vertices, cm.
    node : (V,) int
        Node of the first face at each vertex.
    weight : (V,) float
        Σ over the faces at the vertex of area/4, cm² (sums to the faces' total area).
    """
    h = np.asarray(spacing, float)
    i, j = [a for a in range(3) if a != axis]
    offsets = np.zeros((4, 3))
    offsets[:, i] = [-0.5, 0.5, -0.5, 0.5]
    offsets[:, j] = [-0.5, -0.5, 0.5, 0.5]
    pts = (centre[:, None, :] + offsets[None] * h).reshape(-1, 3)
    if pts.shape[0] == 0:
        return pts, np.zeros(0, np.int64), np.zeros(0)
    key = np.rint(2 * (pts - pts.min(axis=0)) / h).astype(np.int64)   # half-voxel grid index
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    weight = np.bincount(inv.ravel(), minlength=first.size) * (h[i] * h[j] / 4)
    return pts[first], np.repeat(np.asarray(node, np.int64), 4)[first], weight


def end_rule(at: str) -> str:
    """Where end sets are held for ``penalty.at``: ``"vertices"`` (``auto``, ``vertices``), ``"centres"`` or ``"nodes"``."""
    return "vertices" if at in ("auto", "vertices") else at


def _end_faces(faces: Faces, idx: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Face of each node of an end set on that end, and whether it is a boundary face.

    Returns
    -------
    face : (n,) int32
        Index into ``faces`` of each node's face on the end ``name`` (e.g. its −z face for ``z_min``).
    on_end : (n,) bool
        The face is on the boundary (the node's cell has no neighbour beyond it).
    """
    k, s = END_SETS[name]
    face = faces.plus[k, idx] if s > 0 else faces.minus[k, idx]
    return face, faces.boundary[face]


def bone_faces(model, faces: Faces, idx: np.ndarray) -> np.ndarray:
    """Boundary faces of the cells ``idx`` with a bone voxel beyond them (where ``bone_surface`` meets the bone).

    Parameters
    ----------
    model : Model
        Its ``ijk``, ``shape`` and ``bone_ijk`` (None or empty: no bone, no faces).
    faces : Faces
    idx : (n,) int
        Cells (nodes).

    Returns
    -------
    (F_b,) int64
        Sorted face indices into ``faces``.
    """
    bone = model.bone_ijk
    idx = np.asarray(idx, np.int64)
    if bone is None or len(bone) == 0 or idx.size == 0:
        return np.zeros(0, np.int64)
    is_bone = np.zeros(np.asarray(model.shape, np.int64) + 2, bool)   # padded by one voxel on every side
    b = np.asarray(bone, np.int64) + 1
    is_bone[b[:, 0], b[:, 1], b[:, 2]] = True
    f = np.concatenate([faces.plus[:, idx].ravel(), faces.minus[:, idx].ravel()]).astype(np.int64)
    f = np.unique(f[faces.boundary[f]])
    cell = faces.cell_of(f)
    beyond = np.asarray(model.ijk, np.int64)[cell] + 1
    beyond[np.arange(f.size), faces.axis[f]] += faces.normal_sign[f].astype(np.int64)
    return f[is_bone[beyond[:, 0], beyond[:, 1], beyond[:, 2]]]


def _on_faces(faces: Faces, face: np.ndarray, spacing, rule: str):
    """Points, cells and weights (cm²) of a boundary rule on ``face``: their vertices, each once with
    Σ area/4 of the faces that share it (``rule = "vertices"``), or their centres with their areas."""
    cell = faces.cell_of(face)
    if rule == "centres":
        return faces.centre[face], cell, faces.area[face].copy()
    points, avg = face_vertex_rule(faces, face, spacing)
    if points.shape[0] == 0:
        return points, np.zeros(0, np.int64), np.zeros(0)
    per_vertex = avg.T.tocsr()                     # (V, F_v): the faces at each vertex
    return points, cell[per_vertex.indices[per_vertex.indptr[:-1]]], per_vertex @ faces.area[face]


def vertex_rule_faces(model, bcs: list[BoundaryCondition], faces: Faces, *, at: str = "auto") -> np.ndarray:
    """Boundary faces on which the penalty integrates by the vertex (trapezoidal) rule.

    With ``at = "auto"`` or ``"vertices"``: the end faces of every end set (``x_min`` … ``z_max``) that a boundary
    condition constrains, and the bone faces of ``bone_surface`` (:func:`bone_faces`) when it is constrained, each once; SCNI must integrate its boundary term on these faces by the
    same rule (:func:`pixmuscle.mechanics.scni.build_scni`, ``vertex_faces``) so that the penalty
    rows equal SCNI's boundary rows. Empty otherwise.

    Returns
    -------
    (F_v,) int64
        Sorted face indices into ``faces``.
    """
    if end_rule(at) != "vertices":
        return np.zeros(0, np.int64)
    out = [np.zeros(0, np.int64)]
    n = np.asarray(model.X).shape[0]
    for bc in bcs:
        if bc.nodes in END_SETS and bc.nodes in model.sets:
            idx = np.unique(np.asarray(model.sets[bc.nodes], np.int64))
            idx = idx[(idx >= 0) & (idx < n)]
            face, on_end = _end_faces(faces, idx, bc.nodes)
            out.append(face[on_end].astype(np.int64))
        elif bc.nodes == "bone_surface" and bc.nodes in model.sets:
            idx = np.unique(np.asarray(model.sets[bc.nodes], np.int64))
            out.append(bone_faces(model, faces, idx[(idx >= 0) & (idx < n)]))
    return np.unique(np.concatenate(out))


def constraint_points(model, bcs: list[BoundaryCondition], faces: Faces, *, at: str = "auto"):
    """Constraint points, weights and targets of the boundary conditions (no shape functions yet).

    Returns
    -------
    names, points, node, weight, mask, target, group
        See :class:`Constraints`.

    Raises
    ------
    InputError
        See :func:`check_boundary_conditions`.
    """
    check_boundary_conditions(model, bcs)
    X = np.asarray(model.X, float)
    n = X.shape[0]
    h = np.asarray(model.spacing, float)
    vol = float(np.prod(h))
    bnd_area = _boundary_area(faces, n)
    names, pts, nodes, wts, masks, targets, groups = [], [], [], [], [], [], []
    for b, bc in enumerate(bcs):
        name = bc_name(bc, b)
        comps, values = bc.components()
        mask = np.zeros(3, bool)
        mask[comps] = True
        target = np.zeros(3)
        target[comps] = values
        if bc.point is not None:
            p = np.asarray(bc.point, float)
            idx = np.array([int(np.argmin(np.sum((X - p) ** 2, axis=1)))])
            where = X[idx]
            w = np.full(1, vol ** (2.0 / 3.0))
        else:
            idx = np.unique(np.asarray(model.sets[bc.nodes], np.int64))
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise InputError(f"model set {bc.nodes!r}: node index out of range 0..{n - 1}")
            if idx.size == 0:
                _LOG.warning("boundary condition %d: node set %r is empty; it constrains nothing", b, bc.nodes)
            where = X[idx].copy()
            if bc.nodes in END_SETS:
                k, s = END_SETS[bc.nodes]
                w = np.full(idx.size, vol / h[k])
                rule = end_rule(at)
                if rule in ("centres", "vertices"):
                    _, on_end = _end_faces(faces, idx, bc.nodes)
                    where[on_end, k] += s * h[k] / 2
                if rule == "vertices":
                    vpts, vnode, vw = face_vertices(where[on_end], idx[on_end], h, k)
                    where = np.concatenate([vpts, where[~on_end]])
                    idx = np.concatenate([vnode, idx[~on_end]])
                    w = np.concatenate([vw, w[~on_end]])
            elif bc.nodes == "bone_surface" and end_rule(at) in ("centres", "vertices"):
                face = bone_faces(model, faces, idx)
                fpts, fnode, fw = _on_faces(faces, face, h, end_rule(at))
                touching = faces.cell_of(face)
                rest = np.setdiff1d(idx, touching)         # nodes without a face on bone (a set edited by hand)
                w = bnd_area[rest].copy()
                w[w == 0] = vol ** (2.0 / 3.0)
                where, idx, w = np.concatenate([fpts, X[rest]]), np.concatenate([fnode, rest]), np.concatenate([fw, w])
            else:
                w = bnd_area[idx].copy()
                w[w == 0] = vol ** (2.0 / 3.0)
        names.append(name)
        pts.append(where)
        nodes.append(idx)
        wts.append(w)
        masks.append(np.broadcast_to(mask, (idx.size, 3)))
        targets.append(np.broadcast_to(target, (idx.size, 3)))
        groups.append(np.full(idx.size, b))
    return (names, np.concatenate(pts).reshape(-1, 3), np.concatenate(nodes).astype(np.int64), np.concatenate(wts),
            np.concatenate(masks).reshape(-1, 3), np.concatenate(targets).reshape(-1, 3), np.concatenate(groups))


def build_constraints(model, bcs: list[BoundaryCondition], faces: Faces, support, beta: float, *, kernel="cubic",
                      order=1, support_shape="box", at: str = "auto", singular: str = "raise") -> Constraints:
    """Constraint points with their shape functions Ψ(x_c) and the penalty number β (N/cm³)."""
    from ..rk import shape_functions

    names, pts, node, w, mask, target, group = constraint_points(model, bcs, faces, at=at)
    psi = sp.csr_matrix(shape_functions(np.asarray(model.X, float), pts, support, kernel=kernel, order=order,
                                        support_shape=support_shape, singular=singular)) if len(pts) else sp.csr_matrix((0, model.X.shape[0]))
    return Constraints(names=names, points=pts, node=node, weight=w, mask=mask, target=target, group=group, psi=psi,
                       beta=float(beta))
