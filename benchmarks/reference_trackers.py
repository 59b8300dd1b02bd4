"""In-script reference trackers for the tracking and drift benchmarks (not semlab).

The dense optical flows of ``accuracy_matrix.dense_flows`` (OpenCV DeepFlow, DIS medium and
DIS fine), computed **directly from the last frame to every frame** (no chaining, no
validity flag) and sampled bilinearly at the seeds: the positions an off-the-shelf dense
method gives at the same points, in the same run, on the same images. With a registration
(``semlab.registration.Registration``) frame k is first resampled into the last frame's
geometry (``warp_to_reference``) and the flow's end points are mapped back into frame k's
own pixels by its transform, so that a large stage drift does not defeat the flow's
pyramid: the reference then uses the same registration semlab tracked with, and the
comparison isolates the tracker.
"""

from __future__ import annotations

import numpy as np

from accuracy_matrix import _sample_flow, dense_flows
from semlab.registration import warp_to_reference

REFERENCE_TRACKERS = ("DeepFlow", "DIS medium", "DIS fine")


def reference_tracks(frames, seeds, registration=None, frames_to_do=None):
    """Positions of the seeds in every frame by each reference method.

    Parameters
    ----------
    frames : sequence of F (H, W) arrays, chronological (the last is the reference)
    seeds : (N, 2) array of (x, y) pixels in the last frame
    registration : Registration, optional
        Resample each frame into the last frame's geometry first (see the module doc).
    frames_to_do : iterable of int, optional
        Frames to compute (default all but the last); the others are NaN.

    Returns
    -------
    dict name -> (F, N, 2) array of (x, y) pixels in each frame's own pixels (the last
    frame holds the seeds).
    """
    F, seeds = len(frames), np.asarray(seeds, float)
    out = {name: np.full((F, len(seeds), 2), np.nan) for name in REFERENCE_TRACKERS}
    for name in out:
        out[name][-1] = seeds
    for k in (range(F - 1) if frames_to_do is None else frames_to_do):
        img = frames[k]
        if registration is not None:
            img = warp_to_reference(frames[k], registration.transforms[k])[0]
        flows, _ = dense_flows(frames[-1], img)
        for name in REFERENCE_TRACKERS:
            q = seeds + _sample_flow(flows[name], seeds)
            out[name][k] = q if registration is None else registration.transforms[k](q)
    return out


def rms(err, sel=None):
    """RMS of ``err`` (any shape) over ``sel`` (bool, same shape) and finite values; NaN
    when nothing is selected."""
    e = np.asarray(err, float)
    m = np.isfinite(e) if sel is None else (np.asarray(sel, bool) & np.isfinite(e))
    return float(np.sqrt(np.mean(e[m] ** 2))) if m.any() else np.nan
