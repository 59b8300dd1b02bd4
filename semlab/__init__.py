"""semlab: surface heights and in-plane displacements of fatigue-tested metal from SEM images.

Conventions (see DESIGN notes in the README):

- images are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)`` in pixels,
  x to the right, y down, origin at the centre of the top-left pixel;
- lengths in µm (``_um``), angles given by people in degrees (``_deg``), radians inside maths;
- affine SEM camera at stage tilt θ about the image y axis:
  ``u = cx + (x cosθ + z sinθ) / s``, ``v = cy + y / s``, z > 0 is an extrusion.
"""

__version__ = "0.1.0"

from .errors import SemlabError, SemlabWarning, install_warning_format  # noqa: F401

install_warning_format()
