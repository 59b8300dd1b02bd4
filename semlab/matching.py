"""Stereo correspondences between SEM views of the same surface.

Two or more end-state views taken at stage tilts (e.g. ±5°) differ by a near-identity
affine map (x scaling ``cos θ1 / cos θ0``, small shifts) plus a local parallax along the
epipolar direction (x for a tilt about the image y axis) proportional to the height
(``u = cx + (x cos θ + z sin θ) / s``). At ±5° and 0.03 µm/px one pixel of parallax is
about 0.17 µm of height, so the 8 nm height target needs ~0.05 px matching accuracy:
sub-pixel subset matching (:mod:`semlab.subset`, ZNCC search then IC-GN with ZNSSD).

- :func:`refine_correspondences` (in :mod:`semlab.refine`) refines hand clicks: the
  reference-view click defines the material point; the clicks in the other views are only
  starting guesses (~0.5 px error).
- :func:`auto_match` finds correspondences automatically: SIFT features, Lowe's ratio test,
  a global affine RANSAC, dense optical flow for the initial guess (parallax of hundreds of
  pixels on tall objects), then a dense grid refined by IC-GN with robust outlier filters
  (texture, neighbours, forward–backward, multi-view rank 2).
- :func:`merge_matches` merges two results (e.g. clicks and automatic matches).

:func:`auto_match` is a chain of named stages, each in its own module: the prior
(:mod:`semlab.match_prior`: features, global affine, dense flow), grid matching
(:func:`semlab.adaptive.adaptive_icgn` or fixed subsets, :mod:`semlab.match_band`), and
the filters (:mod:`semlab.match_filters`); all its parameters are one frozen
:class:`AutoMatchParams`, recorded in the result. Its body calls the private stages in
order on one :class:`_AutoState`: ``_stage_setup`` (checks, grid), per view
``_stage_prior``, ``_stage_texture`` (first view), ``_stage_guess``, ``_stage_grid_match``
(IC-GN, band-aware, epipolar) and ``_stage_record``, then ``_filter_consistency``,
``_filter_roughness``, ``_filter_backward``, ``_filter_multiview`` and ``_stage_result``.

Conventions: images are 2D arrays indexed ``[row, col]``; points are ``(x, y)`` pixels,
x right, y down, origin at the centre of the top-left pixel. ``pts`` arrays are
``(N, V, 2)``: N points seen in V views.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2

from .adaptive import _grid_icgn
from .errors import GeometryError, SemlabError
from .match_result import MatchResult, _check_images, _check_ref_view, merge_matches
from .match_sigma import aposteriori_sigma, curvature_bias, parallax_model_error
from .match_band import _band_orientation, _combine, _oriented_refine
from .match_epipolar import epipolar_refine
from .match_filters import (_backward_distance, _local_outliers, _multiview_residual,
                            _parallax_gradients)
from .match_prior import (_aligned_noise, _apply_affine, _dense_prior, _field_jacobian,  # noqa: F401
                          _highpass,
                          _flow_field, _flow_guess, _norm8, _robust_affine, _subset_std,
                          _to_uint8, fit_affine)
from .noise import image_noise_sigma
from .refine import refine_correspondences
from .registration import match_features
from .stats import robust_sd
from .subset import icgn_refine, prefilter_image, zncc_match

if TYPE_CHECKING:
    from .variational import VariationalParams

__all__ = ["MatchResult", "AutoMatchParams", "refine_correspondences", "auto_match",
           "merge_matches", "fit_affine"]


# --------------------------------------------------------------------------- automatic
def _choose_smoothing(ref_img, img, pts_ref, guess, guess0, init_w, half_window, min_zncc,
                      seed, n_trial=200, sigma_px=1.0):
    """Gaussian pre-smoothing for noisy views: 0 if unsmoothed IC-GN converges with
    ``zncc >= min_zncc`` on at least half of a random sample of ``n_trial`` points, else
    ``sigma_px`` (on noisy SEM images the unsmoothed ZNSSD cost is too rough to converge;
    Pan 2013, Opt. Lasers Eng. 51(10))."""
    n = len(pts_ref)
    rng = np.random.default_rng(seed)
    k = rng.choice(n, min(n, n_trial), replace=False)
    g = np.where(np.isfinite(guess[k]), guess[k], guess0[k])
    r = icgn_refine(ref_img, img, pts_ref[k], g, half_window=half_window, init_warp=init_w[k],
                    max_iter=30, tol_px=1e-3)
    ok = r.converged & (r.zncc >= min_zncc)
    return 0.0 if ok.mean() >= 0.5 else float(sigma_px)


@dataclass(frozen=True)
class AutoMatchParams:
    """Every parameter of :func:`auto_match`, in one recorded object.

    The fields are the keyword arguments of :func:`auto_match` (documented there), with
    their defaults; ``dataclasses.asdict(params)`` is what a results file records.
    Stages: prior (``detector``, ``ratio``, ``max_features``, ``dense_init``,
    ``dense_prior_below``, ``wide_search_px``), grid matching (``spacing_px``,
    ``half_window``, ``search_px``, ``smooth_sigma_px``, ``max_iter``, ``tol_px``,
    ``target_sigma_px``, ``max_half_window``, ``curvature_neighbours``, ``band_aware``, ``band_half_width_px``,
    ``kappa``, ``epipolar``), filters (``min_texture_snr``, ``min_zncc``, ``consistency_px``,
    ``max_roughness_px``, ``backward_px``, ``backward_sigma_p``, ``multiview_px``), estimate
    (``variational_fusion``, ``variational_params``).
    """

    ref_view: int = 0
    spacing_px: float = 8
    detector: str = "sift"
    ratio: float = 0.8
    half_window: int = 10
    min_zncc: float = 0.9
    max_points: int = None
    seed: int = 0
    search_px: int = 3
    smooth_sigma_px: float = None
    consistency_px: float = 0.3
    band_aware: bool = True
    band_half_width_px: int = 3
    kappa: float = 1.0
    max_roughness_px: float = 0.08
    dense_init: bool = True
    wide_search_px: int = 10
    min_texture_snr: float = 1.0
    multiview_px: float = 0.3
    max_iter: int = 60
    tol_px: float = 1e-3
    max_features: int = 5000
    backward_px: float = 0.1
    dense_prior_below: float = 0.5
    target_sigma_px: float = None
    max_half_window: int = 28
    epipolar: bool = True
    backward_sigma_p: float = None
    curvature_neighbours: int = None
    variational_fusion: bool = True
    variational_params: VariationalParams | None = None


def auto_match(images, params=None, *, progress=True, features=None, **overrides):
    """Automatic dense correspondences between SEM views.

    Called as ``auto_match(images, params)`` with an :class:`AutoMatchParams`, or with
    its fields as keywords (``auto_match(images, spacing_px=6)``), or both (the keywords
    override ``params``). The parameters used are in ``result.params``.

    1. Sparse features (SIFT, Lowe 2004 IJCV 60(2); or Shi–Tomasi corners 1994 described by
       SIFT; or both) matched with Lowe's ratio test.
    2. A global 2D affine map per view by RANSAC (``cv2.estimateAffine2D``; Fischler &
       Bolles 1981), threshold 3 px, then a second test on the residual across the parallax
       direction (the affine epipolar constraint, Hartley & Zisserman 2nd ed. section 14.2):
       matches more than 1 px off the principal direction of the inlier residuals are
       dropped and the affine map is re-fitted.
    3. A regular grid (``spacing_px``) in the reference view. Points whose subset has too
       little texture (featureless background: subset standard deviation, noise removed,
       below ``min_texture_snr`` times the image noise) are flagged ``"low texture"`` and
       not matched. The noise is estimated from the difference of the first view pair
       aligned by the flow of step 4 (whatever its spectrum), locally (the 64×64 tile of
       each point: SEM noise depends on the signal, and relief the flow misses inflates a
       whole-view estimate), with the subset contrast taken on the same high-passed image
       (minus a Gaussian of ``2 half_window``: smooth shading is not texture), or without
       ``dense_init`` by Immerkær's white-noise estimator.
    4. Dense initial guess (``dense_init``): the view is mapped into the reference frame by
       the affine, both are contrast-normalised and DIS optical flow (Kroeger et al. 2016,
       coarse to fine) gives each grid point its position and local warp gradient, to about
       a pixel even where the parallax reaches hundreds of pixels and varies strongly. Where
       the forward and backward flows disagree by more than 1 px the ZNCC search radius is
       ``wide_search_px`` instead of ``search_px``. (With ``dense_init=False`` the guess is
       the affine plus the median parallax of the 8 nearest sparse matches: only good for
       small, slowly varying parallax.)
    5. ZNCC search, then IC-GN refinement (:func:`semlab.subset.icgn_refine`) of an affine
       subset started from the flow's warp gradient.
    6. Band-aware refinement (``band_aware``): each point is matched again with a thin
       subset along the local direction of the parallax bands (structure tensor of the
       dense parallax field) and that estimate is kept where the square subset disagrees
       with it (see :func:`refine_correspondences`).
    6b. Epipolar stage (``epipolar``): points the 2D subsets failed on (diverged, not
       converged, ZNCC below ``min_zncc``) are matched along the parallax direction only
       (:func:`semlab.match_epipolar.epipolar_refine`: the cross-parallax position held
       on the global affine map's epipolar line, the shift searched within
       ``±max(search_px, wide_search_px)`` and refined with its gradient). Texture that
       constrains only the parallax direction (machined grooves, scratches across it)
       makes the 2D Hessian nearly singular; the shift stereo needs is still defined. On
       ``pollen_pot1`` the grooved substrate is matched this way.
    7. Outlier filter: convergence, ``zncc >= min_zncc`` in every view, local consistency
       of the parallax and cross-parallax residuals against the 8 nearest grid neighbours
       (median ± max(4 × 1.4826 MAD, ``consistency_px``)), repeated once, a local
       planarity test of the parallax (``max_roughness_px``), and with 3 or more views the
       multi-view test: the x coordinates of a point in all views must fit the rank-2
       affine model of a tilt series (see ``multiview_px``).
    8. Forward–backward test (``backward_px``): the accepted points matched back from each
       view must return to their reference position.
    8b. Curvature correction of views matched with the dense prior (a tall, curved
       object): each point's affine subset averages the quadratic part of the parallax
       over the subset; that centre bias (:func:`semlab.match_sigma.curvature_bias`, from
       local quadrics through the accepted parallax) is subtracted.
    9. Variational estimate (``variational_fusion``): each non-reference view's
       variational parallax map (:func:`semlab.variational.variational_parallax`, seeded by
       the accepted points) is sampled at the accepted points, and each point's position is
       the inverse-variance average of its subset match and that estimate
       (:func:`semlab.fusion.inverse_variance`; its 1σ is the average's). The map is
       weighted by its error for the surface at hand, its noise plus the prior's plug-in
       bias (``DenseParallax.weight_sigma_px``), and the average's 1σ uses its posterior
       σ, which also holds the prior's roughness (about twice the error on flat parts with
       the band prior) and so holds at walls where the plug-in bias does not; both scaled
       by the map's agreement with the subsets around each point (its 100 nearest, so a map
       wrong on part of the view only is down-weighted there). With three or more views
       the average replaces a view's subset matches only if it predicts the other views'
       matches better than they do (:func:`semlab.fusion.held_out_error`, counting the
       reference view's noise, which the prediction shares with the subset match). The
       two average
       the relief differently (the subset over its square, the variational map through a
       per-pixel smoothness prior), so their errors are partly independent. Where the two
       disagree by more than 3σ (the map misses a tall object's parallax) the subset match
       stays; views matched with the dense prior (step 8b) keep their subsets.

    Parameters
    ----------
    images : sequence of V (H, W) arrays
        The views (same shape), V >= 2.
    ref_view : int
        Reference view (grid points are placed in it and kept exactly).
    spacing_px : float
        Grid spacing in the reference view, pixels.
    detector : {"sift", "shi-tomasi", "both"}
        Sparse feature detector.
    ratio : float
        Lowe ratio-test threshold (0 < ratio < 1).
    half_window : int
        Subset half size for IC-GN.
    min_zncc : float
        Minimum ZNCC in every view.
    max_points : int, optional
        Keep at most this many grid points (a random subset drawn with ``seed``).
    seed : int
        Seed of RANSAC and of the ``max_points`` subsampling.
    progress : bool
        Show progress bars.
    features : dict, optional
        ``{j: (src, dst)}``: feature matches ``(M, 2)`` of ``(x, y)`` pixels between the
        reference view and view ``j`` to use instead of detecting them (stage 1); the
        tiles of :func:`semlab.tiled_stereo.tiled_auto_match` share the whole views'.
    search_px : int
        ZNCC search radius around the predicted position.
    smooth_sigma_px : float or None
        Gaussian pre-smoothing for IC-GN (see :func:`semlab.subset.icgn_refine`). None
        (default) chooses it on the first view pair: 0 when unsmoothed IC-GN converges with
        ``zncc >= min_zncc`` on at least half of 200 random textured grid points, else
        1.0 px (noisy real SEM images, where the unsmoothed cost is too rough).
    consistency_px : float or None
        Floor of the local-consistency threshold, pixels. None skips the test. Its
        evidence is weak: on the real-texture (FEI) 192×256 cells of
        ``benchmarks/accuracy_matrix.py`` (seeds 0 / 1 / 2) it keeps 185 / 183 / 170
        points against 174 / 181 / 160 without it (the outliers it removes otherwise spoil
        their neighbours' roughness test), at a height RMSE of 25.9 / 22.5 / 35.5 nm
        against 28.2 / 26.0 / 31.6 nm; on small synthetic scenes it changed nothing.
    band_aware, band_half_width_px, kappa
        Band-aligned thin subsets near parallax edges, as in
        :func:`refine_correspondences`.
    max_roughness_px : float or None
        Points where the parallax field is not locally planar are marked invalid: the RMS
        residual (pixels) of a least-squares plane (a quadric for views matched with the
        dense prior, whose parallax is curved) through the parallax of the point and
        its 11 nearest accepted neighbours (about ±1.5 grid spacings) must not exceed
        ``max(max_roughness_px, 2 × median sigma_px)`` (the second term keeps the test
        above the random matching error of noisy images). Near the sharp flanks of
        extrusions the parallax is not affine within any subset and heights come out biased
        by tens of nm; these points are dropped here (they remain reachable with
        :func:`refine_correspondences`). Where most of the view is rough (its median
        roughness above the threshold: a pollen grain's reticulum), the threshold rises to
        that median plus 4 × 1.4826 MAD, so that only roughness standing out of the
        surface's own is rejected (steep flanks are a minority). None keeps them.
    dense_init : bool
        Initial guesses from dense optical flow (step 4); False uses the sparse prior.
    wide_search_px : int
        ZNCC search radius where the flow is uncertain.
    min_texture_snr : float
        Texture threshold of step 3 (0 matches every point).
    multiview_px : float or None
        With V >= 3 views: points whose rank-2 residual (RMS over views, pixels) exceeds
        ``max(median + 4 × 1.4826 MAD, multiview_px)`` of the accepted points are marked
        invalid. None skips the test.
    max_iter, tol_px
        IC-GN iteration limit and convergence tolerance (pixels).
    backward_px : float or None
        Forward–backward check: each accepted point is matched back from the view to the
        reference (IC-GN started at the reference position with the inverse warp) and
        marked invalid when it does not return to within ``backward_px`` pixels (a second
        IC-GN pass over the accepted points; None skips it; points of the epipolar stage
        are matched back along the epipolar direction). A threshold growing with each
        point's σ (``max(backward_px, 3√2 σ)``) tripled the accepted grain points of
        ``pollen_pot1`` but let worse points in on the accuracy matrix (quick real:fei
        cell: 58 % coverage at 0.99× DeepFlow's RMSE instead of 37 % at 0.80×). It removes points whose match
        depends on the direction, e.g. subsets straddling occlusions or parallax edges.
    backward_sigma_p : float or None
        Judge the forward–backward distance ``d`` against each point's own error bars
        instead of ``backward_px`` alone: a point passes when ``d <= max(backward_px,
        sqrt(q) · sqrt(σ_f² + σ_b²))``, σ_f and σ_b the a posteriori 1σ of its forward and
        backward matches and q the ``backward_sigma_p`` quantile of χ² with 2 degrees of
        freedom (3.03 at 0.99); a point passing with ``d > backward_px`` gets ``d² / 4``
        added to its variance in that view (the two matches bracket it). None (default):
        ``backward_px`` alone. Measured (benchmarks/reference_surface.py
        ``--backward-sigma-p``, benchmarks/accuracy_matrix.py ``--quick``, 2026-12-01): at
        0.99 the accepted grain points of ``pollen_pot1`` rise from 302 to 842 of 5174 and
        the substrate's from 244 to 316 of 2162, pair-to-pair height differences 0.64 /
        0.59 of their predicted σ (0.54 / 0.58 before); on the quick matrix coverage rises
        (speckle 56 → 83 %, polished 54 → 84 %, real:fei 37 → 64 %) with the error bars
        holding (within 1σ / 2σ 69 / 95, 71 / 97, 76 / 96 %) but the RMSE grows (19.9 →
        22.0, 31.4 → 38.8, 26.2 → 38.0 nm; real:fei 1.02× DeepFlow's at its points
        instead of 0.80×): the points it adds are honest but poorer, hence off by default.
    max_features : int
        At most this many sparse features per view (the strongest; they only fix the
        global affine and, without ``dense_init``, the parallax prior).
    dense_prior_below : float
        When fewer than this fraction of the feature matches fit the global affine map
        (tall objects: hundreds of pixels of parallax varying over the view), the optical
        flow starts from a dense map interpolated from the consistent matches
        (:func:`_dense_prior`) instead of the affine. 0 disables it.
    target_sigma_px, max_half_window : float or None, int
        Size each grid point's subset by its information, from ``half_window`` up to
        ``max_half_window`` (see :func:`refine_correspondences`); the forward–backward
        check uses each point's own subset. None (default since 2026-12-04; 0.05 from
        2026-12-03): one fixed ``half_window``. Why: with ``variational_fusion`` the
        variational map is the estimate that pools information over a large support, and
        the subset is the one that resolves the relief; subsets grown for noise carry the
        same smoothing bias as the map, and the average gains less. On the 16 textured
        cells of ``benchmarks/accuracy_matrix.py``, seeds 0 and 1 (2026-12-04), fixed
        subsets with stage 9 against sized ones with stage 9: ratio to DeepFlow at the same
        points ≤ 0.75× on 11 of 32 cell-seeds against 4 (geometric mean 0.80 / 0.85 against
        0.83 / 0.86), better on the real textures (quartz on 7, FEI on 5 of 8 cell-seeds)
        and 0–9 % worse on ``polished``; 60–75 % within 1σ on 24 against 15 and ≥ 93 %
        within 2σ on 31 against 29 (docs/accuracy.md, "Stage 9 and the grid's
        subset size").
    curvature_neighbours : int or None
        With ``target_sigma_px``: size each grid point by its predicted total error, the
        noise σ and the curvature bias estimated from how its match moves with the subset
        size, averaged over this many nearest grid points (1: each alone;
        :func:`semlab.adaptive.adaptive_icgn`); every size of the ladder is matched.
        ``target_sigma_px=0`` then takes each point's smallest predicted total error. The
        point's model error is then the larger of the chosen size's bias and the
        neighbourhood's non-affine parallax at ``half_window`` (stage 7b; at the grown size
        that one counts the same curvature again). None: sized by the noise alone. Opt-in:
        on seven 384×512 accuracy-matrix cells (``benchmarks/accuracy_matrix.py --sets
        "auto total"``, 2026-12-02) it lowers the ratio to DeepFlow against fixed subsets on
        every cell (1.38 → 1.15× on polished/low ±5°, 1.35 → 0.96× on FEI/realistic 0/+8°,
        coverage 32 → 52 % there) but the FEI/realistic error bars miss 2σ (88 / 85 %).
    epipolar : bool
        Run the epipolar stage 6b (the forward–backward check of its points is along the
        epipolar direction too).
    variational_fusion : bool
        Run stage 9. Measured (``benchmarks/variational_points.py``, 2026-12-03/04) on
        sixteen 384×512 cells of the accuracy matrix (speckle, polished, real FEI and quartz
        textures; low and realistic noise; ±5° and 0/+8°), at the same points: height RMSE
        0.68–0.97× OpenCV DeepFlow's where the subset matches alone are 0.76–1.32× (better
        on fifteen) and the variational map alone 0.77–1.11× (better on thirteen), with 66–81 %
        of the errors within 1σ and 91–97 % within 2σ (the isotropic prior,
        ``VariationalParams(**ISOTROPIC)``). With the map's band prior (the default since
        2026-12-06): 0.34–0.66× DeepFlow on all sixteen, 94–99 % within 2σ, 74–87 %
        within 1σ (``benchmarks/results/accuracy_matrix_band_default.md``); with the two-view
        weight by the map's noise-plus-bias σ (since c991361): 0.28–0.62× (seed 0) and
        0.28–0.75× (seed 1) on all sixteen, ≥ 95 % within 2σ, 78–97 % within 1σ (the bars
        conservative: ``benchmarks/results/accuracy_matrix_stage9_local.md``); with the
        subset's model error kept in full in the average's bar (since 727a2a9), 98–100 %
        within 2σ and 87–98 % within 1σ on the sixteen, 90–99 % within 2σ on their slip-band
        walls, which were 53–95 % (``benchmarks/results/stage9_wall_bars.md``). It costs one
        variational map per view pair: ``auto_match`` took 3–5× as long with the isotropic
        prior (single thread, 2026-12-04: the 384×512 demo pair 2.2 → 8.3 s; a 2048×1536 pair's
        ``run_stereo`` 34 → 182 s), and the band prior makes the map ~2.5× slower again (the
        demo pair's map 6–8 → 16–19 s, 2026-12-06, after 747e202). The map's σ is
        scaled (k ≥ 1) by its agreement with the subset matches around each point (its 100
        nearest, :func:`semlab.fusion.agreement_scale` with ``xy``; 1 at 88–98 % of the
        points of the matrix cells, and on the real ``pollen_pot1`` pairs the grain's
        pair-to-pair residual 0.206 → 0.192 px against one scale for the view). With three
        or more views the held-out views decide whether a view's average is kept
        (:func:`semlab.fusion.held_out_error`; since 2026-12-07, before a held-out scale
        that, uncorrected for what the prediction shares with the subset match, favoured
        the subsets and cost 0.6–5.6 nm on the three-view cells:
        ``benchmarks/results/three_view_pair.md``, docs/accuracy.md "Stage 9 with three or
        more views: a held-out decision"). False: the subset matches
        alone.
    variational_params : semlab.variational.VariationalParams, optional
        Parameters of stage 9's maps (default ``VariationalParams()``); recorded with the
        others (``asdict`` gives its fields).

    Returns
    -------
    MatchResult
        All grid points, ``kind = "auto"``, with ``valid`` and ``reason``; use
        ``result.only_valid()`` to keep the accepted ones.

    Raises
    ------
    ImageError
        On bad images.
    GeometryError
        If no global affine map is found or the grid is empty.
    """
    params = _auto_params(params, overrides)
    st = _stage_setup(images, params)
    for j in range(st.v):
        if j == st.ref:
            continue
        view = _stage_prior(st, j, features)
        st.affine[j] = view.M
        if st.work is None:
            _stage_texture(st, view)
        if len(st.work) == 0:       # every point flagged "low texture"
            break
        _stage_guess(st, view)
        _stage_grid_match(st, view, progress)
        _stage_record(st, view)
    _filter_consistency(st)
    _filter_roughness(st)
    _filter_backward(st)
    _stage_curvature(st)
    _filter_multiview(st)
    _stage_variational(st)
    return _stage_result(st, progress)


@dataclass
class _AutoState:
    """What the stages of :func:`auto_match` share: the inputs, the grid and the arrays of
    the result being filled in (``(n, v, ...)``: n grid points, v views)."""

    params: AutoMatchParams
    ims: list
    v: int
    ref: int
    grid: np.ndarray            # (n, 2) reference-view (x, y) pixels
    gidx: np.ndarray            # (n,) index of each point in the full grid
    out: np.ndarray             # (n, v, 2) matched positions
    zn: np.ndarray              # (n, v) ZNCC
    sig_x: np.ndarray           # (n, v) noise σ of the match
    sig_ap: np.ndarray          # sig_x with the a posteriori variance factor
    vv: np.ndarray              # (n, v) bool: the view's match passed its tests so far
    reason: np.ndarray
    side: np.ndarray            # (n,) subset side, pixels
    epi: np.ndarray             # (n, v) matched along the epipolar direction only
    noise0: float
    eps: float
    sub_std: np.ndarray
    ref8: np.ndarray
    smooth_sigma_px: float = None
    ref_coef: np.ndarray = None
    work: np.ndarray = None     # indices of the textured grid points
    gw: np.ndarray = None       # their positions
    resid: dict = field(default_factory=dict)      # view -> (parallax, cross-parallax)
    e_dir: dict = field(default_factory=dict)      # view -> unit parallax direction
    curved: set = field(default_factory=set)       # views matched with the dense prior
    affine: dict = field(default_factory=dict)     # view -> its global affine map (2, 3)
    ref_cache: dict = field(default_factory=dict)
    fwd_state: dict = field(default_factory=dict)  # view -> state of the backward check
    model_x: np.ndarray = None  # (n, v) model error
    bias: np.ndarray = None     # (n, v) curvature bias of the sized subsets, pixels (NaN:
    #                             not measured)
    fused_sig: np.ndarray = None  # (n, v) 1σ of stage 9's averages (NaN: not averaged)

    @property
    def n(self):
        return len(self.grid)

    @property
    def valid(self):
        """(n,) bool: valid in every view."""
        return self.vv.all(axis=1)

    def fail(self, rows, j, why):
        """Mark view ``j`` (None: every view) of the points ``rows`` invalid; ``why``: the
        reason (a string, or one per row), kept where a point has none yet (its first)."""
        rows = np.asarray(rows, int).ravel()
        whys = [why] * len(rows) if isinstance(why, str) else list(why)
        for i, w in zip(rows, whys):
            if not self.reason[i]:
                self.reason[i] = w if j is None else f"view {j}: {w}"
        if j is None:
            self.vv[rows] = False
        else:
            self.vv[rows, j] = False

    def alive(self, j):
        """Indices of the points whose match in view ``j`` is still valid."""
        return np.flatnonzero(self.vv[:, j])


def _stage_setup(images, params):
    """Check the parameters and images, place the grid, allocate the result arrays."""
    p = params
    ims = _check_images(images)
    v = len(ims)
    ref = _check_ref_view(p.ref_view, v)
    if p.detector not in ("sift", "shi-tomasi", "both"):
        raise SemlabError(f"detector must be 'sift', 'shi-tomasi' or 'both', got {p.detector!r}")
    if not 0 < p.ratio < 1:
        raise SemlabError(f"ratio must be in (0, 1), got {p.ratio!r}")
    if not p.spacing_px > 0:
        raise SemlabError(f"spacing_px must be > 0, got {p.spacing_px!r}")
    if p.smooth_sigma_px is not None and not p.smooth_sigma_px >= 0:
        raise SemlabError(f"smooth_sigma_px must be None or >= 0, got {p.smooth_sigma_px!r}")
    if p.backward_px is not None and not p.backward_px > 0:
        raise SemlabError(f"backward_px must be None or > 0 pixels, got {p.backward_px!r}")
    if p.backward_sigma_p is not None and not 0 < p.backward_sigma_p < 1:
        raise SemlabError(f"backward_sigma_p must be None or in (0, 1), got "
                          f"{p.backward_sigma_p!r}")
    if not p.min_texture_snr >= 0:
        raise SemlabError(f"min_texture_snr must be >= 0, got {p.min_texture_snr!r}")
    hgt, wid = ims[0].shape
    margin = p.half_window + p.search_px + 3
    xs = np.arange(margin, wid - margin, p.spacing_px, dtype=float)
    ys = np.arange(margin, hgt - margin, p.spacing_px, dtype=float)
    if len(xs) == 0 or len(ys) == 0:
        raise GeometryError(f"images of {wid}×{hgt} px are too small for half_window="
                            f"{p.half_window} and search_px={p.search_px}")
    gx, gy = np.meshgrid(xs, ys)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    gidx = np.arange(len(grid))
    if p.max_points is not None and len(grid) > p.max_points:
        rng = np.random.default_rng(p.seed)
        gidx = np.sort(rng.choice(len(grid), int(p.max_points), replace=False))
        grid = grid[gidx]
    n = len(grid)

    out = np.full((n, v, 2), np.nan)
    out[:, ref] = grid
    zn = np.ones((n, v))
    zn[:, [j for j in range(v) if j != ref]] = -1.0
    noise0 = image_noise_sigma(ims[ref])   # white-noise estimate, regulariser of the flow
    eps = max(noise0, 1e-3 * float(np.ptp(ims[ref])) + 1e-12)
    sm = p.smooth_sigma_px
    return _AutoState(
        params=p, ims=ims, v=v, ref=ref, grid=grid, gidx=gidx, out=out, zn=zn,
        sig_x=np.zeros((n, v)), sig_ap=np.zeros((n, v)), vv=np.ones((n, v), bool),
        reason=np.full(n, "", dtype=object), side=np.zeros(n, int),
        epi=np.zeros((n, v), bool), bias=np.full((n, v), np.nan), noise0=noise0, eps=eps,
        fused_sig=np.full((n, v), np.nan),
        sub_std=_subset_std(ims[ref], p.half_window, grid), ref8=_to_uint8(ims[ref]),
        smooth_sigma_px=sm, ref_coef=None if sm is None else prefilter_image(ims[ref], sm))


def _stage_prior(st, j, features):
    """Stages 1-2 (and the flow of 4) for view ``j``: feature matches, the global affine
    map with its epipolar test, the parallax direction, the dense flow. Returns the view's
    working namespace."""
    p, ims, ref = st.params, st.ims, st.ref
    if features is not None and j in features:       # given (tiles: the whole view's)
        src, dst = (np.asarray(a, float) for a in features[j])
    else:
        src, dst = match_features(st.ref8, _to_uint8(ims[j]), ratio=p.ratio,
                                  detector=p.detector, n_max=p.max_features,
                                  cache=st.ref_cache)
    if len(src) < 6:
        raise GeometryError(f"only {len(src)} feature matches between views {ref} and {j}; "
                            "the views do not overlap or have too little texture")
    M, inl = _robust_affine(src, dst, 3.0, p.seed)
    res = dst[inl] - _apply_affine(M, src[inl])
    # parallax direction = principal direction of the inlier residuals
    rc = res - np.median(res, axis=0)
    _, _, vt = np.linalg.svd(rc, full_matrices=False)
    e = vt[0] * np.sign(vt[0][0] if abs(vt[0][0]) > 1e-12 else 1.0)
    eperp = np.array([-e[1], e[0]])
    keep = np.abs(rc @ eperp) < 1.0
    s_src = src[inl][keep]
    if len(s_src) < 6:
        raise GeometryError(f"too few consistent feature matches between views {ref} and {j}")
    s_dst = dst[inl][keep]
    M = fit_affine(s_src, s_dst)
    s_res = s_dst - _apply_affine(M, s_src)
    L = M[:, :2] - np.eye(2)
    grad = np.array([0, L[0, 0], L[0, 1], 0, L[1, 0], L[1, 1]])
    # no global affine describes the pair when most matches disagree with it (a tall
    # object): then the flow starts from a dense map interpolated from the matches
    prior = M
    if p.dense_init and inl.mean() < p.dense_prior_below:
        try:
            prior = _dense_prior(src, dst, ims[ref].shape, p.half_window)
            st.curved.add(j)
        except GeometryError:
            prior = M
    warped = fwd = bwd = None
    if p.dense_init:
        warped, fwd, bwd = _flow_field(ims[ref], ims[j], prior, p.half_window, st.eps)
    return SimpleNamespace(j=j, M=M, e=e, eperp=eperp, grad=grad, prior=prior, s_src=s_src,
                           s_res=s_res, warped=warped, fwd=fwd, bwd=bwd)


def _stage_texture(st, view):
    """Stage 3: the texture test on the reference view, with the noise seen between the
    views (on the first view pair); sets ``st.work`` and ``st.gw``."""
    p, ims, ref, grid = st.params, st.ims, st.ref, st.grid
    noise = _aligned_noise(ims[ref], view.warped, view.fwd, p.half_window, pts=grid) \
        if p.dense_init else st.noise0
    if p.dense_init:   # contrast of the image the noise is measured on (high-passed)
        st.sub_std = _subset_std(_highpass(ims[ref], p.half_window), p.half_window, grid)
    contrast = np.sqrt(np.maximum(st.sub_std ** 2 - noise ** 2, 0.0))
    textured = contrast >= p.min_texture_snr * noise
    noise_i = np.broadcast_to(noise, contrast.shape)
    low = np.flatnonzero(~textured)
    st.fail(low, None, [f"low texture: subset contrast {contrast[i]:.2f} < "
                        f"min_texture_snr × noise = {p.min_texture_snr * noise_i[i]:.2f} "
                        "(featureless background?)" for i in low])
    st.work = np.flatnonzero(textured)
    st.gw = grid[st.work]


def _stage_guess(st, view):
    """Stages 4-5a: each textured point's initial position and warp (dense flow, or the
    sparse prior), then the ZNCC search (wider where the flow is uncertain)."""
    p, ims, ref, gw, j = st.params, st.ims, st.ref, st.gw, view.j
    nw = len(gw)
    if p.dense_init:
        guess0, init_w, fb = _flow_guess(view.prior, view.fwd, view.bwd, gw, p.half_window)
        # parallax direction from the dense field where the flow is reliable
        d = guess0 - _apply_affine(view.M, gw)
        rel = fb < 1.0
        if rel.sum() >= 6:
            dc = d[rel] - np.median(d[rel], axis=0)
            _, _, vt = np.linalg.svd(dc, full_matrices=False)
            view.e = vt[0] * np.sign(vt[0][0] if abs(vt[0][0]) > 1e-12 else 1.0)
            view.eperp = np.array([-view.e[1], view.e[0]])
    else:
        # smooth parallax field from the sparse inliers (median of nearest residuals)
        kk = min(8, len(view.s_src))
        _, nb = cKDTree(view.s_src).query(gw, k=kk)
        par = np.median(view.s_res[nb.reshape(nw, kk)] @ view.e, axis=1)
        guess0 = _apply_affine(view.M, gw) + par[:, None] * view.e
        init_w = np.broadcast_to(view.grad, (nw, 6))
        fb = np.zeros(nw)
    guess = np.full((nw, 2), np.nan)
    near = fb <= 1.0
    for sel, rad in ((near, p.search_px), (~near, max(p.search_px, p.wide_search_px))):
        if sel.any():
            guess[sel], _ = zncc_match(ims[ref], ims[j], gw[sel], guess0[sel],
                                       half_window=p.half_window, search_px=rad)
    view.guess0, view.init_w, view.guess = guess0, init_w, guess


def _stage_grid_match(st, view, progress):
    """Stages 5b-6b: pre-smoothing choice, IC-GN of the grid, band-aware thin subsets and
    the epipolar stage for view ``view.j``."""
    p, ims, ref, gw, j = st.params, st.ims, st.ref, st.gw, view.j
    M, e, init_w, guess, guess0 = view.M, view.e, view.init_w, view.guess, view.guess0
    nw = len(gw)
    if st.smooth_sigma_px is None:
        st.smooth_sigma_px = _choose_smoothing(ims[ref], ims[j], gw, guess, guess0, init_w,
                                               p.half_window, p.min_zncc, p.seed)
        st.ref_coef = prefilter_image(ims[ref], st.smooth_sigma_px)
    sm, ref_coef = st.smooth_sigma_px, st.ref_coef
    cur_coef = prefilter_image(ims[j], sm)
    total = p.curvature_neighbours is not None and p.target_sigma_px is not None
    r, hw_j, bias_j = _grid_icgn(
        ims[ref], ims[j], gw, np.where(np.isfinite(guess), guess, guess0), p.half_window,
        "affine", init_w, sm, ref_coef, cur_coef, p.target_sigma_px, p.max_half_window,
        bias="signed", progress=progress, max_iter=p.max_iter, tol_px=p.tol_px,
        **({"curvature_neighbours": p.curvature_neighbours} if total else {}))
    view.bias_j = bias_j if total else None
    st.side[st.work] = np.maximum(st.side[st.work], np.where(r.converged, 2 * hw_j + 1, 0))
    ok_j = r.converged & (r.zncc >= p.min_zncc)
    pts_j, sig_j, rr_j = r.pts, r.sigma_px[:, 0], r.residual_ratio
    if p.band_aware and ok_j.sum() >= 6:
        par = np.where(ok_j, (r.pts - _apply_affine(M, gw)) @ e, np.nan)
        ang, _, _ = _band_orientation(gw, gw, par, 2.0 * p.half_window)
        sel = np.flatnonzero(ok_j)
        warp_sel = np.where(np.isfinite(r.warp[sel]), r.warp[sel], init_w[sel])
        o_pts, o_sig, o_zn, o_rr = _oriented_refine(
            ims[ref], ims[j], gw[sel], r.pts[sel], warp_sel, ang[sel], 2 * p.half_window,
            p.band_half_width_px, sm, ref_coef, cur_coef,
            return_residual_ratio=True)
        c_pts, c_sig, use = _combine(r.pts[sel], sig_j[sel], o_pts, o_sig, o_zn, p.min_zncc,
                                     p.kappa)
        pts_j, sig_j, rr_j = pts_j.copy(), sig_j.copy(), rr_j.copy()
        pts_j[sel], sig_j[sel] = c_pts, c_sig
        rr_j[sel] = np.where(use, o_rr, rr_j[sel])
    zn_j = r.zncc
    epi_j = np.zeros(nw, bool)
    epi_coef = None
    if p.epipolar and not ok_j.all():
        pts_j, sig_j, rr_j, zn_j, ok_j, epi_j, r, epi_coef = _epipolar_stage(
            ims[ref], ims[j], gw, M, e, np.where(np.isfinite(guess), guess, guess0),
            pts_j, sig_j, rr_j, ok_j, r, p.half_window, view.grad, init_w, p.min_zncc,
            sm, ref_coef, cur_coef, p.max_iter, p.tol_px,
            max(p.search_px, p.wide_search_px), p.seed)
        st.epi[st.work, j] = epi_j
    view.r, view.hw_j, view.cur_coef, view.epi_coef = r, hw_j, cur_coef, epi_coef
    view.pts_j, view.sig_j, view.rr_j, view.zn_j, view.ok_j = pts_j, sig_j, rr_j, zn_j, ok_j


def _stage_record(st, view):
    """Write view ``view.j``'s matches into the result arrays; keep its parallax residuals
    for the filters and its state for the backward check."""
    p, work, j, r = st.params, st.work, view.j, view.r
    st.out[work, j] = view.pts_j
    st.zn[work, j] = view.zn_j
    st.sig_x[work, j] = view.sig_j
    st.sig_ap[work, j] = aposteriori_sigma(view.sig_j, view.rr_j)
    # the square subset's curvature bias (total-error sizing); NaN: none measured (fixed
    # or noise-only sizing, or an epipolar match)
    st.bias[work, j] = np.where(st.epi[work, j] | (view.bias_j is None), np.nan,
                                0.0 if view.bias_j is None else view.bias_j)
    bad = np.flatnonzero(~view.ok_j)
    st.fail(work[bad], j, [r.reason[k] if not r.converged[k] else
                           f"zncc {view.zn_j[k]:.2f} < min_zncc {p.min_zncc}" for k in bad])
    rr = st.out[:, j] - _apply_affine(view.M, st.grid)
    st.resid[j] = (rr @ view.e, rr @ view.eperp)
    st.e_dir[j] = view.e
    if p.backward_px is not None:
        warp_full = np.full((st.n, 6), np.nan)
        warp_full[work] = np.where(np.isfinite(r.warp), r.warp, view.init_w)
        hw_full = np.full(st.n, int(p.half_window))
        hw_full[work] = np.where(view.hw_j > 0, view.hw_j, p.half_window)
        st.fwd_state[j] = (view.cur_coef, warp_full, hw_full, view.e, view.epi_coef)


def _filter_consistency(st):
    """Stage 7a: local consistency of parallax and cross-parallax against grid neighbours
    (twice), each view against the neighbours valid in it."""
    p, grid = st.params, st.grid
    for _ in range(2 if p.consistency_px is not None else 0):
        for j, (pa, pe) in st.resid.items():
            idx = st.alive(j)
            if len(idx) < 4:
                continue
            for name, val in (("parallax", pa), ("cross-parallax", pe)):
                out_l = _local_outliers(grid[idx], val[idx], 8, p.consistency_px)
                st.fail(idx[out_l], j, f"{name} inconsistent with its neighbours")


def _filter_roughness(st):
    """Stage 7b: the model error of each point (the non-affine part of the parallax around
    it) and the local planarity test (``max_roughness_px``)."""
    p, grid, side, sig_x = st.params, st.grid, st.side, st.sig_x
    st.model_x = model_x = np.zeros((st.n, st.v))
    for j, (pa, _) in st.resid.items():
        idx = st.alive(j)
        if len(idx) < 12:
            continue
        thr = max(p.max_roughness_px or 0.0, 2.0 * float(np.median(sig_x[idx, j])))
        curved = j in st.curved
        # with the dense prior (a tall object) the parallax is curved on the scale of the
        # neighbourhood: test against local quadrics, which still reject steps
        _, rough = _parallax_gradients(grid[idx], pa[idx], return_residual=True,
                                       quadratic=curved)
        # the non-affine part of the parallax around each point: its model error; with
        # total-error sizing (a measured bias b) at the smallest subset of the ladder, the
        # growth beyond it is in b (the neighbourhood's estimate scaled to the grown
        # subset by the moments of a quadratic parallax counts that curvature again)
        b = st.bias[idx, j]
        h_me = np.where(np.isfinite(b), p.half_window, (side[idx] - 1) // 2)
        model_x[idx, j] = np.fmax(parallax_model_error(
            grid[idx], pa[idx], sig_x[idx, j], h_me, quadratic=curved,
            spacing_px=p.spacing_px), np.nan_to_num(b))
        if p.max_roughness_px is None:
            continue
        # a surface rough all over (a pollen grain's reticulum) is not a steep flank:
        # only roughness that stands out of the view's own distribution is rejected
        med = float(np.median(rough))
        thr_j = thr if med <= thr else \
            max(thr, med + 4 * robust_sd(rough, about=med))
        bad = rough > thr_j
        st.fail(idx[bad], j, [f"parallax not locally planar (plane RMS {rr:.2f} px "
                              f"> {thr_j:.2f} px: steep flank)" for rr in rough[bad]])


def _filter_backward(st):
    """Stage 8: the forward–backward test (``backward_px``), each point with its own subset
    and shape function, against its own error bars: a point passes when the distance ``d``
    it returns from is within ``max(backward_px, sqrt(q) · sqrt(σ_f² + σ_b²))``, σ_f and
    σ_b the forward and backward matches' a posteriori 1σ and q the
    ``backward_sigma_p`` quantile of χ² with 2 degrees of freedom (None: ``backward_px``
    alone). A point that passes
    with ``d > backward_px`` carries the disagreement in its error bar: ``d² / 4`` is
    added to its variance in that view (the two matches bracket it)."""
    p, ims, ref = st.params, st.ims, st.ref
    if p.backward_px is None:
        return
    k = np.sqrt(chi2.ppf(p.backward_sigma_p, 2)) if p.backward_sigma_p else 0.0
    for j, (coef_j, warp_j, hw_full, e_j, epi_coef) in st.fwd_state.items():
        idx = st.alive(j)
        if len(idx) == 0:
            continue
        fb_d = np.full(len(idx), np.nan)
        sig_b = np.full(len(idx), np.nan)
        for h in np.unique(hw_full[idx]):      # the backward match uses the same subset
            for one_d in (False, True):        # ... and the same shape function
                kk = (hw_full[idx] == h) & (st.epi[idx, j] == one_d)
                if not kk.any():
                    continue
                sm, rc, cc = epi_coef if one_d else (st.smooth_sigma_px, st.ref_coef, coef_j)
                fb_d[kk], sig_b[kk] = _backward_distance(
                    ims[j], ims[ref], st.out[idx[kk], j], st.grid[idx[kk]], warp_j[idx[kk]],
                    int(h), sm, cc, rc, p.max_iter, p.tol_px,
                    direction=e_j if one_d else None, return_sigma=True)
        tol = np.full(len(idx), float(p.backward_px))
        if k:                                  # σ may be inf (texture below the noise)
            tol = np.fmax(tol, k * np.hypot(st.sig_ap[idx, j], sig_b))
        bad = ~(fb_d <= tol)
        st.fail(idx[bad], j, ["forward–backward mismatch " + (
            "(backward match failed)" if np.isnan(dd) else
            f"{dd:.2f} px > {tt:.2f} px (backward_px {p.backward_px}, "
            "or the χ² bound of its error bars)") for dd, tt in zip(fb_d[bad], tol[bad])])
        wide = ~bad & (fb_d > p.backward_px)
        st.sig_ap[idx[wide], j] = np.hypot(st.sig_ap[idx[wide], j], fb_d[wide] / 2)


def _stage_curvature(st):
    """Stage 8b: views matched with the dense prior (a tall, curved object) lose the centre
    bias of their affine subsets on the curved parallax
    (:func:`semlab.match_sigma.curvature_bias`, each point's own subset size), measured
    from the accepted points' parallax; the forward–backward test above judged the
    matches as they were."""
    for j in sorted(st.curved):
        idx = st.alive(j)
        if len(idx) < 12:
            continue
        h = np.maximum((st.side[idx] - 1) // 2, 1)
        b = curvature_bias(st.grid[idx], st.resid[j][0][idx], h)
        st.out[idx, j] -= b[:, None] * st.e_dir[j]


def _filter_multiview(st):
    """Stage 7c: with 3 or more views, the rank-2 tilt-series test (``multiview_px``),
    fitted on the points valid in every view; a point valid in 3 or more views but not all
    is tested against that model with its own views (one seen in two cannot be)."""
    p, valid = st.params, st.valid
    if p.multiview_px is None or st.v < 3 or valid.sum() < 8:
        return
    vm = st.vv & st.vv[:, [st.ref]]
    mres, _ = _multiview_residual(st.out, st.ref, valid, seed=p.seed, view_mask=vm)
    r_in = mres[valid]
    thr = max(np.median(r_in) + 4 * robust_sd(r_in), p.multiview_px)
    tested = vm.sum(1) >= 3
    bad = np.flatnonzero(tested & ~(mres <= thr))
    st.fail(bad, None, [f"views inconsistent: x coordinates off the rank-2 tilt-series model "
                        f"by {mres[i]:.2f} px > {thr:.2f} px" for i in bad])


def _stage_variational(st):
    """Stage 9: the points' positions in each view whose match there passed its tests,
    averaged with the variational parallax map of that view pair (seeded by them), by
    inverse variance, the map weighted by its noise-plus-bias σ and the average's 1σ from
    its posterior σ, both scaled by the map's agreement with the subset matches around each
    point (:func:`semlab.fusion.agreement_scale` with ``xy``); with three or more views the
    average is kept only where it predicts the other views' matches better than the subset
    matches alone do (:func:`semlab.fusion.held_out_error`). Their 1σ become the
    average's (``st.fused_sig``), with the subset's model error kept in full: the map rounds a
    slip band's wall as the subset does, so averaging does not shrink that part
    (``benchmarks/results/stage9_wall_bars.md``)."""
    if not st.params.variational_fusion:
        return
    from . import fusion, variational

    sig = np.sqrt(st.sig_ap ** 2 + st.model_x ** 2)
    subsets = st.out.copy()     # the subset matches: the held-out estimates of every view
    for j in range(st.v):
        # views matched with the dense prior (a tall object: hundreds of pixels of curved
        # parallax) keep their subsets: the map, refined around the flow, misses that
        # parallax by pixels where the affine prior's subsets do not (the 3σ test below
        # keeps them then), and a tall object's views are large
        if j == st.ref or j in st.curved:
            continue
        # every point whose match in this view passed its tests (also the points seen in
        # fewer views: MatchResult.seen_in)
        idx = np.flatnonzero(st.vv[:, j] & st.vv[:, st.ref]
                             & np.all(np.isfinite(st.out[:, j]), axis=1))
        if len(idx) < 8:        # the map's epipolar relation needs 8 seeds
            continue
        # the map's plane (the band prior leaves it out): the global affine map's
        # x-parallax, which a tile of tiled_auto_match fits from the whole views' features
        # as the untiled run does, so the two agree (each tile's seeds would give its own)
        M = st.affine[j]
        plane = [float(M[0, 2]), float(M[0, 0] - 1.0), float(M[0, 1])]
        vp = st.params.variational_params or variational.VariationalParams()
        dm = _variational_map(st.ims[st.ref], st.ims[j], st.out[idx][:, [st.ref, j]],
                              replace(vp, weight_sigma=True),
                              calibration={"parallax_plane": plane})
        xy1, s1 = fusion.sample_parallax(dm, st.grid[idx])
        # only estimates of the same position are averaged: where the map is off the
        # subset match by more than 3σ of the two (a tall object's hundreds of pixels of
        # curved parallax, which the map, refined around the flow, misses by pixels:
        # tests/test_matching.py's dome), the subset match stays
        with np.errstate(invalid="ignore"):
            off = np.abs(xy1[:, 0] - st.out[idx, j, 0]) > 3 * np.hypot(sig[idx, j], s1)
        xy1[off] = np.nan
        # The weight: the map's error for the surface at hand, its noise plus the prior's
        # plug-in bias (`s1w`; the posterior σ also holds the prior's roughness, ~2× the
        # flats' error with the band prior, and gave the subsets too much weight). The
        # average's bar from the posterior σ: it also holds where the plug-in bias misses
        # the smoothing of a band's walls. Both scaled (k ≥ 1) where the map disagrees with
        # the subset matches around the point (its 100 nearest: a map wrong on a tall
        # object only is down-weighted there), the subsets' σ taken as calibrated
        s1w = fusion.sample_parallax(dm, st.grid[idx], sigma="weight_sigma_px")[1]
        k = fusion.agreement_scale(st.out[idx, j, 0], sig[idx, j], xy1[:, 0], s1w,
                                   xy=st.grid[idx])
        fused, s_f, wv = fusion.inverse_variance(st.out[idx, j], sig[idx, j], xy1, k * s1,
                                                 weight_sigma_b=k * s1w,
                                                 shared_sigma=st.model_x[idx, j])
        held = _held_out_positions(subsets, st.vv, st.ref, j, idx)
        if held is not None and not _average_predicts_better(
                st.out[idx, j, 0], fused[:, 0], wv, st.sig_ap[idx, j], k * s1w, held):
            continue    # the held-out views' matches say the map makes it worse
        st.out[idx, j] = fused
        used = wv > 0
        st.fused_sig[idx[used], j] = s_f[used]


def _average_predicts_better(a, fused, weight_b, sigma_noise_a, sigma_b, held):
    """Whether stage 9's average ``fused`` of the subset matches ``a`` ((N,) x positions,
    pixels) predicts the held-out views' matches (``held``: ``(predictions, beta)`` of
    :func:`_held_out_positions`) better than ``a`` alone, by
    :func:`semlab.fusion.held_out_error`, which needs each estimate's error covariance with
    the prediction ``c = … + β x_other``. ``c`` comes from another view's subset match made
    with the same reference subset as ``a``, so the reference view's noise enters both: with
    equal noise in the views (half of a subset match's noise variance ``σ_a²``,
    ``sigma_noise_a``, from each image) ``β σ_a² / 2``. The map shares it through the pixels
    it pools (an average over a larger support than the subset's: about half of its own
    noise variance, at most ``σ_a² / 2``): ``β min(σ_b, σ_a)² / 2`` with ``σ_b`` its weight σ
    (``sigma_b``). Without 8 usable rows in any held-out column (both errors ``inf``) the
    average is kept, as with two views.

    Left out: the subset's model error (the relief its window averages), which ``c`` also
    repeats (the relief's parallax in another view is proportional to this view's), so the
    comparison still leans to the subsets where the relief is sharp. Counted (as ``m_a²``) it
    kept the map on a three-view scene with sharp walls (``tests/test_matching.py``'s
    ``Scene`` with ``edge_um=0.1``, noise 0.3), halving the height error there, but on the
    real ``pollen_pot1`` grain it let in a map that broke the pair-to-pair check (86 % within
    2σ; docs/accuracy.md, "Stage 9 with three or more views: a held-out decision").
    """
    from . import fusion

    pred, beta = held
    sa = np.asarray(sigma_noise_a, float)
    sb = np.asarray(sigma_b, float)
    w = np.asarray(weight_b, float)
    # rows without a finite σ get a NaN covariance, which held_out_error leaves out
    va = np.where(np.isfinite(sa), sa, np.nan) ** 2
    vb = np.fmin(np.where(np.isfinite(sb), sb, np.nan), sa) ** 2
    vb = np.where(w > 0, vb, 0.0)
    half = 0.5 * np.asarray(beta, float)[None, :]
    shared = np.stack([va[:, None] * half, ((1 - w) * va + w * vb)[:, None] * half])
    err = fusion.held_out_error(np.stack([a, fused]), pred, shared)
    return bool(err[1] <= err[0])


def _held_out_positions(pts, view_valid, ref, j, idx):
    """View ``j``'s x positions of the points ``idx`` predicted from each other view's matches.

    Under affine cameras tilted about an axis near the image y axis, a point's x in view
    ``j`` is a linear function of its ``(x, y)`` in the reference view and its x in any
    other view (:func:`semlab.match_filters._multiview_residual`'s rank-2 model):
    fitted per other view by least squares on the points valid in the three views (three
    rounds, dropping residuals beyond 4 × 1.4826 MAD), evaluated with that view's matches.

    Returns
    -------
    (predictions, beta) or None
        ``predictions``: (len(idx), L) array, one column per other view with at least 8 such
        points, NaN where the point is not valid there; ``beta``: (L,) array, each column's
        coefficient of the other view's x (the factor its match's error enters with). None
        without such a view.
    """
    cols, betas = [], []
    for other in range(pts.shape[1]):
        if other in (ref, j):
            continue
        X = np.column_stack([pts[idx, ref, 0], pts[idx, ref, 1], pts[idx, other, 0],
                             np.ones(len(idx))])
        y = pts[idx, j, 0]
        use = view_valid[idx, other] & np.all(np.isfinite(X), axis=1) & np.isfinite(y)
        if use.sum() < 8:
            continue
        fit = use.copy()
        for _ in range(3):
            beta = np.linalg.lstsq(X[fit], y[fit], rcond=None)[0]
            r = y - X @ beta
            mad = robust_sd(r[use])
            fit = use & (np.abs(r - np.median(r[use])) <= 4 * mad) if mad > 0 else use
        cols.append(np.where(use, X @ beta, np.nan))
        betas.append(float(beta[2]))
    return (np.column_stack(cols), np.array(betas)) if cols else None


def _variational_map(view0, view1, seeds, params, tiling=None, calibration=None):
    """Stage 9's variational parallax map of a view pair, seeded by ``seeds`` ((N, 2, 2)
    matches). Views of more than ``tiling.map_min_pixels`` pixels (default
    :data:`~semlab.tiled_stereo.DEFAULT_TILING`: the size above which a height map is tiled)
    are mapped in windows of ``tiling.variational_tile_px`` with one calibration, one after
    another in this thread (:func:`semlab.tiled_stereo.tiled_parallax`,
    ``scheduler="inline"``): the solve's memory grows with its area (a 1216² window peaks at
    1.1 GB, in 512 px windows at 0.35 GB, the points' parallax within 0.002 px RMS of the
    whole map, ~1/8 of its σ), so a tiled run's memory grows by ~0.35 GB, not ~1.1 GB, per
    tile in flight (per core). The 3072×4096 ``semlab run`` (two matching tiles in flight,
    ``benchmarks/memory_large.py --run``, 2026-12-05): the ``semlab`` process peaked at
    1.52 GB with a 850 s stereo step; with the tiles' maps whole, 2.96 GB and 656 s.
    (Windows were twice as slow under :func:`semlab.parallel.limit_heap_growth`'s former
    64 kB mmap threshold: 1702 s.)"""
    from .parallel import INLINE
    from .tiled_stereo import DEFAULT_TILING, tiled_parallax
    from .variational import VariationalParams, variational_parallax

    t = tiling or DEFAULT_TILING
    prm = params or VariationalParams()
    if not t.tiles_map(np.shape(view0)):
        return variational_parallax(view0, view1, seeds=seeds, params=prm,
                                    calibration=calibration)
    return tiled_parallax(view0, view1, seeds=seeds, params=prm, method=variational_parallax,
                          tiling=t, scheduler=INLINE, progress=False, calibration=calibration)


def _stage_result(st, progress):
    """Error bars (noise σ with the a posteriori factor, plus the model error) and the
    :class:`MatchResult`."""
    others = [j for j in range(st.v) if j != st.ref]
    valid, n = st.valid, st.n
    vv = st.vv & st.vv[:, [st.ref]] & (st.vv[:, others].any(axis=1))[:, None]
    view_sig = np.sqrt(st.sig_ap ** 2 + st.model_x ** 2)
    view_sig = np.where(np.isfinite(st.fused_sig), st.fused_sig, view_sig)
    view_sig[:, st.ref] = 0.0
    view_sig[~vv] = np.nan
    seen = vv[:, others].any(axis=1)
    sigma = np.full(n, np.nan)
    sigma[seen] = np.sqrt(np.nanmean(view_sig[seen][:, others] ** 2, axis=1))
    if progress:
        from tqdm.auto import tqdm
        tqdm.write(f"auto_match: {valid.sum()} of {n} grid points accepted")
    return MatchResult(pts=st.out, zncc=st.zn, valid=valid, sigma_px=sigma,
                       reason=st.reason.astype(str), ref_view=st.ref, kind=np.full(n, "auto"),
                       source_index=st.gidx, subset_px=st.side, params=st.params,
                       view_valid=vv, view_sigma_px=view_sig)


def _epipolar_stage(ref_img, img, gw, M, e, start, pts_j, sig_j, rr_j, ok_j, r, half_window,
                    grad, init_w, min_zncc, smooth_sigma_px, ref_coef, cur_coef, max_iter, tol_px,
                    search_px, seed, n_trial=200, smooth_px=1.0):
    """Grid points the 2D subsets failed on, matched along the epipolar direction only.

    Where a subset's texture constrains only the parallax direction ``e`` (grooves or
    scratches across it), the 2D IC-GN diverges along the texture; the affine epipolar
    constraint fixes the cross-parallax position and gradient at the global affine map
    ``M``'s (the parallax gradient starts at the flow's, ``init_w``), and
    :func:`semlab.match_epipolar.epipolar_refine` finds the shift along ``e`` (searched
    within ``±search_px``) and its gradient. Pre-smoothing as :func:`_choose_smoothing`
    decides for 2D subsets: unsmoothed unless fewer than half of ``n_trial`` random
    points then reach ``min_zncc`` (JPEG-compressed views), else ``smooth_px``. Returns the
    updated ``(pts, sigma, residual_ratio, zncc, ok, one_d, result)`` of the view, ``one_d`` marking the
    points taken from this stage (their warp replaces ``r.warp``), and the stage's
    ``(smooth_sigma_px, ref_coef, cur_coef)`` for the backward check.
    """
    fail = np.flatnonzero(~ok_j & np.all(np.isfinite(start), 1))
    zn_j = r.zncc.copy()
    one_d = np.zeros(len(gw), bool)
    coefs = (smooth_sigma_px, ref_coef, cur_coef)
    if len(fail) == 0:
        return pts_j, sig_j, rr_j, zn_j, ok_j, one_d, r, coefs
    base = _apply_affine(M, gw[fail])
    guess = base + ((start[fail] - base) @ e)[:, None] * e
    gm = np.array([[grad[1], grad[2]], [grad[4], grad[5]]])
    iw = np.broadcast_to(init_w, (len(gw), 6))[fail]
    gf = np.stack([np.stack([iw[:, 1], iw[:, 2]], 1), np.stack([iw[:, 4], iw[:, 5]], 1)], 1)
    G = gm + e[:, None] * np.einsum("i,nij->nj", e, gf - gm)[:, None, :]
    z = np.zeros(len(fail))
    held = np.column_stack([z, G[:, 0, 0], G[:, 0, 1], z, G[:, 1, 0], G[:, 1, 1]])

    # the noise the 2D subsets of the view measured (icgn_refine's default), not
    # Immerkær's upper bound again
    noise = r.noise_sigma if r.noise_sigma is not None and np.all(np.isfinite(r.noise_sigma)) \
        else None

    def run(k, sm, rc, cc):
        return epipolar_refine(ref_img, img, gw[fail[k]], guess[k], e, half_window, held[k],
                               search_px=search_px, max_iter=max_iter, tol_px=tol_px,
                               smooth_sigma_px=sm, ref_prefiltered=rc, cur_prefiltered=cc,
                               noise_sigma=noise)

    if not smooth_sigma_px:
        k = np.random.default_rng(seed).choice(len(fail), min(len(fail), n_trial), False)
        t = run(k, 0.0, ref_coef, cur_coef)
        if np.mean(t.converged & (t.zncc >= min_zncc)) < 0.5:
            coefs = (smooth_px, prefilter_image(ref_img, smooth_px),
                     prefilter_image(img, smooth_px))
    q = run(slice(None), *coefs)
    use = q.converged & (q.zncc >= min_zncc) & np.isfinite(q.sigma_px[:, 0])
    k = fail[use]
    pts_j, sig_j, rr_j, ok_j = pts_j.copy(), sig_j.copy(), rr_j.copy(), ok_j.copy()
    pts_j[k], sig_j[k], zn_j[k], ok_j[k], one_d[k] = q.pts[use], q.sigma_px[use, 0], \
        q.zncc[use], True, True
    rr_j[k] = q.residual_ratio[use]
    # an unaccepted 1-D match with a better ZNCC explains the failure better
    better = fail[~use & q.converged & (q.zncc > zn_j[fail])]
    zn_j[better] = q.zncc[np.searchsorted(fail, better)]
    warp = r.warp.copy()
    warp[k] = q.warp[use]
    conv = r.converged.copy()
    conv[k] = True
    conv[better] = True
    return (pts_j, sig_j, rr_j, zn_j, ok_j, one_d, replace(r, warp=warp, converged=conv),
            coefs)


def _auto_params(params, overrides):
    p = AutoMatchParams() if params is None else params
    if not isinstance(p, AutoMatchParams):
        raise SemlabError(f"params must be an AutoMatchParams, got {type(p).__name__}")
    unknown = set(overrides) - {f.name for f in fields(AutoMatchParams)}
    if unknown:
        raise SemlabError(f"auto_match has no parameter {', '.join(sorted(unknown))}; see "
                          "semlab.matching.AutoMatchParams for the parameters")
    p = replace(p, **overrides) if overrides else p
    if p.variational_params is not None:
        from .variational import VariationalParams

        if not isinstance(p.variational_params, VariationalParams):
            raise SemlabError("variational_params must be a semlab.variational."
                              f"VariationalParams, got {type(p.variational_params).__name__}")
    return p


# --------------------------------------------------------------------------- merge