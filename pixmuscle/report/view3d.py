"""A 3-D picture of the model for the report: coloured by muscle and tissue, and the displacement
magnitude and largest principal stress on the deformed body.

Rendered off-screen with VTK (EGL, else OSMesa; no display needed) when the ``vtk`` package is
installed and a render window starts; otherwise drawn with matplotlib's 3-D axes (the outer voxel
faces as a point cloud), and the report says which and why.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..mechanics.results import Results
from ..model.tissues import CONNECTIVE_TISSUE, FAT
from .fields import cells_to_points, voxel_hexahedra

_TISSUE_RGB = {CONNECTIVE_TISSUE: (60, 170, 90), FAT: (235, 200, 70)}


def category_colours(tissue: np.ndarray, muscle_id: np.ndarray, n_muscles: int) -> np.ndarray:
    """(N, 3) uint8: one colour per muscle (tab10/tab20), green connective tissue, yellow fat."""
    import matplotlib

    cmap = matplotlib.colormaps["tab10" if n_muscles <= 10 else "tab20"]
    rgb = np.zeros((tissue.shape[0], 3), np.uint8)
    mus = np.array([[int(255 * c) for c in cmap(i % cmap.N)[:3]] for i in range(max(n_muscles, 1))], np.uint8)
    m = (muscle_id > 0) & (tissue == 1)
    rgb[m] = mus[(muscle_id[m] - 1) % len(mus)]
    rgb[(tissue == 1) & ~m] = (200, 80, 80)
    for code, c in _TISSUE_RGB.items():
        rgb[tissue == code] = c
    return rgb


def render_model(res: Results, step: int, path: str | Path, *, dpi: int = 120) -> tuple[Path | None, str]:
    """Write the three-panel 3-D view of state ``step``; returns (path, how it was drawn)."""
    path = Path(path)
    m = res.model
    fields = res.step(step)
    width = int(13 * dpi)
    try:
        return _render_vtk(res, fields, path, width), "VTK, off-screen"
    except Exception as exc:  # no vtk, no EGL/OSMesa: fall back, and say why
        reason = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
    _render_matplotlib(m, fields, path, dpi)
    return path, f"matplotlib 3-D point cloud (VTK off-screen rendering unavailable: {reason})"


def _render_vtk(res: Results, fields, path: Path, width: int) -> Path:
    import vtkmodules.vtkRenderingOpenGL2 as gl
    from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
    from vtkmodules.vtkCommonCore import vtkObject, vtkPoints
    from vtkmodules.vtkCommonDataModel import VTK_HEXAHEDRON, vtkCellArray, vtkUnstructuredGrid
    from vtkmodules.vtkFiltersGeometry import vtkDataSetSurfaceFilter
    from vtkmodules.vtkIOImage import vtkPNGWriter
    from vtkmodules.vtkRenderingAnnotation import vtkScalarBarActor
    from vtkmodules.vtkRenderingCore import (
        vtkActor,
        vtkDataSetMapper,
        vtkRenderer,
        vtkTextActor,
        vtkWindowToImageFilter,
    )

    vtkObject.GlobalWarningDisplayOff()
    from vtkmodules.vtkCommonCore import vtkLookupTable

    m = res.model
    # cut-away: the half y <= centre, so that the cross-section with the muscles is seen
    keep = m.X[:, 1] <= np.median(m.X[:, 1])
    points, hexa = voxel_hexahedra(m.ijk[keep], m.origin, m.spacing)
    u_pts = cells_to_points(hexa, fields.u[keep], points.shape[0])
    umag = np.linalg.norm(fields.u[keep], axis=1)
    stress = None if fields.max_principal is None else fields.max_principal[keep]

    def lut(name):
        import matplotlib

        cm = matplotlib.colormaps[name]
        t = vtkLookupTable()
        t.SetNumberOfTableValues(256)
        for i in range(256):  # 256 table entries
            t.SetTableValue(i, *cm(i / 255.0))
        t.Build()
        return t

    def grid(pts, scalars=None, rgb=None):
        g = vtkUnstructuredGrid()
        p = vtkPoints()
        p.SetData(numpy_to_vtk(np.ascontiguousarray(pts, float), deep=True))
        g.SetPoints(p)
        ca = vtkCellArray()
        ca.SetData(numpy_to_vtkIdTypeArray(np.arange(0, 8 * hexa.shape[0] + 1, 8, dtype=np.int64), deep=True),
                   numpy_to_vtkIdTypeArray(np.ascontiguousarray(hexa.ravel(), np.int64), deep=True))
        g.SetCells(VTK_HEXAHEDRON, ca)
        arr = numpy_to_vtk(np.ascontiguousarray(rgb if rgb is not None else scalars), deep=True)
        arr.SetName("c")
        g.GetCellData().SetScalars(arr)
        surf = vtkDataSetSurfaceFilter()
        surf.SetInputData(g)
        surf.Update()
        return surf.GetOutput()

    colours = category_colours(m.tissue[keep], m.muscle_id[keep], len(m.muscle_names))
    panels = [("muscles and tissues (reference, cut-away)", grid(points, rgb=colours), None),
              ("|u| [cm], deformed body", grid(points + u_pts, scalars=umag), (umag, "|u| [cm]", "viridis"))]
    if stress is not None:
        panels.append(("max principal Cauchy stress, deformed", grid(points + u_pts, scalars=stress),
                       (stress, "N/cm^2", "magma")))
    win = None
    for cls in ("vtkEGLRenderWindow", "vtkOSOpenGLRenderWindow"):
        try:
            win = getattr(gl, cls)()
            win.SetOffScreenRendering(1)
            win.SetSize(width, int(width * 0.36))
            win.Render()
            break
        except Exception:  # try the next off-screen backend
            win = None
    if win is None:
        raise RuntimeError("no off-screen OpenGL context (EGL or OSMesa)")
    n = len(panels)
    centre = points.mean(axis=0)
    span = float(np.ptp(points, axis=0).max())
    for i, (title, poly, sc) in enumerate(panels):
        ren = vtkRenderer()
        ren.SetViewport(i / n, 0.0, (i + 1) / n, 1.0)
        ren.SetBackground(1.0, 1.0, 1.0)
        mapper = vtkDataSetMapper()
        mapper.SetInputData(poly)
        mapper.SetScalarModeToUseCellData()
        if sc is None:
            mapper.SetColorModeToDirectScalars()
        else:
            vals = np.asarray(sc[0], float)
            fin = vals[np.isfinite(vals)]
            lo, hi = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
            mapper.SetLookupTable(lut(sc[2]))
            mapper.SetScalarRange(lo, hi if hi > lo else lo + 1e-12)
            mapper.SetUseLookupTableScalarRange(False)
            bar = vtkScalarBarActor()
            bar.SetLookupTable(mapper.GetLookupTable())
            bar.SetTitle(sc[1])
            bar.SetNumberOfLabels(4)
            bar.SetWidth(0.12)
            bar.SetHeight(0.6)
            bar.SetPosition(0.86, 0.2)
            for prop in (bar.GetTitleTextProperty(), bar.GetLabelTextProperty()):
                prop.SetColor(0.1, 0.1, 0.1)
            ren.AddViewProp(bar)
        actor = vtkActor()
        actor.SetMapper(mapper)
        ren.AddActor(actor)
        text = vtkTextActor()
        text.SetInput(title)
        text.GetTextProperty().SetColor(0.1, 0.1, 0.1)
        text.GetTextProperty().SetFontSize(max(11, width // 110))
        text.SetPosition(8, int(width * 0.36) - max(11, width // 110) - 12)
        ren.AddViewProp(text)
        cam = ren.GetActiveCamera()
        cam.SetFocalPoint(*centre)
        cam.SetPosition(*(centre + span * np.array([1.2, 2.4, 1.3])))
        cam.SetViewUp(0.0, 0.0, 1.0)
        ren.ResetCamera()
        win.AddRenderer(ren)
    win.Render()
    grab = vtkWindowToImageFilter()
    grab.SetInput(win)
    grab.Update()
    writer = vtkPNGWriter()
    writer.SetFileName(str(path))
    writer.SetInputConnection(grab.GetOutputPort())
    writer.Write()
    win.Finalize()
    return path


def _render_matplotlib(m, fields, path: Path, dpi: int) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    X = np.asarray(m.X, float)
    u = np.asarray(fields.u, float)
    panels = [("muscles and tissues (reference)", X, category_colours(m.tissue, m.muscle_id, len(m.muscle_names)) / 255.0,
               None), ("|u| [cm], deformed", X + u, np.linalg.norm(u, axis=1), "|u| [cm]")]
    if fields.max_principal is not None:
        panels.append(("max principal Cauchy stress, deformed", X + u, fields.max_principal, "N/cm²"))
    fig = plt.figure(figsize=(13.0, 4.6), layout="constrained")
    for i, (title, P, c, lab) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), i + 1, projection="3d")
        sc = ax.scatter(P[:, 0], P[:, 1], P[:, 2], c=c, s=2, depthshade=False)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x [cm]")
        ax.set_ylabel("y [cm]")
        ax.set_zlabel("z [cm]")
        ax.set_box_aspect(np.ptp(P, axis=0) + 1e-9)
        if lab:
            fig.colorbar(sc, ax=ax, label=lab, shrink=0.6)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
