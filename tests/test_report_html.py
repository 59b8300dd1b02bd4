"""HTML pages of a report share one style sheet (they were 280 kB each of the same CSS)."""

import nbformat
from nbformat.v4 import new_code_cell, new_notebook, new_output

from semlab.report import REPORT_CSS, to_html


def _executed(path, text):
    nb = new_notebook(cells=[new_code_cell("print('hi')", outputs=[
        new_output("stream", name="stdout", text=text)])])
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}
    nbformat.write(nb, str(path))
    return path


def test_pages_link_one_shared_style_sheet(tmp_path):
    a = to_html(_executed(tmp_path / "a.ipynb", "first page\n"), tmp_path / "a.html")
    css = tmp_path / REPORT_CSS
    first = css.read_text()
    b = to_html(_executed(tmp_path / "b.ipynb", "second page\n"), tmp_path / "b.html")
    assert len(first) > 100_000 and css.read_text() == first      # one copy, the same
    for page, text in ((a, "first page"), (b, "second page")):
        html = page.read_text()
        assert f'<link rel="stylesheet" href="{REPORT_CSS}">' in html
        assert text in html and len(html) < 60_000
        assert ".jp-Notebook" not in html.split("</head>")[0]     # the big CSS is not inline


def test_a_warning_said_by_several_steps_is_printed_once():
    from semlab.report import step_warning_lines

    said = {"stereo": ["10 clicks left out", "tilts from the stage"],
            "tracking": ["no valid track in frame 0"],
            "stereo_refined": ["10 clicks left out"]}
    assert step_warning_lines(said) == [
        "semlab: warning (stereo, stereo_refined): 10 clicks left out",
        "semlab: warning (stereo): tilts from the stage",
        "semlab: warning (tracking): no valid track in frame 0"]
    assert step_warning_lines({}) == []
