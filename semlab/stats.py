"""Small statistics for distributions of heights, displacements and strains.

- :func:`bimodality`: 1- vs 2-component Gaussian mixtures compared by the Bayesian
  information criterion (Schwarz, Ann. Stat. 6 (1978) 461; ``BIC = -2 ln L + k ln n``,
  lower is better; a difference above ~10 is "very strong" evidence, Kass & Raftery,
  JASA 90 (1995) 773).
- :func:`compare_distributions`: two-sample Kolmogorov-Smirnov test.
- :func:`correlation`: Pearson r and Spearman rho with percentile bootstrap confidence
  intervals (Efron & Tibshirani, *An Introduction to the Bootstrap*, 1993, ch. 13).
- :func:`linear_trend`: least-squares slope with its Student-t confidence interval and the
  p-value of "no slope" (``scipy.stats.linregress``).
- :func:`robust_sd`: ``1.4826 ×`` the median absolute deviation, the robust standard
  deviation every outlier threshold and error-bar check of semlab uses.

NaNs are dropped and counted; fewer than the required number of points raises
:class:`semlab.errors.SemlabError`.
"""

from __future__ import annotations

import numpy as np

from .errors import SemlabError

__all__ = ["bimodality", "compare_distributions", "correlation", "linear_trend", "robust_sd"]

#: Rousseeuw's consistency factor, ``1 / Φ⁻¹(3/4)`` to four digits: the median absolute
#: deviation of a normal sample times this is its standard deviation.
MAD_TO_SIGMA = 1.4826


def robust_sd(values, about=None):
    """Robust standard deviation: ``1.4826 ×`` the median absolute deviation.

    Parameters
    ----------
    values : array_like
        Finite values (any shape; NaNs are not dropped: pass ``values[np.isfinite(values)]``).
    about : float, optional
        The centre of the deviations; default the median of ``values`` (0 for residuals
        already centred, e.g. about a fitted model).

    Returns
    -------
    float
        The standard deviation of a normal sample, unaffected by a minority of outliers.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.random.default_rng(0).normal(0, 2, 100_000)
    >>> round(robust_sd(np.r_[x, [1e6] * 1000]), 1)   # 1 % gross outliers change it little
    2.0
    """
    v = np.asarray(values, float)
    c = np.median(v) if about is None else about
    return float(MAD_TO_SIGMA * np.median(np.abs(v - c)))


def _finite_1d(values, name, min_n):
    v = np.asarray(values, dtype=float).ravel()
    ok = np.isfinite(v)
    v = v[ok]
    if len(v) < min_n:
        raise SemlabError(f"{name} has {len(v)} finite values, at least {min_n} are needed")
    return v, int((~ok).sum())


def _paired_1d(x, y, ci):
    """``x`` and ``y`` as flat float arrays of one length, after checking ``0 < ci < 1``."""
    xa = np.asarray(x, float).ravel()
    ya = np.asarray(y, float).ravel()
    if xa.shape != ya.shape:
        raise SemlabError(f"x and y must have the same length, got {xa.size} and {ya.size}")
    if not 0 < ci < 1:
        raise SemlabError(f"ci must be in (0, 1), got {ci!r}")
    return xa, ya


def bimodality(values, seed=0, min_bic_delta=10.0):
    """Is a sample better described by two Gaussian modes than by one?

    Parameters
    ----------
    values : (N,) array
        Sample (NaNs dropped); N >= 10.
    seed : int
        Random state of ``sklearn.mixture.GaussianMixture`` (k-means initialisation).
    min_bic_delta : float
        ``prefers_two`` when ``bic_1 - bic_2 > min_bic_delta``.

    Returns
    -------
    dict with ``n``, ``n_dropped``, ``bic_1``, ``bic_2``, ``delta_bic`` (= bic_1 - bic_2,
    positive favours two modes), ``prefers_two`` (bool), and for the 2-component fit
    ``means``, ``sigmas``, ``weights`` ((2,) arrays sorted by mean), plus ``mean_1`` and
    ``sigma_1`` of the single Gaussian.
    """
    from sklearn.mixture import GaussianMixture

    v, dropped = _finite_1d(values, "values", 10)
    if np.ptp(v) == 0:
        raise SemlabError("all values are equal: a mixture cannot be fitted")
    x = v.reshape(-1, 1)
    g1 = GaussianMixture(1, random_state=seed).fit(x)
    g2 = GaussianMixture(2, random_state=seed, n_init=3).fit(x)
    b1, b2 = float(g1.bic(x)), float(g2.bic(x))
    order = np.argsort(g2.means_.ravel())
    return {
        "n": len(v),
        "n_dropped": dropped,
        "bic_1": b1,
        "bic_2": b2,
        "delta_bic": b1 - b2,
        "prefers_two": bool(b1 - b2 > min_bic_delta),
        "means": g2.means_.ravel()[order],
        "sigmas": np.sqrt(g2.covariances_.ravel()[order]),
        "weights": g2.weights_.ravel()[order],
        "mean_1": float(g1.means_.ravel()[0]),
        "sigma_1": float(np.sqrt(g1.covariances_.ravel()[0])),
    }


def compare_distributions(a, b):
    """Two-sample Kolmogorov-Smirnov test (``scipy.stats.ks_2samp``) and medians.

    Returns
    -------
    dict with ``ks_statistic``, ``p_value``, ``median_a``, ``median_b``, ``n_a``, ``n_b``,
    ``n_dropped_a``, ``n_dropped_b``.
    """
    from scipy.stats import ks_2samp

    va, da = _finite_1d(a, "a", 2)
    vb, db = _finite_1d(b, "b", 2)
    res = ks_2samp(va, vb)
    return {"ks_statistic": float(res.statistic), "p_value": float(res.pvalue),
            "median_a": float(np.median(va)), "median_b": float(np.median(vb)),
            "n_a": len(va), "n_b": len(vb), "n_dropped_a": da, "n_dropped_b": db}


def correlation(x, y, n_boot=1000, seed=0, ci=0.95):
    """Pearson and Spearman correlation with bootstrap confidence intervals.

    Pairs where either value is NaN are dropped (counted in ``n_dropped``). The p-values
    are those of ``scipy.stats.pearsonr`` / ``spearmanr`` (null hypothesis: no
    correlation); the intervals are percentile bootstrap intervals over resampled pairs.

    Parameters
    ----------
    x, y : (N,) arrays
    n_boot : int
        Bootstrap resamples (>= 100).
    seed : int
    ci : float
        Confidence level in (0, 1).

    Returns
    -------
    dict with ``n``, ``n_dropped``, ``pearson_r``, ``pearson_p``, ``pearson_ci`` (2,),
    ``spearman_rho``, ``spearman_p``, ``spearman_ci`` (2,).

    Raises
    ------
    SemlabError
        Fewer than 3 complete pairs, different lengths, a constant variable, bad ci/n_boot.
    """
    from scipy.stats import pearsonr, rankdata, spearmanr

    xa, ya = _paired_1d(x, y, ci)
    if int(n_boot) < 100:
        raise SemlabError(f"n_boot must be >= 100, got {n_boot!r}")
    ok = np.isfinite(xa) & np.isfinite(ya)
    xa, ya = xa[ok], ya[ok]
    n = len(xa)
    if n < 3:
        raise SemlabError(f"correlation needs at least 3 complete (x, y) pairs, got {n} "
                          f"({int((~ok).sum())} dropped for NaN)")
    if np.ptp(xa) == 0 or np.ptp(ya) == 0:
        raise SemlabError("x or y is constant: the correlation is undefined")
    pr = pearsonr(xa, ya)
    sr = spearmanr(xa, ya)

    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(int(n_boot), n))
    xb, yb = xa[idx], ya[idx]

    def _rows_corr(a, b):
        a = a - a.mean(axis=1, keepdims=True)
        b = b - b.mean(axis=1, keepdims=True)
        den = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
        with np.errstate(invalid="ignore", divide="ignore"):
            return (a * b).sum(axis=1) / den

    rb = _rows_corr(xb, yb)
    sb = _rows_corr(rankdata(xb, axis=1), rankdata(yb, axis=1))
    q = [50 * (1 - ci), 50 * (1 + ci)]
    return {"n": n, "n_dropped": int((~ok).sum()),
            "pearson_r": float(pr.statistic), "pearson_p": float(pr.pvalue),
            "pearson_ci": np.nanpercentile(rb, q),
            "spearman_rho": float(sr.statistic), "spearman_p": float(sr.pvalue),
            "spearman_ci": np.nanpercentile(sb, q)}


def linear_trend(x, y, ci=0.95):
    """Least-squares line ``y = slope x + intercept`` with the slope's confidence interval.

    The interval is ``slope ± t_{(1+ci)/2, n-2} · stderr`` (ordinary least squares,
    independent normal residuals); ``p`` is the two-sided p-value of a zero slope, from
    ``scipy.stats.linregress``. NaN pairs are dropped (counted in ``n_dropped``).

    Parameters
    ----------
    x, y : (N,) arrays
    ci : float
        Confidence level in (0, 1).

    Returns
    -------
    dict with ``slope``, ``intercept``, ``slope_ci`` (2,), ``p``, ``r``, ``n``, ``n_dropped``.

    Raises
    ------
    SemlabError
        Fewer than 3 complete pairs, different lengths, constant x, bad ci.

    Examples
    --------
    >>> t = linear_trend([0, 1, 2, 3, 4], [1.0, 3.1, 4.9, 7.2, 8.9])
    >>> round(t["slope"], 2), bool(t["slope_ci"][0] < 2 < t["slope_ci"][1])
    (1.99, True)
    """
    from scipy.stats import linregress
    from scipy.stats import t as student_t

    xa, ya = _paired_1d(x, y, ci)
    ok = np.isfinite(xa) & np.isfinite(ya)
    xa, ya = xa[ok], ya[ok]
    n = len(xa)
    if n < 3:
        raise SemlabError(f"a trend needs at least 3 complete (x, y) pairs, got {n}")
    if np.ptp(xa) == 0:
        raise SemlabError("x is constant: the slope is undefined")
    fit = linregress(xa, ya)
    half = float(student_t.ppf(0.5 * (1 + ci), n - 2)) * float(fit.stderr)
    return {"slope": float(fit.slope), "intercept": float(fit.intercept),
            "slope_ci": np.array([fit.slope - half, fit.slope + half]),
            "p": float(fit.pvalue), "r": float(fit.rvalue), "n": n,
            "n_dropped": int((~ok).sum())}
