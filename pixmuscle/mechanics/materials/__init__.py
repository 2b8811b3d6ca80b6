r"""Material laws: one module per law, each registering itself in :data:`LAWS`.

A law is a frozen dataclass of its constants (units and bounds in the field metadata) with

``energy(F, **kw)``          W, shape (n,), strain energy per unit reference volume [N/cm²]
``stress(F, **kw)``          P, shape (n, 3, 3), first Piola–Kirchhoff stress [N/cm²]
``stress_tangent(F, **kw)``  (P, A) with ``A[n, i, J, k, L] = ∂P_iJ/∂F_kL`` (n, 3, 3, 3, 3) [N/cm²]
``cauchy(F, **kw)``          σ = J⁻¹ P Fᵀ, shape (n, 3, 3) [N/cm²]
``bulk_modulus``             K [N/cm²] of a volumetric energy K/2 (J − 1)² that is *added* to an
                             isochoric part; ``None`` when the law has no such split (the
                             projected volumetric energy, ``solve.volumetric.method: projected``,
                             then cannot be used)

and is registered with ``@LAWS.register(name, needs=(...))``; ``needs`` lists the keywords the
solver must pass: ``"fiber"`` ((n, 3) reference fibre directions) and ``"activation"`` (α per point).
A deformation gradient with det F ≤ 0 raises :class:`~pixmuscle.errors.SolverError`.

Laws of the paper: ``yeoh`` (:class:`~.yeoh.Yeoh`, eq. 27, connective tissue and fat) and
``blemker`` (:class:`~.muscle.TransverselyIsotropicMuscle`, eqs. 22–26). The config section
``solve.materials.<tissue>`` is ``{law: <name>, …constants}``; without ``law`` it is the tissue's
default law (:data:`DEFAULTS`) with the constants given overriding the paper's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ...errors import InputError
from ...registry import Registry

#: Registered material laws (name → entry; entry.attrs["needs"] lists "fiber", "activation").
LAWS = Registry("material law", key="law", package=__name__)
LAWS.discover()

from .muscle import MUSCLE, TransverselyIsotropicMuscle, f_active, f_passive  # noqa: E402
from .uncoupled import tangent9, voigt9  # noqa: E402
from .yeoh import CONNECTIVE_TISSUE, FAT, Yeoh  # noqa: E402

__all__ = [
    "LAWS",
    "DEFAULTS",
    "Yeoh",
    "TransverselyIsotropicMuscle",
    "CONNECTIVE_TISSUE",
    "FAT",
    "MUSCLE",
    "f_active",
    "f_passive",
    "material_from_config",
    "needs",
    "voigt9",
    "tangent9",
]

#: Default law and constants per tissue: Table 2 (ERRATA) muscle, Table 1 connective tissue and fat.
DEFAULTS = {"muscle": MUSCLE, "connective_tissue": CONNECTIVE_TISSUE, "fat": FAT}


def needs(material) -> tuple[str, ...]:
    """Keywords a material's law needs from the solver (``"fiber"``, ``"activation"``)."""
    return tuple(LAWS.entry_of(material).attrs.get("needs", ()))


def material_from_config(tissue: str, params: Mapping[str, Any] | None = None):
    """Material instance for a tissue name with the paper defaults, overridden by ``params``.

    Parameters
    ----------
    tissue : {"muscle", "connective_tissue", "fat"}
    params : mapping of constant name → number, optional
        Overrides of the defaults (Table 1, Table 2/ERRATA), e.g. ``{"lambda_opt": 1.4}``;
        ``law: <name>`` picks another registered law (its own defaults then apply).

    Raises
    ------
    InputError
        Unknown tissue or law, unknown parameter name (the message lists the allowed ones), or a bad value.
    """
    if tissue not in DEFAULTS:
        raise InputError(f"unknown tissue {tissue!r} for a material; expected one of {sorted(DEFAULTS)}")
    base = DEFAULTS[tissue]
    params = {} if params is None else dict(params)
    law = params.pop("law", None)
    cls = type(base) if law is None else LAWS.get(law, f"materials.{tissue}.law").obj
    allowed = [f.name for f in dataclasses.fields(cls)]
    unknown = [k for k in params if k not in allowed]
    if unknown:
        raise InputError(
            f"unknown material parameter(s) {', '.join(map(repr, unknown))} for tissue {tissue!r}; "
            f"allowed: {', '.join(allowed)}"
        )
    return dataclasses.replace(base, **params) if cls is type(base) else cls(**params)
