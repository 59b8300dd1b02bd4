"""Shared pieces of the figure modules (:mod:`semlab.plots`, :mod:`semlab.plots_motion`):
pyplot on demand, grey-level limits, the report font size and colour codes, the height unit,
image downsampling, shared histogram bins."""

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


def display_range(img, lo=1.0, hi=99.0):
    """Robust grey-level limits (percentiles) for showing an SEM image."""
    a, b = np.percentile(img, [lo, hi])
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
    z = np.abs(np.asarray(z_um, float))
    z = z[np.isfinite(z)]
    return ("nm", 1000.0) if z.size == 0 or z.max() < 1.0 else ("µm", 1.0)


def downsample(img, max_px):
    """Block-mean an image so that its larger side is at most ``max_px`` pixels.

    Returns
    -------
    small : (h, w) float32 array
    k : int
        Block size (1 = unchanged); pixel ``(i, j)`` of ``small`` covers rows
        ``k i .. k i + k - 1`` and columns ``k j .. k j + k - 1`` of ``img``.
    """
    img = np.asarray(img, np.float32)
    k = max(1, int(np.ceil(max(img.shape[:2]) / float(max_px))))
    if k == 1:
        return img, 1
    h, w = (img.shape[0] // k) * k, (img.shape[1] // k) * k
    return img[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3)), k


def _show_gray(ax, img, pixel_size_um=None, max_px=None):
    """An SEM image in grey, its pixel centres at integer pixel (or µm) coordinates; returns
    the scale from pixels to the axes unit (1 or ``pixel_size_um``)."""
    vmin, vmax = display_range(img)
    k = 1
    if max_px:
        img, k = downsample(img, max_px)
    s = pixel_size_um or 1.0
    h, w = img.shape[:2]
    # a downsampled image is smoothed on screen (its pixels are not the data's anyway)
    ax.imshow(img, cmap="gray", vmin=vmin, vmax=vmax,
              interpolation="bilinear" if k > 1 else "nearest",
              extent=(-0.5 * s, (w * k - 0.5) * s, (h * k - 0.5) * s, -0.5 * s))
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
