"""Global registration of images: stage drift between the frames of a series.

Between fatigue blocks the stage is moved and brought back, so every frame of a series is
shifted by tens of pixels, slightly rotated and re-magnified, and the beam drifts slowly
while a frame is scanned (a row-dependent shift, to first order a shear). This module finds
one global 2D transform per frame -- features matched by SIFT and Lowe's ratio test, a
similarity or affine map by RANSAC, refined by intensity (enhanced correlation coefficient,
ECC) -- and it holds the one feature-matching helper of semlab (:func:`match_features`, with
:func:`semlab.transform2d.estimate_transform`), used by tracking and by the view-to-frame
registration.

Conventions: images are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)``
in pixels, x to the right, y down, origin at the centre of the top-left pixel (OpenCV).
Rotation angles are in degrees, positive from +x toward +y (clockwise on the screen, where
y points down).

References
----------
- D. G. Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 60 (2004).
- G. D. Evangelidis, E. Z. Psarakis, "Parametric image alignment using enhanced correlation
  coefficient maximization", IEEE TPAMI 30 (2008) -- ``cv2.findTransformECC``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from .displacement import _new_file
from .errors import GeometryError, SemlabError
from .tracking import _as_2d, normalize_frame
from .transform2d import MODELS, Transform2D, _check_model, estimate_transform, fit_transform

__all__ = [
    "Transform2D",
    "Registration",
    "MODELS",
    "DRIFT_CSV_COLUMNS",
    "to_uint8",
    "detect_features",
    "match_features",
    "fit_transform",
    "estimate_transform",
    "refine_ecc",
    "rigid_region_mask",
    "register_pair",
    "register_frames",
    "register_points",
    "warp_to_reference",
    "as_registration",
    "write_drift_csv",
    "read_drift_csv",
]

#: Columns of ``drift.csv``; then the diagnostics ``n_inliers, ecc`` and the full matrix.
DRIFT_CSV_COLUMNS = ("frame", "dx_px", "dy_px", "rotation_deg", "scale", "residual_px", "method")
_DRIFT_EXTRA = ("n_inliers", "ecc", "m00", "m01", "m02", "m10", "m11", "m12")


# ----------------------------------------------------------------------------- features

def to_uint8(img, name="the image"):
    """8-bit copy of an image for feature detection (0.5-99.5 % contrast stretch).

    A ``uint8`` image is returned as it is. Raises :class:`GeometryError` on a blank image.
    """
    a = np.asarray(img)
    if a.dtype == np.uint8 and a.ndim == 2:
        return a
    f01, blank = normalize_frame(_as_2d(a, name))
    if blank:
        raise GeometryError(f"{name} is blank (no contrast): it has no features to register")
    return np.round(f01 * 255.0).astype(np.uint8)


def detect_features(img, detector="sift", n_max=20000, name="the image"):
    """Keypoints and SIFT descriptors of an image.

    Parameters
    ----------
    img : (H, W) array (any dtype; see :func:`to_uint8`)
    detector : {"sift", "shi-tomasi"}
        SIFT keypoints (Lowe 2004), or Shi-Tomasi corners described by SIFT.
    n_max : int
        At most this many keypoints.

    Returns
    -------
    xy : (n, 2) array of (x, y) pixels
    descriptors : (n, 128) float32 array, or None when nothing was found
    """
    img8 = to_uint8(img, name)
    sift = cv2.SIFT_create(nfeatures=int(n_max))
    if detector == "sift":
        kp, des = sift.detectAndCompute(img8, None)
    elif detector == "shi-tomasi":
        pts = cv2.goodFeaturesToTrack(img8, maxCorners=int(n_max), qualityLevel=0.01, minDistance=4)
        if pts is None:
            return np.zeros((0, 2)), None
        kp = [cv2.KeyPoint(float(x), float(y), 8.0) for x, y in pts.reshape(-1, 2)]
        kp, des = sift.compute(img8, kp)
    else:
        raise GeometryError(f"detector must be 'sift' or 'shi-tomasi', got {detector!r}")
    xy = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return xy, des


def _match_descriptors(fa, fb, ratio, matcher="bf"):
    """Ratio-tested matches between two ``(xy, descriptors)`` feature sets."""
    (xa, da), (xb, db) = fa, fb
    if da is None or db is None or len(xa) < 2 or len(xb) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    if matcher == "flann":                    # randomised kd-trees: approximate, ~10x faster
        m = cv2.FlannBasedMatcher(dict(algorithm=1, trees=4), dict(checks=64))
        knn = m.knnMatch(np.float32(da), np.float32(db), k=2)
    else:
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    return (np.array([xa[m.queryIdx] for m in good], float).reshape(-1, 2),
            np.array([xb[m.trainIdx] for m in good], float).reshape(-1, 2))


def match_features(img0, img1, ratio=0.75, detector="sift", n_max=20000, cache=None,
                   matcher="bf"):
    """Feature correspondences between two images: descriptors matched with Lowe's ratio test.

    Parameters
    ----------
    img0, img1 : (H, W) arrays (any dtype, any size; a ``uint8`` image is used as it is)
    ratio : float
        Ratio-test threshold (Lowe 2004, sec. 7.1).
    detector : {"sift", "shi-tomasi", "both"}
    n_max : int
        Keypoints per image and detector.
    cache : dict, optional
        Keeps the features of ``img0`` between calls (pass the same dict with the same
        ``img0``).
    matcher : {"bf", "flann"}
        Exact brute-force nearest neighbours, or FLANN's approximate kd-trees (faster).

    Returns
    -------
    p0, p1 : (M, 2) arrays of (x, y) pixels in ``img0`` and ``img1`` (M may be 0).
    """
    dets = ["sift", "shi-tomasi"] if detector == "both" else [detector]
    src, dst = [np.zeros((0, 2))], [np.zeros((0, 2))]
    for d in dets:
        if cache is not None and d in cache:
            fa = cache[d]
        else:
            fa = detect_features(img0, d, n_max, "img0")
            if cache is not None:
                cache[d] = fa
        a, b = _match_descriptors(fa, detect_features(img1, d, n_max, "img1"), ratio, matcher)
        src.append(a)
        dst.append(b)
    return np.vstack(src), np.vstack(dst)


_ECC_MOTION = {"translation": cv2.MOTION_TRANSLATION, "similarity": cv2.MOTION_AFFINE,
               "affine": cv2.MOTION_AFFINE}


def refine_ecc(ref, img, init, model="affine", max_iter=100, eps=1e-6, gauss_size=1, mask=None):
    """Refine ``T`` (``ref`` pixels → ``img`` pixels) by maximising the enhanced correlation
    coefficient (Evangelidis & Psarakis 2008, ``cv2.findTransformECC``).

    The ECC is invariant to brightness and contrast changes. For ``model="similarity"`` an
    affine ECC is run and its nearest similarity (least squares over the pixels it was
    measured on: the image, or ``mask``) is returned.

    Parameters
    ----------
    ref, img : (H, W) arrays (contrast-stretched here)
    init : Transform2D
        Starting estimate (within a few pixels).
    model : {"translation", "similarity", "affine"}
    gauss_size : int
        Gaussian pre-smoothing kernel of OpenCV's ECC (odd; 1: none). Smoothing made ECC
        converge 2-4 px off on low-contrast synthetic frames whose topographic contrast
        differs from the reference (1 px: 0.03 px off).
    mask : (H, W) bool array, optional
        Pixels of ``ref`` the correlation is measured on (``cv2.findTransformECCWithMask``),
        e.g. the rigidly moving region of :func:`rigid_region_mask`; default all.

    Returns
    -------
    transform : Transform2D
    rho : float
        The final correlation coefficient.

    Raises
    ------
    GeometryError
        ECC did not converge.
    """
    _check_model(model)
    a = normalize_frame(_as_2d(ref, "ref"))[0]
    b = normalize_frame(_as_2d(img, "img"))[0]
    W = init.affine.astype(np.float32)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(max_iter), float(eps))
    h, w = a.shape
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != a.shape:
            raise GeometryError(f"the ECC mask has shape {mask.shape} but ref has {a.shape}")
        if mask.sum() < 100:
            raise GeometryError(f"the ECC mask has only {int(mask.sum())} pixels (need 100)")
    try:
        if mask is None:
            rho, W = cv2.findTransformECC(a, b, W, _ECC_MOTION[model], crit, None, int(gauss_size))
        else:
            rho, W = cv2.findTransformECCWithMask(a, b, mask.astype(np.uint8) * 255,
                                                  np.full(b.shape, 255, np.uint8), W,
                                                  _ECC_MOTION[model], crit, int(gauss_size))
    except cv2.error as exc:
        raise GeometryError(f"ECC refinement did not converge: {str(exc).strip().splitlines()[-1]}")
    T = Transform2D(W.astype(float))
    if model == "similarity":
        if mask is None:
            g = np.stack(np.meshgrid(np.linspace(0, w - 1, 8), np.linspace(0, h - 1, 8)),
                         -1).reshape(-1, 2)
        else:
            g = np.argwhere(mask)[::7, ::-1].astype(float)
        T = fit_transform(g, T(g), "similarity")
    return T, float(rho)


def rigid_region_mask(shape, p0, residual_px, threshold_px, radius_px=12.0):
    """The part of the reference image that moves with the inlier feature matches.

    Each pixel takes the class of its nearest matched feature: an inlier
    (``residual_px <= threshold_px``), a match that clearly moves otherwise
    (``residual_px > 2 threshold_px``; those in between are ambiguous and ignored); it is in
    the region when that feature is an inlier and at most ``radius_px`` away.

    Parameters
    ----------
    shape : (H, W) of the reference image
    p0 : (N, 2) array of (x, y) pixels of the matches in the reference image
    residual_px : (N,) array
        Transfer residual of each match under the transform, pixels.
    threshold_px : float
        Inlier threshold, pixels.
    radius_px : float
        Largest distance of a region pixel from an inlier, pixels.

    Returns
    -------
    (H, W) bool array
    """
    p0 = np.asarray(p0, float).reshape(-1, 2)
    r = np.asarray(residual_px, float)
    lab = np.zeros(shape, np.int8)              # 0: no feature, 1: inlier, 2: moves otherwise
    ij = np.clip(np.round(p0[:, ::-1]).astype(int), 0, np.array(shape) - 1)
    out, inl = r > 2 * threshold_px, r <= threshold_px
    lab[ij[out, 0], ij[out, 1]] = 2
    lab[ij[inl, 0], ij[inl, 1]] = 1
    if not inl.any():
        return np.zeros(shape, bool)
    dist, (ii, jj) = ndimage.distance_transform_edt(lab == 0, return_indices=True)
    return (lab[ii, jj] == 1) & (dist <= radius_px)


# ----------------------------------------------------------------------------- pairs, series

def register_pair(ref, img, model="affine", ratio=0.75, ransac_threshold_px=2.0, min_inliers=10,
                  ecc=True, init=None, features=None, n_max=5000, rigid_threshold_px=0.3,
                  rigid_iterations=2):
    """Global transform from ``ref`` pixels to ``img`` pixels: features, RANSAC, then ECC,
    measured on the part of the image that moves rigidly.

    A fatigued surface is not rigid: slip bands shift the strips between them by up to a few
    pixels against each other, so a transform fitted to all features (or an ECC over the
    whole image) averages the strips' motions, and the average depends on where the
    features happen to be. Here the transform is that of the **largest rigidly moving
    region** (the stage drift composed with that region's own motion):

    1. SIFT features matched by the ratio test (FLANN), a ``model`` transform by RANSAC
       with the loose ``ransac_threshold_px`` and least squares on the inliers
       (:func:`estimate_transform`);
    2. RANSAC again on those inliers with the tight ``rigid_threshold_px`` (about the
       features' own localisation error): the largest set that moves as one;
    3. refined by intensity (:func:`refine_ecc`) on that set's region only
       (:func:`rigid_region_mask`), the refinement kept only when it stays within
       ``max(0.2, 3 σ, ransac_threshold_px / 2)`` px of the feature estimate everywhere in
       the image, ``σ`` its predicted error (``2 × residual / √n_inliers``): ECC can lock onto a wrong optimum
       when the contrast differs between the images, the features do not;
    4. ``rigid_iterations`` times: the inliers and their region selected again under the
       ECC transform (finer than the features' own estimate), and ECC again.

    Parameters
    ----------
    ref, img : (H, W) arrays
    model : {"translation", "similarity", "affine"}
    ratio, ransac_threshold_px, min_inliers
        See :func:`match_features` / :func:`estimate_transform`.
    ecc : bool
        Refine the feature estimate by intensity.
    init : Transform2D, optional
        Used (and refined by ECC, over the whole image) when the features fail, e.g. the
        transform chained through the neighbouring frame.
    features : list of 2 (xy, descriptors) tuples, optional
        Precomputed :func:`detect_features` of ``ref`` and ``img``.
    n_max : int
        SIFT keypoints per image.
    rigid_iterations : int
        Re-selections of the rigid region from the ECC estimate (stage 4.).
    rigid_threshold_px : float or None
        Inlier threshold of the rigid-region stage (2.), pixels; kept only when it leaves
        ``min_inliers``. None: one RANSAC at ``ransac_threshold_px`` and ECC on the whole
        image.

    Returns
    -------
    dict with ``transform`` (Transform2D), ``residual_px`` (RMS transfer residual of the
    feature inliers under the final transform; NaN without features), ``n_inliers``,
    ``ecc`` (final correlation coefficient or NaN), ``method`` (``"features"``,
    ``"features+ecc"``, ``"chained+ecc"``, ``"chained"``) and ``region_fraction`` (the
    fraction of ``ref`` the ECC was measured on; NaN without ECC).

    Raises
    ------
    GeometryError
        Neither the features nor ``init`` gave a transform.
    """
    fa, fb = features if features is not None else (detect_features(ref, n_max=n_max, name="ref"),
                                                    detect_features(img, n_max=n_max, name="img"))
    p0 = p1 = np.zeros((0, 2))
    mask = None
    try:
        q0, q1 = _match_descriptors(fa, fb, ratio, "flann")
        T, inl = estimate_transform(q0, q1, model, ransac_threshold_px, min_inliers)
        thr = ransac_threshold_px
        if rigid_threshold_px is not None and rigid_threshold_px < ransac_threshold_px:
            try:
                Tr, inr = estimate_transform(q0[inl], q1[inl], model, rigid_threshold_px,
                                             min_inliers)
                T, thr = Tr, rigid_threshold_px
                inl = np.flatnonzero(inl)[inr]
            except GeometryError:
                pass                     # too few at the tight threshold: keep the loose fit
        p0, p1 = q0[inl], q1[inl]
        method = "features"
        r = np.sqrt(np.mean(np.sum((T(p0) - p1) ** 2, axis=1)))
        tol = max(0.2, 3 * 2 * r / np.sqrt(len(p0)))
        if thr < ransac_threshold_px:
            mask = rigid_region_mask(np.shape(ref), q0, np.linalg.norm(T(q0) - q1, axis=1), thr)
            # on the rigid region alone ECC cannot drift to another strip's motion: it only
            # has to stay within the loose threshold of the features (few features, e.g. on
            # an early low-contrast frame, leave their estimate 0.3-0.5 px off)
            tol = max(tol, 0.5 * ransac_threshold_px)
    except GeometryError:
        if init is None:
            raise
        T, method, tol = init, "chained", 3.0
    rho = np.nan
    frac = np.nan
    T_feat = T
    for it in range(1 + (int(rigid_iterations) if ecc and mask is not None else 0)):
        if not ecc:
            break
        try:
            Te, rho_e = refine_ecc(ref, img, T, model, mask=mask)
        except GeometryError:
            break
        if Te.distance(T_feat, np.shape(ref)) > tol:
            break
        T, rho = Te, rho_e
        method = method if method.endswith("+ecc") else method + "+ecc"
        frac = 1.0 if mask is None else float(mask.mean())
        if mask is None or it == int(rigid_iterations):
            break
        # the region again, from the intensity estimate (finer than the features' own)
        r = np.linalg.norm(T(q0) - q1, axis=1)
        if (r <= thr).sum() < min_inliers:
            break
        p0, p1 = q0[r <= thr], q1[r <= thr]
        mask = rigid_region_mask(np.shape(ref), q0, r, thr)
    res = float(np.sqrt(np.mean(np.sum((T(p0) - p1) ** 2, axis=1)))) if len(p0) else np.nan
    return {"transform": T, "residual_px": res, "n_inliers": int(len(p0)), "ecc": float(rho),
            "method": method, "region_fraction": frac}


@dataclass
class Registration:
    """Per-frame global transforms of a series, from the reference frame into each frame.

    Attributes
    ----------
    transforms : list of F Transform2D
        ``transforms[k]`` maps reference-frame pixels (x, y) to pixels of frame k (identity
        for the reference); a material point at ``p`` in the reference geometry is seen at
        ``transforms[k](p)`` in frame k (up to its own deformation).
    residual_px : (F,) float array
        RMS transfer residual of the feature inliers, pixels (NaN: no features used).
    n_inliers : (F,) int array
    ecc : (F,) float array
        Final ECC correlation coefficient (NaN: not refined).
    method : (F,) array of str
        How each transform was found: ``reference``, ``features``, ``features+ecc``,
        ``chained+ecc`` (started from the neighbour's chain), ``chained``, ``none``.
    model : str
    reference : int
    shape : (H, W)
    """

    transforms: list
    residual_px: np.ndarray
    n_inliers: np.ndarray
    ecc: np.ndarray
    method: np.ndarray
    model: str = "similarity"
    reference: int = -1
    shape: tuple = (0, 0)
    params: dict = field(default_factory=dict)

    @property
    def center(self):
        h, w = self.shape
        return ((w - 1) / 2.0, (h - 1) / 2.0)

    def table(self):
        """Rows of ``drift.csv`` as dicts (shift of the image centre, rotation about it)."""
        rows = []
        for k, T in enumerate(self.transforms):
            p = T.params(self.center)
            m = T.affine
            rows.append({"frame": k, **p, "residual_px": float(self.residual_px[k]),
                         "method": str(self.method[k]), "n_inliers": int(self.n_inliers[k]),
                         "ecc": float(self.ecc[k]),
                         **{f"m{i}{j}": float(m[i, j]) for i in range(2) for j in range(3)}})
        return rows

    def between(self, src, dst):
        """Transform of frame ``src`` pixels into frame ``dst`` pixels."""
        return self.transforms[dst] @ self.transforms[src].inverse()

    def carry_warps(self, warps, src, dst):
        """Subset warps ``(u, ux, uy, v, vx, vy)`` (N, 6) from the reference into frame
        ``src``, carried into frame ``dst``: their gradient part ``I + ∇u`` is multiplied by
        the linear part of :meth:`between` (the translation is left as it is)."""
        w = np.array(warps, float)
        L = self.between(src, dst).matrix[:2, :2]
        A = np.eye(2) + w[:, [1, 2, 4, 5]].reshape(-1, 2, 2)
        w[:, [1, 2, 4, 5]] = (L @ A - np.eye(2)).reshape(-1, 4)
        return w

    def to_frames(self, xy):
        """(F, N, 2) reference-geometry positions → each frame's own pixels."""
        return np.stack([T(p) for T, p in zip(self.transforms, np.asarray(xy, float))])

    def to_reference(self, xy, frames, part="rigid"):
        """Points in their frames' own pixels → the reference geometry.

        Parameters
        ----------
        xy : (N, 2) array of (x, y) pixels, point i in frame ``frames[i]``
        frames : (N,) int array of frame indices
        part : {"rigid", "full"}
            Remove only the rigid-body part (shift of the image centre and rotation about it)
            of each frame's transform, or the whole transform (also scale and shear).

        Returns
        -------
        (N, 2) array of (x, y) pixels.
        """
        xy = np.asarray(xy, float)
        out = np.full_like(xy, np.nan)
        for k in np.unique(frames):
            sel = np.asarray(frames) == k
            T = self.transforms[int(k)]
            T = T.rigid(self.center) if part == "rigid" else T
            out[sel] = T.inverse()(xy[sel])
        return out


def register_frames(frames, model="similarity", reference=-1, ecc=True, ratio=0.75,
                    ransac_threshold_px=2.0, min_inliers=10, n_max=5000, progress=False,
                    rigid_threshold_px=0.3, rigid_iterations=2):
    """Register every frame of a series to its neighbour and to the reference frame.

    For each frame ``k`` (from the reference backwards, then forwards):

    1. **Reference.** Features of frame ``k`` matched directly with the reference frame
       (SIFT, ratio test, RANSAC ``model``; :func:`register_pair`), so errors do not
       accumulate along a chain.
    2. **Neighbour.** When that finds too few consistent matches: frame ``k`` registered to
       its already registered neighbour (``k + 1`` before the reference, ``k - 1`` after
       it), chained with the neighbour's transform.
    3. **Intensity.** ECC refinement against the reference (:func:`refine_ecc`), checked
       against the feature estimate.

    Parameters
    ----------
    frames : sequence of F (H, W) arrays, chronological
    model : {"similarity", "affine", "translation"}
        ``"similarity"`` (a stage: shift, rotation, magnification) by default; ``"affine"``
        also absorbs a linear scan drift (a shear) but, fitted to features on a surface
        whose own motion is non-uniform (slip bands), it can take a spurious shear/stretch.
    reference : int
        Index of the reference frame (default the last, the tracking reference).
    ecc : bool
        Refine each transform by intensity.
    ratio, ransac_threshold_px, min_inliers, n_max, rigid_threshold_px, rigid_iterations
        See :func:`register_pair`: each transform is that of the largest rigidly moving
        region (stage drift composed with that region's own motion), found by RANSAC at
        ``rigid_threshold_px`` and ECC on that region.
    progress : bool
        tqdm progress bar.

    Returns
    -------
    Registration

    Raises
    ------
    GeometryError
        Frames of different sizes, an unknown model, or a blank reference frame.
    """
    _check_model(model)
    frames = [_as_2d(f, f"frame {i}") for i, f in enumerate(frames)]
    F = len(frames)
    if F == 0:
        raise GeometryError("no frames to register")
    shape = frames[0].shape
    for i, f in enumerate(frames):
        if f.shape != shape:
            raise GeometryError(f"frame {i} has shape {f.shape} but frame 0 has {shape}: all frames "
                                "of a series must have the same size")
    ref = int(reference) % F
    if normalize_frame(frames[ref])[1]:
        raise GeometryError(f"the reference frame {ref} is blank: nothing to register to")
    Ts = [None] * F
    Ts[ref] = Transform2D.identity()
    res = np.full(F, np.nan)
    res[ref] = 0.0
    nin = np.zeros(F, int)
    rho = np.full(F, np.nan)
    rho[ref] = 1.0
    meth = np.array(["reference"] * F, dtype=object)
    order = list(range(ref - 1, -1, -1)) + list(range(ref + 1, F))
    if progress:
        from tqdm.auto import tqdm
        order = tqdm(order, desc="registering frames", unit="frame")
    feats = {}

    def feat(i):
        if i not in feats:
            feats[i] = detect_features(frames[i], n_max=n_max, name=f"frame {i}")
        return feats[i]

    kw = dict(model=model, ratio=ratio, ransac_threshold_px=ransac_threshold_px,
              min_inliers=min_inliers, rigid_threshold_px=rigid_threshold_px,
              rigid_iterations=rigid_iterations)
    for k in order:
        nb = k + 1 if k < ref else k - 1
        if normalize_frame(frames[k])[1]:
            Ts[k], meth[k] = Ts[nb], "none"            # blank: nothing to measure
            continue
        try:
            r = register_pair(frames[ref], frames[k], ecc=ecc, features=(feat(ref), feat(k)), **kw)
        except GeometryError:
            # too few matches with the reference: chain through the neighbour, then ECC
            chain = Ts[nb]
            try:
                chain = register_pair(frames[nb], frames[k], ecc=False, features=(feat(nb), feat(k)),
                                      **kw)["transform"] @ Ts[nb]
            except GeometryError:
                pass
            r = register_pair(frames[ref], frames[k], ecc=ecc, init=chain,
                              features=(feat(ref), feat(k)), **kw)
        Ts[k] = r["transform"]
        res[k], nin[k], rho[k], meth[k] = r["residual_px"], r["n_inliers"], r["ecc"], r["method"]
    return Registration(transforms=Ts, residual_px=res, n_inliers=nin, ecc=rho,
                        method=meth.astype(str), model=model, reference=ref, shape=shape,
                        params=dict(ecc=ecc, ratio=ratio, ransac_threshold_px=ransac_threshold_px,
                                    min_inliers=min_inliers, n_max=n_max,
                                    rigid_threshold_px=rigid_threshold_px,
                                    rigid_iterations=rigid_iterations))


def warp_to_reference(img, transform, shape=None, margin_px=0, order=3):
    """Resample a frame into the reference geometry: ``out(p) = img(transform(p))``.

    Parameters
    ----------
    img : (H, W) array
    transform : Transform2D
        Reference pixels → ``img`` pixels.
    shape : (H, W), optional
        Output shape (default ``img``'s).
    margin_px : float
        The returned footprint excludes pixels closer than this to the edge of ``img``.
    order : int
        Spline order of the interpolation (3: cubic B-spline, scipy.ndimage).

    Returns
    -------
    out : (H, W) float64 array; where ``transform(p)`` falls outside ``img`` its nearest
        edge pixel (an edge-replicated smear: a constant or NaN fill there made pyramidal LK
        fail on a third of the tracks of small frames, its coarse levels seeing the step)
    footprint : (H, W) bool array, True where ``transform(p)`` lies at least ``margin_px``
        inside ``img``.
    """
    a = np.asarray(img, float)
    h, w = a.shape if shape is None else shape
    M = transform.matrix
    # ndimage works in (row, col): swap x and y on both sides
    P = np.array([[0, 1], [1, 0]])
    lin = P @ M[:2, :2] @ P
    off = P @ M[:2, 2]
    fill = np.nanmedian(a) if np.isfinite(a).any() else 0.0
    out = ndimage.affine_transform(np.where(np.isfinite(a), a, fill), lin, offset=off,
                                   output_shape=(h, w), order=order, mode="nearest")
    yy, xx = np.mgrid[0:h, 0:w]
    q = transform(np.column_stack([xx.ravel(), yy.ravel()]).astype(float))
    H, W = a.shape
    m = float(margin_px)
    foot = ((q[:, 0] >= m) & (q[:, 0] <= W - 1 - m) & (q[:, 1] >= m) & (q[:, 1] <= H - 1 - m))
    return out, foot.reshape(h, w)


def as_registration(register, frames):
    """The registration tracking uses: computed, or a precomputed one checked.

    Parameters
    ----------
    register : {"similarity", "affine", "translation", True} or Registration
        Model to estimate with :func:`register_frames` (reference = last frame; True:
        ``"similarity"``), or a precomputed registration of these frames.
    frames : sequence of F (H, W) arrays

    Returns
    -------
    Registration
    """
    if isinstance(register, Registration):
        if len(register.transforms) != len(frames) or register.reference != len(frames) - 1:
            raise GeometryError(f"the registration has {len(register.transforms)} frames with "
                                f"reference {register.reference}; tracking needs one for these "
                                f"{len(frames)} frames with the last frame as reference")
        return register
    return register_frames(frames, model="similarity" if register is True else register)


def register_points(src_img, dst_img, pts, model="affine", ratio=0.75, ransac_threshold_px=2.0,
                    min_matches=6):
    """Map points of one image into another by SIFT matching and a RANSAC 2D transform.

    Used to bring points found in end-state stereo view 0 into the last frame of the series
    (the views may differ by stage tilt, i.e. x-scaling by cos θ, shift and scale).

    Parameters
    ----------
    src_img, dst_img : (H, W) arrays
    pts : (N, 2) array of (x, y) pixels in ``src_img``
    model : {"affine", "similarity", "translation"}
    ratio : float
        Lowe's ratio-test threshold.
    ransac_threshold_px : float
        RANSAC inlier threshold, pixels.
    min_matches : int
        Fewest inlier matches accepted.

    Returns
    -------
    mapped : (N, 2) array of (x, y) pixels in ``dst_img``
    A : (2, 3) array with ``[x', y']ᵀ = A @ [x, y, 1]ᵀ``
    residual_px : float
        RMS transfer residual of the RANSAC inlier matches, pixels.

    Raises
    ------
    GeometryError
        Too few matches (different scenes, blank image) or unknown model.
    """
    _check_model(model)
    pts = np.asarray(pts, float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise GeometryError(f"pts must be an (N, 2) array of (x, y) pixels, got shape {pts.shape}")
    p0, p1 = match_features(to_uint8(src_img, "src_img"), to_uint8(dst_img, "dst_img"), ratio=ratio)
    T, inl = estimate_transform(p0, p1, model, ransac_threshold_px, min_matches)
    r = T(p0[inl]) - p1[inl]
    return T(pts), T.affine, float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


# ----------------------------------------------------------------------------- drift.csv

def write_drift_csv(path, registration, overwrite=False):
    """Write ``drift.csv``: one row per frame (columns :data:`DRIFT_CSV_COLUMNS`, then
    ``n_inliers, ecc`` and the transform matrix ``m00 .. m12``).

    ``dx_px, dy_px`` are the shift of the image centre from the reference frame into the
    frame, ``rotation_deg`` the rotation about it (positive from +x toward +y), ``scale``
    the magnification relative to the reference, ``residual_px`` the RMS transfer residual
    of the feature inliers and ``method`` how the transform was found.

    Raises
    ------
    SemlabError
        ``path`` exists and ``overwrite`` is False.
    """
    path = _new_file(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(DRIFT_CSV_COLUMNS + _DRIFT_EXTRA))
        w.writeheader()
        for r in registration.table():
            w.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in r.items()})
    return path


def read_drift_csv(path):
    """Read ``drift.csv`` (or ``truth/drift.csv``) into a dict of 1D arrays."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise SemlabError(f"{path}: no rows")
    out = {}
    for k in rows[0]:
        vals = [r[k] for r in rows]
        try:
            out[k] = np.array([float(v) if v != "" else np.nan for v in vals])
        except ValueError:
            out[k] = np.array(vals)
    return out
