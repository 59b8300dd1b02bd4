"""The prior of automatic matching: global affine, dense flow, texture and noise.

Stage 1 of :func:`semlab.matching.auto_match` (with the features of
:func:`semlab.registration.match_features`): a RANSAC affine, and the DIS optical flow (or a
dense prior interpolated from the features on tall objects) that gives every grid point its
starting position and local warp gradient.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .errors import GeometryError
from .stats import robust_sd


def fit_affine(src, dst):
    """Least-squares 2D affine map ``dst ≈ src @ M[:, :2].T + M[:, 2]``.

    Parameters
    ----------
    src, dst : (N, 2) arrays of (x, y) pixels, N >= 3 not collinear.

    Returns
    -------
    M : (2, 3) array.

    Raises
    ------
    GeometryError
        With fewer than 3 points or collinear points.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if len(src) < 3:
        raise GeometryError(f"an affine map needs 3 or more points, got {len(src)}")
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2:
        raise GeometryError(f"src and dst must be (N, 2) arrays of the same shape, got "
                            f"{src.shape} and {dst.shape}")
    c = src - src.mean(0)
    if np.linalg.matrix_rank(c, tol=1e-9 * max(1.0, np.abs(c).max())) < 2:
        raise GeometryError("the points are collinear; an affine map is undetermined")
    X = np.column_stack([src, np.ones(len(src))])
    sol, *_ = np.linalg.lstsq(X, dst, rcond=None)
    return sol.T


def _apply_affine(M, p):
    return p @ M[:, :2].T + M[:, 2]


def _to_uint8(img):
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((img - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)


def _robust_affine(src, dst, thresh_px, seed):
    """Global affine by RANSAC (cv2.estimateAffine2D) then least squares on inliers."""
    import cv2

    cv2.setRNGSeed(int(seed))
    M, inl = cv2.estimateAffine2D(src.astype(np.float32), dst.astype(np.float32),
                                  method=cv2.RANSAC, ransacReprojThreshold=thresh_px,
                                  maxIters=5000, confidence=0.999)
    if M is None or inl is None or inl.sum() < 6:
        raise GeometryError("no consistent global affine map between the views was found "
                            "(too few SIFT matches); check that the views show the same area")
    inl = inl.ravel().astype(bool)
    M = fit_affine(src[inl], dst[inl])
    return M, inl


def _subset_std(img, half_window, pts):
    """Intensity standard deviation of the ``(2h+1)²`` subset at each (x, y) point."""
    import cv2

    k = 2 * int(half_window) + 1
    a = np.asarray(img, np.float64)
    mu = cv2.boxFilter(a, -1, (k, k), borderType=cv2.BORDER_REFLECT)
    m2 = cv2.boxFilter(a * a, -1, (k, k), borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(np.maximum(m2 - mu * mu, 0.0))
    ij = np.rint(pts).astype(int)
    return sd[ij[:, 1], ij[:, 0]]


def _norm8(img, sigma_px, eps):
    """Local contrast normalisation to 8 bits: ``(I - G*I) / (sqrt(G*(I - G*I)²) + eps)``
    with a Gaussian ``G`` of ``sigma_px``, mapped to 128 ± 32 per local standard deviation.
    Removes the smooth shading differences between SEM views before optical flow."""
    import cv2

    a = np.asarray(img, np.float32)
    mu = cv2.GaussianBlur(a, (0, 0), sigma_px)
    d = a - mu
    sd = np.sqrt(cv2.GaussianBlur(d * d, (0, 0), sigma_px))
    return np.clip(d / (sd + np.float32(eps)) * 32 + 128, 0, 255).astype(np.uint8)


def _sample(field, pts):
    """Bilinear samples of an (H, W) or (H, W, C) float field at (x, y) points:
    (n,) or (n, C) array (border values replicated)."""
    import cv2

    f = np.ascontiguousarray(field, dtype=np.float32)
    n = len(pts)
    cols = 1024                        # remap maps must stay below 32767 rows
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = pts[:, 0], pts[:, 1]
    out = cv2.remap(f, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(rows * cols, -1)[:n].astype(np.float64)
    return out[:, 0] if f.ndim == 2 else out


def _flow_field(ref_img, img, M, half_window, eps):
    """Dense optical flow from the reference view to ``img`` mapped into its frame.

    View ``img`` is mapped into the reference frame by the global affine ``M`` (ref → img),
    both views are contrast-normalised (:func:`_norm8`, regulariser ``eps`` grey levels)
    and the residual displacement ``f(x)`` (parallax and what the affine misses) is found by
    DIS optical flow (Kroeger et al. 2016, "Fast optical flow using dense inverse search",
    ECCV; coarse to fine, so it follows parallax of hundreds of pixels that varies over the
    image), forward and backward.

    Returns
    -------
    warped : (H, W) float32 array, ``img`` mapped into the reference frame by ``M``.
    fwd, bwd : (H, W, 2) float32 arrays, flow reference → warped and back, pixels.
    """
    import cv2

    hgt, wid = ref_img.shape
    if np.shape(M) == (2, 3):
        warped = cv2.warpAffine(np.asarray(img, np.float32), M.astype(np.float64), (wid, hgt),
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REFLECT)
    else:   # a dense prior map (H, W, 2): where each reference pixel lies in img
        warped = cv2.remap(np.asarray(img, np.float32), M[..., 0], M[..., 1],
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    sig = 2.0 * half_window
    a8 = _norm8(ref_img, sig, eps)
    b8 = _norm8(warped, sig, eps)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    fwd = dis.calc(a8, b8, None)
    bwd = dis.calc(b8, a8, None)
    return warped, fwd, bwd


def _highpass(img, half_window):
    """``img`` minus its Gaussian blur of σ = ``2 half_window`` (float32): the texture
    without the smooth shading."""
    import cv2

    a = np.asarray(img, np.float32)
    return a - cv2.GaussianBlur(a, (0, 0), 2.0 * half_window)


def _aligned_noise(ref_img, warped, fwd, half_window, pts=None, tile_px=64):
    """Image noise σ (grey levels) from the difference of two aligned views.

    ``warped`` is resampled along the flow onto the reference; both are high-passed
    (minus a Gaussian of ``2 half_window``, which removes shading differences) and the
    second is scaled to the first by least squares. The views share the texture but not the
    noise, so ``1.4826 MAD(difference) / √2`` estimates the noise of one view whatever its
    spectrum (e.g. correlated noise of a resampled image, where single-image estimators
    see almost none); mis-registered edges are outliers of the MAD.

    With ``pts`` ((n, 2) array of (x, y) pixels) the estimate is local: the MAD of the
    ``tile_px`` × ``tile_px`` tile holding each point, an (n,) array. SEM noise depends on
    the signal (a dark background is less noisy in grey levels), and relief the flow does
    not follow inflates a whole-view estimate: on pollen_pot1 the whole-view MAD is 4.1 grey
    levels, 2.4 on the grooved substrate alone, 5.3 on the grain.
    """
    import cv2

    hgt, wid = ref_img.shape
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(np.float32)
    al = cv2.remap(warped, xx + fwd[..., 0], yy + fwd[..., 1], cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_REFLECT)
    ha, hb = _highpass(ref_img, half_window), _highpass(al, half_window)
    m = 2 * half_window
    g = float((ha[m:-m, m:-m] * hb[m:-m, m:-m]).sum()
              / max(float((hb[m:-m, m:-m] ** 2).sum()), 1e-30))
    d = ha - g * hb

    def mad(x):
        x = x.ravel()
        return robust_sd(x) / np.sqrt(2.0)

    whole = mad(d[m:-m, m:-m])
    if pts is None:
        return whole
    ni, nj = hgt // tile_px, wid // tile_px
    out = np.full(len(pts), whole)
    if ni < 1 or nj < 1:
        return out
    ti = np.clip(np.asarray(pts, float)[:, 1] // tile_px, 0, ni - 1).astype(int)
    tj = np.clip(np.asarray(pts, float)[:, 0] // tile_px, 0, nj - 1).astype(int)
    for i, j in set(zip(ti.tolist(), tj.tolist())):   # the last tiles take the remainder
        r1 = hgt if i == ni - 1 else (i + 1) * tile_px
        c1 = wid if j == nj - 1 else (j + 1) * tile_px
        out[(ti == i) & (tj == j)] = mad(d[i * tile_px:r1, j * tile_px:c1])
    return out


def _field_jacobian(field, pts):
    """Jacobian (n, 2, 2) ``[[∂u/∂x, ∂u/∂y], [∂v/∂x, ∂v/∂y]]`` of an (H, W, 2) float32
    field ``(u, v)`` at (x, y) points (central differences, bilinear sampling)."""
    import cv2

    dx = _sample(cv2.Sobel(field, cv2.CV_32F, 1, 0, ksize=1, scale=0.5), pts)   # (n, 2)
    dy = _sample(cv2.Sobel(field, cv2.CV_32F, 0, 1, ksize=1, scale=0.5), pts)
    return np.stack([dx, dy], axis=2)


def _flow_guess(M, fwd, bwd, grid, half_window):
    """Initial guesses of grid points from the flow of :func:`_flow_field`.

    The guess of grid point ``x`` is ``M(x + f(x))`` and its initial warp gradient
    ``A (I + ∇f) − I`` (``A`` the linear part of ``M``, ``∇f`` of the flow smoothed over a
    subset).

    Returns
    -------
    guess : (n, 2) array of (x, y) pixels in the view.
    init_warp : (n, 6) array ``(0, du/dx, du/dy, 0, dv/dx, dv/dy)``.
    fb_err : (n,) array
        Forward–backward inconsistency ``|f(x) + b(x + f(x))|`` of the flow (pixels): large
        where the flow is unreliable (occlusions, no texture).
    """
    import cv2

    f = _sample(fwd, grid)
    fb_err = np.hypot(*(f + _sample(bwd, grid + f)).T)
    if np.shape(M) == (2, 3):
        guess = _apply_affine(M, grid + f)
        A = np.broadcast_to(M[:, :2], (len(grid), 2, 2))
    else:   # dense prior map Φ: guess Φ(x + f), Jacobian ∇Φ there
        guess = _sample(M, grid + f)
        A = _field_jacobian(M, grid + f)
    # flow gradient over a subset (Gaussian-smoothed central differences)
    J = _field_jacobian(cv2.GaussianBlur(fwd, (0, 0), max(1.0, half_window / 2)), grid)
    G = np.einsum("nij,njk->nik", A, np.eye(2) + J) - np.eye(2)
    G = np.clip(G, -0.8, 0.8)
    z = np.zeros(len(grid))
    init = np.column_stack([z, G[:, 0, 0], G[:, 0, 1], z, G[:, 1, 0], G[:, 1, 1]])
    return guess, init, fb_err


def _dense_prior(src, dst, shape, half_window, k=9, thresh_px=3.0, step_px=8):
    """Dense map (H, W, 2) float32: where each reference pixel lies in the other view,
    interpolated from the sparse feature matches.

    For views that no global affine map describes (a tall object: parallax of hundreds of
    pixels varying over the image, so that only a small part of the matches fits one
    affine), the matches are filtered by local consistency (a match whose displacement
    differs by more than ``thresh_px`` from the median of its ``k − 1`` nearest neighbours
    is dropped, twice), linearly interpolated between them (nearest value outside their
    convex hull) on a grid of ``step_px`` and smoothed over a subset.
    """
    import cv2
    from scipy.interpolate import griddata

    s, d = np.asarray(src, float), np.asarray(dst, float) - np.asarray(src, float)
    for _ in range(2):
        if len(s) <= k:
            break
        _, nb = cKDTree(s).query(s, k=k)
        med = np.median(d[nb[:, 1:]], axis=1)
        good = np.hypot(*(d - med).T) < thresh_px
        s, d = s[good], d[good]
    if len(s) < 6:
        raise GeometryError("too few consistent feature matches for a dense parallax prior")
    hgt, wid = shape
    gx = np.arange(0, wid + step_px, step_px, dtype=float)
    gy = np.arange(0, hgt + step_px, step_px, dtype=float)
    GX, GY = np.meshgrid(gx, gy)
    q = np.column_stack([GX.ravel(), GY.ravel()])
    lin = np.column_stack([griddata(s, d[:, c], q, method="linear") for c in (0, 1)])
    near = np.column_stack([griddata(s, d[:, c], q, method="nearest") for c in (0, 1)])
    D = np.where(np.isfinite(lin), lin, near).reshape(len(gy), len(gx), 2).astype(np.float32)
    D = cv2.resize(D, (int(gx[-1]) + 1, int(gy[-1]) + 1), interpolation=cv2.INTER_LINEAR)
    D = cv2.GaussianBlur(D[:hgt, :wid], (0, 0), max(1.0, float(half_window)))
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(np.float32)
    return np.ascontiguousarray(np.stack([xx + D[..., 0], yy + D[..., 1]], -1))
