"""Monte-Carlo accuracy of vanishing-point calibration (semlab.vanishing) vs click noise.

Two scenes, each seen in two views, the second rotated by 10° about the camera y axis:

- ``grid box``: a unit box 2.5 units from a 2000 px camera, 10 grid lines per face and
  direction (20 segments per family, 300-700 px long), strong perspective;
- ``synth block``: the calibration block of ``semlab.synth.render_block`` (its visible edges
  only, 3 segments per family, weak perspective), at stage tilts -5° and +5°.

Gaussian noise of the given standard deviation is added to every end point. Prints a
markdown table of the focal-length error (%) and the relative-rotation error (deg), median
and 95th percentile over the trials, also with the principal point fixed at its true value.

Run: ``.venv/bin/python benchmarks/vanishing_accuracy.py [n_trials]``
"""

import sys
import time

import numpy as np

from semlab import vanishing as vn
from semlab.camera import project_perspective, rotation_about_axis
from semlab.errors import GeometryError

K_BOX = np.array([[2000.0, 0.0, 1010.0], [0.0, 2000.0, 770.0], [0.0, 0.0, 1.0]])
R_BASE = rotation_about_axis([1, 0, 0], np.deg2rad(-30)) @ rotation_about_axis([0, 1, 0], np.deg2rad(40))
RY10 = rotation_about_axis([0, 1, 0], np.deg2rad(10))


def grid_box_views(noise_px, rng, n=11, dist=2.5):
    """Two views of the gridded unit box; returns (views, K, relative rotation)."""
    views = []
    for R in (R_BASE, RY10 @ R_BASE):
        t = np.array([0.0, 0.0, dist]) - R @ np.full(3, 0.5)
        fams = {}
        for along in range(3):
            P, Q = [], []
            for face in [f for f in range(3) if f != along]:
                across = 3 - along - face
                for s in np.linspace(0, 1, n)[1:]:
                    p = np.zeros(3)
                    p[across] = s
                    q = p.copy()
                    q[along] = 1.0
                    P.append(p)
                    Q.append(q)
            S = np.hstack([project_perspective(np.array(P), K_BOX, R, t),
                           project_perspective(np.array(Q), K_BOX, R, t)])
            fams["xyz"[along]] = S + rng.normal(0.0, noise_px, S.shape)
        views.append(fams)
    return views, K_BOX, RY10


def synth_block_views(noise_px, rng):
    """Two views of semlab.synth's calibration block at tilts -5°, +5°."""
    from semlab.synth import render_block

    views, Rs = [], []
    for tilt in (-5.0, 5.0):
        _, fams, K, R, _ = render_block(tilt, (384, 512), line_noise_px=noise_px, rng=rng)
        views.append(fams)
        Rs.append(R)
    return views, K, Rs[1] @ Rs[0].T


def trial_errors(make, noise_px, n_trials, seed, known_pp):
    rng = np.random.default_rng(seed)
    f_err, r_err, failed = [], [], 0
    for _ in range(n_trials):
        views, K, R_rel = make(noise_px, rng)
        try:
            cal = vn.calibrate_views(views, principal_point=K[:2, 2] if known_pp else None)
        except GeometryError:
            failed += 1
            continue
        f_err.append(abs(cal.focal_px / K[0, 0] - 1.0) * 100.0)
        r_err.append(vn.axis_angle(cal.relative_R[1] @ R_rel.T)[1])
    return np.array(f_err), np.array(r_err), failed


def main(n_trials=200):
    scenes = [("grid box", grid_box_views)]
    try:
        from semlab.synth import render_block  # noqa: F401
    except ImportError:
        render_block = None
    if render_block is not None:
        scenes.append(("synth block", synth_block_views))
    print(f"Vanishing-point calibration, {n_trials} trials per row (median / 95th percentile)\n")
    print("| scene | principal point | noise px | focal err % | rotation err deg | failed |")
    print("|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    calls = 0
    for name, make in scenes:
        for known_pp in (False, True):
            for noise in (0.0, 0.5, 1.0, 2.0):
                f, r, failed = trial_errors(make, noise, n_trials, 0, known_pp)
                calls += n_trials
                fs = f"{np.median(f):.3g} / {np.percentile(f, 95):.3g}" if len(f) else "-"
                rs = f"{np.median(r):.3g} / {np.percentile(r, 95):.3g}" if len(r) else "-"
                pp = "known" if known_pp else "estimated"
                print(f"| {name} | {pp} | {noise:g} | {fs} | {rs} | {failed} |")
    dt = time.perf_counter() - t0
    print(f"\n{1e3 * dt / calls:.2f} ms per two-view calibration (scene generation included)")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 200)
