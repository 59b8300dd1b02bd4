"""Variational refinement of the 1-D stereo parallax: robust data term, edge-preserving prior.

Under the affine SEM camera a view-0 pixel ``(x, y)`` lies in view 1 at
``(x + d, y + q)`` with ``q = e0 + e1·x + e2·y + e3·d`` (the epipolar relation, an affine
function; ``e = 0`` for a eucentric tilt about the image y axis). The unknown is the single
parallax field ``d(x, y)`` on the view-0 grid, found as the minimum of

    E(d) = Σ_p ρ_D(r_p(d) / (k σ_p)) + Σ_{p~q} ρ_H((d_p − d_q) / s)

- ``r_p`` is the difference of the **locally normalised** views (per-pixel mean and standard
  deviation over a Gaussian window, which removes the views' different gain and offset),
  view 1 sampled at the warped position; ``σ_p`` its noise, from the measured image noise
  (the matcher's, :func:`semlab.noise.calibrated_noise_sigma`: Immerkær's estimate lowered
  to the matched subsets' residuals) divided by the local standard deviations; ``k``
  (>= 1) rescales it to the residuals actually left (a robust standard deviation), which
  absorbs the model errors of interpolation and SEM contrast.
- ``ρ_D`` and ``ρ_H`` are Huber functions: outlying residuals and steps of the parallax
  (slip bands) cost linearly, so a step is not smoothed away (total variation beyond ``s``).
- ``s``, the prior scale of the parallax difference between neighbour pixels, is **not a
  tuned constant**: one rule from the measured noise sets it to the median data-only 1σ of
  the parallax of a ``15 × 15`` window, ``1 / sqrt(Σ_window J² / σ²)``: neighbour pixels
  may differ by what a subset resolves, so weak texture (large σ) is smoothed more. (An
  expectation–maximisation estimate of ``s`` was tried: on weak texture it collapses to
  over-smoothing, the grooves of slip bands vanish.)

Minimisation: from the initial map at full resolution (a coarse-to-fine pyramid was tried:
the coarse levels of weak textures drifted), several re-warps, the data term
linearised about the current warp and both Huber functions by iteratively reweighted least
squares; each linear system ``A d = b`` (``A = diag(w J²) + Gᵀ W G``, a weighted 2-D
Laplacian plus the data precision) is solved by preconditioned conjugate gradients.

1σ per pixel: ``A`` is the posterior precision of the last linearisation (data precision
from the noise, prior precision from the edge weights); its inverse's diagonal is estimated
by perturbation sampling (``x = A⁻¹ (D^½ n₁ + Gᵀ W^½ n₂)`` has covariance ``A⁻¹``), the
sample variances smoothed over a few pixels, plus the square of the smoothing's plug-in
bias ``A⁻¹ Gᵀ W G d̂`` (``sigma_mode`` for the alternatives).

Conventions: images ``[row, col]``, points ``(x, y)`` pixels, a ``roi = (x0, y0, x1, y1)``
half-open in view-0 pixels (see :mod:`semlab.heightmap`).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from scipy import ndimage

from .errors import ImageError, SemlabError
from .noise import with_seed_noise
from .stats import robust_sd

__all__ = ["VariationalParams", "ISOTROPIC", "normalise_local", "fit_epipolar", "fit_plane",
           "refine_parallax", "variational_parallax"]


@dataclass(frozen=True)
class VariationalParams:
    """Parameters of :func:`refine_parallax` (recorded in the results).

    Attributes
    ----------
    warps : int
        Re-warps (linearisations).
    irls : int
        Reweightings (linear solves) per warp.
    norm_sigma_px : float
        Gaussian σ of the window of the local mean / standard deviation normalisation.
        Smaller than a slip band's wall (2.5 px, was 5): the wall's SEM contrast differs
        between the views over a few pixels, and a window spanning the whole wall leaves
        that difference in the residual (speckle ±5° seed 2: walls 56 → 41 nm).
    grad_sigma_px : float
        Gaussian σ of the smoothing of the images for their gradient (the Jacobian).
    data_huber : float
        Residuals beyond this many noise σ have linear cost.
    smooth_huber : float
        Neighbour differences beyond this many prior scales ``s`` have linear cost (TV).
    n_samples : int
        Posterior samples for the 1σ.
    sigma_smooth_px : float
        Gaussian σ of the smoothing of the sample variances.
    cg_iter : int
        Conjugate-gradient iterations per solve (maximum); ``cg_tol`` relative residual.
    sample_tol : float
        Relative residual of the posterior samples' solves: their variance is a Monte Carlo
        estimate (``n_samples``; tens of per cent of error per pixel before smoothing), so
        1e-3 changes it far less than its own noise (≤ 2 % against exact solves, with the
        multigrid) and saves most of the iterations with the band prior; the same for the
        bias term (squared into the variance).
    step_tol : float
        Relative residual of every IRLS solve but the last, each solved for the step from the
        current map (an inexact Newton step: the next linearisation corrects its error; the
        last solve is to ``cg_tol``). 1e-2 moved the demo pair's band-prior map by 8e-5 px RMS
        (3.5e-3 px at most) against ``cg_tol`` everywhere, with half the iterations.
    margin : int
        Pixels around a ``roi`` included in the solve (the result inside the ``roi`` hardly
        depends on the images farther away); see :meth:`margin_px`.
    half_window : int
        Half size of the windows of the initial guess (:func:`semlab.heightmap.initial_guess`)
        used by :func:`variational_parallax`.
    seed : int
        Seed of the posterior samples.
    prior_scale_px : float, optional
        Prior scale ``s`` of neighbour differences, pixels; default the rule below.
    prior_window_px : int
        The rule: ``s`` = median data-only 1σ of the parallax of a ``window²`` window
        (``1 / sqrt(Σ J² / σ²)`` over the window), from the measured noise.
    sigma_mode : {"posterior+bias", "posterior", "noise", "noise+bias"}
        1σ² from the posterior covariance ``A⁻¹`` plus the square of the prior's plug-in
        bias ``A⁻¹ Gᵀ W G d̂`` (default: the pull of the smoothing at band walls, which the
        posterior of a locally linearised model misses), the posterior alone, the noise only
        (``A⁻¹ D A⁻¹``, misses the smoothing bias) or the noise plus the bias.
    solver : {"amg", "cg", "direct"}
        Each IRLS system and the posterior samples solved by conjugate gradients
        (``cg_iter``, ``cg_tol``) preconditioned by algebraic multigrid (default, ``pyamg``;
        one hierarchy serves all the posterior samples and the bias) or by Jacobi (the same
        answer to the tolerance; 1.8× slower on the 384×512 demo pair), or exactly by a sparse
        LU factor (``scipy.sparse.linalg.splu``, minimum-degree ordering; one factor serves all the
        posterior samples and the bias; ~2 s per 320² window).
    band_along, band_across : float
        The band prior: slip bands are straight traces, so where the parallax map has one
        local direction (the structure tensor of the current map, :func:`_band_field`, with
        coherence ``c`` in [0, 1]), the differences along that direction get the extra
        precision ``band_along · c² / s²`` (Huber like the others) and the isotropic prior is
        multiplied by ``1 − (1 − 1 / band_across) c²``: the profile across a band is then estimated
        from the data of a strip along it, so it needs less smoothing across. The direction
        is that of the map minus its least-squares plane (the affine part the camera
        geometry gives every pixel, e.g. a 0/+8° pair's x-scale, is no band), and the band
        term acts on that difference. ``0`` / ``1``: the isotropic prior alone
        (:data:`ISOTROPIC`). The defaults ``band_along=30, band_across=4`` (with
        ``band_window_px=16``; default since 2026-12-06, opt-in before) were chosen on one
        cell of ``benchmarks/accuracy_matrix.py`` (polished, realistic noise, ±5°; six
        settings) and then measured on all 16 textured two-view cells, the four three-view
        cells, the 8 dense-map scenes and the real four-view series: about half the height
        error of the isotropic prior on the textured cells, at ~2.5× its time
        (docs/accuracy.md, "The band prior").
    band_window_px : float
        Gaussian σ (pixels) over which the structure tensor is averaged (its inner scale, the
        smoothing of the map before its gradient, is 1.5 px).
    weight_sigma : bool
        Also the 1σ of the estimate for the surface at hand, its noise plus the prior's
        plug-in bias (``sigma_mode="noise+bias"``), as ``DenseParallax.weight_sigma_px``
        (with ``sigma_mode="posterior+bias"``: the posterior's noise part and prior part
        sampled apart, ``n_samples / 2`` solves each, so no solve more). Stage 9 of
        :func:`semlab.matching.auto_match` weights the map by it.
    """

    warps: int = 5
    irls: int = 2
    norm_sigma_px: float = 2.5
    grad_sigma_px: float = 0.5
    data_huber: float = 2.0
    smooth_huber: float = 0.1
    n_samples: int = 12
    sigma_smooth_px: float = 2.0
    cg_iter: int = 300
    cg_tol: float = 1e-5
    sample_tol: float = 1e-3
    step_tol: float = 1e-2
    margin: int = 32
    half_window: int = 7
    seed: int = 0
    prior_scale_px: float | None = None
    prior_window_px: int = 15
    sigma_mode: str = "posterior+bias"
    solver: str = "amg"
    band_along: float = 30.0
    band_across: float = 4.0
    band_window_px: float = 16.0
    weight_sigma: bool = False

    @property
    def has_band(self):
        """Whether the band prior is on (``band_along > 0`` or ``band_across != 1``)."""
        return self.band_along > 0 or self.band_across != 1

    def margin_px(self):
        """Pixels around a window that its result depends on (as ``DenseParams``): ``margin``,
        plus three ``band_window_px`` with the band prior (the reach of its structure
        tensor's window)."""
        return int(self.margin + (np.ceil(3 * self.band_window_px) if self.has_band else 0))

    # what the tiling (semlab.tiled_stereo.tiled_parallax) asks of a dense method's params
    def dense_method(self):
        """The dense method these parameters are for: :func:`variational_parallax`."""
        return variational_parallax

    def tile_px(self, tiling):
        """Core tile size of a tiled map, pixels: ``tiling.variational_tile_px`` (the
        solve's arrays are a few per pixel, and a tile's border is a seam of the prior)."""
        return int(tiling.variational_tile_px)

    def shared_calibration(self, view0, view1, seeds, calibration):
        """``calibration`` plus what every tile of one tiled map must share: the epipolar
        relation fitted once on all the ``seeds`` (image pixels, :func:`_with_seed_calibration`;
        the tiling gives each tile it in its crops' pixels) and the parallax's plane
        (least squares on the seeds' x-parallax, with three or more). A variational map
        normalises its views locally, so no B-spline level.

        Parameters
        ----------
        view0, view1 : (H, W) arrays
            Unused.
        seeds : (N, 2, 2) array or None
        calibration : dict

        Returns
        -------
        dict
            A copy.
        """
        return _with_seed_calibration(calibration, seeds)


# ------------------------------------------------------------------------------ helpers
#: The isotropic prior alone (the band prior off): ``VariationalParams(**ISOTROPIC)``
#: (read-only, so no caller changes it for the others).
ISOTROPIC = MappingProxyType({"band_along": 0.0, "band_across": 1.0})


def normalise_local(img, sigma_px, noise_sigma=None):
    """Locally normalised image ``(I − μ) / s`` and the noise σ of its pixels.

    Parameters
    ----------
    img : (H, W) array
    sigma_px : float
        Gaussian σ of the window of the local mean ``μ`` and standard deviation ``s``.
    noise_sigma : float, optional
        White-noise σ of ``img`` (grey units); default measured
        (:func:`semlab.noise.image_noise_sigma`).

    Returns
    -------
    norm : (H, W) float array
    noise : (H, W) float array
        ``noise_sigma / s``, the noise σ of ``norm``.
    """
    from .noise import image_noise_sigma

    a = np.asarray(img, float)
    if noise_sigma is None:
        noise_sigma = image_noise_sigma(a)
    mu = ndimage.gaussian_filter(a, sigma_px, mode="reflect")
    c = a - mu
    s = np.sqrt(ndimage.gaussian_filter(c * c, sigma_px, mode="reflect"))
    floor = max(1e-12, 1e-3 * float(np.median(s)), float(noise_sigma))
    s = np.maximum(s, floor)
    return c / s, float(noise_sigma) / s


def _normalised_crop(img, box, sigma_px, noise_sigma):
    """:func:`normalise_local` of ``img[y0:y1, x0:x1]`` with ``3σ`` of context around it."""
    x0, y0, x1, y1 = box
    c = int(np.ceil(3 * sigma_px))
    hgt, wid = img.shape
    ax, ay = max(0, x0 - c), max(0, y0 - c)
    n, s = normalise_local(img[ay:min(hgt, y1 + c), ax:min(wid, x1 + c)], sigma_px, noise_sigma)
    sl = (slice(y0 - ay, y1 - ay), slice(x0 - ax, x1 - ax))
    return n[sl], s[sl]


def fit_epipolar(x0, y0, x1, y1):
    """Affine epipolar relation ``y1 − y0 = e0 + e1 x0 + e2 y0 + e3 (x1 − x0)``.

    Least squares with a 3.5·MAD outlier cut (twice) over the finite matches.

    Parameters
    ----------
    x0, y0, x1, y1 : arrays of one shape
        Matched positions in views 0 and 1, pixels.

    Returns
    -------
    (4,) float array ``(e0, e1, e2, e3)``.
    """
    x0, y0, x1, y1 = (np.asarray(a, float).ravel() for a in (x0, y0, x1, y1))
    ok = np.isfinite(x0) & np.isfinite(y0) & np.isfinite(x1) & np.isfinite(y1)
    if ok.sum() < 8:
        return np.zeros(4)
    A = np.column_stack([np.ones(len(x0)), x0, y0, x1 - x0])
    b = y1 - y0
    for _ in range(3):
        e, *_ = np.linalg.lstsq(A[ok], b[ok], rcond=None)
        res = b - A @ e
        mad = robust_sd(res[ok], about=0.0)
        new = ok & (np.abs(res) <= max(3.5 * mad, 1e-9))
        if new.sum() < 8 or np.array_equal(new, ok):
            break
        ok = new
    return e


def _plane_from_moments(mx, my, cxx, cxy, cyy, mv, cxv, cyv):
    """``(c0, cx, cy)`` of the least-squares plane from the points' means and central
    second moments (per point) of ``x``, ``y`` and the values ``v``: the 2×2 normal equations
    of the centred slopes (least norm when the points are collinear); the callers ask for
    three points or more."""
    cx, cy = np.linalg.lstsq(np.array([[cxx, cxy], [cxy, cyy]]), np.array([cxv, cyv]),
                             rcond=1e-12)[0]
    return np.array([mv - cx * mx - cy * my, cx, cy])


def _lsq_plane(x, y, values):
    """``(c0, cx, cy)`` of the least-squares plane ``c0 + cx x + cy y`` through ``values``
    at the points ``(x, y)`` (1-D arrays); zeros with fewer than three points."""
    x, y, v = (np.asarray(a, float).ravel() for a in (x, y, values))
    if len(v) < 3:
        return np.zeros(3)
    # (the cross moments need no centred v: the centred coordinates sum to zero)
    xc, yc = x - x.mean(), y - y.mean()
    return _plane_from_moments(x.mean(), y.mean(), np.mean(xc * xc), np.mean(xc * yc),
                               np.mean(yc * yc), v.mean(), np.mean(xc * v), np.mean(yc * v))


def fit_plane(parallax, valid=None):
    """Least-squares plane of a parallax map.

    Parameters
    ----------
    parallax : (H, W) array
        x-parallax of every view-0 pixel, pixels (NaN allowed).
    valid : (H, W) bool array, optional
        Pixels to fit (default: the finite ones).

    Returns
    -------
    (3,) array
        ``(c0, cx, cy)``: the plane ``c0 + cx x + cy y`` (x, y view-0 pixels); zeros with
        fewer than three valid pixels.
    """
    d = np.asarray(parallax, float)
    if d.ndim != 2:
        raise SemlabError(f"fit_plane: parallax must be an (H, W) map, got shape {d.shape}")
    ok = np.isfinite(d) if valid is None else (np.asarray(valid, bool) & np.isfinite(d))
    n = int(ok.sum())
    if n < 3:
        return np.zeros(3)
    # sums over the pixel grid by rows and columns (no (N, 3) design matrix: a whole 12.6 Mpx
    # map's would be 0.3 GB), moments taken about the mean pixel for conditioning (the valid
    # pixels' centred coordinates sum to zero, so the values need no centring)
    ix, iy = np.arange(d.shape[1], dtype=float), np.arange(d.shape[0], dtype=float)
    cols, rows = ok.sum(axis=0), ok.sum(axis=1)
    mx, my = cols @ ix / n, rows @ iy / n
    ix, iy = ix - mx, iy - my
    dz = np.where(ok, d, 0.0)
    mv = dz.sum() / n
    cxx, cyy = cols @ (ix * ix) / n, rows @ (iy * iy) / n
    cxy = iy @ (ok @ ix) / n
    cxv, cyv = (dz @ ix).sum() / n, iy @ dz.sum(axis=1) / n
    return _plane_from_moments(mx, my, cxx, cxy, cyy, mv, cxv, cyv)


def _with_seed_calibration(calibration, seeds):
    """A copy of ``calibration`` with ``"epipolar"`` fitted on ``seeds`` ((N, 2, 2) matches,
    :func:`fit_epipolar`) when it has none and there are 8 seeds (the sparse matches fix
    the relation far better than the flow's y), and ``"parallax_plane"`` (the seeds'
    x-parallax's plane, :func:`_lsq_plane`) when it has none and there are 3."""
    cal = dict(calibration or {})
    if cal.get("epipolar") is None and seeds is not None and len(seeds) >= 8:
        sd = np.asarray(seeds, float)
        cal["epipolar"] = fit_epipolar(sd[:, 0, 0], sd[:, 0, 1], sd[:, 1, 0],
                                       sd[:, 1, 1]).tolist()
    if cal.get("parallax_plane") is None and seeds is not None:
        sd = np.asarray(seeds, float).reshape(len(seeds), -1)
        sd = sd[np.all(np.isfinite(sd), axis=1)]
        if len(sd) >= 3:
            cal["parallax_plane"] = _lsq_plane(sd[:, 0], sd[:, 1], sd[:, 2] - sd[:, 0]).tolist()
    return cal


def _grad_x(a):
    g = np.zeros_like(a)
    g[:, 1:-1] = 0.5 * (a[:, 2:] - a[:, :-2])
    return g


def _grad_y(a):
    g = np.zeros_like(a)
    g[1:-1] = 0.5 * (a[2:] - a[:-2])
    return g


def _diff(x, axis):
    """Forward difference along ``axis`` (``n − 1`` values)."""
    return np.diff(x, axis=axis)


def _diff_t(f, axis, shape):
    """Adjoint of :func:`_diff`: scatter ``f`` back onto an array of ``shape``."""
    out = np.zeros(shape)
    if axis == 1:
        out[:, 1:] += f
        out[:, :-1] -= f
    else:
        out[1:] += f
        out[:-1] -= f
    return out


class _Prior:
    """The prior's weighted differences at one linearisation: ``Gᵀ W G`` with ``G`` the first
    differences along x (weights ``wh``, ``(H, W − 1)``) and y (``wv``, ``(H − 1, W)``) and,
    with the band prior, the difference along the local band direction (``gt``, a sparse
    ``((H − 1)(W − 1), H W)`` matrix, weights ``wt``)."""

    def __init__(self, wh, wv, gt=None, wt=None, gt_plane=None):
        self.wh, self.wv, self.gt, self.wt = wh, wv, gt, wt
        self.gt_plane = gt_plane

    def rhs(self, shape):
        """``Gtᵀ Wt (Gt p)``: the band term acts on the map minus its plane ``p`` (its
        difference along the band is ``Gt (d − p)``), which adds this to the normal equations'
        right-hand side (zero without the band prior)."""
        if self.gt is None or self.gt_plane is None:
            return 0.0
        return (self.gt.T @ (self.wt * self.gt_plane)).reshape(shape)

    def apply(self, x):
        """``Gᵀ W G x``."""
        out = _diff_t(self.wh * _diff(x, 1), 1, x.shape) + _diff_t(self.wv * _diff(x, 0), 0,
                                                                     x.shape)
        if self.gt is not None:
            out += (self.gt.T @ (self.wt * (self.gt @ x.ravel()))).reshape(x.shape)
        return out

    def diag(self, shape):
        """The diagonal of ``Gᵀ W G``."""
        d = np.zeros(shape)
        d[:, :-1] += self.wh
        d[:-1] += self.wv
        d[:, 1:] += self.wh
        d[1:] += self.wv
        if self.gt is not None:
            d += (self.gt.multiply(self.gt).T @ self.wt).reshape(shape)
        return d

    def matrix(self, shape):
        """``Gᵀ W G`` as a sparse matrix on the C-ordered grid of ``shape``."""
        from scipy import sparse

        gh, gv = _diff_matrix(shape, 1), _diff_matrix(shape, 0)
        m = gh.T @ sparse.diags(self.wh.ravel()) @ gh + gv.T @ sparse.diags(self.wv.ravel()) @ gv
        if self.gt is not None:
            m = m + self.gt.T @ sparse.diags(self.wt) @ self.gt
        return m

    def sample(self, rng, shape):
        """``Gᵀ W^½ n`` for standard normal ``n``: the prior's part of a posterior sample."""
        out = _diff_t(np.sqrt(self.wh) * rng.standard_normal(self.wh.shape), 1, shape)
        out += _diff_t(np.sqrt(self.wv) * rng.standard_normal(self.wv.shape), 0, shape)
        if self.gt is not None:
            out += (self.gt.T @ (np.sqrt(self.wt) * rng.standard_normal(len(self.wt)))
                    ).reshape(shape)
        return out


def _cg(D, prior, b, x0, n_iter, tol):
    """Jacobi-preconditioned conjugate gradients for ``(diag(D) + Gᵀ W G) x = b``."""
    M = 1.0 / np.maximum(D + prior.diag(D.shape), 1e-12)
    x = x0.copy()
    r = b - (D * x + prior.apply(x))
    z = M * r
    p = z.copy()
    rz = float(np.sum(r * z))
    bn = float(np.sqrt(np.sum(b * b))) or 1.0
    for _ in range(int(n_iter)):
        Ap = D * p + prior.apply(p)
        alpha = rz / max(float(np.sum(p * Ap)), 1e-300)
        x += alpha * p
        r -= alpha * Ap
        if np.sqrt(np.sum(r * r)) < tol * bn:
            break
        z = M * r
        rz_new = float(np.sum(r * z))
        p = z + (rz_new / max(rz, 1e-300)) * p
        rz = rz_new
    return x


def _diff_matrix(shape, axis):
    """Sparse matrix of :func:`_diff` along ``axis`` on a C-ordered ``shape`` grid."""
    from scipy import sparse

    n, m = shape
    length = shape[axis]
    d1 = sparse.diags([np.full(length - 1, -1.0), np.full(length - 1, 1.0)], [0, 1],
                      shape=(length - 1, length))
    if axis == 1:
        return sparse.kron(sparse.identity(n), d1, format="csr")
    return sparse.kron(d1, sparse.identity(m), format="csr")


def _matrix(D, prior):
    """``A = diag(D) + Gᵀ W G`` as a sparse CSR matrix on the C-ordered grid of ``D``."""
    from scipy import sparse

    return (sparse.diags(D.ravel()) + prior.matrix(D.shape)).tocsr()


def _factor(D, prior):
    """Sparse LU factor of ``A = diag(D) + Gᵀ W G``: a function ``b -> A⁻¹ b``."""
    from scipy.sparse.linalg import splu

    lu = splu(_matrix(D, prior).tocsc(), permc_spec="MMD_AT_PLUS_A",
              options=dict(SymmetricMode=True))
    return lambda b: lu.solve(np.asarray(b, float).ravel()).reshape(D.shape)


def _amg(D, prior, n_iter, tol):
    """Conjugate gradients preconditioned by a classical (Ruge–Stüben) algebraic multigrid
    hierarchy of ``A`` (``pyamg``): a function ``b, x0 -> A⁻¹ b`` to the relative residual
    ``tol``. ``A`` is a diagonal plus a weighted grid Laplacian (an M-matrix, what classical
    AMG is made for): 5–10 iterations instead of Jacobi's ~170 on a 384×512 view. With the
    band prior ``A`` is not an M-matrix: smoothed aggregation preconditions CG instead."""
    import pyamg
    from pyamg.krylov import cg

    A = _matrix(D, prior)
    if prior.gt is None:
        ml = pyamg.ruge_stuben_solver(A)

        def solve(b, x0=None, rtol=None):
            b = np.asarray(b, float)
            x = ml.solve(b.ravel(), x0=None if x0 is None else np.asarray(x0, float).ravel(),
                         tol=tol if rtol is None else rtol, maxiter=int(n_iter), accel="cg")
            return x.reshape(b.shape)
        return solve
    # the band term's oblique couplings make positive off-diagonal entries (not an M-matrix):
    # smoothed aggregation, a V-cycle preconditioning conjugate gradients (~45 iterations
    # to 1e-5 on a 384×512 view with band_along = 30; Ruge–Stüben on the M-matrix with those
    # entries moved to the diagonal needs as many); the prolongation's Jacobi smoother
    # weighted locally (row sums: no eigenvalue estimate, a quarter of the set-up time and
    # ~15 % fewer iterations than the spectral-radius weight on that view)
    ml = pyamg.smoothed_aggregation_solver(A, symmetry="symmetric",
                                           smooth=("jacobi", {"weighting": "local"}))
    M = ml.aspreconditioner(cycle="V")

    def solve(b, x0=None, rtol=None):
        b = np.asarray(b, float)
        x, _ = cg(A, b.ravel(), x0=None if x0 is None else np.asarray(x0, float).ravel(),
                  tol=tol if rtol is None else rtol, maxiter=int(n_iter), M=M)
        return x.reshape(b.shape)
    return solve


def _linear_solver(D, prior, prm):
    """``b, x0 -> A⁻¹ b`` by the method of ``prm.solver`` (one factor or multigrid hierarchy
    reused for all b)."""
    if prm.solver == "direct":
        f = _factor(D, prior)
        return lambda b, x0=None, rtol=None: f(b)
    if prm.solver == "amg":
        return _amg(D, prior, prm.cg_iter, prm.cg_tol)
    return lambda b, x0=None, rtol=None: _cg(D, prior, b,
                                             np.zeros_like(b) if x0 is None else x0,
                                             prm.cg_iter, prm.cg_tol if rtol is None else rtol)


def _huber_w(t, c):
    """IRLS weight ``ρ'(t)/t`` of the Huber function with threshold ``c``."""
    a = np.abs(t)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))


class _Pair:
    """The normalised views, their smoothed gradients and view 1's splines."""

    def __init__(self, n0, s0, n1, s1, grad_sigma):
        self.n0, self.noise0, self.noise1 = n0, s0, s1
        self.shape1 = n1.shape
        self.c1 = ndimage.spline_filter(n1, order=3, mode="mirror")
        g0 = ndimage.gaussian_filter(n0, grad_sigma, mode="reflect")
        g1 = ndimage.gaussian_filter(n1, grad_sigma, mode="reflect")
        self.gx0 = _grad_x(g0)
        self.cgx1 = ndimage.spline_filter(_grad_x(g1), order=3, mode="mirror")
        self.cgy1 = ndimage.spline_filter(_grad_y(g1), order=3, mode="mirror")

    def warp(self, d, e):
        """Warped view 1, its derivative along ``d``, its noise σ and an inside mask."""
        hgt, wid = self.n0.shape
        yy, xx = np.mgrid[0:hgt, 0:wid].astype(float)
        xs = xx + d
        ys = yy + e[0] + e[1] * xx + e[2] * yy + e[3] * d
        h1, w1 = self.shape1
        inside = (xs >= 0) & (xs <= w1 - 1) & (ys >= 0) & (ys <= h1 - 1)
        c = [ys, xs]
        kw = dict(order=3, prefilter=False, mode="mirror")
        warped = ndimage.map_coordinates(self.c1, c, **kw)
        jx = ndimage.map_coordinates(self.cgx1, c, **kw)
        jy = ndimage.map_coordinates(self.cgy1, c, **kw)
        J = 0.5 * (jx + self.gx0) + e[3] * jy
        s1 = ndimage.map_coordinates(self.noise1, c, order=1, mode="nearest")
        return warped, J, np.sqrt(self.noise0 ** 2 + s1 ** 2), inside


def _fill(p, ok):
    """Fill the pixels outside ``ok`` with their nearest valid value (0 if none)."""
    if ok.all():
        return p.copy()
    if not ok.any():
        return np.zeros_like(p)
    _, (iy, ix) = ndimage.distance_transform_edt(~ok, return_indices=True)
    return p[iy, ix]


def _check_image_pair(img0, img1, names, min_px, purpose):
    """The two images as arrays, each 2-D of at least ``min_px`` pixels a side and finite,
    of one shape (an :class:`ImageError` naming ``names`` and ``purpose`` otherwise)."""
    a, b = np.asarray(img0), np.asarray(img1)
    for name, v in zip(names, (a, b)):
        if v.ndim != 2 or min(v.shape) < min_px:
            raise ImageError(f"{name} must be a 2D image of at least {min_px}×{min_px} pixels, "
                             f"got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            raise ImageError(f"{name} holds NaN/inf pixels: replace them before {purpose}")
    if a.shape != b.shape:
        raise ImageError(f"{names[0]} and {names[1]} must have one shape, got {a.shape} and "
                         f"{b.shape}")
    return a, b


def _check_inputs(view0, view1, parallax0, valid0):
    a, b = _check_image_pair(view0, view1, ("view0", "view1"), 8, "refining the parallax")
    p = np.asarray(parallax0, float)
    if p.shape[:2] != a.shape or p.ndim not in (2, 3) or (p.ndim == 3 and p.shape[2] != 2):
        raise SemlabError(f"parallax0 must be the (H, W) = {a.shape} x-parallax x1 - x0 of every "
                          f"view-0 pixel (or (H, W, 2) with y1 - y0), got shape {p.shape}")
    v = np.ones(a.shape, bool) if valid0 is None else np.asarray(valid0, bool)
    if v.shape != a.shape:
        raise SemlabError(f"valid0 must be an (H, W) = {a.shape} bool array, got {v.shape}")
    return a.astype(float), b.astype(float), p, v


# ------------------------------------------------------------------------------ main
def refine_parallax(view0, view1, parallax0, valid0=None, epipolar=None, roi=None, params=None,
                    noise_sigma=None, return_info=False, plane=None):
    """Variational refinement of the x-parallax of the view-0 pixels of ``roi``.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
        The two views (whole images).
    parallax0 : (H, W) or (H, W, 2) array
        Initial parallax ``x1 − x0`` of every view-0 pixel, pixels (e.g. from
        :func:`semlab.heightmap.initial_guess` or a subset map), to about a pixel; with a
        second channel ``y1 − y0``, from which the epipolar relation is fitted. NaN allowed.
    valid0 : (H, W) bool array, optional
        Where ``parallax0`` holds; elsewhere it is filled from the nearest valid pixel.
    epipolar : (4,) sequence, optional
        ``(e0, e1, e2, e3)`` of ``y1 − y0 = e0 + e1 x0 + e2 y0 + e3 d``; default fitted to
        the second channel of ``parallax0``, or zeros.
    roi : (x0, y0, x1, y1), optional
        Half-open window of view-0 pixels to return; the solve covers it plus
        ``params.margin_px()``.
    params : VariationalParams, optional
    noise_sigma : (2,) floats, optional
        White-noise σ of the two views (grey units); default measured as the matcher does
        (:func:`semlab.noise.calibrated_noise_sigma`: Immerkær's estimate lowered to the
        residuals of 21×21 subsets matched on an 8 px grid of ``roi``, started at
        ``parallax0``).
    return_info : bool
        Also return a dict of the measured quantities (prior scale, noise factor, ...).
    plane : (3,) sequence, optional
        ``(c0, cx, cy)`` of the parallax's plane ``c0 + cx x0 + cy y0`` (image pixels): the
        affine part the band prior leaves out (:func:`_prior_weights`); default the
        least-squares plane of ``parallax0`` where valid (the whole image, so a ``roi``
        gets the plane of the whole call); unused (and not fitted) without the band prior.

    Notes
    -----
    Tiles: the solve of a ``roi`` sees its ``margin_px`` surroundings only; pass one
    ``epipolar``, ``noise_sigma`` and ``plane`` (and ``params.prior_scale_px``, the
    ``prior_scale_px`` of ``info`` of a representative call) to every tile so they share the
    calibration.

    Returns
    -------
    parallax : (h, w) float array
        Refined ``x1 − x0`` on the ``roi`` grid, pixels (NaN where not valid).
    sigma : (h, w) float array
        Its 1σ, pixels.
    valid : (h, w) bool array
        Pixels whose match lies inside view 1.
    info : dict, only with ``return_info``.

    Raises
    ------
    ImageError
        NaN/inf pixels or views of different shapes.
    SemlabError
        ``parallax0`` / ``valid0`` / ``roi`` of the wrong shape.
    """
    from .heightmap import _check_roi

    prm = params or VariationalParams()
    if prm.solver not in ("amg", "cg", "direct"):
        raise SemlabError(f"VariationalParams.solver must be 'amg', 'cg' or 'direct', got "
                          f"{prm.solver!r}")
    if prm.sigma_mode not in ("posterior", "noise", "noise+bias", "posterior+bias"):
        raise SemlabError(f"VariationalParams.sigma_mode must be 'posterior', 'noise', "
                          f"'noise+bias' or 'posterior+bias', got {prm.sigma_mode!r}")
    if not (prm.band_along >= 0 and prm.band_across >= 1 and prm.band_window_px > 0):
        raise SemlabError(f"VariationalParams: band_along must be >= 0, band_across >= 1 and "
                          f"band_window_px > 0, got {prm.band_along!r}, {prm.band_across!r}, "
                          f"{prm.band_window_px!r}")
    v0, v1, p0, ok0 = _check_inputs(view0, view1, parallax0, valid0)
    hgt, wid = v0.shape
    roi = _check_roi(roi, v0.shape)
    if p0.ndim == 3:
        py = p0[..., 1]
        p0 = p0[..., 0]
    else:
        py = None
    ok0 = ok0 & np.isfinite(p0)
    if epipolar is None:
        if py is not None:
            yy, xx = np.mgrid[0:hgt, 0:wid].astype(float)
            m = ok0 & np.isfinite(py)
            epipolar = fit_epipolar(xx[m], yy[m], xx[m] + p0[m], yy[m] + py[m])
        else:
            epipolar = np.zeros(4)
    e = np.asarray(epipolar, float)
    if plane is None:       # only the band prior uses it (a whole-image fit is not free)
        plane = fit_plane(p0, ok0) if prm.has_band else np.zeros(3)
    plane = np.asarray(plane, float)
    if plane.shape != (3,) or not np.all(np.isfinite(plane)):
        raise SemlabError(f"plane must be 3 finite numbers (c0, cx, cy), got {plane!r}")
    if noise_sigma is None:
        noise_sigma = _grid_noise_sigma(v0, v1, p0, ok0, roi)
    # the solve window: roi + margin in view 0, view 1 cropped around its matches
    m = prm.margin_px()
    wx0, wy0 = max(0, roi[0] - m), max(0, roi[1] - m)
    wx1, wy1 = min(wid, roi[2] + m), min(hgt, roi[3] + m)
    d = _fill(p0, ok0)[wy0:wy1, wx0:wx1]
    yyw, xxw = np.mgrid[wy0:wy1, wx0:wx1].astype(float)
    qy = e[0] + e[1] * xxw + e[2] * yyw + e[3] * d
    pad = 12
    cx0 = int(max(0, np.floor(np.min(xxw + d)) - pad))
    cx1 = int(min(wid, np.ceil(np.max(xxw + d)) + pad + 1))
    cy0 = int(max(0, np.floor(np.min(yyw + qy)) - pad))
    cy1 = int(min(hgt, np.ceil(np.max(yyw + qy)) + pad + 1))
    n0, s0 = _normalised_crop(v0, (wx0, wy0, wx1, wy1), prm.norm_sigma_px, noise_sigma[0])
    n1, s1 = _normalised_crop(v1, (cx0, cy0, cx1, cy1), prm.norm_sigma_px, noise_sigma[1])
    # window pixel (j, i) is view-0 (j + wx0, i + wy0); its match in the view-1 crop is at
    # (j + d', i + ew0 + e1 j + e2 i + e3 d') with d' = d + wx0 - cx0
    dx_off, dy_off = float(wx0 - cx0), float(wy0 - cy0)
    ew = np.array([e[0] + e[1] * wx0 + e[2] * wy0 + dy_off - e[3] * dx_off, e[1], e[2], e[3]])
    info = {"epipolar": e.tolist(), "noise_sigma": [float(noise_sigma[0]),
                                                    float(noise_sigma[1])]}
    if prm.has_band:
        info["parallax_plane"] = plane.tolist()
    s_init = prm.prior_scale_px
    pw = plane[0] + plane[1] * xxw + plane[2] * yyw + dx_off     # in the solve's terms
    dd, var, inside = _solve(n0, s0, n1, s1, d + dx_off, ew, s_init, prm, info, pw)
    dd = dd - dx_off
    sl = (slice(roi[1] - wy0, roi[3] - wy0), slice(roi[0] - wx0, roi[2] - wx0))
    sig = np.sqrt(var)
    valid = inside[sl] & np.isfinite(dd[sl]) & np.isfinite(sig[sl])
    par = np.where(valid, dd[sl], np.nan)
    sg = np.where(valid, sig[sl], np.nan)
    info["_zncc"] = np.where(valid, info["_zncc"][sl], -1.0)
    if "_weight_var" in info:
        info["_weight_sigma"] = np.where(valid, np.sqrt(info.pop("_weight_var")[sl]), np.nan)
    if return_info:
        return par, sg, valid, info
    return par, sg, valid


def _grid_noise_sigma(v0, v1, p0, ok0, roi, step=8):
    """:func:`semlab.noise.calibrated_noise_sigma` on an ``step`` px grid of ``roi``, the
    matches started at the initial parallax (its y part from the flow is not needed: IC-GN
    finds it)."""
    from .noise import calibrated_noise_sigma

    yy, xx = np.mgrid[roi[1]:roi[3]:step, roi[0]:roi[2]:step]
    yy, xx = yy.ravel(), xx.ravel()
    keep = ok0[yy, xx]
    pts = np.column_stack([xx[keep], yy[keep]]).astype(float)
    cur = pts + np.column_stack([p0[yy[keep], xx[keep]], np.zeros(keep.sum())])
    return calibrated_noise_sigma(v0, v1, pts, cur)


def _window_scale(lv, d, e, window):
    """Prior scale from the noise: median data-only 1σ of the parallax of a window.

    ``1 / sqrt(Σ_window J² / σ²)``: neighbour parallaxes may differ by what a subset of
    ``window²`` pixels resolves, so features a subset sees are not smoothed away.
    """
    _, J, sig, inside = lv.warp(d, e)
    D = np.where(inside, J * J / sig ** 2, 0.0)
    w = max(1, int(window))
    info = ndimage.uniform_filter(D, w, mode="reflect") * w * w
    good = info[inside]
    return float(np.median(1.0 / np.sqrt(np.maximum(good, 1e-12)))) if good.size else 1.0


def _band_field(d, window_px):
    """The local band direction of a parallax map ``d``: the structure tensor of its gradient
    (``d`` smoothed over 1.5 px) averaged over a Gaussian of σ ``window_px`` (Bigun &
    Granlund 1987; Weickert, Anisotropic Diffusion in Image Processing, 1998, ch. 2).

    Returns
    -------
    gt : sparse ((H − 1)(W − 1), H W) matrix
        The derivative along the band direction ``(cos a, sin a)`` (perpendicular to the
        tensor's main eigenvector) at the centre of each cell of four pixels, from the cell's
        gradient ``(∂x, ∂y)`` (the mean of its two differences along x, and along y; second
        order there: the forward differences of one pixel would add half the across-band
        curvature, which is large at a band's wall).
    coherence : ((H − 1) (W − 1),) array
        ``(λ₁ − λ₂) / (λ₁ + λ₂)`` of the tensor, in [0, 1]: 1 where the map has one direction,
        0 where it has none (noise, an isotropic bump).
    """
    from scipy import sparse

    hgt, wid = d.shape
    g = ndimage.gaussian_filter(d, 1.5, mode="reflect")
    gx, gy = _grad_x(g), _grad_y(g)
    avg = lambda a: ndimage.gaussian_filter(a, window_px, mode="reflect")  # noqa: E731
    jxx, jxy, jyy = avg(gx * gx), avg(gx * gy), avg(gy * gy)
    cell = lambda a: 0.25 * (a[:-1, :-1] + a[:-1, 1:] + a[1:, :-1] + a[1:, 1:])  # noqa: E731
    # the direction at the cell centre (the tensor averaged over its corners: no 180° wrap)
    jxx, jxy, jyy = cell(jxx), cell(jxy), cell(jyy)
    coh = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2) / np.maximum(jxx + jyy, 1e-300)
    along = 0.5 * np.arctan2(2 * jxy, jxx - jyy) + 0.5 * np.pi
    c, sn = 0.5 * np.cos(along).ravel(), 0.5 * np.sin(along).ravel()
    ii, jj = np.mgrid[0:hgt - 1, 0:wid - 1]
    p = (ii * wid + jj).ravel()
    rows = np.tile(np.arange(len(p)), 4)
    # c ∂x + s ∂y, ∂x = ½(d01 − d00 + d11 − d10), ∂y = ½(d10 − d00 + d11 − d01)
    gt = sparse.csr_matrix((np.concatenate([-c - sn, c - sn, sn - c, c + sn]),
                            (rows, np.concatenate([p, p + 1, p + wid, p + wid + 1]))),
                           shape=(len(p), hgt * wid))
    return gt, np.clip(coh.ravel(), 0.0, 1.0)


def _prior_weights(d, s, prm, plane):
    """IRLS weights of the prior at the map ``d`` (Huber with threshold ``prm.smooth_huber``
    prior scales ``s``), with the band prior of ``prm`` (see :class:`VariationalParams`) on
    ``d`` minus ``plane`` (an array of ``d``'s shape)."""
    c = prm.smooth_huber
    wh = _huber_w(_diff(d, 1) / s, c) / s ** 2
    wv = _huber_w(_diff(d, 0) / s, c) / s ** 2
    if not prm.has_band:
        return _Prior(wh, wv)
    # the bands are in the relief: the parallax minus its plane (the affine part every pixel
    # has from the camera geometry, e.g. a 0/+8° pair's x-scale, would otherwise give the
    # whole map one "band" direction across x, and a pull on its slope); one plane for the
    # whole call (or tiled map: its calibration), not the window's, so tiles agree
    hgt, wid = d.shape
    gt, coh = _band_field(d - plane, prm.band_window_px)
    c2 = np.ones(d.shape)
    c2[:-1, :-1] = coh.reshape(hgt - 1, wid - 1) ** 2
    iso = 1.0 - (1.0 - 1.0 / prm.band_across) * c2
    gp = gt @ plane.ravel()
    wt = prm.band_along * c2[:-1, :-1].ravel() * _huber_w((gt @ d.ravel() - gp) / s, c) / s ** 2
    return _Prior(wh * iso[:, :-1], wv * iso[:-1, :], gt, wt, gp)


def _sample_variance(D, weights, prm, rng, n, prior=True, split=False):
    """Per-pixel variance ``mean(x²)`` of ``n`` perturbation samples
    ``x = A⁻¹ (D^½ n₁ + Gᵀ W^½ n₂)``, ``A = diag(D) + Gᵀ W G``, and the solver of ``A``.

    With ``prior`` they are posterior samples, ``x ~ N(0, A⁻¹)``; without (``n₂ = 0``),
    ``x ~ N(0, A⁻¹ D A⁻¹)``, the noise of the estimate for a fixed surface. The squares are
    summed as the samples come (one image in memory, not ``n``: a 1216² tile of stage 9 in
    tiled matching held twelve). With ``prior`` and ``split``, the two independent parts of
    the posterior, ``A⁻¹ D^½ n₁`` (the noise) and ``A⁻¹ Gᵀ W^½ n₂``, are sampled apart, half
    the samples each, and the posterior variance is the sum of their variances: the noise
    part's variance comes with it at no extra solve (``(var, var_noise), solve``).
    """
    solve = _linear_solver(D, weights, prm)
    if prior and split:
        n1 = max(int(n) - int(n) // 2, 1)
        n2 = max(int(n) // 2, 1)
        v1 = sum(solve(np.sqrt(D) * rng.standard_normal(D.shape), rtol=prm.sample_tol) ** 2
                 for _ in range(n1)) / n1
        v2 = sum(solve(weights.sample(rng, D.shape), rtol=prm.sample_tol) ** 2
                 for _ in range(n2)) / n2
        return (v1 + v2, v1), solve
    acc = np.zeros(D.shape)
    for _ in range(int(n)):
        b = np.sqrt(D) * rng.standard_normal(D.shape)
        if prior:
            b += weights.sample(rng, D.shape)
        x = solve(b, rtol=prm.sample_tol)
        acc += x * x
    return acc / max(int(n), 1), solve


def _solve(n0, s0, n1, s1, d, e, s, prm, info, plane):
    """IRLS minimisation from the initial map, then the variance of the estimate."""
    lv = _Pair(n0, s0, n1, s1, prm.grad_sigma_px)
    dl = d.copy()
    rng = np.random.default_rng(prm.seed)
    if s is None:
        s = _window_scale(lv, dl, e, prm.prior_window_px)
        info["prior_rule"] = f"data-only 1σ of a {prm.prior_window_px}-px window"
    k = 1.0
    for iw in range(prm.warps):
        w1, J, sig, inside = lv.warp(dl, e)
        r0 = w1 - lv.n0
        tin = (r0 / sig)[inside]
        k = max(0.25, robust_sd(tin)) if tin.size else 1.0
        dw = dl.copy()
        for ii in range(prm.irls):
            last = iw == prm.warps - 1 and ii == prm.irls - 1
            rl = r0 + J * (dl - dw)          # residual linearised about the warp
            wd = np.where(inside, _huber_w(rl / (k * sig), prm.data_huber)
                          / (k * sig) ** 2, 0.0)
            D = wd * J * J
            pw = _prior_weights(dl, s, prm, plane)
            # solved for the step from the current map, so that the tolerance is relative to
            # the step (not to the whole parallax): ``step_tol`` before the last solve (an
            # inexact Newton step, the next linearisation corrects it), ``cg_tol`` for it
            res = D * dw - wd * J * r0 + pw.rhs(D.shape) - (D * dl + pw.apply(dl))
            dl = dl + _linear_solver(D, pw, prm)(res, np.zeros_like(dl),
                                                 prm.cg_tol if last else prm.step_tol)
    # posterior variance at the last linearisation
    w1, J, sig, inside = lv.warp(dl, e)
    r0 = w1 - lv.n0
    wd = np.where(inside, _huber_w(r0 / (k * sig), prm.data_huber) / (k * sig) ** 2, 0.0)
    D = wd * J * J
    post = prm.sigma_mode.startswith("posterior")
    weights = _prior_weights(dl, s, prm, plane)
    split = prm.weight_sigma and post
    var, solve = _sample_variance(D, weights, prm, rng, prm.n_samples, post, split)
    # the weight's variance: the noise part (without the prior's samples, that is all of them)
    var, var_w = var if split else (var, var if prm.weight_sigma else None)
    with_bias = prm.sigma_mode.endswith("+bias")
    if with_bias or var_w is not None:
        # the prior's pull on the estimate: bias = -A⁻¹ Gᵀ W G d (plug-in with d = d̂; the
        # band term's on d̂ minus its plane)
        b2 = solve(weights.apply(dl) - weights.rhs(dl.shape), rtol=prm.sample_tol) ** 2
        var = var + b2 if with_bias else var
        var_w = var_w + b2 if var_w is not None else None
    if prm.sigma_smooth_px > 0:
        var = ndimage.gaussian_filter(var, prm.sigma_smooth_px, mode="reflect")
        if var_w is not None:
            var_w = ndimage.gaussian_filter(var_w, prm.sigma_smooth_px, mode="reflect")
    if var_w is not None:
        info["_weight_var"] = var_w
    g = lambda a: ndimage.gaussian_filter(a, prm.norm_sigma_px, mode="reflect")  # noqa: E731
    with np.errstate(invalid="ignore", divide="ignore"):
        info["_zncc"] = g(lv.n0 * w1) / np.sqrt(g(lv.n0 ** 2) * g(w1 ** 2))
    info.update(prior_scale_px=float(s), noise_factor=float(k),
                median_sigma_px=float(np.median(np.sqrt(var))))
    return dl, var, inside


def variational_parallax(view0, view1, seeds=None, roi=None, params=None, guess=None,
                         calibration=None, progress=False):
    """Dense correspondences of the view-0 pixels of ``roi`` by :func:`refine_parallax`.

    Same signature and result as :func:`semlab.heightmap.dense_parallax` (so
    :func:`semlab.tiled_stereo.tiled_parallax` can tile it with ``method=``): the initial
    guess is :func:`semlab.heightmap.initial_guess` (DIS flow after the seeds' dense prior),
    the x-parallax is refined, ``y1`` follows from the fitted epipolar relation.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
    seeds : (N, 2, 2) array, optional
        Sparse matches ``[:, v] = (x, y)`` in view ``v``.
    roi : (x0, y0, x1, y1), optional
    params : VariationalParams, optional
    guess : (H, W, 2) array or the tuple of ``initial_guess``, optional
        View-1 positions of every view-0 pixel (whole-image grid); overrides the flow.
    calibration : dict, optional
        ``noise_sigma`` (2,), ``epipolar`` (4,), ``prior_scale_px``, ``parallax_plane``
        (3,): shared between tiles; missing ones are measured (the epipolar relation from
        ``seeds`` when there are 8, else from the flow; the prior scale in the call's window;
        the plane from the seeds when there are 3, else from the initial guess,
        :func:`fit_plane`).
    progress : bool
        Unused (the signature of ``dense_parallax``).

    Returns
    -------
    semlab.heightmap.DenseParallax
        ``sigma_scale`` is the noise factor ``k``; ``zncc`` the local correlation of the
        normalised views after the warp (Gaussian window ``norm_sigma_px``).
    """
    from dataclasses import replace

    from .heightmap import DenseParallax, _check_roi, initial_guess

    prm = params or VariationalParams()
    v0 = np.asarray(view0, float)
    hgt, wid = v0.shape[:2] if v0.ndim == 2 else (0, 0)
    if guess is None:
        _check_inputs(view0, view1, np.zeros(v0.shape), None)
        roi_c = _check_roi(roi, v0.shape)
        if seeds is None and roi_c != (0, 0, wid, hgt):
            # the flow of the window only (the result depends on it alone)
            m = prm.margin_px() + 4 * prm.half_window
            wx0, wy0 = max(0, roi_c[0] - m), max(0, roi_c[1] - m)
            wx1, wy1 = min(wid, roi_c[2] + m), min(hgt, roi_c[3] + m)
            gw, _, _ = initial_guess(v0[wy0:wy1, wx0:wx1],
                                     np.asarray(view1, float)[wy0:wy1, wx0:wx1], None,
                                     prm.half_window)
            g = np.full((hgt, wid, 2), np.nan)
            g[wy0:wy1, wx0:wx1] = gw + np.array([wx0, wy0], float)
        else:
            g, _, _ = initial_guess(v0, np.asarray(view1, float), seeds, prm.half_window)
    else:
        g = np.asarray(guess[0] if isinstance(guess, tuple) else guess, float)
        if g.shape != (hgt, wid, 2):
            raise SemlabError(f"guess must be an (H, W, 2) = ({hgt}, {wid}, 2) array of view-1 "
                              f"positions or the tuple of initial_guess, got shape {g.shape}")
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(float)
    p0 = np.stack([g[..., 0] - xx, g[..., 1] - yy], -1)
    cal = _with_seed_calibration(calibration, seeds)     # (a copy)
    cal = with_seed_noise(cal, view0, view1, seeds)   # the matcher's noise at the seeds
    if cal.get("prior_scale_px") is not None and prm.prior_scale_px is None:
        prm = replace(prm, prior_scale_px=float(cal["prior_scale_px"]))
    par, sig, valid, info = refine_parallax(view0, view1, p0, np.all(np.isfinite(p0), -1),
                                            epipolar=cal.get("epipolar"), roi=roi, params=prm,
                                            noise_sigma=cal.get("noise_sigma"),
                                            plane=cal.get("parallax_plane"),
                                            return_info=True)
    roi = _check_roi(roi, v0.shape)
    gx, gy = xx[roi[1]:roi[3], roi[0]:roi[2]], yy[roi[1]:roi[3], roi[0]:roi[2]]
    e = info["epipolar"]
    nanv = lambda a: np.where(valid, a, np.nan)  # noqa: E731
    zncc = info.pop("_zncc")
    wsig = info.pop("_weight_sigma", None)
    cal.update({k: np.asarray(v).tolist() for k, v in info.items()
                if k in ("noise_sigma", "epipolar", "prior_scale_px", "noise_factor",
                         "parallax_plane")})
    return DenseParallax(x1_px=nanv(gx + par),
                         y1_px=nanv(gy + e[0] + e[1] * gx + e[2] * gy + e[3] * par),
                         sigma_px=sig, sigma_y_px=nanv(np.abs(e[3]) * sig), valid=valid,
                         zncc=zncc, roi=roi, sigma_scale=float(info["noise_factor"]),
                         params=params or VariationalParams(), calibration=cal,
                         weight_sigma_px=wsig)
