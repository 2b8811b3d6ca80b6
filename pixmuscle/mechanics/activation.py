"""Per-node muscle activation α from the ``solve.activation`` section.

``activation.from`` and ``activation.to`` are each a number (every muscle alike) or a mapping
muscle name → value with an optional ``default`` for the muscles not named; an optional
activation image (0–1 per voxel) multiplies both. Over the load steps every muscle node's α
goes linearly from its start to its end value::

    α_I(s) = image(X_I) · (from_m + s (to_m − from_m)),   s = 0 … 1 (the load factor),

with m the muscle of node I. Non-muscle nodes carry α = 0 (their materials have no active part).

The image is sampled at each node's position in the scanner frame (the model frame rotated back
with ``grid/rotation``) through the image's own affine, trilinearly: like the masks it may come
on any grid that covers the muscles.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.ndimage import map_coordinates

from ..errors import InputError
from ..model.tissues import MUSCLE

__all__ = ["ActivationRamp", "activation_ramp", "image_on_nodes", "check_muscle_names", "muscle_values", "per_muscle_summary"]


@dataclasses.dataclass(frozen=True)
class ActivationRamp:
    """Node activations at the start and the end of the load ramp.

    Attributes
    ----------
    start, end : (N,) float
        α per node at load factor 0 and 1 (0 on non-muscle nodes).
    muscle : (N,) bool
        Muscle nodes (the ones whose α is summarised by :meth:`mean`).
    """

    start: np.ndarray
    end: np.ndarray
    muscle: np.ndarray

    def at(self, s: float) -> np.ndarray:
        """α per node at ramp parameter ``s`` (0…1), (N,)."""
        return self.start + float(s) * (self.end - self.start)

    def mean(self, s: float) -> float:
        """Mean α over the muscle nodes at ``s`` (equal cells: the volume mean); 0 without muscle."""
        if not self.muscle.any():
            return 0.0
        return float(self.at(s)[self.muscle].mean())

    @classmethod
    def uniform(cls, alpha_from: float, alpha_to: float, muscle: np.ndarray) -> ActivationRamp:
        """Every muscle node ramped from ``alpha_from`` to ``alpha_to``."""
        muscle = np.asarray(muscle, bool)
        return cls(start=np.where(muscle, float(alpha_from), 0.0), end=np.where(muscle, float(alpha_to), 0.0),
                   muscle=muscle)


def muscle_values(spec: float | Mapping[str, float], names: Sequence[str], where: str) -> np.ndarray:
    """Activation per muscle (M,) from a number or a mapping name → value (with optional ``default``).

    Raises
    ------
    InputError
        A name that is not a muscle of the model (the message lists the known ones).
    """
    names = [str(n) for n in names]
    if not isinstance(spec, Mapping):
        return np.full(len(names), float(spec))
    unknown = [k for k in spec if k != "default" and k not in names]
    if unknown:
        known = ", ".join(names) if names else "none"
        raise InputError(f"{where}.{unknown[0]}: unknown muscle {unknown[0]!r}; the model's muscles are: {known} "
                         "(or 'default' for the others)")
    default = float(spec.get("default", 0.0))
    return np.array([float(spec.get(n, default)) for n in names], float)


def check_muscle_names(spec, names: Sequence[str], where: str) -> None:
    """Raise InputError for a name in an activation mapping (``from``/``to``) that is not in ``names``.

    For checking a configuration before any stage runs, when the muscle names are known from it
    (segment seeds, a tissue map); the solve stage checks again against the model.
    """
    if isinstance(spec, Mapping):
        for key in ("from", "to"):
            if isinstance(spec.get(key), Mapping):
                muscle_values(spec[key], names, f"{where}.{key}")


def image_on_nodes(data: np.ndarray, affine: np.ndarray, X: np.ndarray, origin: np.ndarray,
                   rotation: np.ndarray, *, name: str = "activation image") -> tuple[np.ndarray, np.ndarray]:
    """Trilinear samples of a scalar image at model nodes.

    Parameters
    ----------
    data : (I, J, K) float
        Image values.
    affine : (4, 4) float
        Image voxel index → scanner position, cm.
    X : (N, 3) float
        Node coordinates in the model frame, cm.
    origin : (3,) float
        Model grid origin (cm); the model frame is the scanner frame rotated about it.
    rotation : (3, 3) float
        Model frame → scanner frame (``grid/rotation``).
    name : str
        Used in error messages.

    Returns
    -------
    values : (N,) float
        Image value at each node (0 outside the field of view).
    inside : (N,) bool
        Nodes whose position lies within the image's field of view (half a voxel beyond the
        outermost voxel centres).
    """
    data = np.asarray(data, float)
    if data.ndim != 3:
        raise InputError(f"{name}: expected a 3-D image, got shape {data.shape}")
    origin = np.asarray(origin, float)
    world = origin + (np.asarray(X, float) - origin) @ np.asarray(rotation, float).T
    ijk = np.linalg.solve(np.asarray(affine, float), np.c_[world, np.ones(len(world))].T)[:3]
    n = np.array(data.shape, float)[:, None]
    inside = np.all((ijk >= -0.5 - 1e-9) & (ijk <= n - 0.5 + 1e-9), axis=0)
    values = np.zeros(len(world))
    values[inside] = map_coordinates(data, ijk[:, inside], order=1, mode="nearest")
    return values, inside


def activation_ramp(model, activation: Mapping, image: tuple[np.ndarray, np.ndarray] | None = None,
                    *, where: str = "solve.activation") -> ActivationRamp:
    """Node activations of a model from the (validated) ``solve.activation`` section.

    Parameters
    ----------
    model : Model
        Needs ``tissue``, ``muscle_id``, ``muscle_names``; with an image also ``X``, ``origin``,
        ``rotation``.
    activation : mapping
        ``{"from": number or mapping, "to": number or mapping, "image": path or None}`` as
        :class:`pixmuscle.mechanics.config.SolveConfig` stores it.
    image : (data (I, J, K), affine (4, 4) cm), optional
        The activation image's voxels (required when ``activation`` names an image); values in
        [0, 1] (checked).
    where : str
        Key path for messages.

    Returns
    -------
    ActivationRamp

    Raises
    ------
    InputError
        Unknown muscle names, an image named but not given, image values outside [0, 1], or
        muscle nodes outside the image's field of view.
    """
    names = list(model.muscle_names)
    muscle = np.asarray(model.tissue) == MUSCLE
    mid = np.asarray(model.muscle_id, np.int64)
    a0 = muscle_values(activation.get("from", 0.0), names, f"{where}.from")
    a1 = muscle_values(activation.get("to", 1.0), names, f"{where}.to")
    # muscle id 1..M; muscle nodes without an id (none after build-model) take the default
    idx = np.clip(mid - 1, 0, max(len(names) - 1, 0))
    has = muscle & (mid >= 1) & (mid <= len(names))
    d0 = _default(activation.get("from", 0.0))
    d1 = _default(activation.get("to", 1.0))
    start = np.where(has, a0[idx] if names else 0.0, np.where(muscle, d0, 0.0))
    end = np.where(has, a1[idx] if names else 0.0, np.where(muscle, d1, 0.0))
    path = activation.get("image")
    if path is not None:
        if image is None:
            raise InputError(f"{where}.image: {path}: the image must be read by the solve stage (pass its voxels)")
        data, affine = image
        data = np.asarray(data, float)
        bad = ~np.isfinite(data) | (data < 0) | (data > 1)
        if bad.any():
            raise InputError(f"{where}.image: {path}: {int(bad.sum())} voxels are not in [0, 1] "
                             f"(range {np.nanmin(data):.4g}..{np.nanmax(data):.4g})")
        scale, inside = image_on_nodes(data, affine, model.X, model.origin, model.rotation, name=f"{where}.image")
        outside = muscle & ~inside
        if outside.any():
            raise InputError(f"{where}.image: {path}: {int(outside.sum())} of {int(muscle.sum())} muscle nodes lie "
                             "outside the image's field of view")
        start, end = start * scale, end * scale
    return ActivationRamp(start=np.where(muscle, start, 0.0), end=np.where(muscle, end, 0.0), muscle=muscle)


def _default(spec) -> float:
    if isinstance(spec, Mapping):
        return float(spec.get("default", 0.0))
    return float(spec)


def per_muscle_summary(ramp: ActivationRamp, model) -> dict:
    """Mean α per muscle at the start and the end of the ramp: name → [from, to]."""
    mid = np.asarray(model.muscle_id)
    out = {}
    for m, name in enumerate(model.muscle_names, 1):
        sel = ramp.muscle & (mid == m)
        if sel.any():
            out[str(name)] = [float(ramp.start[sel].mean()), float(ramp.end[sel].mean())]
    return out
