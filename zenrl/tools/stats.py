"""Confidence intervals for ``zenrl evaluate``: Wilson for win rates, Student's t for means.

scipy is not a dependency of zenrl, so the t quantile comes from a short table (exact to the
printed digits up to 30 degrees of freedom, then a 1/df correction of the normal quantile)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

_T975 = [12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
         2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
         2.052, 2.048, 2.045, 2.042]


def t975(df: int) -> float:
    """Two-sided 95% critical value of Student's t with ``df`` degrees of freedom (table up to
    30, then a 1/df correction of 1.96 that is within 0.002 of the exact value)."""
    if df < 1:
        return float("nan")
    if df <= 30:
        return _T975[df - 1]
    return 1.959964 + 2.4 / df


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score 95% interval of a proportion k/n (``(0, 1)`` for n = 0)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def mean_ci(x: Sequence[float]) -> tuple[float, float, float]:
    """(mean, low, high): t 95% interval of the mean (NaN bounds for fewer than 2 values)."""
    a = np.asarray(x, np.float64)
    if a.size == 0:
        return float("nan"), float("nan"), float("nan")
    m = float(a.mean())
    if a.size < 2:
        return m, float("nan"), float("nan")
    h = t975(a.size - 1) * float(a.std(ddof=1)) / math.sqrt(a.size)
    return m, m - h, m + h

