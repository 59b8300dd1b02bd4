"""The on-disk format of hand-picked point correspondences, and the backup policy.

``correspondences.csv`` holds one row per material point seen in every view::

    point_id,x0_px,y0_px,x1_px,y1_px[,x2_px,y2_px,...][,crack_id]
    0,101.25,40.5,97.75,40.25,
    1,230.0,118.0,226.5,118.25,3

- ``point_id``: a unique integer per point;
- ``x{k}_px, y{k}_px``: the point in view ``k`` (views in the experiment's order), in pixels,
  x to the right, y down, origin at the centre of the top-left pixel (OpenCV), so an image of
  shape ``(H, W)`` covers ``-0.5 <= x <= W - 0.5`` and ``-0.5 <= y <= H - 0.5``;
- ``crack_id`` (optional column): the integer id (>= 0) of the crack the point lies on, or empty.

Other columns (a ``note`` for instance) are allowed and ignored.

Annotations are the one thing semlab writes into an experiment folder, so nothing is ever
overwritten silently: :func:`semlab.io.write_with_backup` copies an existing file to
``<stem>.bak<suffix>`` (then ``<stem>.bak1<suffix>``, ...) before it is replaced atomically.
"""

from __future__ import annotations

import csv
import io as _io
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ExperimentError
from .io import backup_file, backup_path, read_text, write_with_backup
from .io import write_with_backup as atomic_write_text  # noqa: F401  (the former name)

__all__ = [
    "Correspondences",
    "correspondence_columns",
    "read_correspondences",
    "write_correspondences",
    "backup_path",
    "backup_file",
]

_VIEW_COLUMN = re.compile(r"^([xy])(\d+)_px$")


@dataclass
class Correspondences:
    """Points picked in ``V`` views of the same surface.

    Attributes
    ----------
    point_id : (N,) int array
        Unique id of each point.
    pts : (N, V, 2) float array
        ``pts[i, k]`` is point ``i`` in view ``k`` as ``(x, y)`` pixels (OpenCV convention).
    crack_id : (N,) int array or None
        Crack each point lies on, ``-1`` for none; None when the file has no ``crack_id`` column.
    path : Path or None
        The file the points were read from, if any.
    """

    point_id: np.ndarray
    pts: np.ndarray
    crack_id: np.ndarray | None = None
    path: Path | None = None

    @property
    def n_points(self):
        """Number of points ``N``."""
        return int(self.pts.shape[0])

    @property
    def n_views(self):
        """Number of views ``V``."""
        return int(self.pts.shape[1])

    def __len__(self):
        return self.n_points


def correspondence_columns(n_views, crack_id=False):
    """Column names of a correspondences CSV for ``n_views`` views.

    Examples
    --------
    >>> correspondence_columns(2)
    ['point_id', 'x0_px', 'y0_px', 'x1_px', 'y1_px']
    """
    cols = ["point_id"]
    for k in range(int(n_views)):
        cols += [f"x{k}_px", f"y{k}_px"]
    if crack_id:
        cols.append("crack_id")
    return cols


def _parse_int(text, path, line, column, point_id=None):
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value != int(value):
        where = f"line {line}" + (f" (point_id {point_id})" if point_id is not None else "")
        raise ExperimentError(
            f"{path}: {where}, column {column!r}: {text!r} is not an integer; "
            f"write a whole number there")
    return int(value)


def read_correspondences(path, n_views=None, image_shapes=None):
    """Read and validate a correspondences CSV.

    Parameters
    ----------
    path : str or Path
        The CSV file (comma-separated, UTF-8, header row first; see the module docstring).
    n_views : int, optional
        Number of views the experiment has; the file must hold exactly that many
        ``x{k}_px, y{k}_px`` column pairs.
    image_shapes : sequence of (H, W) tuples, optional
        Shape of each view's image; every point must then lie inside its image,
        ``-0.5 <= x <= W - 0.5`` and ``-0.5 <= y <= H - 0.5``.

    Returns
    -------
    Correspondences
        ``pts`` is ``(N, V, 2)`` float pixels; ``crack_id`` is ``(N,)`` int with ``-1`` for
        none, or None when the file has no ``crack_id`` column.

    Raises
    ------
    ExperimentError
        The file is missing, a column is missing, a value is not a number, a coordinate is
        empty or NaN, a ``point_id`` appears twice, a point lies outside its image, or the
        number of views differs from ``n_views``. The message names the file, the line and
        column (or point and view) and what to change.
    """
    path = Path(path)
    if not path.is_file():
        raise ExperimentError(f"{path}: correspondences file not found; pick points with "
                              f"semlab.widgets.picker_widget or fix the path")
    text = read_text(path, "correspondences file")
    rows = list(csv.reader(_io.StringIO(text, newline="")))
    rows = [(i + 1, r) for i, r in enumerate(rows) if any(c.strip() for c in r)]
    if not rows:
        raise ExperimentError(f"{path}: the file is empty; it needs a header row "
                              f"{','.join(correspondence_columns(n_views or 2))}")
    header_line, header = rows[0]
    header = [h.strip() for h in header]
    if len(header) == 1 and ";" in header[0]:
        raise ExperimentError(f"{path}: the header uses ';' as separator; save the file as "
                              f"comma-separated CSV (columns separated by ',')")
    if len(set(header)) != len(header):
        dup = sorted({h for h in header if header.count(h) > 1})
        raise ExperimentError(f"{path}: column(s) {dup} appear more than once in the header; "
                              f"keep one of each")

    xs, ys = set(), set()
    for h in header:
        m = _VIEW_COLUMN.match(h)
        if m:
            (xs if m.group(1) == "x" else ys).add(int(m.group(2)))
    n_found = max(xs | ys) + 1 if (xs or ys) else 0
    n_expected = int(n_views) if n_views is not None else max(n_found, 1)
    expected = correspondence_columns(max(n_expected, n_found))
    missing = [c for c in expected if c not in header]
    if missing:
        raise ExperimentError(
            f"{path}: missing column(s) {', '.join(missing)}; for {max(n_expected, n_found)} "
            f"view(s) the header must be {','.join(expected)}[,crack_id]")
    if n_views is not None and n_found != n_views:
        raise ExperimentError(
            f"{path}: the file has {n_found} view column pair(s) (x0_px..x{n_found - 1}_px) but "
            f"the experiment has {n_views} view(s); the header must be "
            f"{','.join(correspondence_columns(n_views))}[,crack_id]")
    n_v = n_found
    if image_shapes is not None and len(image_shapes) != n_v:
        raise ExperimentError(f"{path}: {len(image_shapes)} image shape(s) given for "
                              f"{n_v} view(s); pass one (H, W) per view")

    col = {h: j for j, h in enumerate(header)}
    has_crack = "crack_id" in col
    ids, pts, cracks = [], [], []
    first_line = {}
    for line, row in rows[1:]:
        row = [c.strip() for c in row] + [""] * max(0, len(header) - len(row))
        if len(row) > len(header) and any(row[len(header):]):
            raise ExperimentError(f"{path}: line {line} has {len(row)} values but the header "
                                  f"has {len(header)} columns; remove the extra values")
        pid = _parse_int(row[col["point_id"]], path, line, "point_id")
        if pid in first_line:
            raise ExperimentError(f"{path}: point_id {pid} on line {line} is already used on "
                                  f"line {first_line[pid]}; give every point its own id")
        first_line[pid] = line
        p = np.empty((n_v, 2))
        for k in range(n_v):
            for a, name in enumerate((f"x{k}_px", f"y{k}_px")):
                text = row[col[name]]
                if text == "":
                    raise ExperimentError(
                        f"{path}: line {line} (point_id {pid}), column {name!r} is empty; "
                        f"pick the point in view {k} or delete the row")
                try:
                    v = float(text)
                except ValueError:
                    raise ExperimentError(
                        f"{path}: line {line} (point_id {pid}), column {name!r}: {text!r} is "
                        f"not a number; write the coordinate in pixels, e.g. 120.5") from None
                if not math.isfinite(v):
                    raise ExperimentError(
                        f"{path}: line {line} (point_id {pid}), column {name!r} is {text!r}; "
                        f"pick the point in view {k} or delete the row")
                p[k, a] = v
            if image_shapes is not None:
                h, w = image_shapes[k][:2]
                x, y = p[k]
                if not (-0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5):
                    raise ExperimentError(
                        f"{path}: line {line}: point_id {pid} in view {k} at "
                        f"(x={x:g}, y={y:g}) px is outside the {w}x{h} px image "
                        f"(x in [-0.5, {w - 0.5}], y in [-0.5, {h - 0.5}]); "
                        f"correct or delete the point")
        c = -1
        if has_crack and row[col["crack_id"]] != "":
            c = _parse_int(row[col["crack_id"]], path, line, "crack_id", pid)
            if c < 0:
                raise ExperimentError(
                    f"{path}: line {line} (point_id {pid}), column 'crack_id' is {c}; "
                    f"use an integer >= 0, or leave it empty for a point on no crack")
        ids.append(pid)
        pts.append(p)
        cracks.append(c)
    pts = np.asarray(pts, dtype=float).reshape(len(ids), n_v, 2)
    _check_no_repeated_points(pts, ids, [line for line, _ in rows[1:]], path)
    return Correspondences(
        point_id=np.asarray(ids, dtype=int),
        pts=pts,
        crack_id=np.asarray(cracks, dtype=int) if has_crack else None,
        path=path)


def _check_no_repeated_points(pts, ids, lines, path):
    """Refuse two rows at the same position in a view (one surface point clicked twice)."""
    for k in range(pts.shape[1]):
        _, first, inverse = np.unique(pts[:, k], axis=0, return_index=True, return_inverse=True)
        inverse = np.asarray(inverse).ravel()
        rep = np.flatnonzero(first[inverse] != np.arange(len(pts)))
        if len(rep):
            i = int(rep[0])
            j = int(first[inverse[i]])
            x, y = pts[i, k]
            more = f" ({len(rep)} repeated rows in all)" if len(rep) > 1 else ""
            raise ExperimentError(
                f"{path}: line {lines[i]} (point_id {ids[i]}) is at the same position as line "
                f"{lines[j]} (point_id {ids[j]}) in view {k} (x={x:g}, y={y:g}){more}; a point "
                "can be listed once: delete the repeated rows")


def _as_correspondences(obj):
    """Coerce what :func:`write_correspondences` accepts into a validated Correspondences."""
    if isinstance(obj, Correspondences):
        point_id, pts, crack = obj.point_id, obj.pts, obj.crack_id
    elif isinstance(obj, dict):
        pts = obj["pts"]
        point_id = obj.get("point_id")
        crack = obj.get("crack_id")
    elif isinstance(obj, (tuple, list)) and len(obj) in (2, 3):
        point_id, pts = obj[0], obj[1]
        crack = obj[2] if len(obj) == 3 else None
    else:
        point_id, pts, crack = None, obj, None
    pts = np.asarray(pts, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 2 or pts.shape[1] < 1:
        raise ExperimentError(f"pts must be an (N, V, 2) array of (x, y) pixels per view, "
                              f"got shape {pts.shape}")
    n = pts.shape[0]
    point_id = np.arange(n) if point_id is None else np.asarray(point_id)
    if point_id.shape != (n,):
        raise ExperimentError(f"point_id must have shape ({n},) like pts, got {point_id.shape}")
    if n and not np.all(np.asarray(point_id, dtype=float) == np.round(point_id)):
        raise ExperimentError("point_id must hold integers")
    point_id = point_id.astype(int)
    uniq, counts = np.unique(point_id, return_counts=True)
    if np.any(counts > 1):
        raise ExperimentError(f"point_id {uniq[counts > 1].tolist()} used more than once; "
                              f"give every point its own id")
    bad = ~np.isfinite(pts).all(axis=(1, 2))
    if np.any(bad):
        raise ExperimentError(f"point_id {point_id[bad].tolist()} has NaN/inf coordinates; "
                              f"only points picked in every view can be written")
    if crack is not None:
        crack = np.asarray(crack, dtype=int)
        if crack.shape != (n,):
            raise ExperimentError(f"crack_id must have shape ({n},) like pts, got {crack.shape}")
    return Correspondences(point_id, pts, crack)


def _fmt(v):
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def write_correspondences(path, corr_or_arrays, backup=True):
    """Write correspondences as CSV, never silently replacing an existing file.

    Parameters
    ----------
    path : str or Path
        Destination ``.csv``.
    corr_or_arrays : Correspondences, (N, V, 2) array, (point_id, pts[, crack_id]) tuple or dict
        The points; ``pts`` is ``(N, V, 2)`` ``(x, y)`` pixels per view and must be finite.
        Without ``point_id`` the ids are ``0..N-1``. With ``crack_id`` (``(N,)`` int, ``-1`` for
        none) a ``crack_id`` column is written.
    backup : bool
        If ``path`` exists, copy it to ``<stem>.bak.csv`` (or ``.bak1.csv``, ``.bak2.csv``, ...
        whichever is free) first. Default True.

    Returns
    -------
    Path or None
        The backup written, or None.

    Notes
    -----
    Coordinates are written with 4 decimals (1e-4 px), far below any picking accuracy.
    """
    corr = _as_correspondences(corr_or_arrays)
    has_crack = corr.crack_id is not None
    lines = [",".join(correspondence_columns(corr.n_views, crack_id=has_crack))]
    for i in range(corr.n_points):
        cells = [str(int(corr.point_id[i]))]
        cells += [_fmt(v) for v in corr.pts[i].ravel()]
        if has_crack:
            c = int(corr.crack_id[i])
            cells.append(str(c) if c >= 0 else "")
        lines.append(",".join(cells))
    return write_with_backup(path, "\n".join(lines) + "\n", backup=backup)
