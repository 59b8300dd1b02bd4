"""Integer-pixel ZNCC search of square subsets with a sub-pixel quadratic peak."""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import fft as sfft

from ._validate import _as_image, _as_points, _check_int

__all__ = ["zncc_match"]

_ZNCC_CHUNK = 2048  # subsets per chunk of the ZNCC search


def zncc_match(ref_img, cur_img, pts_ref, pts_guess, half_window=10, search_px=5):
    """Integer-pixel ZNCC search plus a sub-pixel quadratic peak, for N subsets at once.

    The ``(2h+1)²`` subset of ``ref_img`` centred on the pixel nearest to each
    ``pts_ref`` is compared with every window of ``cur_img`` whose centre is within
    ``±search_px`` (integer pixels, in x and y) of the pixel nearest to ``pts_guess``.
    The correlation surface is computed with batched FFTs and box sums; its peak is refined
    by the least-squares 2D quadratic through the 3×3 neighbourhood (falling back to two
    1D parabolas where that quadratic has no maximum).

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        Reference and current grey images (any real dtype; may have different sizes).
    pts_ref : (N, 2) array
        Reference points ``(x, y)`` in pixels in ``ref_img``.
    pts_guess : (N, 2) array
        Initial guesses ``(x, y)`` in pixels of the same points in ``cur_img``.
    half_window : int
        Subset half size ``h`` (subset is ``(2h+1)²`` pixels), >= 2.
    search_px : int
        Search radius in pixels, >= 1.

    Returns
    -------
    pts : (N, 2) array
        Matched ``(x, y)`` pixels in ``cur_img`` (the sub-pixel offset of ``pts_ref`` from
        its nearest pixel is carried over as a pure translation). NaN where the subset or
        every candidate window leaves an image, where a point is NaN, where the subset has
        no texture, or where the peak lies on the edge of the search range (the true match
        may be further away: increase ``search_px``).
    zncc : (N,) array
        Peak ZNCC in [-1, 1]; -1 where undefined (window outside an image, NaN point,
        flat subset).

    Raises
    ------
    ImageError
        If an image is not 2D, too small or not finite.
    SemlabError
        If the point arrays have the wrong shape or the window sizes are invalid.
    """
    ref = _as_image(ref_img, "ref_img")
    cur = _as_image(cur_img, "cur_img")
    h = _check_int(half_window, "half_window", 2)
    s = _check_int(search_px, "search_px", 1)
    pr = _as_points(pts_ref, "pts_ref")
    pg = _as_points(pts_guess, "pts_guess", len(pr))
    n = len(pr)
    out_pts = np.full((n, 2), np.nan)
    out_z = np.full(n, -1.0)
    if n == 0:
        return out_pts, out_z

    H0, W0 = ref.shape
    H1, W1 = cur.shape
    finite = np.all(np.isfinite(pr), 1) & np.all(np.isfinite(pg), 1)
    R = np.zeros((n, 2), np.intp)
    G = np.zeros((n, 2), np.intp)
    R[finite] = np.rint(pr[finite]).astype(np.intp)
    G[finite] = np.rint(pg[finite]).astype(np.intp)
    ok = (finite & (R[:, 0] >= h) & (R[:, 0] <= W0 - 1 - h) & (R[:, 1] >= h)
          & (R[:, 1] <= H0 - 1 - h)
          & (G[:, 0] >= 0) & (G[:, 0] <= W1 - 1) & (G[:, 1] >= 0) & (G[:, 1] <= H1 - 1))

    k = 2 * h + 1
    S = k + 2 * s  # search region side
    m = h + s
    # Pad the current image so every region can be cut; a mask tells valid windows.
    curp = np.pad(cur - cur.mean(), m, mode="constant")
    maskp = np.pad(np.ones_like(cur), m, mode="constant")
    reg_view = sliding_window_view(curp, (S, S))
    msk_view = sliding_window_view(maskp, (S, S))
    tpl_view = sliding_window_view(ref, (k, k))

    idx = np.flatnonzero(ok)
    for c0 in range(0, len(idx), _ZNCC_CHUNK):
        ii = idx[c0:c0 + _ZNCC_CHUNK]
        # Region top-left in padded coordinates: (G - m) + m = G.
        reg = reg_view[G[ii, 1], G[ii, 0]]                      # (n, S, S)
        msk = msk_view[G[ii, 1], G[ii, 0]]
        tpl = tpl_view[R[ii, 1] - h, R[ii, 0] - h]              # (n, k, k)
        z, peak = _zncc_surface(tpl, reg, msk, k, s)
        out_z[ii] = np.where(np.isfinite(peak[:, 0]), z, -1.0)
        good = np.all(np.isfinite(peak), 1)
        frac = pr[ii] - R[ii]
        out_pts[ii] = np.where(good[:, None], G[ii] + peak + frac, np.nan)
    return out_pts, out_z


def _box_sum(a, k):
    """Sums of all k×k windows of a batch of images a (n, S, S) -> (n, S-k+1, S-k+1)."""
    c = np.cumsum(np.cumsum(a, axis=1), axis=2)
    c = np.pad(c, ((0, 0), (1, 0), (1, 0)))
    return c[:, k:, k:] - c[:, :-k, k:] - c[:, k:, :-k] + c[:, :-k, :-k]


def _zncc_surface(tpl, reg, msk, k, s):
    """ZNCC of templates (n,k,k) over regions (n,S,S); returns peak value and sub-pixel
    offset (n, 2) = (dx, dy) of the peak relative to the region centre (NaN if invalid)."""
    n, S = reg.shape[0], reg.shape[1]
    P = k * k
    t = tpl - tpl.mean(axis=(1, 2), keepdims=True)
    tn = np.sqrt(np.einsum("nij,nij->n", t, t))
    # Correlation sum_xi t(xi) reg(xi + d) for all offsets via FFT (t is zero-mean, so the
    # window mean drops out of the numerator).
    shape = (S, S)
    Ft = sfft.rfft2(t, s=shape, axes=(1, 2))
    Fr = sfft.rfft2(reg, s=shape, axes=(1, 2))
    cc = sfft.irfft2(Fr * np.conj(Ft), s=shape, axes=(1, 2))[:, :2 * s + 1, :2 * s + 1]
    bs = _box_sum(reg, k)
    bs2 = _box_sum(reg * reg, k)
    cnt = _box_sum(msk, k)
    var = bs2 - bs * bs / P
    tiny = 1e-12 * (np.abs(bs2).max(axis=(1, 2), keepdims=True) + 1e-300)
    valid = (cnt > P - 0.5) & (var > tiny)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = cc / (tn[:, None, None] * np.sqrt(np.where(valid, var, 1.0)))
    z = np.where(valid & (tn[:, None, None] > 0), z, -np.inf)
    flat = z.reshape(n, -1)
    am = np.argmax(flat, axis=1)
    zmax = flat[np.arange(n), am]
    iy, ix = np.divmod(am, 2 * s + 1)
    peak = np.full((n, 2), np.nan)
    has = np.isfinite(zmax)
    inner = has & (ix > 0) & (ix < 2 * s) & (iy > 0) & (iy < 2 * s)
    if np.any(inner):
        j = np.flatnonzero(inner)
        nb = np.stack([z[j, iy[j] + dy, ix[j] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)],
                      axis=1).reshape(-1, 3, 3)
        nbok = np.all(np.isfinite(nb), axis=(1, 2))
        nb = np.where(nbok[:, None, None], nb, 0.0)
        d = _quadratic_peak(nb)
        d[~nbok] = np.nan
        peak[j, 0] = ix[j] - s + d[:, 0]
        peak[j, 1] = iy[j] - s + d[:, 1]
    zmax = np.where(has, np.clip(zmax, -1.0, 1.0), -1.0)
    return zmax, peak


def _quadratic_peak(c):
    """Sub-pixel maximum (dx, dy) of 3×3 samples c (n, 3, 3) by least-squares 2D quadratic.

    Falls back to independent 1D parabolas where the fitted quadratic is not concave or its
    maximum is more than one pixel away; offsets are clipped to ±0.5 px then.
    """
    gx = (c[:, :, 2] - c[:, :, 0]).sum(1) / 6.0
    gy = (c[:, 2, :] - c[:, 0, :]).sum(1) / 6.0
    gxx = (c[:, :, 0] - 2 * c[:, :, 1] + c[:, :, 2]).sum(1) / 3.0
    gyy = (c[:, 0, :] - 2 * c[:, 1, :] + c[:, 2, :]).sum(1) / 3.0
    gxy = (c[:, 2, 2] - c[:, 2, 0] - c[:, 0, 2] + c[:, 0, 0]) / 4.0
    det = gxx * gyy - gxy * gxy
    with np.errstate(invalid="ignore", divide="ignore"):
        dx = (-gyy * gx + gxy * gy) / det
        dy = (gxy * gx - gxx * gy) / det
        ok = (gxx < 0) & (det > 0) & (np.abs(dx) <= 1) & (np.abs(dy) <= 1)
        # 1D parabolas through the central row / column
        px = c[:, 1, 0] - 2 * c[:, 1, 1] + c[:, 1, 2]
        py = c[:, 0, 1] - 2 * c[:, 1, 1] + c[:, 2, 1]
        fx = np.where(px < 0, 0.5 * (c[:, 1, 0] - c[:, 1, 2]) / px, 0.0)
        fy = np.where(py < 0, 0.5 * (c[:, 0, 1] - c[:, 2, 1]) / py, 0.0)
    fx = np.clip(np.nan_to_num(fx), -0.5, 0.5)
    fy = np.clip(np.nan_to_num(fy), -0.5, 0.5)
    return np.stack([np.where(ok, dx, fx), np.where(ok, dy, fy)], axis=1)
