"""In-plane strain from tracked points or dense displacement fields.

Notation (Malvern, *Introduction to the Mechanics of a Continuous Medium*, 1969, sec. 4.5;
Holzapfel, *Nonlinear Solid Mechanics*, 2000, sec. 2.5): ``X`` are reference (undeformed)
positions, ``u(X)`` the displacement, and the displacement gradient is
``G[..., i, j] = ∂u_i / ∂X_j`` with ``i, j`` over ``(x, y)`` (x right, y down, as image
points). The deformation gradient is ``F = I + G``.

- small (infinitesimal) strain ``ε = ½ (G + Gᵀ)``;
- Green-Lagrange strain ``E = ½ (Fᵀ F - I) = ½ (G + Gᵀ + Gᵀ G)``.

Strains are dimensionless; shear components are tensorial (``ε_xy = ½ γ_xy``).
Points are ``(N, 2)`` arrays of ``(x, y)``; displacements ``(N, 2)`` in the same unit
(pixels or µm), so the gradient is dimensionless.
"""

from __future__ import annotations

import numpy as np

from .errors import GeometryError, SemlabError

__all__ = [
    "gradient_from_triangles",
    "gradient_local_lsq",
    "strain_jacobian",
    "strain_covariance",
    "strain_sigma",
    "mean_gradient_cov",
    "triangle_gradient_cov",
    "gradient_from_field",
    "chained_flow_start",
    "dense_field_strain",
    "fill_dense_holes",
    "small_strain",
    "green_lagrange",
    "surface_green_lagrange",
    "principal_strains",
    "max_shear",
    "triangle_areas",
    "strain_history",
    "strain_from_tracks",
]


def _pts_disp(pts_ref, disp):
    X = np.asarray(pts_ref, dtype=float)
    u = np.asarray(disp, dtype=float)
    if X.ndim != 2 or X.shape[1] != 2:
        raise GeometryError(f"pts_ref must be an (N, 2) array of (x, y), got shape {X.shape}")
    if u.shape != X.shape:
        raise GeometryError(f"disp must have the shape of pts_ref {X.shape}, got {u.shape}")
    return X, u


def triangle_areas(pts, triangles):
    """(T,) unsigned areas of ``triangles`` (T, 3) of ``pts`` (N, 2)."""
    P = np.asarray(pts, float)[np.asarray(triangles)]
    a = P[:, 1] - P[:, 0]
    b = P[:, 2] - P[:, 0]
    return 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])


def gradient_from_triangles(pts_ref, disp, min_angle_deg=10.0):
    """Displacement gradient of constant-strain Delaunay triangles (CST elements).

    Within each triangle the displacement is linear, so ``u(X) = u_0 + G (X - X_0)`` is
    solved exactly from the three vertices (Zienkiewicz & Taylor, *The Finite Element
    Method*, vol. 1, ch. 6, the linear triangle). Points with NaN positions or
    displacements are left out before triangulating (``scipy.spatial.Delaunay``).

    Parameters
    ----------
    pts_ref : (N, 2) array of reference positions (x, y)
    disp : (N, 2) array of displacements (same unit)
    min_angle_deg : float
        Triangles whose smallest angle is below this (slivers, whose gradient is
        ill-conditioned) are dropped.

    Returns
    -------
    G : (T, 2, 2) array, ``G[t, i, j] = ∂u_i/∂X_j``
    triangles : (T, 3) int array of indices into ``pts_ref``

    Raises
    ------
    GeometryError
        Fewer than 3 usable points, all collinear, or no triangle passes the sliver test.
    """
    from scipy.spatial import Delaunay
    from scipy.spatial import QhullError

    X, u = _pts_disp(pts_ref, disp)
    ok = np.isfinite(X).all(axis=1) & np.isfinite(u).all(axis=1)
    idx = np.flatnonzero(ok)
    if len(idx) < 3:
        raise GeometryError(f"{len(idx)} usable points (finite position and displacement); "
                            "triangles need at least 3")
    try:
        tri = Delaunay(X[idx])
    except QhullError as exc:
        raise GeometryError("the points are collinear or duplicated: no triangulation "
                            f"possible ({str(exc).splitlines()[0]})") from None
    T = idx[tri.simplices]
    P = X[T]                                                    # (T, 3, 2)
    # smallest interior angle
    ang = []
    for i in range(3):
        a = P[:, (i + 1) % 3] - P[:, i]
        b = P[:, (i + 2) % 3] - P[:, i]
        c = np.einsum("ti,ti->t", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        ang.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    keep = np.min(ang, axis=0) >= float(min_angle_deg)
    if not keep.any():
        raise GeometryError(f"all {len(T)} triangles are slivers (smallest angle < "
                            f"{min_angle_deg}°): lower min_angle_deg or use more points")
    T = T[keep]
    P = X[T]
    U = u[T]
    dX = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], axis=2)     # (T, 2, 2) columns
    dU = np.stack([U[:, 1] - U[:, 0], U[:, 2] - U[:, 0]], axis=2)
    G = dU @ np.linalg.inv(dX)
    return G, T


def _disp_sigma(disp_sigma, n):
    """(N, 2) per-component displacement σ from an (N,) or (N, 2) ``disp_sigma``."""
    sg = np.asarray(disp_sigma, dtype=float)
    if sg.shape == (n,):
        sg = np.repeat(sg[:, None], 2, axis=1)
    if sg.shape != (n, 2):
        raise GeometryError(f"disp_sigma must have shape ({n},) or ({n}, 2), got {sg.shape}")
    if np.any(sg < 0):
        raise GeometryError("disp_sigma must be >= 0 (inf: unknown error)")
    return sg


def gradient_local_lsq(pts_ref, disp, gauge_length, min_neighbours=6, disp_sigma=None,
                       weighted=False):
    """Displacement gradient at each point from a local least-squares affine fit.

    At each point the neighbours within a disc of diameter ``gauge_length`` (radius
    ``gauge_length / 2``, the point itself included) are fitted by
    ``u(X) = a + G (X - X_i)`` in the least-squares sense; this is the "virtual strain
    gauge" of point-wise DIC strain estimation (Pan et al., Opt. Eng. 46 (2007) 033601).

    With ``disp_sigma`` the covariance of each gradient is propagated linearly from the
    displacements' errors, taken independent between points and between the x and y
    components (Gaussian error propagation of a linear estimator: each fit is
    ``c = H u`` with ``H = (AᵀWA)⁻¹AᵀW``, so ``Cov(c) = H diag(σ²) Hᵀ``; with
    ``weighted=True``, ``W = diag(1/σ²)`` and this is ``(AᵀWA)⁻¹``, the weighted normal
    equations; Press et al., *Numerical Recipes*, 3rd ed., sec. 15.4). The σ is that of the
    random error only: errors correlated between neighbours (e.g. a shared model error)
    are not in it.

    Parameters
    ----------
    pts_ref : (N, 2) array of reference positions (x, y)
    disp : (N, 2) array of displacements (same unit)
    gauge_length : float
        Diameter of the fitting disc, in the unit of ``pts_ref``.
    min_neighbours : int
        Fewest points (including the point itself) in the disc; below it (or when the
        neighbours are collinear) the gradient is NaN.
    disp_sigma : (N,) or (N, 2) array, optional
        1σ of each point's displacement (one value for both components, or one per
        component), in the unit of ``disp``; >= 0. A point with an infinite σ is left out
        of every fit, as a point with a NaN displacement is (its own gradient is NaN); a
        NaN σ at a finite displacement raises.
    weighted : bool
        With ``disp_sigma``: weight the fit by ``1/σ²`` (needs σ > 0). False (default):
        the ordinary least-squares fit (the same gradient as without ``disp_sigma``), its
        covariance from the σ.

    Returns
    -------
    G : (N, 2, 2) array, ``G[n, i, j] = ∂u_i/∂X_j`` (dimensionless), NaN where not enough
        neighbours.
    G_cov : (N, 4, 4) array, only with ``disp_sigma``
        Covariance of ``G[n].reshape(4)`` = ``(∂u_x/∂X, ∂u_x/∂Y, ∂u_y/∂X, ∂u_y/∂Y)``
        (dimensionless², block-diagonal: the x and y components are fitted separately);
        NaN where ``G`` is.

    Raises
    ------
    GeometryError
        Bad ``gauge_length`` / ``min_neighbours``, shapes that do not match, negative σ,
        NaN σ at a finite displacement, or σ = 0 with ``weighted=True``.
    """
    from scipy.spatial import cKDTree

    X, u = _pts_disp(pts_ref, disp)
    if not np.isfinite(gauge_length) or gauge_length <= 0:
        raise GeometryError(f"gauge_length must be > 0, got {gauge_length!r}")
    if min_neighbours < 3:
        raise GeometryError(f"min_neighbours must be >= 3 for an affine fit, got {min_neighbours}")
    n = len(X)
    G = np.full((n, 2, 2), np.nan)
    ok = np.isfinite(X).all(axis=1) & np.isfinite(u).all(axis=1)
    with_cov = disp_sigma is not None
    if weighted and not with_cov:
        raise GeometryError("weighted=True needs disp_sigma (the weights are 1/σ²)")
    if with_cov:
        sg = _disp_sigma(disp_sigma, n)
        if np.isnan(sg[ok]).any():
            raise GeometryError(f"disp_sigma is NaN at {int(np.isnan(sg[ok]).any(axis=1).sum())} "
                                "points with a finite displacement (give inf for an unknown error)")
        if weighted and np.any(sg[ok] == 0):
            raise GeometryError("weighted=True needs disp_sigma > 0 (a zero σ is an infinite weight)")
        ok &= np.isfinite(sg).all(axis=1)
        cov = np.full((n, 4, 4), np.nan)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return (G, cov) if with_cov else G
    tree = cKDTree(X[idx])
    nbrs = tree.query_ball_point(X[idx], r=0.5 * float(gauge_length))
    for a, nb in zip(idx, nbrs):
        if len(nb) < min_neighbours:
            continue
        j = idx[np.asarray(nb)]
        D = X[j] - X[a]
        A = np.column_stack([np.ones(len(j)), D])                 # (m, 3)
        if np.linalg.matrix_rank(A) < 3:
            continue
        if not weighted:
            coef, *_ = np.linalg.lstsq(A, u[j], rcond=None)       # (3, 2)
            G[a] = coef[1:].T
        if not with_cov:
            continue
        cov[a] = 0.0
        for c in (0, 1):
            H = _lsq_operator(A, sg[j, c] if weighted else None)  # (3, m)
            if weighted:
                G[a, c] = (H @ u[j, c])[1:]
            cov[a, 2 * c:2 * c + 2, 2 * c:2 * c + 2] = (H[1:] * sg[j, c] ** 2) @ H[1:].T
    return (G, cov) if with_cov else G


def _lsq_operator(A, sigma=None):
    """(3, m) linear operator ``H`` of the least-squares fit ``c = H u`` of ``A c ≈ u``
    (weights ``1/σ²`` with ``sigma``)."""
    if sigma is None:
        return np.linalg.pinv(A)
    w = 1.0 / np.asarray(sigma, float)
    return np.linalg.pinv(A * w[:, None]) * w[None, :]


def strain_jacobian(G, measure="green_lagrange"):
    """Jacobian of the in-plane strain components with respect to the displacement gradient.

    Rows ``(E_xx, E_yy, E_xy)`` (tensorial shear), columns ``G.reshape(4)`` =
    ``(∂u_x/∂X, ∂u_x/∂Y, ∂u_y/∂X, ∂u_y/∂Y)``. Green–Lagrange ``E = ½(FᵀF − I)``,
    ``F = I + G``: ``∂E_ij/∂G_kl = ½(δ_li F_kj + F_ki δ_lj)``; small strain
    ``ε = ½(G + Gᵀ)``: ``∂ε_ij/∂G_kl = ½(δ_ik δ_jl + δ_jk δ_il)`` (constant).

    Parameters
    ----------
    G : (..., 2, 2) array, dimensionless
    measure : {"green_lagrange", "small"}

    Returns
    -------
    (..., 3, 4) array, dimensionless.
    """
    G = _check_G(G)
    if measure not in ("green_lagrange", "small"):
        raise SemlabError(f"measure must be 'green_lagrange' or 'small', got {measure!r}")
    F = G + np.eye(2) if measure == "green_lagrange" else np.broadcast_to(np.eye(2), G.shape)
    d = np.eye(2)
    J = np.zeros(G.shape[:-2] + (3, 4))
    for row, (i, j) in enumerate(((0, 0), (1, 1), (0, 1))):
        for k in range(2):
            for m in range(2):
                J[..., row, 2 * k + m] = 0.5 * (d[m, i] * F[..., k, j] + F[..., k, i] * d[m, j])
    return J


def strain_covariance(G, G_cov, measure="green_lagrange"):
    """First-order (linear) propagation of a gradient's covariance into its strain's.

    ``Cov(E) = J Cov(G) Jᵀ`` with ``J`` of :func:`strain_jacobian` (exact for the small
    strain, first order in the errors for Green–Lagrange).

    Parameters
    ----------
    G : (..., 2, 2) array, dimensionless
    G_cov : (..., 4, 4) array
        Covariance of ``G.reshape(..., 4)`` (e.g. from :func:`gradient_local_lsq`).
    measure : {"green_lagrange", "small"}

    Returns
    -------
    (..., 3, 3) covariance of ``(E_xx, E_yy, E_xy)``, dimensionless².
    """
    C = np.asarray(G_cov, float)
    J = strain_jacobian(G, measure)
    if C.shape != J.shape[:-2] + (4, 4):
        raise SemlabError(f"G_cov must have shape {J.shape[:-2] + (4, 4)} for G {np.shape(G)}, "
                          f"got {C.shape}")
    return J @ C @ np.swapaxes(J, -1, -2)


def strain_sigma(G, G_cov, measure="green_lagrange"):
    """1σ of ``(E_xx, E_yy, E_xy)``: square roots of the diagonal of :func:`strain_covariance`.

    Returns
    -------
    (..., 3) array, dimensionless (NaN where ``G`` or ``G_cov`` is).
    """
    C = strain_covariance(G, G_cov, measure)
    return np.sqrt(np.maximum(np.diagonal(C, axis1=-2, axis2=-1), 0.0))


def _triangle_coefficients(X, T):
    """(T, 3, 2) ``c``: each triangle's gradient row ``G_t[i, :] = Σ_v u_{v,i} c[t, v]`` over
    its three vertices (the linear triangle of :func:`gradient_from_triangles`)."""
    P = X[T]
    dX = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], axis=2)      # (T, 2, 2) columns
    Minv = np.linalg.inv(dX)                                             # rows: ∂/∂(U1-U0), ∂/∂(U2-U0)
    return np.stack([-(Minv[:, 0] + Minv[:, 1]), Minv[:, 0], Minv[:, 1]], axis=1)


def triangle_gradient_cov(pts_ref, triangles, disp_sigma):
    """Covariance of each constant-strain triangle's gradient.

    A triangle's gradient is linear in its three vertices' displacements,
    ``G_t[i, :] = Σ_v u_{v,i} c_v``, so with independent point errors
    ``Cov(G_t[i, :]) = Σ_v σ_{v,i}² c_v c_vᵀ`` exactly (the x and y rows independent).
    Neighbouring triangles share vertices, so their errors are correlated.

    Parameters
    ----------
    pts_ref : (N, 2) array of reference positions (x, y)
    triangles : (T, 3) int array of indices into ``pts_ref`` (from :func:`gradient_from_triangles`)
    disp_sigma : (N,) or (N, 2) array
        1σ of each point's displacement, in the unit of the displacements (>= 0).

    Returns
    -------
    (T, 4, 4) covariance of ``G_t.reshape(4)`` (dimensionless²; NaN for a triangle with a
    vertex whose σ is not finite).
    """
    X = np.asarray(pts_ref, float)
    T = np.asarray(triangles, int)
    sg = _disp_sigma(disp_sigma, len(X))[T]                             # (T, 3, 2)
    c = _triangle_coefficients(X, T)                                      # (T, 3, 2)
    cov = np.zeros((len(T), 4, 4))
    for i in (0, 1):
        cov[:, 2 * i:2 * i + 2, 2 * i:2 * i + 2] = np.einsum("tvk,tv,tvl->tkl", c,
                                                             sg[:, :, i] ** 2, c)
    cov[~np.isfinite(sg).all(axis=(1, 2))] = np.nan
    return cov


def mean_gradient_cov(pts_ref, triangles, weights, disp_sigma):
    """Covariance of the weighted mean gradient of constant-strain triangles.

    The mean ``Ḡ = Σ_t w_t G_t / Σ_t w_t`` of :func:`gradient_from_triangles` is linear in the
    vertex displacements, ``Ḡ[i, :] = Σ_v u_v[i] b_v``, so with independent point errors
    ``Cov(Ḡ[i, :]) = Σ_v σ_{v,i}² b_v b_vᵀ`` exactly (the x and y rows independent).

    Parameters
    ----------
    pts_ref : (N, 2) array of reference positions (x, y)
    triangles : (T, 3) int array of indices into ``pts_ref`` (from :func:`gradient_from_triangles`)
    weights : (T,) array, e.g. :func:`triangle_areas`
    disp_sigma : (N,) or (N, 2) array
        1σ of each point's displacement, in the unit of the displacements (>= 0; only the
        triangles' vertices need to be finite).

    Returns
    -------
    (4, 4) covariance of ``Ḡ.reshape(4)`` (dimensionless²; NaN if a vertex's σ is not
    finite).
    """
    X = np.asarray(pts_ref, float)
    T = np.asarray(triangles, int)
    w = np.asarray(weights, float)
    sg = _disp_sigma(disp_sigma, len(X))
    c = _triangle_coefficients(X, T)
    b = np.zeros((len(X), 2))
    np.add.at(b, T.ravel(), (c * (w / w.sum())[:, None, None]).reshape(-1, 2))
    used = np.unique(T)
    if not np.isfinite(sg[used]).all():
        return np.full((4, 4), np.nan)
    cov = np.zeros((4, 4))
    for i in (0, 1):
        bb = b[used]
        cov[2 * i:2 * i + 2, 2 * i:2 * i + 2] = (bb * sg[used, i, None] ** 2).T @ bb
    return cov


def gradient_from_field(ux, uy, spacing_um, window=None, min_points=6):
    """Displacement gradient of dense fields on a regular grid.

    Parameters
    ----------
    ux, uy : (H, W) arrays
        Displacement components on a regular grid (rows = y, columns = x), in µm; NaN marks
        grid points without a (trustworthy) measurement.
    spacing_um : float or (2,) sequence
        Grid spacing (dx, dy) in µm (a float for both).
    window : int, optional
        ``None``: central differences (``np.gradient``; a NaN spreads to its neighbours).
        An odd int >= 3: the gradient of the least-squares plane fitted to the finite values
        in the ``window × window`` grid points around each point — the "strain window" of
        DIC software (Pan et al. 2009, "Full-field strain measurement using a
        two-dimensional Savitzky-Golay digital differentiator in digital image
        correlation", Opt. Eng. 46(3)). It averages the matching noise over the window
        (gauge length ``window × spacing``) and skips missing points; exact for a linear
        field.
    min_points : int
        With ``window``: fewest finite points a window needs (else NaN), >= 3.

    Returns
    -------
    (H, W, 2, 2) array ``G[r, c, i, j] = ∂u_i/∂X_j``.
    """
    ux = np.asarray(ux, float)
    uy = np.asarray(uy, float)
    if ux.ndim != 2 or ux.shape != uy.shape:
        raise SemlabError(f"ux and uy must be 2D arrays of the same shape, got {ux.shape} and {uy.shape}")
    if min(ux.shape) < 2:
        raise SemlabError(f"fields of shape {ux.shape} are too small for a gradient (need >= 2x2)")
    sp = np.broadcast_to(np.asarray(spacing_um, float), (2,))
    if not (np.isfinite(sp).all() and (sp > 0).all()):
        raise SemlabError(f"spacing_um must be positive, got {spacing_um!r}")
    dx, dy = sp
    G = np.empty(ux.shape + (2, 2))
    if window is None:
        duxdy, duxdx = np.gradient(ux, dy, dx)
        duydy, duydx = np.gradient(uy, dy, dx)
        G[..., 0, 0] = duxdx
        G[..., 0, 1] = duxdy
        G[..., 1, 0] = duydx
        G[..., 1, 1] = duydy
        return G
    if int(window) != window or window < 3 or window % 2 == 0:
        raise SemlabError(f"window must be an odd number of grid points >= 3, got {window!r}")
    if min_points < 3:
        raise SemlabError(f"min_points must be >= 3 (a plane has 3 parameters), got {min_points!r}")
    from scipy import ndimage

    k = int(window) // 2
    oy, ox = np.mgrid[-k:k + 1, -k:k + 1].astype(float)
    one = np.ones_like(ox)

    def wsum(a, kern):  # Σ over the window of a(r + i, c + j) · kern(i, j)
        return ndimage.correlate(a, kern, mode="constant", cval=0.0)

    w = (np.isfinite(ux) & np.isfinite(uy)).astype(float)
    s0, sx, sy = wsum(w, one), wsum(w, ox), wsum(w, oy)
    sxx, sxy, syy = wsum(w, ox * ox), wsum(w, ox * oy), wsum(w, oy * oy)
    N = np.stack([np.stack([s0, sx, sy], -1), np.stack([sx, sxx, sxy], -1),
                  np.stack([sy, sxy, syy], -1)], -2)                     # (H, W, 3, 3)
    det = np.linalg.det(N)
    ok = (s0 >= min_points) & (det > 1e-9 * np.maximum(s0, 1.0) ** 3)
    G[:] = np.nan
    for i, u in enumerate((ux, uy)):
        uw = np.where(w > 0, u, 0.0)
        rhs = np.stack([wsum(uw, one), wsum(uw, ox), wsum(uw, oy)], -1)
        sol = np.linalg.solve(N[ok], rhs[ok][..., None])[..., 0]
        G[ok, i, 0] = sol[:, 1] / dx
        G[ok, i, 1] = sol[:, 2] / dy
    return G


def _check_G(G, d=2):
    G = np.asarray(G, float)
    if G.shape[-2:] != (d, d):
        raise SemlabError(f"expected (..., {d}, {d}) gradients, got shape {G.shape}")
    return G


def small_strain(G):
    """Infinitesimal strain ``ε = ½ (G + Gᵀ)`` of (..., 2, 2) gradients (Malvern eq. 4.5.6)."""
    G = _check_G(G)
    return 0.5 * (G + np.swapaxes(G, -1, -2))


def green_lagrange(G):
    """Green-Lagrange strain ``E = ½ (G + Gᵀ + Gᵀ G)`` (Holzapfel eq. 2.69) of (..., 2, 2)."""
    G = _check_G(G)
    Gt = np.swapaxes(G, -1, -2)
    return 0.5 * (G + Gt + Gt @ G)


def surface_green_lagrange(G_inplane, grad_uz):
    """Green-Lagrange strain of the surface including the out-of-plane displacement.

    ``E_ij = ½ (∂u_i/∂X_j + ∂u_j/∂X_i + Σ_k ∂u_k/∂X_i ∂u_k/∂X_j)``, i, j ∈ {x, y},
    k ∈ {x, y, z}: the in-plane Green-Lagrange strain plus ``½ ∇u_z ⊗ ∇u_z`` (the metric
    change of a surface that also moves out of plane; cf. von Kármán plate kinematics).

    Parameters
    ----------
    G_inplane : (..., 2, 2) array
        In-plane gradient ``∂u_i/∂X_j``.
    grad_uz : (..., 2) array
        ``(∂u_z/∂X, ∂u_z/∂Y)`` (e.g. from the change of height between two states).

    Returns
    -------
    (..., 2, 2) array.
    """
    G = _check_G(G_inplane)
    g = np.asarray(grad_uz, float)
    if g.shape != G.shape[:-1]:
        raise SemlabError(f"grad_uz must have shape {G.shape[:-1]} to match G_inplane {G.shape}, "
                          f"got {g.shape}")
    return green_lagrange(G) + 0.5 * g[..., :, None] * g[..., None, :]


def principal_strains(E):
    """Principal strains and direction of (..., 2, 2) symmetric strain tensors.

    Returns
    -------
    e1, e2 : arrays (...,), ``e1 >= e2``
    angle_deg : array (...,)
        Angle of the ``e1`` direction from the +x axis, degrees in (-90, 90], measured
        toward +y (image y is down, so positive angles turn clockwise on screen).
    """
    E = _check_G(E)
    exx, eyy = E[..., 0, 0], E[..., 1, 1]
    exy = 0.5 * (E[..., 0, 1] + E[..., 1, 0])
    c = 0.5 * (exx + eyy)
    r = np.sqrt((0.5 * (exx - eyy)) ** 2 + exy ** 2)
    ang = 0.5 * np.degrees(np.arctan2(2 * exy, exx - eyy))
    ang = np.where(ang <= -90, ang + 180, ang)
    return c + r, c - r, ang


def max_shear(E):
    """Maximum (tensorial) in-plane shear strain ``(e1 - e2) / 2``; the engineering value is twice it."""
    e1, e2, _ = principal_strains(E)
    return 0.5 * (e1 - e2)


def strain_history(tracks_xy_per_frame, cycles, valid=None, ref_frame=0, pixel_size_um=None,
                   method="triangles", measure="green_lagrange", gauge_length=None,
                   min_points=3, sigma_px=None):
    """Mean in-plane strain of the tracked area in every frame (a strain-vs-cycles curve).

    The reference configuration is frame ``ref_frame`` (default the earliest, 0). In each
    frame the displacement ``u = x_f - x_ref`` of the points valid in both frames gives a
    gradient field whose mean is taken (the strain reported is that of the mean gradient):
    area-weighted over the CST triangles (for linear
    elements this equals the boundary average of the displacement, i.e. the mean gradient
    of the region) or the plain mean of the local least-squares gradients.

    Parameters
    ----------
    tracks_xy_per_frame : (F, N, 2) array of (x, y) pixels (``Tracks.xy``)
    cycles : (F,) array
        Load cycles at each frame.
    valid : (F, N) bool array, optional
        Step validity (``Tracks.valid``); default: finite positions.
    ref_frame : int
    pixel_size_um : float, optional
        Only scales positions; strains are dimensionless either way.
    method : {"triangles", "lsq"}
    measure : {"green_lagrange", "small"}
    gauge_length : float, optional
        Gauge diameter (pixels) for ``method="lsq"`` (required there).
    min_points : int
        Frames with fewer common valid points get NaN.
    sigma_px : (F, N) array, optional
        1σ of each track's position in each frame relative to ``ref_frame``, pixels (with
        ``ref_frame`` the last frame, ``Tracks.sigma_px``): the σ of the displacement from
        ``ref_frame`` to frame f is ``sigma_px[f]``. With ``method="triangles"`` gives
        ``exx_sigma``, ``eyy_sigma``, ``exy_sigma``: the 1σ of the mean strain, propagated
        exactly to the mean gradient (:func:`mean_gradient_cov`, points independent) and to
        first order to the strain; the mean over hundreds of tracks makes it small, and
        errors shared by the tracks (drift, bias) are not in it. NaN with ``method="lsq"``
        (overlapping gauges: the mean's covariance would need their cross-covariances).

    Returns
    -------
    dict of (F,) arrays: ``cycles``, ``exx``, ``eyy``, ``exy``, ``e1``, ``e2``,
    ``angle_deg`` (of the mean tensor), ``n_points``; with ``sigma_px`` also ``exx_sigma``,
    ``eyy_sigma``, ``exy_sigma`` (dimensionless).
    """
    xy = np.asarray(tracks_xy_per_frame, float)
    if xy.ndim != 3 or xy.shape[2] != 2:
        raise SemlabError(f"tracks_xy_per_frame must be (F, N, 2), got shape {xy.shape}")
    F, N, _ = xy.shape
    cyc = np.asarray(cycles, float)
    if cyc.shape != (F,):
        raise SemlabError(f"cycles must have one value per frame ({F}), got shape {cyc.shape}")
    if method not in ("triangles", "lsq"):
        raise SemlabError(f"method must be 'triangles' or 'lsq', got {method!r}")
    if measure not in ("green_lagrange", "small"):
        raise SemlabError(f"measure must be 'green_lagrange' or 'small', got {measure!r}")
    if method == "lsq" and gauge_length is None:
        raise SemlabError("method='lsq' needs gauge_length (pixels)")
    ok = np.isfinite(xy).all(axis=2)
    if valid is not None:
        v = np.asarray(valid, bool)
        if v.shape != (F, N):
            raise SemlabError(f"valid must have shape {(F, N)}, got {v.shape}")
        ok &= v
    r = int(ref_frame) % F
    s = 1.0 if pixel_size_um is None else float(pixel_size_um)
    strain_fn = green_lagrange if measure == "green_lagrange" else small_strain
    keys = ("exx", "eyy", "exy", "e1", "e2", "angle_deg")
    if sigma_px is not None:
        sig = np.asarray(sigma_px, float)
        if sig.shape != (F, N):
            raise SemlabError(f"sigma_px must have shape {(F, N)}, got {sig.shape}")
        keys += ("exx_sigma", "eyy_sigma", "exy_sigma")
    out = {k: np.full(F, np.nan) for k in keys}
    out["n_points"] = np.zeros(F, int)
    for f in range(F):
        use = ok[f] & ok[r]
        out["n_points"][f] = int(use.sum())
        if use.sum() < max(3, min_points):
            continue
        X = xy[r, use] * s
        u = (xy[f, use] - xy[r, use]) * s
        try:
            if method == "triangles":
                G, T = gradient_from_triangles(X, u)
                w = triangle_areas(X, T)
                Gm = (G * w[:, None, None]).sum(axis=0) / w.sum()
                if sigma_px is not None:
                    C = mean_gradient_cov(X, T, w, sig[f, use] * s)
                    sd = strain_sigma(Gm, C, measure)
                    out["exx_sigma"][f], out["eyy_sigma"][f], out["exy_sigma"][f] = sd
            else:
                G = gradient_local_lsq(X, u, gauge_length * s)
                Gm = np.nanmean(G, axis=0) if np.isfinite(G).any() else np.full((2, 2), np.nan)
        except GeometryError:
            continue
        E = strain_fn(Gm)
        e1, e2, a = principal_strains(E)
        out["exx"][f], out["eyy"][f], out["exy"][f] = E[0, 0], E[1, 1], E[0, 1]
        out["e1"][f], out["e2"][f], out["angle_deg"][f] = e1, e2, a
    out["cycles"] = cyc
    return out


#: Dense strain grid (:func:`strain_from_tracks`): Gaussian pre-smoothing of its IC-GN (removes most of the interpolation
#: bias that varies with the sub-pixel phase of the displacement and shows in its gradient),
#: the lowest ZNCC a grid subset needs to enter the strain (None: every converged subset
#: does), and the strain window in grid points (see semlab.strain.gradient_from_field).
#: The ZNCC floor was 0.95 until 2026-12-07: it left out the subsets on the slip bands,
#: whose appearance changes as they deform (ZNCC 0.4-0.95) but whose displacements are
#: measured, so the plane fits missed the bands' steps (``benchmarks/dense_strain_bands.py``);
#: the noise of textureless subsets, which it was for, is averaged by the strain window (on a
#: uniform strain without bands the dense median is within 2.1 % of the truth, with the
#: smaller subsets and the interpolation of DENSE_HALF_WINDOWS and fill_dense_holes; 1.9 %
#: with the floor; ``benchmarks/results/dense_strain_bands.md``).
DENSE_SMOOTH_SIGMA_PX = 0.8
DENSE_MIN_ZNCC = None
DENSE_WINDOW = 7
#: Half sizes of the dense grid's subsets, tried in turn where the larger did not converge:
#: a subset across a slip band's step does not fit any shape function, a smaller one beside
#: the step does (the points left unmatched at a band took part of its step out of the plane
#: fits; ``benchmarks/dense_strain_bands.py``). The first sets the grid's margin.
DENSE_HALF_WINDOWS = (10, 7, 5)
#: Posterior draws of the variational map for the dense strain's 1σ (``E_sigma``).
DENSE_FLOW_SAMPLES = 16


def fill_dense_holes(ux, uy, window=DENSE_WINDOW, min_points=6):
    """Interpolate the grid points without a measurement from their measured neighbours.

    A grid point whose subset did not converge (at a slip band's step, where the surface
    shears within a subset, or in a texture-free patch) would leave its strain window's plane
    fit without the displacement there; at a step that takes part of the step out of the fit
    (a perfect tracker's grid with the speckle band series' unmatched points missing gives a
    mean E_yy of 0.0009 instead of 0.0030, ``benchmarks/results/dense_strain_bands.md``).
    Each such point inside the measured points' convex hull whose own window holds at least
    ``min_points`` measured points gets the displacement linearly interpolated (Delaunay
    triangles of the measured grid points, :func:`scipy.interpolate.griddata`): across a step,
    a ramp that keeps the step's size. Points outside the hull or with fewer measured
    neighbours stay NaN.

    Parameters
    ----------
    ux, uy : (H, W) arrays
        Displacement on a regular grid (rows = y), any unit; NaN where not measured.
    window : int
        Strain window in grid points (odd).
    min_points : int
        Fewest measured points in a point's window for it to be filled.

    Returns
    -------
    ux, uy : (H, W) arrays
        With the holes filled.
    filled : (H, W) bool array
        True where the value is interpolated, not measured.
    """
    from scipy import ndimage
    from scipy.interpolate import griddata
    from scipy.spatial import QhullError

    ux = np.array(ux, float)
    uy = np.array(uy, float)
    measured = np.isfinite(ux) & np.isfinite(uy)
    k = int(window)
    near = ndimage.correlate(measured.astype(float), np.ones((k, k)), mode="constant")
    want = ~measured & (near >= min_points)
    filled = np.zeros(ux.shape, bool)
    if want.any() and measured.sum() >= 3:
        rc = np.argwhere(measured).astype(float)
        at = np.argwhere(want).astype(float)
        try:
            vals = [griddata(rc, u[measured], at, method="linear") for u in (ux, uy)]
        except QhullError:   # the measured points on one line: nothing lies between them
            return ux, uy, filled
        ok = np.isfinite(vals[0]) & np.isfinite(vals[1])
        idx = tuple(np.argwhere(want)[ok].T)
        ux[idx], uy[idx] = vals[0][ok], vals[1][ok]
        filled[idx] = True
    return ux, uy, filled


def dense_field_strain(ux, uy, spacing_um, window=DENSE_WINDOW, zncc=None, min_zncc=None,
                       fill=True):
    """Deformation gradient and Green–Lagrange strain of a dense grid's displacements.

    Parameters
    ----------
    ux, uy : (H, W) arrays
        Displacement ``U(x) = x_end − X_ref`` on the end-state grid (rows = y), µm; NaN where
        the subset did not converge.
    spacing_um : float
        Grid spacing, µm.
    window : int
        Strain window in grid points (:func:`gradient_from_field`).
    zncc : (H, W) array, optional
        The subsets' ZNCC, for ``min_zncc``.
    min_zncc : float, optional
        Leave out subsets below this ZNCC (None: every converged subset enters; see
        :data:`DENSE_MIN_ZNCC`); with ``fill`` they are then interpolated like the points
        that did not converge.
    fill : bool
        Interpolate the points without a measurement before the plane fits
        (:func:`fill_dense_holes`).

    Returns
    -------
    F : (H, W, 2, 2) array
        ``(I − ∂U/∂x)⁻¹`` (NaN where the window has too few points).
    E : (H, W, 2, 2) array
        Green–Lagrange strain ``½(FᵀF − I)``.
    filled : (H, W) bool array
        Where the displacement entering the fits was interpolated (all False without ``fill``).
    """
    good = np.ones(np.shape(ux), bool)
    if min_zncc is not None:
        if zncc is None:
            raise SemlabError("dense_field_strain: min_zncc needs the subsets' zncc")
        good = np.asarray(zncc, float) >= min_zncc
    ux, uy = np.where(good, ux, np.nan), np.where(good, uy, np.nan)
    if fill:
        ux, uy, filled = fill_dense_holes(ux, uy, window)
    else:
        filled = np.zeros(np.shape(ux), bool)
    G = gradient_from_field(ux, uy, spacing_um, window=window)
    eye = np.eye(2)
    finite = np.all(np.isfinite(G), axis=(-2, -1))
    F = np.full(G.shape, np.nan)
    F[finite] = np.linalg.inv(eye - G[finite])
    return F, green_lagrange(F - eye), filled


def _dense_match(last_img, ref_img, grid, guess, half_windows, smooth_sigma_px, progress):
    """IC-GN of the dense grid's subsets (in ``last_img``, searched in ``ref_img`` from
    ``grid + guess``), each with the largest of ``half_windows`` that converges (tried in turn
    on the points still unmatched, not on those whose subset left the image). Returns
    (positions in the reference frame, converged, zncc, half size or 0), per grid point."""
    from .parallel import tiled_icgn
    from .subset import OUTSIDE

    n = len(grid)
    pts, zncc = np.full((n, 2), np.nan), np.full(n, np.nan)
    half = np.zeros(n, int)
    todo = np.ones(n, bool)
    for h in half_windows:
        idx = np.flatnonzero(todo)
        if not len(idx):
            break
        r = tiled_icgn(last_img, ref_img, grid[idx], grid[idx] + guess[idx], half_window=int(h),
                       smooth_sigma_px=smooth_sigma_px, progress=progress)
        ok = r.converged
        pts[idx[ok]], zncc[idx[ok]], half[idx[ok]] = r.pts[ok], r.zncc[ok], int(h)
        todo[idx[ok | (r.reason == OUTSIDE)]] = False
    return pts, half > 0, zncc, half


def _track_interpolator(p_end, back):
    """The tracks' displacement ``back`` ((N, 2), at their last-frame positions ``p_end``)
    as a function of last-frame points: linear on one Delaunay triangulation of the tracks,
    the nearest track's value outside their hull."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    lin = LinearNDInterpolator(p_end, back)
    near = NearestNDInterpolator(p_end, back)

    def at(pts):
        v = lin(pts)
        return np.where(np.isfinite(v), v, near(pts))
    return at


def _dense_flow(last_img, ref_img, start_at, grid, params, progress):
    """The variational displacement map (:func:`semlab.flow.variational_flow`) from the last
    frame into the reference frame, started at ``start_at`` (the tracks' displacement,
    :func:`_track_interpolator`) at every pixel, sampled at the grid points. Returns
    (positions in the reference frame, inside, the map's info)."""
    from .flow import variational_flow

    h, w = last_img.shape
    yy, xx = np.mgrid[0:h, 0:w]
    start = start_at(np.column_stack([xx.ravel(), yy.ravel()]).astype(float))
    c = np.round(grid).astype(int)
    u, v, info = variational_flow(last_img, ref_img, start[:, 0].reshape(h, w),
                                  start[:, 1].reshape(h, w), params=params, progress=progress,
                                  n_samples=DENSE_FLOW_SAMPLES, sample_at=c)
    pts = grid + np.column_stack([u[c[:, 1], c[:, 0]], v[c[:, 1], c[:, 0]]])
    inside = ((pts[:, 0] >= 0) & (pts[:, 0] <= w - 1) & (pts[:, 1] >= 0)
              & (pts[:, 1] <= h - 1))
    return pts, inside, info


def chained_flow_start(frames, ref_frame, registration=None, params=None, progress=False):
    """A start for the dense map from the last frame into ``ref_frame`` without tracks.

    Variational maps (:func:`semlab.flow.variational_flow`) from the last frame into each
    earlier frame in turn, down to ``ref_frame + 1``, each started at the one before plus the
    stage drift between the two frames (``registration``): every map starts within one
    frame's deformation of its answer, as the tracks step back one frame at a time.

    Parameters
    ----------
    frames : sequence of F (H, W) arrays, chronological (the last is the end state)
    ref_frame : int
    registration : semlab.registration.Registration, optional
        The series' drift (``transforms[k]`` maps last-frame pixels into frame k); None: no
        drift.
    params : semlab.flow.FlowParams, optional
    progress : bool

    Returns
    -------
    (H, W, 2) float array
        Displacement (x, y) of every last-frame pixel into ``ref_frame``, pixels: the map into
        ``ref_frame + 1`` moved by the drift between it and ``ref_frame``.
    """
    from tqdm.auto import tqdm

    from .flow import variational_flow

    h, w = frames[-1].shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    p = np.column_stack([xx.ravel(), yy.ravel()])

    def drift(k):
        if registration is None:
            return np.zeros((h, w, 2))
        return (registration.transforms[k](p) - p).reshape(h, w, 2)

    last = len(frames) - 1
    d, before = np.zeros((h, w, 2)), drift(last)
    for k in tqdm(range(last - 1, ref_frame - 1, -1), desc="dense map, frame by frame",
                  disable=not progress):
        now = drift(k)
        d, before = d + now - before, now
        if k > ref_frame:                      # the map into ref_frame is the caller's
            u, v, _ = variational_flow(frames[-1], frames[k], d[..., 0], d[..., 1],
                                       params=params)
            d = np.stack([u, v], -1)
    return d


def _dense_sigma(samples_px, bias_px, ux, uy, E, step_px, s, window):
    """1σ of the dense strain's ``(E_xx, E_yy, E_xy)``, (H, W, 3), from the variational map's
    posterior draws of the grid points' displacement (``(n, N, 2)`` pixels, perturbations of
    the reference-frame position ``X_ref``, so of ``−U``), the RMS over the draws of
    ``E(U + δU) − E(U)``, and its prior's pull (``(N, 2)``, likewise) in full:
    ``σ² = mean_draws ΔE² + ΔE_pull²``."""
    def change(d):
        Es = dense_field_strain(ux - d[:, 0].reshape(ux.shape) * s,
                                uy - d[:, 1].reshape(ux.shape) * s, step_px * s, window,
                                fill=False)[1]
        return np.stack([Es[..., 0, 0] - E[..., 0, 0], Es[..., 1, 1] - E[..., 1, 1],
                         Es[..., 0, 1] - E[..., 0, 1]], -1)

    var = np.mean([change(d) ** 2 for d in samples_px], axis=0)
    return np.sqrt(var + change(bias_px) ** 2)


def strain_from_tracks(frames, xy, valid, pixel_size_um, ref_frame, gauge_length_px=None,
                       grid_step_px=16, heights=None, progress=False,
                       dense_window=DENSE_WINDOW, dense_min_zncc=DENSE_MIN_ZNCC,
                       dense_smooth_sigma_px=DENSE_SMOOTH_SIGMA_PX, sigma_px=None,
                       dense_half_windows=DENSE_HALF_WINDOWS, dense_fill=True,
                       dense_method="variational", dense_flow_params=None,
                       dense_start_px=None):
    """Strain between ``ref_frame`` and the last frame, sparse and dense.

    Sparse: constant-strain Delaunay triangles and a local least-squares gradient with gauge
    length ``gauge_length_px`` on the tracks valid in both frames (None: the diameter of a
    disc that holds about 12 tracks at their mean density). Dense: the displacement from the
    last frame into ``ref_frame`` on a grid of the last frame (every ``grid_step_px``), by
    ``dense_method``: ``"variational"`` (default) the variational displacement map of
    :func:`semlab.flow.variational_flow` (``dense_flow_params``), started at the tracks'
    displacements interpolated to every pixel and sampled at the grid points (solved in
    tiles on frames larger than ``FlowParams.tile_px``); ``"subsets"`` a grid of subsets
    matched by IC-GN (initial guess interpolated from the tracks; each point's subset the
    largest of ``dense_half_windows`` that converges, so a point beside a slip band's step is
    matched by a subset that does not straddle it; every converged subset enters, or with
    ``dense_min_zncc`` only those with at least that ZNCC; with ``dense_fill`` the points left
    without a match are interpolated from their neighbours, :func:`fill_dense_holes`). On
    four series with slip bands the map's strain is 1.4–2.8× more accurate than the
    subsets' on every component (``benchmarks/results/dense_strain_bands.md``). The gradient
    is the plane fit over ``dense_window`` × ``dense_window`` grid points, a gauge of
    ``dense_window × grid_step_px``; with ``U(x)`` the displacement as a function of
    end-state position, ``F = (I − ∂U/∂x)⁻¹`` and the Green–Lagrange strain
    ``E = ½(FᵀF − I)``. With ``heights``
    (a callable z_um(x_px, y_px) in last-frame pixels), the surface strain including the
    out-of-plane gradient (heights taken as the out-of-plane displacement of an initially flat,
    polished surface) is added.

    With ``sigma_px`` (``Tracks.sigma_px`` of :func:`semlab.tracking.track_reverse`), the 1σ
    of the sparse local least-squares strain ``E_lsq_sigma`` is propagated from the tracks'
    errors (:func:`gradient_local_lsq` with ``disp_sigma``, then :func:`strain_sigma`, first
    order). The displacement of a track is ``xy[-1] − xy[ref_frame]``; the last frame holds
    the seeds (the reference of the tracking, σ 0) and, with the tracking's direct correction
    (its default), ``sigma_px[ref_frame]`` is the predicted 1σ of the track's position in
    ``ref_frame`` matched directly against its seed window in the last frame (larger of the
    two components, with sized subsets including the subset's model error): the
    displacement's σ in each component, pixels (times ``pixel_size_um``). Without direct
    correction it is the σ of the last chained step only, not of the accumulated chain, and
    would be too small. The points' errors are taken independent, so an error shared by
    neighbouring tracks (the model error of overlapping subsets, a stage-drift residual) is
    not in ``E_lsq_sigma``; the fit itself stays unweighted (``E_lsq`` is the same with or
    without ``sigma_px``, except that tracks with an infinite σ are left out). ``E_tri_sigma``
    is the same for each triangle, exact to the gradient (:func:`triangle_gradient_cov`)
    and first order to the strain. The dense ``E`` of the variational map has a 1σ,
    ``E_sigma``: its (E_xx, E_yy, E_xy) under the map's posterior draws at the last
    linearisation (:data:`DENSE_FLOW_SAMPLES`; they carry the correlation of neighbouring
    points) through the same plane fits, plus the change the map's prior pull (how it rounds
    a band's step) makes, in full. Measured (``benchmarks/dense_strain_bands.py``): 84–98 %
    of the grid points within 2σ of a perfect tracker's strain on four series with slip bands,
    fewer on E_yy and E_xy of the bands (short there); on a uniform strain with 30 % noise
    1.7–2.7× the empirical scatter (conservative where the field is smooth). The subsets'
    ``E`` has no σ (overlapping subsets, correlated errors). The sparse ``E_lsq_sigma``: on
    the uniform-strain benchmark (``benchmarks/strain_accuracy.py``,
    ``benchmarks/results/strain_sigma.md``) the σ holds with sized subsets (RMS error/σ
    0.93–1.31) and is up to 2.3× too small with LK or fixed subsets, whose ``sigma_px`` is
    itself 1.1–1.8× too small.

    Parameters
    ----------
    sigma_px : (F, N) array, optional
        Predicted 1σ of each track's position in each frame relative to the last frame,
        pixels (``Tracks.sigma_px``). None: ``E_lsq_sigma`` is NaN.
    dense_method : {"variational", "subsets"}
        The dense displacement (above).
    dense_flow_params : semlab.flow.FlowParams, optional
        Parameters of the variational map (default ``FlowParams()``).
    dense_start_px : (H, W, 2) array, optional
        Where the dense displacement starts instead of the tracks' (x, y displacement of
        every last-frame pixel into ``ref_frame``, pixels; e.g. :func:`chained_flow_start`).
        With it, fewer than 6 tracks valid in both frames leave the sparse strain empty
        (``pts_px`` (0, 2), ``gauge_length_um`` NaN) instead of raising.

    Returns
    -------
    dict of arrays: ``ref_frame``, ``gauge_length_um``, sparse ``pts_px`` (M, 2) last-frame
    positions, ``E_lsq`` (M, 2, 2), ``E_lsq_sigma`` (M, 3) the 1σ of ``E_lsq``'s
    ``(E_xx, E_yy, E_xy)`` (dimensionless, NaN where ``E_lsq`` is or without ``sigma_px``),
    ``tri`` (T, 3), ``E_tri`` (T, 2, 2), ``E_tri_sigma`` (T, 3) likewise; dense ``grid_x_px``,
    ``grid_y_px`` (1D), ``ux_um``, ``uy_um``, ``E`` (H, W, 2, 2), ``e1``, ``e2``, ``angle_deg``,
    ``max_shear``, ``zncc`` (the subsets'; NaN with the map), ``dense_gauge_um``,
    ``dense_filled`` (H, W) bool, where the displacement entering the strain was interpolated
    (``ux_um``/``uy_um`` are NaN there; none with the map), ``dense_half_px`` (H, W) int, each
    point's subset half size (0: none converged, or the map; its spatial resolution is
    ``2 h + 1`` pixels), ``dense_method`` (``"variational"`` or ``"subsets"``, the one used),
    ``dense_prior_scale_px`` (the map's prior scale, with the map), ``dense_flow_tiles`` (the
    map's tiles at full resolution, 1: untiled), ``dense_flow_params`` (its
    :class:`~semlab.flow.FlowParams` as a dict), ``E_sigma`` (H, W, 3),
    the 1σ of the dense ``(E_xx, E_yy, E_xy)`` (with the map only), and ``E_surface`` when
    heights are given.

    Examples
    --------
    A texture stretched by 1 % in x between frame 0 and frame 1, tracks on a grid (Green–Lagrange
    E_xx = 0.01 + 0.01²/2):

    >>> import numpy as np, semlab
    >>> from scipy import ndimage
    >>> rng = np.random.default_rng(1)
    >>> f1 = ndimage.gaussian_filter(rng.normal(size=(128, 128)), 1.5)
    >>> yy, xx = np.mgrid[0:128, 0:128].astype(float)
    >>> f0 = ndimage.map_coordinates(f1, [yy, 64 + (xx - 64) * 1.01], order=3, mode="nearest")
    >>> g = np.stack(np.meshgrid(np.arange(24.0, 104, 8), np.arange(24.0, 104, 8)), -1).reshape(-1, 2)
    >>> xy = np.stack([np.column_stack([64 + (g[:, 0] - 64) / 1.01, g[:, 1]]), g])
    >>> valid = np.ones(xy.shape[:2], bool)
    >>> S = semlab.strain_from_tracks([f0, f1], xy, valid, pixel_size_um=0.03, ref_frame=0)
    >>> round(float(np.nanmedian(S["E_lsq"][:, 0, 0])), 4), round(float(np.nanmedian(S["E_lsq"][:, 1, 1])), 4)
    (0.0101, 0.0)

    With each track's position σ (here 0.02 px in frame 0, 0 in the last frame, where the seeds
    are), the 1σ of the sparse strain (E_xx, E_yy, E_xy) at each track:

    >>> sig = np.stack([np.full(len(g), 0.02), np.zeros(len(g))])
    >>> S = semlab.strain_from_tracks([f0, f1], xy, valid, pixel_size_um=0.03, ref_frame=0,
    ...                               sigma_px=sig)
    >>> S["E_lsq_sigma"].shape, np.round(np.nanmedian(S["E_lsq_sigma"], axis=0), 4).tolist()
    ((100, 3), [0.001, 0.001, 0.0007])
    """

    if dense_method not in ("variational", "subsets"):
        raise SemlabError(f"dense_method must be 'variational' or 'subsets', got "
                          f"{dense_method!r}")
    s = float(pixel_size_um)
    ok = valid[ref_frame] & valid[-1] & np.all(np.isfinite(xy[ref_frame]), axis=1)
    out = {"ref_frame": int(ref_frame)}
    p_ref, p_end = xy[ref_frame][ok], xy[-1][ok]
    if ok.sum() < 6 and dense_start_px is None:
        raise SemlabError(f"only {int(ok.sum())} tracks are valid in both frame {ref_frame} and the "
                          "last frame: too few for strain (need 6)")
    h, w = frames[-1].shape
    if dense_start_px is not None:
        start_px = np.asarray(dense_start_px, float)
        if start_px.shape != (h, w, 2) or not np.all(np.isfinite(start_px)):
            raise SemlabError(f"dense_start_px must be a finite ({h}, {w}, 2) array, got "
                              f"shape {start_px.shape}")
    if ok.sum() < 6:
        out.update(_no_sparse_strain())
    else:
        out.update(_sparse_strain(p_ref, p_end, s, gauge_length_px, ok, ref_frame, sigma_px,
                                  np.shape(xy)[:2]))

    # dense: the displacement from the last frame into the reference frame on a grid of the
    # last frame, started from the tracks (or dense_start_px)
    if dense_start_px is None:
        # where end-state points were in the reference frame, interpolated from the tracks
        start_at = _track_interpolator(p_end, p_ref - p_end)
    else:
        def start_at(pts):
            c = np.clip(np.round(pts).astype(int), 0, [w - 1, h - 1])
            return start_px[c[:, 1], c[:, 0]]
    out.update(_dense_strain(frames, ref_frame, s, start_at, heights, progress,
                             grid_step_px=grid_step_px, window=dense_window,
                             min_zncc=dense_min_zncc, smooth_sigma_px=dense_smooth_sigma_px,
                             half_windows=dense_half_windows, fill=dense_fill,
                             method=dense_method, flow_params=dense_flow_params))
    return out


def _no_sparse_strain():
    """The sparse part of :func:`strain_from_tracks` without tracks: empty, NaN gauge."""
    z3, z22 = np.zeros((0, 3)), np.zeros((0, 2, 2))
    return dict(gauge_length_um=np.nan, pts_px=np.zeros((0, 2)), E_lsq=z22, E_lsq_sigma=z3,
                tri=np.zeros((0, 3), int), E_tri=z22, E_tri_sigma=z3)


def _sparse_strain(p_ref, p_end, s, gauge_length_px, ok, ref_frame, sigma_px, shape):
    """The sparse part of :func:`strain_from_tracks` (its docstring)."""
    out = {}
    disp_um = (p_end - p_ref) * s
    if gauge_length_px is None:
        span = np.ptp(p_ref, axis=0)
        density = len(p_ref) / max(span[0] * span[1], 1.0)
        gauge_length_px = 2.0 * np.sqrt(12.0 / (np.pi * density))
    out["gauge_length_um"] = gauge_length_px * s
    if sigma_px is None:
        G_lsq = gradient_local_lsq(p_ref * s, disp_um, gauge_length_px * s)
        E_lsq_sigma = np.full((len(G_lsq), 3), np.nan)
    else:
        sig = np.asarray(sigma_px, float)
        if sig.shape != shape:
            raise SemlabError(f"sigma_px must have shape {shape} (frames, tracks), "
                              f"got {sig.shape}")
        G_lsq, G_cov = gradient_local_lsq(p_ref * s, disp_um, gauge_length_px * s,
                                          disp_sigma=sig[ref_frame][ok] * s)
        E_lsq_sigma = strain_sigma(G_lsq, G_cov)
    G_tri, tri = gradient_from_triangles(p_ref * s, disp_um)
    if sigma_px is None:
        E_tri_sigma = np.full((len(G_tri), 3), np.nan)
    else:
        E_tri_sigma = strain_sigma(G_tri, triangle_gradient_cov(p_ref * s, tri,
                                                                sig[ref_frame][ok] * s))
    out.update(pts_px=p_end, E_lsq=green_lagrange(G_lsq), E_lsq_sigma=E_lsq_sigma, tri=tri,
               E_tri=green_lagrange(G_tri), E_tri_sigma=E_tri_sigma)
    return out


def _dense_strain(frames, ref_frame, s, start_at, heights, progress, grid_step_px, window,
                  min_zncc, smooth_sigma_px, half_windows, fill, method, flow_params):
    """The dense part of :func:`strain_from_tracks` (its docstring; the arguments its
    ``dense_*`` ones), from ``start_at``: last-frame points -> their start displacement."""
    out = {}
    h, w = frames[-1].shape
    half = int(half_windows[0])
    gx = np.arange(half + 2, w - half - 2, grid_step_px, dtype=float)
    gy = np.arange(half + 2, h - half - 2, grid_step_px, dtype=float)
    GX, GY = np.meshgrid(gx, gy)
    grid = np.column_stack([GX.ravel(), GY.ravel()])
    if method == "variational":
        pts, conv, finfo = _dense_flow(frames[-1], frames[ref_frame], start_at, grid,
                                       flow_params, progress)
        zncc, used = np.full(len(grid), np.nan), np.zeros(len(grid), int)
        out["dense_prior_scale_px"] = finfo["prior_scale_px"]
        out["dense_flow_tiles"] = finfo["tiles"]
        out["dense_flow_params"] = finfo["params"]
    else:
        # in tiles on the cluster for large frames (the untiled result, see semlab.parallel)
        pts, conv, zncc, used = _dense_match(frames[-1], frames[ref_frame], grid,
                                             start_at(grid), half_windows,
                                             smooth_sigma_px, progress)
    out["dense_method"] = method
    u = (grid - pts) * s  # U(x) = x_end - X_ref, µm
    u[~conv] = np.nan
    ux = u[:, 0].reshape(GX.shape)
    uy = u[:, 1].reshape(GX.shape)
    zncc = zncc.reshape(GX.shape)
    Fd, E, filled = dense_field_strain(ux, uy, grid_step_px * s, window, zncc, min_zncc,
                                       fill=fill)
    if method == "variational":
        out["E_sigma"] = _dense_sigma(finfo["samples_px"], finfo["bias_px"], ux, uy, E,
                                      grid_step_px, s, window)
    out["dense_gauge_um"] = window * grid_step_px * s
    eye = np.eye(2)
    e1, e2, ang = principal_strains(E)
    out.update(grid_x_px=gx, grid_y_px=gy, ux_um=ux, uy_um=uy, E=E, e1=e1, e2=e2, angle_deg=ang,
               max_shear=max_shear(E), zncc=zncc, dense_filled=filled,
               dense_half_px=used.reshape(GX.shape))
    if heights is not None:
        z = heights(GX, GY)
        dzdy, dzdx = np.gradient(z, grid_step_px * s)
        out["E_surface"] = surface_green_lagrange(Fd - eye, np.stack([dzdx, dzdy], axis=-1))
    return out
