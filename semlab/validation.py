"""Comparing results with the ground truth of a synthetic experiment (``truth/``).

Heights are defined relative to a reference plane, which is a convention (each method fits
its own), so height errors are measured after removing the least-squares plane of the
difference ``z_est − z_true``: what is left is the error in the relief itself. The plane is a
gauge, so it may also be fitted robustly (``plane="robust"``: Huber IRLS), which one gross
error cannot tilt.

Without truth, :func:`view_pair_consistency` checks a multi-view run's error bars by its own
views: the heights of each pair of views alone against all views', over their predicted σ;
:func:`pair_height_differences` is its simplest form, view pairs against each other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from .errors import SemlabError
from .stats import robust_sd


def _truth_dir(truth):
    d = Path(truth)
    if d.name != "truth":
        d = d / "truth"
    if not d.is_dir():
        raise SemlabError(f"{d}: no truth/ folder; validation needs a synthetic experiment "
                          "made by `semlab synth`")
    return d


def true_height_at(truth, pts_view0):
    """True end-state height (µm) at view-0 pixel positions.

    Parameters
    ----------
    truth : path of the experiment folder or its ``truth/``
    pts_view0 : (N, 2) array of (x, y) pixels in view 0

    Returns
    -------
    (N,) array of z in µm (cubic spline interpolation of ``height_view0.npy``)
    """
    z = np.load(_truth_dir(truth) / "height_view0.npy").astype(float)
    p = np.asarray(pts_view0, float).reshape(-1, 2)
    return ndimage.map_coordinates(z, [p[:, 1], p[:, 0]], order=3, mode="nearest")


HUBER_K = 1.345  # Huber threshold in robust σ (1.4826·MAD) units: 95 % efficiency at a Gaussian


def gauge_plane(A, d, plane="lsq", n_iter=50, tol=1e-10):
    """Coefficients of the gauge (plane or mean) fitted to the error ``d``.

    Parameters
    ----------
    A : (N, P) design matrix (``[x, y, 1]`` for a plane, ``[1]`` for the mean)
    d : (N,) error (any unit)
    plane : ``"lsq"`` (unweighted least squares) or ``"robust"`` (iteratively reweighted least
        squares with Huber weights ``min(1, k / |r / s|)``, ``k`` = :data:`HUBER_K`, on the
        residual ``r`` scaled by its ``s`` = 1.4826·MAD, re-estimated every iteration; started
        from the least-squares fit; convex, so one gross error cannot tilt it far)
    n_iter, tol : at most ``n_iter`` reweightings, stopped when the coefficients move by less
        than ``tol`` times the residual scale

    Returns
    -------
    (P,) coefficients
    """
    if plane not in ("lsq", "robust"):
        raise SemlabError(f"plane must be 'lsq' or 'robust', got {plane!r}")
    coef, *_ = np.linalg.lstsq(A, d, rcond=None)
    if plane == "lsq":
        return coef
    for _ in range(n_iter):
        r = d - A @ coef
        s = robust_sd(r)
        if not s > 0:
            break
        u = np.abs(r) / (HUBER_K * s)
        sw = np.sqrt(np.where(u > 1, 1.0 / np.maximum(u, 1e-300), 1.0))
        new, *_ = np.linalg.lstsq(A * sw[:, None], d * sw, rcond=None)
        step = np.max(np.abs(new - coef))
        coef = new
        if step < tol * s:
            break
    return coef


def height_errors(z_est_um, z_true_um, xy=None, plane="lsq"):
    """Height error after removing the best-fit plane of the difference.

    Parameters
    ----------
    z_est_um, z_true_um : (N,) arrays
    xy : (N, 2) array, optional
        Positions (any unit) used for the plane; without them only the mean is removed.
    plane : ``"lsq"`` (default: unweighted least squares) or ``"robust"`` (Huber IRLS,
        :func:`gauge_plane`): the gauge removed, the same for any method scored with it

    Returns
    -------
    dict with ``err_um`` (N,), ``rmse_um``, ``mae_um``, ``max_um``, ``p95_um``, ``n``
    """
    ze = np.asarray(z_est_um, float).ravel()
    zt = np.asarray(z_true_um, float).ravel()
    ok = np.isfinite(ze) & np.isfinite(zt)
    if ok.sum() < 3:
        raise SemlabError(f"height_errors needs at least 3 finite heights, got {ok.sum()}")
    d = ze - zt
    if xy is not None:
        xy = np.asarray(xy, float).reshape(-1, 2)
        A = np.column_stack([xy, np.ones(len(xy))])
    else:
        A = np.ones((len(d), 1))
    d = d - A @ gauge_plane(A[ok], d[ok], plane)
    e = np.where(ok, d, np.nan)
    a = np.abs(e[ok])
    return {"err_um": e, "rmse_um": float(np.sqrt(np.mean(e[ok] ** 2))), "mae_um": float(a.mean()),
            "max_um": float(a.max()), "p95_um": float(np.percentile(a, 95)), "n": int(ok.sum())}


#: below this fraction of pair differences within 2σ (95.4 % for right, Gaussian error bars)
#: :func:`view_pair_consistency` says that the error bars do not hold between those views
CONSISTENT_WITHIN_2SIGMA = 0.9


def _pair_weights(tilt_deg, views, pixel_size_um):
    """(V,) weights of the views' x coordinates (pixels) in the height (µm) solved from
    ``views`` alone by least squares, ``u_i = (x cos θ_i + z sin θ_i)/s`` (two views: the
    parallax closed form)."""
    th = np.deg2rad(np.asarray(tilt_deg, float))
    w = np.zeros(th.size)
    A = np.column_stack([np.cos(th[views]), np.sin(th[views])]) / float(pixel_size_um)
    w[views] = np.linalg.pinv(A)[1]
    return w


def view_pair_consistency(pts, tilt_deg, sigma_px, pixel_size_um, tilt_axis_deg=90.0,
                          min_points=10):
    """Error bars checked without truth: the heights of each view pair against all views'.

    For three or more views, the heights from every two views ``(a, b)`` alone
    (:func:`semlab.reconstruct.heights_from_tilts`, each pair with its own offsets) are
    compared with the heights from all views. Both are linear in the views' x coordinates, so
    under the error model the run's own σ use (:func:`semlab.surface.height_sigma`: each
    view's x error independent, with the given σ) their difference has the predicted σ
    ``sqrt(Σ_v (w_ab,v − w_all,v)² σ_v²)``, ``w`` the least-squares weights of each view's x
    in the height. After the least-squares plane of the difference (a gauge: each solution's
    unknown offsets) is removed, each difference is divided by it. Right error bars give a
    robust SD of about 1 and 95 % within 2σ. With three views each point has one redundant
    coordinate, so every pair gives the same check (its all-view fit's residual over its
    predicted σ): it is reported once; with V views, V − 2 such directions.

    An error no matching σ holds (camera model, scan distortion) shows. So does, outside the
    model, an error common to a point's matches relative to its reference view (the
    reference subset's own noise, or its look the other views do not share): it is an error
    of the reference view's position, which the model takes as exact; how much it shows
    depends on where the reference sits among the tilts (little at one end, where it also
    changes the heights' σ little; twice over in the middle: docs/accuracy.md, quartz). A
    subset's model error (one height bias seen by every view) cancels in every difference:
    this check cannot see it.

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixels of the points in every view, V >= 3 (rows with NaN are skipped).
    tilt_deg : (V,) array_like
        Tilts used for the heights, degrees.
    sigma_px : (N, V) array
        1σ of each view's x coordinate, pixels, as :func:`semlab.surface.height_sigma` takes
        it (the reference column of matched points near 0: ``semlab.pipeline.view_sigmas``).
    pixel_size_um : float
    tilt_axis_deg : float
        As for :func:`semlab.reconstruct.heights_from_tilts`.
    min_points : int
        Fewer finite points: no check.

    Returns
    -------
    list of dict
        One per view pair ``(a, b)`` whose heights are not those of all views and whose check
        is not an earlier pair's (three views: one): ``views`` ``[a, b]``, ``n_points``, ``robust_sd``
        (1.4826·MAD of the normalised differences), ``within_1sigma``, ``within_2sigma``,
        ``consistent`` (``within_2sigma`` >= :data:`CONSISTENT_WITHIN_2SIGMA`), and ``u``
        ((N,) normalised differences, NaN where not computed). Empty with fewer than three
        views.
    """
    from .reconstruct import heights_from_tilts

    P = np.asarray(pts, float)
    if P.ndim != 3 or P.shape[2] != 2:
        raise SemlabError(f"pts must be (N, V, 2) pixels, got shape {P.shape}")
    n, v = P.shape[:2]
    sig = np.asarray(sigma_px, float)
    if sig.shape != (n, v):
        raise SemlabError(f"sigma_px must be (N, V) = {(n, v)} pixels, got shape {sig.shape}")
    th = np.asarray(tilt_deg, float).ravel()
    if th.size != v:
        raise SemlabError(f"tilt_deg has {th.size} values for {v} views")
    ok = np.all(np.isfinite(P.reshape(n, -1)), axis=1) & np.all(np.isfinite(sig) & (sig > 0), 1)
    out = []
    if v < 3 or ok.sum() < max(int(min_points), 4):
        return out
    idx = np.flatnonzero(ok)
    Q, S = P[idx], sig[idx]

    def heights(views):
        return heights_from_tilts(Q[:, views], th[views], pixel_size_um,
                                  tilt_axis_deg=tilt_axis_deg).xyz_um[:, 2]

    every = list(range(v))
    z_all, w_all = heights(every), _pair_weights(th, every, pixel_size_um)
    A = np.column_stack([Q[:, 0], np.ones(len(idx))])
    for a in range(v):
        for b in range(a + 1, v):
            w = _pair_weights(th, [a, b], pixel_size_um) - w_all
            if np.sum(w ** 2) <= 1e-12 * np.sum(w_all ** 2):
                continue     # the same heights as all views' (e.g. the outer pair of ±θ, 0)
            d = heights([a, b]) - z_all
            d = d - A @ gauge_plane(A, d)
            u = np.full(n, np.nan)
            u[idx] = d / np.sqrt((S ** 2) @ (w ** 2))
            if any(np.allclose(np.abs(u[idx]), np.abs(r["u"][idx]), rtol=1e-6, atol=1e-9)
                   for r in out):
                continue     # the same check as an earlier pair (three views: one residual)
            m = np.abs(u[idx])
            within2 = float(np.mean(m <= 2))
            out.append({"views": [a, b], "n_points": int(len(idx)),
                        "robust_sd": robust_sd(u[idx]),
                        "within_1sigma": float(np.mean(m <= 1)), "within_2sigma": within2,
                        "consistent": bool(within2 >= CONSISTENT_WITHIN_2SIGMA), "u": u})
    return out


def pair_height_differences(pts, tilt_deg, sigma_px, pairs, pixel_size_um=1.0):
    """Heights of view pairs compared pairwise: the simplest check of a run's error bars.

    The heights of each view pair ``(a, b)`` of ``pairs`` alone
    (:func:`semlab.reconstruct.heights_from_tilts`) are compared with every other pair's
    after removing the least-squares plane of the difference in view-0 ``(x, y)`` (each
    pair's own offsets and tilt errors; a gauge). The predicted 1σ
    of a pair's height is the two-view one of :func:`semlab.surface.height_sigma` with the
    reference view 0's positions exact (grid points) and ``sigma_px`` for the other view's x,
    ``sqrt(σ_a² cos²θ_b + σ_b² cos²θ_a) / |sin(θ_b − θ_a)|`` × the pixel size, written out
    because ``height_sigma`` takes no zero σ; the two pairs'
    errors are taken independent (pairs that share a view are not, so with right bars the
    difference tends to be inside its σ). :func:`view_pair_consistency` is the check with
    the full error model against all views' heights.

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixels of the points in every view (view 0 the reference).
    tilt_deg : (V,) array_like
        Tilts, degrees.
    sigma_px : (N,) array
        1σ of each point's x in every view other than view 0, pixels.
    pairs : sequence of (a, b)
        View pairs; every two of them are compared.
    pixel_size_um : float

    Returns
    -------
    list of dict
        One per two pairs ``(i, k)`` (indices into ``pairs``, ``i < k``): ``pairs``
        ``[pairs[i], pairs[k]]``, ``diff_um`` ((N,) height difference after the plane),
        ``sigma_um`` ((N,) its predicted 1σ), ``within_1sigma``, ``within_2sigma``,
        ``robust_sd_um`` (1.4826 × the median absolute difference).
    """
    from .reconstruct import heights_from_tilts

    P = np.asarray(pts, float)
    th = np.asarray(tilt_deg, float).ravel()
    s = np.asarray(sigma_px, float).ravel()
    if P.ndim != 3 or P.shape[2] != 2 or len(s) != len(P) or th.size != P.shape[1]:
        raise SemlabError(f"pair_height_differences: pts {P.shape}, {len(s)} σ and {th.size} "
                          "tilts; give (N, V, 2) pixels, N σ and V tilts")
    z, zs = [], []
    for a, b in pairs:
        z.append(heights_from_tilts(P[:, [a, b]], th[[a, b]], pixel_size_um).xyz_um[:, 2])
        sa, sb = (0.0 if v == 0 else s for v in (a, b))
        ca, cb = np.cos(np.deg2rad(th[[a, b]]))
        zs.append(pixel_size_um * np.hypot(sa * cb, sb * ca)
                  / abs(np.sin(np.deg2rad(th[b] - th[a]))))
    A = np.column_stack([P[:, 0], np.ones(len(P))])
    out = []
    for i in range(len(pairs)):
        for k in range(i + 1, len(pairs)):
            d = z[i] - z[k]
            d = d - A @ gauge_plane(A, d)
            sd = np.hypot(zs[i], zs[k])
            out.append({"pairs": [tuple(pairs[i]), tuple(pairs[k])], "diff_um": d,
                        "sigma_um": sd, "within_1sigma": float(np.mean(np.abs(d) <= sd)),
                        "within_2sigma": float(np.mean(np.abs(d) <= 2 * sd)),
                        "robust_sd_um": float(robust_sd(d, about=0.0))})
    return out


def heightmap_errors(z_um, sigma_um, valid, truth, roi=None, border_px=20):
    """Errors of a dense height map against the truth, after removing the plane of the error.

    Parameters
    ----------
    z_um, sigma_um : (h, w) arrays
        The map's heights and 1σ (µm) on the view-0 pixel grid of ``roi``.
    valid : (h, w) bool array
        Measured pixels.
    truth : path of the experiment folder or its ``truth/``
        Its ``height_view0.npy`` (the true height at every view-0 pixel, µm).
    roi : (x0, y0, x1, y1), optional
        Half-open window of view-0 pixels the map covers (default the whole view).
    border_px : int
        Pixels along the edges of the *view* left out of the interior scored.

    Returns
    -------
    dict
        ``err_um`` (M,) plane-removed errors of the measured interior pixels (row-major),
        ``mask`` (h, w) bool array of those pixels, ``rmse_um``, ``measured`` (fraction of the
        interior measured), ``within_1sigma`` and ``within_2sigma`` (fractions of ``err_um``),
        ``n``.

    Raises
    ------
    SemlabError
        Map arrays of different shapes, or a ``roi`` that does not match them.
    """
    z = np.asarray(z_um, float)
    s = np.asarray(sigma_um, float)
    v = np.asarray(valid, bool)
    if not (z.shape == s.shape == v.shape) or z.ndim != 2:
        raise SemlabError(f"heightmap_errors: z, sigma and valid must be one (h, w) shape, got "
                          f"{z.shape}, {s.shape}, {v.shape}")
    zt = np.load(_truth_dir(truth) / "height_view0.npy").astype(float)
    hgt, wid = zt.shape
    x0, y0, x1, y1 = (0, 0, wid, hgt) if roi is None else (int(c) for c in roi)
    if (y1 - y0, x1 - x0) != z.shape:
        raise SemlabError(f"heightmap_errors: roi {roi} is {(y1 - y0, x1 - x0)} pixels, the map "
                          f"{z.shape}")
    yy, xx = np.mgrid[y0:y1, x0:x1]
    interior = ((xx >= border_px) & (xx < wid - border_px) & (yy >= border_px)
                & (yy < hgt - border_px))
    m = interior & v & np.isfinite(z) & np.isfinite(s)
    if m.sum() < 3:
        raise SemlabError(f"heightmap_errors: only {int(m.sum())} measured interior pixels")
    e = height_errors(z[m], zt[y0:y1, x0:x1][m], np.column_stack([xx[m], yy[m]]))
    err = e["err_um"]
    return {"err_um": err, "mask": m, "rmse_um": e["rmse_um"],
            "measured": float(m.sum() / max(int(interior.sum()), 1)),
            "within_1sigma": float(np.mean(np.abs(err) < s[m])),
            "within_2sigma": float(np.mean(np.abs(err) < 2 * s[m])), "n": int(m.sum())}


def subset_model_bias(field_px, pts, half_window, weight=None, quadratic=False, part=None):
    """Centre bias of square subsets matched on a known displacement field, pixels.

    To first order an IC-GN subset on a displacement field ``d`` returns the least-squares
    fit of its shape function to ``d`` over the subset, each pixel weighted by its
    information about that displacement component (e.g. the squared x gradient of the
    reference image for the x displacement). The subset's model bias is that fit at the
    centre minus ``d`` at the centre: zero for a field the shape function spans (any
    linear field with an affine subset), ``a h (h + 1) / 3`` for ``d = a x²`` with uniform
    weights (the mean of ``a x²`` over the subset, as in
    :func:`semlab.match_sigma.curvature_bias`). With the true field of a synthetic
    experiment this is the bias an ideal estimate of the model error would report
    (``benchmarks/subset_bias_oracle.py``).

    Parameters
    ----------
    field_px : (H, W) array
        The displacement component on the reference pixel grid, pixels.
    pts : (N, 2) array of (x, y) pixels
        Subset centres (sub-pixel allowed; the subset is centred on the nearest pixel).
    half_window : int or (N,) array of int
        Half size ``h`` of each square ``(2h+1)²`` subset.
    weight : (H, W) array, optional
        Information of each pixel (default: uniform).
    quadratic : bool
        Second-order shape function (adds ``x², x y, y²`` to ``1, x, y``).
    part : {None, "left", "right", "top", "bottom"}
        A half subset (:func:`semlab.subset.square_subset`), as in subset splitting at a
        discontinuity.

    Returns
    -------
    bias : (N,) array
        Pixels; NaN where the subset leaves the grid or its fit is singular.
    info_inv : (N,) array
        ``[(Aᵀ W A)⁻¹]₀₀`` of the centre term, in inverse weight units: with the squared
        gradients over the noise variance as weights, the Cramér–Rao variance of the
        displacement at the centre; the ratio between two shapes is the ratio of their
        noise variances.
    """
    from .subset import square_subset

    d = np.asarray(field_px, float)
    if d.ndim != 2:
        raise SemlabError(f"field_px must be a 2D array, got shape {d.shape}")
    w = np.ones_like(d) if weight is None else np.asarray(weight, float)
    if w.shape != d.shape:
        raise SemlabError(f"weight must have the shape of field_px {d.shape}, got {w.shape}")
    p = np.asarray(pts, float).reshape(-1, 2)
    hs = np.broadcast_to(np.asarray(half_window, int), (len(p),))
    offsets = {h: square_subset(h, part) for h in np.unique(hs)}   # refuses a wrong part
    bias = np.full(len(p), np.nan)
    info_inv = np.full(len(p), np.nan)
    H, W = d.shape
    d_centre = ndimage.map_coordinates(d, [p[:, 1], p[:, 0]], order=3, mode="nearest")
    for i, ((x, y), h) in enumerate(zip(p, hs)):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        xi, yi = int(round(x)), int(round(y))
        if xi - h < 0 or yi - h < 0 or xi + h >= W or yi + h >= H:
            continue
        ox, oy = offsets[h].T
        X, Y = ox + (xi - x), oy + (yi - y)
        cols = [np.ones_like(X), X, Y] + ([X * X, X * Y, Y * Y] if quadratic else [])
        A = np.column_stack(cols)
        wi, di = w[yi + oy, xi + ox], d[yi + oy, xi + ox]
        N = (A * wi[:, None]).T @ A
        try:
            Ninv = np.linalg.inv(N)
        except np.linalg.LinAlgError:
            continue
        c = Ninv @ ((A * wi[:, None]).T @ di)
        bias[i] = c[0] - d_centre[i]
        info_inv[i] = Ninv[0, 0]
    return bias, info_inv


def load_fields(truth):
    """The true displacement/strain fields (``truth/fields.npz``) as a dict of arrays."""
    d = _truth_dir(truth)
    f = d / "fields.npz"
    if not f.is_file():
        raise SemlabError(f"{f}: not found; this synthetic experiment has no series")
    with np.load(f) as z:
        return {k: z[k] for k in z.files}


def true_track_positions(truth, seeds_last_px):
    """True pixel positions in every frame of material points seen at ``seeds_last_px`` in the
    last frame.

    Parameters
    ----------
    truth : path of the experiment folder or its ``truth/``
    seeds_last_px : (N, 2) array of (x, y) pixels in the last frame

    Returns
    -------
    (F, N, 2) array of (x, y) pixels, frame 0 the earliest: each frame's own pixels, with
    the stage and scan drift of a drifted series (``truth/drift.csv``) included.
    """
    f = load_fields(truth)
    s = float(f["pixel_size_um"])
    p = np.asarray(seeds_last_px, float).reshape(-1, 2)
    # fields are on every other pixel: grid index = px / step
    step_x = f["x_px"][1] - f["x_px"][0]
    step_y = f["y_px"][1] - f["y_px"][0]
    coords = [(p[:, 1] - f["y_px"][0]) / step_y, (p[:, 0] - f["x_px"][0]) / step_x]
    ux = ndimage.map_coordinates(f["ux_um"].astype(float), coords, order=3, mode="nearest")
    uy = ndimage.map_coordinates(f["uy_um"].astype(float), coords, order=3, mode="nearest")
    left = 1.0 - np.asarray(f["f"], float)  # fraction of U still to come at each frame
    pos = np.stack([np.column_stack([p[:, 0] - r * ux / s, p[:, 1] - r * uy / s]) for r in left])
    drift_csv = _truth_dir(truth) / "drift.csv"
    if drift_csv.is_file():   # a drifted series: each frame's own pixels (synth --drift)
        from .registration import read_drift_csv
        from .synth_drift import DRIFT_TRUTH_COLUMNS, drifted_positions

        d = read_drift_csv(drift_csv)
        shape = (2 * len(f["y_px"]), 2 * len(f["x_px"]))   # fields on every other pixel
        for n in range(len(pos)):
            pos[n] = drifted_positions({c: d[c][n] for c in DRIFT_TRUTH_COLUMNS[1:]}, pos[n],
                                       shape)
    return pos


def true_displacement_um(truth, seeds_last_px):
    """True displacement (µm) from frame 0 to the end of material points seen at
    ``seeds_last_px`` in the last frame: (N, 2) array of (dx_um, dy_um)."""
    f = load_fields(truth)
    pos = true_track_positions(truth, seeds_last_px)
    return (pos[-1] - pos[0]) * float(f["pixel_size_um"])
