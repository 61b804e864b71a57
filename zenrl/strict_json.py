"""JSON that strict readers take: what zenrl's commands print or write for other programs
(``--json`` files, the last stdout line of the tools, ``zenrl status --json``).

Python's ``json`` writes ``NaN`` and ``Infinity`` for non-finite floats, which JSON does not have:
JavaScript's ``JSON.parse``, Go and most validators refuse the whole document. A statistic that
does not exist (the confidence interval of one episode) is written as ``null`` instead."""

from __future__ import annotations

import json
import math
from typing import Any


def finite(obj: Any) -> Any:
    """``obj`` with every non-finite float as None, tuples as lists and numpy values as the
    Python values they hold (mappings and sequences are copied, nothing is changed in place)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, bytes, bool, int)) or obj is None:
        return obj
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if hasattr(obj, "tolist") and hasattr(obj, "dtype"):  # a numpy array or scalar
        return finite(obj.tolist())
    return obj


def dumps(obj: Any, **kw: Any) -> str:
    """``json.dumps`` of :func:`finite` ``(obj)``; never writes NaN or Infinity."""
    return json.dumps(finite(obj), allow_nan=False, **kw)
