"""Do the given tilts agree with the views? x-scales, parallax relief, tilt-axis significance.

Matches are ``pts`` : ``(N, V, 2)`` arrays (point, view, ``(x, y)`` pixels) as in
:mod:`semlab.reconstruct`. A flat surface ``z = a x + b y + c`` seen at tilt ``θ_i`` about the
image y axis maps between views by an affine map whose x-scale is::

    A_j = ∂u_j/∂u_ref = cos(θ_j + β) / cos(θ_ref + β),        tan β = -a

(``β`` the tilt of the surface on the stage, a few degrees for a mounted sample), so the
x-scales of the dominant flat surface measure the tilts; and the points off that surface
show a parallax ``Δu_j = z (sin θ_j - A_j sin θ_ref) / s`` that the tilts predict.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import GeometryError
from .plane import ransac_plane

__all__ = [
    "TiltCheck",
    "MAX_PRETILT_DEG",
    "x_scales",
    "check_tilts",
    "tilt_axis_sigma",
    "axis_is_significant",
    "level_tilts",
]

#: The largest tilt of the sample surface on the stage that is taken as plausible.
MAX_PRETILT_DEG = 10.0
#: Residual parallax below this (pixels RMS) between two views means the same image twice.
IDENTICAL_PX = 1e-3
#: Chance that a flat sample is called relief by the count of points beyond 3σ
#: (:func:`_relief_by_points`).
RELIEF_P = 1e-3


def x_scales(pts, ref_view=0, sigma_px=None, region=None, k_sigma=3.0, seed=0):
    """x-scale of the affine map of the dominant flat surface from ``ref_view`` to each view.

    For each view j, ``u_j = A_j u_ref + B_j v_ref + C_j`` is a plane in ``(u_ref, v_ref,
    u_j)``: its dominant plane (:func:`semlab.plane.ransac_plane`, threshold ``k_sigma``
    times ``sqrt(2) σ`` of the matches, or from the points) gives ``A_j``; the 1σ of
    ``A_j`` is the least-squares one with the inliers' residual variance.

    Parameters
    ----------
    pts : (N, V, 2) array
    ref_view : int
    sigma_px : None, float or (N,) array_like
        1σ matching error of an x coordinate, pixels.
    region : (N,) bool array, optional
        Only these points (e.g. a reference region) are used.
    k_sigma, seed
        RANSAC threshold and seed.

    Returns
    -------
    dict
        ``A`` (V,), ``A_sigma`` (V,), ``inliers`` (N,) bool (in every view),
        ``residual_px`` (V,) RMS of the inliers, ``map`` (V, 3) ``(A, B, C)``
        (``A = 1``, sigma 0 for the reference view).
    """
    p = np.asarray(pts, float)
    if p.ndim != 3 or p.shape[2] != 2 or p.shape[1] < 2:
        raise GeometryError(f"pts must be an (N, V, 2) array with V >= 2, got {p.shape}")
    n, v = p.shape[:2]
    use = np.ones(n, bool) if region is None else np.asarray(region, bool)
    if use.sum() < 6:
        raise GeometryError(f"only {int(use.sum())} points to measure the x-scale; need 6")
    sig = None if sigma_px is None else np.sqrt(2.0) * np.broadcast_to(
        np.asarray(sigma_px, float), (n,))[use]
    A, As, res = np.ones(v), np.zeros(v), np.zeros(v)
    maps = np.tile([1.0, 0.0, 0.0], (v, 1))
    inl = np.ones(int(use.sum()), bool)
    r = int(ref_view) % v
    for j in range(v):
        if j == r:
            continue
        q = np.column_stack([p[use, r, 0], p[use, r, 1], p[use, j, 0]])
        plane, m, _ = ransac_plane(q, sig, k_sigma=k_sigma, seed=seed, min_inliers=6)
        inl &= m
        d = np.column_stack([q[m, 0], q[m, 1], np.ones(m.sum())])
        e = q[m, 2] - d @ plane
        dof = max(m.sum() - 3, 1)
        cov = np.linalg.pinv(d.T @ d) * (e @ e) / dof
        A[j], As[j], res[j] = plane[0], np.sqrt(cov[0, 0]), np.sqrt(np.mean(e ** 2))
        maps[j] = plane
    full = np.zeros(n, bool)
    full[np.flatnonzero(use)[inl]] = True
    return {"A": A, "A_sigma": As, "inliers": full, "residual_px": res, "map": maps}


def _predicted_scale(tilt_rad, ref, beta):
    return np.cos(tilt_rad + beta) / np.cos(tilt_rad[ref] + beta)


@dataclass
class TiltCheck:
    """Result of :func:`check_tilts`.

    Attributes
    ----------
    tilt_deg : (V,) array
        The tilts checked.
    x_scale, x_scale_sigma : (V,) arrays
        Measured x-scales of the flat surface relative to the reference view, and 1σ.
    predicted_x_scale : (V,) array
        ``cos(θ_j + β) / cos(θ_ref + β)`` at the fitted surface tilt ``β``.
    pretilt_deg : float
        The tilt ``β`` of the flat surface on the stage implied by the tilts and x-scales.
    consistent : bool or None
        ``|β| <= max_pretilt_deg`` and every x-scale within ``k`` σ (and the model
        tolerance) of its prediction; None when too few points (6) allowed the check (then
        the other fields are NaN and ``message`` says why).
    suggested_tilt_deg : (V,) array
        Tilts that explain the x-scales with a level surface (``β = 0``) and the reference
        view's tilt kept: ``θ_j = ±acos(A_j cos θ_ref)``, the sign of the given order.
    x_scale_tilt_deg, x_scale_tilt_sigma_deg : (V,) arrays
        The tilts the x-scales alone give at the fitted ``β`` and the reference view's
        tilt, ``±acos(A_j cos(θ_ref + β)) - β``, and their 1σ from the x-scales' σ (large
        where ``θ_j + β`` is near 0, where the cosine is flat): compare with estimated tilts.
    parallax_rms_px : (V,) array
        RMS x-parallax of all points relative to the flat surface's map.
    noise_px : (V,) array
        The RMS that matching noise alone would give.
    relief_detected : bool or None
        Parallax above the noise in some view (the surface is not flat): in RMS over all
        points, or at more points beyond 3σ than noise gives (a band or two on a flat
        surface).
    detection_limit_um : float
        Smallest height (3σ) the tilts would show, µm (pixels without a pixel size).
    message : str
    """

    tilt_deg: np.ndarray
    x_scale: np.ndarray
    x_scale_sigma: np.ndarray
    predicted_x_scale: np.ndarray
    pretilt_deg: float
    consistent: bool
    suggested_tilt_deg: np.ndarray
    x_scale_tilt_deg: np.ndarray
    x_scale_tilt_sigma_deg: np.ndarray
    parallax_rms_px: np.ndarray
    noise_px: np.ndarray
    relief_detected: bool
    detection_limit_um: float
    message: str = ""

    def to_dict(self):
        """JSON-ready record for ``calibration.json``."""
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                for k, v in self.__dict__.items()}


def check_tilts(pts, tilt_deg, sigma_px=None, ref_view=0, region=None, pixel_size_um=None,
                max_pretilt_deg=MAX_PRETILT_DEG, k=5.0, scale_tol=2e-3, strict=True,
                where="experiment.toml"):
    """Check given stage tilts against the views' x-scales and parallax.

    1. x-scales ``A_j`` of the dominant flat surface (:func:`x_scales`) against
       ``cos(θ_j + β)/cos(θ_ref + β)``, with the surface tilt ``β`` fitted within
       ``±max_pretilt_deg``: a contradiction (e.g. ``[-5, 85]`` on ±5° views, which
       would need ``β ≈ -40°``) is refused, naming ``tilt_deg``, the measured x-scales and
       the tilts that fit them (``suggested_tilt_deg``).
    2. Parallax relief: the x-parallax of all points relative to the flat map, against
       what matching noise gives. Two views with different tilts but no parallax at all
       (``< IDENTICAL_PX``, the same image twice) are refused; parallax at the noise level
       is a flat sample, reported with the detection limit ``3 σ_z``.

    Parameters
    ----------
    pts : (N, V, 2) array
    tilt_deg : (V,) array_like
    sigma_px : None, float or (N,) array_like
        1σ matching error, pixels (None: from the flat surface's residuals).
    ref_view : int
    region : (N,) bool array, optional
        Points of the reference region (the flat surface).
    pixel_size_um : float, optional
        For ``detection_limit_um``.
    max_pretilt_deg : float
    k : float
        Allowed deviation of an x-scale in its σ.
    scale_tol : float
        Model tolerance added in quadrature to the x-scale σ (the flat surface is not
        exactly flat, and the views not exactly parallel projections).
    strict : bool
        Raise on a contradiction (else only ``consistent = False`` and the message).
    where : str
        Named in the messages (the experiment file).

    Returns
    -------
    TiltCheck

    Raises
    ------
    GeometryError
        With ``strict``: tilts contradicted by the x-scales, or identical views at
        different tilts.
    """
    p = np.asarray(pts, float)
    t = np.asarray(tilt_deg, float).ravel()
    v = p.shape[1]
    if t.size != v:
        raise GeometryError(f"{where}: tilt_deg has {t.size} values but there are {v} views")
    r = int(ref_view) % v
    try:
        xs = x_scales(p, r, sigma_px, region)
    except GeometryError as exc:
        try:  # too few points in the region: all points
            xs = x_scales(p, r, sigma_px, None) if region is not None else None
        except GeometryError:
            xs = None
        if xs is None:
            return _unchecked(t, f"tilts not checked against the views: {exc}")
    A, As = xs["A"], np.hypot(xs["A_sigma"], scale_tol)
    As[r] = 1.0
    th = np.deg2rad(t)
    betas = np.deg2rad(np.linspace(-89.0, 89.0, 3561))
    pred = np.array([_predicted_scale(th, r, b) for b in betas])   # (B, V)
    chi = np.sum(((A - pred) / As) ** 2, axis=1)
    chi[~np.all(np.isfinite(pred), axis=1)] = np.inf
    inside = np.abs(betas) <= np.deg2rad(max_pretilt_deg)
    b_all = betas[np.argmin(chi)]
    b_in = betas[inside][np.argmin(chi[inside])]
    pred_in = _predicted_scale(th, r, b_in)
    dev = np.abs(A - pred_in) / As
    sugg = _level_tilts(A, t, r)
    ok_scale = bool(np.all(dev <= k))
    phi_ref = th[r] + b_in
    cj = np.clip(A * np.cos(phi_ref), -1.0, 1.0)
    sgn = np.where(th + b_in >= 0, 1.0, -1.0)
    xs_tilt = np.rad2deg(sgn * np.arccos(cj) - b_in)
    with np.errstate(divide="ignore", invalid="ignore"):
        xs_sig = np.rad2deg(xs["A_sigma"] * np.cos(phi_ref) / np.sqrt(np.maximum(1 - cj ** 2, 0)))
    xs_tilt[r], xs_sig[r] = t[r], 0.0
    # parallax relief relative to the flat map, all points
    u_pred = xs["map"][:, 0] * p[:, r, :1] + xs["map"][:, 1] * p[:, r, 1:] + xs["map"][:, 2]
    par = p[:, :, 0] - u_pred                                        # (N, V)
    par_rms = np.sqrt(np.mean(par ** 2, axis=0))
    if sigma_px is None:
        noise = xs["residual_px"].copy()
    else:
        noise = np.full(v, np.sqrt(2.0) * float(np.sqrt(np.mean(np.square(sigma_px)))))
    noise[r] = 0.0
    others = np.arange(v) != r
    # relief in RMS over all points, or at a few: a mostly flat surface with a band or two
    # has a parallax RMS near the noise (the demo: 0.067 against 0.054 px) but far more
    # points beyond 3σ than noise gives (3 % against 0.27 %)
    relief = bool(np.any(par_rms[others] > 1.5 * np.maximum(noise[others], IDENTICAL_PX))
                  or _relief_by_points(par[:, others], sigma_px, noise[others]))
    dsin = np.abs(np.sin(th - th[r]))
    s = 1.0 if pixel_size_um is None else float(pixel_size_um)
    with np.errstate(divide="ignore"):
        lim = 3 * np.sqrt(np.maximum(noise, IDENTICAL_PX) ** 2) * s / dsin
    det_lim = float(np.min(lim[others]))
    msgs = []
    same = [j for j in range(v) if j != r and abs(t[j] - t[r]) > 1e-6
            and par_rms[j] < IDENTICAL_PX and xs["residual_px"][j] < IDENTICAL_PX]
    if same:
        msgs.append(
            f"{where}: tilt_deg = {t.tolist()} says views {same} are tilted by "
            f"{[round(float(t[j] - t[r]), 3) for j in same]}° from view {r}, but they show no "
            f"parallax at all against it (RMS {float(np.max(par_rms[same])):.2g} px): the same "
            "image twice? Check [stereo] views")
    if not ok_scale:
        ja = int(np.argmax(dev))
        msgs.append(
            f"{where}: tilt_deg = {t.tolist()} contradicts the views: the flat surface's "
            f"x-scale from view {r} to view {ja} is measured {A[ja]:.4f} ± {xs['A_sigma'][ja]:.1g}"
            f" but these tilts predict {pred_in[ja]:.4f} (cos θ_j / cos θ_ref, surface tilted "
            f"by up to {max_pretilt_deg:g}° on the stage; they would need "
            f"{np.rad2deg(b_all):.1f}°). Tilts that fit the views: tilt_deg = "
            f"{[round(float(x), 2) for x in sugg]} (or leave tilt_deg out with 3+ views to "
            "estimate them)")
    res = TiltCheck(tilt_deg=t, x_scale=A, x_scale_sigma=xs["A_sigma"], predicted_x_scale=pred_in,
                    pretilt_deg=float(np.rad2deg(b_in)), consistent=ok_scale and not same,
                    suggested_tilt_deg=sugg, x_scale_tilt_deg=xs_tilt,
                    x_scale_tilt_sigma_deg=xs_sig, parallax_rms_px=par_rms, noise_px=noise,
                    relief_detected=relief, detection_limit_um=det_lim, message="; ".join(msgs))
    if not relief and not same:
        res.message = (f"no parallax relief above the matching noise: the surface is flat "
                       f"within {det_lim:.3g} {'µm' if pixel_size_um else 'px'} (3σ)")
    if strict and msgs:
        raise GeometryError("; ".join(msgs))
    return res


def _level_tilts(A, t, r):
    """Tilts (degrees) explaining the x-scales ``A`` (relative to view ``r``) on a level
    surface, ``cos θ_j = A_j cos θ_r``, in the order of the given tilts ``t``: the reference
    view's tilt kept where it can be; where a view's x-scale is larger than ``1 / cos θ_r``
    allows (it is nearer 0° than the reference could be), that view at 0° and the others
    from it."""
    cos_r = np.cos(np.deg2rad(t[r]))
    anchor, at = r, t[r]                               # a view whose tilt is kept
    if np.nanmax(A) * cos_r > 1.0:
        anchor, at = int(np.nanargmax(A)), 0.0
        cos_r = 1.0 / A[anchor]
    side = np.where(t >= t[anchor], 1.0, -1.0)         # each view's side of the anchor
    out = np.rad2deg(side * np.arccos(np.clip(A * cos_r, -1.0, 1.0)))
    out[anchor] = at
    return out


def _relief_by_points(par, sigma_px, noise):
    """Whether more points lie beyond 3σ of their parallax noise than matching noise gives.

    Under a flat surface each point's x-parallax ``par`` ((N, W) pixels, relative to the flat
    map) is ``N(0, 2 σ²)`` with ``σ`` its matching 1σ (``sigma_px``: None, a float or (N,)
    pixels; the view's ``noise`` ((W,) RMS parallax noise) where not given), so the number
    of points beyond 3σ is binomial with ``p = 2 Φ(−3)``; relief if that count is improbable
    (tail probability below :data:`RELIEF_P`) in some view.
    """
    from scipy import stats

    view_noise = np.broadcast_to(noise, par.shape)
    s = None if sigma_px is None else np.sqrt(2.0) * np.asarray(sigma_px, float)
    if s is None or (s.ndim and s.size != par.shape[0]):
        sig = view_noise
    else:
        sig = np.broadcast_to(s.reshape(-1, 1) if s.ndim else s, par.shape)
        sig = np.where(np.isfinite(sig) & (sig > 0), sig, view_noise)
    with np.errstate(invalid="ignore"):
        beyond = np.sum(np.abs(par) > 3.0 * np.maximum(sig, IDENTICAL_PX), axis=0)
    n = np.sum(np.isfinite(par), axis=0)          # points matched in each view
    p0 = 2.0 * stats.norm.sf(3.0)
    return bool(np.any((n > 0) & (stats.binom.sf(beyond - 1, n, p0) < RELIEF_P)))


def _unchecked(t, message):
    nan = np.full(t.size, np.nan)
    return TiltCheck(tilt_deg=t, x_scale=nan, x_scale_sigma=nan, predicted_x_scale=nan,
                     pretilt_deg=float("nan"), consistent=None, suggested_tilt_deg=nan,
                     x_scale_tilt_deg=nan, x_scale_tilt_sigma_deg=nan, parallax_rms_px=nan,
                     noise_px=nan, relief_detected=None, detection_limit_um=float("nan"),
                     message=message)


def tilt_axis_sigma(x0, x1, n_boot=200, seed=0, bias_px=None):
    """Tilt-axis direction in view 0 from the affine F, with its 1σ.

    The σ is the spread over random half-samples of the points (without replacement, since
    the affine F refuses duplicate points): a delete-N/2 jackknife, whose variance equals
    that of the estimate from all N points (Shao & Wu 1989). That spread falls as 1/√N and
    misses a matching error shared by the points: the axis is read from how the y-disparity
    follows the relief's part of the x-parallax, so a y-error of ``bias_px`` that follows
    the parallax (a slip band's aperture problem) turns it by up to
    ``atan(bias_px / relief)``, ``relief`` the RMS x-parallax left by the views' affine map.
    With ``bias_px`` that term is added in quadrature: on a 0/+8° polished scene with a
    little relief (``semlab synth --seed 11 --texture polished --noise realistic
    --tilts=0,8``) the axis came out at 97.0 ± 0.11° (half-samples) where the truth is 90°.

    Parameters
    ----------
    x0, x1 : (N, 2) arrays of (x, y) pixels
    n_boot : int
        Half-samples.
    seed : int
    bias_px : float, optional
        A matching error the points may share, pixels (e.g. their median predicted σ).

    Returns
    -------
    axis_deg : float
        In [0, 180), from +x toward +y (90 = image y), from all points
        (:func:`semlab.epipolar.affine_tilt_axis`).
    sigma_deg : float
        1σ over the resamples (NaN with fewer than 2 successful resamples), with the shared
        error's term when ``bias_px`` is given.
    """
    from .epipolar import affine_tilt_axis, fundamental_affine

    a, b = np.asarray(x0, float), np.asarray(x1, float)
    axis = float(affine_tilt_axis(fundamental_affine(a, b))[0][0])
    rng = np.random.default_rng(seed)
    boots = []
    for _ in range(int(n_boot)):  # half-samples: their variance is the full sample's
        idx = rng.choice(len(a), len(a) // 2, replace=False)
        try:
            boots.append(float(affine_tilt_axis(fundamental_affine(a[idx], b[idx]))[0][0]))
        except GeometryError:
            continue
    if len(boots) < 2:
        return axis, float("nan")
    d = (np.array(boots) - axis + 90.0) % 180.0 - 90.0   # axes are defined modulo 180°
    sig = float(np.std(d, ddof=1))
    if bias_px is not None:
        M = np.column_stack([a, np.ones(len(a))])
        r = b[:, 0] - M @ np.linalg.lstsq(M, b[:, 0], rcond=None)[0]
        relief = float(np.sqrt(np.mean(r ** 2)))
        sig = float(np.hypot(sig, np.rad2deg(np.arctan2(float(bias_px), relief))))
    return axis, sig


def axis_is_significant(axis_deg, sigma_deg, k=3.0, tolerance_deg=0.0):
    """Whether a tilt axis is significantly off the image y axis (90°).

    True when its deviation from 90° (modulo 180°) exceeds both ``k`` σ and
    ``tolerance_deg``; False when σ is unknown (NaN).
    """
    dev = abs((float(axis_deg) - 90.0 + 90.0) % 180.0 - 90.0)
    if not np.isfinite(sigma_deg):
        return False
    return bool(dev > k * float(sigma_deg) and dev > tolerance_deg)


def level_tilts(tilt_deg, plane):
    """Tilts turned so that a reference plane becomes level in x.

    A common rotation ``α`` of the material frame about the tilt axis changes every tilt
    to ``θ - α`` and is unobservable from the images (the absolute-tilt gauge of
    :func:`semlab.reconstruct.estimate_tilts`): with ``α = atan(a)`` the plane
    ``z = a x + b y + c`` of heights computed at ``tilt_deg`` has no x slope.

    Parameters
    ----------
    tilt_deg : (V,) array_like
    plane : (3,) array_like
        ``(a, b, c)``, x and z in the same unit.

    Returns
    -------
    (V,) array of tilts, degrees.
    """
    return np.asarray(tilt_deg, float) - np.rad2deg(np.arctan(float(np.ravel(plane)[0])))
