"""Configuration of the ``solve`` stage (section ``solve:`` of the YAML file).

Every class is a frozen dataclass validated by :func:`pixmuscle.config.parse_section`; defaults are
the paper's choices (cubic B-spline kernel, linear basis, a/h = 1.65; Table 1 and 2 material
constants, with σ_max = 30 N/cm² and λ̂0 = 1.0 from the errata; the material sections are derived
from the registered laws' own dataclasses). Example::

    solve:
      steps: 10
      activation: {from: 0.0, to: 0.95}
      boundary_conditions:
        - {nodes: z_min, fix: [x, y, z]}
        - {nodes: z_max, displace: {z: 2.0}}
        - {nodes: bone_surface, fix: [x, y]}

Units: cm, N, N/cm².
"""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Any, Literal

from .linsolve import BACKENDS, AutoOptions
from .materials import DEFAULTS, LAWS

#: most load steps of one solve (docs/failures.md): a sweep needs 10–20; cut-backs refine by themselves
MAX_STEPS = 1000

AXES = ("x", "y", "z")


@dataclasses.dataclass(frozen=True)
class BoundaryCondition:
    """One essential boundary condition, imposed by the penalty method (paper eqs. 9–11).

    Exactly one of ``nodes`` (a node-set name of the model, e.g. ``z_min``) and ``point``
    (coordinates in cm; the node nearest to it is constrained) must be given. Each component is
    free unless listed in ``fix`` (displacement 0) or ``displace`` (prescribed displacement in cm,
    reached at the last load step and ramped linearly over the steps).
    """

    nodes: str | None = field(default=None, metadata={"doc": "name of a node set of the model (z_min, z_max, bone_surface, ...)"})
    point: tuple[float, ...] | None = field(default=None, metadata={"doc": "[x, y, z] in cm: constrain the node nearest to this point"})
    fix: list[Literal["x", "y", "z"]] = field(default_factory=list, metadata={"doc": "components held at zero displacement"})
    displace: dict[str, float] = field(default_factory=dict, metadata={"doc": "prescribed displacement per component, cm (final value)"})
    name: str | None = field(default=None, metadata={"doc": "name of the reaction-force entry (default: the set name, or point<i>)"})

    def __post_init__(self):
        if (self.nodes is None) == (self.point is None):
            raise ValueError("a boundary condition needs exactly one of 'nodes' (a node-set name) or 'point' ([x, y, z] cm)")
        if self.point is not None and len(self.point) != 3:
            raise ValueError(f"'point' must have 3 coordinates [x, y, z] (cm), got {len(self.point)}")
        bad = [k for k in self.displace if k not in AXES]
        if bad:
            raise ValueError(f"'displace' keys must be x, y or z, got {bad[0]!r}")
        both = sorted(set(self.fix) & set(self.displace))
        if both:
            raise ValueError(f"component {both[0]!r} is both fixed and displaced")
        if len(set(self.fix)) != len(self.fix):
            raise ValueError(f"'fix' lists a component twice: {self.fix}")
        if not self.fix and not self.displace:
            raise ValueError("a boundary condition must fix or displace at least one component")

    def components(self) -> tuple[list[int], list[float]]:
        """Constrained component indices (0..2) and their final prescribed values (cm)."""
        comps, values = [], []
        for i, a in enumerate(AXES):
            if a in self.fix:
                comps.append(i)
                values.append(0.0)
            elif a in self.displace:
                comps.append(i)
                values.append(float(self.displace[a]))
        return comps, values


def _law(tissue: str):
    """Field of ``solve.materials.<tissue>``: ``{law: <name>, …constants}``, default the tissue's law."""
    default = DEFAULTS[tissue]
    return field(default=default, metadata={"registry": LAWS, "default": default,
                                            "doc": f"{{law: name, …constants}}: material law ({', '.join(LAWS.names())}), "
                                                   f"default {LAWS.entry_of(default).name} with the paper's constants"})


@dataclasses.dataclass(frozen=True)
class MaterialsConfig:
    """Material law and constants per tissue (N/cm²), :mod:`pixmuscle.mechanics.materials`.

    Each entry is ``{law: <name>, …constants}``; without ``law`` the tissue's default law (muscle:
    ``blemker``, eqs. 22–26; connective tissue and fat: ``yeoh``, eq. 27) with the constants given
    overriding Tables 1–2, e.g. ``muscle: {sigma_max: 25}``.
    """

    muscle: Any = _law("muscle")
    connective_tissue: Any = _law("connective_tissue")
    fat: Any = _law("fat")


@dataclasses.dataclass(frozen=True)
class SupportConfig:
    """RK shape functions (paper §2 and §5): kernel, basis order and support a = (a/h)·spacing per axis."""

    kernel: Literal["tent", "cubic", "quartic", "quintic"] = "cubic"
    order: int = field(default=1, metadata={"range": (1, 2), "doc": "order n of the complete monomial basis"})
    a_over_h: tuple[float, ...] = field(default=(1.65, 1.65, 1.65), metadata={"gt": 0, "doc": "normalised support a/h per axis (x, y, z)"})
    shape: Literal["box", "sphere"] = field(default="box", metadata={"doc": "tensor-product (box) or radial (sphere) kernel"})

    def __post_init__(self):
        if len(self.a_over_h) != 3:
            raise ValueError(f"support.a_over_h must have 3 values (x, y, z), got {len(self.a_over_h)}")


@dataclasses.dataclass(frozen=True)
class StabilizationConfig:
    """Stabilisation of the nodal integration (see :mod:`pixmuscle.mechanics.stabilization`)."""

    method: Literal["nsni", "none"] = field(default="nsni", metadata={"doc": "nsni: naturally stabilised nodal integration (Hillman & Chen 2016); none: plain SCNI"})
    coefficient: float = field(default=1.0, metadata={"range": (0.0, None), "doc": "scale of the stabilisation term (1 = Taylor-expansion value)"})
    modulus: Literal["shear", "tangent"] = field(default="shear", metadata={"doc": "shear: 2μ₀·I (no volumetric locking); tangent: full reference tangent A(F = I)"})


@dataclasses.dataclass(frozen=True)
class VolumetricConfig:
    """Volumetric energy of the nearly incompressible tissues (:mod:`pixmuscle.mechanics.volumetric`)."""

    method: Literal["projected", "nodal"] = field(default="projected", metadata={"doc": "projected: mean dilatation per patch of voxels (no volumetric locking); nodal: K/2 (J − 1)² at every node as in the paper"})
    patch: tuple[int, ...] = field(default=(2, 2, 3), metadata={"doc": "patch size in voxels per axis (x, y, z) of the projected dilatation; 2 × 2 × 3 is inf-sup stable on the voxel grid (1 × 1 × 3 is not: a pressure alternating between neighbouring columns is invisible to the displacements)"})
    held: Literal["own", "patch"] = field(default="own", metadata={"doc": "nodes held by a boundary condition at the node itself (penalty.at: nodes, node sets other than the end sets and bone_surface, point conditions): own: a single-node patch each (their nodal volumetric energy; the region solves of mixed_amg take their K-scaled terms); patch: in their ordinary patch like every other node, which lets an activated muscle shorten against its clamp at no volumetric cost where a patch holds held and free nodes (the demo with penalty.at: nodes: 149 N against 544 N with own)"})

    def __post_init__(self):
        if len(self.patch) != 3 or any(int(p) != p or p < 1 for p in self.patch):
            raise ValueError(f"volumetric.patch: expected 3 whole numbers >= 1 (voxels per axis), got {list(self.patch)}")


@dataclasses.dataclass(frozen=True)
class PenaltyConfig:
    """Penalty number β of the essential boundary conditions (paper eq. 9).

    The default factor 1 makes β the stiffness of one cell of the stiffest tissue in bulk
    (≈ 3·10⁵ N/cm³ at 0.156 cm). Reaction forces are insensitive to it (≤ 0.3 % between factors
    1 and 10³ on the leg, docs/linsolve-research.md §4), while iterative solvers slow down with it
    (2× the CG iterations at factor 10; no convergence at 10³), so the same default serves both
    backends and their results agree.
    """

    factor: float = field(default=1.0, metadata={"gt": 0, "doc": "β = factor · (largest reference tangent modulus) / (smallest spacing)"})
    beta: float | None = field(default=None, metadata={"gt": 0, "doc": "explicit β in N/cm³ (overrides factor)"})
    at: Literal["auto", "vertices", "centres", "nodes"] = field(default="auto", metadata={"doc": "auto = vertices: end sets (x_min..z_max) are constrained at the vertices of their end faces (trapezoidal rule; SCNI integrates those faces by the same rule, so a homogeneous deformation is reproduced exactly; the whole face is held, outer edges included), bone_surface at the vertices of the faces it shares with bone (where hex8 FE holds the bone; by the same rule in SCNI), other sets at the nodes; centres: end sets and bone_surface at the centres of those faces (midpoint rule; the outer edges of the end faces are left free); nodes: always at the nodes"})


@dataclasses.dataclass(frozen=True)
class NewtonConfig:
    """Newton–Raphson iteration per load step."""

    max_iterations: int = field(default=25, metadata={"range": (1, None)})
    residual_tol: float = field(default=1.0e-4, metadata={"gt": 0, "doc": "‖r‖ ≤ tol · max(‖f_int‖, ‖f_penalty‖)"})
    energy_tol: float = field(default=1.0e-6, metadata={"gt": 0, "doc": "|Δd·r| ≤ tol · (largest |Δd·r| of the step)"})
    forcing_max: float = field(default=1.0e-2, metadata={"gt": 0, "range": (None, 1.0), "doc": "largest relative tolerance of an iterative linear solve per Newton iteration (inexact Newton, Eisenstat–Walker η_max; direct solves are exact)"})
    max_cutbacks: int = field(default=6, metadata={"range": (0, None), "doc": "halvings of the load increment before giving up (with hold_cutback, counted from the nominal increment 1/steps)"})
    hold_cutback: bool = field(default=True, metadata={"doc": "after a cutback the halved load increment is kept for the rest of the ramp, the reported load steps unchanged (an increment that overshot once tends to overshoot again, and each overshoot costs a solve given up on); false: every load step starts again at its full increment"})
    line_search: bool = True
    max_line_search: int = field(default=8, metadata={"range": (0, None)})
    pressure_update: Literal["exact", "linearised", "mixed"] = field(default="mixed", metadata={"doc": "projected volumetric energy: how Newton treats the patch pressure. exact: the tangent takes K̄(θ − 1) of the new state; linearised: the pressure Newton on the mixed (displacement, pressure) form carries, K̄(θ − 1 + g·Δd) from the last state, which leaves out the bulk-modulus-amplified second-order term of a large update (the 21k leg's load step 1: 3 Newton iterations against 7); mixed: as linearised, and with a backend that solves the mixed form (mixed_amg, petsc_mixed) the pressure is an unknown of Newton and each linear solve stops on the mixed residual instead of the condensed one (21k leg: half the Krylov iterations). Convergence tests and results are those of the exact pressure in every case"})

    def __post_init__(self):
        if self.max_iterations < 2 and self.energy_tol < 1.0:
            raise ValueError("max_iterations: 1 can never converge a load step (the energy test compares an update "
                             "with the largest of the step, so it needs a second iteration); use 2 or more")


def _default_bcs() -> list:
    # paper Example 2: both ends fixed, bone surface fixed in the cross-sectional plane
    return [
        BoundaryCondition(nodes="z_min", fix=["x", "y", "z"]),
        BoundaryCondition(nodes="z_max", fix=["x", "y", "z"]),
        BoundaryCondition(nodes="bone_surface", fix=["x", "y"]),
    ]


@dataclasses.dataclass(frozen=True)
class SolveConfig:
    """Section ``solve``: load steps, activation ramp, boundary conditions and numerics."""

    steps: int = field(default=10, metadata={"range": (1, MAX_STEPS), "doc": "number of load steps"})
    activation: dict[str, float | dict[str, float] | Path] = field(
        default_factory=lambda: {"from": 0.0, "to": 1.0},
        metadata={"doc": "{from: α0, to: α1[, image: file]}: muscle activation ramped linearly over the steps (0..1); "
                         "from/to each a number or a mapping muscle name → value with optional 'default'; "
                         "image: NIfTI 0..1 per voxel multiplying both (:mod:`pixmuscle.mechanics.activation`)"},
    )
    boundary_conditions: list[BoundaryCondition] = field(default_factory=_default_bcs)
    materials: MaterialsConfig = field(default_factory=MaterialsConfig)
    support: SupportConfig = field(default_factory=SupportConfig)
    stabilization: StabilizationConfig = field(default_factory=StabilizationConfig)
    volumetric: VolumetricConfig = field(default_factory=VolumetricConfig)
    penalty: PenaltyConfig = field(default_factory=PenaltyConfig)
    newton: NewtonConfig = field(default_factory=NewtonConfig)
    solver: Any = field(default=AutoOptions(), metadata={
        "registry": BACKENDS, "default": AutoOptions(),
        "doc": f"{{backend: name, …options}}: linear-solver backend ({', '.join(BACKENDS.names())}; "
               "pixmuscle.mechanics.linsolve), default auto: direct on small models, mixed_amg on large ones (cg_amg with the nodal volumetric energy)"})

    def __post_init__(self):
        act = dict(self.activation)
        bad = [k for k in act if k not in ("from", "to", "image")]
        if bad:
            raise ValueError(f"activation: unknown key {bad[0]!r}; expected 'from', 'to' and optionally 'image'")
        act.setdefault("from", 0.0)
        act.setdefault("to", 1.0)
        act.setdefault("image", None)
        for k in ("from", "to"):
            act[k] = _activation_value(act[k], f"activation.{k}")
        if act["image"] is not None:
            if not isinstance(act["image"], Path):
                raise ValueError(f"activation.image: expected a file path (NIfTI, 0..1 per voxel), got {act['image']!r}")
            if not act["image"].exists():
                raise ValueError(f"activation.image: file not found: {act['image']}")
        object.__setattr__(self, "activation", act)
        for i, bc in enumerate(self.boundary_conditions):
            if not isinstance(bc, BoundaryCondition):
                raise ValueError(f"boundary_conditions[{i}]: expected a mapping")

    @property
    def uniform_activation(self) -> bool:
        """True when every muscle node has the same α (numbers for from/to, no image)."""
        a = self.activation
        return not isinstance(a["from"], dict) and not isinstance(a["to"], dict) and a.get("image") is None

    @property
    def alpha_from(self) -> float:
        """α at the start of the ramp (uniform activation; else the ``default`` value)."""
        return _nominal(self.activation["from"])

    @property
    def alpha_to(self) -> float:
        """α at the end of the ramp (uniform activation; else the ``default`` value)."""
        return _nominal(self.activation["to"])


def _activation_value(v, where: str):
    """A number in [0, 1], or a mapping name → number in [0, 1] (muscle names are checked against the model)."""
    if isinstance(v, dict):
        out = {}
        for name, x in v.items():
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not 0.0 <= float(x) <= 1.0:
                raise ValueError(f"{where}.{name}: expected a number in [0, 1], got {x!r}")
            out[str(name)] = float(x)
        return out
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= float(v) <= 1.0:
        got = repr(v.name) if isinstance(v, Path) else repr(v)
        raise ValueError(f"{where}: expected a number in [0, 1] or a mapping muscle name → number, got {got}")
    return float(v)


def _nominal(v) -> float:
    return float(v.get("default", 0.0)) if isinstance(v, dict) else float(v)


def bc_name(bc: BoundaryCondition, index: int) -> str:
    """Name of the reaction entry of a boundary condition: ``name``, else the set name, else ``point<index>``."""
    if bc.name:
        return bc.name
    if bc.nodes is not None:
        return bc.nodes
    return f"point{index}"
