"""Interactive height profile between two clicked points of a height map (ipympl).

``ProfileTool(z_um, sigma_um, pixel_size_um)`` shows the map; two clicks on it (left button)
set the end points and the profile with its ±1σ band appears beside it; a third click starts
a new segment. :meth:`ProfileTool.set_points` does the same from code (and in executed
reports, where nobody clicks). The profile itself is :func:`semlab.metrology.profile_between`;
use ``%matplotlib widget`` in the notebook to click.
"""

from __future__ import annotations

import numpy as np

from . import metrology, plots

__all__ = ["ProfileTool"]


class ProfileTool:
    """Click two points on a height map to see the profile between them.

    Parameters
    ----------
    z_um, sigma_um : (H, W) arrays
        Height map and its 1σ (µm), NaN where not measured.
    pixel_size_um : float
        The map's axes are in µm (clicks too); the end points and the profile are in map
        pixels.
    width_px : float
        Width of the averaged strip (see :func:`semlab.metrology.profile_between`).
    max_px : int
        Largest side of the map as shown (:func:`semlab.plots.downsample`); the profile
        is always sampled from the full map.

    Attributes
    ----------
    points : list of (x, y)
        The clicked end points (0, 1 or 2), view-0 pixels.
    profile : dict or None
        The last profile.
    fig, ax_map, ax_profile : the matplotlib figure and axes.
    """

    def __init__(self, z_um, sigma_um, pixel_size_um, width_px=1.0, figsize=(11, 4),
                 max_px=2048):
        plt = plots._plt()
        self.z_um = np.asarray(z_um)
        self.sigma_um = None if sigma_um is None else np.asarray(sigma_um)
        self.pixel_size_um = float(pixel_size_um)
        self.width_px = float(width_px)
        self.points = []
        self.profile = None
        self.fig, (self.ax_map, self.ax_profile) = plt.subplots(
            1, 2, figsize=figsize, gridspec_kw={"width_ratios": [1.1, 1]},
            constrained_layout=True)      # the map's colour bar label clear of the profile
        # the map's axes are in µm; clicks come in µm and the end points are kept in pixels
        plots.show_height_map(self.z_um, ax=self.ax_map, pixel_size_um=self.pixel_size_um,
                              title="click two points", max_px=max_px)
        (self._line,) = self.ax_map.plot([], [], "k.-", lw=1.2, ms=8)
        self.ax_profile.set_xlabel("distance (µm)")
        self.ax_profile.set_ylabel("z (nm)")
        self._cid = self.fig.canvas.mpl_connect("button_press_event", self._on_click)

    def _on_click(self, event):
        if event.inaxes is not self.ax_map or event.xdata is None or event.button not in (1, None):
            return
        if len(self.points) >= 2:
            self.points = []
        s = self.pixel_size_um
        self.points.append((float(event.xdata) / s, float(event.ydata) / s))
        self._redraw()

    def set_points(self, p0_px, p1_px):
        """Set both end points ``(x, y)`` (view-0 pixels) and draw the profile."""
        self.points = [tuple(map(float, p0_px)), tuple(map(float, p1_px))]
        self._redraw()
        return self.profile

    def _redraw(self):
        xs = [p[0] * self.pixel_size_um for p in self.points]
        ys = [p[1] * self.pixel_size_um for p in self.points]
        self._line.set_data(xs, ys)
        if len(self.points) == 2:
            self.profile = metrology.profile_between(self.z_um, self.sigma_um, self.points[0],
                                                     self.points[1], self.pixel_size_um,
                                                     width_px=self.width_px)
            self.ax_profile.cla()
            plots.plot_profile(self.profile, ax=self.ax_profile)
            (x0, y0), (x1, y1) = self.points
            self.ax_profile.set_title(f"({x0:.0f}, {y0:.0f}) → ({x1:.0f}, {y1:.0f}) px, ±1σ")
        self.fig.canvas.draw_idle()
