"""semlab: surface heights and in-plane displacements of fatigue-tested metal from SEM images.

Conventions (see the README):

- images are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)`` in pixels,
  x to the right, y down, origin at the centre of the top-left pixel;
- lengths in µm (``_um``), angles given by people in degrees (``_deg``), radians inside maths;
- affine SEM camera at stage tilt θ about the image y axis:
  ``u = cx + (x cosθ + z sinθ) / s``, ``v = cy + y / s``, z > 0 is an extrusion.

The public API works on plain arrays (:func:`match_views`, :func:`surface_heights`,
:func:`estimate_tilts`, :func:`track_reverse`, :func:`strain_from_tracks`) or on an experiment
folder (:func:`load_experiment`, :class:`Analysis`, which runs every step once, caches it and
writes the result files).
"""

__version__ = "0.2.0"

from .analysis import Analysis, AnalysisConfig, StepFailed
from .errors import SemlabError, SemlabWarning, install_warning_format
from .experiment import load as load_experiment
from .pipeline import Heights, match_views, surface_heights
from .reconstruct import estimate_tilts
from .strain import strain_from_tracks
from .tracking import track_reverse

__all__ = [
    "Analysis",
    "AnalysisConfig",
    "Heights",
    "SemlabError",
    "SemlabWarning",
    "StepFailed",
    "estimate_tilts",
    "load_experiment",
    "match_views",
    "strain_from_tracks",
    "surface_heights",
    "track_reverse",
]

install_warning_format()
