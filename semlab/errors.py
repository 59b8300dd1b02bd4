"""Exceptions raised by semlab.

Every error a user can cause (a missing file, a typo in ``experiment.toml``, too few
points, a degenerate geometry) is a :class:`SemlabError`; its message names the file or
the argument at fault and says how to fix it.
"""


class SemlabError(ValueError):
    """Base class of all user-facing semlab errors (a ``ValueError``)."""


class ExperimentError(SemlabError):
    """An experiment folder or its ``experiment.toml`` is invalid."""


class ImageError(SemlabError):
    """An image file cannot be read or does not fit the experiment."""


class GeometryError(SemlabError):
    """Too few points, degenerate configuration, or an ill-conditioned estimate."""


class TrackingError(SemlabError):
    """Tracking cannot proceed (one frame, blank images, every track lost)."""


class SemlabWarning(UserWarning):
    """A remark about the input that does not stop the analysis (e.g. the TOML overrides the
    image metadata). Shown as one line, ``semlab: warning: ...``, without a source line."""


def _is_semlab_warning(category, filename):
    """A warning of semlab's: its category, or raised from semlab's own source files."""
    import os

    if issubclass(category, SemlabWarning) or category.__module__.startswith("semlab."):
        return True
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        return os.path.commonpath([here, os.path.abspath(filename)]) == here
    except (TypeError, ValueError):
        return False


def install_warning_format():
    """Show semlab's warnings as one line ``semlab: warning: <message>``.

    Python prints a warning with the file, line number and the source line that raised it,
    which buries the message a user needs. Only semlab's warnings (:class:`SemlabWarning`,
    the warning classes defined in semlab's modules, and warnings raised from semlab's
    source files) are reformatted; other warnings keep Python's format. Installed when semlab is imported;
    calling it again does nothing.
    """
    import warnings

    previous = warnings.formatwarning
    if getattr(previous, "_semlab", False):
        return

    def formatwarning(message, category, filename, lineno, line=None):
        if _is_semlab_warning(category, filename):
            return f"semlab: warning: {message}\n"
        return previous(message, category, filename, lineno, line)

    formatwarning._semlab = True
    warnings.formatwarning = formatwarning
