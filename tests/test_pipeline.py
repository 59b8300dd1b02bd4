"""The stereo pipeline end to end on synthetic experiments with truth."""

import warnings

import numpy as np
import pytest

from semlab import experiment, pipeline, synth, validation
from semlab.errors import GeometryError


def _make(tmp_path, **kw):
    kw.setdefault("n_frames", 0)
    kw.setdefault("progress", False)
    return experiment.load(synth.make_experiment(tmp_path / "exp", **kw))


def test_three_views_unknown_tilts_are_estimated(tmp_path):
    """-5/0/+5° with no tilt anywhere: tilts estimated (differences within 0.1°), heights
    within 10 nm RMSE of the truth."""
    tilts = np.array([-5.0, 0.0, 5.0])
    exp = _make(tmp_path, seed=0, tilts_deg=tuple(tilts), tilt_in_toml=False,
                tilt_in_metadata=False, write_block=False)
    assert exp.stereo.tilt_deg is None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = pipeline.run_stereo(exp, method="auto", n_boot=0, progress=False)
    assert res.tilt_source == "estimated"
    rel = res.tilt_deg - res.tilt_deg[1]
    assert np.abs(rel - (tilts - tilts[1])).max() < 0.1
    assert np.all(np.asarray(res.tilt_sigma_deg) < 0.1)
    zt = validation.true_height_at(exp.truth_dir, res.pts[:, 0])
    err = validation.height_errors(res.z_um, zt, res.xyz_um[:, :2])
    assert err["n"] >= 1000 and err["rmse_um"] < 0.010


def test_two_views_without_tilt_or_lines_raise_bas_relief(tmp_path):
    exp = _make(tmp_path, seed=1, size=(128, 160), tilt_in_toml=False, tilt_in_metadata=False,
                write_block=False, n_clicks=12)
    with pytest.raises(GeometryError, match="bas-relief"):
        pipeline.run_stereo(exp, method="refined", n_boot=0, progress=False)


def test_empty_correspondences_file_means_automatic_matching(tmp_path):
    """A correspondences CSV with a header and no rows (a picker session that saved nothing)
    is treated as no clicks: automatic matching, not an error."""
    exp = _make(tmp_path, seed=2, size=(160, 200), write_block=False, n_clicks=12)
    csv = exp.stereo.correspondences_path
    csv.write_text(csv.read_text().splitlines()[0] + "\n")
    exp = experiment.load(exp.toml_path)
    assert len(exp.correspondences().pts) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = pipeline.run_stereo(exp, n_boot=0, progress=False)
    assert res.method == "auto" and len(res.pts) > 50
