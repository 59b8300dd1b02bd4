"""The stereo chain (end state) behind :class:`semlab.Analysis`, and its result files.

Stereo (end state)::

    views + correspondences ─► matching (raw / refined / automatic / merged)
        ─► epipolar (affine F, eight-point F, tilt axis) ─► tilts (experiment, metadata,
        estimated from 3+ views, or vanishing points) ─► reconstruct.heights_from_tilts
        ─► surface (reference plane, z, 1σ) ─► points3d.csv, calibration.json

The series chain (tracking, displacements, strain) is :mod:`semlab.series`.

Each step is a function of semlab's modules; this file only chains them and writes files.
"""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ._api import strict_keywords
from .errors import GeometryError, SemlabError, SemlabWarning

#: Tilt-axis deviations from the image y axis smaller than this are treated as zero.
AXIS_TOLERANCE_DEG = 0.2
#: ...and so are larger ones within this many σ of their (half-sample) uncertainty.
AXIS_SIGNIFICANCE = 3.0
#: The x-scale check of the tilts (semlab.tiltcheck) needs this many reference-surface points.
MIN_TILT_CHECK_POINTS = 10
#: 1σ error assumed for hand clicks that were not refined (pixels).
RAW_CLICK_SIGMA_PX = 0.5


@dataclass
class StereoResult:
    """Heights from the end-state views.

    Attributes
    ----------
    point_id : (N,) int
    pts : (N, V, 2) float
        Matched (x, y) pixel positions in every view. With 3 or more views, automatic points
        matched in the reference view and at least one other but not in all come after the
        others, NaN in their other views (:attr:`n_views`): their heights come from their
        own views at the tilts, offsets and reference surface of the complete points
        (:func:`fewer_view_heights`), their ``z_err_um`` is the matching σ only.
    kind : (N,) str
        ``"click"`` (refined or raw hand clicks) or ``"auto"`` (automatic matching).
    crack_id : (N,) int
        -1 where the point is on no crack.
    xyz_um : (N, 3) float
        Material (x, y) and height z above the reference plane, µm (z > 0 extrusion).
    z_err_um : (N,) float
        1σ height uncertainty (matching and bootstrap combined).
    sigma_px : (N,) float
        1σ matching error per point, pixels (NaN where unknown).
    tilt_deg : (V,) float
    tilt_source : str
        ``experiment``, ``metadata``, ``estimated`` or ``vanishing_points``.
    tilt_sigma_deg : (V,) float
    tilt_axis_deg : float
        Tilt-axis direction in view 0 used for the reconstruction (90 = image y).
    calibration : dict
        JSON-ready: F matrices, epipoles, vanishing-point K and rotations, tilts.
    method : str
    notes : list of str
    reference : semlab.surface.ReferenceSurface or None
        The plane the heights are measured from (method, inliers, residual).
    """

    point_id: np.ndarray
    pts: np.ndarray
    kind: np.ndarray
    crack_id: np.ndarray
    xyz_um: np.ndarray
    z_err_um: np.ndarray
    sigma_px: np.ndarray
    tilt_deg: np.ndarray
    tilt_source: str
    tilt_sigma_deg: np.ndarray
    tilt_axis_deg: float
    calibration: dict
    method: str
    notes: list = field(default_factory=list)
    reference: object = None

    @property
    def n_views(self):
        """(N,) int: the views each point was matched in (``pts`` finite there)."""
        return np.isfinite(self.pts[..., 0]).sum(axis=1)

    @property
    def z_um(self):
        """Heights above the reference plane, µm."""
        return self.xyz_um[:, 2]

    def in_views(self, *views):
        """(N,) bool: the points matched in all of ``views`` (:func:`rows_in_views`)."""
        return rows_in_views(self.pts, *views)


def rows_in_views(pts, *views):
    """(N,) bool: the rows of ``pts`` matched in all of ``views``.

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixel positions per view, NaN where a point is not matched.
    *views : int
        View indices.
    """
    return np.all(np.isfinite(np.asarray(pts, float)[:, list(views)]), axis=(1, 2))


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return None if not np.isfinite(obj) else float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


# ------------------------------------------------------------------------------ stereo steps
def summarise_reasons(reasons):
    """Why points failed, each distinct reason once: ``"k× reason"``, a number that differs
    between the points shown as its range (``"centred 0.68–0.81 of the half size"``), the
    reasons of a point's views (``"view 1: …; view 2: …"``) counted separately.

    >>> summarise_reasons(["view 1: off by 0.5 px; view 2: off by 0.7 px",
    ...                    "view 1: off by 0.6 px"])
    '3× view 1–2: off by 0.5–0.7 px'
    """
    number = re.compile(r"-?\d+(?:\.\d+)?")
    groups = {}
    for reason in reasons:
        for part in re.split(r"; (?=view \d+: )", str(reason)):
            groups.setdefault(number.sub("#", part), []).append(number.findall(part))
    out = []
    for template, values in groups.items():
        text = template.split("#")
        s = text[0]
        for k, rest in enumerate(text[1:]):
            slot = sorted({v[k] for v in values}, key=float)
            s += slot[0] if len(slot) == 1 else f"{slot[0]}–{slot[-1]}"
            s += rest
        out.append(f"{len(values)}× {s}")
    return "; ".join(out)


@strict_keywords
def match_views(views, clicks=None, method="auto", progress=True, refine_kw=None, auto_kw=None,
                with_partial=False):
    """Correspondences between the views by the chosen method.

    Parameters
    ----------
    views : list of (H, W) arrays
    clicks : (N, V, 2) array or None
        Hand-clicked points.
    method : {"raw", "refined", "auto", "merged"}
        ``raw``: the clicks as they are (the reference paper's method); ``refined``: clicks
        refined by sub-pixel matching; ``auto``: automatic matching only; ``merged``:
        refined clicks plus automatic points.

    with_partial : bool
        Also return, as a fifth item, the automatic points valid in the reference view and
        at least one other but not in all (a :class:`semlab.matching.MatchResult`, those
        within 3 px of a returned point left out; None without automatic matching).

    Returns
    -------
    pts (M, V, 2), kind (M,) str, sigma_px (M,), index into clicks (M,) int (-1 for auto)

    Examples
    --------
    Two views of a random texture, the second shifted by (0.3, 0) px:

    >>> import numpy as np, semlab
    >>> from scipy import ndimage
    >>> rng = np.random.default_rng(0)
    >>> a = ndimage.gaussian_filter(rng.normal(size=(160, 160)), 2.0)
    >>> b = ndimage.shift(a, (0.0, 0.3), order=3, mode="nearest")
    >>> clicks = np.array([[[60.0, 60.0], [60.0, 60.0]], [[100.0, 90.0], [100.0, 90.0]]])
    >>> pts, kind, sigma_px, idx = semlab.match_views([a, b], clicks, method="refined",
    ...                                              progress=False)
    Traceback (most recent call last):
    ...
    semlab.errors.GeometryError: only 2 matched points: heights need at least 4; add clicks or use automatic matching
    >>> pts, kind, sigma_px, idx = semlab.match_views([a, b], method="auto", progress=False)
    >>> bool(abs(np.median(pts[:, 1, 0] - pts[:, 0, 0]) - 0.3) < 0.01), len(pts) > 50
    (True, True)
    """
    from . import matching
    from .tiled_stereo import run_auto_match

    if method in ("raw", "refined") and clicks is None:
        raise SemlabError(f"method {method!r} needs hand-clicked correspondences; the experiment "
                          "has none (add [stereo] correspondences, or use method='auto')")
    if method == "raw":
        n = len(clicks)
        out = clicks.copy(), np.array(["click"] * n), np.full(n, np.nan), np.arange(n)
        return out + (None,) if with_partial else out
    parts = []
    partial = None
    if method in ("refined", "merged") and clicks is not None:
        r = matching.refine_correspondences(views, clicks, **(refine_kw or {}))
        ok = np.asarray(r.valid)
        parts.append((r.pts[ok], np.array(["click"] * ok.sum()), r.sigma_px[ok], np.flatnonzero(ok)))
        if (~ok).any():
            warnings.warn(f"{(~ok).sum()} clicked points could not be refined and were left out "
                          f"({summarise_reasons(np.asarray(r.reason)[~ok])})",
                          SemlabWarning, stacklevel=2)
    if method in ("auto", "merged"):
        # views larger than DEFAULT_TILING.min_pixels are matched in tiles
        a = run_auto_match(views, progress=progress, **(auto_kw or {}))
        ok = np.asarray(a.valid)
        apts = a.pts[ok]
        if with_partial:
            partial = a.seen_in(2)
            partial = partial.select(~partial.valid)
        if parts:  # drop automatic points that duplicate a clicked one
            cp = parts[0][0][:, 0]
            if len(cp):
                d = np.min(np.hypot(*(apts[:, None, 0, :] - cp[None, :, :]).transpose(2, 0, 1)), axis=1)
                keep = d > 3.0
            else:
                keep = np.ones(len(apts), bool)
            apts = apts[keep]
            asig = a.sigma_px[ok][keep]
        else:
            asig = a.sigma_px[ok]
        parts.append((apts, np.array(["auto"] * len(apts)), asig, np.full(len(apts), -1)))
    if not parts:
        raise SemlabError(f"unknown matching method {method!r}; use raw, refined, auto or merged")
    pts = np.concatenate([p[0] for p in parts])
    kind = np.concatenate([p[1] for p in parts])
    sig = np.concatenate([p[2] for p in parts]).astype(float)
    idx = np.concatenate([p[3] for p in parts]).astype(int)
    if len(pts) < 4:
        hint = ("the views have too little texture for automatic matching; click points "
                "(method refined)" if method == "auto" else
                "add clicks or use automatic matching")
        raise GeometryError(f"only {len(pts)} matched points: heights need at least 4; {hint}")
    if not with_partial:
        return pts, kind, sig, idx
    if partial is not None and len(partial):
        near = cKDTree(pts[:, 0]).query(partial.pts[:, partial.ref_view])[0] <= 3.0
        partial = partial.select(~near & np.isfinite(partial.sigma_px))
    return pts, kind, sig, idx, partial


def fewer_view_heights(pts, partial, tilt_deg, pixel_size_um, tilt_axis_deg, reference):
    """Heights of points matched in fewer views, in the frame of the complete points.

    Parameters
    ----------
    pts : (N, V, 2) array
        The complete points (every view), as the heights of the run were computed from.
    partial : semlab.matching.MatchResult
        Points valid in the reference view and at least one other (``view_valid``).
    tilt_deg, pixel_size_um, tilt_axis_deg
        As the run's heights used.
    reference : semlab.surface.ReferenceSurface
        The run's reference surface.

    Returns
    -------
    pts (P, V, 2) with NaN in the views a point is not valid in, xyz_um (P, 3) with z
    above the reference, z_err_um (P,) (matching σ of its own views through the tilts,
    :func:`semlab.surface.height_sigma`), sigma_px (P,)

    The complete points fix the per-view offsets (the gauge), so each partial point is
    solved over its own views with the same offsets
    (:func:`semlab.reconstruct.heights_from_tilts` with ``view_valid``).
    """
    from . import reconstruct, surface

    vv = partial.views_valid()
    pp = np.where(vv[..., None], partial.pts, np.nan)
    both = np.concatenate([pts, pp])
    mask = np.concatenate([np.ones(pts.shape[:2], bool), vv])
    hr = reconstruct.heights_from_tilts(both, tilt_deg, pixel_size_um,
                                        tilt_axis_deg=tilt_axis_deg, view_valid=mask)
    xyz3 = hr.xyz_um[len(pts):]
    xyz = np.column_stack([xyz3[:, :2], reference.heights(xyz3)])
    ref = partial.ref_view
    sv = partial.view_sigma_px if partial.view_sigma_px is not None else \
        np.where(vv, partial.sigma_px[:, None], np.nan)
    sv = np.where(vv, np.clip(np.nan_to_num(sv, nan=np.inf), 1e-4, None), np.inf)
    sv = view_sigmas(sv, sv.shape[1], np.ones(len(sv), bool), ref,
                     point_sigma_px=np.clip(partial.sigma_px, 1e-4, None))
    z_err = surface.height_sigma(sv, tilt_deg, pixel_size_um)
    return pp, xyz, np.asarray(z_err, float), partial.sigma_px.astype(float)


@dataclass
class Heights:
    """Heights above the reference plane with their error bars (see :func:`surface_heights`).

    Attributes
    ----------
    xyz_um : (N, 3) float
        Material x, y (µm) and height z above the reference plane (µm, z > 0 extrusion).
    z_err_um : (N,) float
        1σ of z: the matching σ propagated through the tilts, and the bootstrap of the
        reference plane and view offsets when ``n_boot`` > 0.
    plane : (3,) float
        Reference plane ``z = a x + b y + c`` (µm) of the reconstructed points.
    reference : semlab.surface.ReferenceSurface
        How the reference plane was chosen (method, inliers, residual).
    """

    xyz_um: np.ndarray
    z_err_um: np.ndarray
    plane: np.ndarray
    reference: object = None

    @property
    def z_um(self):
        """Heights above the reference plane, µm."""
        return self.xyz_um[:, 2]


@strict_keywords
def surface_heights(pts, tilt_deg, pixel_size_um, sigma_px=None, n_boot=0, seed=0,
                    tilt_axis_deg=90.0, region=None, three_points_px=None, progress=False):
    """Heights of matched points above the reference surface, with 1σ error bars.

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixel positions of N points in V >= 2 views (origin at the centre of the
        top-left pixel).
    tilt_deg : (V,) array_like
        Stage tilt of each view about the image y axis, degrees.
    pixel_size_um : float
        Pixel size, µm/px.
    sigma_px : float, (N,) or (N, V) array, optional
        1σ error of each point's x coordinate in every view (pixels); None: 0.5 px (a hand
        click, in every view). The σ of :func:`match_views` is that of the disparity (the
        reference-view position is exact): pass ``view_sigmas(sigma_px, V, matched)`` (N, V)
        so that it is not counted in the reference view too.
    n_boot : int
        Bootstrap resamples of the plane and offsets added to the error bars (0: none).
    seed : int
    tilt_axis_deg : float
        Tilt-axis direction in view 0, degrees from +x (90 = image y).
    region, three_points_px : optional
        The reference surface (:func:`semlab.surface.reference_surface`): by default the
        dominant flat surface; or the dominant plane within a region of view 0 (rectangle
        ``(x0, y0, x1, y1)`` px, polygon, or mask); or the plane through three view-0 points.

    Returns
    -------
    Heights

    Examples
    --------
    A bump of 0.1 µm on a flat surface, seen at -5° and +5° (0.03 µm/px):

    >>> import numpy as np, semlab
    >>> from semlab.camera import project_affine
    >>> rng = np.random.default_rng(0)
    >>> xy = rng.uniform(0, 6, (200, 2))                       # µm
    >>> z = 0.1 * np.exp(-((xy - 3) ** 2).sum(1) / 0.5)        # µm
    >>> pts = np.stack([project_affine(np.column_stack([xy, z]), t, 0.03)
    ...                 for t in (-5.0, 5.0)], axis=1)
    >>> h = semlab.surface_heights(pts, [-5.0, 5.0], 0.03, sigma_px=0.02)
    >>> h.reference.method                                      # the flat part is the reference
    'dominant_plane'
    >>> bool(np.abs(h.z_um - z).max() < 0.001)                 # within 1 nm of the truth
    True
    >>> round(float(np.median(h.z_err_um)) * 1000, 1)          # nm, from 0.02 px matching
    4.9
    """
    from . import surface

    pts = np.asarray(pts, float)
    if sigma_px is None:
        sig = np.full(len(pts), RAW_CLICK_SIGMA_PX)
    elif np.ndim(sigma_px) == 2:
        sig = np.asarray(sigma_px, float)
    else:
        sig = np.broadcast_to(np.asarray(sigma_px, float), (len(pts),))
    xyz, z_err, ref = _heights_and_reference(pts, tilt_deg, pixel_size_um, sig, tilt_axis_deg,
                                             region, three_points_px, seed)
    if n_boot:
        boot = surface.bootstrap_heights(pts, tilt_deg, pixel_size_um, n_boot=n_boot, seed=seed,
                                         tilt_axis_deg=tilt_axis_deg, progress=progress,
                                         reference=ref)
        z_err = np.sqrt(z_err ** 2 + np.asarray(boot, float) ** 2)
    z = ref.heights(xyz)
    return Heights(xyz_um=np.column_stack([xyz[:, :2], z]), z_err_um=z_err,
                   plane=np.asarray(ref.plane, float), reference=ref)


def _heights_and_reference(pts, tilt_deg, pixel_size_um, sigma_px, tilt_axis_deg, region,
                           three_points_px, seed):
    """3D points at known tilts, their matching σ of z, and the reference surface."""
    from . import reconstruct, surface

    xyz = reconstruct.heights_from_tilts(pts, tilt_deg, pixel_size_um,
                                         tilt_axis_deg=tilt_axis_deg).xyz_um
    z_err = np.asarray(surface.height_sigma(sigma_px, tilt_deg, pixel_size_um), float)
    ref = surface.reference_surface(xyz, z_err, xy_px=pts[:, 0], seed=seed, region=region,
                                    three_points_px=three_points_px)
    return xyz, z_err, ref


def epipolar_summary(pts):
    """Affine and eight-point F between view 0 and each other view, with the tilt axis.

    Returns a JSON-ready dict; the eight-point F is None (with the reason) when it is
    undetermined, which is the normal case for affine SEM views of a nearly flat surface.
    """
    from . import epipolar

    out = {"pairs": []}
    for j in range(1, pts.shape[1]):
        x0, x1 = pts[:, 0], pts[:, j]
        pair = {"views": [0, j]}
        try:
            Fa = epipolar.fundamental_affine(x0, x1)
            e0, e1 = epipolar.epipoles(Fa)
            axis, line = epipolar.affine_tilt_axis(Fa)
            pair.update(F_affine=Fa, epipoles_affine=[e0, e1], tilt_axis_deg=axis,
                        epipolar_line_deg=line,
                        sampson_affine_px_median=float(np.median(np.abs(
                            epipolar.sampson_distance(Fa, x0, x1)))))
        except GeometryError as exc:
            # with little relief and noisy clicks the affine F is undetermined: keep the
            # stage convention (tilt axis along image y) and say so
            pair.update(F_affine=None, F_affine_error=str(exc), tilt_axis_deg=[90.0, 90.0])
        try:
            F8 = epipolar.fundamental_8point(x0, x1)
            e0, e1 = epipolar.epipoles(F8)
            pair.update(F_8point=F8, epipoles_8point=[e0, e1],
                        sampson_8point_px_median=float(np.median(np.abs(epipolar.sampson_distance(F8, x0, x1)))))
        except GeometryError as exc:
            pair.update(F_8point=None, F_8point_error=str(exc))
        out["pairs"].append(pair)
    return out


def vanishing_summary(lines):
    """K, rotations and relative rotations from the line families (JSON-ready), or the error."""
    from . import vanishing

    try:
        cal = vanishing.calibrate_views(lines)
    except SemlabError as exc:
        return {"error": str(exc)}, None
    d = {"K": cal.K, "focal_px": cal.focal_px, "principal_point_px": cal.principal_point,
         "families": list(cal.families), "R": cal.R, "vanishing_points": cal.vps,
         "relative_R": cal.relative_R, "relative_axis": cal.axis,
         "relative_angle_deg": cal.angle_deg, "relative_euler_zyx_deg": cal.euler_zyx_deg,
         "line_residual_px_rms": [float(np.sqrt(np.mean(np.concatenate(list(r.values())) ** 2)))
                                  for r in cal.residuals_px]}
    return d, cal


def match_for_tilts(exp, progress=True, auto_kw=None):
    """Matches for the tilt estimation of 3+ views: square subsets, the middle view as the
    matching reference (see :func:`choose_tilts`), otherwise the keywords ``auto_kw`` of
    :func:`semlab.matching.auto_match` that the heights use. Returns (M, V, 2) valid
    matches, pixels."""
    from .tiled_stereo import run_auto_match

    v = len(exp.stereo.view_paths)
    kw = {**(auto_kw or {}), "ref_view": (v - 1) // 2, "band_aware": False}
    m = run_auto_match(exp.views(), progress=progress, **kw)
    return m.pts[m.valid]


def choose_tilts(exp, pts, lines_cal=None, progress=True, tilt_matches=None, auto_kw=None):
    """The stage tilt of each view and where it came from.

    Order of preference: experiment.toml, the images' SEM metadata, estimation from 3+ views
    (:func:`semlab.reconstruct.estimate_tilts` on ``tilt_matches``, by default
    :func:`match_for_tilts` with ``auto_kw``), the vanishing-point relative rotation (for
    two views, split symmetrically about 0°: only the difference is observable).

    Returns
    -------
    tilt_deg (V,), source str, tilt_sigma_deg (V,)
    """
    from . import reconstruct

    st = exp.stereo
    v = len(st.view_paths)
    if st.tilt_deg is not None:
        return np.asarray(st.tilt_deg, float), st.tilt_source, np.zeros(v)
    if v >= 3:
        # Square affine subsets smooth the parallax of narrow ribbons, but by the same linear
        # operator in every view pair, so their matches stay exactly consistent with a
        # (smoothed) surface and the metric upgrade stays unbiased. The band-aware matches
        # used for heights switch subsets point by point, which breaks that consistency.
        # The middle view (in the listed order, normally the tilt order) is the matching
        # reference: both matches then span one tilt step, and the view-dependent matching
        # biases, alike in both, cancel in the metric upgrade. With the first view as
        # reference the middle tilt came out 0.08-0.18° off on synthetic -5/0/+5° scenes;
        # with the middle one 0.04-0.06° (benchmarks/stereo_accuracy.py).
        if tilt_matches is None:
            tilt_matches = match_for_tilts(exp, progress=progress, auto_kw=auto_kw)
        tilt_pts = tilt_matches if len(tilt_matches) >= 20 else pts
        est = reconstruct.estimate_tilts(tilt_pts, exp.pixel_size_um, progress=progress,
                                         increasing=st.tilt_order == "increasing")
        return np.asarray(est.tilt_deg), "estimated", np.asarray(est.tilt_sigma_deg)
    if lines_cal is not None:
        d = reconstruct.tilt_from_rotation(lines_cal.relative_R[1])
        d = float(np.asarray(d).ravel()[0])
        return np.array([-d / 2, d / 2]), "vanishing_points", np.zeros(2)
    raise GeometryError(f"{exp.toml_path}: " + reconstruct.TWO_VIEW_MESSAGE)


def pair_consistency_summary(pts, tilt_deg, sigma_views, pixel_size_um, tilt_axis_deg):
    """The error bars of a run with 3+ views checked by its own views.

    :func:`semlab.validation.view_pair_consistency` of the complete points: for the
    ``calibration.json`` key ``pair_consistency`` (one dict per view pair: ``views``,
    ``n_points``, ``robust_sd``, ``within_1sigma``, ``within_2sigma``, ``consistent``) and one
    note (the range over the pairs), which names the pairs whose error bars do not hold.

    Returns
    -------
    (list of dict, list of str)
    """
    from .validation import CONSISTENT_WITHIN_2SIGMA, view_pair_consistency

    rows = view_pair_consistency(pts, tilt_deg, sigma_views, pixel_size_um,
                                 tilt_axis_deg=tilt_axis_deg)
    out = [{k: v for k, v in r.items() if k != "u"} for r in rows]
    if not out:
        return out, []

    def span(key, fmt):
        lo, hi = min(r[key] for r in out), max(r[key] for r in out)
        return format(lo, fmt) if format(lo, fmt) == format(hi, fmt) else \
            f"{format(lo, fmt)}–{format(hi, fmt)}"

    def names(rows):
        return ", ".join(f"({r['views'][0]}, {r['views'][1]})" for r in rows)

    msg = (f"error bars checked by the views: heights from view pairs alone ({names(out)}) "
           f"differ from all views' by {span('robust_sd', '.2f')} of their predicted σ (robust SD, "
           f"{out[0]['n_points']} points), {span('within_1sigma', '.0%')} within 1σ and "
           f"{span('within_2sigma', '.0%')} within 2σ")
    bad = [r for r in out if not r["consistent"]]
    if bad:
        msg += (f"; for {names(bad)} fewer than {CONSISTENT_WITHIN_2SIGMA:.0%} within 2σ, so "
                "the error bars do not hold (an error the matching σ leaves out: one common to a "
                "point's views, the camera model, scan distortion, or the surface looking "
                "different at these tilts)")
    return out, [msg]


def view_sigmas(sigma_px, n_views, matched, ref_view=0, point_sigma_px=None):
    """Per-view 1σ of the x coordinates, (N, V) pixels, for :func:`surface.height_sigma`.

    A matched point (refined click or automatic match) keeps its reference-view position
    exactly (it defines the material point) and its ``sigma_px`` is the error of the
    *disparity*: the Gauss–Newton covariance of :func:`semlab.subset.icgn_refine` holds
    the noise of both images. Counting it again in the reference view (``(N,)`` σ for every
    view) made the height σ √2 too large. The reference view gets 1e-3 of the point's σ
    (height_sigma needs positive values; the height σ changes by < 1e-6). Raw clicks
    (``matched`` False) carry their click error in every view.

    Parameters
    ----------
    sigma_px : (N,) or (N, V) array
        Pixels: one σ per point (every view), or per view (``inf`` where a point is not
        matched, as :func:`surface.height_sigma` takes it; the reference column of a
        matched point is replaced).
    n_views : int
        V.
    matched : (N,) bool
        The points whose reference-view position is exact.
    ref_view : int
    point_sigma_px : (N,) array, optional
        The point's σ (pixels) the reference view gets 1e-3 of; default ``sigma_px`` when it
        is (N,), the root mean square of the finite non-reference columns when (N, V) (as
        :class:`semlab.match_result.MatchResult` defines ``sigma_px``).

    Returns
    -------
    (N, V) float array, pixels
    """
    sig = np.asarray(sigma_px, float)
    if sig.ndim == 1:
        out = np.repeat(sig[:, None], n_views, axis=1)
        base = sig
    elif sig.ndim == 2 and sig.shape[1] == n_views:
        out = sig.copy()
        oth = np.delete(sig, ref_view, axis=1)
        fin = np.isfinite(oth)
        with np.errstate(invalid="ignore", divide="ignore"):
            base = np.sqrt(np.sum(np.where(fin, oth, 0.0) ** 2, axis=1) / fin.sum(axis=1))
    else:
        raise SemlabError(f"sigma_px must be (N,) or (N, {n_views}), got shape {sig.shape}")
    if point_sigma_px is not None:
        base = np.asarray(point_sigma_px, float)
    m = np.asarray(matched, bool)
    out[m, ref_view] = 1e-3 * base[m]
    return out


def affine_heights(exp, pts, tilt, tilt_source, sigma_px, tilt_axis_deg=90.0, seed=0,
                   sigma_views=None):
    """Heights at known (or estimated) tilts above the experiment's reference surface.

    Heights (:func:`semlab.reconstruct.heights_from_tilts`), their matching σ, the reference
    surface (:func:`semlab.surface.reference_surface`, from ``[stereo] reference_region`` /
    ``reference_points`` or the dominant flat surface); estimated tilts (whose common
    rotation is a convention) are turned so that the reference surface is level
    (:func:`semlab.tiltcheck.level_tilts`); then the tilts are checked against the
    reference surface's x-scales (:func:`semlab.tiltcheck.check_tilts`), refusing given
    tilts (experiment.toml or metadata) that the views contradict.

    Returns
    -------
    xyz_um (N, 3), z_err_um (N,), ReferenceSurface, tilt_deg (V,), TiltCheck or None
        (None: fewer than :data:`MIN_TILT_CHECK_POINTS` points on the reference surface, the
        tilts are not checked)

    ``sigma_views`` (N, V): per-view σ for the height σ (:func:`view_sigmas`); default
    ``sigma_px`` in every view.
    """
    from . import tiltcheck

    sig_z = sigma_px if sigma_views is None else sigma_views

    st = exp.stereo
    estimated = tilt_source in ("estimated", "vanishing_points")
    for _ in range(3 if estimated else 1):
        xyz, z_err, ref = _heights_and_reference(pts, tilt, exp.pixel_size_um, sig_z,
                                                 tilt_axis_deg, st.reference_region,
                                                 st.reference_points, seed)
        if estimated and _ < 2:
            tilt = tiltcheck.level_tilts(tilt, ref.plane)
    n_flat = int(np.count_nonzero(ref.inliers))
    if n_flat < MIN_TILT_CHECK_POINTS:  # a small scene: too few points to measure x-scales
        return xyz, z_err, ref, np.asarray(tilt, float), None
    chk = tiltcheck.check_tilts(pts, tilt, sigma_px, region=ref.inliers,
                                pixel_size_um=exp.pixel_size_um,
                                strict=tilt_source in ("experiment", "metadata"),
                                where=f"{exp.toml_path} ({tilt_source} tilts)")
    return xyz, z_err, ref, np.asarray(tilt, float), chk


@strict_keywords
def run_stereo(exp, method=None, n_boot=200, seed=0, progress=True, refine_kw=None, auto_kw=None,
               tilt_matches=None):
    """Heights of the end-state surface from the experiment's views.

    Parameters
    ----------
    exp : semlab.experiment.Experiment
    method : {"raw", "refined", "auto", "merged"}, optional
        Default: ``merged`` when the experiment has correspondences, else ``auto``.
    n_boot : int
        Bootstrap resamples for the height uncertainty.
    seed : int
        Seed of the bootstrap and of the reference-surface RANSAC.
    refine_kw, auto_kw : dict, optional
        Keyword arguments of :func:`semlab.matching.refine_correspondences` and
        :func:`semlab.matching.auto_match` (unknown names raise ``TypeError``).
    tilt_matches : (M, V, 2) array, optional
        Matches for the tilt estimation of 3+ views without given tilts (default: computed
        by :func:`match_for_tilts`; :class:`semlab.Analysis` computes them once for every
        stereo method).

    Returns
    -------
    StereoResult
    """
    from . import reconstruct, surface, tiltcheck

    if exp.stereo is None:
        raise SemlabError(f"{exp.toml_path}: no [stereo] table, so no heights to compute")
    if (len(exp.stereo.view_paths) == 2 and exp.stereo.tilt_deg is None
            and exp.lines() is None):      # refused before any matching, not after it
        raise GeometryError(f"{exp.toml_path}: " + reconstruct.TWO_VIEW_MESSAGE)
    views = exp.views()
    corr = exp.correspondences()
    clicks = None if corr is None or len(corr.pts) == 0 else corr.pts
    if clicks is None and corr is not None and method in ("raw", "refined"):
        raise SemlabError(f"{corr.path}: method {method!r} needs clicked points, but this "
                          "correspondences file has only its header; add points, or use "
                          "method='auto'")
    method = method or ("merged" if clicks is not None else "auto")
    pts, kind, sigma_px, idx, partial = match_views(
        views, clicks, method, progress=progress, refine_kw=refine_kw, auto_kw=auto_kw,
        with_partial=True)
    notes = []
    calib = {"pixel_size_um": exp.pixel_size_um, "pixel_size_source": exp.pixel_size_source,
             "camera": exp.stereo.camera, "method": method, "n_points": int(len(pts))}
    if method in ("auto", "merged"):   # the one parameter object of automatic matching
        from dataclasses import asdict

        from .matching import AutoMatchParams
        calib["auto_match_params"] = asdict(AutoMatchParams(**(auto_kw or {})))
        from .tiled_stereo import DEFAULT_TILING
        if DEFAULT_TILING.tiles(views[0].shape):
            calib["auto_match_tiling"] = asdict(DEFAULT_TILING)
    epi = epipolar_summary(pts)
    calib["epipolar"] = epi
    lines = exp.lines()
    lines_cal = None
    if lines is not None:
        calib["vanishing"], lines_cal = vanishing_summary(lines)
    axis, axis_sigma = float(epi["pairs"][0]["tilt_axis_deg"][0]), float("nan")
    if epi["pairs"][0].get("F_affine") is not None:
        sig = np.asarray(sigma_px, float)
        axis, axis_sigma = tiltcheck.tilt_axis_sigma(
            pts[:, 0], pts[:, 1], seed=seed,
            bias_px=float(np.nanmedian(sig)) if np.isfinite(sig).any() else None)
    calib["tilt_axis_measured_deg"], calib["tilt_axis_sigma_deg"] = axis, axis_sigma
    if tiltcheck.axis_is_significant(axis, axis_sigma, AXIS_SIGNIFICANCE, AXIS_TOLERANCE_DEG):
        axis_used = axis
        notes.append(f"tilt axis at {axis:.2f} ± {axis_sigma:.2f}° in the image (not along y): "
                     "coordinates rotated")
    else:
        axis_used = 90.0
    tilt, tilt_source, tilt_sigma = choose_tilts(exp, pts, lines_cal, progress=progress,
                                                 tilt_matches=tilt_matches, auto_kw=auto_kw)
    if tilt_source == "estimated":
        other = "decreasing" if exp.stereo.tilt_order == "increasing" else "increasing"
        notes.append(f"the sign of the heights is a convention: the estimated tilts are "
                     f"{exp.stereo.tilt_order} with the views' order ([stereo] tilt_order = "
                     f"\"{exp.stereo.tilt_order}\"); the images cannot tell this from the "
                     f"reverse (θ → −θ, z → −z). If extrusions come out as intrusions (a grain "
                     f"as a bowl), the stage tilted the other way: set tilt_order = "
                     f"\"{other}\" in [stereo] of {exp.toml_path}")
    # raw clicks carry no matching estimate: assume the typical hand-click error
    matched = np.isfinite(sigma_px)
    sigma_px = np.clip(np.where(matched, sigma_px, RAW_CLICK_SIGMA_PX), 1e-4, None)
    if exp.stereo.camera == "perspective":
        if lines_cal is None:
            raise GeometryError(
                f"{exp.toml_path}: camera = 'perspective' needs the intrinsics K from "
                "vanishing points: add [stereo] lines (see the README's lines.json), or use "
                "camera = 'affine'")
        if pts.shape[1] > 2:
            notes.append("camera = perspective: heights from views 0 and 1 only")
        try:  # refuses affine-looking (SEM) views before any result exists
            xyz_p, R_p, t_p, tilt_p = reconstruct.heights_perspective(
                pts[:, 0], pts[:, 1], lines_cal.K, exp.pixel_size_um)
        except GeometryError as exc:
            raise GeometryError(f"{exp.toml_path}: [stereo] {exc}") from None
        calib["perspective"] = {"K": lines_cal.K, "R_1": R_p, "t_1_um": t_p,
                                "tilt_difference_deg": tilt_p,
                                "scale": "median depth = pixel_size_um * focal_px"}
        notes.append("camera = perspective: z_err_um from the matching error through the "
                     "triangulation (pose uncertainty not included)")
        xyz_3d = xyz_p
        z_err = reconstruct.perspective_height_sigma(lines_cal.K, R_p, t_p, pts[:, 0],
                                                     pts[:, 1], sigma_px)
        ref = surface.reference_surface(xyz_3d, z_err, xy_px=pts[:, 0], seed=seed,
                                        region=exp.stereo.reference_region,
                                        three_points_px=exp.stereo.reference_points)
    else:
        sigma_views = view_sigmas(sigma_px, pts.shape[1], matched)
        xyz_3d, z_err, ref, tilt, chk = affine_heights(
            exp, pts, tilt, tilt_source, sigma_px, axis_used, seed, sigma_views=sigma_views)
        if chk is None:
            calib["tilt_check"] = {"checked": False}
            notes.append(f"tilts not checked against the views: fewer than "
                         f"{MIN_TILT_CHECK_POINTS} points on the reference surface")
        else:
            calib["tilt_check"] = chk.to_dict()
            notes += [chk.message] if chk.message else []
        if pts.shape[1] >= 3:
            calib["pair_consistency"], pair_notes = pair_consistency_summary(
                pts, tilt, sigma_views, exp.pixel_size_um, axis_used)
            notes += pair_notes
    if exp.stereo.camera != "perspective" and n_boot:
        sig_boot = surface.bootstrap_heights(pts, tilt, exp.pixel_size_um, n_boot=n_boot,
                                             seed=seed, tilt_axis_deg=axis_used,
                                             progress=progress, reference=ref)
        z_err = np.sqrt(z_err ** 2 + np.asarray(sig_boot, float) ** 2)
    z = ref.heights(xyz_3d)
    xyz = np.column_stack([xyz_3d[:, :2], z])
    if partial is not None and len(partial) and exp.stereo.camera != "perspective":
        pp, xyz_p, zerr_p, sig_p = fewer_view_heights(pts, partial, tilt, exp.pixel_size_um,
                                                      axis_used, ref)
        pts, xyz = np.concatenate([pts, pp]), np.concatenate([xyz, xyz_p])
        z_err, sigma_px = np.concatenate([z_err, zerr_p]), np.concatenate([sigma_px, sig_p])
        kind = np.concatenate([kind, np.full(len(pp), "auto")])
        idx = np.concatenate([idx, np.full(len(pp), -1)])
        # the reference surface was chosen among the complete points: the others are not
        # its inliers (its arrays follow the points)
        ref = replace(ref, inliers=np.concatenate([ref.inliers, np.zeros(len(pp), bool)]))
        notes.append(f"{len(pp)} automatic points matched in the reference view and at least "
                     f"one other but not in all {pts.shape[1]}: heights from their own views "
                     "(z_err_um: matching σ only, no bootstrap)")
    calib.update(tilt_deg=tilt, tilt_source=tilt_source, tilt_sigma_deg=tilt_sigma,
                 tilt_axis_deg=axis_used, reference_plane=np.asarray(ref.plane),
                 reference_surface=ref.to_dict())
    n = len(pts)
    clicked = idx >= 0
    point_id = np.empty(n, int)
    crack = np.full(n, -1)
    start = 0
    if corr is not None:
        point_id[clicked] = np.asarray(corr.point_id)[idx[clicked]]
        if corr.crack_id is not None:
            crack[clicked] = np.asarray(corr.crack_id)[idx[clicked]]
        start = int(np.max(corr.point_id)) + 1 if len(corr.point_id) else 0
    point_id[~clicked] = start + np.arange((~clicked).sum())
    n_views = np.isfinite(pts[..., 0]).sum(axis=1)
    few = n_views < pts.shape[1]
    if few.any():   # they come last: point_id from first_point_id on
        calib["fewer_views"] = {
            "n_points": int(few.sum()), "first_point_id": int(point_id[few][0]),
            "n_views": {str(k): int(np.sum(n_views == k)) for k in range(2, pts.shape[1])},
            "z_err_um": "matching σ of the point's own views only (no bootstrap)"}
    return StereoResult(point_id=point_id.astype(int), pts=pts, kind=kind, crack_id=crack.astype(int),
                        xyz_um=xyz, z_err_um=z_err, sigma_px=sigma_px, tilt_deg=np.asarray(tilt),
                        tilt_source=tilt_source, tilt_sigma_deg=np.asarray(tilt_sigma),
                        tilt_axis_deg=axis_used, calibration=calib, method=method, notes=notes,
                        reference=ref)


def write_stereo_results(result, out_dir, overwrite=False):
    """Write ``points3d.csv`` and ``calibration.json`` into ``out_dir``.

    ``points3d.csv`` columns: ``point_id,x_px,y_px,x_um,y_um,z_um,z_err_um,n_views`` with
    pixel coordinates in view 0 and the number of views each point was matched in
    (:attr:`StereoResult.n_views`).
    """
    from . import surface

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    p = out / "points3d.csv"
    surface.write_points3d_csv(p, result.point_id, result.pts[:, 0], result.xyz_um,
                               result.z_err_um, overwrite=overwrite, n_views=result.n_views)
    c = out / "calibration.json"
    if c.exists() and not overwrite:
        raise SemlabError(f"{c}: exists already; write results to a new folder")
    cal = dict(result.calibration)
    cal["notes"] = list(result.notes)
    c.write_text(json.dumps(_jsonable(cal), indent=1))
    return p, c
