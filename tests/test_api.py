"""The public API: what ``import semlab`` gives, its doctests, and strict keywords."""

import doctest

import numpy as np
import pytest

import semlab


def test_all_names_exist():
    for name in semlab.__all__:
        assert getattr(semlab, name) is not None, name


@pytest.mark.parametrize("name", [n for n in semlab.__all__ if n not in ("SemlabError", "SemlabWarning")])
def test_doctest_examples_run(name):
    """Every public function documents an Examples section, and it runs as written."""
    obj = getattr(semlab, name)
    tests = [t for t in doctest.DocTestFinder(recurse=False).find(obj, name) if t.examples]
    if name in ("Heights", "AnalysisConfig", "StepFailed"):
        return  # data holders: documented by the functions that return them
    assert tests, f"semlab.{name} has no Examples section"
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    for t in tests:
        runner.run(t)
    res = runner.summarize(verbose=False)
    assert res.failed == 0, f"{res.failed} doctest example(s) of semlab.{name} failed"


def test_unknown_keyword_names_the_nearest():
    with pytest.raises(TypeError, match="did you mean 'n_boot'"):
        semlab.AnalysisConfig(n_boot=0).replace(nboot=3)
    with pytest.raises(TypeError, match="did you mean 'sigma_px'"):
        semlab.surface_heights(np.zeros((4, 2, 2)), [-5, 5], 0.03, sigma=0.1)


def test_run_stereo_refuses_unknown_keywords(small_experiment):
    from semlab import pipeline

    exp = semlab.load_experiment(small_experiment)
    with pytest.raises(TypeError, match="half_window"):
        pipeline.run_stereo(exp, half_window=15)
