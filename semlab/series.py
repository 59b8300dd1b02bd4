"""The series chain (during the test) behind :class:`semlab.Analysis`: tracking,
displacements, strain, and their result files.

Series::

    frames ─► registration (stage drift) ─► seeds (Shi–Tomasi corners in the last frame, a
        grid where its texture allows valid steps (with sized subsets), stereo points
        registered into it) ─► tracking.track_reverse ─► displacements ─► strain
        ─► tracks.csv, displacements.csv, drift.csv, strain.npz

:class:`semlab.Analysis` (``semlab run``) tracks with subsets sized by their information by
default (``AnalysisConfig.track_method="subset"``, target 0.02 px); :func:`run_tracking`'s
own default stays pyramidal LK on the corners.

Each step is a function of semlab's modules; this file only chains them and writes files.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._api import strict_keywords
from .errors import SemlabError, SemlabWarning

__all__ = ["TrackingResult", "earliest_valid_frame", "run_tracking", "run_strain",
           "tracking_strain_history", "write_tracking_results", "write_strain_results"]


@dataclass
class TrackingResult:
    """Tracks, displacements and strain from the frontal series.

    Attributes
    ----------
    tracks : semlab.tracking.Tracks
        Every step with its forward–backward error and valid flag, by chronological frame.
    seed : (N,) str
        ``"corner"`` (Shi–Tomasi in the last frame), ``"grid"`` (a regular grid, see
        :func:`run_tracking`'s ``grid_kw``) or ``"stereo"`` (a stereo point registered into
        the last frame).
    stereo_index : (N,) int
        Index into the stereo result of a stereo-seeded track, -1 for corners.
    z_um : (N,) float
        Height of stereo-seeded tracks (NaN for corners).
    frame_from : (N,) int
        Earliest frame where the track is valid (-1: never valid besides the last frame).
    dx_um, dy_um, d_um : (N,) float
        Displacement from ``frame_from`` to the last frame (NaN where ``frame_from`` = -1),
        the stage's rigid-body motion removed (see
        :func:`semlab.displacement.earliest_displacements`).
    dx_raw_um, dy_raw_um, d_raw_um : (N,) float
        The same in raw pixel coordinates (stage drift included).
    registration : dict
        Stereo view 0 → last frame registration (``A`` (2, 3), ``residual_px``), or empty.
    pixel_size_um : float
    cycles : (F,) float or None
    """

    tracks: object
    seed: np.ndarray
    stereo_index: np.ndarray
    z_um: np.ndarray
    frame_from: np.ndarray
    dx_um: np.ndarray
    dy_um: np.ndarray
    d_um: np.ndarray
    registration: dict
    pixel_size_um: float
    cycles: np.ndarray | None = None
    dx_raw_um: np.ndarray | None = None
    dy_raw_um: np.ndarray | None = None
    d_raw_um: np.ndarray | None = None


def earliest_valid_frame(valid):
    """Per track, the earliest frame whose step is valid, ignoring the reference (last) frame.

    Parameters
    ----------
    valid : (F, N) bool array

    Returns
    -------
    (N,) int, -1 where only the reference frame is valid.
    """
    v = np.asarray(valid, bool)[:-1]
    first = np.argmax(v, axis=0)
    return np.where(v.any(axis=0), first, -1)


@strict_keywords
def run_tracking(exp, stereo=None, method="lk", corner_kw=None, track_kw=None, progress=True,
                 register="similarity", grid_kw="auto"):
    """Track points backwards through the series and derive the displacements.

    Parameters
    ----------
    exp : semlab.experiment.Experiment
    stereo : (pts_view0 (M, 2), z_um (M,)), optional
        Stereo points (view-0 pixels and heights, e.g. from :func:`run_stereo`): registered from view 0 into the last frame
        and tracked too.
    method : {"lk", "subset"}
        Pyramidal Lucas–Kanade, or the DIC-grade IC-GN subset matching.
    corner_kw, track_kw : dict, optional
        Passed to :func:`semlab.tracking.shi_tomasi_seeds` / :func:`~semlab.tracking.track_reverse`.
    register : {"similarity", "affine", "translation", None}
        Register every frame to the last one first and track in the registered geometry
        (stage drift); None: track in the raw frames. ``"similarity"`` (shift, rotation,
        magnification: a stage) is the default because an affine fit to features on a
        slip-banded surface can take a shear and a 3 % stretch from the material's own,
        non-uniform motion; ``"affine"`` also absorbs a linear scan drift.
    grid_kw : dict, "auto" or None
        Also seed a regular grid of the last frame (:func:`semlab.tracking.grid_seeds`
        with these keywords; ``{}`` for its defaults), ``seed`` ``"grid"``: grid points
        within half a grid step of a corner are left out, and so are those whose subset
        cannot reach the steps' ``max_sigma_px`` even in the last frame
        (:func:`semlab.tracking.seed_sigma_px` at ``max_half_window``: no texture there).
        ``"auto"`` (default): the default grid when ``track_kw`` sizes the subsets by
        their information (``target_sigma_px``), none otherwise. None: corners (and stereo
        points) only. On a polished surface the corners are a few dozen particles (29 on
        the 384×512 series of ``benchmarks/tracking_series.py``), too few for a strain.

    Returns
    -------
    TrackingResult
    """
    from . import tracking
    from .displacement import earliest_displacements
    from .registration import register_points

    if exp.series is None:
        raise SemlabError(f"{exp.toml_path}: no [series] table, so nothing to track")
    frames = exp.frames(progress=progress)
    if len(frames) < 2:
        raise SemlabError(f"{exp.toml_path}: the series has {len(frames)} frame; tracking needs 2 or more")
    corners = tracking.shi_tomasi_seeds(frames[-1], name=exp.series.frame_paths[-1].name,
                                        **(corner_kw or {}))
    seeds, kinds, sidx = [corners], [np.array(["corner"] * len(corners))], [np.full(len(corners), -1)]
    tkw = dict(track_kw or {})
    if isinstance(grid_kw, str):
        if grid_kw != "auto":
            raise SemlabError(f"grid_kw={grid_kw!r}: give a dict of grid_seeds keywords, "
                              "'auto' or None")
        grid_kw = {} if tkw.get("target_sigma_px") is not None else None
    if grid_kw is not None:
        grid = tracking.grid_seeds(frames[-1].shape, avoid=corners, **grid_kw)
        max_sigma = tracking._max_sigma(tkw.get("max_sigma_px", "auto"),
                                        tkw.get("target_sigma_px"))
        if max_sigma is not None and len(grid):
            hw = tkw.get("max_half_window", 20) if tkw.get("target_sigma_px") is not None \
                else tkw.get("subset_half_window") or tkw.get("win_size", 21) // 2
            sm = tkw.get("smooth_sigma_px")
            sm = (0.8 if tkw.get("target_sigma_px") is not None else 0.0) if sm is None else sm
            grid = grid[tracking.seed_sigma_px(frames[-1], grid, half_window=hw,
                                               smooth_sigma_px=sm) <= max_sigma]
        seeds.append(grid)
        kinds.append(np.array(["grid"] * len(grid)))
        sidx.append(np.full(len(grid), -1))
    registration = {}
    if stereo is not None and exp.stereo is not None:
        mapped, A, residual = register_points(exp.views()[0], frames[-1], stereo[0])
        h, w = frames[-1].shape
        inside = ((mapped[:, 0] > 12) & (mapped[:, 0] < w - 13) & (mapped[:, 1] > 12)
                  & (mapped[:, 1] < h - 13))
        seeds.append(mapped[inside])
        kinds.append(np.array(["stereo"] * inside.sum()))
        sidx.append(np.flatnonzero(inside))
        registration = {"A": A, "residual_px": float(np.atleast_1d(residual).mean())}
    seeds = np.concatenate(seeds)
    kind = np.concatenate(kinds)
    stereo_index = np.concatenate(sidx)
    from .parallel import tiled_track_reverse

    # in tiles on the cluster for large frames (the untiled result, see semlab.parallel)
    tracks = tiled_track_reverse(frames, seeds, method=method, seed_kind=kind,
                                 progress=progress, register=register,
                                 **(track_kw or {}))
    s = exp.pixel_size_um
    first = earliest_valid_frame(tracks.valid)
    n = tracks.n_tracks
    disp = earliest_displacements(tracks, s, frame_from=first)
    z = np.full(n, np.nan)
    if stereo is not None:
        z[stereo_index >= 0] = np.asarray(stereo[1])[stereo_index[stereo_index >= 0]]
    return TrackingResult(tracks=tracks, seed=kind, stereo_index=stereo_index, z_um=z,
                          frame_from=first, dx_um=disp["dx_um"], dy_um=disp["dy_um"], d_um=disp["d_um"],
                          dx_raw_um=disp["dx_raw_um"], dy_raw_um=disp["dy_raw_um"],
                          d_raw_um=disp["d_raw_um"],
                          registration=registration, pixel_size_um=s,
                          cycles=exp.series.cycles)


@strict_keywords
def run_strain(exp, tracking_result, gauge_length_px=None, min_tracks=20, progress=False,
               dense_method="variational"):
    """Strain between the earliest frame that still has enough valid tracks and the last.

    When no frame before the last has enough valid tracks (weak texture against the noise,
    large deformation between frames), the dense strain still comes from the variational
    map, which needs no tracks: from frame 0 to the last, the map found frame by frame back
    from the last (:func:`semlab.strain.chained_flow_start`, with the tracking's drift),
    without a sparse strain (``sparse_strain`` False, a warning of the step says why). On a
    5-frame polished series with realistic noise that kept 62 of 1433 tracks valid one step
    back (``semlab synth --seed 11 --texture polished --noise realistic --frames 5 --size
    300x420``, 2026-12-08, ``semlab run``) its strain from frame 0 was off by 0.0020 / 0.0081 /
    0.0020 RMS (E_xx / E_yy / E_xy, perfect-tracker truth) where OpenCV DeepFlow from the
    same frames was off by 0.0049 / 0.059 / 0.020; its E_yy 1σ is short there (48 % within
    2σ: the bands' strain is rounded).

    Parameters
    ----------
    exp : semlab.experiment.Experiment
    tracking_result : TrackingResult
    gauge_length_px : float, optional
        Sparse-strain gauge length (None: from the track density).
    min_tracks : int
        A reference frame needs at least ``max(min_tracks, 0.2 × tracks)`` valid tracks.
    dense_method : {"variational", "subsets"}
        The dense strain's displacement (:func:`semlab.strain.strain_from_tracks`).

    Returns
    -------
    dict
        :func:`semlab.strain.strain_from_tracks` plus ``history`` (mean strain of every frame
        relative to the end state) and ``sparse_strain`` (False: no frame had enough valid
        tracks, the dense strain alone, from frame 0). ``E_lsq_sigma`` is the 1σ of the sparse strain propagated
        from the tracks' ``sigma_px`` in the reference frame (each track's predicted error
        relative to its seed in the last frame); NaN when the tracks were made without
        direct correction, whose ``sigma_px`` is that of the last chained step only.

    Raises
    ------
    SemlabError
        No frame before the last has enough valid tracks and ``dense_method`` is
        ``"subsets"`` (whose start comes from the tracks): the strain cannot be computed (an
        error of this step, never an empty result).
    """
    from scipy.interpolate import griddata

    from . import strain as st

    tr = tracking_result
    tracks = tr.tracks
    n = tracks.n_tracks
    counts = tracks.valid[:-1].sum(axis=1)
    need = max(min_tracks, 0.2 * n)
    enough = np.flatnonzero(counts >= need)
    best = int(np.argmax(counts)) if len(counts) else 0
    why = (f"no frame before the last has enough valid tracks (best: "
           f"{int(counts.max()) if len(counts) else 0} of {n} in frame {best}, need "
           f"{int(np.ceil(need))}); {_why_tracks_invalid(tracks, best)}")
    dense_only = not len(enough)
    if dense_only and dense_method != "variational":
        raise SemlabError(f"{exp.toml_path}: no strain: {why}; the dense strain's variational "
                          "map (dense_strain_method = 'variational') does not need the tracks")
    heights = None
    has_z = np.isfinite(tr.z_um)
    if has_z.sum() >= 10:
        pz = tracks.xy[-1][has_z]
        zz = tr.z_um[has_z]

        def heights(x, y):
            zi = griddata(pz, zz, (x, y), method="linear")
            return np.where(np.isfinite(zi), zi, griddata(pz, zz, (x, y), method="nearest"))
    frames = exp.frames(progress=progress)
    ref, start, valid = (0 if dense_only else int(enough[0])), None, tracks.valid
    if dense_only:
        # the map needs no tracks: it steps back from the last frame one frame at a time
        # (semlab.strain.chained_flow_start) to the earliest frame; no sparse strain
        warnings.warn(f"sparse strain: none, {why}; the dense strain is the variational map's "
                      "alone, from frame 0, found frame by frame back from the last",
                      SemlabWarning, stacklevel=2)
        start = st.chained_flow_start(frames, ref, tracks.registration, progress=progress)
        valid = valid.copy()
        valid[ref] = False                     # too few for a sparse strain: none
    out = st.strain_from_tracks(frames, tracks.xy, valid, tr.pixel_size_um, ref,
                                gauge_length_px=gauge_length_px, heights=heights,
                                progress=progress, sigma_px=_position_sigma(tracks),
                                dense_method=dense_method, dense_start_px=start)
    out["sparse_strain"] = not dense_only
    out["history"] = tracking_strain_history(tracks, exp.series.cycles, tr.pixel_size_um)
    return out


def _position_sigma(tracks):
    """(F, N) 1σ of each track's position relative to its seed in the last frame, pixels:
    ``Tracks.sigma_px`` when the tracking matched every frame directly against the last one
    (its direct correction, the default); None otherwise, where ``sigma_px`` is the σ of the
    last chained step only, not of the accumulated chain."""
    return tracks.sigma_px if tracks.params.get("direct_correction", True) else None


def tracking_strain_history(tracks, cycles, pixel_size_um):
    """Mean Green–Lagrange strain of every frame relative to the last one (end state).

    The last frame is the reference here because every track is valid in it; the strain of
    frame f relative to the end is the deformation still to come, plotted against cycles.
    With the tracking's direct correction (its default) the history has ``exx_sigma``,
    ``eyy_sigma``, ``exy_sigma``, the 1σ of each frame's mean strain from the tracks'
    ``sigma_px[f]`` (:func:`semlab.strain.strain_history`); NaN without it.
    """
    from . import strain as st

    cyc = np.arange(tracks.n_frames, dtype=float) if cycles is None else np.asarray(cycles, float)
    sig = _position_sigma(tracks)
    sig = np.full(tracks.sigma_px.shape, np.nan) if sig is None else sig
    return st.strain_history(tracks.xy, cyc, valid=tracks.valid, ref_frame=tracks.n_frames - 1,
                             pixel_size_um=pixel_size_um, sigma_px=sig)


def write_tracking_results(result, out_dir, overwrite=False):
    """Write ``tracks.csv``, ``displacements.csv`` and, when the frames were registered,
    ``drift.csv`` into ``out_dir``.

    ``tracks.csv``: ``track_id,seed,frame,x_px,y_px,fb_error_px,valid`` (frame 0 = earliest).
    ``displacements.csv``: :data:`semlab.displacement.DISPLACEMENTS_CSV_COLUMNS`, with the
    last-frame position and the displacement from ``frame_from`` to the last frame
    (``z_um`` for stereo-seeded tracks, empty otherwise; rigid stage motion removed, then
    the raw columns). ``drift.csv``: :func:`semlab.registration.write_drift_csv`.
    """
    from . import tracking
    from .displacement import write_displacements_csv
    from .registration import write_drift_csv

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    reg = getattr(result.tracks, "registration", None)
    paths = [out / "tracks.csv", out / "displacements.csv"]
    paths += [out / "drift.csv"] if reg is not None else []
    for p in paths:
        if p.exists() and not overwrite:
            raise SemlabError(f"{p}: exists already; write results to a new folder")
    tracking.write_tracks_csv(paths[0], result.tracks, seed_kind=result.seed, overwrite=overwrite)
    disp = {"frame_from": result.frame_from}
    for k in ("dx", "dy", "d"):
        disp[f"{k}_um"] = getattr(result, f"{k}_um")
        raw = getattr(result, f"{k}_raw_um")
        disp[f"{k}_raw_um"] = disp[f"{k}_um"] if raw is None else raw
    write_displacements_csv(paths[1], result.tracks, disp, seed_kind=result.seed, z_um=result.z_um,
                            overwrite=overwrite)
    if reg is not None:
        write_drift_csv(paths[2], reg, overwrite=overwrite)
    return paths


def _why_tracks_invalid(tracks, frame):
    """What a user can do about too few valid tracks in ``frame``: with LK, the subsets; with
    subsets whose predicted σ exceeds the tracking's ``max_sigma_px`` at most points, the
    frames' information (texture against noise) is the limit, said with the numbers."""
    if tracks.method != "subset":
        return "try track_method='subset' or a series with more texture in its early frames"
    cap = tracks.params.get("max_sigma_px")
    sig = tracks.sigma_px[frame][np.isfinite(tracks.sigma_px[frame])]
    if cap is None or not len(sig) or np.mean(sig > cap) < 0.5:
        return ("the steps failed the tracking's other checks (forward–backward, ZNCC, residual, "
                "median test): see the tracking notebook's reliability flags; a series with more "
                "texture in its early frames, or less motion between frames, tracks further")
    return (f"there the tracks' median predicted 1σ is {np.median(sig):.2f} px and "
            f"{100 * np.mean(sig > cap):.0f} % of them exceed the {cap:g} px a valid step may "
            "have: within subsets small enough to follow the deformation, the frames' texture "
            "is too weak for their noise; frames with less noise (a longer dwell or more "
            "averaging), more texture, or more frames (less deformation between them) are "
            "needed")


def write_strain_results(strain, out_dir, overwrite=False):
    """Write ``strain.npz`` (the dict of :func:`run_strain`, nested dicts flattened as
    ``outer_inner``) into ``out_dir``."""
    p = Path(out_dir) / "strain.npz"
    if p.exists() and not overwrite:
        raise SemlabError(f"{p}: exists already; write results to a new folder")
    flat = {}
    for k, v in strain.items():
        if isinstance(v, dict):
            for kk, vv in v.items():
                flat[f"{k}_{kk}"] = np.asarray(vv)
        else:
            flat[k] = np.asarray(v)
    np.savez_compressed(p, **flat)
    return [p]
