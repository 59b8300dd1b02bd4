"""Matplotlib and ipywidgets plumbing shared by the pickers (:mod:`semlab.widgets`,
:mod:`semlab.line_picking`): figures kept out of pyplot's list, images shown at screen
resolution, the canvas as a widget, keyboard focus given back to the canvas.
"""

from __future__ import annotations

import io
import json
import warnings

import numpy as np

from .errors import SemlabError
from .plots import display_range

def _new_figure(figsize):
    import matplotlib.pyplot as plt
    from matplotlib._pylab_helpers import Gcf

    with plt.ioff():
        fig = plt.figure(figsize=figsize)
    # keep the picker out of pyplot's figure list: a later plt.close("all") or a backend
    # switch in another cell must not close the live picker
    Gcf.figs.pop(fig.canvas.manager.num, None)
    return fig


class _ReportsErrors:
    """Mixin of the picker figures: ``_run(fn, *args)`` calls ``fn`` and turns a
    :class:`~semlab.errors.SemlabError` into ``self.message`` (shown in the status line)."""

    def _run(self, fn, *args):
        try:
            out = fn(*args)
            self.message = ""
            return out
        except SemlabError as err:
            self.message = str(err)
            return None


def _toolbar_busy(fig):
    """True when the navigation toolbar is in zoom or pan mode."""
    toolbar = getattr(fig.canvas, "toolbar", None)
    return bool(str(getattr(toolbar, "mode", "") or ""))


def _display_scale(ax):
    """Display pixels per data pixel along x of ``ax``."""
    t = ax.transData.transform([[0.0, 0.0], [1.0, 0.0]])
    return max(abs(t[1, 0] - t[0, 0]), 1e-12)


class _ScreenImage:
    """Show an image at the resolution of the screen: only the visible part, block-averaged
    by ``k`` so that it has about as many pixels as the axes has on the screen.

    A full SEM view (2048×1536) costs matplotlib ~0.12 s to resample at every draw, which
    makes clicking sluggish in ipympl (which cannot blit); the visible part at screen
    resolution draws in a fraction of that. Zoomed in (one image pixel over several screen
    pixels) the crop is shown at full resolution, so what the user clicks on is the image
    itself. The extent keeps pixel centres at integer coordinates (pixel ``(i, j)`` is
    the square ``[j - 0.5, j + 0.5] × [i - 0.5, i + 0.5]``).
    """

    def __init__(self, ax, img, **imshow_kw):
        self.ax = ax
        self.img = np.asarray(img)
        h, w = self.img.shape[:2]
        self.artist = ax.imshow(self.img[:1, :1], extent=(-0.5, 0.5, 0.5, -0.5), **imshow_kw)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        self.key = None
        self.update()
        # matplotlib keeps only weak references to these bound methods: the owner keeps
        # this object alive (see _show_image)
        ax.callbacks.connect("xlim_changed", self.update)
        ax.callbacks.connect("ylim_changed", self.update)

    def update(self, *_):
        """Re-crop and re-decimate for the current view limits."""
        h, w = self.img.shape[:2]
        x0, x1 = sorted(self.ax.get_xlim())
        y0, y1 = sorted(self.ax.get_ylim())
        c0 = int(np.clip(np.floor(x0 + 0.5), 0, w - 1))
        c1 = int(np.clip(np.ceil(x1 + 0.5), c0 + 1, w))
        r0 = int(np.clip(np.floor(y0 + 0.5), 0, h - 1))
        r1 = int(np.clip(np.ceil(y1 + 0.5), r0 + 1, h))
        try:
            screen_px = max(self.ax.get_window_extent().width, 1.0)
        except Exception:  # no renderer yet
            screen_px = 400.0
        k = max(1, int((c1 - c0) // screen_px))
        key = (c0, c1, r0, r1, k)
        if key == self.key:
            return
        self.key = key
        nr, nc = -(-(r1 - r0) // k), -(-(c1 - c0) // k)   # blocks, the last one partial
        crop = self.img[r0:r1, c0:c1].astype(np.float32)
        if k > 1:
            pad = np.full((nr * k, nc * k), np.nan, np.float32)
            pad[:r1 - r0, :c1 - c0] = crop
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                crop = np.nanmean(pad.reshape(nr, k, nc, k), axis=(1, 3))
        self.artist.set_data(crop)
        self.artist.set_extent((c0 - 0.5, c0 + nc * k - 0.5, r0 + nr * k - 0.5, r0 - 0.5))


def _image_limits(img):
    """Grey-level limits (0.5 and 99.5 percentiles) of a 2D image, (None, None) for RGB."""
    img = np.asarray(img)
    if img.ndim != 2:
        return None, None
    return display_range(img, 0.5, 99.5)


def _show_image(ax, img, title):
    lo, hi = _image_limits(img)
    ax._semlab_screen_image = _ScreenImage(ax, img, cmap="gray", vmin=lo, vmax=hi,
                                           interpolation="nearest")
    ax.set_autoscale_on(False)
    ax.set_title(title)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")


def _canvas_widget(fig, refresh_callbacks):
    """The figure as a widget: the ipympl canvas itself, else a static PNG preview."""
    import ipywidgets as W

    if isinstance(fig.canvas, W.DOMWidget):
        fig.canvas.header_visible = False
        fig.canvas.toolbar_visible = "visible"  # always, not only while the mouse is over it
        fig.canvas.toolbar_position = "top"     # not over the y labels of the first view
        fig.canvas.footer_visible = True        # the data coordinates under the mouse
        return fig.canvas
    image = W.Image(format="png")

    def refresh():
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=72)
        image.value = buf.getvalue()

    refresh_callbacks.append(refresh)
    note = W.HTML("<b>Static preview</b>: run <code>%matplotlib widget</code> (ipympl) "
                  "before creating the picker to click in the images.")
    return W.VBox([note, image])


def _focus_canvas_js(css_class):
    """JavaScript that gives the keyboard focus to the ipympl canvas inside the element of
    class ``css_class`` (after a button click the focus is on the button, and keys would go
    to JupyterLab's own shortcuts: ``a`` inserts a cell, ``d d`` deletes one)."""
    sel = json.dumps(f".{css_class} .jupyter-matplotlib-canvas-div")
    return (f"(function(){{var t=document.querySelector({sel});"
            f"if(t){{t.focus({{preventScroll:true}});}}}})();")


class _Focus:
    """Gives the keyboard focus back to the canvas of a panel, through an Output widget that
    runs a line of JavaScript (JupyterLab runs it: the output is from this session)."""

    def __init__(self, css_class):
        import ipywidgets as W

        self.css_class = css_class
        self.output = W.Output(layout=W.Layout(height="0px", overflow="hidden"))
        self.count = 0

    def __call__(self):
        self.count += 1
        # set the output directly (not through the kernel's display hook), with the count in
        # it so that a repeated call is a new output the frontend runs again
        js = f"/* {self.count} */ " + _focus_canvas_js(self.css_class)
        self.output.outputs = ({"output_type": "display_data", "metadata": {},
                                "data": {"application/javascript": js,
                                         "text/plain": "(keyboard focus to the picker)"}},)
