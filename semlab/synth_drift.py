"""Stage drift between frames and scan drift within a frame of a synthetic series.

Used by :func:`semlab.synth.render` and :func:`semlab.synth.make_experiment`; all names are
re-exported by :mod:`semlab.synth`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["DRIFT_TRUTH_COLUMNS", "stage_drift", "drift_pixel_map", "drifted_positions"]

#: Columns of ``truth/drift.csv``.
DRIFT_TRUTH_COLUMNS = ("frame", "dx_px", "dy_px", "rotation_deg", "scale", "scan_dx_px",
                       "scan_dy_px")


def stage_drift(n_frames, shift_px=0.0, rotation_deg=0.0, scale=0.0, scan_px=0.0, rng=None):
    """Random stage drift of each frame of a series, the last frame being the reference.

    Every frame but the last is placed independently (a stage moved and brought back): a
    shift of the image centre of length uniform in ``[0.5, 1] × shift_px`` in a random
    direction, a rotation about the centre uniform in ``±rotation_deg`` and a magnification
    ``1 + uniform(±scale)``. ``scan_px`` adds a slow drift while the frame is scanned: row
    ``v`` sees the sample shifted by ``(scan_dx, scan_dy) · (t + 0.3 t²) / 1.3`` with
    ``t = v / (H − 1)``, ``(scan_dx, scan_dy)`` uniform in ``±scan_px``. The last frame is
    neither drifted nor scan-drifted (truth positions there are the end-state pixels).

    Returns
    -------
    list of n_frames dicts with ``dx_px, dy_px, rotation_deg, scale, scan_dx_px, scan_dy_px``.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    out = []
    for n in range(n_frames):
        a, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 1.0) * shift_px
        d = {"dx_px": r * np.cos(a), "dy_px": r * np.sin(a),
             "rotation_deg": rng.uniform(-1, 1) * rotation_deg, "scale": 1 + rng.uniform(-1, 1) * scale,
             "scan_dx_px": rng.uniform(-1, 1) * scan_px, "scan_dy_px": rng.uniform(-1, 1) * scan_px}
        if n == n_frames - 1:
            d = {k: (1.0 if k == "scale" else 0.0) for k in d}
        out.append({k: float(v) for k, v in d.items()})
    return out


def _stage_matrix(drift, shape):
    """(3, 3) map of undrifted pixels to drifted pixels (before the scan drift)."""
    h, w = shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    t = np.deg2rad(drift["rotation_deg"])
    A = drift["scale"] * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    m = np.eye(3)
    m[:2, :2] = A
    m[:2, 2] = c + np.array([drift["dx_px"], drift["dy_px"]]) - A @ c
    return m


def _scan_offset(drift, v, h):
    t = np.asarray(v, float) / max(h - 1, 1)
    f = (t + 0.3 * t * t) / 1.3
    return drift["scan_dx_px"] * f, drift["scan_dy_px"] * f


def drift_pixel_map(drift, shape):
    """Undrifted pixel (x, y) seen at every pixel of a drifted image: (2, H, W) array.

    Pixel ``q`` of the drifted image, scanned at row ``q_y``, shows the undrifted position
    ``D⁻¹(q − s(q_y))`` with ``D`` the stage similarity and ``s`` the scan offset.
    """
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w].astype(float)
    sx, sy = _scan_offset(drift, vv, h)
    mi = np.linalg.inv(_stage_matrix(drift, shape))
    x, y = uu - sx, vv - sy
    return np.stack([mi[0, 0] * x + mi[0, 1] * y + mi[0, 2], mi[1, 0] * x + mi[1, 1] * y + mi[1, 2]])


def drifted_positions(drift, pts_px, shape):
    """Where undrifted pixel positions ``(N, 2)`` appear in the drifted image (inverse of
    :func:`drift_pixel_map`; the scan offset depends on the row reached, solved by
    fixed-point iteration)."""
    p = np.asarray(pts_px, float)
    m = _stage_matrix(drift, shape)
    q0 = p @ m[:2, :2].T + m[:2, 2]
    q = q0.copy()
    for _ in range(20):
        sx, sy = _scan_offset(drift, q[:, 1], shape[0])
        q = q0 + np.column_stack([sx, sy])
    return q
