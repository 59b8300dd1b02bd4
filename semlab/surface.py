"""Surface analysis of reconstructed points: reference surface, heights, errors, profiles, CSV.

Points are ``xyz_um`` : ``(N, 3)`` arrays of ``(x, y, z)`` in µm in the material frame of
:mod:`semlab.camera` (x, y in the surface plane, z toward the detector). Heights are measured
vertically from a reference plane ``z = a x + b y + c`` (:func:`reference_surface`): by
default the dominant flat surface, or a named region, or three picked points; positive =
extrusion, negative = intrusion.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats
from tqdm.auto import tqdm

from .errors import GeometryError, SemlabError
from .metrology import _segment, crack_lines
from .plane import (_as_xyz, fit_reference_plane, heights_above_plane, plane_through_points,
                    ransac_plane)
from .reconstruct import heights_from_tilts

__all__ = [
    "POINTS3D_COLUMNS",
    "ReferenceSurface",
    "reference_surface",
    "region_mask",
    "fit_reference_plane",
    "heights_above_plane",
    "plane_through_points",
    "ransac_plane",
    "height_sigma",
    "bootstrap_heights",
    "profile_along_line",
    "crack_profiles",
    "height_trend",
    "write_points3d_csv",
    "read_points3d_csv",
]

POINTS3D_COLUMNS = ("point_id", "x_px", "y_px", "x_um", "y_um", "z_um", "z_err_um", "n_views")
#: Matched points averaged around each picked point of a three-point reference plane.
THREE_POINT_NEIGHBOURS = 5


# ----------------------------------------------------------------------------- reference surface

def _region_kind(region):
    if isinstance(region, (str, Path)):
        return "mask"
    r = np.asarray(region)
    if r.dtype == bool and r.ndim == 2:
        return "mask"
    if r.ndim == 1 and r.size == 4:
        return "rectangle"
    if r.ndim == 2 and r.shape[1] == 2 and r.shape[0] >= 3:
        return "polygon"
    raise GeometryError(
        f"a reference region is a rectangle [x0, y0, x1, y1], a polygon [[x, y], ...] (3+ "
        f"vertices) in view-0 pixels, or a mask image path; got {region!r}")


def region_mask(region, xy_px):
    """Which points lie in a reference region of view 0.

    Parameters
    ----------
    region : (4,) array_like, (K, 2) array_like, str/Path or (H, W) bool array
        ``[x0, y0, x1, y1]`` rectangle (pixels, inclusive), polygon vertices ``(x, y)``
        pixels (K >= 3), or a mask image (a path to an image, non-zero = in the region,
        or a boolean array) indexed ``[row, col]`` like view 0.
    xy_px : (N, 2) array
        Point positions ``(x, y)`` in view-0 pixels.

    Returns
    -------
    (N,) bool array
    """
    xy = np.asarray(xy_px, float).reshape(-1, 2)
    kind = _region_kind(region)
    if kind == "rectangle":
        x0, y0, x1, y1 = np.asarray(region, float)
        if not (x1 > x0 and y1 > y0):
            raise GeometryError(f"reference rectangle {list(region)} must have x1 > x0 and y1 > y0")
        return (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
    if kind == "polygon":
        from matplotlib.path import Path as MplPath

        return MplPath(np.asarray(region, float)).contains_points(xy)
    if isinstance(region, (str, Path)):
        from .io import read_image

        m = read_image(region).data != 0
    else:
        m = np.asarray(region, bool)
    col = np.clip(np.rint(xy[:, 0]).astype(int), 0, m.shape[1] - 1)
    row = np.clip(np.rint(xy[:, 1]).astype(int), 0, m.shape[0] - 1)
    inside = (xy[:, 0] > -0.5) & (xy[:, 0] < m.shape[1] - 0.5) & (xy[:, 1] > -0.5) \
        & (xy[:, 1] < m.shape[0] - 0.5)
    return inside & m[row, col]


@dataclass
class ReferenceSurface:
    """The plane heights are measured from, and how it was chosen.

    Attributes
    ----------
    plane : (3,) array
        ``(a, b, c)`` of ``z = a x + b y + c`` (µm, in the frame of ``xyz_um``).
    method : str
        ``"dominant_plane"`` (RANSAC over all points), ``"region"`` (RANSAC over the points
        in a named region), ``"three_points"`` (plane through three picked points) or
        ``"robust_all"`` (no flat set of 10+ points: the robust plane of all points).
    inliers : (N,) bool array
        The points that define the plane.
    residual_rms_um : float
        RMS height of the inliers above the plane.
    spread_um : float
        5–95 % range of the inliers' heights.
    sigma_um : float
        Median 1σ height error of the inliers (NaN when no σ was given).
    threshold_um : float
        RANSAC inlier threshold (median over the points), NaN where none was used.
    detail : dict
        JSON-ready description of the choice (region, picked points, k_sigma).
    """

    plane: np.ndarray
    method: str
    inliers: np.ndarray
    residual_rms_um: float
    spread_um: float
    sigma_um: float
    threshold_um: float = np.nan
    detail: dict = field(default_factory=dict)
    neighbours: list = field(default_factory=list, repr=False)

    @property
    def n_inliers(self):
        return int(np.count_nonzero(self.inliers))

    def heights(self, xyz_um):
        """Heights ``(N,)`` µm of points above this plane."""
        return heights_above_plane(xyz_um, self.plane)

    def refit(self, xyz_um, index=None):
        """The same choice applied to other coordinates of the same points (bootstrap).

        ``index`` (M,) selects a resample of the points (None: all); the inlier set is kept.
        """
        p = np.asarray(xyz_um, float)
        idx = np.arange(len(p)) if index is None else np.asarray(index)
        if self.method == "three_points":
            return plane_through_points(np.array([p[nb].mean(axis=0) for nb in self.neighbours]))
        if self.method == "robust_all":
            return fit_reference_plane(p[idx])
        sel = idx[self.inliers[idx]]
        return fit_reference_plane(p[sel], robust=False)

    def to_dict(self):
        """JSON-ready record for ``calibration.json``."""
        return {"method": self.method, "plane": [float(v) for v in self.plane],
                "plane_form": "z_um = a x_um + b y_um + c", "n_inliers": self.n_inliers,
                "n_points": int(len(self.inliers)), "residual_rms_um": self.residual_rms_um,
                "spread_5_95_um": self.spread_um, "sigma_um": self.sigma_um,
                "threshold_um": self.threshold_um, **self.detail}


def _describe_region(region):
    kind = _region_kind(region)
    if kind == "mask":
        return {"region": "mask", "mask": str(region) if isinstance(region, (str, Path))
                else "array"}
    return {"region": kind, f"{kind}_px": np.asarray(region, float).tolist()}


def reference_surface(xyz_um, z_sigma_um=None, xy_px=None, region=None, three_points_px=None,
                      k_sigma=3.0, n_iter=1000, seed=0):
    """Choose the reference plane of a reconstructed surface.

    - default: the dominant flat surface, :func:`semlab.plane.ransac_plane` with the
      inlier threshold ``k_sigma`` times each point's own height σ (``z_sigma_um``; None:
      estimated from the points), refitted by weighted least squares on the inliers. A
      tall object, or rough regions covering much of the view, do not tilt it.
    - ``region``: the same dominant plane, among the points whose view-0 position lies in
      the region (:func:`region_mask`), so that the region's own relief (grooves, pits)
      is measured rather than levelled away; the robust plane of the region's points
      (:func:`semlab.plane.fit_reference_plane`) if no 10 of them are coplanar.
    - ``three_points_px``: the plane through three picked view-0 positions (Gwyddion's
      three-point levelling); each picked point's ``(x, y, z)`` is the mean of its
      :data:`THREE_POINT_NEIGHBOURS` nearest matched points.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Points ``(x, y, z)`` µm.
    z_sigma_um : None, float or (N,) array_like
        1σ height error of each point, µm.
    xy_px : (N, 2) array, optional
        View-0 pixel positions ``(x, y)``; needed with ``region`` or ``three_points_px``.
    region : see :func:`region_mask`, optional
    three_points_px : (3, 2) array_like, optional
        Picked ``(x, y)`` view-0 pixels.
    k_sigma, n_iter, seed
        RANSAC threshold (σ), samples and seed.

    Returns
    -------
    ReferenceSurface

    Raises
    ------
    GeometryError
        Too few points in the region, collinear points, no dominant plane.
    """
    p = _as_xyz(xyz_um)
    n = len(p)
    sig = None if z_sigma_um is None else np.broadcast_to(np.asarray(z_sigma_um, float), (n,))
    if (region is not None or three_points_px is not None) and xy_px is None:
        raise GeometryError("a reference region or three points need xy_px, the view-0 pixel "
                            "positions of the points")
    if region is not None and three_points_px is not None:
        raise GeometryError("give either a reference region or three reference points, not both")
    threshold, neighbours = np.nan, []
    if three_points_px is not None:
        picks = np.asarray(three_points_px, float)
        if picks.shape != (3, 2):
            raise GeometryError(f"three reference points must be [[x, y]] x 3 pixels, got "
                                f"{three_points_px!r}")
        xy = np.asarray(xy_px, float)
        k = min(THREE_POINT_NEIGHBOURS, n)
        neighbours = [np.argsort(np.hypot(*(xy - q).T))[:k] for q in picks]
        plane = plane_through_points(np.array([p[nb].mean(axis=0) for nb in neighbours]))
        inl = np.zeros(n, bool)
        inl[np.concatenate(neighbours)] = True
        method = "three_points"
        detail = {"three_points_px": picks.tolist(), "neighbours": k}
    elif region is not None:
        inr = region_mask(region, xy_px)
        if inr.sum() < 3:
            raise GeometryError(f"only {int(inr.sum())} matched points lie in the reference "
                                f"region {_describe_region(region)}: it needs 3 or more")
        method, detail = "region", _describe_region(region)
        detail["n_in_region"] = int(inr.sum())
        try:  # the dominant plane of the region: its own relief (grooves) is not levelled
            plane, m, used = ransac_plane(p[inr], None if sig is None else sig[inr],
                                          k_sigma=k_sigma, n_iter=n_iter, seed=seed,
                                          min_inliers=min(10, int(inr.sum())))
            threshold = float(k_sigma * np.median(used))
            inl = np.zeros(n, bool)
            inl[np.flatnonzero(inr)[m]] = True
        except GeometryError:  # no flat set in the region: its robust plane
            plane, inl = fit_reference_plane(p[inr]), inr
    else:
        try:
            plane, inl, used = ransac_plane(p, sig, k_sigma=k_sigma, n_iter=n_iter, seed=seed,
                                            min_inliers=min(10, n))
            threshold = float(k_sigma * np.median(used))
            method = "dominant_plane"
            detail = {"k_sigma": k_sigma, "sigma_from": "points" if sig is None else "given"}
        except GeometryError as exc:  # no flat set: the robust plane of everything, said so
            plane = fit_reference_plane(p)
            inl = np.abs(heights_above_plane(p, plane)) <= k_sigma * (
                np.median(sig) if sig is not None else np.std(heights_above_plane(p, plane)))
            inl = inl if inl.sum() else np.ones(n, bool)
            method, detail = "robust_all", {"reason": str(exc)}
    h = heights_above_plane(p[inl], plane)
    q5, q95 = np.percentile(h, [5, 95])
    return ReferenceSurface(
        plane=np.asarray(plane, float), method=method, inliers=inl,
        residual_rms_um=float(np.sqrt(np.mean(h ** 2))), spread_um=float(q95 - q5),
        sigma_um=np.nan if sig is None else float(np.median(sig[inl])),
        threshold_um=threshold, detail=detail, neighbours=neighbours)


# ----------------------------------------------------------------------------- heights and errors

def height_sigma(sigma_px, tilt_deg, pixel_size_um):
    """1σ height error propagated from per-point matching σ (first-order, known tilts).

    Each view gives ``u_i = (x cos θ_i + z sin θ_i)/s``, i.e. ``u = A (x, z)`` with
    ``A = [cos θ_i, sin θ_i]/s``; the weighted least-squares covariance is
    ``(Aᵀ Σ⁻¹ A)⁻¹`` with ``Σ = diag(σ_i²)`` (H&Z 2nd ed. §5.2). For two views this is::

        σ_z = s sqrt(σ0² cos²θ1 + σ1² cos²θ0) / |sin(θ1 - θ0)|

    i.e. ``s cos θ sqrt(σ0² + σ1²) / sin Δθ`` for a symmetric pair — the parallax σ
    ``sqrt(σ0² + σ1²)`` turned into height. The per-view offset estimate and the plane
    fit add an O(1/N) error common to all points, not included.

    Parameters
    ----------
    sigma_px : float or array_like
        1σ error of the x pixel coordinate of the matches: a scalar (all points, all
        views), ``(N,)`` (per point, same in every view) or ``(N, V)`` / ``(1, V)``;
        ``inf`` for a view the point was not matched in (it does not count).
    tilt_deg : (V,) array_like
        Tilts, degrees.
    pixel_size_um : float
        Pixel size, µm/px.

    Returns
    -------
    float or (N,) array
        1σ z error in µm (float for a scalar ``sigma_px``).
    """
    th = np.deg2rad(np.asarray(tilt_deg, float).ravel())
    v = th.size
    if v < 2 or np.ptp(np.sin(th)) < 1e-9:
        raise GeometryError(f"need at least two different tilts, got {np.rad2deg(th).tolist()}")
    if pixel_size_um is None or not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise GeometryError(f"pixel_size_um must be a positive number, got {pixel_size_um!r}")
    sig = np.asarray(sigma_px, float)
    scalar = sig.ndim == 0
    if sig.ndim <= 1:
        sig = sig.reshape(-1, 1)
    if sig.ndim != 2 or sig.shape[1] not in (1, v):
        raise GeometryError(
            f"sigma_px must be a scalar, (N,) or (N, {v}) pixels, got shape {np.shape(sigma_px)}")
    if np.any(np.isnan(sig)) or np.any(sig <= 0) or np.any(np.isneginf(sig)):
        raise GeometryError("sigma_px must be positive (and finite, or +inf for a view a "
                            "point was not matched in)")
    sig = np.broadcast_to(sig, (sig.shape[0], v))
    s = float(pixel_size_um)
    c, si = np.cos(th) / s, np.sin(th) / s
    w = 1.0 / sig ** 2  # (N, V); 0 for a view not matched (σ = inf)
    m00 = w @ (c * c)
    m01 = w @ (c * si)
    m11 = w @ (si * si)
    det = m00 * m11 - m01 ** 2
    if np.any(~(det > 1e-12 * np.maximum(m00 * m11, 1e-300))):
        raise GeometryError("sigma_px leaves a point with fewer than two views of different "
                            "tilts (finite σ): its height is not defined")
    var_z = m00 / det
    out = np.sqrt(var_z)
    return float(out[0]) if scalar else out


def bootstrap_heights(pts, tilt_deg, pixel_size_um, n_boot=200, seed=0, sigma_px=None,
                      tilt_axis_deg=90.0, progress=True, reference=None):
    """Bootstrap 1σ of the height above the reference plane of every point.

    Each resample draws the points with replacement, estimates the per-view offsets and
    fits the reference plane on them (``reference``: the same choice,
    :meth:`ReferenceSurface.refit`; None: the robust plane of all points), and evaluates the
    height of *all* points;
    with ``sigma_px`` the matches are also perturbed by Gaussian noise of that σ (x and y).
    The per-view offsets only shift all ``(x, z)`` by one constant (see
    :func:`semlab.reconstruct.heights_from_tilts`), which the plane absorbs exactly, so
    resampling the plane fit covers the offset estimation too.

    Parameters
    ----------
    pts : (N, V, 2) array
        Matches, pixels (point, view, xy).
    tilt_deg : (V,) array_like
        Tilts, degrees.
    pixel_size_um : float
        Pixel size, µm/px.
    n_boot : int
        Number of resamples (>= 2).
    seed : int
        Random seed.
    sigma_px : None, float, (N,) or (N, V) array_like
        Matching 1σ in pixels to add as noise (None: resample points only).
    tilt_axis_deg : float
        See :func:`semlab.reconstruct.heights_from_tilts`.
    progress : bool
        tqdm progress bar.
    reference : ReferenceSurface, optional
        How the reference plane was chosen (:func:`reference_surface`).

    Returns
    -------
    (N,) array
        Standard deviation of the height of each point over the resamples, µm.
    """
    if int(n_boot) < 2:
        raise GeometryError(f"n_boot must be >= 2, got {n_boot}")
    base = heights_from_tilts(pts, tilt_deg, pixel_size_um, tilt_axis_deg=tilt_axis_deg)
    p = np.asarray(pts, float)
    n, v = p.shape[:2]
    if n < 3:
        raise GeometryError(f"need at least 3 points for a reference plane, got {n}")
    noise = None
    if sigma_px is not None:
        sig = np.asarray(sigma_px, float)
        if sig.ndim <= 1:
            sig = sig.reshape(-1, 1)
        try:
            noise = np.broadcast_to(sig, (n, v))[:, :, None]
        except ValueError:
            raise GeometryError(
                f"sigma_px must be a scalar, ({n},) or ({n}, {v}) pixels, got shape "
                f"{np.shape(sigma_px)}") from None
    rng = np.random.default_rng(seed)
    z = np.empty((int(n_boot), n))
    for k in tqdm(range(int(n_boot)), disable=not progress, desc="height bootstrap"):
        xyz = base.xyz_um
        if noise is not None:
            pb = p + rng.normal(size=p.shape) * noise
            xyz = heights_from_tilts(pb, tilt_deg, pixel_size_um,
                                     tilt_axis_deg=tilt_axis_deg).xyz_um
        idx = rng.integers(0, n, n)
        try:
            plane = fit_reference_plane(xyz[idx]) if reference is None \
                else reference.refit(xyz, idx)
        except GeometryError:  # a degenerate (collinear) resample
            z[k] = np.nan
            continue
        z[k] = heights_above_plane(xyz, plane)
    return np.nanstd(z, axis=0, ddof=1)


def profile_along_line(xy_um, z_um, p0_um, p1_um, width_um, n_bins=None):
    """Height profile of the points in a strip along the segment ``p0 → p1``.

    Parameters
    ----------
    xy_um : (N, 2) array
        In-plane positions ``(x, y)`` µm.
    z_um : (N,) array
        Heights µm.
    p0_um, p1_um : (2,) array_like
        Segment end points ``(x, y)`` µm (e.g. across a crack).
    width_um : float
        Full width of the strip: points with ``|offset| <= width_um / 2`` from the line and
        ``0 <= distance <= |p1 - p0|`` along it are kept.
    n_bins : int, optional
        Also return binned statistics over ``[0, |p1 - p0|]``.

    Returns
    -------
    dict
        ``distance_um`` (M,) along the line from ``p0`` (sorted ascending), ``offset_um``
        (M,) signed distance from the line (positive to the left of ``p0 → p1`` with y
        down, i.e. toward ``d`` rotated by -90°), ``z_um`` (M,), ``index`` (M,) into the
        input; with ``n_bins``: ``bin_center_um``, ``bin_mean_um``, ``bin_std_um`` (NaN for
        empty bins), ``bin_count``.
    """
    xy = np.asarray(xy_um, float)
    z = np.asarray(z_um, float).ravel()
    if xy.ndim != 2 or xy.shape[1] != 2 or z.shape[0] != xy.shape[0]:
        raise GeometryError(
            f"xy_um must be (N, 2) and z_um (N,), got {xy.shape} and {np.shape(z_um)}")
    p0, p1, length = _segment(p0_um, p1_um, "p0_um and p1_um", "pairs in µm",
                              "a segment of non-zero length")
    if not np.isfinite(width_um) or width_um <= 0:
        raise GeometryError(f"width_um must be positive, got {width_um!r}")
    d = (p1 - p0) / length
    rel = xy - p0
    along = rel @ d
    across = rel[:, 0] * d[1] - rel[:, 1] * d[0]
    keep = ((along >= 0) & (along <= length) & (np.abs(across) <= width_um / 2)
            & np.isfinite(z) & np.all(np.isfinite(xy), axis=1))
    idx = np.nonzero(keep)[0]
    idx = idx[np.argsort(along[idx], kind="stable")]
    out = {"distance_um": along[idx], "offset_um": across[idx], "z_um": z[idx], "index": idx}
    if n_bins is not None:
        nb = int(n_bins)
        if nb < 1:
            raise GeometryError(f"n_bins must be >= 1, got {n_bins}")
        edges = np.linspace(0.0, length, nb + 1)
        b = np.clip(np.searchsorted(edges, out["distance_um"], side="right") - 1, 0, nb - 1)
        cnt = np.bincount(b, minlength=nb)
        s1 = np.bincount(b, weights=out["z_um"], minlength=nb)
        s2 = np.bincount(b, weights=out["z_um"] ** 2, minlength=nb)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s1 / cnt
            std = np.sqrt(np.maximum(s2 / cnt - mean ** 2, 0.0))
        out.update(bin_center_um=(edges[:-1] + edges[1:]) / 2, bin_mean_um=mean,
                   bin_std_um=std, bin_count=cnt)
    return out


def crack_profiles(xyz_um, z_um, crack_id, width_um=1.0):
    """Height profiles along each clicked crack.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Points' material ``(x, y, z)``, µm (``StereoResult.xyz_um``).
    z_um : (N,) array
        Their heights above the reference surface, µm.
    crack_id : (N,) int array or None
        The crack each point lies on, ``-1`` for none (``StereoResult.crack_id``).
    width_um : float
        Full width of the strip around each crack's line whose points are profiled.

    Returns
    -------
    list of (int, dict)
        ``(crack_id, profile)`` for every crack with two or more distinct points: the
        :func:`profile_along_line` along the total least-squares line through its points
        (:func:`semlab.metrology.crack_lines`), between their extreme projections. Empty
        without such a crack.
    """
    if crack_id is None:
        return []
    xy = np.asarray(xyz_um, float)[:, :2]
    return [(cid, profile_along_line(xy, z_um, p0, p1, width_um=width_um))
            for cid, p0, p1 in crack_lines(xy, crack_id)]


def height_trend(xyz_um):
    """Trend of height with position: robust slopes and correlations.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Points ``(x, y, z)`` µm (z raw, or heights above the plane to look for where the
        extrusions are, e.g. more extrusion at high y).

    Returns
    -------
    dict
        ``dz_dx``, ``dz_dy`` (µm/µm, from :func:`fit_reference_plane`, robust),
        ``pearson_r_x``, ``pearson_p_x``, ``pearson_r_y``, ``pearson_p_y``,
        ``spearman_r_x``, ``spearman_p_x``, ``spearman_r_y``, ``spearman_p_y``, ``n``.
    """
    p = _as_xyz(xyz_um, min_points=3)
    if np.ptp(p[:, 2]) == 0:
        raise GeometryError("all heights are equal: correlations are undefined")
    a, b, _ = fit_reference_plane(p)
    out = {"dz_dx": float(a), "dz_dy": float(b), "n": int(len(p))}
    for name, col in (("x", 0), ("y", 1)):
        pr = stats.pearsonr(p[:, col], p[:, 2])
        sr = stats.spearmanr(p[:, col], p[:, 2])
        out[f"pearson_r_{name}"] = float(pr[0])
        out[f"pearson_p_{name}"] = float(pr[1])
        out[f"spearman_r_{name}"] = float(sr[0])
        out[f"spearman_p_{name}"] = float(sr[1])
    return out


def write_points3d_csv(path, point_id, pts_px, xyz_um, z_err_um, overwrite=False, *,
                       n_views=None):
    """Write ``points3d.csv`` with columns :data:`POINTS3D_COLUMNS`
    (``point_id,x_px,y_px,x_um,y_um,z_um,z_err_um,n_views``).

    Parameters
    ----------
    path : str or Path
        Output file; an existing file is refused unless ``overwrite=True``.
    point_id : (N,) array_like
        Unique point identifiers (ints or strings without commas).
    pts_px : (N, 2) or (N, V, 2) array
        Pixel ``(x, y)`` of each point in view 0 (view 0 is taken from ``(N, V, 2)``).
    xyz_um : (N, 3) array
        ``(x, y, z)`` µm (z usually the height above the reference plane).
    z_err_um : (N,) array_like or float
        1σ height error, µm (NaN allowed when unknown).
    n_views : (N,) array_like of int
        Number of views each point was matched in (its height comes from those), >= 1.
        Required (e.g. :attr:`semlab.pipeline.StereoResult.n_views`).

    Returns
    -------
    Path
        The written path.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise SemlabError(f"{path} already exists: pass overwrite=True or choose another path")
    ids = np.asarray(point_id).ravel()
    n = ids.size
    px = np.asarray(pts_px, float)
    if px.ndim == 3 and px.shape[2] == 2:
        px = px[:, 0, :]
    xyz = np.asarray(xyz_um, float)
    err = np.broadcast_to(np.asarray(z_err_um, float), (n,)) if np.ndim(z_err_um) == 0 \
        else np.asarray(z_err_um, float).ravel()
    if n_views is None:
        raise SemlabError("n_views is required: the number of views each point was matched in")
    nv = np.asarray(n_views)
    if px.shape != (n, 2) or xyz.shape != (n, 3) or err.shape != (n,) or nv.shape != (n,):
        raise SemlabError(
            f"inconsistent lengths: point_id {ids.shape}, pts_px {np.shape(pts_px)}, xyz_um "
            f"{np.shape(xyz_um)}, z_err_um {np.shape(z_err_um)}, n_views {nv.shape}; "
            f"expected N={n} rows each")
    if n and (nv.dtype.kind not in "iu" or nv.min() < 1):
        raise SemlabError(f"n_views must be integers >= 1, got {nv.dtype} values")
    if len(set(ids.tolist())) != n:
        raise SemlabError("point_id has duplicates: each point needs a unique id")
    if any("," in str(i) or "\n" in str(i) for i in ids.tolist()):
        raise SemlabError("point_id values must not contain commas or newlines")
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        wr = csv.writer(fh, lineterminator="\n")
        wr.writerow(POINTS3D_COLUMNS)
        for i in range(n):
            wr.writerow([ids[i], *(f"{val:.10g}" for val in (*px[i], *xyz[i], err[i])),
                         int(nv[i])])
    return path


def read_points3d_csv(path):
    """Read a ``points3d.csv`` written by :func:`write_points3d_csv`.

    Files from before the ``n_views`` column (2026-12-03: the other columns only) are read
    too, without an ``n_views`` entry.

    Returns
    -------
    dict
        One array per column of the file; ``point_id`` is int64 when every id is an
        integer, otherwise str; ``n_views`` int64; the others are float (N,).
    """
    path = Path(path)
    if not path.is_file():
        raise SemlabError(f"{path} does not exist or is not a file")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    cols = tuple(h.strip() for h in rows[0]) if rows else ()
    if cols not in (POINTS3D_COLUMNS, POINTS3D_COLUMNS[:-1]):
        raise SemlabError(
            f"{path} is not a points3d.csv: the header must be {','.join(POINTS3D_COLUMNS)}")
    body = [r for r in rows[1:] if r]
    if any(len(r) != len(cols) for r in body):
        raise SemlabError(f"{path}: every row needs {len(cols)} fields")
    ids = [r[0] for r in body]
    try:
        id_arr = np.array([int(i) for i in ids], dtype=np.int64)
    except ValueError:
        id_arr = np.array(ids, dtype=str)
    try:
        vals = np.array([[float(x) for x in r[1:7]] for r in body], dtype=float).reshape(-1, 6)
        nv = np.array([int(r[7]) for r in body], dtype=np.int64) if len(cols) == 8 else None
    except ValueError as exc:
        raise SemlabError(f"{path}: non-numeric value ({exc})") from None
    out = {"point_id": id_arr}
    for k, name in enumerate(POINTS3D_COLUMNS[1:7]):
        out[name] = vals[:, k]
    if nv is not None:
        out["n_views"] = nv
    return out
