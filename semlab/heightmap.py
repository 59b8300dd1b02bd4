"""Dense height maps on the view-0 pixel grid: every pixel matched, edges kept, σ per pixel.

The chain (one function per stage, :func:`dense_parallax` runs them on a window):

1. **Initial guess** (:func:`initial_guess`): where each view-0 pixel lies in view 1, from
   DIS optical flow (Kroeger et al. 2016, ECCV) of the contrast-normalised views — after a
   dense prior interpolated from sparse seed matches when they are given (tall objects,
   parallax of hundreds of pixels), as in :func:`semlab.matching.auto_match`.
2. **Dense subsets** (:func:`semlab.subset.icgn_refine`): an affine IC-GN subset of
   ``(2h+1)²`` pixels centred on *every* pixel, with its ZNCC and its matching σ.
3. **σ scale** (:func:`sigma_scale`): the IC-GN σ is the noise-only error of one subset; it
   misses interpolation bias and the view-to-view differences of SEM contrast. Its factor
   is measured on the map itself, without any truth: second differences of three
   *non-overlapping* subsets in a row (independent noise, a linear trend cancels) divided
   by their predicted σ have a robust standard deviation (1.4826 MAD) equal to the factor.
4. **Edge-preserving fusion** (:func:`fuse_shiftable`): each pixel takes the ZNCC-weighted
   mean of the predictions of the subsets that contain it (centres within ``h − 1``, a
   "shiftable window", Bobick & Intille 1999, IJCV 33(3)), each carried to the pixel with
   its affine warp gradient (5×5 median of the neighbours' gradients, to cut its noise). A subset that straddles a slip-band step fits worse (lower
   ZNCC), so at a step the pixel is given by the subsets on its own side of the step, and
   the step is not smoothed by the full subset width. The fused 1σ is the larger of the
   contributors' scaled matching σ and their weighted spread (which grows where the
   subsets disagree: steps, groove walls).
5. **Heights** (:class:`HeightModel`): under the affine camera, the height above the
   reference plane is a linear function of the pixel positions in the two views,
   ``z = a·(u1, v1, u0, v0, 1)``; either from the tilts (:func:`height_model_from_tilts`)
   or fitted to the heights of the sparse points (:func:`height_model_from_points`, which
   then uses their reference plane, so the map and ``points3d.csv`` agree).

Conventions: images ``[row, col]``; points ``(x, y)`` pixels, origin at the centre of the
top-left pixel; a region of interest ``roi = (x0, y0, x1, y1)`` is half-open in pixels of
view 0 (columns ``x0..x1-1``, rows ``y0..y1-1``). Heights in µm, z > 0 extrusion.

Tiling (see :func:`dense_parallax`): the result for a ``roi`` depends only on the images
within ``margin_px`` of it, so tiles overlapping by ``2 · margin_px`` give the same values
as one call on the whole image (up to the σ scale, which is measured per call).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .errors import GeometryError, ImageError, SemlabError
from .heightmap_results import hillshade, measure_map, write_heightmap_results
from .pipeline import rows_in_views
from .stats import robust_sd

__all__ = [
    "DenseParams",
    "DenseParallax",
    "HeightModel",
    "HeightMap",
    "initial_guess",
    "sigma_scale",
    "fuse_shiftable",
    "smooth_bilateral",
    "dense_parallax",
    "height_model_from_tilts",
    "height_model_from_points",
    "dense_heights",
    "stereo_noise_sigma",
    "heightmap_from_stereo",
    "hillshade",
    "measure_map",
    "write_heightmap_results",
]


@dataclass(frozen=True)
class DenseParams:
    """Parameters of the dense map (recorded in the results).

    Attributes
    ----------
    half_window : int
        Subset half size ``h`` (subsets of ``(2h+1)²`` pixels).
    min_zncc : float
        Subsets with a lower ZNCC do not contribute.
    max_iter, tol_px : IC-GN iteration limit and convergence tolerance (pixels).
    fusion_radius_px : int, optional
        Centres of the subsets fused into a pixel lie within this radius (Chebyshev);
        default ``h - 1``. 0 turns the fusion off (each pixel its own subset).
    fusion_step_px : int
        Spacing of the fused subset centres (2 = every other subset, 4× fewer terms).
    zncc_tau : float
        Weight of a subset ``exp(-(1 - ZNCC) / τ)`` with ``τ = zncc_tau × median(1 − ZNCC)``
        of the map (so the selection adapts to the noise level): small values select the
        best fitting subset (sharper steps, more noise).
    outlier_px : float
        A subset whose parallax differs from the median of its 5×5 neighbours by more
        than ``max(outlier_px, 4 σ)`` is dropped.
    smooth_radius_px : int
        Radius of the edge-preserving smoothing prior after the fusion (0 = none): a
        bilateral mean over the parallax field (:func:`smooth_bilateral`) whose range
        kernel is ``smooth_range`` × the pixel's σ, so it averages independent subsets
        where the surface is smooth and stops at steps larger than the noise.
    smooth_range : float
    """

    half_window: int = 7
    min_zncc: float = 0.8
    max_iter: int = 30
    tol_px: float = 1e-3
    fusion_radius_px: int | None = None
    fusion_step_px: int = 2
    zncc_tau: float = 0.5
    outlier_px: float = 0.5
    smooth_radius_px: int = 0
    smooth_range: float = 2.0

    def margin_px(self):
        """Pixels around a window that its result depends on (subset + fusion reach)."""
        r = self.half_window - 1 if self.fusion_radius_px is None else self.fusion_radius_px
        return int(2 * self.half_window + r + 6 + self.smooth_radius_px)

    # what the tiling (semlab.tiled_stereo.tiled_parallax) asks of a dense method's params
    def dense_method(self):
        """The dense method these parameters are for: :func:`dense_parallax`."""
        return dense_parallax

    def tile_px(self, tiling):
        """Core tile size of a tiled map, pixels: ``tiling.dense_tile_px`` (one subset per
        pixel: small tiles keep the work arrays small)."""
        return int(tiling.dense_tile_px)

    def shared_calibration(self, view0, view1, seeds, calibration):
        """``calibration`` plus what every tile of one tiled map must share: view 1's mean
        B-spline coefficient (``coef_offset``, :func:`semlab.subset.icgn_refine`), which a
        tile's crop would give differently.

        Parameters
        ----------
        view0, view1 : (H, W) arrays
        seeds : (N, 2, 2) array or None
            Unused (the variational map fits its epipolar relation on them).
        calibration : dict

        Returns
        -------
        dict
            A copy.
        """
        from scipy import ndimage

        cal = dict(calibration or {})
        if "coef_offset" not in cal:
            cal["coef_offset"] = float(ndimage.spline_filter(
                np.asarray(view1, np.float64), order=3, mode="mirror").mean())
        return cal


@dataclass
class DenseParallax:
    """Dense correspondences of view-0 pixels in view 1 (result of :func:`dense_parallax`).

    Arrays are ``(h, w)`` on the view-0 pixel grid of ``roi``: element ``[i, j]`` is the
    pixel ``(x, y) = (roi[0] + j, roi[1] + i)``.

    Attributes
    ----------
    x1_px, y1_px : (h, w) float arrays
        Position ``(x, y)`` of each view-0 pixel in view 1, pixels; NaN where not measured.
    sigma_px : (h, w) float array
        1σ error of ``x1_px`` (the parallax direction), pixels.
    sigma_y_px : (h, w) float array
        1σ error of ``y1_px``, pixels.
    valid : (h, w) bool array
    zncc : (h, w) float array
        ZNCC of the best subset contributing to the pixel.
    roi : (x0, y0, x1, y1) ints
    sigma_scale : float
        Factor applied to the IC-GN σ (:func:`sigma_scale`).
    params : DenseParams
    calibration : dict
        The measured quantities of the call (see :func:`dense_parallax`), to reuse in tiles.
    weight_sigma_px : (h, w) float array or None
        A variational map's 1σ of ``x1_px`` for the surface at hand (noise plus the prior's
        plug-in bias), when asked (``VariationalParams.weight_sigma``); None otherwise.
    """

    x1_px: np.ndarray
    y1_px: np.ndarray
    sigma_px: np.ndarray
    sigma_y_px: np.ndarray
    valid: np.ndarray
    zncc: np.ndarray
    roi: tuple
    sigma_scale: float
    params: DenseParams
    calibration: dict = field(default_factory=dict)
    weight_sigma_px: np.ndarray | None = None

    def grid(self):
        """View-0 pixel coordinates ``(x0_px, y0_px)`` of the map, two ``(h, w)`` arrays."""
        x0, y0, x1, y1 = self.roi
        return np.meshgrid(np.arange(x0, x1, dtype=float), np.arange(y0, y1, dtype=float))


@dataclass(frozen=True)
class HeightModel:
    """Height above the reference plane as a linear function of the two views' positions.

    ``z_um = coef · (x1, y1, x0, y0, 1)`` with ``(x0, y0)`` in view 0 and ``(x1, y1)`` in
    view 1, pixels (exact for an affine camera pair). ``rms_um`` is the residual of the fit
    (0 from tilts).
    """

    coef: tuple
    rms_um: float = 0.0
    source: str = "tilts"

    def height(self, x1, y1, x0, y0):
        c = self.coef
        return c[0] * x1 + c[1] * y1 + c[2] * x0 + c[3] * y0 + c[4]

    def sigma(self, sigma_x_px, sigma_y_px=0.0):
        """1σ height (µm) from the 1σ errors of the view-1 position (pixels)."""
        return np.hypot(self.coef[0] * sigma_x_px, self.coef[1] * sigma_y_px)


@dataclass
class HeightMap:
    """Dense heights on the view-0 pixel grid.

    Attributes
    ----------
    z_um : (h, w) float32 array
        Height above the reference surface, µm (z > 0 extrusion), NaN where not measured.
    sigma_um : (h, w) float32 array
        1σ of ``z_um``, µm (NaN where not measured).
    valid : (h, w) bool array
    pixel_size_um : float
    roi : (x0, y0, x1, y1)
    parallax : DenseParallax
        The view-1 positions the heights come from, their σ and ZNCC (float32 arrays: the
        heights were computed from them in float64).
    model : HeightModel
    notes : list of str
    """

    z_um: np.ndarray
    sigma_um: np.ndarray
    valid: np.ndarray
    pixel_size_um: float
    roi: tuple
    parallax: DenseParallax = field(repr=False)
    model: HeightModel = None
    notes: list = field(default_factory=list)

    def metadata(self):
        """JSON-ready description of how the map was made."""
        return {"pixel_size_um": float(self.pixel_size_um), "roi": list(map(int, self.roi)),
                "params": asdict(self.parallax.params),
                "sigma_scale": float(self.parallax.sigma_scale),
                "calibration": {k: np.asarray(v).tolist()
                                for k, v in self.parallax.calibration.items()},
                "height_model": {"coef": list(map(float, self.model.coef)),
                                 "rms_um": float(self.model.rms_um),
                                 "source": self.model.source},
                "measured_fraction": float(self.valid.mean()) if self.valid.size else 0.0,
                "notes": list(self.notes)}


# ------------------------------------------------------------------------------ validation
def _as_view(img, name):
    a = np.asarray(img)
    if a.ndim != 2 or min(a.shape) < 8:
        raise ImageError(f"{name} must be a 2D image of at least 8×8 pixels, got shape {a.shape}")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise ImageError(f"{name} holds NaN/inf pixels: replace them before dense matching")
    return a


def _check_roi(roi, shape):
    hgt, wid = shape
    if roi is None:
        return (0, 0, wid, hgt)
    r = tuple(int(v) for v in roi)
    if len(r) != 4 or not (0 <= r[0] < r[2] <= wid and 0 <= r[1] < r[3] <= hgt):
        raise SemlabError(f"roi must be (x0, y0, x1, y1) with 0 <= x0 < x1 <= {wid} and "
                          f"0 <= y0 < y1 <= {hgt} (view-0 pixels, half-open), got {roi!r}")
    return r


def _take(a, dx, dy, fill):
    """``out[i, j] = a[i + dy, j + dx]`` (``fill`` outside)."""
    hgt, wid = a.shape
    out = np.full(a.shape, fill, a.dtype)
    if abs(dx) >= wid or abs(dy) >= hgt:
        return out
    y0, y1 = max(0, -dy), hgt - max(0, dy)
    x0, x1 = max(0, -dx), wid - max(0, dx)
    out[y0:y1, x0:x1] = a[y0 + dy:y1 + dy, x0 + dx:x1 + dx]
    return out


# ------------------------------------------------------------------------------ stages
def initial_guess(view0, view1, seeds=None, half_window=7):
    """Where every view-0 pixel lies in view 1, to about a pixel.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
    seeds : (N, 2, 2) array, optional
        Sparse matches ``[:, v] = (x, y)`` in view ``v`` (e.g. ``StereoResult.pts[:, :2]``);
        with at least 6 of them, a dense prior map interpolated from them is applied first
        (needed when the parallax is large and varies, e.g. tall objects).
    half_window : int
        Subset half size (sets the scale of the contrast normalisation and smoothing).

    Returns
    -------
    guess : (H, W, 2) float array of (x, y) in view 1.
    grad : (H, W, 4) float array of the warp gradient ``(du/dx, du/dy, dv/dx, dv/dy)``.
    fb_err : (H, W) float array
        Forward–backward disagreement of the flow, pixels.
    """
    from . import matching

    hgt, wid = view0.shape
    if seeds is not None and len(seeds) >= 6:
        s = np.asarray(seeds, float)
        ok = np.all(np.isfinite(s.reshape(len(s), -1)), 1)
        M = matching._dense_prior(s[ok, 0], s[ok, 1], view0.shape, half_window)
    else:
        M = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    _, fwd, bwd = matching._flow_field(view0, view1, M, half_window, 2.0)
    yy, xx = np.mgrid[0:hgt, 0:wid]
    grid = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    guess, init, fb = matching._flow_guess(M, fwd, bwd, grid, half_window)
    return (guess.reshape(hgt, wid, 2), init[:, [1, 2, 4, 5]].reshape(hgt, wid, 4),
            fb.reshape(hgt, wid))


def sigma_scale(x1_px, sigma_px, valid, half_window):
    """Factor between the actual and the IC-GN-predicted random error, from the map itself.

    Along each row, subsets ``D = 2h + 1`` apart do not share pixels, so their noise is
    independent. The third difference ``p₀ − 3p₁ + 3p₂ − p₃`` of the parallax of four of them
    cancels a quadratic trend and has standard deviation ``k sqrt(σ₀² + 9σ₁² + 9σ₂² + σ₃²)``
    if the actual errors are ``k`` times the predicted ones; ``k`` is the robust standard
    deviation (1.4826 MAD) of the normalised differences (steps are outliers of the MAD).
    Clipped to >= 1: the prediction is never taken to be pessimistic.

    Parameters
    ----------
    x1_px, sigma_px : (H, W) arrays
        Matched x position in view 1 and its predicted 1σ, pixels.
    valid : (H, W) bool array
    half_window : int

    Returns
    -------
    float
    """
    D = 2 * int(half_window) + 1
    p = np.where(valid, x1_px - np.arange(x1_px.shape[1])[None, :], np.nan)
    n = p.shape[1] - 3 * D
    if n <= 0:
        return 1.0
    q = [p[:, i * D:i * D + n] for i in range(4)]
    s = [sigma_px[:, i * D:i * D + n] for i in range(4)]
    with np.errstate(invalid="ignore"):
        r = ((q[0] - 3 * q[1] + 3 * q[2] - q[3])
             / np.sqrt(s[0] ** 2 + 9 * s[1] ** 2 + 9 * s[2] ** 2 + s[3] ** 2))
    r = r[np.isfinite(r)]
    if len(r) < 100:
        return 1.0
    k = robust_sd(r)
    return float(max(1.0, k))


def _drop_outliers(par, sig, ok, outlier_px):
    """Subsets whose parallax leaves the median of its 5×5 converged neighbours."""
    p = np.where(ok, par, np.nan)
    with np.errstate(invalid="ignore"):
        bad = np.abs(p - _nanmedian5(p)) > np.maximum(outlier_px, 4 * sig)
    return ok & ~bad


def _nanmedian5(p):
    """Median of the finite values of each pixel's 5×5 neighbourhood (NaN if none)."""
    stack = np.sort(np.stack([_take(p, dx, dy, np.nan) for dx in range(-2, 3)
                              for dy in range(-2, 3)]), axis=0)       # NaNs sort last
    n = np.isfinite(stack).sum(0)
    lo = np.take_along_axis(stack, np.maximum(n - 1, 0)[None] // 2, 0)[0]
    hi = np.take_along_axis(stack, (n // 2)[None], 0)[0] if stack.shape[0] else lo
    med = 0.5 * (lo + np.where(n > 0, hi, np.nan))
    return np.where(n > 0, med, np.nan)


def fuse_shiftable(values, sigma, zncc, valid, gradients, radius_px, step_px=2, tau=0.01):
    """Edge-preserving fusion of dense subset estimates ("shiftable windows").

    Pixel ``p`` gets ``Σ w_q [v_q + ∇v_q · (p − q)] / Σ w_q`` over the subsets ``q`` within
    ``radius_px`` (every ``step_px``), ``w_q = exp(-(1 − zncc_q) / tau)`` (computed relative
    to the best subset around ``p``, which cancels in the ratio): subsets that
    straddle a step fit worse and drop out, so the step stays sharp.

    Parameters
    ----------
    values : (H, W, C) float array
        Estimate of each subset centred on each pixel (e.g. the x and y parallax).
    sigma : (H, W, C) float array
        Their 1σ (already scaled).
    zncc : (H, W) float array
    valid : (H, W) bool array
    gradients : (H, W, C, 2) float array
        ``(∂v/∂x, ∂v/∂y)`` of each subset (e.g. its affine warp, median-filtered).
    radius_px, step_px : int
    tau : float

    Returns
    -------
    fused : (H, W, C)
    fused_sigma : (H, W, C)
        ``max(RMS σ, spread)`` with the same weights: the contributors' errors are strongly
        correlated (they share pixels, so averaging does not divide σ), and their weighted
        spread, which already holds their noise, takes over where they disagree (steps,
        groove walls).
    best_zncc : (H, W)
    support : (H, W) float
        Sum of the weights (0: no contributor, not measured).
    """
    v = np.asarray(values, float)
    s = np.asarray(sigma, float)
    g = np.nan_to_num(np.asarray(gradients, float))
    hgt, wid, nc = v.shape
    ok = valid & np.all(np.isfinite(v), -1) & np.all(np.isfinite(s), -1) & (zncc > -1)
    from scipy import ndimage

    zq = np.where(ok, zncc, -1.0)
    r = int(radius_px)
    zmax = ndimage.maximum_filter(zq, size=2 * r + 1, mode="constant", cval=-1.0)
    vz = np.where(ok[..., None], v, 0.0)
    sz = np.where(ok[..., None], s, 0.0)
    offs = [(dx, dy) for dy in range(-r, r + 1, max(1, step_px))
            for dx in range(-r, r + 1, max(1, step_px))]
    if (0, 0) not in offs:
        offs.append((0, 0))
    sw = np.zeros((hgt, wid))
    s1 = np.zeros((hgt, wid, nc))
    ss = np.zeros((hgt, wid, nc))
    best = np.full((hgt, wid), -1.0)
    preds = []
    for dx, dy in offs:
        zs = _take(zq, dx, dy, -1.0)
        # relative to the best subset around p (no underflow; the factor cancels)
        w = np.where(zs > -1.0, np.exp(-(zmax - zs) / max(tau, 1e-12)), 0.0)
        pred = np.stack([_take(vz[..., c], dx, dy, 0.0) - _take(g[..., c, 0], dx, dy, 0.0) * dx
                         - _take(g[..., c, 1], dx, dy, 0.0) * dy for c in range(nc)], -1)
        sg = np.stack([_take(sz[..., c], dx, dy, 0.0) for c in range(nc)], -1)
        sw += w
        s1 += w[..., None] * pred
        ss += w[..., None] * sg ** 2
        best = np.maximum(best, np.where(w > 0, zs, -1.0))
        preds.append((w, pred))
    with np.errstate(invalid="ignore", divide="ignore"):
        mu = s1 / sw[..., None]
        mu0 = np.nan_to_num(mu)
        s2 = np.zeros_like(s1)
        for w, pred in preds:
            s2 += w[..., None] * (pred - mu0) ** 2
        fs = np.maximum(np.sqrt(ss / sw[..., None]), np.sqrt(s2 / sw[..., None]))
    none = sw <= 0
    mu[none] = np.nan
    fs[none] = np.nan
    return mu, fs, best, sw


def smooth_bilateral(values, sigma, valid, radius_px, range_k=2.0, step_px=2,
                     corr_px=15):
    """Edge-preserving smoothing prior: a σ-weighted bilateral mean of the parallax field.

    ``v'(p) = Σ w_q v_q / Σ w_q`` over ``q`` within ``radius_px`` (every ``step_px``) with
    ``w_q = exp(-|q - p|² / (2 (radius_px/2)²)) · exp(-(v_q - v_p)² / (2 (range_k σ_p)²)) / σ_q²``
    (Tomasi & Manduchi 1998, ICCV, with the range kernel in units of the estimate's own
    noise): neighbours that differ by more than the noise — across a step — get no weight.

    Returns
    -------
    smoothed : like ``values``
    sigma : like ``sigma``
        ``σ_p / sqrt(n_eff)`` with ``n_eff = (Σw)² / Σw²`` counted in independent subsets
        (``× step_px² / corr_px²``, at least 1); :func:`dense_parallax` then re-measures
        its scale on the smoothed map.
    """
    v = np.asarray(values, float)
    s = np.asarray(sigma, float)
    ok = valid & np.isfinite(v) & np.isfinite(s) & (s > 0)
    vz, sz = np.where(ok, v, 0.0), np.where(ok, s, np.inf)
    r = int(radius_px)
    sw = np.zeros(v.shape)
    sw2 = np.zeros(v.shape)
    s1 = np.zeros(v.shape)
    for dy in range(-r, r + 1, max(1, step_px)):
        for dx in range(-r, r + 1, max(1, step_px)):
            vq, sq = _take(vz, dx, dy, 0.0), _take(sz, dx, dy, np.inf)
            with np.errstate(invalid="ignore", over="ignore"):
                w = (np.exp(-(dx * dx + dy * dy) / (2 * (r / 2.0) ** 2))
                     * np.exp(-0.5 * ((vq - vz) / (range_k * np.where(ok, s, 1.0))) ** 2)
                     / sq ** 2)
            w = np.where(ok & np.isfinite(w), w, 0.0)
            sw += w
            sw2 += w * w
            s1 += w * vq
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(ok, s1 / sw, np.nan)
        n_eff = np.maximum(1.0, sw ** 2 / sw2 * (step_px / float(corr_px)) ** 2)
        sig = np.where(ok, s / np.sqrt(n_eff), np.nan)
    return out, sig


def dense_parallax(view0, view1, seeds=None, roi=None, params=None, guess=None,
                   calibration=None, progress=False):
    """Dense correspondences of the view-0 pixels of ``roi`` in view 1.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
        The two views (whole images; only the part within ``params.margin_px()`` of
        ``roi`` in view 0, and around its guessed match in view 1, is used).
    seeds : (N, 2, 2) array, optional
        Sparse matches (view 0, view 1) of the whole images for the initial guess.
    roi : (x0, y0, x1, y1), optional
        Half-open window of view-0 pixels; default the whole image.
    params : DenseParams, optional
    guess : (H, W, 2) array or the tuple returned by :func:`initial_guess`, optional
        Initial guess of every view-0 pixel's position in view 1 (whole-image grid), and
        with the tuple the warp gradients too; overrides ``seeds``/flow. For tiles: compute
        ``initial_guess(view0, view1, seeds)`` once and pass it, with one ``calibration``,
        to every tile: the tiles then give the values of one whole-image call (test
        ``test_tiles_with_a_shared_guess_equal_the_whole_image``).
    calibration : dict, optional
        Quantities otherwise measured in this call, to share between tiles (e.g. the
        ``calibration`` of a result on a representative window): ``sigma_factor``
        (:func:`sigma_scale`), ``zncc_tau`` (absolute fusion τ), ``noise_sigma`` (image
        noise of the two views, for the IC-GN σ; e.g. the stereo matches' calibrated
        noise, :func:`semlab.noise.calibrated_noise_sigma`), ``coef_offset`` (view 1's
        B-spline coefficient mean). Missing keys are measured in the window: the noise by
        :func:`semlab.subset.icgn_refine`'s default (Immerkær's estimate lowered to the
        dense subsets' residuals, as the matcher measures it), ``coef_offset`` on the
        whole view 1.
    progress : bool

    Returns
    -------
    DenseParallax
        Arrays of shape ``(y1 - y0, x1 - x0)``.
    """
    from . import subset

    p = params or DenseParams()
    v0 = _as_view(view0, "view0")
    v1 = _as_view(view1, "view1")
    if v0.shape != v1.shape:
        raise ImageError(f"view0 and view1 must have one shape, got {v0.shape} and {v1.shape}")
    roi = _check_roi(roi, v0.shape)
    h = int(p.half_window)
    if h < 2:
        raise SemlabError(f"half_window must be >= 2, got {p.half_window}")
    hgt, wid = v0.shape
    m = p.margin_px()
    # window of view 0 with its margin
    wx0, wy0 = max(0, roi[0] - m), max(0, roi[1] - m)
    wx1, wy1 = min(wid, roi[2] + m), min(hgt, roi[3] + m)
    if guess is None:
        if seeds is None and roi != (0, 0, wid, hgt):
            g, grad, _ = initial_guess(v0[wy0:wy1, wx0:wx1], v1[wy0:wy1, wx0:wx1], None, h)
            g = g + np.array([wx0, wy0], float)
        else:
            g, grad, _ = initial_guess(v0, v1, seeds, h)
            g, grad = g[wy0:wy1, wx0:wx1], grad[wy0:wy1, wx0:wx1]
    else:
        gg, gr = (guess[0], guess[1]) if isinstance(guess, tuple) else (guess, None)
        gg = np.asarray(gg, float)
        if gg.shape != (hgt, wid, 2) or (gr is not None and np.shape(gr) != (hgt, wid, 4)):
            raise SemlabError(f"guess must be an (H, W, 2) = ({hgt}, {wid}, 2) array of view-1 "
                              "positions or the (guess, grad, fb_err) tuple of initial_guess, "
                              f"got shape {gg.shape}")
        g = gg[wy0:wy1, wx0:wx1]
        grad = (np.zeros(g.shape[:2] + (4,)) if gr is None
                else np.asarray(gr, float)[wy0:wy1, wx0:wx1])
    gh, gw = g.shape[:2]
    yy, xx = np.mgrid[wy0:wy1, wx0:wx1]
    pts = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    gflat = g.reshape(-1, 2)
    # view-1 window around the guesses (with room for the subset and its motion)
    fin = np.all(np.isfinite(gflat), 1)
    if not fin.any():
        raise GeometryError("no finite initial guess in the window: give seeds or a guess")
    pad = 2 * h + 8
    cx0 = int(max(0, np.floor(gflat[fin, 0].min()) - pad))
    cy0 = int(max(0, np.floor(gflat[fin, 1].min()) - pad))
    cx1 = int(min(wid, np.ceil(gflat[fin, 0].max()) + pad + 1))
    cy1 = int(min(hgt, np.ceil(gflat[fin, 1].max()) + pad + 1))
    ref = v0[wy0:wy1, wx0:wx1]
    cur = v1[cy0:cy1, cx0:cx1]
    init = np.zeros((len(pts), 6))
    init[:, [1, 2, 4, 5]] = grad.reshape(-1, 4)
    cal = dict(calibration or {})
    whole = roi == (0, 0, wid, hgt)
    if "coef_offset" not in cal and not whole:
        from scipy import ndimage

        cal["coef_offset"] = float(ndimage.spline_filter(v1, order=3, mode="mirror").mean())
    r = subset.icgn_refine(ref, cur, pts - [wx0, wy0], gflat - [cx0, cy0], half_window=h,
                           max_iter=p.max_iter, tol_px=p.tol_px, init_warp=init,
                           noise_sigma=cal.get("noise_sigma"), coef_offset=cal.get("coef_offset"),
                           progress=progress)
    # without a given noise, icgn_refine's own calibrated measurement (the matcher's: Immerkær
    # lowered to the converged subsets' residuals), recorded so that tiles can share it
    cal.setdefault("noise_sigma", tuple(float(v) for v in r.noise_sigma))
    x1 = (r.pts[:, 0] + cx0).reshape(gh, gw)
    y1 = (r.pts[:, 1] + cy0).reshape(gh, gw)
    sx = r.sigma_px[:, 0].reshape(gh, gw)
    sy = r.sigma_px[:, 1].reshape(gh, gw)
    zn = r.zncc.reshape(gh, gw)
    ok = r.converged.reshape(gh, gw) & (zn >= p.min_zncc) & np.isfinite(sx)
    par = x1 - xx
    ok = _drop_outliers(par, sx, ok, p.outlier_px)
    k = float(cal["sigma_factor"]) if "sigma_factor" in cal else sigma_scale(x1, sx, ok, h)
    cal["sigma_factor"] = k
    radius = h - 1 if p.fusion_radius_px is None else int(p.fusion_radius_px)
    vals = np.stack([x1 - xx, y1 - yy], -1)
    sigs = np.stack([k * sx, k * sy], -1)
    if radius > 0:
        wg = np.where(ok[..., None], r.warp.reshape(gh, gw, 6), np.nan)
        grads = np.stack([np.stack([_nanmedian5(wg[..., 1]), _nanmedian5(wg[..., 2])], -1),
                          np.stack([_nanmedian5(wg[..., 4]), _nanmedian5(wg[..., 5])], -1)], 2)
        if "zncc_tau" not in cal:
            cal["zncc_tau"] = max(1e-6, p.zncc_tau * float(np.median(1.0 - zn[ok]))
                                  if ok.any() else 1.0)
        fused, fsig, best, support = fuse_shiftable(vals, sigs, zn, ok, grads, radius,
                                                    p.fusion_step_px, cal["zncc_tau"])
        valid = support > 0
    else:
        fused = np.where(ok[..., None], vals, np.nan)
        fsig = np.where(ok[..., None], sigs, np.nan)
        best, valid = np.where(ok, zn, -1.0), ok
    if p.smooth_radius_px > 0:
        sm, ssm = smooth_bilateral(fused[..., 0], fsig[..., 0], valid, p.smooth_radius_px,
                                   p.smooth_range, corr_px=2 * h + 1)
        if "smooth_factor" not in cal:
            cal["smooth_factor"] = sigma_scale(sm + xx, ssm, valid, h + p.smooth_radius_px)
        fused[..., 0] = sm
        fsig[..., 0] = cal["smooth_factor"] * ssm
    # crop to the roi
    sl = (slice(roi[1] - wy0, roi[3] - wy0), slice(roi[0] - wx0, roi[2] - wx0))
    gx, gy = xx[sl].astype(float), yy[sl].astype(float)
    valid = valid[sl]
    nanv = lambda a: np.where(valid, a, np.nan)  # noqa: E731
    return DenseParallax(x1_px=nanv(gx + fused[sl][..., 0]), y1_px=nanv(gy + fused[sl][..., 1]),
                         sigma_px=nanv(fsig[sl][..., 0]), sigma_y_px=nanv(fsig[sl][..., 1]),
                         valid=valid, zncc=np.where(valid, best[sl], -1.0), roi=roi,
                         sigma_scale=k, params=p, calibration=cal)


# ------------------------------------------------------------------------------ heights
def height_model_from_tilts(tilt0_deg, tilt1_deg, pixel_size_um, center_x_px=0.0):
    """:class:`HeightModel` of an affine eucentric pair (tilt axis along image y).

    ``z = s [(x1 - c) cos θ0 - (x0 - c) cos θ1] / sin(θ1 - θ0)`` (see
    :func:`semlab.reconstruct.parallax_height`): heights above the plane ``z = 0`` of the
    camera model, not a fitted reference plane.
    """
    from .reconstruct import parallax_height

    c = float(center_x_px)
    z00 = float(parallax_height(0.0, 0.0, tilt0_deg, tilt1_deg, pixel_size_um, c, c))
    a1 = float(parallax_height(0.0, 1.0, tilt0_deg, tilt1_deg, pixel_size_um, c, c)) - z00
    a0 = float(parallax_height(1.0, 0.0, tilt0_deg, tilt1_deg, pixel_size_um, c, c)) - z00
    return HeightModel(coef=(a1, 0.0, a0, 0.0, z00), rms_um=0.0, source="tilts")


def height_model_from_points(pts, z_um):
    """Fit the :class:`HeightModel` to sparse points with known heights.

    Parameters
    ----------
    pts : (N, V, 2) array
        Matched positions; views 0 and 1 are used.
    z_um : (N,) array
        Heights above the reference plane of those points (e.g. ``StereoResult.z_um``).

    Returns
    -------
    HeightModel
        Exact (``rms_um`` ~ 1e-12) when the heights come from views 0 and 1 by the affine
        model; with more views its residual says how far the pair departs from them.
        Least squares with a 3.5·MAD outlier cut, repeated twice.
    """
    P = np.asarray(pts, float)
    z = np.asarray(z_um, float).ravel()
    if P.ndim != 3 or P.shape[1] < 2 or P.shape[2] != 2 or len(P) != len(z):
        raise GeometryError(f"pts must be (N, V>=2, 2) and z_um (N,), got {P.shape}, {z.shape}")
    A = np.column_stack([P[:, 1, 0], P[:, 1, 1], P[:, 0, 0], P[:, 0, 1], np.ones(len(P))])
    ok = np.all(np.isfinite(A), 1) & np.isfinite(z)
    if ok.sum() < 8:
        raise GeometryError(f"need at least 8 points with heights to fit the height model, "
                            f"got {int(ok.sum())}")
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(A[ok], z[ok], rcond=None)
        res = z - A @ coef
        mad = robust_sd(res[ok], about=0.0)
        new = np.isfinite(res) & (np.abs(res) <= max(3.5 * mad, 1e-9))
        if new.sum() < 8 or np.array_equal(new, ok):
            break
        ok = new
    rms = float(np.sqrt(np.mean(res[ok] ** 2)))
    return HeightModel(coef=tuple(float(c) for c in coef), rms_um=rms, source="points")


def dense_heights(view0, view1, tilt_deg=None, pixel_size_um=None, seeds=None, roi=None,
                  params=None, model=None, progress=False):
    """Dense height map (µm) of ``roi`` on the view-0 pixel grid.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
    tilt_deg : (2,) sequence, optional
        Stage tilts of the two views (for :func:`height_model_from_tilts`); not needed
        with ``model``.
    pixel_size_um : float
    seeds : (N, 2, 2) array, optional
        Sparse matches for the initial guess.
    roi : (x0, y0, x1, y1), optional
    params : DenseParams, optional
    model : HeightModel, optional
        Default: from the tilts, about the image centre.

    Returns
    -------
    HeightMap
    """
    if pixel_size_um is None or not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise SemlabError(f"pixel_size_um must be a positive number, got {pixel_size_um!r}")
    if model is None:
        if tilt_deg is None or len(tilt_deg) < 2:
            raise SemlabError("dense_heights needs tilt_deg = (tilt0, tilt1) or a HeightModel")
        cx = (np.shape(view0)[1] - 1) / 2.0
        model = height_model_from_tilts(tilt_deg[0], tilt_deg[1], pixel_size_um, cx)
    par = dense_parallax(view0, view1, seeds=seeds, roi=roi, params=params, progress=progress)
    return _heights(par, model, pixel_size_um)


def _heights(par, model, pixel_size_um):
    """:class:`HeightMap` of a :class:`DenseParallax` under ``model``."""
    gx, gy = par.grid()
    z = model.height(par.x1_px, par.y1_px, gx, gy)
    sz = model.sigma(par.sigma_px, par.sigma_y_px)
    valid = par.valid & np.isfinite(z) & np.isfinite(sz)
    # the parallax is kept for inspection in float32, like the heights (computed above in
    # float64): a 3072×4096 map's five float arrays take 0.25 GB instead of 0.5 GB in every
    # process that loads the map (the notebook kernel too); positions up to 4096 px keep
    # 2.4e-4 px (0.04 nm of height at ±5°, 0.03 µm/px)
    kept = replace(par, **{k: getattr(par, k).astype(np.float32)
                           for k in ("x1_px", "y1_px", "sigma_px", "sigma_y_px", "zncc")})
    return HeightMap(z_um=np.where(valid, z, np.nan).astype(np.float32),
                     sigma_um=np.where(valid, sz, np.nan).astype(np.float32), valid=valid,
                     pixel_size_um=float(pixel_size_um), roi=par.roi, parallax=kept,
                     model=model)


def heightmap_from_stereo(exp, stereo, params=None, progress=False, roi=None, tiling=None,
                          scheduler=None):
    """Dense height map of an experiment's views 0 and 1, consistent with its sparse result.

    Parameters
    ----------
    exp : semlab.experiment.Experiment
    stereo : semlab.pipeline.StereoResult
        Its matches seed the guess and its heights fix the :class:`HeightModel` (so the
        map is above the same reference plane as ``points3d.csv``).
    params : DenseParams or semlab.variational.VariationalParams, optional
        The subset map (default) or the variational refinement
        (:func:`semlab.variational.variational_parallax`).
    roi : (x0, y0, x1, y1), optional
        Half-open window of view-0 pixels to map (default the whole view).
    tiling : semlab.tiled_stereo.TilingParams, optional
        Views of more than ``tiling.min_pixels`` pixels, and maps of more than
        ``tiling.map_min_pixels``, are mapped in tiles with one calibration
        (:func:`semlab.tiled_stereo.tiled_parallax`; default ``DEFAULT_TILING``).
    scheduler : str, optional
        Where the tiles run (see :func:`semlab.parallel.dask_client`).

    Returns
    -------
    HeightMap
    """
    views = exp.views()
    notes = []
    if stereo.pts.shape[1] > 2:
        notes.append("dense map from views 0 and 1 (height model fitted to the "
                     "multi-view heights)")
    if exp.stereo.camera == "perspective":
        notes.append("camera = perspective: the map uses a linear (affine) height model "
                     "fitted to the triangulated points")
    # points matched in views 0 and 1 (with 3+ views some are seen in fewer views)
    pair = rows_in_views(stereo.pts, 0, 1)
    try:
        model = height_model_from_points(stereo.pts[pair, :2], stereo.z_um[pair])
        rms_nm = model.rms_um * 1e3
        fit = (f"residual {rms_nm:.2g} nm" if rms_nm >= 1e-3 else
               "exact (residual below 0.001 nm: two views' heights are linear in the parallax)")
        notes.append(f"height model fitted to {pair.sum()} points, {fit}")
    except GeometryError:
        # too few points to fit: the tilts' closed form, above the plane z = 0 of the
        # camera model rather than the points' reference plane
        cx = (np.shape(views[0])[1] - 1) / 2.0
        model = height_model_from_tilts(stereo.tilt_deg[0], stereo.tilt_deg[1],
                                        exp.pixel_size_um, cx)
        notes.append(f"only {len(stereo.pts)} points: heights from the tilts above the "
                     "camera model's z = 0 plane, not the points' reference plane")
    from .tiled_stereo import DEFAULT_TILING, tiled_parallax

    t = tiling or DEFAULT_TILING
    params = params or DenseParams()
    method = params.dense_method()
    if method is not dense_parallax:
        notes.append(f"dense method {method.__module__}.{method.__name__}")
    noise, how = stereo_noise_sigma(views[0], views[1], stereo)
    cal = {"noise_sigma": noise}
    notes.append(f"image noise σ {noise[0]:.4g}, {noise[1]:.4g} (grey levels) {how}")
    seeds = stereo.pts[pair, :2]
    if t.tiles_map(np.shape(views[0]), roi):
        par = tiled_parallax(views[0], views[1], seeds=seeds, roi=roi, params=params,
                             method=method, calibration=cal, tiling=t, scheduler=scheduler,
                             progress=progress)
        notes.append(f"mapped in {params.tile_px(t)} px tiles with one calibration "
                     "(semlab.tiled_stereo.tiled_parallax)")
    else:
        par = method(views[0], views[1], seeds=seeds, roi=roi, params=params,
                     calibration=cal, progress=progress)
    hm = _heights(par, model, exp.pixel_size_um)
    hm.notes.extend(notes)
    return hm


def stereo_noise_sigma(view0, view1, stereo):
    """Image noise of views 0 and 1 as the stereo step's matcher measured it.

    ``stereo.calibration["noise_sigma"]`` (one σ per view) where the stereo step recorded
    it; otherwise the same measurement again at its matches of views 0 and 1
    (:func:`semlab.noise.calibrated_noise_sigma`: :func:`semlab.subset.icgn_refine`'s
    default, Immerkær's estimate lowered to the matched subsets' residuals), so a run
    measures its noise one way, for the points and for the dense map.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
    stereo : semlab.pipeline.StereoResult
        (or any object with ``pts``, (N, V, 2) pixel positions (x, y) per view, and
        optionally ``calibration``).

    Returns
    -------
    noise : (float, float)
        Noise σ of view 0 and view 1, grey units.
    how : str
        Where it came from (for the map's notes).
    """
    from .noise import calibrated_noise_sigma

    rec = (getattr(stereo, "calibration", None) or {}).get("noise_sigma")
    if rec is not None and len(rec) >= 2 and np.all(np.isfinite(np.asarray(rec[:2], float))):
        return (float(rec[0]), float(rec[1])), "recorded by the stereo step"
    pts = np.asarray(stereo.pts, float)
    pts = pts[rows_in_views(pts, 0, 1)]
    noise = calibrated_noise_sigma(view0, view1, pts[:, 0], pts[:, 1])
    return noise, (f"calibrated on the {len(pts)} stereo matches "
                   "(semlab.noise.calibrated_noise_sigma)")
