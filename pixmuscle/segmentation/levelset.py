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

from pixmuscle.errors import InputError

__all__ = [
    "checkerboard_level_set",
    "disk_level_set",
    "signed_distance",
    "squared_edt",
    "region_index",
    "region_means",
    "evolve_step",
    "evolve",
]

_BIG = 1e30
#: half-width (in units of the smallest spacing) of the band kept exact on reinitialisation
_REINIT_BAND = 6.0


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
        radius = min((n - 1) / 2.0 * h for n, h in zip(shape, spacing, strict=True))
    grids = np.meshgrid(*[(np.arange(n) - c) * h for n, c, h in zip(shape, center, spacing, strict=True)],
                        indexing="ij")
    dist = np.sqrt(sum(g**2 for g in grids))
    return (radius - dist) / radius


def signed_distance(inside, spacing=None, band=None):
    """Signed distance function of a binary mask, positive inside.

    The zero level lies half a voxel outside the boundary voxels of ``inside``
    (``+d - h/2`` inside, ``-(d - h/2)`` outside, with ``d`` the exact Euclidean distance to the
    nearest voxel of the other side and ``h`` the smallest spacing). The distance transform is
    the separable lower-envelope algorithm of Felzenszwalb & Huttenlocher (2012), in numba.

    Parameters
    ----------
    inside : ndarray of bool
        1-, 2- or 3-D.
    spacing : sequence of float, optional
        Voxel size per axis; the distance is in these units.
    band : float, optional
        If given, distances are exact up to ``band`` (same units) and ``phi`` is clipped to
        ``[-band, band]``; points farther than ``band`` from the other side are left out of
        the lower envelopes, which makes the transform several times faster.

    Returns
    -------
    phi : ndarray of float64, same shape
    """
    inside = np.asarray(inside, bool)
    if inside.ndim not in (1, 2, 3):
        raise InputError(f"signed_distance: expected a 1-, 2- or 3-D mask, got {inside.ndim}-D")
    if inside.all() or not inside.any():
        return np.where(inside, 1.0, -1.0) * float(max(inside.shape))
    spacing = np.ones(inside.ndim) if spacing is None else np.asarray(spacing, dtype=float)
    shape3 = (1,) * (3 - inside.ndim) + inside.shape
    h2 = np.concatenate([np.ones(3 - inside.ndim), spacing**2])
    ins = np.ascontiguousarray(inside.reshape(shape3))
    h = 0.5 * float(np.min(spacing))
    cap = _BIG if band is None else (float(band) + h) ** 2
    lim = np.inf if band is None else float(band)
    return _signed_distance3(ins, h2, cap, h, lim).reshape(inside.shape)


@njit(cache=True, error_model="numpy")
def _signed_distance3(ins, h2, cap, h, lim):
    nz, ny, nx = ins.shape
    g_in = np.empty((nz, ny, nx))  # 0 on the outside: distance of inside voxels to it
    g_out = np.empty((nz, ny, nx))
    for iz in range(nz):
        for iy in range(ny):
            for ix in range(nx):
                if ins[iz, iy, ix]:
                    g_in[iz, iy, ix] = _BIG
                    g_out[iz, iy, ix] = 0.0
                else:
                    g_in[iz, iy, ix] = 0.0
                    g_out[iz, iy, ix] = _BIG
    _edt3(g_in, h2, cap)
    _edt3(g_out, h2, cap)
    for iz in range(nz):
        for iy in range(ny):
            for ix in range(nx):
                if ins[iz, iy, ix]:
                    d = np.sqrt(g_in[iz, iy, ix]) - h
                else:
                    d = h - np.sqrt(g_out[iz, iy, ix])
                g_in[iz, iy, ix] = min(max(d, -lim), lim)
    return g_in


@njit(cache=True, error_model="numpy")
def _edt_line(f, h2, v, z, out):
    # squared distance transform of a sampled function f on a line of spacing sqrt(h2)
    n = f.shape[0]
    k = -1
    for q in range(n):
        if f[q] >= _BIG:
            continue
        fq = f[q] + h2 * q * q
        s = 0.0
        while k >= 0:
            p = v[k]
            s = (fq - (f[p] + h2 * p * p)) / (2.0 * h2 * (q - p))
            if s <= z[k]:
                k -= 1
            else:
                break
        k += 1
        v[k] = q
        z[k] = -np.inf if k == 0 else s
        z[k + 1] = np.inf
    if k < 0:
        for q in range(n):
            out[q] = _BIG
        return
    k = 0
    for q in range(n):
        while z[k + 1] < q:
            k += 1
        p = v[k]
        out[q] = h2 * (q - p) * (q - p) + f[p]


@njit(cache=True, error_model="numpy")
def _edt3(g, h2, cap):
    # in place, axis by axis (X, Y, Z), on g (Z, Y, X); values above cap are dropped (_BIG)
    nz, ny, nx = g.shape
    n = max(nz, ny, nx)
    v = np.empty(n, np.int64)
    z = np.empty(n + 1)
    line = np.empty(n)
    out = np.empty(n)
    for iz in range(nz):
        for iy in range(ny):
            for ix in range(nx):
                line[ix] = g[iz, iy, ix]
            _edt_line(line[:nx], h2[2], v, z, out[:nx])
            for ix in range(nx):
                g[iz, iy, ix] = out[ix] if out[ix] <= cap else _BIG
    if ny > 1:
        for iz in range(nz):
            for ix in range(nx):
                for iy in range(ny):
                    line[iy] = g[iz, iy, ix]
                _edt_line(line[:ny], h2[1], v, z, out[:ny])
                for iy in range(ny):
                    g[iz, iy, ix] = out[iy] if out[iy] <= cap else _BIG
    if nz > 1:
        for iy in range(ny):
            for ix in range(nx):
                for iz in range(nz):
                    line[iz] = g[iz, iy, ix]
                _edt_line(line[:nz], h2[0], v, z, out[:nz])
                for iz in range(nz):
                    g[iz, iy, ix] = out[iz] if out[iz] <= cap else _BIG


def squared_edt(target, h2, cap=None):
    """Squared Euclidean distance of every voxel to the nearest ``target`` voxel.

    Parameters
    ----------
    target : ndarray of bool, shape ``(Z, Y, X)``
    h2 : array_like, shape ``(3,)``
        Squared voxel size per axis.
    cap : float, optional
        Squared distances above ``cap`` are not computed exactly (they come out ``> cap``).

    Returns
    -------
    ndarray of float64, shape ``(Z, Y, X)``; ``1e30`` where there is no target (within
    ``cap``).
    """
    g = np.where(np.asarray(target, bool), 0.0, _BIG)
    _edt3(g, np.asarray(h2, dtype=np.float64), _BIG if cap is None else float(cap))
    return g


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


_FM = {"reassoc", "nsz", "contract", "arcp"}


@njit(cache=True, fastmath=_FM, error_model="numpy", inline="always")
def _update(f0, fxp, fxm, fyp, fym, fzp, fzm, force, mu, dt, eps, wz, wy, wx):
    # one voxel of the semi-implicit update; an axis with weight 0 drops out exactly
    eta = 1e-16
    gx2 = 0.25 * wx * (fxp - fxm) ** 2
    gy2 = 0.25 * wy * (fyp - fym) ** 2
    gz2 = 0.25 * wz * (fzp - fzm) ** 2
    c1 = wx / np.sqrt(eta + wx * (fxp - f0) ** 2 + gy2 + gz2)
    c2 = wx / np.sqrt(eta + wx * (f0 - fxm) ** 2 + gy2 + gz2)
    c3 = wy / np.sqrt(eta + wy * (fyp - f0) ** 2 + gx2 + gz2)
    c4 = wy / np.sqrt(eta + wy * (f0 - fym) ** 2 + gx2 + gz2)
    num = c1 * fxp + c2 * fxm + c3 * fyp + c4 * fym
    den = c1 + c2 + c3 + c4
    if wz != 0.0:
        c5 = wz / np.sqrt(eta + wz * (fzp - f0) ** 2 + gx2 + gy2)
        c6 = wz / np.sqrt(eta + wz * (f0 - fzm) ** 2 + gx2 + gy2)
        num += c5 * fzp + c6 * fzm
        den += c5 + c6
    a = dt * eps / (eps * eps + f0 * f0)
    return (f0 + a * (mu * num + force)) / (1.0 + mu * a * den)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_2d(r, n, s, f, o, mu, dt, eps, wy, wx):
    # rows r (this), n (y+1), s (y-1); x-interior loop is branch-free
    nx = r.shape[0]
    change = 0.0
    for ix in range(1, nx - 1):
        v = _update(r[ix], r[ix + 1], r[ix - 1], n[ix], s[ix], 0.0, 0.0, f[ix], mu, dt, eps,
                    0.0, wy, wx)
        o[ix] = v
        change += (v - r[ix]) ** 2
    for ix in (0, nx - 1):
        xp = min(ix + 1, nx - 1)
        xm = max(ix - 1, 0)
        v = _update(r[ix], r[xp], r[xm], n[ix], s[ix], 0.0, 0.0, f[ix], mu, dt, eps,
                    0.0, wy, wx)
        o[ix] = v
        change += (v - r[ix]) ** 2
    return change


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _row_3d(r, n, s, up, dn, f, o, mu, dt, eps, wz, wy, wx):
    nx = r.shape[0]
    change = 0.0
    for ix in range(1, nx - 1):
        v = _update(r[ix], r[ix + 1], r[ix - 1], n[ix], s[ix], up[ix], dn[ix], f[ix], mu, dt,
                    eps, wz, wy, wx)
        o[ix] = v
        change += (v - r[ix]) ** 2
    for ix in (0, nx - 1):
        xp = min(ix + 1, nx - 1)
        xm = max(ix - 1, 0)
        v = _update(r[ix], r[xp], r[xm], n[ix], s[ix], up[ix], dn[ix], f[ix], mu, dt, eps,
                    wz, wy, wx)
        o[ix] = v
        change += (v - r[ix]) ** 2
    return change


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _stencil(phi, force, out, mu, dt, eps, wz, wy, wx):
    # semi-implicit curvature update of one level set, phi/force/out (Z, Y, X)
    nz, ny, nx = phi.shape
    if nx < 2:
        raise ValueError("level-set grids need at least 2 voxels along x")
    change = 0.0
    for iz in range(nz):
        zp = min(iz + 1, nz - 1)
        zm = max(iz - 1, 0)
        for iy in range(ny):
            yp = min(iy + 1, ny - 1)
            ym = max(iy - 1, 0)
            if nz == 1:
                change += _row_2d(phi[iz, iy], phi[iz, yp], phi[iz, ym], force[iz, iy],
                                  out[iz, iy], mu, dt, eps, wy, wx)
            else:
                change += _row_3d(phi[iz, iy], phi[iz, yp], phi[iz, ym], phi[zp, iy],
                                  phi[zm, iy], force[iz, iy], out[iz, iy], mu, dt, eps, wz, wy,
                                  wx)
    return change


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _region_sums(phi, u, mask, sums, counts):
    # channel sums and voxel counts per region over the masked voxels (branch-free inner loop)
    K = phi.shape[0]
    C = u.shape[0]
    _, nz, ny, nx = phi.shape
    sums[...] = 0.0
    counts[...] = 0.0
    if K == 1:
        # two regions: vectorisable reductions instead of a scatter
        n_all = 0.0
        n_in = 0.0
        for iz in range(nz):
            for iy in range(ny):
                for ix in range(nx):
                    m = mask[iz, iy, ix] * 1.0
                    n_all += m
                    n_in += m * (phi[0, iz, iy, ix] > 0.0)
        counts[1] = n_in
        counts[0] = n_all - n_in
        for i in range(C):
            s_all = 0.0
            s_in = 0.0
            for iz in range(nz):
                for iy in range(ny):
                    for ix in range(nx):
                        v = mask[iz, iy, ix] * u[i, iz, iy, ix]
                        s_all += v
                        s_in += v * (phi[0, iz, iy, ix] > 0.0)
            sums[1, i] = s_in
            sums[0, i] = s_all - s_in
        return
    for iz in range(nz):
        for iy in range(ny):
            for ix in range(nx):
                p = 0
                for k in range(K):
                    p += (phi[k, iz, iy, ix] > 0.0) << k
                m = mask[iz, iy, ix] * 1.0
                counts[p] += m
                for i in range(C):
                    sums[p, i] += m * u[i, iz, iy, ix]


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _forces(phi, u, c, lam, area, mask, force, e):
    # force[k] = e_{p without bit k} - e_{p with bit k}; zero outside mask
    K = phi.shape[0]
    C = u.shape[0]
    P = c.shape[0]
    _, nz, ny, nx = phi.shape
    inv_c = 1.0 / C
    for iz in range(nz):
        for iy in range(ny):
            # data energy of every region along the row (vectorised over x)
            for q in range(P):
                eq = e[q]
                for ix in range(nx):
                    eq[ix] = area[q]
                for i in range(C):
                    w = lam[q, i] * inv_c
                    cq = c[q, i]
                    ur = u[i, iz, iy]
                    for ix in range(nx):
                        d = ur[ix] - cq
                        eq[ix] += w * d * d
            if K == 1:
                f = force[0, iz, iy]
                mr = mask[iz, iy]
                for ix in range(nx):
                    f[ix] = mr[ix] * (e[0, ix] - e[1, ix])
                continue
            for ix in range(nx):
                p = 0
                for k in range(K):
                    p += (phi[k, iz, iy, ix] > 0.0) << k
                m = mask[iz, iy, ix] * 1.0
                for k in range(K):
                    bit = 1 << k
                    force[k, iz, iy, ix] = m * (e[p & ~bit, ix] - e[p | bit, ix])


def region_means(u, phi, mask, previous=None):
    """Mean of each channel over each region (within ``mask``).

    Parameters
    ----------
    u : ndarray of float64, shape ``(C, Z, Y, X)``
    phi : ndarray of float64, shape ``(K, Z, Y, X)``
    mask : ndarray of bool, shape ``(Z, Y, X)``
    previous : ndarray, shape ``(2**K, C)``, optional
        Values kept for empty regions; default the mean over ``mask``.

    Returns
    -------
    c : ndarray of float64, shape ``(2**K, C)``
    counts : ndarray of float64, shape ``(2**K,)``
    """
    P = 2 ** phi.shape[0]
    sums = np.zeros((P, u.shape[0]))
    counts = np.zeros(P)
    _region_sums(np.ascontiguousarray(phi, dtype=np.float64),
                 np.ascontiguousarray(u, dtype=np.float64),
                 np.ascontiguousarray(mask, dtype=bool), sums, counts)
    if previous is None:
        previous = np.broadcast_to(sums.sum(axis=0) / max(counts.sum(), 1.0), sums.shape)
    c = np.array(previous, dtype=float, copy=True)
    nz = counts > 0
    c[nz] = sums[nz] / counts[nz, None]
    return c, counts


def evolve_step(phi, u, c, lam, area, mu, dt, eps, inv_h2, mask, out, force, scratch):
    """One semi-implicit sweep of the multiphase multichannel level-set flow (paper eq. 21).

    For each level set ``k`` (Jacobi over ``k``: all use the old ``phi``)::

        phi_k <- (phi_k + a (mu_k sum_j C_j phi_j + F_k)) / (1 + a mu_k sum_j C_j),
        a = dt * delta_eps(phi_k),
        F_k = e_{p with bit k cleared} - e_{p with bit k set},
        e_q = area_q + (1/C) sum_i lam_{q,i} (u_i - c_{q,i})**2,

    where ``p`` is the voxel's current region, ``phi_j`` its 4 (2-D) or 6 (3-D) neighbours and
    ``C_j`` the curvature face coefficients. ``F_k`` is the first variation of the data term of
    eq. (21) with respect to ``phi_k`` when the other level sets enter through sharp Heaviside
    functions (exact for ``K = 1``). Outside ``mask`` the data force is zero (curvature only).

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
    force : ndarray like ``phi``
        Work array (receives ``F_k``).
    scratch : ndarray of float64, shape ``(2**K, X)``
        Work array.

    Returns
    -------
    change : float
        ``sum((out - phi)**2)`` over all level sets and voxels.
    """
    _forces(phi, u, c, lam, area, mask, force, scratch)
    wz = inv_h2[0] if phi.shape[1] > 1 else 0.0
    wy = inv_h2[1] if phi.shape[2] > 1 else 0.0
    change = 0.0
    for k in range(phi.shape[0]):
        change += _stencil(phi[k], force[k], out[k], float(mu[k]), float(dt), float(eps),
                           float(wz), float(wy), float(inv_h2[2]))
    return change


def evolve(u, phi, lam, area, mu, *, dt, eps, tol, max_iter, reinit_every=0, spacing=None,
           mask=None, stop="phi", window=5, energy_scale="range"):
    """Iterate :func:`evolve_step` until the level sets stop changing.

    Region means are recomputed (over ``mask``, sharp Heaviside) before every sweep; an empty
    region keeps its previous means. Stops when the root-mean-square change of ``phi`` over one
    sweep (over all level sets and voxels: the criterion of scikit-image's ``chan_vese``) is at
    most ``tol`` (``stop="phi"``), or when at most the fraction ``tol`` of the voxels changed
    region over the last ``window`` sweeps (``stop="regions"``; the level sets may keep growing
    away from the contours, which the first test would count as change), or after
    ``max_iter`` sweeps.

    The energy is divided by a constant ``s`` before the flow starts. This does not change its
    minimisers; it makes the time step ``dt`` (and ``eps``, which is in level-set units)
    independent of the intensity scale of the channels. ``energy_scale="range"``:
    ``s = max_{q,i} lam_{q,i} R_i**2`` with ``R_i`` the range of channel ``i`` over ``mask``;
    one channel on ``[0, 1]`` with ``lam = 1`` has ``s = 1``, the setting of scikit-image
    (which rescales its image to ``[0, 1]``). ``"variance"``: ``s = (1/C) sum_i mean_q
    lam_{q,i} var_i``, the data energy per voxel of the one-region partition, so typical data
    forces are of order one whatever the contrast (the flow moves in a few sweeps instead of
    hundreds when the classes differ by a small part of the range). A number: ``s`` itself.

    Parameters
    ----------
    u : ndarray, shape ``(C, Z, Y, X)``
        Channels.
    phi : ndarray, shape ``(K, Z, Y, X)``
        Initial level sets (copied).
    lam : array_like, broadcastable to ``(2**K, C)``
    area : array_like, broadcastable to ``(2**K,)``
    mu : array_like, broadcastable to ``(K,)``
    dt, eps, tol : float
    max_iter : int
    reinit_every : int
        If > 0, reset every level set to the signed distance of its inside region
        (in units of the smallest spacing, clipped to +-6) every ``reinit_every`` sweeps.
    spacing : sequence of 3 float, optional
        Voxel size ``(Z, Y, X)`` used in the curvature term; default 1.
    mask : ndarray of bool, shape ``(Z, Y, X)``, optional
        Voxels that carry data (see :func:`evolve_step`); default all.
    stop : {"phi", "regions"}
        Stopping test (see above).
    window : int
        Sweeps between two region comparisons (``stop="regions"``).
    energy_scale : {"range", "variance"} or float
        Normalisation of the energy (see above).

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
    if min(u.shape[2:]) < 2:
        raise InputError(f"image: in-plane size {u.shape[2:]}; level sets need at least 2 x 2 "
                         "pixels")
    K = phi.shape[0]
    P = 2**K
    mask = (np.ones(u.shape[1:], bool) if mask is None
            else np.ascontiguousarray(mask, dtype=bool))
    spacing = np.ones(3) if spacing is None else np.asarray(spacing, dtype=float)
    inv_h2 = 1.0 / spacing**2
    lam = np.ascontiguousarray(np.broadcast_to(lam, (P, u.shape[0])), dtype=np.float64)
    area = np.ascontiguousarray(np.broadcast_to(area, (P,)), dtype=np.float64)
    mu = np.ascontiguousarray(np.broadcast_to(mu, (K,)), dtype=np.float64)
    # energy scale: minimisers do not change, the time step becomes scale free
    if isinstance(energy_scale, str):
        if energy_scale == "range":
            ranges = np.array([np.ptp(ui[mask]) for ui in u])
            scale = float(np.max(lam * ranges**2))
        elif energy_scale == "variance":
            var = np.array([np.var(ui[mask]) for ui in u])
            scale = float(np.mean(lam.mean(axis=0) * var))
        else:
            raise InputError(f"energy_scale: expected 'range', 'variance' or a number, got "
                             f"{energy_scale!r}")
    else:
        scale = float(energy_scale)
        if not scale > 0:
            raise InputError(f"energy_scale: expected a number > 0, got {energy_scale!r}")
    if scale > 0:
        lam, area, mu = lam / scale, area / scale, mu / scale
    out = np.empty_like(phi)
    force = np.empty_like(phi)
    scratch = np.empty((P, phi.shape[-1]))
    if stop not in ("phi", "regions"):
        raise InputError(f"stop: expected 'phi' or 'regions', got {stop!r}")
    c = None
    converged = False
    it = 0
    last = region_index(phi) if stop == "regions" else None
    while it < max_iter:
        c, _ = region_means(u, phi, mask, c)
        change = evolve_step(phi, u, c, lam, area, mu, dt, eps, inv_h2, mask, out, force,
                             scratch)
        phi, out = out, phi
        it += 1
        if stop == "phi" and np.sqrt(change / phi.size) <= tol:
            converged = True
            break
        if stop == "regions" and it % window == 0:
            now = region_index(phi)
            if np.count_nonzero(now != last) <= tol * now.size:
                converged = True
                break
            last = now
        if reinit_every and it % reinit_every == 0:
            unit = float(spacing.min())
            for k in range(K):
                phi[k] = signed_distance(phi[k] > 0, spacing, band=_REINIT_BAND * unit) / unit
    c, _ = region_means(u, phi, mask, c)
    return phi, c, it, converged
