"""Shared pieces of the figure modules (:mod:`semlab.plots`, :mod:`semlab.plots_motion`):
pyplot on demand, grey-level limits, the report font size and colour codes, the height unit,
image and map downsampling (NaN-aware), shared histogram bins."""

from __future__ import annotations

import numpy as np

#: smallest font of the report figures (points), readable at the notebook's width
REPORT_FONTSIZE = 9
#: colours of the reliability flag of a tracking step, and of the seed kinds
FLAG_COLOURS = {"valid": "tab:green", "flagged": "tab:red"}
SEED_COLOURS = {"corner": "tab:blue", "stereo": "tab:orange"}


def _plt():
    import matplotlib.pyplot as plt

    return plt


def display_range(img, lo=1.0, hi=99.0, max_samples=1 << 20):
    """Robust grey-level limits (percentiles) for showing an SEM image (of at most
    ``max_samples`` pixels on a regular sub-grid: the same limits, without a sorted copy of a
    12 Mpx image)."""
    img = np.asarray(img)
    step = max(1, int(np.ceil(np.sqrt(img.size / max_samples))))
    a, b = np.percentile(img[::step, ::step], [lo, hi])
    return (float(a), float(b)) if b > a else (float(a), float(a) + 1.0)


def height_unit(z_um):
    """The unit heights read best in: ``("nm", 1000.0)`` when every finite ``|z|`` is below
    1 µm, else ``("µm", 1.0)``.

    Returns
    -------
    unit : str
    factor : float
        Multiply µm by it to get ``unit``.
    """
    z = np.asarray(z_um)
    z = np.abs(z[np.isfinite(z)])          # the map's own dtype: no float64 copy of it
    return ("nm", 1000.0) if z.size == 0 or z.max() < 1.0 else ("µm", 1.0)


def _block(shape, max_px):
    """Block size bringing the larger side to at most ``max_px``, but never more than the
    smaller side (a long strip keeps at least one block across)."""
    k = max(1, int(np.ceil(max(shape[:2]) / float(max_px))))
    return max(1, min(k, min(shape[:2])))


def downsample(img, max_px):
    """Block-mean an image or a map so that its larger side is at most ``max_px`` pixels.

    A block is the mean of its *finite* pixels, NaN only where none of them is (a sparsely
    measured height map stays visible; an image has no NaN).

    Returns
    -------
    small : (h, w) float32 array
    k : int
        Block size (1 = unchanged); pixel ``(i, j)`` of ``small`` covers rows
        ``k i .. k i + k - 1`` and columns ``k j .. k j + k - 1`` of ``img``.
    """
    img = np.asarray(img)
    k = _block(img.shape, max_px)
    if k == 1:
        return img.astype(np.float32, copy=False), 1
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    blocks = img[:h, :w].reshape(h // k, k, w // k, k)
    finite = np.isfinite(blocks)
    n = finite.sum(axis=(1, 3))
    total = np.where(finite, blocks, 0).sum(axis=(1, 3), dtype=np.float64)
    out = np.full(n.shape, np.nan, np.float32)
    np.divide(total, n, out=out, where=n > 0, casting="unsafe")
    return out, k


def _show_map(ax, a, k, pixel_size_um=None, **kw):
    """``imshow`` a (downsampled, block ``k``) map on the full map's pixel (or µm) axes."""
    s = pixel_size_um or 1.0
    h, w = np.shape(a)[:2]
    return ax.imshow(a, extent=(-0.5 * s, (w * k - 0.5) * s, (h * k - 0.5) * s, -0.5 * s),
                     interpolation="nearest" if k == 1 else "antialiased", **kw)


def _show_gray(ax, img, pixel_size_um=None, max_px=None):
    """An SEM image in grey, its pixel centres at integer pixel (or µm) coordinates; returns
    the scale from pixels to the axes unit (1 or ``pixel_size_um``)."""
    vmin, vmax = display_range(img)
    k = 1
    if max_px:
        img, k = downsample(img, max_px)
    _show_map(ax, img, k, pixel_size_um, cmap="gray", vmin=vmin, vmax=vmax)
    s = pixel_size_um or 1.0
    unit = "µm" if pixel_size_um else "px"
    ax.set_xlabel(f"x ({unit})", fontsize=REPORT_FONTSIZE)
    ax.set_ylabel(f"y ({unit})", fontsize=REPORT_FONTSIZE)
    ax.tick_params(labelsize=REPORT_FONTSIZE)
    return s


def shared_bins(arrays, n_bins=30):
    """Histogram bin edges covering the finite values of all ``arrays`` (so that their
    histograms compare bin by bin)."""
    vals = np.concatenate([np.asarray(a, float).ravel() for a in arrays])
    vals = vals[np.isfinite(vals)]
    if vals.size == 0:
        return np.linspace(0.0, 1.0, n_bins + 1)
    lo, hi = float(vals.min()), float(vals.max())
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    return np.linspace(lo, hi, n_bins + 1)
