"""Figures for the notebooks: every axis carries its unit.

Functions take numpy arrays (and an optional matplotlib ``Axes``) and return the figure or
axes they drew on, so notebooks stay thin.
"""

from __future__ import annotations

import numpy as np


def _plt():
    import matplotlib.pyplot as plt

    return plt


def display_range(img, lo=1.0, hi=99.0):
    """Robust grey-level limits (percentiles) for showing an SEM image."""
    a, b = np.percentile(img, [lo, hi])
    return (float(a), float(b)) if b > a else (float(a), float(a) + 1.0)


def show_image(img, ax=None, title=None, pixel_size_um=None, points=None, labels=None, **kw):
    """Show an SEM image with axes in pixels (and a µm scale bar when the pixel size is known).

    Parameters
    ----------
    img : (H, W) array
    pixel_size_um : float, optional
    points : (N, 2) array of (x, y) pixels, optional
        Drawn as markers.
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    vmin, vmax = display_range(img)
    ax.imshow(img, cmap="gray", vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    if title:
        ax.set_title(title)
    if points is not None and len(points):
        p = np.asarray(points)
        ax.plot(p[:, 0], p[:, 1], "+", color=kw.get("color", "tab:orange"), ms=7, mew=1.2)
        if labels is not None:
            for (x, y), lab in zip(p, labels):
                ax.annotate(str(lab), (x, y), xytext=(3, 3), textcoords="offset points",
                            color=kw.get("color", "tab:orange"), fontsize=7)
    if pixel_size_um:
        add_scale_bar(ax, img.shape, pixel_size_um)
    return ax


def add_scale_bar(ax, shape, pixel_size_um):
    """A white scale bar of a round length (µm) at the bottom left of an image axes."""
    h, w = shape[:2]
    target = 0.2 * w * pixel_size_um
    nice = 10 ** np.floor(np.log10(target))
    for m in (5, 2, 1):
        if m * nice <= target:
            nice *= m
            break
    length_px = nice / pixel_size_um
    x0, y0 = 0.05 * w, 0.93 * h
    ax.plot([x0, x0 + length_px], [y0, y0], color="white", lw=3)
    ax.text(x0 + length_px / 2, y0 - 0.02 * h, f"{nice:g} µm", color="white", ha="center",
            va="bottom", fontsize=8)


def show_images(images, titles=None, pixel_size_um=None, ncols=None, size=3.6):
    """Show several images side by side; returns the figure."""
    plt = _plt()
    n = len(images)
    ncols = ncols or min(n, 3)
    nrows = int(np.ceil(n / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(size * 1.3 * ncols, size * nrows), squeeze=False)
    for i, ax in enumerate(axes.ravel()):
        if i < n:
            show_image(images[i], ax=ax, title=None if titles is None else titles[i],
                       pixel_size_um=pixel_size_um)
        else:
            ax.axis("off")
    fig.tight_layout()
    return fig


def show_height_map(z_um, ax=None, pixel_size_um=None, title="height z (µm)", cmap="RdBu_r"):
    """A height map (µm) with a symmetric diverging colour scale; z > 0 is an extrusion."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    lim = float(np.nanpercentile(np.abs(z_um), 99.5)) or 1.0
    im = ax.imshow(z_um, cmap=cmap, vmin=-lim, vmax=lim)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(title)
    ax.figure.colorbar(im, ax=ax, label="z (µm)")
    if pixel_size_um:
        add_scale_bar(ax, np.shape(z_um), pixel_size_um)
    return ax
