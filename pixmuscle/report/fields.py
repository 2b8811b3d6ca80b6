"""Fields for ParaView: the model as voxel cells, one VTU per load step, a PVD collection, and the
same series as XDMF + HDF5 for large models (writers: :mod:`pixmuscle.io.vtu`, :mod:`pixmuscle.io.xdmf`).

Every node of the pixel-point model owns an axis-aligned integration cell of size ``grid/spacing``
centred on it (docs/architecture.md, "Model frame"); the files hold exactly these cells as VTK
hexahedra, so ParaView's Slice, Clip, Threshold and Contour return pieces of the body at any
plane. Nodal values are **cell data** (one value per node = per cell). The displacement is also
**point data**: at every cell corner x the model's own field there, the RK approximation
u(x) = Σ_J Ψ_J(x) d_J with the solve's shape functions and coefficients
(:func:`corner_displacements`), for *Warp By Vector*: held ends stay where the penalty holds
them (end sets: at the vertices of their end faces, which are these corners). Stresses are cell data only: the model's stress is the smoothed
(SCNI) stress of each integration cell, with a material that changes from cell to cell;
ParaView's *Cell Data to Point Data* smooths it for colouring. The field-data array ``notes``
says so in the files. Coordinates are the **reference** configuration, cm.

Arrays (units in the names and in the field-data array ``units``):

``displacement [cm]`` (3, cells and points), ``fiber_direction [1]`` (3, cells), ``tissue`` (cells:
1 muscle, 2 connective tissue, 3 fat; names in field data ``tissue_names``), ``muscle_id`` (cells:
0 or 1..M; names in ``muscle_names``, index = id), ``imat`` (cells: 1 where the fat node counts as
IMAT), ``max_principal_cauchy [N/cm^2]`` (cells), ``cauchy [N/cm^2]`` (cells; 6 components XX YY ZZ
XY YZ XZ, VTK's symmetric-tensor order, component names stored; the XDMF writer stores them in
the XDMF ``Tensor6`` order). At the state whose strong ellipticity the results record (the last
converged one, :class:`pixmuscle.mechanics.results.NodeEllipticity`) also
``acoustic_minimum [N/cm^2]`` (cells: the material law's smallest acoustic-tensor eigenvalue) and
``non_elliptic`` (cells: 1 where it is < 0, the law not strongly elliptic); absent at the other
states and for results files that do not record it.

Frames: ``"model"`` writes the grid-aligned model frame (cm). ``"rotated"`` applies
``grid/rotation`` R about the frame origin: points and vectors become ``R x``, stresses ``R σ Rᵀ``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ..mechanics.results import StepFields
from ..model.tissues import TISSUE_NAMES

#: corner offsets of a voxel in VTK_HEXAHEDRON order
HEX_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
CAUCHY_COMPONENTS = ("XX", "YY", "ZZ", "XY", "YZ", "XZ")
DISPLACEMENT = "displacement [cm]"
FIBER = "fiber_direction [1]"
CAUCHY = "cauchy [N/cm^2]"
MAX_PRINCIPAL = "max_principal_cauchy [N/cm^2]"
ACOUSTIC_MINIMUM = "acoustic_minimum [N/cm^2]"
NON_ELLIPTIC = "non_elliptic"
UNITS = (f"{DISPLACEMENT}: cm", f"{CAUCHY}: N/cm^2 (components XX YY ZZ XY YZ XZ)", f"{MAX_PRINCIPAL}: N/cm^2",
         f"{FIBER}: unit vector", "tissue: code, see tissue_names", "muscle_id: index into muscle_names",
         "imat: 1 = fat counted as IMAT", "coordinates: cm, reference configuration", "time: activation alpha",
         f"{ACOUSTIC_MINIMUM}: N/cm^2, smallest acoustic-tensor eigenvalue of the material law (last converged step)",
         f"{NON_ELLIPTIC}: 1 = the material law is not strongly elliptic at the node ({ACOUSTIC_MINIMUM} < 0)")
#: the field-data array ``notes``: what the point data are
NOTE_POINTS = (f"{DISPLACEMENT} point data: the RK approximation u(x) = sum_J Psi_J(x) d_J at the cell corners, "
               "with the solve's shape functions (kernel, basis, supports) and coefficients d_J")
NOTE_NO_POINTS = (f"{DISPLACEMENT}: cell data only (the results file holds no RK coefficients /steps/d or no "
                  "readable solve configuration to evaluate the field at the cell corners)")
NOTE_STRESS = (f"{CAUCHY}, {MAX_PRINCIPAL}: cell data only, the smoothed (SCNI) stress of each node's integration "
               "cell; ParaView's Cell Data to Point Data smooths them for colouring")


def voigt_to_tensor(v: np.ndarray) -> np.ndarray:
    """(N, 6) Voigt (xx yy zz xy yz xz) → (N, 3, 3) symmetric tensors."""
    xx, yy, zz, xy, yz, xz = np.moveaxis(np.asarray(v, float), -1, 0)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def rotate_voigt(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rotate symmetric tensors given in Voigt order: ``R σ Rᵀ``.

    Parameters
    ----------
    v : (N, 6) float64
        xx yy zz xy yz xz.
    R : (3, 3) float64

    Returns
    -------
    (N, 6) float64
    """
    t = np.einsum("ij,njk,lk->nil", R, voigt_to_tensor(v), R)
    return np.stack([t[:, 0, 0], t[:, 1, 1], t[:, 2, 2], t[:, 0, 1], t[:, 1, 2], t[:, 0, 2]], axis=-1)


def voxel_hexahedra(ijk: np.ndarray, origin, spacing) -> tuple[np.ndarray, np.ndarray]:
    """The integration cells of the nodes as hexahedra sharing their corners.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel index of each node.
    origin, spacing : (3,) float, cm

    Returns
    -------
    points : (P, 3) float64, cm
        Cell corners, ``origin + (corner - 1/2) * spacing``.
    hexa : (N, 8) int64
        Corner indices of each node's cell, VTK_HEXAHEDRON order; cell n belongs to node n.
    """
    ijk = np.asarray(ijk, np.int64)
    lo = ijk.min(axis=0) if ijk.size else np.zeros(3, np.int64)
    corner = (ijk - lo)[:, None, :] + HEX_CORNERS[None]          # (N, 8, 3)
    dims = corner.reshape(-1, 3).max(axis=0) + 1 if ijk.size else np.ones(3, np.int64)
    flat = np.ravel_multi_index(tuple(corner.reshape(-1, 3).T), tuple(dims))
    uniq, inv = np.unique(flat, return_inverse=True)
    pts = np.stack(np.unravel_index(uniq, tuple(dims)), axis=-1) + lo
    points = np.asarray(origin, float) + (pts - 0.5) * np.asarray(spacing, float)
    return points, inv.reshape(-1, 8).astype(np.int64)


def cells_to_points(hexa: np.ndarray, values: np.ndarray, n_points: int) -> np.ndarray:
    """Mean of the cell values around each corner point.

    Parameters
    ----------
    hexa : (N, 8) int
    values : (N,) or (N, c) float
    n_points : int

    Returns
    -------
    (P,) or (P, c) float64
    """
    v = np.asarray(values, float)
    flat = v.reshape(v.shape[0], -1)
    idx = hexa.ravel()
    count = np.bincount(idx, minlength=n_points).astype(float)
    out = np.stack([np.bincount(idx, weights=np.repeat(flat[:, c], 8), minlength=n_points) for c in range(flat.shape[1])],
                   axis=-1)  # loop over components (≤ 6)
    out /= np.maximum(count, 1.0)[:, None]
    return out.reshape((n_points, *v.shape[1:]))


def step_mesh(ijk: np.ndarray, origin, spacing, fields: StepFields, *, fiber: np.ndarray, tissue: np.ndarray,
              muscle_id: np.ndarray, imat: np.ndarray | None = None, rotation: np.ndarray | None = None,
              cells: tuple | None = None, point_u: np.ndarray | None = None):
    """A meshio mesh of one step: the model's voxel cells with cell data and point data.

    Parameters
    ----------
    ijk : (N, 3) int; origin, spacing : (3,) cm
        The model grid.
    fields : StepFields
        Displacement (cm) and stresses (N/cm²) of the step at the nodes (cell data); its
        ``acoustic_minimum`` (N/cm²), when given, as ``acoustic_minimum [N/cm^2]`` and the 0/1
        ``non_elliptic``.
    fiber : (N, 3); tissue, muscle_id : (N,)
        Model data.
    imat : (N,) bool, optional
    rotation : (3, 3), optional
        Applied to points, vectors and tensors when given.
    cells : (points, hexa), optional
        The output of :func:`voxel_hexahedra` (computed when not given).
    point_u : (P, 3) float, cm, optional
        Displacement at the cell corners (model frame; :func:`corner_displacements`); the point
        data ``displacement [cm]`` when given, none otherwise.
    """
    import meshio

    points, hexa = cells if cells is not None else voxel_hexahedra(ijk, origin, spacing)
    u, fib, cau = np.asarray(fields.u, float), np.asarray(fiber, float), fields.cauchy
    pu = None if point_u is None else np.asarray(point_u, float)
    if rotation is not None:
        R = np.asarray(rotation, float)
        points, u, fib = points @ R.T, u @ R.T, fib @ R.T
        pu = None if pu is None else pu @ R.T
        cau = rotate_voigt(cau, R) if cau is not None else None
    cd = {DISPLACEMENT: u, FIBER: fib, "tissue": np.asarray(tissue, np.int32), "muscle_id": np.asarray(muscle_id, np.int32)}
    pd = {} if pu is None else {DISPLACEMENT: pu}
    if imat is not None:
        cd["imat"] = np.asarray(imat, np.int32)
    if fields.max_principal is not None:
        cd[MAX_PRINCIPAL] = np.asarray(fields.max_principal, np.float64)
    if cau is not None:
        cd[CAUCHY] = np.asarray(cau, np.float64)
    q = getattr(fields, "acoustic_minimum", None)
    if q is not None:  # a scalar of the law at F: the same in every frame
        cd[ACOUSTIC_MINIMUM] = np.asarray(q, np.float64)
        cd[NON_ELLIPTIC] = (np.asarray(q) < 0.0).astype(np.int32)
    return meshio.Mesh(np.ascontiguousarray(points, np.float64), [("hexahedron", hexa)],
                       point_data={k: np.ascontiguousarray(v) for k, v in pd.items()},
                       cell_data={k: [np.ascontiguousarray(v)] for k, v in cd.items()})


def field_data(muscle_names: Sequence[str], *, point_displacement: bool = True) -> dict[str, list[str]]:
    """The files' field data: ``units``, ``tissue_names`` (index = code), ``muscle_names`` (index = id)
    and ``notes`` (what the point data are)."""
    return {"units": list(UNITS), "tissue_names": ["background", *[TISSUE_NAMES.get(c, str(c)) for c in (1, 2, 3)]],
            "muscle_names": ["(not muscle)", *muscle_names],
            "notes": [NOTE_POINTS if point_displacement else NOTE_NO_POINTS, NOTE_STRESS]}


def rk_support(res) -> tuple[np.ndarray, dict]:
    """The RK shape-function options a solve used, from its results file.

    Reads the ``support`` section (and ``penalty.at``) of the solve configuration stored in the
    file (defaults where it is not given, as the solve did) and, when the solve enlarged supports around thin features
    (``solver_info["supports_enlarged"]``, or not recorded), computes them again with the solve's
    own function (:func:`pixmuscle.mechanics.solve.rk_supports`).

    Returns
    -------
    support : (3,) or (N, 3) float64, cm
    options : dict
        ``kernel``, ``order``, ``support_shape`` for :func:`pixmuscle.rk.shape_functions`.

    Raises
    ------
    InputError
        The stored configuration cannot be read.
    """
    import yaml

    from ..config import parse_section
    from ..errors import InputError
    from ..mechanics.boundary import end_rule
    from ..mechanics.config import SupportConfig
    from ..mechanics.scni import support_radius
    from ..mechanics.solve import rk_supports

    text = (res.meta or {}).get("config") or ""
    try:
        raw = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as exc:
        raise InputError(f"{(res.meta or {}).get('path', 'results')}: attribute config is not YAML: {exc}") from None
    penalty = raw.get("penalty") if isinstance(raw, dict) else None
    corners = end_rule(penalty.get("at", "auto") if isinstance(penalty, dict) else "auto") == "vertices"
    raw = raw.get("support") if isinstance(raw, dict) else None
    sc = parse_section(SupportConfig, raw or {}, "solve.support")
    m = res.model
    enlarged = (res.info or {}).get("supports_enlarged")
    if enlarged is None or int(enlarged) > 0:
        support = rk_supports(m, sc, corners=corners)[0]
    else:
        support = support_radius(m.spacing, sc.a_over_h)
    return support, {"kernel": sc.kernel, "order": sc.order, "support_shape": sc.shape}


def corner_displacements(res, steps: Sequence[int], points: np.ndarray, hexa: np.ndarray) -> tuple[np.ndarray, int]:
    """The model's displacement field at the cell corners for each of ``steps``: u(x) = Σ_J Ψ_J(x) d_J.

    Parameters
    ----------
    res : Results
        With RK coefficients ``d`` and the solve configuration in ``meta["config"]``.
    steps : sequence of int
        Stored states.
    points : (P, 3) float, cm; hexa : (N, 8) int
        Cell corners (model frame) and the corners of each node's cell (:func:`voxel_hexahedra`).

    Returns
    -------
    u : (k, P, 3) float64, cm
    n_fallback : int
        Corners where the RK field is not defined (a singular moment matrix beside a one-voxel
        strand; when end sets are held at their end-face vertices, ``penalty.at`` ``auto`` or
        ``vertices``, the solve's supports cover every corner): there
        ``u`` is the mean of the nodal displacements of the cells around the corner.

    Raises
    ------
    InputError
        No coefficients in the results, or an unreadable solve configuration.
    """
    from ..errors import InputError
    from ..rk import rk_evaluate

    if res.d is None:
        raise InputError(f"{(res.meta or {}).get('path', 'results')}: no /steps/d (RK coefficients)")
    support, options = rk_support(res)
    steps = [int(s) for s in steps]
    d = np.concatenate([np.asarray(res.d[s], float) for s in steps], axis=1)  # (N, 3k): all states at once
    u = rk_evaluate(np.asarray(res.model.X, float), points, support, d, singular="nan", **options)
    bad = ~np.isfinite(u).all(axis=1)
    if bad.any():
        nodal = np.concatenate([np.asarray(res.u[s], float) for s in steps], axis=1)
        u[bad] = cells_to_points(hexa, nodal, points.shape[0])[bad]
    return np.ascontiguousarray(u.reshape(points.shape[0], len(steps), 3).transpose(1, 0, 2)), int(bad.sum())


def vtu_steps(converged: np.ndarray, every_nth: int) -> np.ndarray:
    """Steps to export: converged steps whose index is a multiple of ``every_nth``, plus the last
    converged step.

    Returns
    -------
    (k,) int64, ascending
    """
    conv = np.flatnonzero(np.asarray(converged, bool))
    if conv.size == 0:
        return conv
    keep = conv[conv % every_nth == 0]
    return np.union1d(keep, conv[-1:])


def write_vtu_series(outdir: str | Path, steps: Sequence[int], times: Sequence[float],
                     load_fields: Callable[[int], StepFields], *, ijk, origin, spacing, fiber, tissue, muscle_id,
                     muscle_names: Sequence[str] = (), imat=None, rotation=None, compression: str | None = "zlib",
                     xdmf: bool = False, point_u: Callable[[np.ndarray], np.ndarray] | None = None,
                     progress=None) -> dict:
    """Write ``fields/step_XXXX.vtu`` for each step, ``fields.pvd`` listing them at ``times`` and,
    with ``xdmf``, the same series as ``fields.xdmf`` + ``fields.h5``.

    Parameters
    ----------
    point_u : callable, optional
        ``point_u(points, hexa)`` → (k, P, 3): the displacement at the cell corners ``points``
        (model frame, cm) for each of ``steps`` (:func:`corner_displacements`); without it the
        files hold no point data.

    Returns
    -------
    dict
        ``pvd`` (Path), ``vtu`` (list of Path), ``xdmf`` (Path or None).
    """
    from ..io.vtu import write_pvd, write_vtu
    from ..io.xdmf import XdmfSeries

    outdir = Path(outdir)
    (outdir / "fields").mkdir(parents=True, exist_ok=True)
    cells = voxel_hexahedra(ijk, origin, spacing)
    corner_u = None if point_u is None else point_u(*cells)
    fd = field_data(muscle_names, point_displacement=corner_u is not None)
    rel, paths = [], []
    writer = None
    try:
        for n, (s, t) in enumerate(zip(steps, times, strict=True)):  # loop over load steps
            name = f"fields/step_{int(s):04d}.vtu"
            mesh = step_mesh(ijk, origin, spacing, load_fields(int(s)), fiber=fiber, tissue=tissue, muscle_id=muscle_id,
                             imat=imat, rotation=rotation, cells=cells, point_u=None if corner_u is None else corner_u[n])
            write_vtu(outdir / name, mesh, field_data=fd, component_names={CAUCHY: CAUCHY_COMPONENTS},
                      compression=compression)
            if xdmf:
                if writer is None:
                    writer = XdmfSeries(outdir / "fields.xdmf", mesh.points, mesh.cells[0].data)
                writer.write(float(t), mesh.point_data, mesh.cell_data)
            rel.append(name)
            paths.append(outdir / name)
            if progress is not None:
                progress.advance()
    finally:
        xdmf_path = writer.close() if writer is not None else None
    return {"pvd": write_pvd(outdir / "fields.pvd", rel, times), "vtu": paths, "xdmf": xdmf_path}
