"""The synthetic calibration block: a box seen by a perspective camera of known K and R.

One image per stereo tilt with the visible edges and ruled grid lines of the box, as lines for
:mod:`semlab.vanishing` (plus click noise). Used by :func:`semlab.synth.make_experiment`; all
names are re-exported by :mod:`semlab.synth`.
"""

from __future__ import annotations

import numpy as np

from .camera import project_perspective, rotation_about_axis

__all__ = ["BOX_DIMS", "GRID_FRACTIONS", "block_camera", "render_block"]

BOX_DIMS = (40.0, 30.0, 20.0)
#: Fractions of a face at which grid lines are ruled on the block.
GRID_FRACTIONS = tuple(np.linspace(0.1, 0.9, 9))


def block_camera(tilt_deg, shape, focal_px=None):
    """True K, R, t of the block view at stage tilt ``tilt_deg``.

    World frame: the box's edges along x, y, z (z up out of the stage). The base orientation
    looks at a corner so that three faces are visible; the stage tilt is a rotation about the
    camera's y axis applied after it.
    """
    h, w = shape
    # a short focal length (strong perspective) puts the vanishing points near the image, which
    # is what makes them measurable; the box fills most of the image
    focal_px = 1.37 * w if focal_px is None else focal_px
    K = np.array([[focal_px, 0, (w - 1) / 2 + 0.014 * w], [0, focal_px, (h - 1) / 2 + 0.045 * h],
                  [0, 0, 1.0]])
    r_base = (rotation_about_axis([1, 0, 0], np.deg2rad(-120.0))
              @ rotation_about_axis([0, 0, 1], np.deg2rad(35.0)))
    R = rotation_about_axis([0, 1, 0], np.deg2rad(tilt_deg)) @ r_base
    centre = np.array(BOX_DIMS) / 2
    t = np.array([0.0, 0.0, 92.0]) - R @ centre
    return K, R, t


def _box_geometry():
    lx, ly, lz = BOX_DIMS
    corners = np.array([[i * lx, j * ly, k * lz] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    edges = {"x": [], "y": [], "z": []}
    for a in range(8):
        for b in range(a + 1, 8):
            d = np.abs(corners[a] - corners[b])
            if np.count_nonzero(d) == 1:
                edges["xyz"[int(np.argmax(d))]].append((a, b))
    faces = []
    for axis in range(3):
        for val in (0, 1):
            idx = [i for i in range(8) if (corners[i][axis] > 0) == bool(val)]
            # order the 4 corners around the face
            other = [k for k in range(3) if k != axis]
            ring = sorted(idx, key=lambda i: np.arctan2(corners[i][other[1]] - BOX_DIMS[other[1]] / 2,
                                                        corners[i][other[0]] - BOX_DIMS[other[0]] / 2))
            normal = np.zeros(3)
            normal[axis] = 1 if val else -1
            faces.append((ring, normal))
    return corners, edges, faces


def render_block(tilt_deg, shape, line_noise_px=1.0, rng=None):
    """Render the calibration block and return its visible edges grouped by direction.

    Returns
    -------
    image : (H, W) uint8
    families : dict name -> (M, 4) array of noisy segments (x1, y1, x2, y2) in pixels
    K, R, t : true camera
    """
    import cv2

    rng = np.random.default_rng() if rng is None else rng
    K, R, t = block_camera(tilt_deg, shape)
    corners, edges, faces = _box_geometry()
    img_pts = project_perspective(corners, K, R, t)
    cam_centre = -R.T @ t
    visible_faces = []
    img = np.full(shape, 40, np.uint8)
    for ring, normal in faces:
        face_centre = corners[ring].mean(axis=0)
        if np.dot(normal, cam_centre - face_centre) > 0:
            visible_faces.append(set(ring))
            shade = int(110 + 120 * abs(normal @ np.array([0.3, 0.5, 0.8])))
            cv2.fillPoly(img, [np.round(img_pts[ring] * 16).astype(np.int32)], shade,
                         lineType=cv2.LINE_AA, shift=4)
    # visible edges, plus a grid ruled on the visible faces (as on a real calibration block):
    # every segment is the image of a 3D line along x, y or z
    segs3d = {name: [(corners[a], corners[b]) for a, b in pairs
                     if any(a in f and b in f for f in visible_faces)]
              for name, pairs in edges.items()}
    dims = np.array(BOX_DIMS)
    for ring, normal in faces:
        if set(ring) not in visible_faces:
            continue
        axis = int(np.argmax(np.abs(normal)))
        level = dims[axis] if normal[axis] > 0 else 0.0
        b_ax, c_ax = [k for k in range(3) if k != axis]
        for along, across in ((b_ax, c_ax), (c_ax, b_ax)):
            for frac in GRID_FRACTIONS:
                p = np.zeros(3)
                p[axis] = level
                p[across] = frac * dims[across]
                q = p.copy()
                q[along] = dims[along]
                segs3d["xyz"[along]].append((p, q))
    families = {}
    for name, lst in segs3d.items():
        out = []
        for p3, q3 in lst:
            p, q = project_perspective(np.array([p3, q3]), K, R, t)
            cv2.line(img, tuple(np.round(p * 16).astype(int)), tuple(np.round(q * 16).astype(int)),
                     255, 1, cv2.LINE_AA, shift=4)
            # clicked end points: a little inside the ends, with click noise
            p_in = p + 0.05 * (q - p)
            q_in = q - 0.05 * (q - p)
            out.append(np.concatenate([p_in, q_in]) + rng.normal(0, line_noise_px, 4))
        families[name] = np.array(out)
    return img, families, K, R, t
