"""Experiment folders: ``experiment.toml`` and the images and annotations it names.

An experiment folder looks like::

    my_experiment/experiment.toml
      name = "..."
      pixel_size_um = 0.03          # optional when the images carry SEM metadata
      [stereo]
      views = ["end_state/a.tif", "end_state/b.tif"]      # 2 or more
      tilt_deg = [-5.0, 5.0]        # optional stage tilts (about the image y axis)
      camera = "affine"             # or "perspective"; default affine
      correspondences = "annotations/correspondences.csv" # optional
      lines = "annotations/lines.json"                    # optional
      reference_region = [x0, y0, x1, y1]  # optional, view-0 px; or [[x, y], ...] or "mask.png"
      reference_points = [[x, y], [x, y], [x, y]]         # optional three-point levelling
      [series]
      frames = ["series/f00.tif", ...]   # or a glob; chronological, earliest first
      cycles = [...]                # optional, one per frame
      minutes = [...]               # optional, one per frame
      [metrology]
      regions = { band_1 = [x0, y0, x1, y1], grain = [[x, y], ...], pit = "masks/pit.png" }
                                    # optional named regions of view 0 (as reference_region)

Paths are relative to the TOML file. ``[stereo]`` and ``[series]`` are each optional but not
both absent. Values in the TOML override the SEM metadata of the images; a disagreement is
reported as a warning and kept in :attr:`Experiment.notes`.

:func:`load` validates everything that can be checked without heavy computation and raises
:class:`~semlab.errors.ExperimentError` naming the file, the key and the fix.
"""

from __future__ import annotations

import difflib
import glob as _glob
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ExperimentError, SemlabWarning
from .io import IMAGE_SUFFIXES, read_image, read_text

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

TOML_NAME = "experiment.toml"
TOP_KEYS = {"name", "description", "pixel_size_um", "stereo", "series", "metrology"}
METROLOGY_KEYS = {"regions"}
STEREO_KEYS = {"views", "tilt_deg", "camera", "correspondences", "lines", "reference_region",
               "reference_points", "tilt_order"}
#: ``[stereo] tilt_order``: how estimated tilts run with the views' order (the sign of the
#: heights, which the images cannot tell; :func:`semlab.reconstruct.estimate_tilts`)
TILT_ORDERS = ("increasing", "decreasing")
SERIES_KEYS = {"frames", "cycles", "minutes"}
CAMERAS = ("affine", "perspective")
#: Relative disagreement between TOML and metadata pixel sizes that is reported.
PIXEL_SIZE_RTOL = 0.01
#: Disagreement in degrees between TOML and metadata tilts that is reported.
TILT_ATOL_DEG = 0.05
#: Pixel sizes an SEM can have, µm/px (10 pm to 100 µm per pixel); others are refused.
PIXEL_SIZE_RANGE_UM = (1e-5, 100.0)
#: Largest stage tilt accepted, degrees (|tilt| must be smaller; SEM stages reach ~70°).
MAX_TILT_DEG = 80.0
#: Smallest image side accepted, pixels: automatic matching needs a 21 px window, its search
#: range and a border on both sides (33 px) and room for a grid of points (below ~48 px it
#: finds none); any SEM image is far larger.
MIN_IMAGE_PX = 64


@dataclass
class StereoSpec:
    """The ``[stereo]`` table: end-state views at two or more stage tilts.

    Attributes
    ----------
    view_paths : list of Path
    tilt_deg : list of float or None
        Stage tilt of each view in degrees, from the TOML or the image metadata; None when
        neither gives all of them (then tilts must be estimated, which needs 3+ views).
    tilt_source : str
        ``"experiment"``, ``"metadata"`` or ``"unknown"``.
    camera : str
        ``"affine"`` (default) or ``"perspective"``.
    correspondences_path, lines_path : Path or None
    shape : (H, W)
        Image-area size shared by all views.
    reference_region : list or Path or None
        Where heights are measured from (view-0 pixels): a rectangle ``[x0, y0, x1, y1]``,
        a polygon ``[[x, y], ...]`` or a mask image path; None: the dominant flat surface
        (see :func:`semlab.surface.reference_surface`).
    reference_points : (3, 2) list or None
        Three view-0 pixels ``[x, y]`` the reference plane goes through.
    tilt_order : str
        ``"increasing"`` (default) or ``"decreasing"``: how the stage tilt runs with the
        views' order, used where the tilts are estimated (it fixes the sign of the heights,
        which the images cannot tell: the Necker reversal ``θ → -θ, z → -z``).
    """

    view_paths: list
    tilt_deg: list | None
    tilt_source: str
    camera: str = "affine"
    correspondences_path: Path | None = None
    lines_path: Path | None = None
    shape: tuple = (0, 0)
    reference_region: object = None
    reference_points: list | None = None
    tilt_order: str = "increasing"


@dataclass
class SeriesSpec:
    """The ``[series]`` table: frontal frames during the test, earliest first.

    Attributes
    ----------
    frame_paths : list of Path
        Chronological (frame 0 is the earliest).
    cycles, minutes : (F,) float arrays or None
    shape : (H, W)
    """

    frame_paths: list
    cycles: np.ndarray | None = None
    minutes: np.ndarray | None = None
    shape: tuple = (0, 0)


@dataclass
class Experiment:
    """A validated experiment. Images are read lazily and cached.

    Attributes
    ----------
    name : str
    toml_path : Path
    root : Path
        Folder of the TOML file; relative paths are resolved against it.
    pixel_size_um : float
    pixel_size_source : str
        ``"experiment"`` (the TOML) or ``"metadata:<file name>"``.
    stereo : StereoSpec or None
    series : SeriesSpec or None
    notes : list of str
        Disagreements between the TOML and the image metadata, and other remarks.
    metrology_regions : dict
        ``[metrology] regions``: name → rectangle ``[x0, y0, x1, y1]`` (inclusive, like
        ``reference_region``), polygon ``[[x, y], ...]`` or mask image Path, view-0 pixels;
        each gets its ISO 25178 row in ``surface_parameters.csv``.
    """

    name: str
    toml_path: Path
    root: Path
    pixel_size_um: float
    pixel_size_source: str
    stereo: StereoSpec | None = None
    series: SeriesSpec | None = None
    description: str = ""
    notes: list = field(default_factory=list)
    metrology_regions: dict = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, repr=False)

    # -- images ---------------------------------------------------------------------------
    def _image(self, path):
        key = str(path)
        if key not in self._cache:
            self._cache[key] = read_image(path).data
        return self._cache[key]

    def views(self):
        """End-state views as a list of (H, W) float64 arrays (raw intensity), in view order."""
        if self.stereo is None:
            raise ExperimentError(f"{self.toml_path}: this experiment has no [stereo] table")
        return [self._image(p) for p in self.stereo.view_paths]

    def frames(self, progress=False):
        """Series frames as a list of (H, W) float64 arrays, earliest first."""
        if self.series is None:
            raise ExperimentError(f"{self.toml_path}: this experiment has no [series] table")
        paths = self.series.frame_paths
        if progress:
            from tqdm.auto import tqdm
            paths = tqdm(paths, desc="reading frames")
        return [self._image(p) for p in paths]

    def correspondences(self):
        """The stereo correspondences file parsed, or None when the TOML names none.

        Returns
        -------
        semlab.annotations.Correspondences or None
            ``pts`` is an (N, V, 2) array of (x, y) pixels, one column pair per view.
        """
        if self.stereo is None or self.stereo.correspondences_path is None:
            return None
        from .annotations import read_correspondences

        shape = self.stereo.shape
        return read_correspondences(self.stereo.correspondences_path,
                                    n_views=len(self.stereo.view_paths),
                                    image_shapes=[shape] * len(self.stereo.view_paths))

    def lines(self):
        """The vanishing-point line families (list per view of {family: (M, 4) array}) or None."""
        if self.stereo is None or self.stereo.lines_path is None:
            return None
        from .vanishing import read_lines

        return read_lines(self.stereo.lines_path)

    @property
    def truth_dir(self):
        """``truth/`` beside the TOML when the experiment is synthetic, else None."""
        d = self.root / "truth"
        return d if d.is_dir() else None

    def summary(self):
        """A human-readable multi-line description (what ``semlab info`` prints)."""
        out = [f"experiment: {self.name}", f"  file: {self.toml_path}",
               f"  pixel size: {self.pixel_size_um:.6g} µm/px (from {self.pixel_size_source})"]
        if self.stereo is not None:
            st = self.stereo
            h, w = st.shape
            out.append(f"  stereo: {len(st.view_paths)} views, {w}×{h} px, camera {st.camera}")
            for i, p in enumerate(st.view_paths):
                t = "unknown" if st.tilt_deg is None else f"{st.tilt_deg[i]:+.3f}°"
                out.append(f"    view {i}: {p.relative_to(self.root) if p.is_relative_to(self.root) else p}"
                           f"  tilt {t}")
            out.append(f"  tilts from: {st.tilt_source}" + (
                f" (estimated from 3+ views as {st.tilt_order} with the views' order: the "
                "sign of the heights; [stereo] tilt_order flips it)"
                if st.tilt_deg is None and len(st.view_paths) >= 3 else ""))
            out.append(f"  correspondences: {st.correspondences_path or 'none (automatic matching)'}")
            out.append(f"  lines: {st.lines_path or 'none'}")
        else:
            out.append("  stereo: none")
        if self.series is not None:
            se = self.series
            h, w = se.shape
            out.append(f"  series: {len(se.frame_paths)} frames, {w}×{h} px, earliest first")
            out.append(f"    first: {se.frame_paths[0].name}, last: {se.frame_paths[-1].name}")
            if se.cycles is not None:
                out.append(f"    cycles: {se.cycles[0]:g} … {se.cycles[-1]:g}")
            if se.minutes is not None:
                out.append(f"    minutes: {se.minutes[0]:g} … {se.minutes[-1]:g}")
        else:
            out.append("  series: none")
        if self.truth_dir is not None:
            out.append(f"  ground truth: {self.truth_dir}")
        for n in self.notes:
            out.append(f"  note: {n}")
        return "\n".join(out)


# -- validation helpers -----------------------------------------------------------------------
def _table(cfg, name, allowed, toml_path):
    """``cfg[name]``, refused unless it is a TOML table ``[name]`` with only ``allowed`` keys."""
    table = cfg[name]
    if not isinstance(table, dict):
        raise ExperimentError(f"{toml_path}: {name} must be a table [{name}]")
    _check_keys(table, allowed, f"[{name}]", toml_path)
    return table


def _check_keys(table, allowed, where, toml_path):
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=0.5)
            hint = f"did you mean {close[0]!r}?" if close else f"valid keys: {', '.join(sorted(allowed))}"
            raise ExperimentError(f"{toml_path}: unknown key {key!r} in {where}; {hint}")


def _resolve(root, rel, key, toml_path, must_exist=True):
    if not isinstance(rel, str) or not rel:
        raise ExperimentError(f"{toml_path}: {key} must be a path string relative to the TOML file, "
                              f"got {rel!r}")
    p = (root / rel).resolve() if not Path(rel).is_absolute() else Path(rel)
    if must_exist and not p.is_file():
        raise ExperimentError(f"{toml_path}: {key} = {rel!r}: file not found ({p}); "
                              "paths are relative to the TOML file")
    return p


def _number_list(value, key, toml_path, n=None):
    if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                              for v in value):
        raise ExperimentError(f"{toml_path}: {key} must be a list of numbers, got {value!r}")
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ExperimentError(f"{toml_path}: {key} contains nan or inf; write a finite number "
                              "for every entry")
    if n is not None and len(arr) != n:
        raise ExperimentError(f"{toml_path}: {key} has {len(arr)} values but there are {n} "
                              f"{'views' if 'stereo' in key else 'frames'}; give one per image")
    return arr


def _region_value(region, key, root, toml_path):
    """A region of view 0 from the TOML: a rectangle ``[x0, y0, x1, y1]`` or polygon
    ``[[x, y], ...]`` (list), or a mask image (resolved Path)."""
    if isinstance(region, str):
        return _resolve(root, region, key, toml_path)
    try:
        arr = np.asarray(region, float)
    except (TypeError, ValueError):
        arr = np.zeros((0,))
    rect = arr.shape == (4,) and arr[2] > arr[0] and arr[3] > arr[1]
    poly = arr.ndim == 2 and arr.shape[1] == 2 and arr.shape[0] >= 3
    if not (rect or poly) or not np.all(np.isfinite(arr)):
        raise ExperimentError(
            f"{toml_path}: {key} = {region!r} is neither a rectangle [x0, y0, x1, y1] (x1 > "
            "x0, y1 > y0) nor a polygon [[x, y], ...] of 3+ vertices in view-0 pixels, nor "
            "a mask image path")
    return arr.tolist()


def _metrology_regions(cfg, root, toml_path, shape):
    """``[metrology] regions``: named regions of view 0 for the map's ISO 25178 parameters."""
    if "metrology" not in cfg:
        return {}
    me = _table(cfg, "metrology", METROLOGY_KEYS, toml_path)
    regions = me.get("regions", {})
    if not isinstance(regions, dict):
        raise ExperimentError(f"{toml_path}: [metrology] regions must be a table of named "
                              "regions, e.g. regions = { band_1 = [x0, y0, x1, y1] }, got "
                              f"{regions!r}")
    if regions and shape is None:
        raise ExperimentError(f"{toml_path}: [metrology] regions are regions of the height "
                              "map (view-0 pixels): they need a [stereo] table")
    h, w = shape if shape is not None else (0, 0)
    out = {}
    for name, value in regions.items():
        key = f"[metrology] regions.{name}"
        if name.strip().lower() == "map":
            raise ExperimentError(f"{toml_path}: {key}: the name 'map' is reserved for the "
                                  "whole map in surface_parameters.csv; rename the region")
        reg = _region_value(value, key, root, toml_path)
        if isinstance(reg, Path):
            m = read_image(reg).data
            if m.shape[:2] != (h, w):
                raise ExperimentError(f"{toml_path}: {key}: mask {reg.name} is "
                                      f"{m.shape[1]}×{m.shape[0]} px, the views "
                                      f"{w}×{h} px; draw the mask on view 0 at its size")
            if not np.any(m):
                raise ExperimentError(f"{toml_path}: {key}: mask {reg.name} is empty (no "
                                      "non-zero pixel)")
        else:
            xy = np.asarray(reg, float).reshape(-1, 2)
            if np.any(xy < -0.5) or np.any(xy[:, 0] > w - 0.5) or np.any(xy[:, 1] > h - 0.5):
                raise ExperimentError(f"{toml_path}: {key} = {reg} reaches outside the "
                                      f"{w}×{h} px views (view-0 pixels, x right, y down)")
        out[str(name)] = reg
    return out


def _reference_region(st, root, toml_path, shape):
    """``[stereo] reference_region`` and ``reference_points``, checked (view-0 pixels)."""
    region, points = st.get("reference_region"), st.get("reference_points")
    key = "[stereo] reference_region"
    if region is not None and points is not None:
        raise ExperimentError(f"{toml_path}: give {key} or [stereo] reference_points, not both")
    h, w = shape
    if region is not None:
        region = _region_value(region, key, root, toml_path)
    if points is not None:
        try:
            arr = np.asarray(points, float)
        except (TypeError, ValueError):
            arr = np.zeros((0,))
        if arr.shape != (3, 2) or not np.all(np.isfinite(arr)):
            raise ExperimentError(f"{toml_path}: [stereo] reference_points = {points!r} must be "
                                  "three view-0 pixels [[x, y], [x, y], [x, y]]")
        if np.any(arr < -0.5) or np.any(arr[:, 0] > w - 0.5) or np.any(arr[:, 1] > h - 0.5):
            raise ExperimentError(f"{toml_path}: [stereo] reference_points {arr.tolist()} are "
                                  f"outside the {w}×{h} px views")
        points = arr.tolist()
    return region, points


def _image_header(path):
    """(shape, pixel_size_um, tilt_deg, pixel digest) of an image, reading it once."""
    import hashlib

    im = read_image(path)
    digest = hashlib.sha1(np.ascontiguousarray(im.data).tobytes()).hexdigest()
    return im.shape, im.pixel_size_um, im.tilt_deg, digest


def _check_image_size(shapes, paths, what, toml_path):
    for p, (h, w) in zip(paths, shapes):
        if min(h, w) < MIN_IMAGE_PX:
            raise ExperimentError(
                f"{toml_path}: {what}: {p.name} is {w}×{h} px, too small to match or track "
                f"(semlab needs at least {MIN_IMAGE_PX}×{MIN_IMAGE_PX} px); give the full "
                "SEM image")


def _check_distinct_images(paths, digests, keys, toml_path, tilts=None):
    """Refuse the same file twice and, with ``digests``, images with identical pixels."""
    seen = {}
    for i, p in enumerate(paths):
        if p in seen:
            j = seen[p]
            raise ExperimentError(
                f"{toml_path}: {keys[i]} and {keys[j]} are the same file ({p.name}); every "
                "entry must be a different image")
        seen[p] = i
    if digests is None:
        return
    first = {}
    for i, d in enumerate(digests):
        if d in first:
            j = first[d]
            tilt = ("" if tilts is None else
                    f" although their tilts are {tilts[j]:g}° and {tilts[i]:g}°")
            raise ExperimentError(
                f"{toml_path}: {keys[j]} ({paths[j].name}) and {keys[i]} ({paths[i].name}) "
                f"have identical pixels{tilt}: a copy of one image shows no parallax, so "
                "it gives no heights. List the views recorded at each tilt")
        first[d] = i


def _check_pixel_size(value, where, fix):
    """A pixel size in µm/px an SEM can have, else ExperimentError naming ``where``."""
    lo, hi = PIXEL_SIZE_RANGE_UM
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ExperimentError(f"{where} must be a number of µm per pixel, got {value!r}"
                              + (" (a string: remove the quotes)" if isinstance(value, str) else "")
                              + f"; {fix}")
    if not (np.isfinite(value) and lo <= value <= hi):
        raise ExperimentError(
            f"{where} is {value!r} µm/px, which no SEM has (expected a positive number between "
            f"{lo:g} and {hi:g} µm per pixel); {fix}")
    return float(value)


def _check_tilts(tilts, where, fix):
    """Stage tilts in degrees: finite and ``|tilt| < MAX_TILT_DEG``."""
    for i, t in enumerate(tilts):
        if not (np.isfinite(t) and abs(t) < MAX_TILT_DEG):
            raise ExperimentError(
                f"{where(i)} is {t:g}°, not a stage tilt (|tilt| must be below "
                f"{MAX_TILT_DEG:g}°; give degrees, not radians or a typo); {fix}")


def _check_same_shape(shapes, paths, what, toml_path):
    ref = shapes[0]
    for p, s in zip(paths, shapes):
        if s != ref:
            raise ExperimentError(
                f"{toml_path}: {what} must all have the same size; {paths[0].name} is "
                f"{ref[1]}×{ref[0]} px but {p.name} is {s[1]}×{s[0]} px. Crop or re-export them "
                "at one resolution")


def natural_key(path):
    """Sort key of a path by its name with the digit runs compared as numbers, so that
    ``f2.tif`` comes before ``f10.tif`` (the order a microscope's numbering means)."""
    import re

    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower())
            for t in re.split(r"(\d+)", Path(path).name) if t] + [(2, 0, str(path))]


def _expand_frames(frames, root, toml_path):
    if isinstance(frames, str):
        pattern = frames if Path(frames).is_absolute() else str(root / frames)
        found = sorted((p for p in (Path(x) for x in _glob.glob(pattern))
                        if p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
        if not found:
            raise ExperimentError(f"{toml_path}: [series] frames = {frames!r} matches no image "
                                  f"file (looked for {pattern}); check the pattern")
        return found
    if not isinstance(frames, list) or not frames:
        raise ExperimentError(f"{toml_path}: [series] frames must be a list of paths or a glob "
                              "string, earliest frame first")
    return [_resolve(root, f, f"[series] frames[{i}]", toml_path) for i, f in enumerate(frames)]


def _check_increasing(arr, key, toml_path):
    if arr is not None and np.any(np.diff(arr) <= 0):
        i = int(np.argmax(np.diff(arr) <= 0))
        raise ExperimentError(f"{toml_path}: {key} must increase strictly (frames are "
                              f"chronological), but value {i + 1} ({arr[i + 1]:g}) follows "
                              f"{arr[i]:g}")


def _read_toml(toml_path):
    text = read_text(toml_path, TOML_NAME)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ExperimentError(f"{toml_path}: not valid TOML ({exc}); fix the syntax at that line") from exc


def _find_toml(path):
    path = Path(path)
    if path.is_dir():
        path = path / TOML_NAME
        if not path.is_file():
            raise ExperimentError(f"{path}: experiment file not found: {path.parent} is a folder "
                                  f"without {TOML_NAME}; give an experiment folder (see the "
                                  "README for the format), or write one for images with "
                                  "`semlab init NEW_FOLDER --views IMAGES`")
    elif path.is_file() and path.suffix.lower() != ".toml":
        kind = "an image" if path.suffix.lower() in IMAGE_SUFFIXES else "a file"
        raise ExperimentError(f"{path}: this is {kind}, not an experiment; give the experiment "
                              f"folder or its {TOML_NAME}, which lists the images (see the "
                              "README for the format)")
    if not path.is_file():
        raise ExperimentError(f"{path}: experiment file not found; give the experiment folder "
                              f"or its {TOML_NAME} (see the README for the format)")
    return path.resolve()


def find_experiment_root(path):
    """The experiment folder of ``path`` (a folder or its ``experiment.toml``), resolved.

    Raises
    ------
    ExperimentError
        ``path`` is not an experiment (a folder without the TOML, an image, another file).
    """
    return _find_toml(path).parent


def load(path) -> Experiment:
    """Load and validate an experiment.

    Parameters
    ----------
    path : str or Path
        The experiment folder or its ``experiment.toml``.

    Returns
    -------
    Experiment

    Raises
    ------
    ExperimentError
        With the file, the key and the fix: missing files, unknown keys (the nearest valid
        key is suggested), fewer than 2 views, images of different sizes, a glob matching
        nothing, cycles/minutes not increasing or of the wrong length, no pixel size anywhere,
        invalid correspondences or lines files.

    Examples
    --------
    >>> import tempfile, semlab
    >>> from semlab.synth import make_experiment
    >>> folder = make_experiment(tempfile.mkdtemp() + "/exp", seed=1, size=(96, 128),
    ...                          n_frames=3, progress=False)
    >>> exp = semlab.load_experiment(folder)
    >>> len(exp.stereo.view_paths), len(exp.series.frame_paths), exp.pixel_size_um
    (2, 3, 0.03)
    """
    toml_path = _find_toml(path)
    root = toml_path.parent
    cfg = _read_toml(toml_path)
    _check_keys(cfg, TOP_KEYS, "the top level", toml_path)
    if "stereo" not in cfg and "series" not in cfg:
        raise ExperimentError(f"{toml_path}: neither [stereo] nor [series] is given; an experiment "
                              "needs at least one of them")
    for key in ("name", "description"):
        if key in cfg and not isinstance(cfg[key], str):
            raise ExperimentError(f"{toml_path}: {key} must be a string, e.g. {key} = \"...\", "
                                  f"got {cfg[key]!r}")
    notes = []
    meta_pixel_sizes = []  # (value, file) from image metadata

    stereo = None
    if "stereo" in cfg:
        st = _table(cfg, "stereo", STEREO_KEYS, toml_path)
        views = st.get("views")
        if not isinstance(views, list) or len(views) < 2:
            raise ExperimentError(f"{toml_path}: [stereo] views must list 2 or more images (stage "
                                  f"tilts of the same area), got {views!r}")
        view_paths = [_resolve(root, v, f"[stereo] views[{i}]", toml_path) for i, v in enumerate(views)]
        view_keys = [f"[stereo] views[{i}]" for i in range(len(view_paths))]
        _check_distinct_images(view_paths, None, view_keys, toml_path)
        headers = [_image_header(p) for p in view_paths]
        _check_same_shape([h[0] for h in headers], view_paths, "[stereo] views", toml_path)
        _check_image_size([h[0] for h in headers], view_paths, "[stereo] views", toml_path)
        meta_pixel_sizes += [(h[1], p.name) for h, p in zip(headers, view_paths) if h[1] is not None]
        camera = st.get("camera", "affine")
        if camera not in CAMERAS:
            close = difflib.get_close_matches(str(camera), CAMERAS, n=1)
            raise ExperimentError(f"{toml_path}: [stereo] camera = {camera!r} is not one of "
                                  f"{CAMERAS}" + (f"; did you mean {close[0]!r}?" if close else ""))
        meta_tilts = [h[2] for h in headers]
        if "tilt_deg" in st:
            tilt = _number_list(st["tilt_deg"], "[stereo] tilt_deg", toml_path, n=len(view_paths))
            tilt_deg, tilt_source = [float(t) for t in tilt], "experiment"
            _check_tilts(tilt_deg, lambda i: f"{toml_path}: [stereo] tilt_deg[{i}]",
                         "correct tilt_deg in experiment.toml")
            for i, (t, m) in enumerate(zip(tilt_deg, meta_tilts)):
                if m is not None and not (np.isfinite(m) and abs(m) < MAX_TILT_DEG):
                    notes.append(f"view {i} ({view_paths[i].name}): the image metadata tilt "
                                 f"{m:g}° is impossible; using experiment.toml's {t:g}°")
                elif m is not None and abs(t - m) > TILT_ATOL_DEG:
                    notes.append(f"view {i} ({view_paths[i].name}): experiment.toml tilt {t:g}° "
                                 f"overrides the image metadata {m:g}°")
        elif all(m is not None for m in meta_tilts):
            tilt_deg, tilt_source = [float(m) for m in meta_tilts], "metadata"
            _check_tilts(tilt_deg, lambda i: f"{view_paths[i]}: the stage tilt in the image's "
                         "SEM metadata", "give [stereo] tilt_deg = [...] in experiment.toml")
        else:
            tilt_deg, tilt_source = None, "unknown"
        if tilt_deg is not None and max(tilt_deg) - min(tilt_deg) == 0:
            where = ("[stereo] tilt_deg" if tilt_source == "experiment"
                     else "the tilts in the images' SEM metadata")
            raise ExperimentError(
                f"{toml_path}: {where} give every view the same tilt ({tilt_deg[0]:g}°): heights "
                "need at least two different stage tilts; give the tilt of each view in "
                "[stereo] tilt_deg")
        _check_distinct_images(view_paths, [h[3] for h in headers], view_keys, toml_path,
                               tilt_deg)
        tilt_order = st.get("tilt_order", "increasing")
        if tilt_order not in TILT_ORDERS:
            close = difflib.get_close_matches(str(tilt_order), TILT_ORDERS, n=1)
            raise ExperimentError(f"{toml_path}: [stereo] tilt_order = {tilt_order!r} is not one "
                                  f"of {TILT_ORDERS}" + (f"; did you mean {close[0]!r}?" if close
                                                         else ""))
        if tilt_deg is not None and "tilt_order" in st and len(tilt_deg) >= 2 and (
                (tilt_deg[-1] > tilt_deg[0]) != (tilt_order == "increasing")):
            raise ExperimentError(
                f"{toml_path}: [stereo] tilt_order = {tilt_order!r} but the tilts "
                f"({'[stereo] tilt_deg' if tilt_source == 'experiment' else 'image metadata'}: "
                f"{tilt_deg[0]:g}° … {tilt_deg[-1]:g}°) run the other way; remove tilt_order "
                "(it is used only where the tilts are estimated) or correct the tilts")
        corr = st.get("correspondences")
        lines = st.get("lines")
        stereo = StereoSpec(
            view_paths=view_paths, tilt_deg=tilt_deg, tilt_source=tilt_source, camera=camera,
            correspondences_path=None if corr is None else _resolve(root, corr, "[stereo] correspondences", toml_path),
            lines_path=None if lines is None else _resolve(root, lines, "[stereo] lines", toml_path),
            shape=headers[0][0], tilt_order=tilt_order)
        stereo.reference_region, stereo.reference_points = _reference_region(
            st, root, toml_path, headers[0][0])

    series = None
    if "series" in cfg:
        se = _table(cfg, "series", SERIES_KEYS, toml_path)
        if "frames" not in se:
            raise ExperimentError(f"{toml_path}: [series] needs frames = [...] or a glob string")
        frame_paths = _expand_frames(se["frames"], root, toml_path)
        _check_distinct_images(frame_paths, None, [f"[series] frames[{i}]" for i in
                                                   range(len(frame_paths))], toml_path)
        headers = [_image_header(p) for p in frame_paths]
        _check_same_shape([h[0] for h in headers], frame_paths, "[series] frames", toml_path)
        _check_image_size([h[0] for h in headers], frame_paths, "[series] frames", toml_path)
        meta_pixel_sizes += [(h[1], p.name) for h, p in zip(headers, frame_paths) if h[1] is not None]
        n = len(frame_paths)
        cycles = _number_list(se["cycles"], "[series] cycles", toml_path, n) if "cycles" in se else None
        minutes = _number_list(se["minutes"], "[series] minutes", toml_path, n) if "minutes" in se else None
        _check_increasing(cycles, "[series] cycles", toml_path)
        _check_increasing(minutes, "[series] minutes", toml_path)
        series = SeriesSpec(frame_paths=frame_paths, cycles=cycles, minutes=minutes,
                            shape=headers[0][0])

    lo, hi = PIXEL_SIZE_RANGE_UM
    meta_ok = [(m, name) for m, name in meta_pixel_sizes if np.isfinite(m) and lo <= m <= hi]
    meta_bad = [(m, name) for m, name in meta_pixel_sizes if (m, name) not in meta_ok]
    if "pixel_size_um" in cfg:
        ps = _check_pixel_size(cfg["pixel_size_um"], f"{toml_path}: pixel_size_um",
                               "write the pixel size in µm per pixel, e.g. pixel_size_um = 0.03")
        pixel_size_um, source = ps, "experiment"
        for m, name in meta_bad[:1]:
            notes.append(f"{name}: the image metadata pixel size {m:g} µm is impossible; using "
                         f"experiment.toml's {ps:g} µm")
        for m, name in meta_ok:
            if abs(m - ps) > PIXEL_SIZE_RTOL * ps:
                notes.append(f"{name}: experiment.toml pixel_size_um {ps:g} µm overrides the image "
                             f"metadata {m:g} µm")
                break
    elif meta_bad:
        m, name = meta_bad[0]
        _check_pixel_size(m, f"{name}: the pixel size in the image's SEM metadata",
                          f"add pixel_size_um = <µm per pixel> to the top of {toml_path}")
    elif meta_pixel_sizes:
        pixel_size_um, name = meta_pixel_sizes[0]
        source = f"metadata:{name}"
        for m, other in meta_pixel_sizes[1:]:
            if abs(m - pixel_size_um) > PIXEL_SIZE_RTOL * pixel_size_um:
                notes.append(f"{other}: metadata pixel size {m:g} µm differs from {name} "
                             f"({pixel_size_um:g} µm); using {pixel_size_um:g} µm")
                break
    else:
        raise ExperimentError(f"{toml_path}: no pixel size anywhere: the images carry no SEM "
                              "metadata; add pixel_size_um = <µm per pixel> to the top of the file")

    exp = Experiment(name=str(cfg.get("name", root.name)), toml_path=toml_path, root=root,
                     pixel_size_um=pixel_size_um, pixel_size_source=source, stereo=stereo,
                     series=series, description=str(cfg.get("description", "")), notes=notes,
                     metrology_regions=_metrology_regions(
                         cfg, root, toml_path, None if stereo is None else stereo.shape))
    for n in notes:
        warnings.warn(n, SemlabWarning, stacklevel=2)
    # Parse the annotation files now so that a bad CSV or JSON fails at load time.
    exp.correspondences()
    exp.lines()
    return exp


def _images_of(entries, what):
    """Image files named by ``entries`` (files, folders or glob patterns), in natural order
    within each entry, the entries' order kept."""
    out = []
    for e in entries:
        p = Path(e)
        if p.is_dir():
            found = sorted((q for q in p.iterdir()
                            if q.is_file() and q.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
            if not found:
                raise ExperimentError(f"{p}: {what}: the folder holds no image file "
                                      f"({', '.join(IMAGE_SUFFIXES)}); give the folder of the "
                                      "images or the image files")
        elif p.is_file():
            if p.suffix.lower() not in IMAGE_SUFFIXES:
                raise ExperimentError(f"{p}: {what}: not an image file (expected one of "
                                      f"{', '.join(IMAGE_SUFFIXES)})")
            found = [p]
        else:
            found = sorted((Path(x) for x in _glob.glob(str(e))
                            if Path(x).is_file() and Path(x).suffix.lower() in IMAGE_SUFFIXES),
                           key=natural_key)
            if not found:
                raise ExperimentError(f"{e}: {what}: no such file or folder, and no image file "
                                      "matches it as a pattern; check the path")
        out += [q.resolve() for q in found]
    return out


def init_experiment(out, views=None, frames=None, name=None, pixel_size_um=None,
                    tilt_deg=None, cycles=None):
    """Write a new experiment folder ``out`` whose ``experiment.toml`` names existing images.

    The images stay where they are (the TOML points to them by paths relative to ``out``); no
    image folder is written to. The TOML is loaded back with :func:`load` before this returns,
    so what it writes is an experiment that loads; on any error nothing is left in ``out``.

    Parameters
    ----------
    out : str or Path
        New (or empty) folder for ``experiment.toml``.
    views : sequence of str or Path, optional
        End-state views at different stage tilts: image files, folders (every image inside)
        or glob patterns, in this order; within a folder or pattern in natural order
        (``v2`` before ``v10``).
    frames : sequence of str or Path, optional
        Frames of the fatigue series, earliest first, given like ``views``.
    name : str, optional
        Experiment name (default: the name of ``out``).
    pixel_size_um : float, optional
        µm per pixel; needed when no image carries it in its SEM metadata (FEI / Zeiss TIFF).
    tilt_deg : sequence of float, optional
        Stage tilt of every view, degrees; default the images' metadata, or estimated from
        3+ views when they have none.
    cycles : sequence of float, optional
        Fatigue cycles of every frame (strictly increasing).

    Returns
    -------
    Experiment
        The loaded experiment (``toml_path`` is the written file).

    Raises
    ------
    ExperimentError
        ``out`` not empty, no views and no frames, a path without images, fewer than two
        views or frames, a tilt or cycle list of the wrong length, no pixel size anywhere, or
        anything :func:`load` refuses (images of different sizes, a copy of one view, ...).
    """
    import json
    import os
    import shutil
    from datetime import datetime, timezone

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ExperimentError(f"{out}: exists and is not an empty folder; give a new folder for "
                              "the experiment (the images stay where they are)")
    if not views and not frames:
        raise ExperimentError("give the end-state views (--views) or the series frames "
                              "(--frames), or both")
    view_paths = _images_of(views or [], "views")
    frame_paths = _images_of(frames or [], "frames")
    for what, paths in (("views", view_paths), ("frames", frame_paths)):
        if paths and len(paths) < 2:
            raise ExperimentError(f"{paths[0]}: {what}: only one image; {what} need two or "
                                  "more (stage tilts of the same area / frames of the series)")
    for what, values, paths in (("tilts", tilt_deg, view_paths), ("cycles", cycles, frame_paths)):
        if values is not None and len(values) != len(paths):
            raise ExperimentError(f"{len(values)} {what} for {len(paths)} "
                                  f"{'views' if what == 'tilts' else 'frames'} "
                                  f"({', '.join(p.name for p in paths)}); give one per image")
    if pixel_size_um is None:
        first = (view_paths + frame_paths)[0]
        if all(read_image(p).pixel_size_um is None for p in view_paths + frame_paths):
            raise ExperimentError(f"{first.parent}: the images carry no pixel size in SEM "
                                  "metadata; give it, e.g. --pixel-size 0.03 (µm per pixel, "
                                  "from the microscope or the scale bar)")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    root = out.resolve()

    def rel(p):
        # relative to the TOML when the two share a folder below the file system's root (the
        # experiment can move with its images), else absolute
        try:
            common = Path(os.path.commonpath([p, root]))
        except ValueError:          # another drive
            return p.as_posix()
        return p.as_posix() if common == Path(common.anchor) else \
            Path(os.path.relpath(p, root)).as_posix()

    def array(paths):
        return "[\n" + "".join(f"  {json.dumps(rel(p))},\n" for p in paths) + "]"

    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# written by semlab init on {stamp}; relative paths are relative to this file",
             f"name = {json.dumps(str(name) if name else out.resolve().name)}"]
    if pixel_size_um is not None:
        lines.append(f"pixel_size_um = {float(pixel_size_um)!r}")
    else:
        lines.append("# pixel_size_um: from the images' SEM metadata (a value here overrides it)")
    if view_paths:
        lines += ["", "[stereo]", "views = " + array(view_paths)]
        if tilt_deg is not None:
            lines.append(f"tilt_deg = {json.dumps([float(t) for t in tilt_deg])}")
        else:
            lines.append("# tilt_deg = [...]  # stage tilts, degrees: from the images' metadata, "
                         "else estimated from 3+ views")
    if frame_paths:
        lines += ["", "[series]", "frames = " + array(frame_paths)]
        if cycles is not None:
            lines.append(f"cycles = {json.dumps([float(c) for c in cycles])}")
    toml_path = out / TOML_NAME
    toml_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SemlabWarning)   # the notes are in exp.notes
            return load(out)
    except BaseException:       # refused (an ExperimentError, a damaged image) or interrupted
        if created:
            shutil.rmtree(out, ignore_errors=True)
        else:
            toml_path.unlink(missing_ok=True)
        raise
