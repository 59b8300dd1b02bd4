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


FAMILY_COLOURS = ("tab:red", "tab:green", "tab:blue", "tab:orange", "tab:purple")


def show_line_families(img, families, ax=None, title=None, vps=None):
    """Line segments of each direction family over an image, extended toward their vanishing
    points when ``vps`` (F, 3) homogeneous are given (only where the point is finite)."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(7, 5))
    show_image(img, ax=ax, title=title)
    h, w = np.shape(img)[:2]
    for k, (name, segs) in enumerate(families.items()):
        col = FAMILY_COLOURS[k % len(FAMILY_COLOURS)]
        segs = np.asarray(segs)
        for i, (x1, y1, x2, y2) in enumerate(segs):
            ax.plot([x1, x2], [y1, y2], "-", color=col, lw=1.5, label=f"family {name}" if i == 0 else None)
        if vps is not None and abs(vps[k][2]) > 1e-12:
            vx, vy = vps[k][0] / vps[k][2], vps[k][1] / vps[k][2]
            for x1, y1, x2, y2 in segs:
                ax.plot([(x1 + x2) / 2, vx], [(y1 + y2) / 2, vy], ":", color=col, lw=0.6)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.legend(loc="lower right", fontsize=8)
    return ax


def show_epipolar_lines(img0, img1, F, x0, x1, n_lines=12, title=""):
    """Both views with matched points and the epipolar lines of a subset of them.

    ``F`` maps view 0 to view 1 (``x1ᵀ F x0 = 0``): the line of a point of view 0 is drawn in
    view 1 and that of a point of view 1 (``Fᵀ x1``) in view 0.
    """
    from .epipolar import epipolar_lines

    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8))
    idx = np.linspace(0, len(x0) - 1, min(n_lines, len(x0))).round().astype(int)
    for ax, img, pts, other, view in ((axes[0], img0, x0, x1, 1), (axes[1], img1, x1, x0, 0)):
        show_image(img, ax=ax, points=pts, title=f"view {1 - view}{title}")
        h, w = img.shape[:2]
        lines = epipolar_lines(F, other[idx], from_view=view)
        xs = np.array([0, w - 1.0])
        for (a, b, c), col in zip(lines, plt.cm.tab20(np.linspace(0, 1, len(idx)))):
            if abs(b) > 1e-9:
                ax.plot(xs, -(a * xs + c) / b, "-", color=col, lw=0.8)
            else:
                ax.axvline(-c / a, color=col, lw=0.8)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
    fig.tight_layout()
    return fig


def plot_stability(stab, ax=None, label=None):
    """F and epipole change against the number of correspondences used (median ± IQR/2)."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4))
    n = stab["sizes"]
    for key, name in (("f_angle_deg", "F"), ("epipole_angle_deg", "epipole / epipolar direction")):
        med, iqr = stab[f"{key}_median"], stab[f"{key}_iqr"]
        ax.errorbar(n, med, yerr=iqr / 2, marker="o", ms=3, capsize=2,
                    label=f"{name}" + (f" ({label})" if label else ""))
    ax.set_xlabel("number of correspondences used")
    ax.set_ylabel("change vs all points (deg)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return ax


def show_static(fig, dpi=90):
    """Display a figure as a still PNG and close it (for notebooks that use the interactive
    ipympl backend, so that executed reports keep a picture)."""
    import io

    from IPython.display import Image, display

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    _plt().close(fig)
    display(Image(buf.getvalue()))
