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
