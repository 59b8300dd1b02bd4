"""The committed notebooks are what ``tools/make_notebooks.py`` writes.

The notebooks are generated (the tool is their source); an edit made in an ``.ipynb`` only is
undone by the next ``python tools/make_notebooks.py``. That happened once (2026-12-07: the
notebooks' ``Analysis.optional`` steps and a known-answer check lived only in the
``.ipynb`` files), so the two are compared here, cell by cell.
"""

import importlib.util
from pathlib import Path

import nbformat

ROOT = Path(__file__).resolve().parents[1]


def test_committed_notebooks_are_the_generators_output():
    spec = importlib.util.spec_from_file_location("make_notebooks",
                                                  ROOT / "tools" / "make_notebooks.py")
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert len(tool.NOTEBOOKS) >= 9
    for name, cells in tool.NOTEBOOKS.items():
        committed = nbformat.read(ROOT / "notebooks" / f"{name}.ipynb", as_version=4)
        want = [(c.cell_type, c.source) for c in cells]
        got = [(c.cell_type, c.source) for c in committed.cells]
        assert got == want, (f"notebooks/{name}.ipynb is not what tools/make_notebooks.py "
                             "writes: edit the tool, then run python tools/make_notebooks.py")
