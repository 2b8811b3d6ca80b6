"""Strong ellipticity of the material law at the nodes of a solved state, from its RK coefficients.

A solve records the smallest acoustic-tensor eigenvalue at every node at its last converged state
(``/ellipticity/acoustic_minimum`` of ``results.h5``, :class:`~.results.NodeEllipticity`). For a
results file written before that was recorded, or for another stored state, it is computed here
again from what every results file holds: the model, the solve configuration (root attribute
``config``) and the RK coefficients ``/steps/d``. The deformation gradient is the solve's own
smoothed (SCNI) F_L = I + Σ_I d_I ⊗ b̃_I(X_L) with the same shape functions and supports
(:func:`.system.model_scni`), the materials and activation those of the solve, so the field equals
the one the solve records (to round-off).

Cost: the SCNI operators of the model (no stabilisation, no stiffness): 68k nodes about 15 s and
1 GB, then the acoustic tensor at every node (about 10 s per 100k nodes on one core).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .ellipticity import acoustic_minimum, directions
from .results import NodeEllipticity

__all__ = ["state_acoustic_minimum", "results_ellipticity", "solve_config_of"]


def state_acoustic_minimum(model, cfg, d: np.ndarray, alpha: float, activation=None,
                           n_directions: int = 300) -> np.ndarray:
    """Smallest acoustic-tensor eigenvalue of the material law at every node, N/cm², (N,).

    Parameters
    ----------
    model : Model
    cfg : SolveConfig
        The configuration of the solve (supports, boundary conditions, materials).
    d : (N, 3) float
        RK coefficients of the state, cm.
    alpha : float
        Activation of the state; with ``activation`` the ramp parameter (load factor) 0…1.
    activation : ActivationRamp, optional
        Per-node activation of a solve with per-muscle or image activation.
    n_directions : int
        Reference directions of :func:`.ellipticity.acoustic_minimum`.

    Returns
    -------
    (N,) float64
        < 0 where the law is not strongly elliptic.
    """
    from .system import material_response, model_scni, solve_materials, tissue_groups

    scni, _ = model_scni(model, cfg)
    F = scni.deformation_gradient(np.asarray(d, float))
    del scni
    groups = tissue_groups(model.tissue, solve_materials(cfg))
    _, A = material_response(groups, np.asarray(model.fiber, float), F, float(alpha), activation)
    return acoustic_minimum(F, A, directions(n_directions))


def solve_config_of(res):
    """The :class:`~.config.SolveConfig` stored in a results file (root attribute ``config``).

    Raises
    ------
    InputError
        The file holds no readable solve configuration.
    """
    import yaml

    from ..config import parse_section
    from .config import SolveConfig

    text = (res.meta or {}).get("config") or ""
    where = (res.meta or {}).get("path", "results")
    try:
        raw = yaml.safe_load(text) if text.strip() else None
    except yaml.YAMLError as exc:
        raise InputError(f"{where}: attribute config is not YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise InputError(f"{where}: no solve configuration stored (attribute config)")
    return parse_section(SolveConfig, _without_nulls(raw), "solve")


def _without_nulls(x):
    """A stored configuration with its null entries left out (the file writes unset options as null;
    the parser takes an absent key as its default)."""
    if isinstance(x, dict):
        return {k: _without_nulls(v) for k, v in x.items() if v is not None}
    if isinstance(x, list):
        return [_without_nulls(v) for v in x]
    return x


def results_ellipticity(res, step: int | None = None, n_directions: int = 300) -> NodeEllipticity:
    """The acoustic-tensor minimum at the nodes of stored state ``step`` of a results file, computed
    again from its RK coefficients (default: the last converged state, the one a solve records).

    Parameters
    ----------
    res : Results
        Read with :func:`pixmuscle.io.results.load_results` (with ``/steps/d`` and ``config``).
    step : int, optional
    n_directions : int

    Raises
    ------
    InputError
        No RK coefficients, no converged state or no readable configuration in the file.
    """
    from .activation import activation_ramp

    where = (res.meta or {}).get("path", "results")
    if res.d is None:
        raise InputError(f"{where}: no /steps/d (RK coefficients): the deformation gradients cannot be computed")
    if step is None:
        conv = np.flatnonzero(np.asarray(res.converged, bool))
        if conv.size == 0:
            raise InputError(f"{where}: no converged state")
        step = int(conv[-1])
    cfg = solve_config_of(res)
    if cfg.uniform_activation:
        activation, alpha = None, float(res.alpha[step])
    else:  # the solve ramps its per-node α with the load factor
        image = None
        if cfg.activation.get("image") is not None:
            from ..imaging.nifti import load_volume

            vol = load_volume(cfg.activation["image"], kind="image", allow_empty=True)
            image = (vol.data, vol.affine)
        activation, alpha = activation_ramp(res.model, cfg.activation, image), float(res.load_factor[step])
    q = state_acoustic_minimum(res.model, cfg, np.asarray(res.d[step], float), alpha, activation, n_directions)
    return NodeEllipticity(step=int(step), minimum=q, n_directions=int(n_directions))
