"""Command-line helpers shared by the benchmark scripts."""

from __future__ import annotations

import dataclasses

from semlab import variational


def variational_params(items):
    """``VariationalParams`` from ``KEY=VALUE`` strings (values typed like the defaults), the
    ``--var`` option of ``dense_map.py``, ``accuracy_matrix.py`` and ``stage9_walls.py``."""
    fields = {f.name: f for f in dataclasses.fields(variational.VariationalParams)}
    kw = {}
    for it in items:
        key, _, val = it.partition("=")
        if key not in fields:
            raise SystemExit(f"--var {it}: unknown VariationalParams field {key!r}")
        default = fields[key].default
        if val.lower() == "none":
            kw[key] = None
        elif isinstance(default, bool):
            kw[key] = val.lower() in ("1", "true", "yes")
        elif isinstance(default, int):
            kw[key] = int(val)
        elif isinstance(default, float) or default is None:
            kw[key] = float(val)
        else:
            kw[key] = val
    return variational.VariationalParams(**kw)
