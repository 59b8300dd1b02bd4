"""Image noise measured from the images, and the noise gains of linear filters.

- :func:`image_noise_sigma`: robust estimate of the standard deviation of additive white
  noise in one grey image, from the response to Immerkær's mask (the difference of two
  discrete Laplacians), which cancels any locally quadratic intensity and passes white
  noise with a known gain (J. Immerkær 1996, "Fast noise variance estimation", Computer
  Vision and Image Understanding 64(2), 300-302). The median absolute response is used
  instead of the mean, so edges, particles and saturated specks do not inflate it.
- :func:`filter_noise_gain`: ``Σ w²`` of any linear filter (given as a function), the
  factor by which it multiplies the variance of white noise.
- :func:`calibrated_noise_sigma`: the noise of a view pair as the matcher measures it
  (:func:`semlab.subset.icgn_refine`'s default, at given matches): Immerkær's estimate
  lowered to what the matched subsets' residuals allow. The dense height maps use it, so a
  run measures its noise one way.
- :func:`with_seed_noise`: a dense map's calibration completed with that noise at its seeds
  (the sparse matches), unless the calibration already holds one.

The noise of SEM images is signal-dependent (shot noise) and can be correlated along scan
lines; :func:`image_noise_sigma` reports one white-noise level for the whole image, which
is what the per-point error of :func:`semlab.subset.icgn_refine` needs. Where the texture is
sharp at the pixel scale (real SEM images, a fine speckle) it is an upper bound:
``icgn_refine`` lowers it by default to what the matched subsets' residuals allow
(``SubsetResult.noise_ratio``).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .errors import ImageError

__all__ = ["image_noise_sigma", "filter_noise_gain", "calibrated_noise_sigma",
           "with_seed_noise"]

# Immerkær's mask: L2 - 2 L1 of two Laplacians; a white noise of variance s² gives a
# response of variance 36 s² (the sum of the squared weights).
_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])
_MAD_TO_SIGMA = 1.482602218505602    # 1 / Φ⁻¹(3/4)


def image_noise_sigma(img, mask=None):
    """Standard deviation of the additive white noise of an image, robustly.

    Parameters
    ----------
    img : (H, W) array
        Grey image (any real dtype), at least 3×3.
    mask : (H, W) bool array, optional
        Pixels to use (e.g. the valid part of an image); default all.

    Returns
    -------
    float
        Noise standard deviation, in the grey units of ``img``. ``1.4826 ×`` the median
        absolute response to Immerkær's mask, divided by 6 (its white-noise gain). A
        texture that is smooth on the scale of 3 pixels (any SEM image sampled finer than
        its beam) contributes almost nothing; sharp texture at the pixel scale makes the
        value an upper bound.

    Raises
    ------
    ImageError
        If ``img`` is not a finite 2D array of at least 3×3 pixels.
    """
    a = np.asarray(img, dtype=np.float64)
    if a.ndim != 2 or min(a.shape) < 3:
        raise ImageError(f"image_noise_sigma needs a 2D grey image of at least 3x3 pixels, "
                         f"got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ImageError("image_noise_sigma: the image has NaN or infinite values")
    resp = ndimage.correlate(a, _MASK, mode="nearest")[1:-1, 1:-1]
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != a.shape:
            raise ImageError(f"mask has shape {m.shape}, the image {a.shape}")
        resp = resp[m[1:-1, 1:-1]]
    if resp.size == 0:
        return float("nan")
    return float(_MAD_TO_SIGMA * np.median(np.abs(resp)) / 6.0)


def filter_noise_gain(apply, size=41):
    """Variance gain ``Σ w²`` of a linear, shift-invariant 2D filter on white noise.

    Parameters
    ----------
    apply : callable
        ``apply(img) -> img`` for a ``(size, size)`` float image (the filter).
    size : int
        Side of the test image (odd; larger than the filter's support).

    Returns
    -------
    float
        The sum of the squared impulse response of ``apply`` at the image centre.
    """
    delta = np.zeros((size, size))
    delta[size // 2, size // 2] = 1.0
    return float(np.sum(np.asarray(apply(delta), float) ** 2))


def calibrated_noise_sigma(ref_img, cur_img, pts_ref, pts_cur, half_window=10, max_points=2000,
                           seed=0):
    """White-noise σ of two views, calibrated on matched subsets as the matcher does.

    Runs :func:`semlab.subset.icgn_refine` with its default noise measurement
    (``noise_sigma=None``: each view's :func:`image_noise_sigma`, an upper bound where the
    texture is sharp at the pixel scale, lowered to the median residual ratio of the
    converged subsets, see ``semlab.subset._calibrate_noise``) at the given matches and
    returns the noise it used. No estimator of its own.

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        The two views (grey units).
    pts_ref, pts_cur : (N, 2) arrays
        Matched positions ``(x, y)`` in pixels in each view (e.g. the stereo step's matches;
        ``pts_cur`` is the IC-GN start). Rows with NaN are skipped.
    half_window : int
        Subset half size, pixels (default the automatic matcher's, 10).
    max_points : int
        At most this many matches are used (a seeded random choice), for speed.
    seed : int

    Returns
    -------
    (float, float)
        Noise σ of ``ref_img`` and ``cur_img``, grey units. Immerkær's values when fewer
        than 10 subsets converge (``icgn_refine`` then keeps them).
    """
    from .subset import icgn_refine

    pr = np.asarray(pts_ref, float).reshape(-1, 2)
    pc = np.asarray(pts_cur, float).reshape(-1, 2)
    if len(pr) != len(pc):
        raise ImageError(f"pts_ref and pts_cur must have one length, got {len(pr)} and {len(pc)}")
    keep = np.flatnonzero(np.all(np.isfinite(pr), 1) & np.all(np.isfinite(pc), 1))
    if len(keep) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(keep, int(max_points), replace=False))
    if len(keep) == 0:
        return (image_noise_sigma(ref_img), image_noise_sigma(cur_img))
    r = icgn_refine(ref_img, cur_img, pr[keep], pc[keep], half_window=half_window,
                    noise_sigma=None)
    return (float(r.noise_sigma[0]), float(r.noise_sigma[1]))


MIN_NOISE_SEEDS = 10     # fewer seeds: the dense method measures the noise on its own subsets


def with_seed_noise(calibration, view0, view1, seeds):
    """A dense map's calibration with the image noise measured at its seeds.

    The calibration's own ``"noise_sigma"`` wins (e.g. measured at the stereo matches by
    :func:`semlab.heightmap.stereo_noise_sigma`, or given by the caller); otherwise, with at
    least ``MIN_NOISE_SEEDS`` seeds, it is :func:`calibrated_noise_sigma` at them; with fewer it stays unset (the dense method then
    calibrates on its own subsets, ``icgn_refine``'s default).

    Parameters
    ----------
    calibration : dict or None
        Not modified.
    view0, view1 : (H, W) arrays
    seeds : (N, 2, 2) array or None
        Sparse matches: ``seeds[:, v]`` the ``(x, y)`` pixel position in view ``v``.

    Returns
    -------
    dict
        A copy of ``calibration``, with ``"noise_sigma"`` (σ of view 0, σ of view 1, grey
        units) where it could be measured.
    """
    cal = dict(calibration or {})
    if cal.get("noise_sigma") is None and seeds is not None and len(seeds) >= MIN_NOISE_SEEDS:
        sd = np.asarray(seeds, float)
        cal["noise_sigma"] = calibrated_noise_sigma(view0, view1, sd[:, 0, :2], sd[:, 1, :2])
    return cal
