"""The steps of reverse-time tracking (:func:`semlab.tracking.track_reverse`): frame
normalisation, seeds, window sampling and ZNCC, the predicted σ of an LK step, the median
outlier test, pyramidal LK and the track-loss checks.

Conventions: images are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)`` in
pixels, x to the right, y down, origin at the centre of the top-left pixel (OpenCV).
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from .errors import TrackingError

__all__ = ["TrackingWarning", "normalize_frame", "match_sigma_px", "median_outliers",
           "shi_tomasi_seeds", "grid_seeds"]

#: A frame whose robust intensity range (0.5-99.5 percentile) is below this fraction of its
#: absolute level (or exactly zero) is treated as blank.
_BLANK_REL_RANGE = 1e-6


class TrackingWarning(UserWarning):
    """Tracks were lost or a frame could not be used; the message names the frame."""


# ----------------------------------------------------------------------------- images

def _as_2d(img, what):
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = a[..., :3].astype(np.float64).mean(axis=2)
    if a.ndim != 2:
        raise TrackingError(f"{what} must be a 2D image [row, col], got an array of shape {a.shape}")
    if a.shape[0] < 8 or a.shape[1] < 8:
        raise TrackingError(f"{what} is too small ({a.shape}); tracking needs images of at least 8x8 pixels")
    return a


def normalize_frame(img, low_pct=0.5, high_pct=99.5):
    """Robust contrast stretch of one frame to ``[0, 1]``.

    Intensities between the ``low_pct`` and ``high_pct`` percentiles are mapped linearly to
    ``[0, 1]`` and clipped, so that global brightness and contrast changes between frames
    do not matter for matching.

    Parameters
    ----------
    img : (H, W) array, any real dtype
    low_pct, high_pct : float
        Percentiles of the stretch.

    Returns
    -------
    out : (H, W) float32 array in ``[0, 1]``
    blank : bool
        True when the frame has no usable contrast (constant or NaN); ``out`` is then zeros.
    """
    a = np.asarray(img, dtype=np.float64)
    finite = np.isfinite(a)
    if not finite.any():
        return np.zeros(a.shape, np.float32), True
    lo, hi = np.percentile(a[finite], [low_pct, high_pct])
    scale = max(abs(lo), abs(hi), 1e-300)
    if not np.isfinite(hi - lo) or (hi - lo) <= _BLANK_REL_RANGE * scale:
        return np.zeros(a.shape, np.float32), True
    out = (np.where(finite, a, lo) - lo) / (hi - lo)
    return np.clip(out, 0.0, 1.0).astype(np.float32), False


def _to_u8(f01):
    return np.round(f01 * 255.0).astype(np.uint8)


# ----------------------------------------------------------------------------- seeds

def shi_tomasi_seeds(img, quality=0.35, min_distance=7, block_size=7, max_corners=2000,
                     mask=None, border_px=11, name="the image"):
    """Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) as track seeds.

    The defaults are the reference paper's settings. The image is contrast-stretched first
    (:func:`normalize_frame`), so its dtype and brightness do not matter.

    Parameters
    ----------
    img : (H, W) array
        Usually the last frame of the series (the tracking reference).
    quality : float
        Minimal accepted corner quality relative to the best corner, in ``(0, 1]``.
    min_distance : float
        Minimal distance between corners, pixels.
    block_size : int
        Size of the averaging block of the structure tensor, pixels.
    max_corners : int
        At most this many corners, strongest first.
    mask : (H, W) bool/uint8 array, optional
        Non-zero where corners may be found.
    border_px : float
        Drop corners closer than this to the image edge, pixels (default 11: the tracking
        window of :func:`track_reverse`, 21 px, must fit in the image to be verified).
    name : str
        How to call the image in error messages (e.g. ``"frame 11"``).

    Returns
    -------
    (N, 2) float array of (x, y) in pixels, N >= 1.

    Raises
    ------
    TrackingError
        Blank image or no corner found: an empty seed set is never returned silently.
    """
    a = _as_2d(img, name)
    f01, blank = normalize_frame(a)
    if blank:
        raise TrackingError(f"{name} is blank (no contrast): no Shi-Tomasi seeds can be found; "
                            "seed on the last, best-contrast frame of the series")
    if not 0 < quality <= 1:
        raise TrackingError(f"quality must be in (0, 1], got {quality!r}")
    m = None
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != a.shape:
            raise TrackingError(f"mask shape {m.shape} differs from {name} shape {a.shape}")
        m = (m != 0).astype(np.uint8)
    c = cv2.goodFeaturesToTrack(f01, maxCorners=int(max_corners), qualityLevel=float(quality),
                                minDistance=float(min_distance), mask=m, blockSize=int(block_size))
    pts = np.zeros((0, 2)) if c is None else c.reshape(-1, 2).astype(np.float64)
    b = float(border_px)
    h, w = a.shape
    keep = ((pts[:, 0] >= b) & (pts[:, 0] <= w - 1 - b) & (pts[:, 1] >= b) & (pts[:, 1] <= h - 1 - b))
    pts = pts[keep]
    if len(pts) == 0:
        raise TrackingError(f"no Shi-Tomasi corners found in {name} (featureless, or all within "
                            f"{b:g} px of the edge): lower quality (now {quality}) or min_distance, "
                            "or seed on a frame with more texture")
    return pts


# ----------------------------------------------------------------------------- helpers

def _patch_grid(half):
    r = np.arange(-half, half + 1, dtype=np.float32)
    gx, gy = np.meshgrid(r, r)
    return gx, gy


def _sample_patches(img01, pts, half, linear=None):
    """(N, 2h+1, 2h+1) bilinear samples of ``img01`` around ``pts`` (NaN outside); with
    ``linear`` (2, 2), on the grid mapped by it (a registered frame's rotation and scale)."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    gx, gy = _patch_grid(half)
    if linear is not None:
        L = np.asarray(linear, np.float32)
        gx, gy = L[0, 0] * gx + L[0, 1] * gy, L[1, 0] * gx + L[1, 1] * gy
    n = len(pts)
    w = 2 * half + 1
    out = np.empty((n, w, w), np.float32)
    chunk = max(1, 30000 // w)            # cv2.remap needs fewer than 32767 rows
    for i in range(0, n, chunk):
        p = pts[i:i + chunk]
        m = len(p)
        # map relative to the integer pixel so float32 keeps the sub-pixel part exactly
        ix = np.floor(np.nan_to_num(p, nan=-1e6))
        fx = (np.nan_to_num(p, nan=-1e6) - ix).astype(np.float32)
        mx = (ix[:, 0, None, None].astype(np.float32) + fx[:, 0, None, None] + gx[None]).reshape(m * w, w)
        my = (ix[:, 1, None, None].astype(np.float32) + fx[:, 1, None, None] + gy[None]).reshape(m * w, w)
        out[i:i + m] = cv2.remap(img01, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                 borderValue=float("nan")).reshape(m, w, w)
    return out


def _zncc(p, q):
    """ZNCC of matching patch stacks (N, w, w); NaN if a patch is flat or leaves the image."""
    p = p.reshape(len(p), -1).astype(np.float64)
    q = q.reshape(len(q), -1).astype(np.float64)
    p = p - p.mean(axis=1, keepdims=True)
    q = q - q.mean(axis=1, keepdims=True)
    den = np.sqrt((p * p).sum(axis=1) * (q * q).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = (p * q).sum(axis=1) / den
    z[~(den > 1e-12)] = np.nan
    return z


def _min_gradient_energy(ref01, seeds, half):
    """Smallest eigenvalue of the structure tensor of each unit-variance reference window.

    ``λ_min(Σ ∇P̂ ∇P̂ᵀ)`` over the window, with ``P̂`` the window scaled to zero mean and unit
    variance (the sum of squared subset intensity gradients of Pan et al., Meas. Sci. Technol.
    19 (2008) 105503, taken in its weakest direction).
    """
    P = _sample_patches(ref01, seeds, half + 1).astype(np.float64)
    gy, gx = np.gradient(P, axis=(1, 2))
    core = P[:, 1:-1, 1:-1].reshape(len(P), -1)
    sd = core.std(axis=1)
    sd[~(sd > 1e-12)] = np.nan
    gx = gx[:, 1:-1, 1:-1] / sd[:, None, None]
    gy = gy[:, 1:-1, 1:-1] / sd[:, None, None]
    a = (gx * gx).sum(axis=(1, 2))
    b = (gx * gy).sum(axis=(1, 2))
    c = (gy * gy).sum(axis=(1, 2))
    return 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)


def grid_seeds(shape, spacing_px=None, border_px=24, max_seeds=2000, avoid=None,
               min_distance=None):
    """A regular grid of track seeds over the last frame, for strain and low texture.

    Shi-Tomasi corners with a quality relative to the best corner (:func:`shi_tomasi_seeds`)
    put a handful of seeds on the few particles of a polished surface (28-52 on the
    384x512 series of ``benchmarks/tracking_series.py``): too few for a strain gauge, and
    none where the texture is weak but still trackable by a subset sized by its
    information (``track_reverse(target_sigma_px=...)``). A grid covers the frame evenly,
    as the grid of a DIC analysis does; which of its points can be followed is then the
    tracker's decision, step by step, from each step's predicted σ.

    Parameters
    ----------
    shape : (H, W)
        Frame size, pixels.
    spacing_px : float, optional
        Grid step, pixels (default: 16 px, or wider so that at most ``max_seeds`` points
        fit).
    border_px : float
        Distance of the outermost points from the frame edge, pixels (default 24: the
        41 px subsets of ``max_half_window=20`` fit).
    max_seeds : int
        Largest number of grid points when ``spacing_px`` is None.
    avoid : (M, 2) array, optional
        Existing seeds ``(x, y)``: grid points closer than ``min_distance`` to one are left
        out (no duplicate tracks).
    min_distance : float, optional
        Default ``spacing_px / 2``.

    Returns
    -------
    (N, 2) float array of (x, y) pixels (possibly empty when the frame is smaller than
    twice the border).

    Examples
    --------
    >>> grid_seeds((96, 128), spacing_px=16).shape
    (15, 2)
    """
    h, w = int(shape[0]), int(shape[1])
    b = float(border_px)
    def axes(step):
        return np.arange(b, w - 1 - b + 1e-9, step), np.arange(b, h - 1 - b + 1e-9, step)

    if spacing_px is None:
        spacing_px = 16.0
        while np.prod([len(a) for a in axes(spacing_px)]) > max(int(max_seeds), 1):
            spacing_px += 1.0
    step = float(spacing_px)
    if not step > 0:
        raise TrackingError(f"spacing_px must be > 0, got {spacing_px!r}")
    xs, ys = axes(step)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()]).astype(np.float64)
    if avoid is not None and len(pts) and len(avoid):
        from scipy.spatial import cKDTree

        d, _ = cKDTree(np.asarray(avoid, float)).query(pts)
        pts = pts[d >= (step / 2 if min_distance is None else float(min_distance))]
    return pts


def match_sigma_px(zncc, lambda_min):
    """Predicted 1-sigma error of a window match, pixels.

    A window match is a least-squares fit; its covariance is ``σ² (JᵀJ)⁻¹`` with ``J`` the
    window intensity gradients (Gauss-Newton covariance, Nocedal & Wright 2nd ed. sec. 10.3).
    For unit-variance windows with correlation ``ρ`` (ZNCC) the signal part of the current
    window has gain ``ρ`` and the noise variance ``1 - ρ²``, so in the weakest direction::

        σ² = (1 - ρ²) / (ρ² λ_min)

    Parameters
    ----------
    zncc : array
        ZNCC of the match.
    lambda_min : array
        From the structure tensor of the unit-variance reference window.

    Returns
    -------
    array of σ in pixels (inf where ``zncc <= 0`` or the window is flat).
    """
    z = np.asarray(zncc, float)
    lam = np.asarray(lambda_min, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = (1.0 - np.clip(z, -1, 1) ** 2) / (np.clip(z, 0, 1) ** 2 * lam)
    s2 = np.where(np.isfinite(s2) & (z > 0) & (lam > 0), s2, np.inf)
    return np.sqrt(np.maximum(s2, 0.0))


def median_outliers(pts_ref, disp, candidates, threshold=2.0, n_neighbours=8, eps_px=0.1,
                    neighbours=None):
    """Normalised median test of a scattered displacement field.

    Westerweel & Scarano, "Universal outlier detection for PIV data", Exp. Fluids 39 (2005)
    1096-1100: with ``u_m`` the median displacement of the ``n_neighbours`` nearest
    neighbours and ``r_m`` the median of their own deviations from ``u_m``, a point is an
    outlier when ``|u - u_m| / (r_m + eps_px) > threshold``.

    Parameters
    ----------
    pts_ref : (N, 2) array of (x, y) pixels (neighbourhoods are taken here)
    disp : (N, 2) array of displacements, pixels
    candidates : (N,) bool
        Points to test.
    neighbours : (N,) bool, optional
        Points that may serve as neighbours (default: every point with a finite
        displacement).

    Returns
    -------
    (N,) bool, True for candidates that fail the test. With fewer than
    ``n_neighbours + 1`` usable neighbours no point is flagged.
    """
    from scipy.spatial import cKDTree

    out = np.zeros(len(pts_ref), bool)
    fin = np.isfinite(disp).all(axis=1)
    nbr = fin if neighbours is None else (np.asarray(neighbours, bool) & fin)
    idx = np.flatnonzero(np.asarray(candidates, bool) & fin)
    jdx = np.flatnonzero(nbr)
    if len(jdx) < n_neighbours + 1 or len(idx) == 0:
        return out
    tree = cKDTree(pts_ref[jdx])
    dist, nb = tree.query(pts_ref[idx], k=n_neighbours + 1)
    # drop the point itself where it is among its neighbours, else the farthest one
    self_hit = jdx[nb[:, 0]] == idx
    nb = np.where(self_hit[:, None], nb[:, 1:], nb[:, :-1])
    d = disp[idx]
    dn = disp[jdx][nb]                                 # (M, k, 2)
    um = np.median(dn, axis=1)                         # (M, 2)
    rm = np.median(np.linalg.norm(dn - um[:, None, :], axis=2), axis=1)
    r = np.linalg.norm(d - um, axis=1) / (rm + eps_px)
    out[idx] = r > threshold
    return out


def _seed_kinds(seed_kind, n):
    """(n,) object array of seed labels: ``"seed"`` (None), one label for all (a str), or the
    given per-seed labels as they are (the caller checks their number)."""
    if seed_kind is None:
        return np.array(["seed"] * n, dtype=object)
    if isinstance(seed_kind, str):
        return np.array([seed_kind] * n, dtype=object)
    return np.asarray(list(seed_kind), dtype=object)


def _inside(pts, shape):
    h, w = shape
    return (np.isfinite(pts).all(axis=1) & (pts[:, 0] >= 0) & (pts[:, 0] <= w - 1)
            & (pts[:, 1] >= 0) & (pts[:, 1] <= h - 1))


def _lk(prev_u8, next_u8, p0, guess, lk_kw):
    """LK from prev to next; returns (pts (N,2) with NaN where failed, ok (N,) bool)."""
    n = len(p0)
    out = np.full((n, 2), np.nan)
    ok = np.zeros(n, bool)
    good = np.isfinite(p0).all(axis=1)
    if guess is not None:
        good &= np.isfinite(guess).all(axis=1)
    if not good.any():
        return out, ok
    a = p0[good].astype(np.float32).reshape(-1, 1, 2)
    if guess is not None:
        g = guess[good].astype(np.float32).reshape(-1, 1, 2).copy()
        p1, st, _ = cv2.calcOpticalFlowPyrLK(prev_u8, next_u8, a, g,
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk_kw)
    else:
        p1, st, _ = cv2.calcOpticalFlowPyrLK(prev_u8, next_u8, a, None, **lk_kw)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    st = st.reshape(-1).astype(bool) & np.isfinite(p1).all(axis=1)
    idx = np.flatnonzero(good)
    out[idx[st]] = p1[st]
    ok[idx] = st
    ok &= _inside(np.where(np.isfinite(out), out, -1.0), next_u8.shape)
    out[~ok] = np.nan
    return out, ok


# ----------------------------------------------------------------------------- tracking

def _check_track_loss(valid, blank):
    """Warnings and error of a finished reverse tracking, ``valid`` (F, N) with the reference
    last: the blank frames (list of indices), every track lost at the first step (error), the
    frames without any valid track. Warnings point at the caller of the tracking function."""
    ref = len(valid) - 1
    if blank:
        warnings.warn(f"frame(s) {blank} are blank (no contrast): every track is invalid there "
                      "and resumes from its last valid frame", TrackingWarning, stacklevel=3)
    if ref > 0 and not valid[:ref].any():
        raise TrackingError(f"every track was lost at the first step (frame {ref - 1}) and none "
                            "recovered in any earlier frame: check the frame order (frame 0 = "
                            "earliest), the seeds (pixels of the last frame) or loosen "
                            "fb_threshold_px/min_zncc")
    empty = [k for k in range(ref) if not valid[k].any() and k not in blank]
    if empty:
        alive = np.flatnonzero(valid.any(axis=1))
        msg = f"no valid track in frame(s) {empty}: their displacements are undefined"
        if alive.min() > 0:
            msg += (f"; the last track was lost at frame {alive.min() - 1} (valid for the last "
                    f"time in frame {alive.min()})")
        warnings.warn(msg, TrackingWarning, stacklevel=3)
