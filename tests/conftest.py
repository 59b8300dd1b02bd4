"""Shared fixtures: a small synthetic experiment, and the location of ../shared/data."""

import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


def shared_path(*parts):
    """Path inside ../shared/data, or skip the test cleanly when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"needs {p} (../shared/data is not present in this checkout)")
    return p


@pytest.fixture(scope="session")
def small_experiment_master(tmp_path_factory):
    """A small synthetic experiment (2 views, 4 frames), made once per test session."""
    from semlab.synth import make_experiment

    out = tmp_path_factory.mktemp("synth") / "exp"
    make_experiment(out, seed=3, size=(96, 128), n_frames=4, n_clicks=12, progress=False)
    return out


@pytest.fixture
def small_experiment(small_experiment_master, tmp_path):
    """A private copy of the small synthetic experiment that a test may edit."""
    dst = tmp_path / "exp"
    shutil.copytree(small_experiment_master, dst)
    return dst


def pytest_collection_modifyitems(config, items):
    """Files holding a ``slow`` test first, each file's tests in their order (a stable sort).

    ``scripts/test.sh`` runs the files in parallel (pytest-xdist, ``--dist loadfile
    --no-loadscope-reorder``), handing them to the workers in this order: a long file started
    last would leave one worker running it alone at the end.
    """
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)
