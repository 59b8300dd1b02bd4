"""Small helpers for semlab's public functions (a leaf module: imports nothing of semlab)."""

from __future__ import annotations

import difflib
import functools
import inspect

__all__ = ["check_keywords", "strict_keywords"]


def check_keywords(where, given, valid):
    """Raise ``TypeError`` for names in ``given`` that are not in ``valid``, naming the
    nearest valid one.

    Parameters
    ----------
    where : str
        What takes the keywords (for the message), e.g. ``"AnalysisConfig"``.
    given : iterable of str
    valid : iterable of str

    Examples
    --------
    >>> check_keywords("f", ["n_boot"], ["n_boot", "seed"])
    >>> check_keywords("f", ["nboot"], ["n_boot", "seed"])
    Traceback (most recent call last):
    ...
    TypeError: f() got an unexpected keyword argument 'nboot'; did you mean 'n_boot'?
    """
    valid = list(valid)
    for name in given:
        if name not in valid:
            near = difflib.get_close_matches(name, valid, n=1, cutoff=0.5)
            hint = (f"; did you mean {near[0]!r}?" if near
                    else f"; valid keywords: {', '.join(valid)}")
            raise TypeError(f"{where}() got an unexpected keyword argument {name!r}{hint}")


def strict_keywords(func):
    """Decorate ``func`` so that an unknown keyword argument raises ``TypeError`` naming the
    nearest valid one (Python's own message names none)."""
    sig = inspect.signature(func)
    params = sig.parameters
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return func
    valid = [n for n, p in params.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        if kwargs:
            check_keywords(func.__name__, kwargs, valid)
        return func(*args, **kwargs)

    return wrapper
