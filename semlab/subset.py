"""Local sub-pixel image matching of square subsets (digital image correlation engine).

Shared by stereo matching (:mod:`semlab.matching`) and tracking. Everything is vectorised
over all subsets at once: arrays of shape ``(N, n_pix)`` with ``n_pix = (2 h + 1)²``; the
only Python loops are over chunks of a few hundred subsets (to bound memory, keep the
working arrays in cache and use two threads) and over IC-GN iterations.

Two steps:

1. :func:`zncc_match` — integer-pixel search of the zero-normalised cross-correlation
   (ZNCC) peak, computed for all subsets at once with batched FFTs and box sums, then a
   sub-pixel peak from a 2D quadratic fit of the 3×3 neighbourhood of the peak.
2. :func:`icgn_refine` — inverse-compositional Gauss–Newton (IC-GN) refinement of an affine
   (or translation) subset warp, minimising the zero-normalised sum of squared differences
   (ZNSSD), which is invariant to an intensity offset and gain between the two images
   (Baker & Matthews 2004, "Lucas-Kanade 20 years on", IJCV 56(3), section 3.2;
   Pan, Li & Tong 2013, "Fast, robust and accurate digital image correlation calculation
   without redundant computations", Exp. Mech. 53, eqs. 1–12). The current image is
   interpolated with cubic B-splines (Unser 1999, "Splines: a perfect fit for signal and
   image processing", IEEE SPM 16(6)): prefiltered once with
   :func:`scipy.ndimage.spline_filter`, then sampled by explicit 4×4 tap gathers from a
   float32 copy of the coefficients (the values of ``map_coordinates(order=3,
   prefilter=False)`` to ~1e-7 of the contrast, 2–3× faster), or by a separable filter
   while a square subset is only translated.

Conventions: images are 2D arrays indexed ``[row, col]``; points are ``(N, 2)`` arrays of
``(x, y)`` in pixels, x to the right, y down, origin at the centre of the top-left pixel.
A warp is ``(u, du/dx, du/dy, v, dv/dx, dv/dy)``: a reference point ``X`` near ``pts_ref``
maps to ``pts_ref + (u, v) + G (X - pts_ref)`` in the current image, with
``G = [[du/dx, du/dy], [dv/dx, dv/dy]]``.

Reference subsets are centred on the integer pixel nearest to each ``pts_ref`` (no
interpolation of the reference image, exact gradients of its B-spline interpolant at the
pixel nodes), and the sub-pixel reference position is carried through the fitted affine
warp, which is exact under the affine subset model.

Failures are never silent: a subset that leaves an image, has too little texture or does
not converge gets ``NaN`` positions, ``converged = False`` and a ``reason``.
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ._validate import _as_image, _as_points, _check_int
from .bspline import (_bspline_sample, _pair_table, _smooth, _smoothing_variance_gain,
                      _spline_gradients, _translate_square, prefilter_image)
from .errors import SemlabError
from .noise import filter_noise_gain, image_noise_sigma
from .zncc import zncc_match

__all__ = ["SubsetResult", "zncc_match", "icgn_refine", "prefilter_image", "oriented_subset",
           "square_subset"]

_CHUNK_PIX = 2 ** 17  # IC-GN subset pixels per chunk (working arrays stay in cache)
_N_THREADS = max(1, min(2, os.cpu_count() or 1))

# Reason strings (empty string = success).
OK = ""
OUTSIDE = "subset leaves the image"
NO_TEXTURE = "too little texture (singular Hessian)"
NO_TEXTURE_CUR = "too little texture in the current image"
DIVERGED = "IC-GN diverged"
MAX_ITER = "IC-GN did not converge within max_iter"
NAN_INPUT = "NaN input point"


@dataclass(frozen=True)
class SubsetResult:
    """Result of :func:`icgn_refine` for ``N`` subsets.

    Attributes
    ----------
    pts : (N, 2) float array
        Matched positions ``(x, y)`` in the current image, pixels; NaN where not converged.
    warp : (N, 6) float array
        Affine warp ``(u, du/dx, du/dy, v, dv/dx, dv/dy)`` about ``pts_ref``
        (``(u, v) = pts - pts_ref``); NaN where not converged.
    zncc : (N,) float array
        Zero-normalised cross-correlation at convergence, in [-1, 1] (-1 where undefined).
    converged : (N,) bool array
        True where the IC-GN step fell below ``tol_px``.
    n_iter : (N,) int array
        IC-GN iterations used.
    sigma_px : (N, 2) float array
        Predicted 1σ random error of ``pts`` in x and y, pixels, from the Gauss–Newton
        covariance of the subset and the measured image noise (see :func:`icgn_refine`),
        propagated to the sub-pixel reference position. It does not include
        interpolation bias. NaN where not converged; inf where the reference subset's
        texture does not stand above its noise.
    reason : (N,) str array
        Empty where converged, otherwise why not.
    residual_ratio : (N,) float array
        Residual variance of the matched subset over the variance the measured image
        noise predicts (about 1 for a subset that fits its shape function; much more than
        1 where it does not, e.g. across a height step or an occlusion). NaN where not
        converged or where the noise is taken from the residual.
    noise_sigma : (2,) float array
        Noise standard deviation of the reference and current images used for
        ``sigma_px`` (grey units; NaN with ``noise_sigma="residual"``).
    noise_ratio : (N,) float array
        Residual variance of each converged subset over the one the images' own noise
        estimate (:func:`semlab.noise.image_noise_sigma`, or the given ``noise_sigma``)
        predicts with the smoothing, interpolation and fitted-parameter gains, before the
        calibration: its median, capped at 1, is the factor the default applies to the
        noise variances (:func:`_calibrate_noise`). NaN where not converged or with
        ``noise_sigma="residual"``.
    """

    pts: np.ndarray
    warp: np.ndarray
    zncc: np.ndarray
    converged: np.ndarray
    n_iter: np.ndarray
    sigma_px: np.ndarray
    reason: np.ndarray
    residual_ratio: np.ndarray = None
    noise_sigma: np.ndarray = None
    noise_ratio: np.ndarray = None

    def __len__(self):
        return len(self.pts)


@functools.lru_cache(maxsize=16)
def _gradient_noise_gain(smooth_sigma_px):
    """White-noise variance gain of the B-spline x gradient at the nodes (after smoothing);
    the y gradient has the same by symmetry."""
    def grad(a):
        coef = ndimage.spline_filter(_smooth(a, smooth_sigma_px), order=3, mode="mirror")
        return _spline_gradients(coef)[0]
    return filter_noise_gain(grad)


@functools.lru_cache(maxsize=16)
def _smoothed_gradient_noise_gain(smooth_sigma_px):
    """White-noise variance gain of the smoothed B-spline x gradient ``K ∇(K n)``: the
    noise part of ``Hk`` (:func:`_covariance`); equal to :func:`_gradient_noise_gain`
    without smoothing."""
    if not smooth_sigma_px:
        return _gradient_noise_gain(smooth_sigma_px)

    def grad(a):
        coef = ndimage.spline_filter(_smooth(a, smooth_sigma_px), order=3, mode="mirror")
        return _smooth(_spline_gradients(coef)[0], smooth_sigma_px)
    return filter_noise_gain(grad)


def _noise_variances(noise_sigma, ref, cur):
    """(s_ref², s_cur²) from the ``noise_sigma`` argument of :func:`icgn_refine`."""
    if noise_sigma is None or (isinstance(noise_sigma, str) and noise_sigma == "calibrated"):
        return (image_noise_sigma(ref) ** 2, image_noise_sigma(cur) ** 2)
    if isinstance(noise_sigma, str):
        if noise_sigma != "residual":
            raise SemlabError(f"noise_sigma must be None, a number, a pair or 'residual', "
                              f"got {noise_sigma!r}")
        return (np.nan, np.nan)
    v = np.broadcast_to(np.asarray(noise_sigma, dtype=np.float64), (2,))
    if not np.all(np.isfinite(v) & (v >= 0)):
        raise SemlabError(f"noise_sigma must be finite and >= 0, got {noise_sigma!r}")
    return (float(v[0]) ** 2, float(v[1]) ** 2)


# --------------------------------------------------------------------------- IC-GN
_SQUARE_PARTS = {None: lambda x, y: np.ones(x.shape, bool), "left": lambda x, y: x <= 0,
                 "right": lambda x, y: x >= 0, "top": lambda x, y: y <= 0,
                 "bottom": lambda x, y: y >= 0}


def square_subset(half_window, part=None):
    """Integer pixel offsets of the ``(2h+1)²`` square, or of one of its halves.

    Parameters
    ----------
    half_window : int
        Half size ``h``.
    part : {None, "left", "right", "top", "bottom"}
        The whole square, or its half ``dx <= 0``, ``dx >= 0``, ``dy <= 0`` or ``dy >= 0``
        (the centre on its edge, as in subset splitting at a discontinuity).

    Returns
    -------
    (P, 2) int array of ``(dx, dy)`` offsets, for ``icgn_refine(subset_offsets=...)``.
    """
    if part not in _SQUARE_PARTS:
        raise SemlabError(f"part must be one of {sorted(k for k in _SQUARE_PARTS if k)} or "
                          f"None, got {part!r}")
    h = _check_int(half_window, "half_window", 0)
    oy, ox = np.mgrid[-h:h + 1, -h:h + 1]
    keep = _SQUARE_PARTS[part](ox, oy)
    return np.column_stack([ox[keep], oy[keep]])


def oriented_subset(half_length, half_width, angle_deg):
    """Integer pixel offsets of a rectangle rotated by ``angle_deg``.

    Parameters
    ----------
    half_length, half_width : float
        Half sizes (pixels) along and across the direction ``angle_deg``.
    angle_deg : float
        Direction of the long side, degrees from the image x axis (toward +y, i.e.
        clockwise on screen since y points down).

    Returns
    -------
    (P, 2) int array of ``(dx, dy)`` offsets, for ``icgn_refine(subset_offsets=...)``.
    """
    if not (half_length > 0 and half_width > 0):
        raise SemlabError("half_length and half_width must be > 0")
    a = np.deg2rad(angle_deg)
    r = int(np.ceil(np.hypot(half_length, half_width)))
    oy, ox = np.mgrid[-r:r + 1, -r:r + 1]
    along = ox * np.cos(a) + oy * np.sin(a)
    across = -ox * np.sin(a) + oy * np.cos(a)
    keep = (np.abs(along) <= half_length + 1e-9) & (np.abs(across) <= half_width + 1e-9)
    return np.column_stack([ox[keep], oy[keep]])


def icgn_refine(ref_img, cur_img, pts_ref, pts_guess, half_window=10, warp="affine",
                max_iter=30, tol_px=1e-4, init_warp=None, *, smooth_sigma_px=0.0,
                subset_offsets=None, ref_prefiltered=None, cur_prefiltered=None,
                noise_sigma=None, progress=False, coef_offset=None):
    """Sub-pixel subset matching by inverse-compositional Gauss–Newton with ZNSSD.

    For each point, the ``(2h+1)²`` subset of ``ref_img`` centred on the pixel nearest to
    ``pts_ref`` is matched in ``cur_img`` by minimising the zero-normalised SSD

    ``C(p) = Σ [ (f - f̄)/Δf - (g(W(ξ; p)) - ḡ)/Δg ]²``

    over an affine (6 parameters) or translation (2 parameters) warp ``W``, which is
    insensitive to an offset and a gain of intensity between the images. The IC-GN update
    ``W(p) ← W(p) ∘ W(Δp)⁻¹`` with ``Δp = -H⁻¹ Σ Jᵀ [(f - f̄) - Δf/Δg (g - ḡ)]`` uses the
    steepest-descent images ``J = ∇f ∂W/∂p`` and Hessian ``H = Σ JᵀJ`` of the reference
    subset, computed once (Baker & Matthews 2004, section 3.2; Pan et al. 2013, eqs. 5–10).
    ``cur_img`` is interpolated with cubic B-splines. At convergence ``ZNCC = 1 - C/2``.

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        Reference and current grey images.
    pts_ref : (N, 2) array
        Reference points ``(x, y)`` in pixels in ``ref_img`` (sub-pixel allowed).
    pts_guess : (N, 2) array
        Initial guesses of the matched positions ``(x, y)`` in ``cur_img``, pixels (within
        a few tenths of a pixel is best; e.g. from :func:`zncc_match`).
    half_window : int
        Subset half size ``h``; subsets are ``(2h+1)²`` pixels.
    warp : {"affine", "translation"}
        Subset shape function. With ``"translation"`` only ``u, v`` are estimated and the
        gradient terms of ``init_warp`` (default zero) are held fixed.
    max_iter : int
        Maximum IC-GN iterations.
    tol_px : float
        Convergence when the root-mean-square over the subset pixels of the change of
        their warped positions in one update is below ``tol_px`` (pixels).
    init_warp : (N, 6) or (6,) array, optional
        Initial warps ``(u, du/dx, du/dy, v, dv/dx, dv/dy)``; only the gradient terms are
        used (the translation comes from ``pts_guess``).
    smooth_sigma_px : float
        Standard deviation (pixels) of a Gaussian low-pass applied to both images first
        (0 = none). About 0.8 px removes most of the noise-induced bias of the
        interpolation (a pull of the estimate toward half-pixel shifts that grows with the
        noise variance) at the cost of ~10 % more random error (Pan 2013, "Bias error
        reduction of digital image correlation using Gaussian pre-filtering", Opt. Lasers
        Eng. 51(10)). Exact translations are unaffected (smoothing commutes with shifts).
    subset_offsets : (P, 2) int array, optional
        Custom subset shape: integer pixel offsets ``(dx, dy)`` from the subset centre
        (e.g. a thin rectangle along a slip band, see :func:`oriented_subset`), at least 6
        pixels. Default: the ``(2h+1)²`` square. ``half_window`` is then only used as the
        divergence limit.
    ref_prefiltered, cur_prefiltered : (H, W) arrays, optional
        B-spline coefficients from :func:`prefilter_image` (with the same
        ``smooth_sigma_px``), to save the prefilter when the same image is matched many
        times.
    noise_sigma : None, float, (σ_ref, σ_cur) or "residual"
        Standard deviation of the white noise of the (unsmoothed) images, in their grey
        units, for ``sigma_px``. None (default) measures it from the images and the
        matched subsets: each image's Immerkær estimate
        (:func:`semlab.noise.image_noise_sigma`, an upper bound where the texture is sharp
        at the pixel scale, which the mask counts as noise) is lowered to what the median
        residual variance of the converged subsets allows, that residual being divided by
        the noise gains of the pre-smoothing and of the B-spline interpolation of the
        current image (:func:`_calibrate_noise`; kept when fewer than 10 subsets converge).
        On DIC Challenge sample 5 the predicted σ is then close to the actual error (see
        ``tests/test_subset.py::test_dic_challenge_sample5``); on smooth textures the
        Immerkær value is kept. ``"calibrated"`` is the same as None. Give the values to
        impose them (no calibration). ``"residual"`` takes each subset's own residual
        variance instead (no measurement; it also counts model misfit).
    progress : bool
        Show a tqdm bar over chunks of subsets.
    coef_offset : float, optional
        Constant removed from the current image's B-spline coefficients before they are
        rounded to float32 (default: their mean; the zero-normalised criterion ignores it).
        A tile of a large image (:mod:`semlab.parallel`) passes the whole image's value so
        that the float32 rounding, hence the result, is the untiled one to ~1e-12 px
        (with its own mean: ~4e-8 px).

    Returns
    -------
    SubsetResult
        Subsets that leave either image (at any iteration), whose reference subset has a
        singular Hessian (too little texture), that diverge (move more than ``h`` pixels
        from the guess or gradient terms beyond ±0.5) or that do not reach ``tol_px``
        within ``max_iter`` have ``converged = False``, NaN ``pts``/``warp`` and a
        ``reason``. NaN input points are flagged the same way.

    Raises
    ------
    ImageError
        If an image is not 2D, too small or not finite.
    SemlabError
        On wrong shapes or invalid parameters.
    """
    ref = _as_image(ref_img, "ref_img")
    cur = _as_image(cur_img, "cur_img")
    h = _check_int(half_window, "half_window", 2)
    max_iter = _check_int(max_iter, "max_iter", 1)
    if warp not in ("affine", "translation"):
        raise SemlabError(f"warp must be 'affine' or 'translation', got {warp!r}")
    if not (np.isfinite(tol_px) and tol_px > 0):
        raise SemlabError(f"tol_px must be a positive number, got {tol_px!r}")
    pr = _as_points(pts_ref, "pts_ref")
    n = len(pr)
    pg = _as_points(pts_guess, "pts_guess", n)
    if subset_offsets is None:
        off = np.arange(-h, h + 1, dtype=np.float64)
        oy, ox = np.meshgrid(off, off, indexing="ij")
        xi = np.stack([ox.ravel(), oy.ravel()])
    else:
        so = np.asarray(subset_offsets, dtype=np.float64)
        if so.ndim != 2 or so.shape[1] != 2 or len(so) < 6 or not np.all(so == np.round(so)):
            raise SemlabError("subset_offsets must be a (P, 2) array of integer (dx, dy) "
                              f"offsets with P >= 6, got shape {so.shape}")
        xi = so.T.copy()
    ext = int(np.abs(xi).max())
    if init_warp is None:
        grad0 = np.zeros((n, 4))
    else:
        iw = np.asarray(init_warp, dtype=np.float64)
        if iw.shape == (6,):
            iw = np.broadcast_to(iw, (n, 6))
        if iw.shape != (n, 6):
            raise SemlabError(f"init_warp must have shape (N, 6) = ({n}, 6) or (6,), "
                              f"got {np.shape(init_warp)}")
        grad0 = iw[:, [1, 2, 4, 5]].copy()
        grad0[~np.all(np.isfinite(grad0), 1)] = 0.0

    noise_var = _noise_variances(noise_sigma, ref, cur)
    ref = _smooth(ref, smooth_sigma_px)
    if cur_prefiltered is None:
        cur = _smooth(cur, smooth_sigma_px)
        ccoef = ndimage.spline_filter(cur, order=3, mode="mirror", output=np.float64)
    else:
        ccoef = np.asarray(cur_prefiltered, dtype=np.float64)
        if ccoef.shape != cur.shape:
            raise SemlabError("cur_prefiltered must have the shape of cur_img")
    if ref_prefiltered is None:
        rcoef = ndimage.spline_filter(ref, order=3, mode="mirror", output=np.float64)
    else:
        rcoef = np.asarray(ref_prefiltered, dtype=np.float64)
        if rcoef.shape != ref.shape:
            raise SemlabError("ref_prefiltered must have the shape of ref_img")
    rgx, rgy = _spline_gradients(rcoef)
    kgx = kgy = None
    if smooth_sigma_px and np.isfinite(noise_var[0]):
        kgx, kgy = (_smooth(g, smooth_sigma_px).ravel() for g in (rgx, rgy))

    pts, wout, zncc, conv, nit, sig, rres, reason = _unsolved_outputs(n)

    finite = np.all(np.isfinite(pr), 1) & np.all(np.isfinite(pg), 1)
    X0 = np.zeros((n, 2), np.intp)
    X0[finite] = np.rint(pr[finite]).astype(np.intp)
    H0, W0 = ref.shape
    ex = int(np.abs(xi[0]).max())
    ey = int(np.abs(xi[1]).max())
    inside = (finite & (X0[:, 0] >= ex) & (X0[:, 0] <= W0 - 1 - ex) & (X0[:, 1] >= ey)
              & (X0[:, 1] <= H0 - 1 - ey))
    reason[finite & ~inside] = OUTSIDE
    idx = np.flatnonzero(inside)

    # Flat arrays for np.take gathers: reference values and gradients, and the current
    # image's coefficients padded by 2 (mirror), in float64 for the separable translation
    # path and as a float32 pair table for general warps (:func:`_bspline_sample`).
    offset = ccoef.mean() if coef_offset is None else float(coef_offset)
    cpad = np.pad(ccoef - offset, 2, mode="reflect")
    roff = (xi[1] * ref.shape[1] + xi[0]).astype(np.intp)
    ctx = dict(ref_flat=np.ascontiguousarray(ref).ravel(), rgx_flat=rgx.ravel(),
               rgy_flat=rgy.ravel(), ref_w=ref.shape[1], roff=roff,
               kgx_flat=kgx, kgy_flat=kgy,
               cur_shape=ccoef.shape, h=h, xi=xi, ext=ext,
               square=subset_offsets is None, cpad=cpad,
               table=_pair_table(cpad),
               affine=(warp == "affine"),
               max_iter=max_iter, tol=float(tol_px),
               noise_gain=_smoothing_variance_gain(smooth_sigma_px),
               noise_var=noise_var, grad_gain=_gradient_noise_gain(smooth_sigma_px),
               kgrad_gain=_smoothed_gradient_noise_gain(smooth_sigma_px))
    chunk = max(32, _CHUNK_PIX // xi.shape[1])                # subsets per chunk
    chunks = [idx[i:i + chunk] for i in range(0, len(idx), chunk)]

    def run(ii):
        return ii, _icgn_chunk(ctx, X0[ii], pr[ii], pg[ii], grad0[ii])

    cov_in = []
    qout = np.full(n, np.nan)
    if len(chunks) > 1 and _N_THREADS > 1:
        with ThreadPoolExecutor(_N_THREADS) as ex:
            results = ex.map(run, chunks)
            results = _maybe_tqdm(results, len(chunks), progress)
            for ii, r in results:
                cov_in.append(_store(ii, r, pts, wout, zncc, conv, nit, reason))
    else:
        for ii in _maybe_tqdm(chunks, len(chunks), progress):
            cov_in.append(_store(ii, run(ii)[1], pts, wout, zncc, conv, nit, reason))
    if cov_in:
        Hs, Hk, Hinv, rvar, rat, e = (np.concatenate(a) for a in zip(*cov_in))
        ii = idx if len(chunks) == 1 else np.concatenate([c for c in chunks])
        q = _noise_ratios(noise_var, _noise_residual_variance(ctx, Hk, Hinv, rvar), rat,
                          ctx["noise_gain"], _interp_noise_gain(smooth_sigma_px, pts[ii]))
        qout[ii] = q
        noise_var = _calibrate_noise(noise_var, q, noise_sigma)
        ctx["noise_var"] = noise_var
        xi_ = ctx["xi"]
        B = np.stack([np.ones(xi_.shape[1]), xi_[0], xi_[1]], 1) if ctx["affine"] else \
            np.ones((xi_.shape[1], 1))
        var, rr = _covariance(ctx, Hs, Hk, Hinv, B, rvar, rat, e)
        ok = conv[ii]
        sig[ii] = np.where(ok[:, None], np.sqrt(np.maximum(var, 0)), np.nan)
        rres[ii] = np.where(ok, rr, np.nan)

    reason = np.array([str(r) for r in reason], dtype=object).astype(str) if n else \
        np.zeros(0, dtype="<U1")
    return SubsetResult(pts=pts, warp=wout, zncc=zncc, converged=conv, n_iter=nit,
                        sigma_px=sig, reason=reason, residual_ratio=rres,
                        noise_sigma=np.sqrt(np.array(noise_var)), noise_ratio=qout)


def _maybe_tqdm(it, total, progress):
    if not progress:
        return it
    from tqdm.auto import tqdm
    return tqdm(it, total=total, desc="IC-GN subsets", unit="chunk")


def _unsolved_outputs(n):
    """Per-point outputs of :func:`icgn_refine` before any of ``n`` points is solved: pts (n, 2),
    warp (n, 6), zncc, converged, n_iter, sigma_px (n, 2), residual_ratio, reason."""
    return (np.full((n, 2), np.nan), np.full((n, 6), np.nan), np.full(n, -1.0),
            np.zeros(n, bool), np.zeros(n, int), np.full((n, 2), np.nan), np.full(n, np.nan),
            np.full(n, NAN_INPUT, dtype=object))


def _store(ii, r, pts, wout, zncc, conv, nit, reason):
    p, w, z, c, k, why, cov_in = r
    pts[ii], wout[ii], zncc[ii], conv[ii], nit[ii] = p, w, z, c, k
    reason[ii] = why
    return cov_in


def _rowdot(X, B):
    """``X @ B`` for X (n, P) and a small B (P, k), in blocks of rows.

    Each block product has at most 2^15 multiply-adds: one large GEMM would be spread by
    OpenBLAS over its own threads (above ~2^18), which spin-wait, fight the chunk threads
    of :func:`icgn_refine` and more than double the CPU time on a busy 2-core machine.
    """
    rows = max(1, 32768 // (X.shape[1] * B.shape[1]))
    if len(X) <= rows:
        return X @ B
    return np.concatenate([X[i:i + rows] @ B for i in range(0, len(X), rows)])


def _icgn_chunk(ctx, X0, pr, pg, grad0):
    """IC-GN for one chunk of subsets (all with reference subsets inside ref_img).

    Costs per iteration are kept to a few passes over the ``(m, P)`` arrays of the still
    active subsets: the warped samples (:func:`_bspline_sample`, or the separable
    :func:`_translate_square` while the warp is a pure translation), their
    normalisation, and ``Jᵀ r``, computed as two small matrix products
    ``(∇f_x r) B`` and ``(∇f_y r) B`` with the basis ``B = [1, ξx, ξy]`` of the affine
    shape function instead of storing the ``(m, 6, P)`` steepest-descent images.
    Subsets that converge or fail are dropped from the working arrays.
    """
    h, affine = ctx["h"], ctx["affine"]
    n = len(X0)
    xi = ctx["xi"]                                          # (2, P) local coordinates
    P = xi.shape[1]
    Sxi = xi @ xi.T / P                                     # second moments of the subset
    dx, dy = xi
    # Reference subsets (exact pixel values and B-spline gradients at the nodes).
    ridx = (X0[:, 1] * ctx["ref_w"] + X0[:, 0])[:, None] + ctx["roff"][None, :]
    f = ctx["ref_flat"].take(ridx)
    fx = ctx["rgx_flat"].take(ridx)
    fy = ctx["rgy_flat"].take(ridx)
    fz = f - f.mean(1, keepdims=True)
    df = np.sqrt(np.einsum("np,np->n", fz, fz))
    # Shape-function basis: J = [fx B, fy B] with B = [1, ξx, ξy] (affine) or [1].
    B = np.stack([np.ones(P), dx, dy], axis=1) if affine else np.ones((P, 1))
    nb = B.shape[1]
    cols_p = np.array([0, 1, 2, 3, 4, 5]) if affine else np.array([0, 3])
    npar = 2 * nb
    # Hessian H = Σ Jᵀ J from the three gradient products and the moments B_k B_l
    # (the nb (nb+1) / 2 distinct ones, then mirrored).
    iu, ju = np.triu_indices(nb)
    BB = B[:, iu] * B[:, ju]                                # (P, nb (nb+1) / 2)

    def sym(prod):
        out = np.empty((n, nb, nb))
        vals = _rowdot(prod, BB)
        out[:, iu, ju] = vals
        out[:, ju, iu] = vals
        return out
    Hxx, Hxy, Hyy = sym(fx * fx), sym(fx * fy), sym(fy * fy)
    Hs = np.concatenate([np.concatenate([Hxx, Hxy], 2), np.concatenate([Hxy, Hyy], 2)], 1)
    if ctx["kgx_flat"] is None:
        Hk = Hs
    else:   # the noise of smoothed images reaches the estimate through K J (see below)
        kx, ky = ctx["kgx_flat"].take(ridx), ctx["kgy_flat"].take(ridx)
        Kxx, Kxy, Kyy = sym(kx * kx), sym(kx * ky), sym(ky * ky)
        Hk = np.concatenate([np.concatenate([Kxx, Kxy], 2), np.concatenate([Kxy, Kyy], 2)], 1)
    # Texture test: relative conditioning of the (scaled) Hessian.
    scale = np.sqrt(np.einsum("nii->ni", Hs)) + 1e-300
    Hn = Hs / scale[:, :, None] / scale[:, None, :]
    ev = np.linalg.eigvalsh(Hn)
    fmax = np.abs(f).max(1) + 1e-12
    gmag = np.sqrt(Hs[:, 0, 0] + Hs[:, nb, nb])              # B[:, 0] = 1: Σ fx² + Σ fy²
    textured = (df > 1e-8 * fmax * np.sqrt(P)) & (gmag > 1e-8 * fmax * np.sqrt(P)) & \
        (ev[:, 0] > 1e-6)
    # Inverse compositional: the Hessian is that of the reference subset, inverted once.
    Hinv = np.zeros_like(Hs)
    Hinv[textured] = np.linalg.inv(Hs[textured])

    # Warp state about the integer centre X0: x' = X0 + t + A xi, xi = X - X0.
    A = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    A[:, 0, 0] += grad0[:, 0]
    A[:, 0, 1] += grad0[:, 1]
    A[:, 1, 0] += grad0[:, 2]
    A[:, 1, 1] += grad0[:, 3]
    o = pr - X0                                           # sub-pixel offset of pts_ref
    c = pg - np.einsum("nij,nj->ni", A, o)                # image position of the centre
    c_init = c.copy()

    Hc, Wc = ctx["cur_shape"]
    status = np.where(textured, 0, 2)    # 0 active, 1 converged, >= 2 failed
    why = np.where(textured, OK, NO_TEXTURE).astype(object)
    nit = np.zeros(n, int)
    zn = np.full(n, -1.0)
    rvar = np.full(n, np.nan)
    rat = np.full(n, np.nan)
    eye = np.eye(2)

    # Working copies restricted to the active subsets (compressed when the set shrinks).
    act = np.flatnonzero(textured)
    if len(act) == n:
        w_fz, w_fx, w_fy, w_df, w_Hinv = fz, fx, fy, df, Hinv
    else:
        w_fz, w_fx, w_fy, w_df, w_Hinv = fz[act], fx[act], fy[act], df[act], Hinv[act]
    # Constant parts of Jᵀ r: Jᵀ fz and Jᵀ 1.
    w_Jfz = np.concatenate([_rowdot(w_fx * w_fz, B), _rowdot(w_fy * w_fz, B)], axis=1)
    w_J1 = np.concatenate([_rowdot(w_fx, B), _rowdot(w_fy, B)], axis=1)

    def keep_only(mask):
        nonlocal act, w_fz, w_fx, w_fy, w_df, w_Hinv, w_Jfz, w_J1
        act = act[mask]
        w_fz, w_fx, w_fy, w_df, w_Hinv = (w_fz[mask], w_fx[mask], w_fy[mask], w_df[mask],
                                          w_Hinv[mask])
        w_Jfz, w_J1 = w_Jfz[mask], w_J1[mask]

    for _ in range(ctx["max_iter"]):
        if len(act) == 0:
            break
        a = A[act]
        # corner test is enough for an affine map: extreme coordinates are at corners
        cen = c[act]
        ext = np.abs(a).sum(2) * ctx["ext"]               # (m, 2) half extent in x, y
        ins = ((cen[:, 0] - ext[:, 0] >= 0) & (cen[:, 0] + ext[:, 0] <= Wc - 1)
               & (cen[:, 1] - ext[:, 1] >= 0) & (cen[:, 1] + ext[:, 1] <= Hc - 1))
        if not np.all(ins):
            status[act[~ins]] = 3
            why[act[~ins]] = OUTSIDE
            keep_only(ins)
            a, cen = a[ins], cen[ins]
            if len(act) == 0:
                break
        m = len(act)
        nit[act] += 1
        g = np.empty((m, P))      # current subsets g(W(ξ; p)), raw (mean not removed)
        ident = np.all(a == eye, axis=(1, 2)) if ctx["square"] else np.zeros(m, bool)
        if np.any(ident):      # pure translation of a square subset: separable B-spline
            if np.all(ident):
                g = _translate_square(ctx["cpad"], cen, h)
            else:
                g[ident] = _translate_square(ctx["cpad"], cen[ident], h)
        if not np.all(ident):
            gen = ~ident
            allgen = not np.any(ident)
            coords = np.matmul(a if allgen else a[gen], xi)   # (m', 2, P) = (x, y)
            coords += (cen if allgen else cen[gen])[:, :, None]
            table, wp, _ = ctx["table"]
            gg = _bspline_sample(table, wp, coords)
            if allgen:
                g = gg
            else:
                g[gen] = gg
        # ZNSSD terms without forming g - ḡ: Σ(g-ḡ)² = Σg² - P ḡ², Σ fz (g-ḡ) = Σ fz g
        # (fz is zero-mean). Both interpolants hold coefficients minus their mean, so the
        # cancellation costs no precision.
        gbar = g.sum(1) / P
        dg = np.sqrt(np.maximum(np.einsum("np,np->n", g, g) - P * gbar * gbar, 0.0))
        # Flat current subset: contrast below the float32 rounding of the pair table
        # (relative 1e-6 of the image's largest coefficient deviation).
        flat = dg <= 1e-6 * ctx["table"][2] * np.sqrt(P)
        if np.any(flat):
            status[act[flat]] = 4
            why[act[flat]] = NO_TEXTURE_CUR
            keep = ~flat
            keep_only(keep)
            a, g, dg, gbar, cen = a[keep], g[keep], dg[keep], gbar[keep], cen[keep]
            m = len(act)
        ratio = w_df / dg
        rat[act] = ratio
        fg = np.einsum("np,np->n", w_fz, g)
        zn[act] = fg / (w_df * dg)
        # residual r = fz - ratio g: |r|^2 = df^2 - 2 ratio fg + ratio^2 dg^2
        rvar[act] = np.maximum(2 * w_df * w_df * (1 - zn[act]), 0) / max(P - npar, 1)
        # Gauss-Newton step dp = -H^-1 Jᵀ r, residual r = fz - ratio (g - ḡ), so
        # Jᵀ r = Jᵀ fz - ratio (Jᵀ g - ḡ Jᵀ 1) with Jᵀ g = [(fx g) B, (fy g) B].
        Jg = np.concatenate([_rowdot(w_fx * g, B), _rowdot(w_fy * g, B)], axis=1)
        Jg -= gbar[:, None] * w_J1
        Jr = w_Jfz - ratio[:, None] * Jg
        dp = -np.einsum("nij,nj->ni", w_Hinv, Jr)
        full = np.zeros((m, 6))
        full[:, cols_p] = dp
        # W(p) <- W(p) o W(dp)^-1 ; W(dp): xi -> D xi + d, D = I + gradient terms
        D = np.empty((m, 2, 2))
        D[:, 0, 0] = 1 + full[:, 1]
        D[:, 0, 1] = full[:, 2]
        D[:, 1, 0] = full[:, 4]
        D[:, 1, 1] = 1 + full[:, 5]
        d = full[:, [0, 3]]
        with np.errstate(all="ignore"):
            det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
            Dinv = np.empty_like(D)                        # closed-form 2×2 inverse
            Dinv[:, 0, 0] = D[:, 1, 1] / det
            Dinv[:, 0, 1] = -D[:, 0, 1] / det
            Dinv[:, 1, 0] = -D[:, 1, 0] / det
            Dinv[:, 1, 1] = D[:, 0, 0] / det
        dinv = -np.einsum("nij,nj->ni", Dinv, d)
        c[act] = cen + np.einsum("nij,nj->ni", a, dinv)
        A[act] = np.matmul(a, Dinv)
        # RMS over the subset pixels of the displacement change of this update
        Dm = D - eye
        step = np.sqrt(np.einsum("ni,ni->n", d, d)
                       + np.einsum("nij,jk,nik->n", Dm, Sxi, Dm))
        moved = np.linalg.norm(c[act] - c_init[act], axis=1)
        with np.errstate(invalid="ignore"):
            gradbad = ~(np.abs(A[act] - eye).max(axis=(1, 2)) <= 0.5)
        div = ~np.isfinite(step) | (moved > h) | gradbad
        status[act[div]] = 5
        why[act[div]] = DIVERGED
        done = ~div & (step < ctx["tol"])
        status[act[done]] = 1
        if np.any(div | done):
            keep_only(~(div | done))
    why[status == 0] = MAX_ITER
    ok = status == 1

    # Outputs: matched position of pts_ref, warp about pts_ref, uncertainty.
    pos = c + np.einsum("nij,nj->ni", A, o)
    pts = np.where(ok[:, None], pos, np.nan)
    w = np.full((n, 6), np.nan)
    w[:, 0] = pos[:, 0] - pr[:, 0]
    w[:, 3] = pos[:, 1] - pr[:, 1]
    w[:, 1] = A[:, 0, 0] - 1
    w[:, 2] = A[:, 0, 1]
    w[:, 4] = A[:, 1, 0]
    w[:, 5] = A[:, 1, 1] - 1
    w[~ok] = np.nan
    # Covariance of the parameters (reference frame, f units): see _covariance. The
    # position of the sub-pixel reference point depends on (u, v) and on the gradients
    # times offset o.
    e = np.zeros((n, 2, 6))
    e[:, 0, 0] = 1
    e[:, 0, 1] = o[:, 0]
    e[:, 0, 2] = o[:, 1]
    e[:, 1, 3] = 1
    e[:, 1, 4] = o[:, 0]
    e[:, 1, 5] = o[:, 1]
    e = e[:, :, cols_p]
    zn = np.where(np.isfinite(zn) & (status != 2) & (status != 3) & (status != 4),
                  np.clip(zn, -1, 1), -1.0)
    return pts, w, zn, ok, nit, why, (Hs, Hk, Hinv, np.where(ok, rvar, np.nan), rat, e)


@functools.lru_cache(maxsize=16)
def _interp_gain_table(smooth_sigma_px=0.0):
    """1D white-noise variance gains of the cubic B-spline interpolant at the sub-pixel
    fractions ``t = 0, 1/20, … 1`` (21 values), relative to the gain of the Gaussian
    pre-smoothing of ``smooth_sigma_px``."""
    t = np.linspace(0, 1, 21)
    delta = np.zeros(41)
    delta[20] = 1.0
    k = ndimage.gaussian_filter1d(delta, float(smooth_sigma_px), mode="mirror", truncate=3.0) \
        if smooth_sigma_px else delta
    c = ndimage.spline_filter1d(k, order=3, mode="mirror")
    g1 = [np.sum(ndimage.map_coordinates(c, [np.arange(41) + tt], order=3, prefilter=False,
                                         mode="mirror") ** 2) for tt in t]
    return np.array(g1) / float(np.sum(k ** 2))


def _interp_noise_gain(smooth_sigma_px=0.0, pts=None):
    """White-noise variance gain of the cubic B-spline interpolant (both axes), relative
    to the gain of the Gaussian pre-smoothing: the factor by which sampling the current
    image between pixels shrinks its (smoothed) noise. Without ``pts`` the mean over
    sub-pixel fractions (0.764 unsmoothed; 0.98 after a 0.8 px Gaussian: smoothed noise is
    nearly band-limited and interpolates almost unchanged); with ``pts`` ((n, 2) sampled
    positions (x, y)) the gain at each one's fractions, (n,)."""
    g1 = _interp_gain_table(float(smooth_sigma_px or 0.0))
    if pts is None:
        return float(np.mean(g1[:-1])) ** 2
    t = np.linspace(0, 1, 21)
    frac = np.asarray(pts, float) % 1.0
    return np.interp(frac[:, 0], t, g1) * np.interp(frac[:, 1], t, g1)


def _noise_residual_variance(ctx, Hk, Hinv, rvar):
    """Residual variances (n,) rescaled to the degrees of freedom the fit leaves the noise.

    ``rvar`` divides the squared residual by ``P - npar``, which holds for white noise; a
    pre-smoothed noise has fewer independent pixels, and the warp's columns ``J`` (smooth
    where the texture is) absorb more of it: ``E|P_J n|² = s² tr(H⁻¹ Hk)`` with
    ``Hk = Σ (K J)ᵀ (K J)``, i.e. ``tr(H⁻¹ Hk) / γ_K`` pixels' worth of the per-pixel
    variance ``γ_K s²`` (``npar`` without smoothing); removing the subset means takes
    ``1 / γ_K`` more. On the smooth synthetic texture of
    ``tests/test_subset.py`` (0.8 px smoothing, 17-21 px subsets) the uncorrected residual
    gives a noise σ 4-6 % low.
    """
    P = ctx["xi"].shape[1]
    npar = 6 if ctx["affine"] else 2
    if ctx["kgx_flat"] is None:
        return rvar
    # the warp's share, plus the subset mean removed from each image (for a smoothed noise
    # 1 / γ_K pixels' worth of its variance)
    dof_fit = (np.einsum("nij,nji->n", Hinv, Hk) + 1.0) / ctx["noise_gain"]
    return rvar * (P - npar) / np.maximum(P - dof_fit, 1.0)


def _noise_ratios(noise_var, rvar, ratio, gain, interp_gain):
    """Residual variance of each subset over the one the noise variances predict, (n,).

    The residual variance of a converged subset (ZNSSD, per degree of freedom left to the
    noise, in reference grey units, :func:`_noise_residual_variance`) is, where the warp
    fits, the noise's ``γ_K (s_f² + ratio² γ_I s_g²)`` (``γ_K`` the smoothing gain
    ``gain``, ``γ_I`` the interpolation gain of the current image at the matched position
    ``interp_gain``, scalar or (n,), ``ratio = Δf/Δg``), and more where it does not (model
    misfit). NaN where not converged or where the noise is not measured.
    """
    ig = np.broadcast_to(interp_gain, np.shape(rvar))
    pred = gain * (noise_var[0] + ig * np.asarray(ratio) ** 2 * noise_var[1])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(rvar) / np.maximum(pred, 1e-300)


def _calibration_factor(noise_ratio):
    """Variance factor ``min(1, median(noise_ratio))`` of the default noise measurement
    (1 with fewer than 10 finite ratios)."""
    q = np.asarray(noise_ratio, float)
    q = q[np.isfinite(q)]
    if len(q) < 10:
        return 1.0
    f = float(np.median(q))
    return min(1.0, f) if np.isfinite(f) else 1.0


def _calibrate_noise(noise_var, noise_ratio, mode):
    """Measured noise variances, lowered to what the matched subsets' residuals allow.

    Immerkær's estimate is an upper bound where the texture is sharp at the pixel scale;
    the median of the subsets' ``noise_ratio`` (:func:`_noise_ratios`) is a second upper
    bound of the variance scale (it also holds model misfit). When the noise is measured
    (``mode`` None or ``"calibrated"``), both image variances are multiplied by
    :func:`_calibration_factor` (their relative level is kept from the image estimates);
    given values are returned unchanged.
    """
    measured = mode is None or (isinstance(mode, str) and mode == "calibrated")
    if not measured or not np.isfinite(noise_var[0]):
        return noise_var
    f = _calibration_factor(noise_ratio)
    return (noise_var[0] * f, noise_var[1] * f)


def _covariance(ctx, Hs, Hk, Hinv, B, rvar, ratio, e):
    """Variance (n, 2) of the matched position and the residual ratio (n,).

    With measured noise variances ``s_f²`` and ``s_g²`` of the reference and current
    images, the Hessian of the reference subset ``H = Σ JᵀJ`` holds the texture's
    ``H0`` plus the noise's gradient energy ``Hn = s_f² γ Σ B Bᵀ`` (``γ`` the white-noise
    gain of the B-spline gradient, after pre-smoothing). At convergence ``Jᵀ r = 0``
    gives ``δp = (Jᵀ J0)⁻¹ Jᵀ n``, so ``Cov(δp) = s² H0⁻¹ H H0⁻¹`` with
    ``s² = s_f² + (Δf/Δg)² s_g²``: for noise-free gradients this is ``2σ² H⁻¹``, the
    Cramér–Rao bound (Pan et al. 2008, Opt. Express 16(10), "Study on subset size
    selection in digital image correlation for speckle patterns", eq. 11), and it grows
    where the texture hardly stands above the noise. With Gaussian pre-smoothing ``K``
    the noise reaching ``Jᵀ n`` is ``(K J)ᵀ n`` of the unsmoothed noise, so the middle
    ``H`` becomes ``Hk = Σ (K J)ᵀ (K J)`` (``K J`` sampled on the subset). With
    ``noise_sigma="residual"`` the subset's own residual variance (divided by the
    kernel's ``Σ w²``) replaces ``s²`` in ``s² H⁻¹`` (the former estimate).
    """
    sf2, sg2 = ctx["noise_var"]
    gain = ctx["noise_gain"]
    if not np.isfinite(sf2):
        var = np.einsum("nai,nij,naj->na", e, Hinv, e) * (rvar / gain)[:, None]
        return var, np.full(len(rvar), np.nan)
    nb = B.shape[1]
    Hn = np.zeros((2 * nb, 2 * nb))
    BtB = B.T @ B
    Hn[:nb, :nb] = BtB
    Hn[nb:, nb:] = BtB
    H0 = Hs - (sf2 * ctx["grad_gain"]) * Hn
    good = np.all(np.isfinite(Hs), axis=(1, 2)) & (np.einsum("nii->n", Hinv) > 0)
    good[good] &= np.linalg.eigvalsh(H0[good])[:, 0] > 0
    H0i = np.zeros_like(Hs)
    H0i[good] = np.linalg.inv(H0[good])
    s2 = sf2 + np.nan_to_num(ratio) ** 2 * sg2
    # Middle term E[Jᵀn nᵀJ]: the reference noise's gradients meet the reference noise
    # itself in an antisymmetric quadratic form (odd gradient kernel, even smoothing
    # kernel), which vanishes, so only the current image's noise multiplies the noise part
    # of Hk: s² Hk0 + s_f² s_g'² γ_K ΣBBᵀ = s² Hk − s_f⁴ γ_K ΣBBᵀ.
    M = Hk * s2[:, None, None] - (sf2 * sf2 * ctx["kgrad_gain"]) * Hn
    var = np.einsum("nai,nij,naj->na", e, np.matmul(np.matmul(H0i, M), H0i), e)
    var[~good] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        rr = (rvar / gain) / s2
    return var, rr
