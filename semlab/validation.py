"""Comparing results with the ground truth of a synthetic experiment (``truth/``).

Heights are defined relative to a reference plane, which is a convention (each method fits
its own), so height errors are measured after removing the least-squares plane of the
difference ``z_est − z_true``: what is left is the error in the relief itself.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import ndimage

from .errors import SemlabError


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


def height_errors(z_est_um, z_true_um, xy=None):
    """Height error after removing the best-fit plane of the difference.

    Parameters
    ----------
    z_est_um, z_true_um : (N,) arrays
    xy : (N, 2) array, optional
        Positions (any unit) used for the plane; without them only the mean is removed.

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
        A = np.column_stack([xy[ok], np.ones(ok.sum())])
        coef, *_ = np.linalg.lstsq(A, d[ok], rcond=None)
        d = d - np.column_stack([xy, np.ones(len(xy))]) @ coef
    else:
        d = d - np.mean(d[ok])
    e = np.where(ok, d, np.nan)
    a = np.abs(e[ok])
    return {"err_um": e, "rmse_um": float(np.sqrt(np.mean(e[ok] ** 2))), "mae_um": float(a.mean()),
            "max_um": float(a.max()), "p95_um": float(np.percentile(a, 95)), "n": int(ok.sum())}


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
    (F, N, 2) array of (x, y) pixels, frame 0 the earliest.
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
    return np.stack([np.column_stack([p[:, 0] - r * ux / s, p[:, 1] - r * uy / s]) for r in left])


def true_displacement_um(truth, seeds_last_px):
    """True displacement (µm) from frame 0 to the end of material points seen at
    ``seeds_last_px`` in the last frame: (N, 2) array of (dx_um, dy_um)."""
    f = load_fields(truth)
    pos = true_track_positions(truth, seeds_last_px)
    return (pos[-1] - pos[0]) * float(f["pixel_size_um"])
