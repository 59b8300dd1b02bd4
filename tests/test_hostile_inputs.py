"""Hostile and impossible inputs (issue #10): each is refused by the CLI in one line.

Every case below is run through ``semlab info`` or ``semlab run`` in-process and must give
exit code 2, one line ``semlab: error: ...`` naming the file (and the key or row) and the
fix, no traceback, no result file, and an experiment folder whose checksum is unchanged.
The cases are classes, each with several values (encodings, scales, tilts, folders).
"""

import codecs
import hashlib
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from semlab.cli import main
from semlab.errors import GeometryError, SemlabError
from semlab.io import write_tiff

ROOT = Path(__file__).resolve().parents[1]
RESULT_SUFFIXES = (".csv", ".json", ".npz", ".txt", ".html", ".ipynb")


def checksum(folder):
    """sha256 over every file's relative path and bytes (the folder's content)."""
    h = hashlib.sha256()
    for p in sorted(Path(folder).rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def set_toml(exp, old, new):
    toml = exp / "experiment.toml"
    text = toml.read_text()
    assert old in text, (old, text)
    toml.write_text(text.replace(old, new, 1))


def add_top(exp, line):
    toml = exp / "experiment.toml"
    toml.write_text(line + "\n" + toml.read_text())


def rewrite_view(exp, k, data=None, **meta):
    from semlab.io import read_image

    p = exp / "end_state" / f"view_{k}.tif"
    im = read_image(p)
    if data is None:
        data = im.data.astype(np.uint16)
    kw = {"pixel_size_um": im.pixel_size_um, "tilt_deg": im.tilt_deg}
    kw.update(meta)
    write_tiff(p, data, overwrite=True, **kw)


def encode_file(path, how):
    text = Path(path).read_text(encoding="utf-8")
    if how == "utf16":
        data = text.encode("utf-16")
    elif how == "utf16le-nobom":
        data = text.encode("utf-16-le")
    elif how == "latin1":
        data = ("# µ = micro\n" + text if path.suffix != ".json" else
                text.replace('"schema"', '"note": "5 µm", "schema"', 1)).encode("latin-1")
    else:  # binary garbage
        data = bytes(np.random.default_rng(0).integers(0, 256, 600, dtype=np.uint8))
    Path(path).write_bytes(data)


# --------------------------------------------------------------------- the table of cases
def _enc(target, how):
    def mutate(exp):
        encode_file(exp / target, how)
    return mutate


ENCODINGS = {"utf16": ("UTF-16", "iconv -f UTF-16"), "utf16le-nobom": ("UTF-16LE", "iconv"),
             "latin1": ("Latin-1", "iconv -f latin1 -t utf-8"), "binary": ("binary", "not a text file")}

CASES = {}
for target, name in (("experiment.toml", "experiment.toml"),
                     ("annotations/correspondences.csv", "correspondences.csv"),
                     ("annotations/lines.json", "lines.json")):
    for how, (seems, fix) in ENCODINGS.items():
        CASES[f"{name}-{how}"] = (_enc(target, how), [name, "not UTF-8", seems, fix])

for value in ("1e300", "1e6", "1e-9", "0", "-0.03", "nan", "inf"):
    CASES[f"pixel_size_um={value}"] = (
        lambda exp, v=value: add_top(exp, f"pixel_size_um = {v}"),
        ["experiment.toml", "pixel_size_um", "µm per pixel"])

for value in (-0.03, 0.0, float("nan"), 1e6):
    CASES[f"metadata-pixel-size={value}"] = (
        lambda exp, v=value: rewrite_view(exp, 0, pixel_size_um=v),
        ["view_0.tif", "pixel size in the image's SEM metadata", "add pixel_size_um"])

for tilts in ("[0, 90]", "[-90, 90]", "[-5, 715]", "[-5, 80]", "[-5, nan]", "[-5, inf]"):
    CASES[f"tilt_deg={tilts}"] = (
        lambda exp, t=tilts: set_toml(exp, "tilt_deg = [-5.0, 5.0]", f"tilt_deg = {t}"),
        ["experiment.toml", "tilt_deg"] + (["nan or inf", "finite number"] if "n" in tilts
                                           else ["below 80°"]))
CASES["tilt_deg-all-equal"] = (
    lambda exp: set_toml(exp, "tilt_deg = [-5.0, 5.0]", "tilt_deg = [5.0, 5.0]"),
    ["experiment.toml", "tilt_deg give every view the same tilt (5°)"])
CASES["tilt_deg-length"] = (
    lambda exp: set_toml(exp, "tilt_deg = [-5.0, 5.0]", "tilt_deg = [-5.0, 0.0, 5.0]"),
    ["experiment.toml", "tilt_deg has 3 values", "one per image"])


def _metadata_tilt(exp):
    set_toml(exp, "tilt_deg = [-5.0, 5.0]\n", "")
    rewrite_view(exp, 1, tilt_deg=715.0)


CASES["metadata-tilt=715"] = (_metadata_tilt, ["view_1.tif", "stage tilt", "tilt_deg"])
CASES["same-file-twice"] = (
    lambda exp: set_toml(exp, '"end_state/view_1.tif"', '"end_state/view_0.tif"'),
    ["experiment.toml", "views[1]", "same file"])


def _byte_copy(exp):
    shutil.copy(exp / "end_state" / "view_0.tif", exp / "end_state" / "copy.tif")
    set_toml(exp, '"end_state/view_1.tif"', '"end_state/copy.tif"')


def _pixel_copy(exp):
    from semlab.io import read_image

    rewrite_view(exp, 1, data=read_image(exp / "end_state" / "view_0.tif").data.astype(np.uint16),
                 tilt_deg=5.0)


CASES["byte-identical-views"] = (_byte_copy, ["experiment.toml", "copy.tif", "identical pixels"])
CASES["pixel-identical-views"] = (_pixel_copy, ["view_0.tif", "view_1.tif", "identical pixels",
                                                "-5° and 5°"])
CASES["empty-image"] = (lambda exp: (exp / "end_state" / "view_1.tif").write_bytes(b""),
                        ["view_1.tif", "empty (0 bytes)"])


def _truncate(exp):
    p = exp / "series" / "frame_002.tif"
    p.write_bytes(p.read_bytes()[:300])


CASES["truncated-tiff"] = (_truncate, ["frame_002.tif", "cannot read this TIFF", "complete"])
for size in ((3, 3), (16, 300), (40, 40)):
    CASES[f"tiny-image-{size[0]}x{size[1]}"] = (
        lambda exp, s=size: [write_tiff(exp / "end_state" / f"view_{k}.tif",
                                        (np.arange(s[0] * s[1]).reshape(s) * (k + 1) % 255).astype(np.uint8),
                                        pixel_size_um=0.03, overwrite=True) for k in range(2)],
        ["view_0.tif", "too small", "64×64"])


def _repeat_click(exp):
    p = exp / "annotations" / "correspondences.csv"
    lines = p.read_text().splitlines()
    first = lines[1].split(",")
    lines.append(",".join(["999"] + first[1:]))
    p.write_text("\n".join(lines) + "\n")


def _all_same_clicks(exp):
    p = exp / "annotations" / "correspondences.csv"
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0]] + [f"{i},10,10,12,10" for i in range(8)]) + "\n")


# wrong types and wrong files in the right places
CASES["pixel_size_um-string"] = (lambda exp: add_top(exp, 'pixel_size_um = "0.03"'),
                                 ["experiment.toml", "pixel_size_um", "remove the quotes"])
CASES["name-table"] = (lambda exp: set_toml(exp, 'name = "', 'name = [1, 2]  # "'),
                       ["experiment.toml", "name must be a string"])
CASES["lines-is-an-image"] = (
    lambda exp: set_toml(exp, '"annotations/lines.json"', '"calibration/block_0.png"'),
    ["block_0.png", "lines file", "not a text file"])
CASES["correspondences-is-an-image"] = (
    lambda exp: set_toml(exp, '"annotations/correspondences.csv"', '"end_state/view_0.tif"'),
    ["view_0.tif", "correspondences file", "not a text file"])
CASES["tif-holding-a-png"] = (
    lambda exp: shutil.copy(exp / "calibration" / "block_0.png", exp / "end_state" / "view_1.tif"),
    ["view_1.tif", "cannot read this TIFF"])


def _text_as_png(exp):
    (exp / "end_state" / "x.png").write_text("not an image")
    set_toml(exp, '"end_state/view_1.tif"', '"end_state/x.png"')


def _nan_image(exp):
    import tifffile

    tifffile.imwrite(exp / "end_state" / "view_1.tif", np.full((96, 128), np.nan, np.float32))


def _truncated_jpeg(exp):
    import cv2

    from semlab.io import read_image

    im = read_image(exp / "end_state" / "view_1.tif").data
    p = exp / "end_state" / "view_1.jpg"
    cv2.imwrite(str(p), np.clip(im, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95])
    p.write_bytes(p.read_bytes()[: p.stat().st_size * 2 // 3])   # libjpeg fills it with grey
    set_toml(exp, '"end_state/view_1.tif"', '"end_state/view_1.jpg"')


CASES["truncated-jpeg"] = (_truncated_jpeg, ["view_1.jpg", "damaged", "Premature end of JPEG"])
CASES["png-holding-text"] = (_text_as_png, ["x.png", "cannot read this image", "re-export"])
CASES["nan-image"] = (_nan_image, ["view_1.tif", "NaN", "8/16-bit"])

CASES["repeated-click"] = (_repeat_click, ["correspondences.csv", "point_id 999", "same position",
                                           "delete the repeated"])
CASES["identical-clicks"] = (_all_same_clicks, ["correspondences.csv", "line 3", "same position"])


@pytest.mark.parametrize("case", sorted(CASES))
def test_hostile_experiment_is_refused_in_one_line(case, small_experiment, tmp_path, capsys,
                                                   caplog):
    mutate, expected = CASES[case]
    mutate(small_experiment)
    before = checksum(small_experiment)
    caplog.set_level(logging.DEBUG)
    for argv in (["info", str(small_experiment)],
                 ["run", str(small_experiment), "--out", str(tmp_path / "out"), "--quiet"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("semlab: error: "), err
        assert "Traceback" not in err
        for fragment in expected:
            assert fragment in err, (fragment, err)
    assert not (tmp_path / "out").exists()          # refused before any work
    assert checksum(small_experiment) == before
    assert not [r for r in caplog.records if r.name.startswith("tifffile")]


def test_utf8_with_bom_is_read(small_experiment, capsys):
    for name in ("experiment.toml", "annotations/correspondences.csv", "annotations/lines.json"):
        p = small_experiment / name
        p.write_bytes(codecs.BOM_UTF8 + p.read_bytes())
    assert main(["info", str(small_experiment)]) == 0
    assert "stereo: 2 views" in capsys.readouterr().out


# ------------------------------------------------------------------ not an experiment
@pytest.mark.parametrize("what", ["image", "random-file", "folder-without-toml", "other-toml"])
def test_info_on_something_that_is_not_an_experiment(what, small_experiment, tmp_path, capsys):
    if what == "image":
        target, expected = small_experiment / "end_state" / "view_0.tif", "is an image, not an experiment"
    elif what == "random-file":
        target = tmp_path / "notes.dat"
        target.write_bytes(os.urandom(64))
        expected = "is a file, not an experiment"
    elif what == "folder-without-toml":
        target, expected = small_experiment / "series", "without experiment.toml"
    else:
        target = tmp_path / "pyproject.toml"
        target.write_text('[project]\nname = "x"\n')
        expected = "unknown key 'project'"
    assert main(["info", str(target)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expected in err and str(target.name) in err


# ------------------------------------------------------------------------- --out folders
def _out_cases(exp, tmp_path):
    afile = tmp_path / "a_file.txt"
    afile.write_text("x")
    link = tmp_path / "link"
    link.symlink_to(exp / "series")
    return {
        "experiment-folder": (exp, "inside the experiment folder"),
        "experiment-subfolder": (exp / "series", "inside the experiment folder"),
        "new-folder-in-experiment": (exp / "report", "inside the experiment folder"),
        "symlink-into-experiment": (link, "inside the experiment folder"),
        "notebooks-folder": (ROOT / "notebooks" / "report", "notebooks folder"),
        "proc": (Path("/proc/semlab-report"), "system folder"),
        "a-file": (afile, "is a file"),
        "under-a-file": (afile / "sub", "is a file"),
    }


OUT_CASES = ["experiment-folder", "experiment-subfolder", "new-folder-in-experiment",
             "symlink-into-experiment", "notebooks-folder", "proc", "a-file", "under-a-file"]


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("case", OUT_CASES)
def test_bad_out_folder_is_refused_before_any_work(case, force, small_experiment, tmp_path, capsys):
    out, expected = _out_cases(small_experiment, tmp_path)[case]
    before = checksum(small_experiment)
    argv = ["run", str(small_experiment), "--out", str(out), "--quiet"] + (["--force"] if force else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("semlab: error: --out") and expected in err, err
    assert checksum(small_experiment) == before
    assert not (ROOT / "notebooks" / "report").exists()


def test_unwritable_out_folder_is_refused(small_experiment, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "readonly"
    ro.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == ro
                        else real_access(p, mode, **kw))
    assert main(["run", str(small_experiment), "--out", str(ro / "report"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "cannot write in" in err and str(ro) in err and err.count("\n") == 1
    assert not (ro / "report").exists()


# -------------------------------------------------------------- steps that must refuse
def test_header_only_correspondences_named_for_clicked_methods(small_experiment):
    from semlab import experiment, pipeline

    p = small_experiment / "annotations" / "correspondences.csv"
    p.write_text(p.read_text().splitlines()[0] + "\n")
    exp = experiment.load(small_experiment)
    with pytest.raises(SemlabError, match=r"correspondences\.csv: method 'raw' .* only its header"):
        pipeline.run_stereo(exp, method="raw", n_boot=0, progress=False)


def test_perspective_camera_on_sem_views_refused_before_heights(small_experiment):
    """The issue's case: the demo-like affine views with camera = "perspective" gave heights
    of -1849 ... +5223 µm; now the stereo step refuses them (no result is returned)."""
    from semlab import experiment, pipeline

    set_toml(small_experiment, 'camera = "affine"', 'camera = "perspective"')
    exp = experiment.load(small_experiment)
    with pytest.raises(GeometryError, match=r"experiment\.toml: \[stereo\] camera = 'perspective'.*"
                                            r"as well as a perspective one.*use camera = 'affine'"):
        pipeline.run_stereo(exp, n_boot=0, progress=False)


def test_perspective_check_passes_true_perspective_and_refuses_affine_noise():
    from semlab import reconstruct
    from semlab.camera import project_affine, project_perspective, rotation_about_axis
    from semlab.epipolar import fundamental_8point

    rng = np.random.default_rng(1)
    X = np.column_stack([rng.uniform(-40, 40, 200), rng.uniform(-30, 30, 200),
                         rng.uniform(-8, 8, 200)])
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    R = rotation_about_axis([0, 1, 0], np.deg2rad(8))
    a = project_perspective(X, K, np.eye(3), np.array([0, 0, 150.0]))
    b = project_perspective(X, K, R, np.array([0, 0, 150.0]))
    a, b = a + rng.normal(0, 0.1, a.shape), b + rng.normal(0, 0.1, b.shape)
    r_aff, r_per = reconstruct.check_perspective_visible(a, b, fundamental_8point(a, b))
    assert r_aff > 10 * r_per
    # an affine (SEM) pair with the same noise: the eight-point F exists but fits only noise
    a = project_affine(X, 0.0, 0.05, (320, 240)) + rng.normal(0, 0.1, (200, 2))
    b = project_affine(X, 8.0, 0.05, (320, 240)) + rng.normal(0, 0.1, (200, 2))
    with pytest.raises(GeometryError, match="use camera = 'affine'"):
        reconstruct.check_perspective_visible(a, b, fundamental_8point(a, b))


# ------------------------------------------------------------------------------ noise
def test_warnings_are_one_line_without_source(small_experiment):
    """A TOML value overriding the metadata is a warning: one line, no source line."""
    add_top(small_experiment, "pixel_size_um = 0.05")
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="default")
    r = subprocess.run([sys.executable, "-m", "semlab.cli", "info", str(small_experiment)],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stderr.splitlines() == [
        "semlab: warning: view_0.tif: experiment.toml pixel_size_um 0.05 µm overrides the "
        "image metadata 0.03 µm"]


def test_semlab_warnings_format_as_one_line():
    import warnings

    from semlab import pipeline
    from semlab.errors import SemlabWarning

    fmt = warnings.formatwarning
    assert fmt("odd", SemlabWarning, "/elsewhere/user.py", 3) == "semlab: warning: odd\n"
    assert fmt("odd", UserWarning, pipeline.__file__, 3) == "semlab: warning: odd\n"
    assert "user.py:3" in fmt("odd", UserWarning, "/elsewhere/user.py", 3)  # not ours


def test_cli_error_has_no_traceback_in_a_real_process(small_experiment):
    encode_file(small_experiment / "experiment.toml", "latin1")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-m", "semlab.cli", "info", str(small_experiment)],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and "iconv -f latin1 -t utf-8" in r.stderr


def test_atomic_writer_leaves_old_file_on_failure(tmp_path, monkeypatch):
    from semlab import io

    p = tmp_path / "points3d.csv"
    io.atomic_write_text(p, "old\n")

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(io.os, "replace", boom)
    with pytest.raises(OSError):
        io.atomic_write_text(p, "new\n")
    monkeypatch.undo()
    assert p.read_text() == "old\n" and sorted(x.name for x in tmp_path.iterdir()) == ["points3d.csv"]
    assert io.write_with_backup(p, "new\n") == tmp_path / "points3d.bak.csv"
    assert p.read_text() == "new\n" and (tmp_path / "points3d.bak.csv").read_text() == "old\n"


# --------------------------------------------------------------- --force and failed runs
def _fake_notebooks(tmp_path, fail):
    """Two tiny notebooks: 00 writes points3d.csv, 01 fails when ``fail``."""
    import nbformat
    from nbformat.v4 import new_code_cell, new_notebook

    d = tmp_path / ("nbs_fail" if fail else "nbs_ok")
    d.mkdir()
    par = new_code_cell('experiment = ""\nout_dir = None\ntag = "x"', metadata={"tags": ["parameters"]})
    w = new_notebook(cells=[par, new_code_cell(
        "from pathlib import Path\n"
        "Path(out_dir, 'points3d.csv').write_text('run ' + Path(out_dir).name + '\\n')")])
    second = new_notebook(cells=[par.copy(), new_code_cell(
        "raise RuntimeError('step broke')" if fail else "print('ok')")])
    for nb in (w, second):
        nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(w, str(d / "00_write.ipynb"))
    nbformat.write(second, str(d / "01_second.ipynb"))
    return d


@pytest.mark.slow
def test_force_replaces_results_only_after_success(small_experiment, tmp_path, monkeypatch, capfd):
    out = tmp_path / "report"
    before = checksum(small_experiment)
    ok, bad = _fake_notebooks(tmp_path, False), _fake_notebooks(tmp_path, True)
    monkeypatch.setenv("SEMLAB_NOTEBOOKS", str(ok))
    assert main(["run", str(small_experiment), "--out", str(out), "--quiet"]) == 0
    first = (out / "points3d.csv").read_text()
    (out / "my_notes.txt").write_text("mine")
    (out / "01_second.html").write_text("stale")
    # a failing --force run changes nothing in out
    monkeypatch.setenv("SEMLAB_NOTEBOOKS", str(bad))
    assert main(["run", str(small_experiment), "--out", str(out), "--force", "--quiet"]) == 2
    err = capfd.readouterr().err
    assert "01_second.ipynb failed" in err and "no result file was written" in err
    assert "IPKernelApp" not in err and "Traceback" not in err
    assert (out / "points3d.csv").read_text() == first
    kept = {p.name for p in (out / "failed_run").iterdir()}
    assert not [n for n in kept if n.endswith((".csv", ".txt", ".json", ".npz"))]
    assert {"00_write.html", "01_second.ipynb", "01_second.html", "report.css"} <= kept
    # a successful --force run replaces semlab's files, keeps the user's, drops the failed run
    monkeypatch.setenv("SEMLAB_NOTEBOOKS", str(ok))
    assert main(["run", str(small_experiment), "--out", str(out), "--force", "--quiet"]) == 0
    assert (out / "points3d.csv").read_text() != first
    assert (out / "my_notes.txt").read_text() == "mine"
    assert "stale" not in (out / "01_second.html").read_text()
    assert not (out / "failed_run").exists()
    # nothing hidden is left but the analysis step cache (kept between runs, holds no result)
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [".semlab"]
    assert not list((out / ".semlab").glob("*.csv"))
    assert ".semlab-run-" not in (out / "00_write.html").read_text()   # reports name out
    assert checksum(small_experiment) == before


@pytest.mark.slow
def test_perspective_run_writes_no_points3d(small_experiment, tmp_path, capfd):
    """Through the real notebooks (00 and 04): the refused stereo step leaves no result
    of its own; it is the error of that step, named with the fix in the message (exit 2)
    and in the report, whose notebooks go on without it."""
    set_toml(small_experiment, 'camera = "affine"', 'camera = "perspective"')
    out = tmp_path / "report"
    before = checksum(small_experiment)
    assert main(["run", str(small_experiment), "--out", str(out), "--only", "00,04",
                 "--quiet"]) == 2
    err = capfd.readouterr().err
    assert "step 'stereo' failed" in err and "use camera = 'affine'" in err
    assert "IPKernelApp" not in err and "Traceback" not in err
    files = {p.name for p in out.iterdir()}
    assert not files & {"points3d.csv", "calibration.json", "heightmap.tif", "failed_run"}
    assert "use camera = 'affine'" in (out / "04_depth.ipynb").read_text()
    assert checksum(small_experiment) == before


def test_interrupt_is_one_line(small_experiment, tmp_path, monkeypatch, capsys):
    import semlab.report

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(semlab.report, "run", interrupted)
    assert main(["run", str(small_experiment), "--out", str(tmp_path / "o"), "--quiet"]) == 130
    assert capsys.readouterr().err == "semlab: interrupted (no result file was written)\n"


def test_impossible_metadata_is_ignored_when_the_toml_gives_the_value(small_experiment):
    from semlab import experiment
    from semlab.errors import SemlabWarning

    rewrite_view(small_experiment, 0, pixel_size_um=-0.03, tilt_deg=715.0)
    add_top(small_experiment, "pixel_size_um = 0.03")
    with pytest.warns(SemlabWarning) as rec:
        exp = experiment.load(small_experiment)
    text = " | ".join(str(w.message) for w in rec)
    assert "view_0.tif: the image metadata pixel size -0.03 µm is impossible" in text
    assert "the image metadata tilt 715° is impossible; using experiment.toml's -5°" in text
    assert exp.pixel_size_um == 0.03 and exp.stereo.tilt_deg == [-5.0, 5.0]
