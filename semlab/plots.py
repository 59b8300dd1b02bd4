"""Figures for the notebooks: every axis carries its unit, every colour code a legend.

Functions take numpy arrays (and an optional matplotlib ``Axes``) and return the figure or
axes they drew on, so notebooks stay thin. Heights below 1 µm are shown in nm
(:func:`height_unit`); images and maps in report figures are downsampled to the size they
are seen at (:func:`downsample`), which keeps executed notebooks and
the notebook kernel small (a 3072×4096 map is shown from a 1024 px copy).
"""

from __future__ import annotations

import numpy as np

from ._plotting import (FLAG_COLOURS, REPORT_FONTSIZE, SEED_COLOURS, _plt, _show_gray,
                        _show_map, display_range, downsample, height_unit,
                        shared_bins)
from .plots_motion import (displacement_histograms, lateral_vs_depth, plot_fb_errors,
                           principal_directions, strain_history, strain_maps, tracks_overview)

__all__ = [
    "display_range", "show_image", "add_scale_bar", "show_images", "show_height_map",
    "show_line_families", "show_epipolar_lines", "plot_stability", "show_static",
    "height_unit", "downsample", "show_height_points", "plot_height_projections",
    "plot_point_profile", "trend_sentence", "tracks_overview", "plot_fb_errors", "shared_bins",
    "displacement_histograms", "show_picked_points", "show_line_families_views",
    "stability_figure", "lateral_vs_depth", "strain_maps", "principal_directions",
    "strain_history", "error_histograms",
    "show_heightmap_panels", "show_hillshade", "plot_profile", "show_bands", "plot_band_profiles",
    "plot_drift", "REPORT_FONTSIZE", "FLAG_COLOURS", "SEED_COLOURS",
]


def show_image(img, ax=None, title=None, pixel_size_um=None, points=None, labels=None,
               max_px=1024, **kw):
    """Show an SEM image with axes in pixels (and a µm scale bar when the pixel size is known).

    Parameters
    ----------
    img : (H, W) array
    pixel_size_um : float, optional
    points : (N, 2) array of (x, y) pixels, optional
        Drawn as markers.
    max_px : int
        An image larger than this is drawn from block means (:func:`downsample`) on the full
        image's pixel axes.
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    _show_gray(ax, img, max_px=max_px)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    if title:
        ax.set_title(title)
    if points is not None and len(points):
        p = np.asarray(points)
        ax.plot(p[:, 0], p[:, 1], "+", color=kw.get("color", "tab:orange"), ms=7, mew=1.2)
        if labels is not None:
            for (x, y), lab in zip(p, labels):
                if not (np.isfinite(x) and np.isfinite(y)):   # not matched in this view
                    continue
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


def show_height_map(z_um, ax=None, pixel_size_um=None, title="height z", cmap="RdBu_r",
                    max_px=1024):
    """A height map with a symmetric diverging colour scale; z > 0 is an extrusion.

    Axes in µm when ``pixel_size_um`` is given (else pixels); heights in nm where every
    ``|z|`` is below 1 µm (:func:`height_unit`). A map larger than ``max_px`` is shown as
    block means (:func:`downsample`) on the full map's axes.

    Parameters
    ----------
    z_um : (H, W) array of heights (µm), NaN where unknown
    max_px : int
        Largest side shown, pixels.
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    unit, f = height_unit(z_um)
    z, k = downsample(z_um, max_px)
    z = z * np.float32(f)
    finite = np.abs(z[np.isfinite(z)])
    lim = float(np.percentile(finite, 99.5)) if finite.size else 1.0
    im = _show_map(ax, z, k, pixel_size_um, cmap=cmap, vmin=-(lim or 1.0), vmax=lim or 1.0)
    xy_unit = "µm" if pixel_size_um else "px"
    ax.set_xlabel(f"x ({xy_unit})")
    ax.set_ylabel(f"y ({xy_unit})")
    ax.set_title(title)
    ax.figure.colorbar(im, ax=ax, label=f"z ({unit}), > 0 extrusion")
    return ax


def show_reference_surface(img, xy_px, z, inliers, ax=None, unit="µm", lim=None,
                           title="heights above the reference surface"):
    """View 0 with every point coloured by its height and the reference points outlined.

    Parameters
    ----------
    img : (H, W) array
        View 0.
    xy_px : (N, 2) array of (x, y) pixels in view 0
    z : (N,) array
        Heights above the reference surface (``unit``).
    inliers : (N,) bool array
        The points that define the reference plane (``ReferenceSurface.inliers``), outlined
        in black.
    lim : float, optional
        Colour scale ``[-lim, lim]``; default the 95th percentile of ``|z|`` of the inliers
        times 3 (the reference's own scatter stays pale, relief stands out).
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 5))
    xy = np.asarray(xy_px, float)
    z = np.asarray(z, float)
    inl = np.asarray(inliers, bool)
    show_image(img, ax=ax, title=title)
    if lim is None:
        lim = 3 * float(np.percentile(np.abs(z[inl]), 95)) if inl.any() else float(np.ptp(z))
    sc = ax.scatter(xy[:, 0], xy[:, 1], c=z, s=7, cmap="RdBu_r", vmin=-lim, vmax=lim)
    ax.scatter(xy[inl, 0], xy[inl, 1], s=9, facecolors="none", edgecolors="k", linewidths=0.3,
               label=f"reference ({int(inl.sum())} points)")
    ax.figure.colorbar(sc, ax=ax, label=f"z ({unit})")
    ax.legend(loc="lower right", fontsize=7)
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


def show_static(fig, dpi=90, fmt="png", quality=80):
    """Display a figure as a still picture and close it.

    For notebooks that use the interactive ipympl backend (so that executed reports keep a
    picture), and for figures of SEM images: ``fmt="jpeg"`` stores noisy images 5-10 times
    smaller than PNG, which keeps executed notebooks small.

    Parameters
    ----------
    fig : Figure
    dpi : float
    fmt : {"png", "jpeg"}
    quality : int
        JPEG quality (1-95).
    """
    import io

    from IPython.display import Image, display

    if fmt not in ("png", "jpeg"):
        raise ValueError(f"fmt must be 'png' or 'jpeg', got {fmt!r}")
    buf = io.BytesIO()
    kw = {"pil_kwargs": {"quality": int(quality)}} if fmt == "jpeg" else {}
    fig.savefig(buf, format=fmt, dpi=dpi, bbox_inches="tight", **kw)
    _plt().close(fig)
    display(Image(buf.getvalue(), format=fmt))


# --------------------------------------------------------------------------- report figures



def show_height_points(img, pts_px, z_um, pixel_size_um, ax=None, title=None, cmap="coolwarm",
                       max_px=1024):
    """Measured heights as dots over the image, in µm axes.

    Heights below 1 µm are shown in nm. The dots have a black edge so that a near-zero
    height (the light middle of the diverging colour scale) does not look like a particle.

    Parameters
    ----------
    img : (H, W) array
        View 0.
    pts_px : (N, 2) array of (x, y) pixels in that view
    z_um : (N,) heights (µm), z > 0 extrusion
    pixel_size_um : float
    ax : Axes, optional
    max_px : int
        The image is shown from block means of at most this side (:func:`downsample`).

    Returns
    -------
    Axes
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(8, 5.5))
    unit, f = height_unit(z_um)
    s = _show_gray(ax, img, pixel_size_um, max_px=max_px)
    z = np.asarray(z_um, float) * f
    lim = float(np.nanpercentile(np.abs(z), 99)) or 1.0
    p = np.asarray(pts_px, float)
    sc = ax.scatter(p[:, 0] * s, p[:, 1] * s, c=z, cmap=cmap, vmin=-lim, vmax=lim, s=16,
                    edgecolors="black", linewidths=0.5)
    cb = ax.figure.colorbar(sc, ax=ax, fraction=0.046, pad=0.02)
    cb.set_label(f"z ({unit}), > 0 extrusion", fontsize=REPORT_FONTSIZE)
    cb.ax.tick_params(labelsize=REPORT_FONTSIZE)
    ax.set_title(title or f"heights of {len(z)} points over view 0", fontsize=REPORT_FONTSIZE + 1)
    return ax


def plot_height_projections(xyz_um, z_um, z_err_um):
    """x–z and y–z projections of the heights with 1σ error bars (nm below 1 µm).

    Parameters
    ----------
    xyz_um : (N, 3) array of material (x, y, z) µm
    z_um, z_err_um : (N,) heights above the reference and their 1σ, µm

    Returns
    -------
    Figure
    """
    plt = _plt()
    unit, f = height_unit(z_um)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharey=True)
    for ax, k, name in ((axes[0], 0, "x"), (axes[1], 1, "y")):
        ax.errorbar(xyz_um[:, k], np.asarray(z_um) * f, yerr=np.asarray(z_err_um) * f, fmt=".",
                    ms=3, elinewidth=0.5, alpha=0.7, label="point ± 1σ")
        ax.axhline(0, color="k", lw=0.6, label="reference surface")
        ax.set_xlabel(f"{name} (µm)", fontsize=REPORT_FONTSIZE)
        ax.tick_params(labelsize=REPORT_FONTSIZE)
    axes[0].set_ylabel(f"z ({unit}), > 0 extrusion", fontsize=REPORT_FONTSIZE)
    axes[0].legend(fontsize=REPORT_FONTSIZE, loc="best")
    fig.tight_layout()
    return fig


def plot_point_profile(distance_um, z_um, z_err_um, ax=None, title="heights along the crack"):
    """Heights of measured points along a line with 1σ error bars (nm below 1 µm) against
    distance (µm); :func:`plot_profile` draws a dense profile with its 1σ band."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(7, 3.5))
    unit, f = height_unit(z_um)
    ax.errorbar(distance_um, np.asarray(z_um) * f, yerr=np.asarray(z_err_um) * f, fmt="o", ms=3,
                label="point ± 1σ")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("distance along the line (µm)", fontsize=REPORT_FONTSIZE)
    ax.set_ylabel(f"z ({unit})", fontsize=REPORT_FONTSIZE)
    ax.tick_params(labelsize=REPORT_FONTSIZE)
    ax.set_title(title, fontsize=REPORT_FONTSIZE + 1)
    return ax


def _format_p(p):
    return f"p = {p:.2g}" if p >= 1e-4 else "p < 0.0001"


def trend_sentence(pos_um, z_um, axis="y", ci=0.95, per_um=10.0, alpha=0.05):
    """One sentence on how height changes with position: slope, its CI and p.

    Parameters
    ----------
    pos_um : (N,) positions along ``axis`` (µm)
    z_um : (N,) heights (µm)
    axis : str
        Name of the position axis in the sentence.
    ci : float
        Confidence level of the interval.
    per_um : float
        The slope is given per this many µm (10: "per 10 µm").
    alpha : float
        Below this p the trend is called significant.

    Returns
    -------
    str
        e.g. ``"Along y, z rises by 12 nm per 10 µm (95 % CI 4.1 to 20 nm, p = 0.003,
        n = 120): more extrusion at high y."``

    Raises
    ------
    SemlabError
        From :func:`semlab.stats.linear_trend` (fewer than 3 points, constant position).
    """
    from .stats import linear_trend

    t = linear_trend(pos_um, z_um, ci=ci)
    unit, f = height_unit(np.asarray(t["slope_ci"]) * per_um)
    slope, lo, hi = (v * per_um * f for v in (t["slope"], *t["slope_ci"]))
    verb = "rises" if slope > 0 else "falls"
    head = (f"Along {axis}, z {verb} by {abs(slope):.2g} {unit} per {per_um:g} µm "
            f"({100 * ci:.0f} % CI {lo:.2g} to {hi:.2g} {unit}, {_format_p(t['p'])}, "
            f"n = {t['n']})")
    if t["p"] >= alpha:
        return head + f": no significant trend with {axis}."
    side = "high" if slope > 0 else "low"
    return head + f": more extrusion at {side} {axis}."


def show_picked_points(images, pts, point_id, titles=None, pixel_size_um=None):
    """The saved correspondences over every view, labelled by ``point_id``.

    Parameters
    ----------
    images : list of V (H, W) arrays
    pts : (N, V, 2) array of (x, y) pixels
    point_id : (N,) int array

    Returns
    -------
    Figure
    """
    plt = _plt()
    v = len(images)
    fig, axes = plt.subplots(1, v, figsize=(6 * v, 4.5), squeeze=False)
    for k, ax in enumerate(axes[0]):
        show_image(images[k], ax=ax, title=titles[k] if titles else f"view {k}",
                   points=pts[:, k], labels=point_id, pixel_size_um=pixel_size_um)
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------ dense height maps
def show_heightmap_panels(z_um, sigma_um, pixel_size_um=None, size=3.6, max_px=1024):
    """Three panels: the height map, its 1σ (nm) and the measured mask, all on the map's
    axes (µm when ``pixel_size_um`` is given) and shown from block means of at most
    ``max_px`` pixels a side (the mask as the measured fraction of each block).

    Returns the figure (axes: map, σ, mask).
    """
    plt = _plt()
    fig, axs = plt.subplots(1, 3, figsize=(3 * size + 1.5, size * 0.8), constrained_layout=True)
    show_height_map(z_um, ax=axs[0], pixel_size_um=pixel_size_um, max_px=max_px)
    sg, k = downsample(sigma_um, max_px)
    sg = sg * np.float32(1e3)
    hi = float(np.percentile(sg[np.isfinite(sg)], 99)) if np.isfinite(sg).any() else 1.0
    im = _show_map(axs[1], sg, k, pixel_size_um, cmap="magma", vmin=0, vmax=hi or 1.0)
    fig.colorbar(im, ax=axs[1], label="1σ (nm)")
    axs[1].set_title("height 1σ (nm)")
    valid = np.isfinite(np.asarray(z_um))
    fraction = float(valid.mean()) if valid.size else 0.0
    _show_map(axs[2], downsample(valid, max_px)[0], k, pixel_size_um, cmap="gray", vmin=0,
              vmax=1)
    axs[2].set_title(f"measured: {100 * fraction:.1f} %")
    unit = "µm" if pixel_size_um else "px"
    for ax in axs[1:]:
        ax.set_xlabel(f"x ({unit})")
        ax.set_ylabel(f"y ({unit})")
    return fig


def show_hillshade(z_um, pixel_size_um, ax=None, azimuth_deg=315.0, altitude_deg=45.0,
                   z_factor=5.0, title=None, max_px=1024):
    """Hill-shaded relief of a height map (heights exaggerated ``z_factor`` times);
    not-measured pixels in red. A map larger than ``max_px`` is shaded from its block means
    (:func:`downsample`, slopes over the blocks' spacing), which is all a figure shows."""
    from .heightmap import hillshade

    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4.5))
    z, k = downsample(z_um, max_px)
    hs = hillshade(z, pixel_size_um * k, azimuth_deg, altitude_deg, z_factor)
    rgb = np.dstack([hs, hs, hs])
    rgb[~np.isfinite(hs)] = (0.8, 0.1, 0.1)
    _show_map(ax, np.nan_to_num(rgb), k)
    ax.set_title(title or f"hill shade (z × {z_factor:g}, light from {azimuth_deg:g}°)")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    add_scale_bar(ax, np.shape(z_um), pixel_size_um)
    return ax


def plot_profile(profile, ax=None, label=None, color=None, x_key="distance_um"):
    """A height profile (dict with ``distance_um``, ``z_um``, ``sigma_um``, as returned by
    :func:`semlab.metrology.profile_between` or :func:`~semlab.metrology.band_profile`)
    with its ±1σ band; heights in nm."""
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 3))
    x = np.asarray(profile[x_key], float)
    z = np.asarray(profile["z_um"], float) * 1e3
    s = np.asarray(profile["sigma_um"], float) * 1e3
    (line,) = ax.plot(x, z, color=color, label=label, lw=1.2)
    ax.fill_between(x, z - s, z + s, color=line.get_color(), alpha=0.25, lw=0)
    ax.set_xlabel("distance (µm)" if x_key == "distance_um" else x_key)
    ax.set_ylabel("z (nm)")
    ax.axhline(0, color="0.6", lw=0.6)
    if label:
        ax.legend(fontsize=8)
    return ax


def show_bands(z_um, bands, ax=None, pixel_size_um=None, max_px=1024):
    """The height map with each band trace drawn and labelled by its id (axes in µm when
    ``pixel_size_um`` is given, else pixels; the traces are in view-0 map pixels)."""
    ax = show_height_map(z_um, ax=ax, pixel_size_um=pixel_size_um, title="bands",
                         max_px=max_px)
    s = pixel_size_um or 1.0
    for b in bands:
        (x0, y0), (x1, y1) = b.p0_px, b.p1_px
        ax.plot([x0 * s, x1 * s], [y0 * s, y1 * s], "k-", lw=1)
        ax.text(s * (x0 + x1) / 2, s * (y0 + y1) / 2, str(b.band_id), fontsize=8,
                bbox=dict(fc="w", alpha=0.7, lw=0))
    ax.set_xlim(-0.5 * s, (np.shape(z_um)[1] - 0.5) * s)
    ax.set_ylim((np.shape(z_um)[0] - 0.5) * s, -0.5 * s)
    return ax


def plot_band_profiles(profiles, ncols=3, size=3.2):
    """One panel per band profile (:func:`semlab.metrology.band_profile`): the mean profile
    across the trace with ±1σ, the baseline, and extrusion/intrusion/width in the title."""
    plt = _plt()
    n = max(1, len(profiles))
    ncols = min(ncols, n)
    nrows = -(-n // ncols)
    fig, axs = plt.subplots(nrows, ncols, figsize=(ncols * size, nrows * size * 0.75),
                            squeeze=False, constrained_layout=True)
    for ax, p in zip(axs.ravel(), profiles):
        plot_profile(p, ax=ax)
        if np.isfinite(p.get("baseline_um", np.nan)):
            ax.axhline(p["baseline_um"] * 1e3, color="k", ls=":", lw=0.8)
        # the highest and the lowest point against the baseline, signed (an "intrusion" whose
        # lowest point is above the baseline is a positive height, not "−-")
        hi, lo = (f"{1e3 * v:+.0f}".replace("-", "−")
                  for v in (p["extrusion_um"], -p["intrusion_um"]))
        ax.set_title(f"band {p['band'].band_id}: {hi}±{1e3 * p['extrusion_err_um']:.0f} / "
                     f"{lo}±{1e3 * p['intrusion_err_um']:.0f} nm, w {p['width_um']:.2f} µm",
                     fontsize=8)
        ax.set_xlabel("across the trace (µm)")
    for ax in axs.ravel()[len(profiles):]:
        ax.set_visible(False)
    return fig


def plot_drift(drift, truth=None, axes=None):
    """Stage drift of every frame relative to the last one: shift, rotation, magnification.

    Parameters
    ----------
    drift : semlab.registration.Registration or dict
        A registration, or the columns of ``drift.csv`` (:func:`semlab.registration.read_drift_csv`):
        ``frame, dx_px, dy_px, rotation_deg, scale, method``.
    truth : dict, optional
        The same columns from ``truth/drift.csv`` of a synthetic experiment, drawn as
        open circles.
    axes : sequence of 3 Axes, optional

    Returns
    -------
    fig : matplotlib Figure with three panels: shift of the image centre (px), rotation about
    it (degrees, positive from +x toward +y) and magnification change (%), against the frame
    index (0 = earliest). Frames registered through their neighbour (no direct feature
    match) are drawn with open squares.
    """
    plt = _plt()
    cols = drift.table() if hasattr(drift, "table") else None
    if cols is not None:
        drift = {k: np.array([r[k] for r in cols]) for k in cols[0]}
    f = np.asarray(drift["frame"], float)
    if axes is None:
        fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.0))
    fig = axes[0].figure
    chained = np.array([str(m).startswith("chained") or str(m) == "none" for m in drift["method"]])
    panels = (((drift["dx_px"], "dx"), (drift["dy_px"], "dy")), ((drift["rotation_deg"], "rotation"),),
              (((np.asarray(drift["scale"], float) - 1) * 100, "magnification"),))
    labels = ("shift of the image centre (px)", "rotation (°)", "magnification change (%)")
    keys = (("dx_px", "dy_px"), ("rotation_deg",), ("scale",))
    for ax, series, ylabel, ks in zip(axes, panels, labels, keys):
        for (v, name), c in zip(series, ("tab:blue", "tab:orange")):
            v = np.asarray(v, float)
            ax.plot(f, v, "-o", color=c, ms=4, label=name)
            if chained.any():
                ax.plot(f[chained], v[chained], "s", mfc="none", color="k", ms=7)
        if truth is not None:
            for k, c in zip(ks, ("tab:blue", "tab:orange")):
                t = np.asarray(truth[k], float)
                t = (t - 1) * 100 if k == "scale" else t
                ax.plot(np.asarray(truth["frame"], float), t, "o", mfc="none", color=c, ms=9,
                        label=f"{k.split('_')[0]} truth" if k != "scale" else "truth")
        ax.set_xlabel("frame (0 = earliest)", fontsize=REPORT_FONTSIZE)
        ax.set_ylabel(ylabel, fontsize=REPORT_FONTSIZE)
        ax.tick_params(labelsize=REPORT_FONTSIZE)
        if len(series) > 1 or truth is not None:
            ax.legend(fontsize=REPORT_FONTSIZE)
    fig.tight_layout()
    return fig


def show_line_families_views(images, lines, vps=None, size=(7.0, 5.2)):
    """The line families of every calibration view, one panel per view.

    Parameters
    ----------
    images : list of (H, W) arrays or None
        A view without an image gets an empty panel saying so.
    lines : list of dict ``{family: (M, 4) segments}`` per view
    vps : list of (F, 3) homogeneous vanishing points per view, optional
    """
    plt = _plt()
    n = len(lines)
    fig, axes = plt.subplots(1, n, figsize=(size[0] * n, size[1]), squeeze=False)
    for i, ax in enumerate(axes[0]):
        if images[i] is None:
            ax.axis("off")
            ax.text(0.5, 0.5, f"view {i}: no image in lines.json", ha="center",
                    transform=ax.transAxes, fontsize=REPORT_FONTSIZE)
            continue
        show_line_families(images[i], lines[i], ax=ax, title=f"view {i}",
                           vps=None if vps is None else vps[i])
    fig.tight_layout()
    return fig


def stability_figure(stabs, title="F stability against the number of clicked points"):
    """:func:`plot_stability` of several models in one axes.

    Parameters
    ----------
    stabs : dict ``{model name: stability dict}`` (:func:`semlab.epipolar.stability`)
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for model, st in stabs.items():
        plot_stability(st, ax=ax, label=model)
    ax.set_title(title, fontsize=REPORT_FONTSIZE + 1)
    return fig


def error_histograms(errors_um, ax=None, n_bins=40):
    """Histograms of ``|height error|`` (nm) per method: shared bins, overlapping outlines.

    Parameters
    ----------
    errors_um : dict ``{method: (N,) errors in µm}``
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 4))
    vals = {m: np.abs(np.asarray(e, float)) * 1000 for m, e in errors_um.items()}
    bins = shared_bins(list(vals.values()), n_bins)
    for m, v in vals.items():
        v = v[np.isfinite(v)]
        ax.hist(v, bins=bins, histtype="step", lw=1.6, density=True, label=f"{m} ({len(v)})")
    ax.set_xlabel("|height error| (nm)", fontsize=REPORT_FONTSIZE)
    ax.set_ylabel("density", fontsize=REPORT_FONTSIZE)
    ax.tick_params(labelsize=REPORT_FONTSIZE)
    ax.legend(fontsize=REPORT_FONTSIZE)
    return ax
