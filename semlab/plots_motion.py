"""Figures of the motion during the test: tracks, their reliability flags, displacements,
lateral motion against height, strain maps and history (re-exported by :mod:`semlab.plots`).

Functions take numpy arrays and return the figure or axes they drew on.
"""

from __future__ import annotations

import numpy as np

from ._plotting import (FLAG_COLOURS, REPORT_FONTSIZE, SEED_COLOURS, _plt, _show_gray,
                        height_unit, shared_bins)

__all__ = ["tracks_overview", "plot_fb_errors", "displacement_histograms", "lateral_vs_depth",
           "strain_maps", "principal_directions", "strain_history"]


def tracks_overview(frames, xy, valid, cycles=None, max_frames=4, max_px=300, trail_every=3):
    """Tracks over at most ``max_frames`` frames, latest first, in a 2-column grid.

    Each frame is downsampled (:func:`downsample`, larger side ``<= max_px``) so that the
    figure stays small in an executed notebook; the markers stay at full-resolution pixel
    coordinates. Titles give the frame and its cycle count; a legend explains the colours.

    Parameters
    ----------
    frames : list of F (H, W) arrays, frame 0 the earliest
    xy : (F, T, 2) array of (x, y) pixels of T tracks per frame
    valid : (F, T) bool array, the reliability flag of each step
    cycles : (F,) array, optional
    max_frames : int
    max_px : int
    trail_every : int
        Draw the trail (positions in the later frames) of every n-th valid track.

    Returns
    -------
    Figure
    """
    plt = _plt()
    n = len(frames)
    order = np.unique(np.linspace(n - 1, 0, min(max_frames, n)).round().astype(int))[::-1]
    ncols = min(2, len(order))
    nrows = int(np.ceil(len(order) / ncols))
    h, w = np.shape(frames[0])[:2]
    panel_w = 5.0
    fig, axes = plt.subplots(nrows, ncols, squeeze=False,
                             figsize=(panel_w * ncols, panel_w * h / w * nrows + 0.9))
    xy, valid = np.asarray(xy, float), np.asarray(valid, bool)
    for ax, f in zip(axes.ravel(), order):
        _show_gray(ax, frames[f], max_px=max_px)
        ok = valid[f]
        ax.plot(xy[f, ok, 0], xy[f, ok, 1], ".", color="lime", ms=4, label="valid step")
        ax.plot(xy[f, ~ok, 0], xy[f, ~ok, 1], "x", color="red", ms=4, mew=1.2,
                label="flagged step")
        for j, i in enumerate(np.flatnonzero(ok)[::max(1, trail_every)]):
            seg = xy[f:, i]
            ax.plot(seg[:, 0], seg[:, 1], "-", color="yellow", lw=1.0,
                    label="trail to the last frame" if j == 0 else None)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        title = f"frame {f}" + ("" if cycles is None else f" · {cycles[f]:g} cycles")
        ax.set_title(title, fontsize=REPORT_FONTSIZE + 1)
    for ax in axes.ravel()[len(order):]:
        ax.axis("off")
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=REPORT_FONTSIZE,
               frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    return fig


def plot_fb_errors(fb_error_px, valid, threshold_px, ax=None):
    """Forward–backward error of every tracking step by frame, coloured by its flag.

    Parameters
    ----------
    fb_error_px : (F, T) array (NaN where a track has no step)
    valid : (F, T) bool array
    threshold_px : float
        The flag's threshold, drawn as a dashed line.
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.5, 3.8))
    e, v = np.asarray(fb_error_px, float), np.asarray(valid, bool)
    rng = np.random.default_rng(0)
    for flag, sel_fn in (("valid", lambda f: v[f]), ("flagged", lambda f: ~v[f])):
        xs, ys = [], []
        for f in range(e.shape[0]):
            sel = sel_fn(f) & np.isfinite(e[f]) & (e[f] > 0)
            xs.append(f + rng.uniform(-0.2, 0.2, int(sel.sum())))
            ys.append(e[f, sel])
        xs, ys = np.concatenate(xs), np.concatenate(ys)
        ax.scatter(xs, ys, s=5, color=FLAG_COLOURS[flag], label=f"{flag} ({len(xs)})")
    ax.axhline(threshold_px, color="k", lw=0.8, ls="--", label=f"threshold {threshold_px:g} px")
    ax.set_yscale("log")
    ax.set_xlabel("frame (0 = earliest)", fontsize=REPORT_FONTSIZE)
    ax.set_ylabel("forward–backward error (px)", fontsize=REPORT_FONTSIZE)
    ax.tick_params(labelsize=REPORT_FONTSIZE)
    ax.legend(fontsize=REPORT_FONTSIZE)
    return ax


def displacement_histograms(dx_um, dy_um, d_um, seed, n_bins=30):
    """Histograms of dx, dy and |d| (µm) per seed kind, with shared bins and overlapping
    outlines (no kind hides another).

    Parameters
    ----------
    dx_um, dy_um, d_um : (T,) arrays (NaN for tracks without a displacement)
    seed : (T,) str array, e.g. ``"corner"`` / ``"stereo"``

    Returns
    -------
    Figure
    """
    plt = _plt()
    seed = np.asarray(seed)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    kinds = [k for k in SEED_COLOURS if np.any(seed == k)] + sorted(
        set(np.unique(seed)) - set(SEED_COLOURS))
    for ax, v, name in zip(axes, (dx_um, dy_um, d_um), ("dx", "dy", "|d|")):
        v = np.asarray(v, float)
        bins = shared_bins([v], n_bins)
        for j, kind in enumerate(kinds):
            sel = np.isfinite(v) & (seed == kind)
            if sel.any():
                ax.hist(v[sel], bins=bins, histtype="step", lw=1.6,
                        color=SEED_COLOURS.get(kind, f"C{j + 2}"),
                        label=f"{kind}-seeded ({int(sel.sum())})")
        ax.set_xlabel(f"{name} (µm)", fontsize=REPORT_FONTSIZE)
        ax.set_ylabel("tracks", fontsize=REPORT_FONTSIZE)
        ax.tick_params(labelsize=REPORT_FONTSIZE)
        ax.legend(fontsize=REPORT_FONTSIZE)
    fig.tight_layout()
    return fig


def lateral_vs_depth(d_um, z_um, dx_um, dy_um, n_boot=500, seed=0):
    """Height against lateral displacement, four panels, with Pearson and Spearman
    correlations and their bootstrap CIs (:func:`semlab.stats.correlation`) in the titles.

    Heights are in nm when every ``|z|`` is below 1 µm.

    Parameters
    ----------
    d_um, z_um, dx_um, dy_um : (N,) arrays (µm)

    Returns
    -------
    Figure
    """
    from .stats import correlation

    plt = _plt()
    unit, f = height_unit(z_um)
    z = np.asarray(z_um, float)
    pairs = ((d_um, z, "|d| (µm)", f"z ({unit})"), (d_um, np.abs(z), "|d| (µm)", f"|z| ({unit})"),
             (dx_um, z, "dx (µm)", f"z ({unit})"), (dy_um, z, "dy (µm)", f"z ({unit})"))
    fig, axes = plt.subplots(2, 2, figsize=(10, 8))
    for ax, (x, y, xl, yl) in zip(axes.ravel(), pairs):
        ax.plot(x, np.asarray(y) * f, ".", ms=4)
        c = correlation(x, y, n_boot=n_boot, seed=seed)
        ax.set_title(f"Pearson {c['pearson_r']:+.2f} [{c['pearson_ci'][0]:+.2f}, "
                     f"{c['pearson_ci'][1]:+.2f}]\nSpearman {c['spearman_rho']:+.2f} "
                     f"[{c['spearman_ci'][0]:+.2f}, {c['spearman_ci'][1]:+.2f}]",
                     fontsize=REPORT_FONTSIZE)
        ax.set_xlabel(xl, fontsize=REPORT_FONTSIZE)
        ax.set_ylabel(yl, fontsize=REPORT_FONTSIZE)
        ax.tick_params(labelsize=REPORT_FONTSIZE)
    fig.tight_layout()
    return fig


def strain_maps(grid_x_px, grid_y_px, maps, pixel_size_um=None, interpolated=None,
                sigma=False):
    """Strain component maps side by side, each with its colour bar: a symmetric scale (98th
    percentile of ``|value|``), or with ``sigma`` a one-sided scale from 0 for their 1σ.

    Parameters
    ----------
    grid_x_px, grid_y_px : (nx,), (ny,) grid coordinates (pixels)
    maps : dict ``{name: (ny, nx) array}`` of dimensionless strains
    pixel_size_um : float, optional
        Axes in µm when given.
    interpolated : (ny, nx) bool array, optional
        Grid points whose displacement was interpolated, not measured (``strain.npz``
        ``dense_filled``): marked with a grey dot on every map and named in the legend.
    sigma : bool
        The maps are 1σ error bars (``strain.npz`` ``E_sigma``): a sequential colour scale
        from 0 to the 98th percentile, labelled as a 1σ.
    """
    plt = _plt()
    s = pixel_size_um or 1.0
    unit = "µm" if pixel_size_um else "px"
    # each grid value is drawn as the cell centred on its grid point (imshow's extent is
    # the outer edges: half a spacing beyond the first and last points)
    gx, gy = np.asarray(grid_x_px, float), np.asarray(grid_y_px, float)
    hx = 0.5 * (gx[-1] - gx[0]) / (len(gx) - 1) if len(gx) > 1 else 0.5
    hy = 0.5 * (gy[-1] - gy[0]) / (len(gy) - 1) if len(gy) > 1 else 0.5
    ext = [(gx[0] - hx) * s, (gx[-1] + hx) * s, (gy[-1] + hy) * s, (gy[0] - hy) * s]
    marked = interpolated is not None and bool(np.any(interpolated))
    if marked:
        mx, my = np.meshgrid(gx * s, gy * s)
        m = np.asarray(interpolated, bool)
    fig, axes = plt.subplots(1, len(maps), figsize=(4.5 * len(maps), 3.8 + 0.3 * marked),
                             squeeze=False)
    for ax, (name, v) in zip(axes[0], maps.items()):
        finite = np.abs(np.asarray(v, float))
        finite = finite[np.isfinite(finite)]
        lim = (float(np.percentile(finite, 98)) if finite.size else 0.0) or 1e-6
        im = ax.imshow(v, extent=ext, cmap="viridis" if sigma else "RdBu_r",
                       vmin=0.0 if sigma else -lim, vmax=lim)
        ax.set_title(name, fontsize=REPORT_FONTSIZE + 1)
        ax.set_xlabel(f"x ({unit})", fontsize=REPORT_FONTSIZE)
        ax.set_ylabel(f"y ({unit})", fontsize=REPORT_FONTSIZE)
        ax.tick_params(labelsize=REPORT_FONTSIZE)
        fig.colorbar(im, ax=ax, label="1σ of the strain (–)" if sigma else "strain (–)")
        if marked:
            ax.plot(mx[m], my[m], ".", color="0.3", ms=2.5,
                    label="displacement interpolated (no subset matched)")
    if marked:   # one legend for the row, below it
        fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="lower center",
                   fontsize=REPORT_FONTSIZE, frameon=False)
        fig.tight_layout(rect=(0, 0.07, 1, 1))
    else:
        fig.tight_layout()
    return fig


def principal_directions(grid_x_px, grid_y_px, e1, angle_deg, pixel_size_um=None, ax=None):
    """The first principal strain as headless arrows (direction, length = size) on the grid.

    Parameters
    ----------
    grid_x_px, grid_y_px : (nx,), (ny,) grid coordinates (pixels)
    e1 : (ny, nx) first principal strain
    angle_deg : (ny, nx) its direction, degrees from the x axis (image y down)
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6.5, 4.5))
    s = pixel_size_um or 1.0
    unit = "µm" if pixel_size_um else "px"
    gx, gy = np.meshgrid(np.asarray(grid_x_px) * s, np.asarray(grid_y_px) * s)
    a = np.deg2rad(angle_deg)
    ax.quiver(gx, gy, e1 * np.cos(a), e1 * np.sin(a), color="tab:red", pivot="mid",
              headwidth=0, angles="xy", label="e1: direction and size")
    ax.invert_yaxis()
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({unit})", fontsize=REPORT_FONTSIZE)
    ax.set_ylabel(f"y ({unit})", fontsize=REPORT_FONTSIZE)
    ax.set_title("first principal strain: direction and size", fontsize=REPORT_FONTSIZE + 1)
    ax.legend(fontsize=REPORT_FONTSIZE, loc="upper right")
    return ax


def strain_history(history, cycles=None, ax=None):
    """Mean strain of each frame relative to the end state, against cycles (or frame).

    Parameters
    ----------
    history : dict with any of ``"exx"``, ``"eyy"``, ``"exy"``: (F,) arrays
        With ``"exx_sigma"`` etc. (the 1σ of each frame's mean strain, see
        :func:`semlab.strain.strain_history`), each point gets its ±1σ error bar.
    cycles : (F,) array, optional
    """
    plt = _plt()
    if ax is None:
        _, ax = plt.subplots(figsize=(6, 3.8))
    n = len(next(iter(history.values())))
    x = np.arange(n) if cycles is None else np.asarray(cycles)
    with_sigma = False
    for k in ("exx", "eyy", "exy"):
        if k not in history:
            continue
        sd = history.get(f"{k}_sigma")
        if sd is not None and np.isfinite(sd).any():
            with_sigma = True
            ax.errorbar(x, history[k], yerr=np.where(np.isfinite(sd), sd, 0.0), fmt="o-",
                        capsize=3, label=k)
        else:
            ax.plot(x, history[k], "o-", label=k)
    if with_sigma:
        ax.set_title("error bars: ±1σ of the mean strain (track errors)",
                     fontsize=REPORT_FONTSIZE)
    ax.set_xlabel("cycles" if cycles is not None else "frame (0 = earliest)",
                  fontsize=REPORT_FONTSIZE)
    ax.set_ylabel("mean strain relative to the end (–)", fontsize=REPORT_FONTSIZE)
    ax.tick_params(labelsize=REPORT_FONTSIZE)
    ax.legend(fontsize=REPORT_FONTSIZE)
    return ax
