"""Displacements of tracked points, and the on-disk formats of tracking results.

``tracks.csv`` (every step of every track, each frame's own pixels) and
``displacements.csv`` (from the earliest valid frame of each track to the last frame). With
a frame registration (:mod:`semlab.registration`), the displacement has the rigid-body
motion of the stage (shift of the image centre and rotation about it, measured by the
registration) removed; the raw displacement is kept alongside.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .errors import SemlabError, TrackingError

__all__ = [
    "TRACKS_CSV_COLUMNS",
    "TRACKS_CSV_EXTRA_COLUMNS",
    "DISPLACEMENTS_CSV_COLUMNS",
    "tracks_to_records",
    "write_tracks_csv",
    "displacements",
    "displacement_history",
    "earliest_displacements",
    "write_displacements_csv",
]

TRACKS_CSV_COLUMNS = ("track_id", "seed", "frame", "x_px", "y_px", "fb_error_px", "valid")
#: Diagnostic columns written after the contract columns: the step's ZNCC, its predicted
#: 1σ matching error (pixels) and how many frames the track has been suspended.
TRACKS_CSV_EXTRA_COLUMNS = ("zncc", "sigma_px", "gap_frames")
#: Columns of ``displacements.csv``: ``dx_um, dy_um, d_um`` with the stage's rigid-body
#: motion removed (equal to the raw ones without a registration), then the raw ones.
DISPLACEMENTS_CSV_COLUMNS = ("track_id", "seed", "x_px", "y_px", "frame_from", "dx_um", "dy_um",
                             "d_um", "z_um", "dx_raw_um", "dy_raw_um", "d_raw_um")


# ----------------------------------------------------------------------------- records / csv

def tracks_to_records(tracks, seed_kind=None):
    """Rows of ``tracks.csv``: one per (track, frame), frames chronological.

    Parameters
    ----------
    tracks : Tracks
    seed_kind : (N,) sequence of str, optional
        Overrides ``tracks.seed_kind``.

    Returns
    -------
    list of dict with keys ``track_id, seed, frame, x_px, y_px, fb_error_px, valid`` and
    then ``zncc, sigma_px, gap_frames`` (NaN positions where no estimate exists; ``valid``
    is bool).
    """
    kinds = tracks.seed_kind if seed_kind is None else np.asarray(list(seed_kind), dtype=object)
    if len(kinds) != tracks.n_tracks:
        raise TrackingError(f"seed_kind has {len(kinds)} labels for {tracks.n_tracks} tracks")
    rows = []
    for i in range(tracks.n_tracks):
        for f in range(tracks.n_frames):
            rows.append({"track_id": i, "seed": str(kinds[i]), "frame": f,
                         "x_px": float(tracks.xy[f, i, 0]), "y_px": float(tracks.xy[f, i, 1]),
                         "fb_error_px": float(tracks.fb_error_px[f, i]),
                         "valid": bool(tracks.valid[f, i]),
                         "zncc": float(tracks.zncc[f, i]),
                         "sigma_px": float(tracks.sigma_px[f, i]),
                         "gap_frames": int(tracks.gap_frames[f, i])})
    return rows


def _new_file(path, overwrite):
    """``Path(path)``, after refusing an existing file unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise SemlabError(f"{path} already exists: pass overwrite=True to replace it or choose "
                          "another --out folder")
    return path


def write_tracks_csv(path, tracks, seed_kind=None, overwrite=False):
    """Write ``tracks.csv`` (columns :data:`TRACKS_CSV_COLUMNS`, then the diagnostic
    :data:`TRACKS_CSV_EXTRA_COLUMNS`).

    Raises
    ------
    SemlabError
        ``path`` exists and ``overwrite`` is False.
    """
    path = _new_file(path, overwrite)
    rows = tracks_to_records(tracks, seed_kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(TRACKS_CSV_COLUMNS + TRACKS_CSV_EXTRA_COLUMNS))
        w.writeheader()
        for r in rows:
            r = dict(r)
            for k in ("x_px", "y_px", "fb_error_px", "zncc", "sigma_px"):
                r[k] = "" if not np.isfinite(r[k]) else f"{r[k]:.6f}"
            r["valid"] = int(r["valid"])
            w.writerow(r)
    return path


# ----------------------------------------------------------------------------- displacements

def _check_pixel_size(pixel_size_um):
    if pixel_size_um is None or not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise SemlabError(f"pixel_size_um must be a positive number, got {pixel_size_um!r}; it is "
                          "in the SEM file metadata or experiment.toml")
    return float(pixel_size_um)


def _frame_index(f, F, what):
    fi = int(f)
    if not -F <= fi < F:
        raise TrackingError(f"{what}={f} is out of range for {F} frames")
    return fi % F


def displacements(tracks, pixel_size_um, frame_from=0, frame_to=-1):
    """In-plane displacement of each material point from ``frame_from`` to ``frame_to``.

    Parameters
    ----------
    tracks : Tracks
    pixel_size_um : float
        µm per pixel.
    frame_from, frame_to : int
        Chronological frame indices (negative counts from the end).

    Returns
    -------
    dict of (N,) arrays ``dx_um, dy_um, d_um`` (x right, y down), NaN where the track is
    invalid in either frame, plus ``valid`` (N,) bool.
    """
    s = _check_pixel_size(pixel_size_um)
    F = tracks.n_frames
    a = _frame_index(frame_from, F, "frame_from")
    b = _frame_index(frame_to, F, "frame_to")
    ok = tracks.valid[a] & tracks.valid[b]
    d = (tracks.xy[b] - tracks.xy[a]) * s
    d[~ok] = np.nan
    return {"dx_um": d[:, 0], "dy_um": d[:, 1], "d_um": np.hypot(d[:, 0], d[:, 1]), "valid": ok}


def displacement_history(tracks, pixel_size_um, frame_from=0):
    """Displacement of each material point in every frame relative to ``frame_from``.

    Returns
    -------
    dict of (F, N) arrays ``dx_um, dy_um, d_um`` (NaN where the track is invalid in that
    frame or in ``frame_from``) and ``valid`` (F, N) bool.
    """
    s = _check_pixel_size(pixel_size_um)
    a = _frame_index(frame_from, tracks.n_frames, "frame_from")
    ok = tracks.valid & tracks.valid[a][None, :]
    d = (tracks.xy - tracks.xy[a][None]) * s
    d[~ok] = np.nan
    return {"dx_um": d[..., 0], "dy_um": d[..., 1], "d_um": np.hypot(d[..., 0], d[..., 1]),
            "valid": ok}


def earliest_displacements(tracks, pixel_size_um, registration=None, frame_from=None):
    """Displacement of each track from its earliest valid frame to the last frame.

    Parameters
    ----------
    tracks : semlab.tracking.Tracks
    pixel_size_um : float
    registration : semlab.registration.Registration, optional
        Default ``tracks.registration``. When present, the start position (in its frame's
        own pixels) is first mapped into the last frame's geometry through the inverse of
        the **rigid-body part** of that frame's transform (the shift of the image centre and
        the rotation about it): ``dx, dy`` then hold the material's own motion (plus any
        magnification change and scan shear, which cannot be told apart from strain), the
        ``*_raw_um`` columns the motion in pixel coordinates, stage drift included.
    frame_from : (N,) int array, optional
        Start frame per track (default: the earliest valid frame, -1 where only the last
        frame is valid).

    Returns
    -------
    dict of (N,) arrays: ``frame_from``, ``dx_um, dy_um, d_um`` (rigid motion removed),
    ``dx_raw_um, dy_raw_um, d_raw_um``; NaN where ``frame_from`` is -1.
    """
    s = _check_pixel_size(pixel_size_um)
    reg = tracks.registration if registration is None else registration
    if frame_from is None:
        v = np.asarray(tracks.valid, bool)[:-1]
        frame_from = np.where(v.any(axis=0), np.argmax(v, axis=0), -1)
    first = np.asarray(frame_from, int)
    n = tracks.n_tracks
    start = tracks.xy[np.clip(first, 0, None), np.arange(n)].copy()
    start[first < 0] = np.nan
    end = tracks.xy[-1]
    raw = (end - start) * s
    if reg is not None:
        start = reg.to_reference(start, np.clip(first, 0, None), part="rigid")
    d = (end - start) * s
    return {"frame_from": first, "dx_um": d[:, 0], "dy_um": d[:, 1], "d_um": np.hypot(*d.T),
            "dx_raw_um": raw[:, 0], "dy_raw_um": raw[:, 1], "d_raw_um": np.hypot(*raw.T)}


def write_displacements_csv(path, tracks, disp, seed_kind=None, z_um=None, overwrite=False):
    """Write ``displacements.csv`` (:data:`DISPLACEMENTS_CSV_COLUMNS`).

    Parameters
    ----------
    tracks : semlab.tracking.Tracks
        ``x_px, y_px`` are the last-frame positions.
    disp : dict
        From :func:`earliest_displacements`.
    seed_kind : (N,) str, optional
    z_um : (N,) float, optional
        Heights of stereo-seeded tracks (empty cells for NaN).
    """
    path = _new_file(path, overwrite)
    kinds = tracks.seed_kind if seed_kind is None else seed_kind
    z = np.full(tracks.n_tracks, np.nan) if z_um is None else np.asarray(z_um, float)
    xy = tracks.xy[-1]

    def fmt(v):
        return "" if not np.isfinite(v) else f"{v:.6g}"

    rows = [",".join(DISPLACEMENTS_CSV_COLUMNS)]
    for i in range(tracks.n_tracks):
        rows.append(",".join([str(i), str(kinds[i]), f"{xy[i, 0]:.4f}", f"{xy[i, 1]:.4f}",
                              str(int(disp["frame_from"][i]))]
                             + [fmt(disp[k][i]) for k in ("dx_um", "dy_um", "d_um")] + [fmt(z[i])]
                             + [fmt(disp[k][i]) for k in ("dx_raw_um", "dy_raw_um", "d_raw_um")]))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(rows) + "\n")
    return path
