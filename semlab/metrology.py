"""Surface metrology of a dense height map: ISO 25178 areal parameters, slip-band profiles.

- :func:`surface_parameters`: Sa, Sq, Sp, Sv, Sz, Ssk, Sku, Sdr (ISO 25178-2) of the whole
  map and of named regions, computed by the maintained ``surfalize`` package. The map is
  already the scale-limited surface above the reference plane (no further levelling or
  filtering). Non-measured pixels (NaN) are excluded: they are masked for the height
  parameters, and filled with their nearest measured value for Sdr (surfalize needs a
  complete grid for the area; the filled pixels are flat copies, so they add little area).
- Slip markings: a :class:`Band` is a straight trace (from the ``crack_id`` of clicked
  points, :func:`bands_from_clicks`, or detected in the map, :func:`detect_bands`);
  :func:`band_profile` averages the map along the trace into a profile across it and
  measures extrusion height, intrusion depth and width with their 1σ.
- :func:`profile_between`: the height profile (with its 1σ band) between two points, for
  the interactive profile tool (:mod:`semlab.profile_tool`).

Coordinates: maps ``[row, col]``; points ``(x, y)`` in view-0 pixels; lengths in µm.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import GeometryError, SemlabError

__all__ = [
    "SURFACE_PARAMETERS",
    "BANDS_COLUMNS",
    "surface_parameters",
    "regions_on_map",
    "write_surface_parameters_csv",
    "Band",
    "bands_from_clicks",
    "detect_bands",
    "map_bands",
    "band_profile",
    "write_bands_csv",
    "profile_between",
]

SURFACE_PARAMETERS = ("Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku", "Sdr")
BANDS_COLUMNS = ("band_id", "source", "x0_px", "y0_px", "x1_px", "y1_px", "angle_deg",
                 "length_um", "extrusion_um", "extrusion_err_um", "intrusion_um",
                 "intrusion_err_um", "width_um", "width_err_um", "n_pixels")


def _as_map(z, name="z_um", keep_float32=False):
    a = np.asarray(z)
    a = a if keep_float32 and a.dtype == np.float32 else a.astype(float, copy=False)
    if a.ndim != 2 or min(a.shape) < 2:
        raise SemlabError(f"{name} must be a 2D height map, got shape {a.shape}")
    return a


def _segment(p0, p1, names, pairs, segment):
    """Ends (2,) and length of a profile segment, refused unless two finite, distinct (x, y)
    points; ``names``, ``pairs`` and ``segment`` word the errors."""
    p0 = np.asarray(p0, float).ravel()
    p1 = np.asarray(p1, float).ravel()
    if p0.shape != (2,) or p1.shape != (2,) or not np.all(np.isfinite(np.r_[p0, p1])):
        raise GeometryError(f"{names} must be finite (x, y) {pairs}")
    length = float(np.hypot(*(p1 - p0)))
    if length == 0:
        raise GeometryError(f"{names} are the same point: give {segment}")
    return p0, p1, length


def _fill_nearest(z):
    """Each NaN pixel takes the value of its nearest finite pixel."""
    from scipy import ndimage

    bad = ~np.isfinite(z)
    if not bad.any():
        return z
    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    return z[tuple(idx)]


def _region_mask(region, shape, name):
    if isinstance(region, np.ndarray) and region.dtype == bool:
        if region.shape != shape:
            raise SemlabError(f"region {name!r}: mask shape {region.shape} is not the map's "
                              f"{shape}")
        return region
    r = tuple(int(v) for v in region)
    if len(r) != 4 or not (0 <= r[0] < r[2] <= shape[1] and 0 <= r[1] < r[3] <= shape[0]):
        raise SemlabError(f"region {name!r} must be a bool mask or (x0, y0, x1, y1) pixels "
                          f"inside the {shape[1]}×{shape[0]} map, got {region!r}")
    m = np.zeros(shape, bool)
    m[r[1]:r[3], r[0]:r[2]] = True
    return m


def regions_on_map(regions, roi):
    """Named regions of view 0 as bool masks of a map over ``roi``.

    Parameters
    ----------
    regions : dict name -> region
        As ``[metrology] regions`` of an experiment (:attr:`Experiment.metrology_regions`):
        a rectangle ``[x0, y0, x1, y1]`` (inclusive), a polygon ``[[x, y], ...]`` or a mask
        image (path or ``(H, W)`` array, non-zero inside), view-0 pixels; the semantics of
        :func:`semlab.surface.region_mask` (the ``[stereo] reference_region`` parser).
    roi : (x0, y0, x1, y1)
        Half-open window of view-0 pixels the map covers (``HeightMap.roi``).

    Returns
    -------
    dict name -> (y1 - y0, x1 - x0) bool array
        Pixel ``[i, j]`` is view-0 pixel ``(x0 + j, y0 + i)``; a region outside the map is
        all False (its row in ``surface_parameters.csv`` is then NaN).
    """
    from pathlib import Path

    from .io import read_image
    from .surface import region_mask

    x0, y0, x1, y1 = (int(v) for v in roi)
    out = {}
    for name, reg in (regions or {}).items():
        m = np.zeros((y1 - y0, x1 - x0), bool)
        if isinstance(reg, (str, Path)) or (isinstance(reg, np.ndarray) and reg.ndim == 2
                                            and reg.shape[1] != 2):
            a = read_image(reg).data if isinstance(reg, (str, Path)) else np.asarray(reg)
            m[:] = a[y0:y1, x0:x1] != 0
        else:
            # only the pixels of the region's bounding box are tested
            xy = np.asarray(reg, float).reshape(-1, 2)
            bx0, by0 = max(x0, int(np.floor(xy[:, 0].min()))), max(y0, int(np.floor(xy[:, 1].min())))
            bx1 = min(x1, int(np.ceil(xy[:, 0].max())) + 1)
            by1 = min(y1, int(np.ceil(xy[:, 1].max())) + 1)
            if bx1 > bx0 and by1 > by0:
                gx, gy = np.meshgrid(np.arange(bx0, bx1, dtype=float),
                                     np.arange(by0, by1, dtype=float))
                inside = region_mask(reg, np.column_stack([gx.ravel(), gy.ravel()]))
                m[by0 - y0:by1 - y0, bx0 - x0:bx1 - x0] = inside.reshape(gx.shape)
        out[str(name)] = m
    return out


def surface_parameters(z_um, pixel_size_um, regions=None, min_pixels=16):
    """ISO 25178-2 areal parameters of the map and of named regions (``surfalize``).

    Parameters
    ----------
    z_um : (H, W) array
        Heights µm above the reference surface, NaN where not measured.
    pixel_size_um : float
    regions : dict name -> (x0, y0, x1, y1) or (H, W) bool mask, optional
        Named regions (half-open pixel boxes or masks); ``"map"`` is always the whole map.
    min_pixels : int
        Regions with fewer measured pixels get NaN parameters.

    Returns
    -------
    list of dict
        One row per region: ``region``, ``n_pixels`` (measured), ``measured_fraction``,
        and the :data:`SURFACE_PARAMETERS` (heights in µm, ``Sdr`` in %).
    """
    from surfalize import Surface

    z = _as_map(z_um)
    s = float(pixel_size_um)
    if not np.isfinite(s) or s <= 0:
        raise SemlabError(f"pixel_size_um must be positive, got {pixel_size_um!r}")
    items = [("map", np.ones(z.shape, bool))]
    for name, reg in (regions or {}).items():
        if name == "map":
            raise SemlabError("region name 'map' is reserved for the whole map: rename it")
        items.append((str(name), _region_mask(reg, z.shape, name)))
    rows = []
    for name, m in items:
        meas = m & np.isfinite(z)
        row = {"region": name, "n_pixels": int(meas.sum()),
               "measured_fraction": float(meas.sum() / max(1, m.sum()))}
        if meas.sum() < min_pixels:
            row.update({k: np.nan for k in SURFACE_PARAMETERS})
            rows.append(row)
            continue
        ii, jj = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        sl = (slice(ii[0], ii[-1] + 1), slice(jj[0], jj[-1] + 1))
        crop = z[sl].copy()
        crop[~m[sl]] = np.nan
        filled = _fill_nearest(crop)
        if np.ptp(z[meas]) == 0:          # a perfectly flat region: Ssk, Sku undefined
            row.update(Sa=0.0, Sq=0.0, Sp=0.0, Sv=0.0, Sz=0.0, Ssk=np.nan, Sku=np.nan)
        else:
            hp = Surface(filled, s, s, mask=~meas[sl]).height_parameters()
            row.update({k: float(hp[k]) for k in ("Sa", "Sq", "Sp", "Sv", "Sz", "Ssk", "Sku")})
        row["Sdr"] = _sdr(filled, s)
        rows.append(row)
    return rows


def _sdr(z_um, pixel_size_um, strip_rows=256):
    """Sdr (%) of a gap-free map, surfalize's, summed over strips of ``strip_rows`` rows.

    The developed area (ISO 25178-2 D.3) and the projected area are sums over the grid's
    cells; strips that share their boundary row hold every cell once, so the sums, and Sdr,
    are the whole map's, while surfalize's work arrays (~9 copies of the map) are a strip's.
    """
    from surfalize import Surface

    area = projected = 0.0
    for r0 in range(0, max(1, z_um.shape[0] - 1), strip_rows):
        strip = Surface(z_um[r0:r0 + strip_rows + 1], pixel_size_um, pixel_size_um)
        area += strip.surface_area()
        projected += strip.projected_area()
    return float((area / projected - 1.0) * 100.0)


def write_surface_parameters_csv(path, rows):
    """Write the rows of :func:`surface_parameters` (``region,n_pixels,measured_fraction,
    Sa_um,Sq_um,Sp_um,Sv_um,Sz_um,Ssk,Sku,Sdr_percent``)."""
    cols = ["region", "n_pixels", "measured_fraction", "Sa_um", "Sq_um", "Sp_um", "Sv_um",
            "Sz_um", "Ssk", "Sku", "Sdr_percent"]
    keys = ["region", "n_pixels", "measured_fraction", "Sa", "Sq", "Sp", "Sv", "Sz", "Ssk",
            "Sku", "Sdr"]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(cols)
        for r in rows:
            w.writerow([_fmt(r[k]) for k in keys])
    return Path(path)


def _fmt(v):
    if isinstance(v, (float, np.floating)):
        return "" if not np.isfinite(v) else f"{float(v):.6g}"
    return str(v)


# ------------------------------------------------------------------------------ bands
@dataclass(frozen=True)
class Band:
    """A straight slip-band or crack trace in view-0 pixels.

    Attributes
    ----------
    band_id : int
    p0_px, p1_px : (x, y) tuples
        End points of the trace.
    source : str
        ``"crack_id"`` (from clicked points) or ``"detected"``.
    half_width_px : float
        Half length of the profiles across the trace.
    """

    band_id: int
    p0_px: tuple
    p1_px: tuple
    source: str = "detected"
    half_width_px: float = 25.0

    @property
    def angle_deg(self):
        """Trace direction, degrees from the image x axis (y down), in [0, 180)."""
        d = np.subtract(self.p1_px, self.p0_px)
        return float(np.degrees(np.arctan2(d[1], d[0])) % 180.0)


def line_through(points):
    """The total least-squares line through points, between their extreme projections.

    Parameters
    ----------
    points : (N, 2) array
        ``(x, y)`` in any one unit; rows with NaN are ignored.

    Returns
    -------
    (p0, p1) of (2,) arrays, or None
        The segment's end points (same unit); None with fewer than 2 finite points or when
        they all coincide (no direction).
    """
    q = np.asarray(points, float).reshape(-1, 2)
    q = q[np.all(np.isfinite(q), axis=1)]
    if len(q) < 2:
        return None
    mu = q.mean(0)
    _, _, vt = np.linalg.svd(q - mu)
    t = (q - mu) @ vt[0]
    if t.max() - t.min() <= 0:
        return None
    return mu + t.min() * vt[0], mu + t.max() * vt[0]


def crack_lines(points, crack_id):
    """The line of each crack: ``(crack_id, p0, p1)`` of :func:`line_through` the points of
    every ``crack_id`` (>= 0) that has a direction, in the points' unit.

    Parameters
    ----------
    points : (N, 2) array of (x, y)
    crack_id : (N,) int array (-1 = on no crack).
    """
    p = np.asarray(points, float)
    c = np.asarray(crack_id).astype(int).ravel()
    if p.ndim != 2 or p.shape[1] != 2 or len(p) != len(c):
        raise GeometryError(f"points must be (N, 2) and crack_id (N,), got {p.shape}, {c.shape}")
    out = []
    for cid in sorted(set(c[c >= 0].tolist())):
        seg = line_through(p[c == cid])
        if seg is not None:
            out.append((int(cid), seg[0], seg[1]))
    return out


def bands_from_clicks(pts_px, crack_id, half_width_px=25.0):
    """One :class:`Band` per ``crack_id`` (>= 0) with at least 2 points: the total
    least-squares line through its points, between the extreme projections.

    Parameters
    ----------
    pts_px : (N, 2) array of (x, y) in view 0.
    crack_id : (N,) int array (-1 = on no crack).
    """
    return [Band(cid, tuple(p0), tuple(p1), "crack_id", float(half_width_px))
            for cid, p0, p1 in crack_lines(pts_px, crack_id)]


def map_bands(z_um, pixel_size_um, sigma_um=None, pts_px=None, crack_id=None, detect=True,
              **detect_kw):
    """The bands of a map: those of the clicked cracks (``crack_id`` >= 0, see
    :func:`bands_from_clicks`) first, then (``detect``) those found in the map
    (:func:`detect_bands`), numbered on after the cracks' ids and marked ``"detected"``."""
    out = []
    if pts_px is not None and crack_id is not None:
        out = bands_from_clicks(pts_px, crack_id)
    if detect:
        start = max([b.band_id for b in out], default=-1) + 1
        for k, b in enumerate(detect_bands(z_um, pixel_size_um, sigma_um=sigma_um, **detect_kw)):
            out.append(Band(start + k, b.p0_px, b.p1_px, b.source, b.half_width_px))
    return out


def _dominant_angle(z):
    """Direction (radians, from x, y down) along which the height varies least: the
    eigenvector of the smallest eigenvalue of the gradient structure tensor."""
    gy, gx = np.gradient(z)
    bad = ~(np.isfinite(gx) & np.isfinite(gy))
    gx[bad] = 0.0               # (zeroed in place: no masked copies of a 12 Mpx map)
    gy[bad] = 0.0
    gx, gy = gx.ravel(), gy.ravel()
    gxy = float(np.dot(gx, gy))
    J = np.array([[np.dot(gx, gx), gxy], [gxy, np.dot(gy, gy)]])
    w, v = np.linalg.eigh(J)
    d = v[:, 0]
    return float(np.arctan2(d[1], d[0]))


def _clip_line(c, d, n, shape):
    """End points of the line ``{c·n + t d}`` inside the image (or None)."""
    hgt, wid = shape
    base = c * n
    ts = []
    for k, lim in ((0, wid - 1), (1, hgt - 1)):
        if abs(d[k]) > 1e-12:
            for edge in (0.0, lim):
                t = (edge - base[k]) / d[k]
                q = base + t * d
                if -1e-6 <= q[0] <= wid - 1 + 1e-6 and -1e-6 <= q[1] <= hgt - 1 + 1e-6:
                    ts.append(t)
    if len(ts) < 2:
        return None
    return tuple(base + min(ts) * d), tuple(base + max(ts) * d)


def detect_bands(z_um, pixel_size_um, sigma_um=None, max_bands=12, min_prominence_um=None,
                 half_width_px=None, smooth_px=2.0):
    """Straight band traces in a height map (extrusions and intrusions).

    1. The band direction is the direction of least height variation (structure tensor of
       the height gradient: slip bands of one system are parallel).
    2. The map is projected along it (a Radon transform at that one angle): the mean
       height as a function of the distance across the bands, 1 px bins.
    3. Extrusions are the peaks and intrusions the valleys of that profile with a
       prominence above ``min_prominence_um`` (default 5× the median σ of the map, or
       10 nm without ``sigma_um``) (``scipy.signal.find_peaks``).
    4. Each trace is re-centred on the extremum of its own profile across it
       (:func:`band_profile`), kept only if that extremum reaches ``min_prominence_um``
       above (below) the reference surface, and dropped if it lands within half a profile
       width of a stronger one.

    Returns
    -------
    list of Band
        Sorted by prominence (largest first), at most ``max_bands``.
    """
    from scipy import ndimage, signal

    z = _as_map(z_um)
    if not np.isfinite(z).any():
        return []
    zf = _fill_nearest(z)
    zs = ndimage.gaussian_filter(zf, smooth_px)
    a = _dominant_angle(zs)
    d = np.array([np.cos(a), np.sin(a)])
    n = np.array([-d[1], d[0]])
    del zf, zs
    hgt, wid = z.shape
    yy, xx = np.ogrid[0:hgt, 0:wid]
    off = xx * n[0] + yy * n[1]                 # distance across the bands, pixels
    ok = np.isfinite(z)
    lo = np.floor(off.min())
    off -= lo
    b = off.astype(np.intp)                     # off >= 0: truncation is the floor
    del off
    nb = int(b.max()) + 1
    b = b[ok]
    cnt = np.bincount(b, minlength=nb)
    sm = np.bincount(b, weights=z[ok], minlength=nb)
    del b
    with np.errstate(invalid="ignore", divide="ignore"):
        prof = sm / cnt
    good = cnt >= max(5, 0.05 * cnt.max())
    prof = np.where(good, prof, np.nan)
    fill = np.interp(np.arange(len(prof)), np.flatnonzero(good), prof[good])
    fill = ndimage.gaussian_filter1d(fill, smooth_px)
    if min_prominence_um is None:
        min_prominence_um = 5 * float(np.nanmedian(sigma_um)) if sigma_um is not None else 0.01
    hw = float(half_width_px) if half_width_px is not None else max(15.0, 0.05 * max(z.shape))
    found = []
    for sign, kind in ((1, "extrusion"), (-1, "intrusion")):
        pk, props = signal.find_peaks(sign * fill, prominence=min_prominence_um,
                                      distance=max(3, int(hw / 2)))
        for p_, pr in zip(pk, props["prominences"]):
            if good[p_]:
                found.append((pr, p_ + lo + 0.5, sign))
    found.sort(key=lambda t: -t[0])
    # re-centre each trace on its own extremum across it (the image-wide projection can
    # put it on a shoulder), then drop traces that landed on an earlier one
    bands, offsets = [], []
    for pr, c, sign in found:
        seg = _clip_line(c, d, n, z.shape)
        if seg is None:
            continue
        prof = band_profile(z, None, 1.0, Band(0, seg[0], seg[1], "detected", hw))
        inner = (np.abs(prof["distance_um"]) <= 0.6 * hw) & (prof["count"] > 0)
        if not inner.any():
            continue
        zi = np.where(inner, sign * prof["z_um"], -np.inf)
        if zi.max() < min_prominence_um:            # no band of this sign along the trace
            continue
        c = c + float(prof["distance_um"][int(np.argmax(zi))])
        seg = _clip_line(c, d, n, z.shape)
        if seg is None or any(abs(c - o) < hw / 2 for o in offsets):
            continue
        offsets.append(c)
        bands.append(Band(len(bands), seg[0], seg[1], "detected", hw))
        if len(bands) == max_bands:
            break
    return bands


def band_profile(z_um, sigma_um, pixel_size_um, band, bin_px=1.0, corr_px=15.0,
                 baseline="reference"):
    """Mean height profile across a band trace and its extrusion, intrusion and width.

    The pixels within ``band.half_width_px`` of the trace (and between its end points) are
    binned by their signed distance across it; each bin's mean is the profile.

    - baseline: ``"reference"`` (default) the reference surface of the map, z = 0 (heights
      are already above it; the slip bands of a fatigued grain are often closer together
      than a profile is long, so "beside the band" is another band), or ``"local"``: the
      median of the profile beyond 0.75 ``half_width_px``, with its own σ;
    - extrusion height = max(profile) − baseline, intrusion depth = baseline − min(profile)
      within 0.6 ``half_width_px`` of the trace (the band and a crack along its edge);
    - width: full width at half of the dominant feature (extrusion or intrusion), from
      linear interpolation of the half-level crossings.

    σ: a bin's 1σ is its root-mean-square pixel σ divided by √n_eff (the map's errors are
    correlated over a subset, ``corr_px``; ``n_eff`` = pixels along the trace / ``corr_px``)
    combined with the standard error of the heights along the trace (the band's own
    variation); heights add the baseline's σ; the width's σ is the crossings' height σ over
    the local slope, added in quadrature for the two sides.

    Returns
    -------
    dict
        ``band`` (Band), ``distance_um`` (M,) bin centres across the trace (positive to the
        right of p0 → p1 in the image, i.e. toward the direction rotated by +90° with y
        down), ``z_um`` (M,), ``sigma_um`` (M,), ``count`` (M,), and the scalars
        ``extrusion_um``, ``extrusion_err_um``, ``intrusion_um``, ``intrusion_err_um``,
        ``width_um``, ``width_err_um``, ``n_pixels``, ``length_um``, ``baseline_um``.
    """
    z = _as_map(z_um)
    sg = _as_map(sigma_um, "sigma_um") if sigma_um is not None else np.zeros_like(z)
    if sg.shape != z.shape:
        raise SemlabError(f"sigma_um shape {sg.shape} is not the map's {z.shape}")
    s = float(pixel_size_um)
    p0 = np.asarray(band.p0_px, float)
    p1 = np.asarray(band.p1_px, float)
    L = float(np.hypot(*(p1 - p0)))
    if L < 2:
        raise GeometryError(f"band {band.band_id}: trace shorter than 2 px")
    d = (p1 - p0) / L
    n = np.array([-d[1], d[0]])
    hw = float(band.half_width_px)
    hgt, wid = z.shape
    # the pixels within hw of the trace lie in its end points' box widened by hw (open
    # grids and that box: no full-size coordinate arrays of a 12 Mpx map)
    x0 = int(max(0, np.floor(min(p0[0], p1[0]) - hw)))
    x1 = int(min(wid, np.ceil(max(p0[0], p1[0]) + hw) + 1))
    y0 = int(max(0, np.floor(min(p0[1], p1[1]) - hw)))
    y1 = int(min(hgt, np.ceil(max(p0[1], p1[1]) + hw) + 1))
    z, sg = z[y0:y1, x0:x1], sg[y0:y1, x0:x1]
    yy, xx = np.ogrid[y0:y1, x0:x1]
    rx, ry = xx - p0[0], yy - p0[1]
    along = rx * d[0] + ry * d[1]
    across = rx * n[0] + ry * n[1]
    keep = (along >= 0) & (along <= L) & (np.abs(across) <= hw) & np.isfinite(z) \
        & np.isfinite(sg)
    nb = int(np.ceil(2 * hw / bin_px))
    edges = np.linspace(-hw, hw, nb + 1)
    b = np.clip(np.searchsorted(edges, across[keep], side="right") - 1, 0, nb - 1)
    zk, sk = z[keep], sg[keep]
    cnt = np.bincount(b, minlength=nb)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(b, weights=zk, minlength=nb) / cnt
        var = np.bincount(b, weights=zk ** 2, minlength=nb) / cnt - mean ** 2
        msig2 = np.bincount(b, weights=sk ** 2, minlength=nb) / cnt
    n_eff = np.maximum(1.0, cnt / max(1.0, corr_px))
    sig = np.sqrt(msig2 / n_eff + np.maximum(var, 0) / np.maximum(cnt, 1) * corr_px)
    centers = 0.5 * (edges[:-1] + edges[1:])
    out = {"band": band, "distance_um": centers * s, "z_um": mean, "sigma_um": sig,
           "count": cnt, "n_pixels": int(keep.sum()), "length_um": L * s}
    nan = dict(extrusion_um=np.nan, extrusion_err_um=np.nan, intrusion_um=np.nan,
               intrusion_err_um=np.nan, width_um=np.nan, width_err_um=np.nan,
               baseline_um=np.nan)
    ok = cnt > 0
    outer = ok & (np.abs(centers) > 0.75 * hw)
    inner = ok & (np.abs(centers) <= 0.6 * hw)
    if outer.sum() < 2 or inner.sum() < 2:
        out.update(nan)
        return out
    if baseline == "reference":
        base, base_err = 0.0, 0.0
    elif baseline == "local":
        base = float(np.median(mean[outer]))
        n_ind = max(1.0, outer.sum() * bin_px / max(1.0, corr_px))   # independent bins
        base_err = float(1.2533 * np.hypot(np.sqrt(np.mean(sig[outer] ** 2)),
                                           np.std(mean[outer])) / np.sqrt(n_ind))
    else:
        raise SemlabError(f"baseline must be 'reference' or 'local', got {baseline!r}")
    zi = np.where(inner, mean, np.nan)
    i_hi, i_lo = int(np.nanargmax(zi)), int(np.nanargmin(zi))
    ext, intr = float(mean[i_hi] - base), float(base - mean[i_lo])
    out.update(baseline_um=base, extrusion_um=ext,
               extrusion_err_um=float(np.hypot(sig[i_hi], base_err)),
               intrusion_um=intr, intrusion_err_um=float(np.hypot(sig[i_lo], base_err)))
    # width of the dominant feature at half its height
    ipk, amp = (i_hi, ext) if ext >= intr else (i_lo, -intr)
    rel = np.where(ok, (mean - base) / amp, np.nan) if amp != 0 else np.full(nb, np.nan)
    sides, errs = [], []
    for step in (-1, 1):
        j = ipk
        while 0 <= j + step < nb and np.isfinite(rel[j + step]) and rel[j + step] > 0.5:
            j += step
        k = j + step
        if not (0 <= k < nb) or not np.isfinite(rel[k]):
            break
        f = (rel[j] - 0.5) / (rel[j] - rel[k])
        sides.append(centers[j] + f * (centers[k] - centers[j]))
        slope = abs(mean[k] - mean[j]) / bin_px
        errs.append(np.hypot(sig[j], sig[k]) / 2 / max(slope, 1e-12))
    if len(sides) == 2:
        out["width_um"] = float(abs(sides[1] - sides[0]) * s)
        out["width_err_um"] = float(np.hypot(*errs) * s)
    else:
        out["width_um"], out["width_err_um"] = np.nan, np.nan
    return out


def write_bands_csv(path, profiles):
    """Write one row per band profile (:data:`BANDS_COLUMNS`; heights and widths in µm)."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(BANDS_COLUMNS)
        for p in profiles:
            b = p["band"]
            w.writerow([b.band_id, b.source, _fmt(b.p0_px[0]), _fmt(b.p0_px[1]),
                        _fmt(b.p1_px[0]), _fmt(b.p1_px[1]), _fmt(b.angle_deg),
                        _fmt(p["length_um"])]
                       + [_fmt(p[k]) for k in BANDS_COLUMNS[8:14]] + [p["n_pixels"]])
    return Path(path)


def profile_between(z_um, sigma_um, p0_px, p1_px, pixel_size_um, width_px=1.0, step_px=0.5):
    """Height profile with its 1σ from ``p0`` to ``p1`` (view-0 pixels).

    Samples every ``step_px`` along the segment by bilinear interpolation (a sample next to
    a NaN pixel is NaN); with ``width_px > 1`` each sample is the mean over
    ``round(width_px)`` parallel lines 1 px apart (σ: RMS σ of the lines, not divided,
    since neighbouring pixels' errors are correlated).

    Returns
    -------
    dict with ``distance_um`` (M,), ``z_um`` (M,), ``sigma_um`` (M,), ``xy_px`` (M, 2).
    """
    from scipy import ndimage

    # a float32 map is sampled as it is (a click on a 12.6 Mpx map copies nothing)
    z = _as_map(z_um, keep_float32=True)
    sg = (_as_map(sigma_um, "sigma_um", keep_float32=True) if sigma_um is not None
          else np.zeros(z.shape, np.float32))
    p0, p1, L = _segment(p0_px, p1_px, "p0_px and p1_px", "pixel pairs", "a segment")
    m = int(np.floor(L / step_px)) + 1
    t = np.linspace(0.0, L, m)
    d = (p1 - p0) / L
    nrm = np.array([-d[1], d[0]])
    k = max(1, int(round(width_px)))
    offs = (np.arange(k) - (k - 1) / 2.0)
    zs, ss = [], []
    for o in offs:
        xy = p0 + t[:, None] * d + o * nrm
        coords = [xy[:, 1], xy[:, 0]]
        zs.append(ndimage.map_coordinates(z, coords, order=1, mode="constant", cval=np.nan))
        ss.append(ndimage.map_coordinates(sg, coords, order=1, mode="constant", cval=np.nan))
    zs, ss = np.array(zs, float), np.array(ss, float)
    with np.errstate(invalid="ignore"):
        zm = zs.mean(0)
        sm = np.sqrt((ss ** 2).mean(0))
    return {"distance_um": t * float(pixel_size_um), "z_um": zm, "sigma_um": sm,
            "xy_px": p0 + t[:, None] * d}
