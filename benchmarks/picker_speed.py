"""How quickly the correspondence picker responds on full-size SEM views.

Run:  python benchmarks/picker_speed.py

Two 1536×2048 views; times (Agg canvas, no browser) of a full figure draw zoomed out and
zoomed in, of a click in one view (the matched proposal in the other view plus the redraw),
and of one mouse move while dragging a point. In JupyterLab (ipympl) the browser adds the
PNG transfer of the figure; ipympl 0.10 cannot blit, so there a drag move costs a draw.
"""

from __future__ import annotations

import time

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
from matplotlib.backend_bases import MouseEvent  # noqa: E402

from semlab import widgets  # noqa: E402
from semlab.proposals import matching_refine  # noqa: E402


def send(fig, ax, name, xy):
    x, y = ax.transData.transform(xy)
    fig.canvas.callbacks.process(name, MouseEvent(name, fig.canvas, x, y, button=1))


def timed(fn, n=5):
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def main():
    from scipy import ndimage

    rng = np.random.default_rng(0)
    a = ndimage.gaussian_filter(rng.random((1536, 2048)), 2.0).astype(np.float32)
    b = ndimage.shift(a, (0.0, 2.5), order=1)
    picker = widgets.CorrespondencePicker([a, b], refine=matching_refine())
    view = widgets.PickerFigure(picker)
    fig, (a0, a1) = view.fig, view.axes
    fig.canvas.draw()
    for ax in view.axes:
        ax._semlab_screen_image.update()
    rows = [("full draw, zoomed out", timed(fig.canvas.draw))]

    def click():
        send(fig, a0, "button_press_event", (700.0, 600.0))
        send(fig, a0, "button_release_event", (700.0, 600.0))
        picker.cancel()

    rows.append(("click: matched proposal + redraw", timed(click)))
    send(fig, a0, "button_press_event", (700.0, 600.0))
    send(fig, a0, "button_release_event", (700.0, 600.0))
    send(fig, a1, "button_press_event", tuple(picker.pts[0, 1]))
    send(fig, a1, "button_release_event", tuple(picker.pts[0, 1]))
    start = picker.pts[0, 1].copy()
    send(fig, a1, "button_press_event", tuple(start))
    # the drag starts once the mouse has moved 3 screen px (about 15 image px zoomed out)
    send(fig, a1, "motion_notify_event", tuple(start + 30))
    k = iter(range(31, 130))
    rows.append(("drag: one mouse move", timed(lambda: send(fig, a1, "motion_notify_event",
                                                            tuple(start + next(k))))))
    assert view._drag is not None and view._drag["started"], "the timed moves were no drag"
    send(fig, a1, "button_release_event", tuple(start + 5))
    a0.set_xlim(600.5, 800.5)
    a0.set_ylim(700.5, 500.5)
    rows.append(("full draw, view 0 zoomed to 200×200 px", timed(fig.canvas.draw)))
    print("| two 1536×2048 views (Agg) | seconds |")
    print("|---|---|")
    for name, t in rows:
        print(f"| {name} | {t:.3f} |")


if __name__ == "__main__":
    main()
