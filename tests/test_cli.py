"""The command line: info, synth, run (refuses non-empty output folders)."""

import sys

import numpy as np
import pytest

import semlab
from semlab.cli import main


def test_info_prints_summary(small_experiment_master, capsys):
    assert main(["info", str(small_experiment_master)]) == 0
    out = capsys.readouterr().out
    assert "pixel size: 0.03 µm/px (from metadata:view_0.tif)" in out
    assert "series: 4 frames" in out and "view 1:" in out


def test_info_on_bad_folder_gives_error_exit(tmp_path, capsys):
    assert main(["info", str(tmp_path)]) == 2
    assert "experiment file not found" in capsys.readouterr().err


def test_synth_writes_experiment(tmp_path):
    out = tmp_path / "s"
    assert main(["synth", str(out), "--seed", "2", "--size", "64x96", "--frames", "2",
                 "--tilts=-5,0,5", "--clicks", "6", "--quiet"]) == 0
    from semlab.experiment import load

    exp = load(out)
    assert exp.stereo.tilt_deg == [-5.0, 0.0, 5.0] and exp.stereo.shape == (64, 96)
    assert len(exp.series.frame_paths) == 2
    # and refuses to overwrite it
    assert main(["synth", str(out), "--quiet"]) == 2


def test_synth_series_only(tmp_path):
    out = tmp_path / "s"
    assert main(["synth", str(out), "--size", "64x96", "--frames", "3", "--tilts=", "--quiet"]) == 0
    from semlab.experiment import load

    exp = load(out)
    assert exp.stereo is None and len(exp.frames()) == 3


def test_synth_drift_writes_its_truth(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["synth", str(out), "--size", "64x96", "--frames", "3", "--tilts=", "--quiet",
                 "--drift", "10,1,0.002"]) == 0
    from semlab.registration import read_drift_csv

    d = read_drift_csv(out / "truth" / "drift.csv")
    assert len(d["frame"]) == 3 and d["dx_px"][-1] == 0 and 5 <= np.hypot(d["dx_px"][0], d["dy_px"][0]) <= 10
    assert main(["synth", str(tmp_path / "e"), "--quiet", "--drift", "10,1"]) == 2
    assert "--drift takes" in capsys.readouterr().err


def test_run_refuses_nonempty_out(small_experiment_master, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    assert main(["run", str(small_experiment_master), "--out", str(out), "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (out / "precious.txt").read_text() == "keep me"


def test_run_unknown_notebook_number(small_experiment_master, tmp_path, capsys):
    assert main(["run", str(small_experiment_master), "--out", str(tmp_path / "o"),
                 "--only", "99", "--quiet"]) == 2
    assert "no such notebook" in capsys.readouterr().err


@pytest.mark.slow
def test_run_executes_notebook_and_writes_html(small_experiment_master, tmp_path):
    out = tmp_path / "report"
    assert main(["run", str(small_experiment_master), "--out", str(out), "--only", "00",
                 "--quiet"]) == 0
    assert (out / "00_experiment.ipynb").is_file()
    html = (out / "00_experiment.html").read_text()
    assert "hide code" in html and "views=2 frames=4" in html
    assert "00_experiment.html" in (out / "index.html").read_text()


def _failing_notebooks(tmp_path):
    import nbformat
    from nbformat.v4 import new_code_cell, new_notebook

    d = tmp_path / "nbs"
    d.mkdir()
    ok = new_notebook(cells=[new_code_cell('experiment = ""\nout_dir = None', metadata={"tags": ["parameters"]}),
                             new_code_cell("print('fine')")])
    bad = new_notebook(cells=[new_code_cell('experiment = ""\nout_dir = None', metadata={"tags": ["parameters"]}),
                              new_code_cell("raise ValueError('broken analysis step')")])
    for nb in (ok, bad):
        nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nbformat.write(ok, str(d / "00_ok.ipynb"))
    nbformat.write(bad, str(d / "01_bad.ipynb"))
    return d


@pytest.mark.slow
def test_run_failing_notebook_gives_error_and_nonzero_exit(small_experiment_master, tmp_path,
                                                           monkeypatch, capsys):
    monkeypatch.setenv("SEMLAB_NOTEBOOKS", str(_failing_notebooks(tmp_path)))
    out = tmp_path / "report"
    assert main(["run", str(small_experiment_master), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "01_bad.ipynb failed" in err and "ValueError: broken analysis step" in err
    # all or nothing: the partial report is kept apart, no result file is written
    failed = out / "failed_run"
    assert (failed / "00_ok.html").is_file() and (failed / "01_bad.ipynb").is_file()
    assert sorted(p.name for p in out.iterdir()) == [".semlab", "failed_run"]  # + step cache
    assert not any(p.suffix in (".csv", ".json", ".npz", ".txt") for p in failed.iterdir())
    # --only re-runs a part, into the same folder
    assert main(["run", str(small_experiment_master), "--out", str(out), "--only", "00",
                 "--quiet"]) == 0
    assert (out / "00_ok.html").is_file() and not failed.exists()


@pytest.mark.slow
def test_run_with_a_failed_tracking_step_keeps_the_rest(small_experiment_master, tmp_path,
                                                        monkeypatch, capsys):
    """A series whose tracking fails (every track lost, as on a featureless series): the
    notebooks of the series say so once and go on, the stereo results and the whole report
    are written, and the run ends with an error naming the tracking step (it stopped in
    notebook 05 with no result file at all before)."""
    from semlab import series

    def lost(*a, **k):
        raise semlab.SemlabError("every track was lost at the first step (a test)")

    monkeypatch.setattr(series, "run_tracking", lost)
    out = tmp_path / "report"
    assert main(["run", str(small_experiment_master), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "step 'tracking' failed" in err and err.count("every track was lost") == 1
    assert "step 'strain' failed: it needs the tracking step, which failed" in err
    files = {p.name for p in out.iterdir()}
    assert {"points3d.csv", "calibration.json", "index.html", "05_tracking.html",
            "07_strain.html", "08_validation.html"} <= files
    assert not files & {"tracks.csv", "strain.npz", "failed_run"}
    nb = (out / "05_tracking.ipynb").read_text()
    assert "every track was lost at the first step (a test)" in nb


@pytest.mark.slow
@pytest.mark.parametrize("only", ["stereo", "series"])
def test_run_on_partial_experiment_finishes(tmp_path, only, capsys):
    """An experiment with only [stereo] or only [series]: every notebook finishes cleanly."""
    from semlab.synth import make_experiment

    exp = tmp_path / "exp"
    if only == "stereo":
        make_experiment(exp, seed=1, size=(128, 160), n_frames=0, n_clicks=12, progress=False)
    else:
        make_experiment(exp, seed=1, size=(128, 160), tilts_deg=(), n_frames=3, progress=False)
    out = tmp_path / "report"
    from test_hostile_inputs import checksum

    before = checksum(exp)
    code = main(["run", str(exp), "--out", str(out), "--quiet"])
    assert checksum(exp) == before                 # the experiment folder is only read
    files = {p.name for p in out.iterdir()}
    if only == "series" and "strain.npz" not in files:
        # too few tracks in so small a series for strain: an error of that step, named in
        # the exit status and the message, never an empty strain.npz
        assert code == 2 and "step 'strain' failed" in capsys.readouterr().err
        files.add("strain.npz")
    else:
        assert code == 0
    assert "index.html" in files and "08_validation.html" in files
    if only == "stereo":
        assert {"points3d.csv", "calibration.json"} <= files and "tracks.csv" not in files
    else:
        assert {"tracks.csv", "displacements.csv", "strain.npz"} <= files and "points3d.csv" not in files
    import re

    # every step ran once, in semlab run itself; the notebooks only loaded the cache
    import json

    log = [json.loads(line) for line in (out / ".semlab" / "steps.jsonl").read_text().splitlines()]
    computed = [(e["step"], e["key"]) for e in log if e["event"] != "cached"]
    assert len(computed) == len(set(computed)) and len({e["pid"] for e in log
                                                          if e["event"] != "cached"}) == 1
    assert any(e["event"] == "cached" for e in log)
    if sys.platform.startswith("linux"):
        # each entry carries the process's peak memory so far (which step raised it)
        peaks = [e["peak_rss_gb"] for e in log if e["event"] != "cached"]
        assert all(p > 0.01 for p in peaks) and peaks == sorted(peaks)
    html = (out / "05_tracking.html").read_text()
    # the printed summary (not the code, which the HTML also shows) tells what ran
    tracked = re.search(r"\d+ tracks \(\d+ corner-seeded", html) is not None
    assert tracked == (only == "series")


def _images(folder, names, pixel_size_um=None, tilts=None, seed=0):
    """Distinct textured 8-bit images ``names`` in ``folder`` (with Zeiss metadata when given)."""
    from semlab.io import write_tiff

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i, n in enumerate(names):
        img = rng.integers(0, 255, (80, 96)).astype(np.uint8)
        p = folder / n
        if p.suffix == ".tif":
            write_tiff(p, img, pixel_size_um=pixel_size_um,
                       tilt_deg=None if tilts is None else tilts[i])
        else:
            import cv2

            cv2.imwrite(str(p), img)
        paths.append(p)
    return paths


def test_init_writes_an_experiment_that_loads(tmp_path, capsys):
    _images(tmp_path / "data" / "tilt", ["v_m5.tif", "v_p5.tif"], pixel_size_um=0.02,
            tilts=[-5.0, 5.0])
    _images(tmp_path / "data" / "series", ["f10.tif", "f2.tif", "f1.tif"], pixel_size_um=0.02,
            seed=1)
    out = tmp_path / "exp"
    assert main(["init", str(out), "--views", str(tmp_path / "data" / "tilt"),
                 "--frames", str(tmp_path / "data" / "series" / "f*.tif"),
                 "--cycles", "100,200,1000"]) == 0
    assert "semlab run" in capsys.readouterr().out
    from semlab.experiment import load

    exp = load(out)
    # pixel size and tilts from the metadata, frames in natural (not character) order
    assert exp.pixel_size_um == 0.02 and exp.stereo.tilt_deg == [-5.0, 5.0]
    assert [p.name for p in exp.series.frame_paths] == ["f1.tif", "f2.tif", "f10.tif"]
    assert exp.series.cycles.tolist() == [100, 200, 1000]
    # the images stay where they are, named relative to the new folder
    text = (out / "experiment.toml").read_text()
    assert '"../data/tilt/v_m5.tif"' in text and sorted(p.name for p in out.iterdir()) == \
        ["experiment.toml"]


def test_init_refuses_and_writes_nothing(tmp_path, capsys):
    views = _images(tmp_path / "png", ["a.png", "b.png", "c.png"])
    out = tmp_path / "exp"
    # no pixel size in PNGs: asked for, nothing written
    assert main(["init", str(out), "--views", str(tmp_path / "png")]) == 2
    assert "--pixel-size" in capsys.readouterr().err and not out.exists()
    # a tilt list of the wrong length
    assert main(["init", str(out), "--views", *map(str, views), "--pixel-size", "0.03",
                 "--tilts=-5,5"]) == 2
    assert "3 views" in capsys.readouterr().err and not out.exists()
    # a copy of one view: load refuses it, and init leaves no file behind
    (tmp_path / "png" / "d.png").write_bytes(views[0].read_bytes())
    assert main(["init", str(out), "--views", str(tmp_path / "png"), "--pixel-size",
                 "0.03"]) == 2
    assert "identical pixels" in capsys.readouterr().err and not out.exists()
    # one image, a folder without images, a non-empty target
    assert main(["init", str(out), "--views", str(views[0]), "--pixel-size", "0.03"]) == 2
    assert "only one image" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["init", str(out), "--frames", str(tmp_path / "empty")]) == 2
    assert "holds no image" in capsys.readouterr().err
    assert main(["init", str(tmp_path / "png"), "--views", str(views[0])]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == ["a.png", "b.png", "c.png",
                                                                      "d.png"]
    # a damaged image found while loading the written file: nothing left behind either
    (tmp_path / "png" / "d.png").write_bytes(b"not a png")
    assert main(["init", str(out), "--views", str(tmp_path / "png"), "--pixel-size",
                 "0.03"]) == 2
    assert "d.png" in capsys.readouterr().err and not out.exists()
    # given a pixel size, the three distinct views load (tilts to be estimated)
    (tmp_path / "png" / "d.png").unlink()
    assert main(["init", str(out), "--views", str(tmp_path / "png"), "--pixel-size",
                 "0.03"]) == 0
    assert "tilts from: unknown" in capsys.readouterr().out
