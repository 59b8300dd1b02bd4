"""Reverse-time point tracking on a frontal SEM image series.

During a fatigue test a fixed frontal view is taken every N cycles; frames are chronological
(frame 0 = earliest). Features are well defined only at the end of the test, so points are
seeded in the LAST frame (the reference) and followed BACKWARDS in time to frame 0.
Results are always stored by chronological frame index ``0 .. F-1``, never reversed.

Every step of every track carries a reliability flag (forward-backward error, LK status,
ZNCC against the reference); a track never jumps silently.

Conventions: images are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)`` in
pixels, x to the right, y down, origin at the centre of the top-left pixel (OpenCV).

References
----------
- J.-Y. Bouguet, "Pyramidal implementation of the affine Lucas Kanade feature tracker",
  Intel Corp. (2001) -- ``cv2.calcOpticalFlowPyrLK``.
- Z. Kalal, K. Mikolajczyk, J. Matas, "Forward-backward error: automatic detection of
  tracking failures", ICPR 2010.
- J. Shi, C. Tomasi, "Good features to track", CVPR 1994.
- D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60 (2004)
  (SIFT and the ratio test).
- B. Pan, K. Li, W. Tong, "Fast, robust and accurate digital image correlation calculation
  without redundant computations", Exp. Mech. 53 (2013) (ZNCC, IC-GN).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from .displacement import (TRACKS_CSV_COLUMNS, TRACKS_CSV_EXTRA_COLUMNS,  # noqa: F401 (re-exported)
                           displacement_history, displacements, tracks_to_records,
                           write_tracks_csv)
from .errors import TrackingError
from .track_steps import (_BLANK_REL_RANGE, TrackingWarning, _as_2d,  # noqa: F401 (re-exported)
                          _check_track_loss, _inside, _lk, _min_gradient_energy,
                          _sample_patches, _seed_kinds, _to_u8, _zncc,
                          grid_seeds, match_sigma_px, median_outliers, normalize_frame,
                          shi_tomasi_seeds)

__all__ = [
    "Tracks",
    "TrackingWarning",
    "normalize_frame",
    "match_sigma_px",
    "median_outliers",
    "shi_tomasi_seeds",
    "grid_seeds",
    "seed_sigma_px",
    "track_reverse",
    "tracks_to_records",
    "write_tracks_csv",
    "displacements",
    "displacement_history",
    "TRACKS_CSV_COLUMNS",
    "TRACKS_CSV_EXTRA_COLUMNS",
]


@dataclass
class Tracks:
    """Result of :func:`track_reverse`; every array is indexed by chronological frame.

    Attributes
    ----------
    xy : (F, N, 2) float array
        Position ``(x, y)`` in pixels of each track in each frame. Holds the best estimate
        whenever a match was computed, also for steps flagged invalid; NaN where no estimate
        exists (LK failure, point left the image, blank frame). Use ``valid`` to select.
    fb_error_px : (F, N) float array
        Forward-backward error of the step, pixels (0 in the reference frame, NaN when not
        computed).
    valid : (F, N) bool array
        True where the step passed every check (LK status, fb error, ZNCC).
    zncc : (F, N) float array
        Zero-normalised cross-correlation between the window at the track position in the
        frame and the window at the seed in the reference frame.
    sigma_px : (F, N) float array
        Predicted 1-sigma position uncertainty of the step, pixels (see
        :func:`match_sigma_px`); 0 in the reference frame.
    gap_frames : (F, N) int array
        Number of suspended (invalid) frames bridged by the step: 0 for a step from the
        next-later frame, k > 0 for a track re-acquired after k invalid frames. Re-acquired
        steps are where a look-alike feature is most likely to be matched instead; treat
        large gaps with suspicion.
    seed_kind : (N,) array of str
        Caller's label of each seed (e.g. ``"shi_tomasi"``, ``"stereo"``, ``"click"``).
    reference_frame : int
        Index of the reference (seed) frame, ``F - 1``.
    method : str
        ``"lk"`` or ``"subset"``.
    registration : semlab.registration.Registration or None
        The frame-to-reference transforms when tracking ran in the registered geometry
        (``register=``), else None.
    subset_px : (F, N) int array or None
        With ``method="subset"``: side (pixels) of the square subset of each step (0 where
        it did not converge and in the reference frame); times the pixel size it is the
        step's spatial resolution. None for ``method="lk"``.
    """

    xy: np.ndarray
    fb_error_px: np.ndarray
    valid: np.ndarray
    zncc: np.ndarray
    sigma_px: np.ndarray
    gap_frames: np.ndarray
    seed_kind: np.ndarray
    reference_frame: int
    method: str = "lk"
    params: dict = field(default_factory=dict)
    registration: object = None
    subset_px: np.ndarray = None

    @property
    def n_frames(self) -> int:
        return self.xy.shape[0]

    @property
    def n_tracks(self) -> int:
        return self.xy.shape[1]

    def valid_fraction(self):
        """(F,) fraction of tracks valid in each frame."""
        return self.valid.mean(axis=1) if self.n_tracks else np.zeros(self.n_frames)


def track_reverse(frames, seeds, method="lk", win_size=21, max_level=3, fb_threshold_px=0.5,
                  min_zncc=0.7, direct_correction=True, progress=True, seed_kind=None,
                  max_sigma_px="auto", outlier_threshold=2.0, n_neighbours=8,
                  max_jump_px=None, subset_half_window=None, max_gap_frames=3,
                  lk_check_px=0.2, register=None, target_sigma_px=None, max_half_window=20,
                  curvature_neighbours=9, max_residual_ratio=2.0,
                  smooth_sigma_px=None, model_neighbours=12):
    """Track points seeded in the last frame backwards in time to frame 0.

    With ``register``, every frame is first registered to the reference by one global
    transform (:func:`semlab.registration.register_frames`: features, RANSAC, ECC) and the
    steps below run in the registered geometry: every start position, subset warp and
    jump/neighbour test carries the frame-to-frame transform, so stage drift between
    frames does not enter them. The frames are not resampled (resampling smooths the noise
    and made the predicted ``sigma_px`` over-confident): positions, ``fb_error_px`` and
    ``sigma_px`` are in each frame's own pixels.

    Algorithm (for each frame ``k = F-2, F-3, ..., 0``):

    1. **Chained step.** Each track is matched by pyramidal Lucas-Kanade (Bouguet 2001) from
       its *source* frame -- the most recent (in processing order) frame where it was valid,
       normally ``k + 1`` -- into frame ``k``.
    2. **Direct-to-reference correction** (``direct_correction=True``). The seed window in the
       reference (last) frame is matched directly into frame ``k``, starting from the chained
       position, so errors do not accumulate along the chain. With ``method="subset"`` this
       match is an IC-GN subset refinement (:func:`semlab.subset.icgn_refine`, affine warp)
       instead of LK.
    3. **Forward-backward check** (Kalal et al. 2010). The final position is matched back into
       the frame it was matched from (the reference with direct correction, else the source
       frame); ``fb_error_px`` is the distance between the point reached and the start point.
    4. **ZNCC check.** ZNCC between the window at the track position in frame ``k`` and the
       seed window in the reference frame (images contrast-stretched per frame).
    5. **Predicted uncertainty.** ``sigma_px`` from the ZNCC and the gradient energy of the
       reference window (:func:`match_sigma_px`).
    6. **No jump.** The position may not lie more than ``max_jump_px`` from the track's last
       valid position (also across suspended frames), so a track re-acquired after a gap
       cannot lock onto a look-alike feature far away.
    7. **Neighbour consistency.** Normalised median test of the displacement (from the
       reference) against the ``n_neighbours`` nearest tracks (:func:`median_outliers`,
       Westerweel & Scarano 2005), which catches isolated jumps.
    8. **Subset agreement** (``method="lk"``). The LK position is re-matched against the
       reference by IC-GN with an affine subset and the zero-normalised criterion; the step
       is valid only if the two agree within ``lk_check_px``. LK minimises plain squared
       differences, so on frames whose brightness and contrast differ from the reference
       (low-contrast early frames, charging) it can be biased by more than its predicted
       ``sigma_px``: on a synthetic series without this check 38 valid LK steps were
       0.5–0.8 px off. The subset's position is the one kept: zero-normalised and affine
       (with ``register`` its warp also carries the frame's rotation and scale), where
       LK's window is a plain translation (RMS error of the valid steps of the synthetic
       drift benchmark 0.091/0.131/0.123 → 0.076/0.075/0.080 px, seeds 0/1/2).

    A step is **valid** when the match succeeded (LK status ok / IC-GN converged, inside the
    image), ``fb_error_px <= fb_threshold_px``, ``zncc >= min_zncc``,
    ``sigma_px <= max_sigma_px``, it moved at most ``max_jump_px`` and it passes the median
    test (each check can be disabled by passing None, except the jump bound).

    The forward-backward error alone does not bound the position error in noisy frames
    (both directions see the same noise), hence checks 5-6. On a synthetic series with
    white noise, real errors have heavy tails (up to ~8 sigma_px at signal-to-noise ~1.5,
    partly the noise-induced interpolation bias of sub-pixel matching), which is why the
    default ``max_sigma_px`` is a tenth of the 0.5 px error budget (a fifth for subsets sized
    by their information, whose σ also counts the model error, see ``model_neighbours``).
    The translation-only LK
    window is also biased by strain between the frame and the reference (about
    ``strain x win_size / 4`` px); use ``method="subset"`` (affine subsets) where strains
    exceed ~2 %.

    Policy for invalid steps: an invalid step *suspends* the track. Its estimate is stored in
    ``xy`` (flagged invalid) but is never used to continue: at each earlier frame the track is
    re-attempted from its last valid frame and position (the chained LK skips the bad
    frames). It stays invalid until a step passes every check again, and then it is valid
    from that frame on. Hence ``valid[k]`` never depends on an unverified position.

    Parameters
    ----------
    frames : sequence of F >= 2 (H, W) arrays, chronological (frame 0 = earliest)
        Any real dtype; each frame is contrast-stretched (:func:`normalize_frame`).
    seeds : (N, 2) array of (x, y) pixels in the last frame
    method : {"lk", "subset"}
        Matcher of the direct-to-reference step (``"subset"`` needs ``direct_correction``).
    win_size : int
        LK window size (pixels, odd) and ZNCC window size.
    max_level : int
        Number of LK pyramid levels above the full image.
    fb_threshold_px : float
        Largest forward-backward error of a valid step, pixels.
    min_zncc : float or None
        Smallest ZNCC of a valid step; None to skip this check (ZNCC is still reported).
    direct_correction : bool
        Re-match every frame directly against the reference (recommended).
    progress : bool
        Show a tqdm progress bar over frames.
    seed_kind : str or (N,) sequence of str, optional
        Label(s) stored in ``Tracks.seed_kind`` (default ``"seed"``).
    max_sigma_px : float, "auto" or None
        Largest predicted 1-sigma error of a valid step, pixels. ``"auto"``: 0.05 (a tenth
        of the 0.5 px error budget), 0.1 (a fifth) with ``target_sigma_px``, whose σ is the
        Gauss–Newton covariance with the a posteriori residual factor and the model error
        of ``model_neighbours``: on the 8-frame polished / real:fei / real:quartz series of
        ``benchmarks/tracking_series.py`` (609 grid seeds) the sized subsets with 0.1 and
        the noise σ alone kept 0 / 19 / 5 valid steps more than 0.5 px off (errors 5–12 σ
        beside the slip bands, where a 41 px subset straddles a 3–5 px slip step), with
        the model error counted 0 / 1 / 0.
    outlier_threshold : float or None
        Threshold of the normalised median test (2 is Westerweel & Scarano's value).
    n_neighbours : int
        Neighbours of the median test.
    max_jump_px : float, optional
        Largest distance between a valid step and the track's last valid position, pixels
        (default ``win_size``; raise it for series with large motion between frames).
    subset_half_window : int, optional
        IC-GN subset half size for ``method="subset"`` (default ``win_size // 2``).
    max_gap_frames : int or None
        A track suspended for more than this many consecutive frames has ended: it is never
        valid again (re-acquisition after a long gap is where look-alike features are
        matched). None: no limit.
    lk_check_px : float or None
        With ``method="lk"``: largest distance between the LK position and its IC-GN
        re-match (check 8), pixels. None: no check (the plain LK of the reference paper).
    target_sigma_px : float or None
        With ``method="subset"``: size each track's subset per step by its information
        (:func:`semlab.adaptive.adaptive_icgn`, affine): the smallest square subset from
        ``subset_half_window`` up to ``max_half_window`` (half sizes growing by ~√2)
        whose predicted total error (1σ and the curvature bias of the affine subset, see
        ``curvature_neighbours``) reaches this target (pixels), else the one with the
        smallest; ``Tracks.subset_px`` holds each step's subset side. None: one fixed
        ``subset_half_window``.
    max_half_window : int
        Largest subset half size with ``target_sigma_px``.
    curvature_neighbours : int or None
        With ``target_sigma_px``: the curvature bias of each track is estimated from how
        its match moves with the subset size, averaged over this many nearest tracks
        (:func:`semlab.adaptive.adaptive_icgn`); None sizes by the noise alone. On a
        0.1 px sinusoid on a real texture (``benchmarks/resolution_sinusoid.py``) the
        noise alone grew the subsets to 41 px and gave 0.025 px RMS at a 100 px period
        and 0.043 at 75; with the curvature 0.014 and 0.021.
    max_residual_ratio : float or None
        With ``method="subset"``: largest ratio of a step's residual to the one the
        measured noise predicts (:attr:`semlab.subset.SubsetResult.residual_ratio`): a
        subset over a slip step or changed relief fits no affine map, and its σ does not
        hold. None: no check. On three synthetic series (``benchmarks/tracking_accuracy.py``
        (d)) 2.0 removed the 4 / 1 / 1 valid steps more than 0.5 px off of fixed 21×21
        subsets (valid fraction 0.365 / 0.339 / 0.350 -> 0.341 / 0.327 / 0.313); with
        ``target_sigma_px=0.02`` (and its 0.8 px smoothing) none is left, at a valid
        fraction of 0.483 / 0.415 / 0.358 and 0.05–0.06 px RMS (unsmoothed: 1 / 2 / 0 left,
        7 / 4 / 2 without the check).
    smooth_sigma_px : float or None
        Gaussian pre-smoothing (pixels) of the frames for the IC-GN subsets (see
        :func:`semlab.subset.icgn_refine`: on noisy frames the unsmoothed cost is too rough
        to converge; the predicted σ accounts for the smoothing). None: 0.8 px with
        ``target_sigma_px`` (as :func:`semlab.matching.refine_correspondences`), else 0.
        On a low-texture ``polished`` synthetic series (realistic detector, 8 frames,
        462 truth points) fixed 21×21 subsets, smoothed or not, and unsmoothed subsets
        sized up to 57 px (``target_sigma_px=0.02, max_half_window=28``) lose every track
        at the first step; smoothed sized subsets keep 3 % there, and 76 % with
        ``max_sigma_px=0.1`` (0.22–0.5 in frames 1–5, 1 % in frame 0, none 0.5 px off,
        RMS 0.11 px).
    model_neighbours : int or None
        With ``target_sigma_px``: each step's σ also holds the model error of its affine
        subset, measured per frame from how far the displacements of the ``model_neighbours``
        nearest converged tracks (more where the subsets are larger than their spacing)
        depart from a local plane beyond what their own σ explains
        (:func:`semlab.match_sigma.parallax_model_error` on each component, the larger
        kept), and the a posteriori factor of its residual
        (:func:`semlab.match_sigma.match_sigma`). A subset over a slip step fits a blend
        whose residual the noise of a weak texture hides; its neighbours' field is not
        planar there. None: the noise σ alone.
    register : {None, "similarity", "affine", "translation"} or Registration
        Track in the registered geometry: the transform model to estimate, or a
        precomputed :class:`~semlab.registration.Registration` of these frames (reference
        = last frame). None: track in the raw frames.

    Returns
    -------
    Tracks

    Raises
    ------
    TrackingError
        Fewer than 2 frames, frames of different sizes, a blank reference frame, no seeds,
        seeds outside the reference frame, bad parameters, or not a single valid step in the
        whole series. Frames where every track is invalid give a :class:`TrackingWarning`
        naming them.

    Examples
    --------
    Three frames of a texture moving by 0.5 px in x per frame; seeds in the last frame:

    >>> import numpy as np, semlab
    >>> from scipy import ndimage
    >>> rng = np.random.default_rng(2)
    >>> last = ndimage.gaussian_filter(rng.normal(size=(128, 128)), 1.5)
    >>> frames = [ndimage.shift(last, (0.0, -0.5 * (2 - k)), order=3, mode="nearest")
    ...           for k in range(3)]
    >>> seeds = np.array([[40.0, 40.0], [64.0, 80.0], [90.0, 60.0]])
    >>> t = semlab.track_reverse(frames, seeds, method="subset", progress=False)
    >>> (np.round(t.xy[0] - seeds, 2) + 0.0).tolist(), bool(t.valid.all())
    ([[-1.0, 0.0], [-1.0, 0.0], [-1.0, 0.0]], True)
    """
    if method not in ("lk", "subset"):
        raise TrackingError(f"method must be 'lk' or 'subset', got {method!r}")
    if method == "subset" and not direct_correction:
        raise TrackingError("method='subset' matches each frame against the reference: "
                            "use direct_correction=True")
    frames = list(frames) if not isinstance(frames, np.ndarray) or frames.ndim == 3 else [frames]
    if len(frames) < 2:
        raise TrackingError(f"tracking needs at least 2 frames, got {len(frames)}; pass the whole "
                            "series, chronological (frame 0 = earliest)")
    shape0 = None
    for i, fr in enumerate(frames):
        a = _as_2d(fr, f"frame {i}")
        if shape0 is None:
            shape0 = a.shape
        elif a.shape != shape0:
            raise TrackingError(f"frame {i} has shape {a.shape} but frame 0 has {shape0}: all frames "
                                "of a series must have the same size (crop them identically)")
    seeds = np.asarray(seeds, dtype=np.float64)
    if seeds.ndim != 2 or seeds.shape[1] != 2:
        raise TrackingError(f"seeds must be an (N, 2) array of (x, y) pixels, got shape {seeds.shape}")
    if len(seeds) == 0:
        raise TrackingError("no seeds to track: pass at least one (x, y) point of the last frame "
                            "(e.g. from shi_tomasi_seeds(frames[-1]))")
    if not np.isfinite(seeds).all():
        raise TrackingError("seeds contain NaN/inf: remove them before tracking")
    if not _inside(seeds, shape0).all():
        bad = np.flatnonzero(~_inside(seeds, shape0))
        raise TrackingError(f"{len(bad)} seed(s) lie outside the last frame ({shape0[1]}x{shape0[0]} px), "
                            f"first index {bad[0]}: seeds are (x, y) pixels of the LAST frame")
    if target_sigma_px is not None and not (method == "subset" and np.isfinite(
            target_sigma_px) and target_sigma_px > 0):
        raise TrackingError(f"target_sigma_px={target_sigma_px!r}: subsets sized by their "
                            "information need method='subset' and a target > 0 pixels")
    max_sigma_px = _max_sigma(max_sigma_px, target_sigma_px)
    win_size = int(win_size)
    if win_size < 5 or win_size % 2 == 0:
        raise TrackingError(f"win_size must be an odd integer >= 5, got {win_size}")
    max_jump = float(win_size if max_jump_px is None else max_jump_px)
    if not max_jump > 0:
        raise TrackingError(f"max_jump_px must be > 0, got {max_jump_px!r}")
    if not fb_threshold_px > 0:
        raise TrackingError(f"fb_threshold_px must be > 0, got {fb_threshold_px!r}")
    n = len(seeds)
    kinds = _seed_kinds(seed_kind, n)
    if len(kinds) != n:
        raise TrackingError(f"seed_kind has {len(kinds)} labels for {n} seeds")

    F = len(frames)
    ref = F - 1
    half = win_size // 2
    reg = None
    if register is not None:
        from .registration import as_registration
        reg = as_registration(register, frames)
    norm, blank = [], []
    for fr in frames:
        f01, b = normalize_frame(_as_2d(fr, "frame"))
        norm.append(f01)
        blank.append(b)
    if blank[ref]:
        raise TrackingError(f"the reference (last) frame {ref} is blank: nothing can be tracked")
    u8 = [_to_u8(f) for f in norm]

    lk_kw = dict(winSize=(win_size, win_size), maxLevel=int(max_level),
                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-3))
    # the backward LK starts at the answer it should find: with registered frames that start
    # is tens of px from the point, and the coarse pyramid levels of a low-contrast frame
    # diverged from it (fb errors of 20-200 px on 15 of 44 tracks); full resolution only
    lk_back = lk_kw if reg is None else dict(lk_kw, maxLevel=0)

    xy = np.full((F, n, 2), np.nan)
    fb = np.full((F, n), np.nan)
    valid = np.zeros((F, n), bool)
    zn = np.full((F, n), np.nan)
    xy[ref] = seeds
    fb[ref] = 0.0
    valid[ref] = True
    zn[ref] = 1.0
    ref_patches = _sample_patches(norm[ref], seeds, half)
    lam_min = _min_gradient_energy(norm[ref], seeds, half)
    sig = np.full((F, n), np.nan)
    sig[ref] = 0.0
    gap = np.zeros((F, n), int)
    side = np.zeros((F, n), int)

    last_frame = np.full(n, ref)          # frame index of the last valid step
    last_pos = seeds.copy()               # position there

    icgn_refine = None
    lk_check = method == "lk" and lk_check_px is not None
    if method == "subset" or lk_check:
        from .subset import icgn_refine, prefilter_image   # lazy: only IC-GN users need it
        hw = int(subset_half_window if subset_half_window is not None else half)
        if target_sigma_px is not None:
            from .adaptive import _ladder, adaptive_icgn
            ladder = _ladder(hw, max(hw, int(max_half_window)))
        ref64 = norm[ref].astype(np.float64)
        sm = float((0.0 if target_sigma_px is None else 0.8) if smooth_sigma_px is None
                   else smooth_sigma_px)
        ref_coef = prefilter_image(ref64, sm)
        grad_last = np.zeros((n, 6))      # affine warp of each track's last valid step
    init = None

    def moved(p, src, dst):               # frame src pixels -> frame dst pixels (registration)
        return p if reg is None else reg.between(src, dst)(p)

    order = range(F - 2, -1, -1)
    if progress:
        from tqdm.auto import tqdm
        order = tqdm(order, total=F - 1, desc=f"tracking backwards ({method})", unit="frame")
    warned_blank = []
    for k in order:
        if blank[k]:
            warned_blank.append(k)
            continue                      # nothing can be matched; tracks stay suspended
        # 1. chained LK from each track's source frame
        chain = np.full((n, 2), np.nan)
        chain_ok = np.zeros(n, bool)
        chain_fb = np.full(n, np.nan)
        pred = last_pos.copy()            # last valid positions carried into frame k
        if icgn_refine is not None:
            init = grad_last.copy()       # and their subset warps
        for src in np.unique(last_frame):
            sel = np.flatnonzero(last_frame == src)
            p_src = last_pos[sel]
            pred[sel] = moved(p_src, src, k)
            p_k, ok = _lk(u8[src], u8[k], p_src, None if reg is None else pred[sel], lk_kw)
            back, okb = _lk(u8[k], u8[src], p_k, p_src, lk_back)
            e = np.linalg.norm(back - p_src, axis=1)
            chain[sel] = p_k
            chain_ok[sel] = ok & okb
            chain_fb[sel] = e
            if reg is not None and icgn_refine is not None:
                init[sel] = reg.carry_warps(grad_last[sel], src, k)
        guess = np.where(np.isfinite(chain), chain, pred)

        if not direct_correction:
            pos, ok, e = chain, chain_ok, chain_fb
        elif method == "lk":
            pos, ok = _lk(u8[ref], u8[k], seeds, guess, lk_kw)
            back, okb = _lk(u8[k], u8[ref], pos, seeds, lk_back)
            ok &= okb
            e = np.linalg.norm(back - seeds, axis=1)
        else:
            cur = norm[k].astype(np.float64)
            cur_coef = prefilter_image(cur, sm)
            if target_sigma_px is None:
                res = icgn_refine(ref64, cur, seeds, guess, half_window=hw, warp="affine",
                                  init_warp=init, ref_prefiltered=ref_coef,
                                  cur_prefiltered=cur_coef, smooth_sigma_px=sm)
                hw_k = np.full(n, hw)
            else:
                a = adaptive_icgn(ref64, cur, seeds, guess, target_sigma_px, ladder,
                                  warp="affine", init_warp=init, ref_prefiltered=ref_coef,
                                  cur_prefiltered=cur_coef, smooth_sigma_px=sm,
                                  curvature_neighbours=curvature_neighbours)
                res, hw_k = a.subset, np.where(a.half_window > 0, a.half_window, hw)
            side[k] = np.where(res.converged, 2 * hw_k + 1, 0)
            pos = np.asarray(res.pts, float).copy()
            ok = np.asarray(res.converged, bool) & _inside(np.nan_to_num(pos, nan=-1.0), shape0)
            pos[~ok] = np.nan
            w = np.asarray(res.warp, float)
            # backward check: the subset at pos in frame k matched back into the reference,
            # starting from the inverse of the forward affine warp
            e = np.full(n, np.nan)
            okp = np.flatnonzero(ok)
            if len(okp):
                A = np.stack([[1 + w[okp, 1], w[okp, 2]], [w[okp, 4], 1 + w[okp, 5]]], axis=0)
                Ainv = np.linalg.inv(np.moveaxis(A, (0, 1), (1, 2)))
                iw = np.zeros((len(okp), 6))
                iw[:, [1, 2, 4, 5]] = (Ainv - np.eye(2)).reshape(-1, 4)
                okb = np.zeros(n, bool)
                for h in np.unique(hw_k[okp]):        # each with its own subset
                    g = hw_k[okp] == h
                    ig = okp[g]
                    rb = icgn_refine(cur, ref64, pos[ig], seeds[ig], half_window=int(h),
                                     warp="affine", init_warp=iw[g], smooth_sigma_px=sm,
                                     ref_prefiltered=cur_coef, cur_prefiltered=ref_coef)
                    e[ig] = np.linalg.norm(np.asarray(rb.pts, float) - seeds[ig], axis=1)
                    okb[ig] = np.asarray(rb.converged, bool)
                ok &= okb
        if method == "subset":
            # the subset's own affine-warped ZNCC and Gauss-Newton sigma
            z = np.where(ok, np.asarray(res.zncc, float), np.nan)
            sx = np.asarray(res.sigma_px, float).reshape(n, 2)
            fin = ok & np.isfinite(sx).all(axis=1)
            sig[k] = np.where(fin, np.where(np.isfinite(sx), sx, 0).max(axis=1), np.inf)
            if target_sigma_px is not None and model_neighbours is not None:
                sig[k] = _with_model_error(seeds, moved(pos, k, ref) - seeds, sig[k], hw_k,
                                           np.asarray(res.residual_ratio, float),
                                           int(model_neighbours))
        else:
            z = _zncc(ref_patches, _sample_patches(
                norm[k], pos, half, None if reg is None else reg.transforms[k].matrix[:2, :2]))
            sig[k] = match_sigma_px(z, lam_min)
        zn[k] = z
        good = ok & np.isfinite(e) & (e <= fb_threshold_px)
        with np.errstate(invalid="ignore"):
            good &= np.linalg.norm(pos - pred, axis=1) <= max_jump
        if min_zncc is not None:
            good &= np.isfinite(z) & (z >= min_zncc)
        if max_sigma_px is not None:
            good &= sig[k] <= max_sigma_px
        if max_residual_ratio is not None and method == "subset":
            # a subset whose residual the noise does not explain fits no affine map (a
            # slip step, changed relief): its σ does not hold
            rr = np.asarray(res.residual_ratio, float)
            good &= np.isfinite(rr) & (rr <= float(max_residual_ratio))
        if max_gap_frames is not None:
            # a track suspended for longer than max_gap_frames has ended: re-acquiring it
            # after a long gap is where look-alike features get matched
            good &= (last_frame - k - 1) <= max_gap_frames
        if lk_check:
            chk = np.flatnonzero(good)
            if len(chk):
                rc = icgn_refine(ref64, norm[k].astype(np.float64), seeds[chk], pos[chk],
                                 half_window=hw, warp="affine", init_warp=init[chk],
                                 ref_prefiltered=ref_coef, smooth_sigma_px=sm)
                d = np.linalg.norm(np.asarray(rc.pts, float) - pos[chk], axis=1)
                agree = np.asarray(rc.converged, bool) & (d <= float(lk_check_px))
                good[chk[~agree]] = False
                grad_last[chk[agree]] = np.asarray(rc.warp, float)[agree]
                # keep the check's position: zero-normalised and affine (with ``register``
                # its warp also carries the frame's rotation and scale), LK is neither
                pos[chk[agree]] = np.asarray(rc.pts, float)[agree]
        if outlier_threshold is not None:
            # on the displacement in the reference geometry (the drift is no outlier)
            good &= ~median_outliers(seeds, moved(pos, k, ref) - seeds, good,
                                     threshold=outlier_threshold, n_neighbours=int(n_neighbours))
        xy[k] = pos
        fb[k] = e
        gap[k] = last_frame - k - 1
        valid[k] = good
        last_frame[good] = k
        last_pos[good] = pos[good]
        if method == "subset":
            grad_last[good] = w[good]

    _check_track_loss(valid, sorted(warned_blank))
    params = dict(win_size=win_size, max_level=max_level, fb_threshold_px=fb_threshold_px,
                  min_zncc=min_zncc, direct_correction=direct_correction,
                  max_sigma_px=max_sigma_px, outlier_threshold=outlier_threshold,
                  n_neighbours=n_neighbours, max_jump_px=max_jump, max_gap_frames=max_gap_frames,
                  register=None if reg is None else reg.model,
                  target_sigma_px=target_sigma_px,
                  max_half_window=max_half_window if target_sigma_px is not None else None,
                  curvature_neighbours=curvature_neighbours if target_sigma_px is not None
                  else None, max_residual_ratio=max_residual_ratio,
                  smooth_sigma_px=smooth_sigma_px,
                  model_neighbours=model_neighbours if target_sigma_px is not None else None)
    return Tracks(xy=xy, fb_error_px=fb, valid=valid, zncc=zn, sigma_px=sig, gap_frames=gap, seed_kind=kinds,
                  subset_px=side if method == "subset" else None,
                  reference_frame=ref, method=method, params=params, registration=reg)


def _with_model_error(seeds, disp, sigma, half_window, residual_ratio, k):
    """Steps' σ with the a posteriori residual factor and the model error of their affine
    subsets from the neighbours' displacement field (see ``track_reverse``'s
    ``model_neighbours``); inf stays inf."""
    from scipy.spatial import cKDTree

    from .match_sigma import match_sigma, parallax_model_error

    out = np.asarray(sigma, float).copy()
    idx = np.flatnonzero(np.isfinite(out) & np.isfinite(disp).all(axis=1))
    if len(idx) < 4:
        return out
    p = seeds[idx]
    d, _ = cKDTree(p).query(p, k=2)
    spacing = float(np.median(d[:, 1]))
    h = np.asarray(half_window, float)[idx]
    m = np.fmax(*[parallax_model_error(p, disp[idx, c], out[idx], h, k=min(k, len(idx)),
                                       spacing_px=spacing) for c in (0, 1)])
    out[idx] = match_sigma(out[idx], residual_ratio[idx], m)
    return out


def _max_sigma(max_sigma_px, target_sigma_px):
    """``track_reverse``'s ``max_sigma_px`` with ``"auto"`` resolved."""
    if isinstance(max_sigma_px, str):
        if max_sigma_px != "auto":
            raise TrackingError(f"max_sigma_px={max_sigma_px!r}: give pixels, 'auto' or None")
        return 0.05 if target_sigma_px is None else 0.1
    return max_sigma_px


def seed_sigma_px(frame, seeds, half_window=20, smooth_sigma_px=0.8):
    """Predicted 1σ of matching each seed's subset against an equally noisy copy, pixels.

    The Gauss–Newton σ of :func:`semlab.subset.icgn_refine` (affine subset of half size
    ``half_window``, ``smooth_sigma_px`` pre-smoothing) with the noise measured in the frame
    (:func:`semlab.noise.image_noise_sigma`, on the contrast-stretched frame as tracking sees
    it): the best any tracking step of that seed can reach (the earlier frames of a test
    have less contrast, not more). A seed whose σ exceeds a step's ``max_sigma_px`` even
    here can never give a valid step.

    Parameters
    ----------
    frame : (H, W) array
        The reference (last) frame.
    seeds : (N, 2) array of (x, y) pixels
    half_window : int
        Subset half size (the largest a sized step may use: ``max_half_window``).

    Returns
    -------
    (N,) array of pixels (the larger of x and y; inf where the subset leaves the frame or
    has no texture).
    """
    from .noise import image_noise_sigma
    from .subset import icgn_refine

    f01 = normalize_frame(_as_2d(frame, "frame"))[0].astype(np.float64)
    p = np.asarray(seeds, float).reshape(-1, 2)
    if not len(p):
        return np.zeros(0)
    r = icgn_refine(f01, f01, p, p, half_window=int(half_window), warp="affine",
                    smooth_sigma_px=float(smooth_sigma_px), noise_sigma=image_noise_sigma(f01))
    sx = np.asarray(r.sigma_px, float).reshape(-1, 2)
    ok = np.asarray(r.converged, bool) & np.isfinite(sx).all(axis=1)
    return np.where(ok, np.where(ok[:, None], sx, 0).max(axis=1), np.inf)
