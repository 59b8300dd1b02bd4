"""Per-pixel fusion of two dense height maps by their predicted 1σ.

The subset map (:func:`semlab.heightmap.dense_parallax`) and the variational map
(:func:`semlab.variational.variational_parallax`) are computed from the same two views, so
their errors are correlated and an inverse-variance average would understate the σ. The
fusion here is the *minimum-σ choice*: at each pixel keep the estimate with the smaller
predicted 1σ (a map's value where only it is measured), and keep that estimate's σ.

Measured on the 8 scenes of ``benchmarks/dense_map.py`` (docs/accuracy.md, "Min-σ fusion of the
two maps"), it does not beat the better of the two maps: the two σ do not rank their errors
(on speckle the variational σ is smaller on most pixels while its error is larger), so it is
not a run option.

At the sparse points of automatic matching the two estimates are combined instead
(:func:`inverse_variance`, stage 9 of :func:`semlab.matching.auto_match`): there the
average beats the subset matches on fifteen of the sixteen accuracy-matrix cells measured
(docs/accuracy.md, "Stage 9: the subset matches averaged with the variational map at
the points"). There the map's σ is scaled where its errors are larger than it says, by
:func:`agreement_scale` (how the two disagree around each point); the weight uses the map's
noise-plus-bias σ and the average's 1σ its posterior σ (:func:`inverse_variance`'s
``weight_sigma_b``), with the subset's model error kept in full (``shared_sigma``: the map
rounds a slip band's wall as the subset does). With a third view, :func:`held_out_error`
(how well the average and the subset match each predict that view, their shared noise
counted) decides whether the map enters at all.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .errors import SemlabError
from .stats import robust_sd

__all__ = ["min_sigma_choice", "fuse_heightmaps", "inverse_variance", "sample_parallax",
           "agreement_scale", "held_out_error"]


def min_sigma_choice(z_a, sigma_a, valid_a, z_b, sigma_b, valid_b):
    """Per-pixel choice of the estimate with the smaller predicted 1σ.

    Parameters
    ----------
    z_a, sigma_a : (h, w) arrays
        First map's heights and 1σ (any unit, the same for both maps).
    valid_a : (h, w) bool array
    z_b, sigma_b, valid_b : (h, w) arrays
        The second map, on the same pixel grid.

    Returns
    -------
    z, sigma : (h, w) float32 arrays
        The chosen heights and their 1σ, NaN where neither map is measured.
    valid : (h, w) bool array
        Measured by at least one map.
    pick_b : (h, w) bool array
        True where the second map was chosen.
    """
    arrs = [np.asarray(a) for a in (z_a, sigma_a, valid_a, z_b, sigma_b, valid_b)]
    if len({a.shape for a in arrs}) != 1:
        raise SemlabError("min_sigma_choice: the two maps must be on the same pixel grid "
                          f"(shapes {[a.shape for a in arrs]}); map them with the same roi")
    z_a, s_a, v_a, z_b, s_b, v_b = arrs
    v_a = v_a.astype(bool) & np.isfinite(z_a) & np.isfinite(s_a)
    v_b = v_b.astype(bool) & np.isfinite(z_b) & np.isfinite(s_b)
    with np.errstate(invalid="ignore"):
        pick_b = v_b & (~v_a | (s_b < s_a))
    valid = v_a | v_b
    z = np.where(pick_b, z_b, z_a)
    s = np.where(pick_b, s_b, s_a)
    z = np.where(valid, z, np.nan).astype(np.float32)
    s = np.where(valid, s, np.nan).astype(np.float32)
    return z, s, valid, pick_b


def fuse_heightmaps(subset, variational):
    """Min-σ fusion of a subset and a variational :class:`~semlab.heightmap.HeightMap`.

    Parameters
    ----------
    subset, variational : semlab.heightmap.HeightMap
        Maps of the same views over the same ``roi`` and height model (both from
        :func:`semlab.heightmap.heightmap_from_stereo` with the same stereo result).

    Returns
    -------
    HeightMap
        Heights and 1σ of the map with the smaller σ at each pixel; ``parallax`` is the
        subset map's, and a note gives the share of pixels taken from each map.
    """
    if tuple(subset.roi) != tuple(variational.roi):
        raise SemlabError(f"fuse_heightmaps: roi {subset.roi} != {variational.roi}; map both "
                          "with the same heightmap_roi")
    z, s, valid, pick_v = min_sigma_choice(subset.z_um, subset.sigma_um, subset.valid,
                                           variational.z_um, variational.sigma_um,
                                           variational.valid)
    n = max(int(valid.sum()), 1)
    note = (f"min-σ fusion (semlab.fusion): {100 * (valid & ~pick_v).sum() / n:.1f} % of the "
            f"measured pixels from the subset map, {100 * pick_v.sum() / n:.1f} % from the "
            "variational map")
    return replace(subset, z_um=z, sigma_um=s, valid=valid,
                   notes=list(subset.notes) + [note])


def inverse_variance(a, sigma_a, b, sigma_b, weight_sigma_b=None, shared_sigma=None):
    """Inverse-variance average of two estimates of the same quantities.

    Parameters
    ----------
    a, b : (N, ...) arrays
        The two estimates (the same unit, e.g. view-1 positions ``(x, y)`` in pixels).
    sigma_a, sigma_b : (N,) arrays
        Their 1σ (the same unit), one per row.
    weight_sigma_b : (N,) array, optional
        ``b``'s 1σ for the weight, when it is not the one its error bar holds to: the weight
        is then ``σ_b'² / (σ_a² + σ_b'²)`` with this ``σ_b'`` and the average's 1σ
        ``sqrt(w² σ_a² + (1 − w)² σ_b²)`` with ``sigma_b`` (stage 9 of
        :func:`semlab.matching.auto_match`: the variational map's noise-plus-bias σ for the
        weight, its posterior σ for the bar). Default ``sigma_b``.
    shared_sigma : (N,) array, optional
        The part of ``sigma_a`` (in quadrature) that ``b``'s error repeats with the same sign,
        so that averaging does not shrink it: the average's 1σ is then
        ``sqrt(w² (σ_a² − σ_s²) + (1 − w)² σ_b² + σ_s²)`` (the weight is unchanged). Stage 9
        gives the subset's model error here: a slip band's wall is rounded by the subset
        and by the map alike (their errors correlate, ``benchmarks/results/stage9_bar.md``),
        and the map's plug-in bias, taken from its own rounded estimate, misses it.

    Returns
    -------
    fused : (N, ...) array
        ``w a + (1 − w) b``, ``w = σ_b² / (σ_a² + σ_b²)``; ``a`` where ``b`` or either σ
        is not finite (or a σ is not positive), ``b`` where only ``b`` is.
    sigma : (N,) array
        ``sqrt(w² σ_a² + (1 − w)² σ_b²)`` (with ``shared_sigma``, as given there): the 1σ of
        the average when the two errors are uncorrelated, which the two estimates from the same pixels are not in general. At the
        points of :func:`semlab.matching.auto_match` (stage 9: ``weight_sigma_b`` the map's
        noise-plus-bias σ, ``sigma_b`` its posterior σ, ``shared_sigma`` the subset's model
        error) it is conservative: 83–99 % of the errors within 1σ, 98–100 % within 2σ on 21
        two-view cells, and 90–99 % within 2σ on their slip-band walls
        (``benchmarks/results/stage9_wall_bars.md``), because the posterior σ holds the
        prior's roughness, about twice the map's error on flat parts. Without
        ``shared_sigma`` the walls were 53–95 % within 2σ.
    weight_b : (N,) array
        ``1 − w`` (0 where ``b`` was not used, 1 where only ``b`` was).
    """
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    sa = np.asarray(sigma_a, float).ravel()
    sb = np.asarray(sigma_b, float).ravel()
    sw = sb if weight_sigma_b is None else np.asarray(weight_sigma_b, float).ravel()
    if a.shape != b.shape or len(sa) != len(a) or len(sb) != len(a) or len(sw) != len(a):
        raise SemlabError(f"inverse_variance: estimates of shapes {a.shape} and {b.shape} with "
                          f"{len(sa)}, {len(sb)} and {len(sw)} σ; give one σ per row of "
                          "equal-shaped estimates")
    sh = None if shared_sigma is None else np.asarray(shared_sigma, float).ravel()
    if sh is not None and len(sh) != len(a):
        raise SemlabError(f"inverse_variance: {len(sh)} shared σ for {len(a)} rows; give one "
                          "per row")
    rows = lambda m: m.reshape(len(m), -1).all(axis=1)  # noqa: E731
    with np.errstate(invalid="ignore"):
        ok_a = rows(np.isfinite(a)) & np.isfinite(sa) & (sa > 0)
        ok_b = (rows(np.isfinite(b)) & np.isfinite(sb) & (sb > 0) & np.isfinite(sw)
                & (sw > 0))
    both = ok_a & ok_b
    # σ outside the rows that use them set to 1, and the ratios in a form that a tiny or a huge
    # σ (a point the map barely constrains) cannot overflow
    sa1 = np.where(ok_a, sa, 1.0)
    sb1 = np.where(ok_b, sb, 1.0)
    sw1 = np.where(ok_b, sw, 1.0)
    with np.errstate(over="ignore", under="ignore"):
        wb = np.where(both, 1.0 / (1.0 + (sw1 / sa1) ** 2), np.where(ok_b, 1.0, 0.0))
        if weight_sigma_b is None:
            # sqrt(w² σa² + (1 − w)² σb²) = σa σb / hypot(σa, σb), the factor in [1/√2, 1]
            s_both = np.minimum(sa1, sb1) * (np.maximum(sa1, sb1) / np.hypot(sa1, sb1))
        else:
            s_both = np.hypot((1.0 - wb) * sa1, wb * sb1)
    w = wb.reshape((-1,) + (1,) * (a.ndim - 1))
    fused = np.where(w > 0, w * np.nan_to_num(b) + (1 - w) * np.where(w < 1, a, 0.0), a)
    if sh is not None:
        sh2 = np.minimum(np.where(np.isfinite(sh), sh, 0.0) ** 2, sa1 ** 2)
        # w² σa² − w² σs² + σs² (w the subset's weight): the shared part kept in full
        s_both = np.sqrt(s_both ** 2 + (1.0 - (1.0 - wb) ** 2) * sh2)
    sigma = np.where(both, s_both, np.where(ok_b & ~ok_a, sb, sa))
    return fused, sigma, wb


#: median of χ² with one degree of freedom: the median of u² for a standard normal u
CHI2_1_MEDIAN = 0.454936423119572


def _usable(a, sa, b, sb):
    """Rows where both estimates are finite and both σ finite and positive."""
    with np.errstate(invalid="ignore"):
        return (np.isfinite(a) & np.isfinite(b) & np.isfinite(sa) & np.isfinite(sb)
                & (sa > 0) & (sb > 0))


#: Neighbours of each point in :func:`agreement_scale`'s local scale: the median of that many
#: χ²₁ values scatters by about 2.3 / √n of its value (n = 100: ~23 % in k², ~11 % in k), and
#: 100 points of an 8-px grid span ~80 px, a fraction of a view but more than a slip band.
AGREEMENT_NEIGHBOURS = 100


def agreement_scale(a, sigma_a, b, sigma_b, xy=None, neighbours=AGREEMENT_NEIGHBOURS):
    """How much larger ``sigma_b`` must be for ``a`` and ``b`` to disagree as their σ say.

    Estimates of the same quantities with independent errors differ by ``d = b − a`` with
    variance ``σ_a² + σ_b²``. The scale is the ``k ≥ 1`` for which the median of
    ``d² / (σ_a² + k² σ_b²)`` is that of χ² with one degree of freedom (0.455): a variance
    component of ``b``'s estimated from the data, with ``σ_a`` taken as calibrated (a robust
    median, so a few wrong estimates do not set it). 1 where the two already agree as
    predicted or better (``σ_b`` is not lowered).

    With positions ``xy`` the scale is local: each row's ``k`` from the ``neighbours`` usable
    rows nearest to it. A robust median over the whole view cannot see an estimate that is
    wrong on less than half of it (stage 9's variational map on a tall curved object: on the
    real pollen_pot1 grain the global scale left the average less consistent pair to pair
    than the subset matches alone, docs/accuracy.md); the local one down-weights it there and
    nowhere else.

    Parameters
    ----------
    a, b : (N,) arrays
        The two estimates (e.g. the x position of the subset match and of the map).
    sigma_a, sigma_b : (N,) arrays
        Their 1σ. Rows with a non-finite or non-positive value are left out.
    xy : (N, 2) array of (x, y), optional
        The rows' positions (e.g. view-0 pixels) for a local scale.
    neighbours : int
        Rows in each local median (with ``xy``); with fewer usable rows, every row gets the
        scale of all of them.

    Returns
    -------
    float, or (N,) array with ``xy``
        ``k`` (1.0 with fewer than 8 usable rows).
    """
    a, sa, b, sb = (np.asarray(v, float).ravel() for v in (a, sigma_a, b, sigma_b))
    ok = _usable(a, sa, b, sb)
    n = len(a)
    if ok.sum() < 8:
        return 1.0 if xy is None else np.ones(n)
    d2, va, vb = (b[ok] - a[ok]) ** 2, sa[ok] ** 2, sb[ok] ** 2
    if xy is None or ok.sum() <= neighbours:
        k = float(_median_scale(d2[None], va[None], vb[None])[0])
        return k if xy is None else np.full(n, k)
    from scipy.spatial import cKDTree

    p = np.asarray(xy, float).reshape(n, 2)
    tree = cKDTree(p[ok])
    k = np.empty(n)
    for s in range(0, n, 4096):          # (rows × neighbours) arrays in chunks
        _, nb = tree.query(p[s:s + 4096], int(neighbours))
        k[s:s + 4096] = _median_scale(d2[nb], va[nb], vb[nb])
    return k


def _median_scale(d2, va, vb):
    """Per row of the (M, K) arrays, the ``k`` in [1, 2²⁰] with the median of
    ``d2 / (va + k² vb)`` at χ²₁'s (1 where it is below already): bisection on log₂ k."""
    excess = lambda lk: (np.median(d2 / (va + (4.0 ** lk)[:, None] * vb), axis=1)  # noqa: E731
                         - CHI2_1_MEDIAN)
    lo, hi = np.zeros(len(d2)), np.full(len(d2), 20.0)
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        up = excess(mid) > 0
        lo, hi = np.where(up, mid, lo), np.where(up, hi, mid)
    return np.where(excess(np.zeros(len(d2))) > 0, 2.0 ** hi, 1.0)


def held_out_error(estimates, c, shared):
    """Each estimate's mean-square error, up to one constant, from how well it predicts
    held-out estimates whose errors partly share its own.

    For an estimate ``f`` of ``t`` and another estimate ``c`` of the same quantity,
    ``E(f − t)² = E(f − c)² − E(c − t)² + 2 Cov(f − t, c − t)``. The middle term is the same
    for every ``f``, so ``E(f − c)² + 2 Cov(f − t, c − t)`` ranks estimates by their
    mean-square error, whatever their σ claim. Without the covariance term (the errors taken
    as independent) an estimate whose error ``c`` shares looks better than it is: stage 9 of
    :func:`semlab.matching.auto_match` predicts a view's position from another view's subset
    match, which shares the reference view's subset, and so its noise, with the subset match
    being judged. Here ``E(f − c)²`` is the robust variance (1.4826 × the median absolute
    deviation, squared) of ``f − c`` after removing its median (a few outliers do not rank the
    estimates), and the covariance is the mean of ``shared``; each held-out column is
    compared on the rows where every estimate, that column and its ``shared`` values are
    finite (columns with fewer than 8 such rows are left out), and the columns' sums are
    added.

    Parameters
    ----------
    estimates : (M, N) array
        ``M`` estimates of the same ``N`` quantities (e.g. a point's x position in one view:
        its subset match, and its average with the variational map), pixels; NaN where not
        available.
    c : (N, L) array
        ``L`` held-out estimates of the same quantities, NaN where not available.
    shared : (M, N, L) array
        ``Cov(f_m − t, c_l − t)`` per row: the error covariance of estimate ``m`` with column
        ``l`` (squared units of the estimates).

    Returns
    -------
    (M,) array
        The ranking errors (squared units); ``inf`` for every estimate when no column has 8
        usable rows.
    """
    f = np.asarray(estimates, float)
    f = f.reshape(len(f), -1)
    m, n = f.shape
    c = np.asarray(c, float).reshape(n, -1)
    cov = np.asarray(shared, float)
    if cov.shape != (m, n, c.shape[1]):
        raise SemlabError(f"held_out_error: {m} estimates of {n} values and {c.shape[1]} "
                          f"held-out columns need shared of shape {(m, n, c.shape[1])}, got "
                          f"{cov.shape}")
    err = np.zeros(m)
    used = 0
    for col in range(c.shape[1]):
        ok = np.isfinite(c[:, col]) & np.all(np.isfinite(f), axis=0) \
            & np.all(np.isfinite(cov[:, :, col]), axis=0)
        if ok.sum() < 8:
            continue
        used += 1
        for i in range(m):
            r = f[i, ok] - c[ok, col]
            err[i] += robust_sd(r) ** 2 + 2 * np.mean(cov[i, ok, col])
    return err if used else np.full(m, np.inf)


def sample_parallax(dense, pts_px, sigma="sigma_px"):
    """A dense parallax map at view-0 points, bilinearly.

    Parameters
    ----------
    dense : semlab.heightmap.DenseParallax
    pts_px : (N, 2) array of view-0 ``(x, y)`` pixels
    sigma : {"sigma_px", "weight_sigma_px"}
        Which of the map's 1σ to sample.

    Returns
    -------
    xy1 : (N, 2) array
        View-1 positions ``(x1, y1)`` in pixels, NaN where any of the four pixels around the
        point is not measured (or the point is outside ``dense.roi``).
    sigma : (N,) array
        1σ of ``x1`` (pixels), NaN where ``xy1`` is.
    """
    if sigma not in ("sigma_px", "weight_sigma_px") or getattr(dense, sigma, None) is None:
        raise SemlabError(f"sample_parallax: the map has no {sigma!r}; give 'sigma_px', or "
                          "'weight_sigma_px' of a variational map made with "
                          "VariationalParams(weight_sigma=True)")
    from scipy import ndimage

    p = np.asarray(pts_px, float).reshape(-1, 2)
    x0, y0 = dense.roi[0], dense.roi[1]
    c = [p[:, 1] - y0, p[:, 0] - x0]
    take = lambda m: ndimage.map_coordinates(np.nan_to_num(np.asarray(m, float)), c,  # noqa: E731
                                             order=1, mode="constant", cval=np.nan)
    ok = ndimage.map_coordinates(np.asarray(dense.valid, float), c, order=1, mode="constant",
                                 cval=0.0) > 0.999
    xy1 = np.where(ok[:, None], np.column_stack([take(dense.x1_px), take(dense.y1_px)]), np.nan)
    return xy1, np.where(ok, take(getattr(dense, sigma)), np.nan)
