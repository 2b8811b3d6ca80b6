"""Level-set building blocks shared by the two-phase and the multiphase Chan–Vese models.

One semi-implicit sweep of the (multiphase, multichannel) Vese–Chan flow is a single numba
kernel, :func:`evolve_step`; the two-phase model of Chan & Vese (2001) is the case of one level
set and two regions. Everything here works on 3-D arrays ``(Z, Y, X)``; a 2-D image is a volume
with one slice (``Z = 1``), in which case the slice axis takes no part in the curvature.

Conventions
-----------
* A voxel is *inside* level set ``k`` where ``phi[k] > 0``. The region index of a voxel is
  ``p = sum_k 2**k * (phi[k] > 0)``, so ``K`` level sets give ``2**K`` regions (Vese & Chan 2002).
* Regularised Dirac: ``delta_eps(x) = eps / (eps**2 + x**2)``. This is ``pi`` times the
  derivative of the regularised Heaviside ``H_eps(x) = 1/2 + arctan(x / eps) / pi`` of
  Chan & Vese (2001); the factor ``1/pi`` is absorbed into the time step, as in scikit-image's
  ``chan_vese`` (so that the same ``dt`` means the same scheme).
* Curvature ``div(grad phi / |grad phi|)`` uses the discretisation of Getreuer (IPOL 2012) in the
  simplified form of scikit-image: at each face the gradient norm is built from the one-sided
  difference across the face and central differences along the other axes, all evaluated at the
  centre voxel. With grid spacing ``h`` the face coefficient is ``1 / (h_d**2 |grad phi|)``.
  Boundaries are Neumann (edge replication).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy import ndimage as ndi

__all__ = [
    "checkerboard_level_set",
    "disk_level_set",
    "signed_distance",
    "region_index",
    "evolve_step",
]


def checkerboard_level_set(shape, square_size=5.0):
    """Smooth checkerboard ``prod_d sin(pi * x_d / square_size)`` (Getreuer 2012).

    Parameters
    ----------
    shape : tuple of int
        Spatial shape, 2-D ``(Y, X)`` or 3-D ``(Z, Y, X)``.
    square_size : float
        Side of one square, voxels.

    Returns
    -------
    phi : ndarray of float64, shape ``shape``
    """
    phi = np.ones(shape)
    for axis, n in enumerate(shape):
        s = [1] * len(shape)
        s[axis] = n
        phi = phi * np.sin(np.pi / square_size * np.arange(n, dtype=float)).reshape(s)
    return phi


def disk_level_set(shape, center=None, radius=None, spacing=None):
    """Signed distance to a disk/ball, positive inside, scaled by the radius.

    Parameters
    ----------
    shape : tuple of int
        Spatial shape ``(Y, X)`` or ``(Z, Y, X)``.
    center : sequence of float, optional
        Centre in voxel indices; default the middle of the grid.
    radius : float, optional
        Radius in the units of ``spacing``; default half the smallest extent.
    spacing : sequence of float, optional
        Voxel size per axis (default 1).

    Returns
    -------
    phi : ndarray of float64, shape ``shape``
        ``(radius - |x - center|) / radius``.
    """
    spacing = np.ones(len(shape)) if spacing is None else np.asarray(spacing, float)
    if center is None:
        center = [(n - 1) / 2.0 for n in shape]
    if radius is None:
        radius = min((n - 1) / 2.0 * h for n, h in zip(shape, spacing))
    grids = np.meshgrid(*[(np.arange(n) - c) * h for n, c, h in zip(shape, center, spacing)],
                        indexing="ij")
    dist = np.sqrt(sum(g**2 for g in grids))
    return (radius - dist) / radius


def signed_distance(inside, spacing=None):
    """Signed distance function of a binary mask, positive inside.

    The zero level lies half a voxel outside the boundary voxels of ``inside``
    (``+d - 1/2`` inside, ``-(d - 1/2)`` outside, with ``d`` the Euclidean distance transform).

    Parameters
    ----------
    inside : ndarray of bool
        Any number of dimensions.
    spacing : sequence of float, optional
        Voxel size per axis; the distance is in these units.

    Returns
    -------
    phi : ndarray of float64, same shape
    """
    inside = np.asarray(inside, bool)
    if inside.all() or not inside.any():
        return np.where(inside, 1.0, -1.0) * float(max(inside.shape))
    h = 0.5 * (1.0 if spacing is None else float(np.min(spacing)))
    d_in = ndi.distance_transform_edt(inside, sampling=spacing)
    d_out = ndi.distance_transform_edt(~inside, sampling=spacing)
    return np.where(inside, d_in - h, h - d_out)


def region_index(phi):
    """Region index ``p = sum_k 2**k [phi_k > 0]`` of ``K`` level sets.

    Parameters
    ----------
    phi : ndarray, shape ``(K, ...)``

    Returns
    -------
    p : ndarray of int64, shape ``phi.shape[1:]``, values in ``0 .. 2**K - 1``
    """
    phi = np.asarray(phi)
    p = np.zeros(phi.shape[1:], dtype=np.int64)
    for k in range(phi.shape[0]):
        p |= (phi[k] > 0).astype(np.int64) << k
    return p


@njit(cache=True, fastmath=False, boundscheck=False)
def _kernel(phi, u, c, lam, area, mu, dt, eps, w, mask, out, sums, counts, e):
    K, nz, ny, nx = phi.shape
    C = u.shape[0]
    P = c.shape[0]
    eta = 1e-16
    wz, wy, wx = w[0], w[1], w[2]
    use_z = nz > 1
    use_y = ny > 1
    use_x = nx > 1
    inv_c = 1.0 / C
    change = 0.0
    for iz in range(nz):
        zp = min(iz + 1, nz - 1)
        zm = max(iz - 1, 0)
        for iy in range(ny):
            yp = min(iy + 1, ny - 1)
            ym = max(iy - 1, 0)
            for ix in range(nx):
                xp = min(ix + 1, nx - 1)
                xm = max(ix - 1, 0)
                inside = mask[iz, iy, ix]
                p = 0
                if inside:
                    for k in range(K):
                        if phi[k, iz, iy, ix] > 0.0:
                            p |= 1 << k
                    for q in range(P):
                        acc = 0.0
                        for i in range(C):
                            d = u[i, iz, iy, ix] - c[q, i]
                            acc += lam[q, i] * d * d
                        e[q] = area[q] + acc * inv_c
                pnew = 0
                for k in range(K):
                    f0 = phi[k, iz, iy, ix]
                    num = 0.0
                    den = 0.0
                    gx2 = 0.0
                    gy2 = 0.0
                    gz2 = 0.0
                    fxp = fxm = fyp = fym = fzp = fzm = f0
                    if use_x:
                        fxp = phi[k, iz, iy, xp]
                        fxm = phi[k, iz, iy, xm]
                        gx2 = 0.25 * wx * (fxp - fxm) ** 2
                    if use_y:
                        fyp = phi[k, iz, yp, ix]
                        fym = phi[k, iz, ym, ix]
                        gy2 = 0.25 * wy * (fyp - fym) ** 2
                    if use_z:
                        fzp = phi[k, zp, iy, ix]
                        fzm = phi[k, zm, iy, ix]
                        gz2 = 0.25 * wz * (fzp - fzm) ** 2
                    if use_x:
                        c1 = wx / np.sqrt(eta + wx * (fxp - f0) ** 2 + gy2 + gz2)
                        c2 = wx / np.sqrt(eta + wx * (f0 - fxm) ** 2 + gy2 + gz2)
                        num += c1 * fxp + c2 * fxm
                        den += c1 + c2
                    if use_y:
                        c3 = wy / np.sqrt(eta + wy * (fyp - f0) ** 2 + gx2 + gz2)
                        c4 = wy / np.sqrt(eta + wy * (f0 - fym) ** 2 + gx2 + gz2)
                        num += c3 * fyp + c4 * fym
                        den += c3 + c4
                    if use_z:
                        c5 = wz / np.sqrt(eta + wz * (fzp - f0) ** 2 + gx2 + gy2)
                        c6 = wz / np.sqrt(eta + wz * (f0 - fzm) ** 2 + gx2 + gy2)
                        num += c5 * fzp + c6 * fzm
                        den += c5 + c6
                    force = 0.0
                    if inside:
                        bit = 1 << k
                        force = e[p & ~bit] - e[p | bit]
                    a = dt * eps / (eps * eps + f0 * f0)
                    fnew = (f0 + a * (mu[k] * num + force)) / (1.0 + mu[k] * a * den)
                    out[k, iz, iy, ix] = fnew
                    change += (fnew - f0) ** 2
                    if fnew > 0.0:
                        pnew |= 1 << k
                if inside:
                    counts[pnew] += 1.0
                    for i in range(C):
                        sums[pnew, i] += u[i, iz, iy, ix]
    return change


def region_means(u, phi, mask, previous=None):
    """Mean of each channel over each region (within ``mask``).

    Parameters
    ----------
    u : ndarray, shape ``(C, Z, Y, X)``
    phi : ndarray, shape ``(K, Z, Y, X)``
    mask : ndarray of bool, shape ``(Z, Y, X)``
    previous : ndarray, shape ``(2**K, C)``, optional
        Values kept for empty regions; default the mean over ``mask``.

    Returns
    -------
    c : ndarray of float64, shape ``(2**K, C)``
    counts : ndarray of float64, shape ``(2**K,)``
    """
    P = 2 ** phi.shape[0]
    p = region_index(phi)[mask]
    counts = np.bincount(p, minlength=P).astype(float)
    sums = np.stack([np.bincount(p, weights=ui[mask], minlength=P) for ui in u], axis=1)
    return _means_from_sums(sums, counts, u, mask, previous), counts


def _means_from_sums(sums, counts, u, mask, previous):
    if previous is None:
        previous = np.broadcast_to(u[:, mask].mean(axis=1), sums.shape)
    c = np.array(previous, dtype=float, copy=True)
    nz = counts > 0
    c[nz] = sums[nz] / counts[nz, None]
    return c


def evolve_step(phi, u, c, lam, area, mu, dt, eps, inv_h2, mask, out, sums, counts, scratch):
    """One semi-implicit sweep of the multiphase multichannel level-set flow (paper eq. 21).

    For each level set ``k`` (Jacobi over ``k``: all use the old ``phi``)::

        phi_k <- (phi_k + a (mu_k sum_j C_j phi_j + F_k)) / (1 + a mu_k sum_j C_j),
        a = dt * delta_eps(phi_k),
        F_k = e_{p with bit k cleared} - e_{p with bit k set},
        e_q = area_q + (1/C) sum_i lam_{q,i} (u_i - c_{q,i})**2,

    where ``p`` is the voxel's current region and ``C_j`` the curvature face coefficients.
    ``F_k`` is the exact first variation of the data term of eq. (21) with respect to ``phi_k``
    when the other level sets enter through sharp Heaviside functions. Outside ``mask`` the data
    force is zero (curvature only). The new region sums (for the next means) are accumulated
    in the same pass.

    Parameters
    ----------
    phi : ndarray of float64, shape ``(K, Z, Y, X)``, C-contiguous
    u : ndarray of float64, shape ``(C, Z, Y, X)``
    c, lam : ndarray of float64, shape ``(2**K, C)``
        Region means and weights.
    area : ndarray of float64, shape ``(2**K,)``
        Area weight of each region (``nu`` of Chan–Vese for the inside region).
    mu : ndarray of float64, shape ``(K,)``
    dt, eps : float
    inv_h2 : ndarray of float64, shape ``(3,)``
        ``1 / spacing**2`` for axes ``(Z, Y, X)``.
    mask : ndarray of bool, shape ``(Z, Y, X)``
    out : ndarray like ``phi``
        Receives the new level sets.
    sums, counts, scratch : ndarray, shapes ``(2**K, C)``, ``(2**K,)``, ``(2**K,)``
        Work arrays; ``sums`` and ``counts`` are zeroed here and hold the region sums of ``out``.

    Returns
    -------
    change : float
        ``sum((out - phi)**2)`` over all level sets and voxels.
    """
    sums[...] = 0.0
    counts[...] = 0.0
    return _kernel(phi, u, c, lam, area, mu, float(dt), float(eps), inv_h2, mask, out, sums,
                   counts, scratch)


def evolve(u, phi, lam, area, mu, *, dt, eps, tol, max_iter, reinit_every=0, spacing=None,
           mask=None):
    """Iterate :func:`evolve_step` until the level sets stop changing.

    Stops when the root-mean-square change of ``phi`` over one sweep (over all level sets and
    voxels, the criterion of scikit-image's ``chan_vese``) is at most ``tol``, or after
    ``max_iter`` sweeps. Region means are updated after every sweep.

    Parameters
    ----------
    u : ndarray, shape ``(C, Z, Y, X)``
        Channels.
    phi : ndarray, shape ``(K, Z, Y, X)``
        Initial level sets (copied).
    lam : ndarray, shape ``(2**K, C)``
    area : ndarray, shape ``(2**K,)``
    mu : ndarray, shape ``(K,)``
    dt, eps, tol : float
    max_iter : int
    reinit_every : int
        If > 0, reset every level set to the signed distance of its inside region
        (in voxel units of the smallest spacing) every ``reinit_every`` sweeps.
    spacing : sequence of 3 float, optional
        Voxel size ``(Z, Y, X)`` used in the curvature term; default 1.
    mask : ndarray of bool, shape ``(Z, Y, X)``, optional
        Voxels that carry data (see :func:`evolve_step`); default all.

    Returns
    -------
    phi : ndarray, shape ``(K, Z, Y, X)``
    c : ndarray, shape ``(2**K, C)``
        Region means of the final level sets.
    n_iter : int
    converged : bool
    """
    u = np.ascontiguousarray(u, dtype=np.float64)
    phi = np.array(phi, dtype=np.float64, order="C", copy=True)
    K = phi.shape[0]
    P = 2**K
    spatial = u.shape[1:]
    mask = np.ones(spatial, bool) if mask is None else np.ascontiguousarray(mask, dtype=bool)
    spacing = np.ones(3) if spacing is None else np.asarray(spacing, dtype=float)
    inv_h2 = np.ascontiguousarray(1.0 / spacing**2)
    lam = np.ascontiguousarray(np.broadcast_to(lam, (P, u.shape[0])), dtype=np.float64)
    area = np.ascontiguousarray(np.broadcast_to(area, (P,)), dtype=np.float64)
    mu = np.ascontiguousarray(np.broadcast_to(mu, (K,)), dtype=np.float64)
    out = np.empty_like(phi)
    sums = np.zeros((P, u.shape[0]))
    counts = np.zeros(P)
    scratch = np.zeros(P)
    c, _ = region_means(u, phi, mask)
    n_voxels = phi.size
    converged = False
    it = 0
    while it < max_iter:
        change = evolve_step(phi, u, c, lam, area, mu, dt, eps, inv_h2, mask, out, sums, counts,
                             scratch)
        phi, out = out, phi
        c = _means_from_sums(sums, counts, u, mask, c)
        it += 1
        if np.sqrt(change / n_voxels) <= tol:
            converged = True
            break
        if reinit_every and it % reinit_every == 0:
            unit = float(spacing.min())
            for k in range(K):
                phi[k] = signed_distance(phi[k] > 0, spacing) / unit
    return phi, c, it, converged
