"""Medians as the pipeline takes them: of one array, and of each group of a sorted one."""

from __future__ import annotations

import math

import numpy as np


def median_of_groups(values: np.ndarray, owner: np.ndarray, groups: int) -> np.ndarray:
    """`median` of each group's values (NaN for none); `owner` is non-decreasing, so each
    group's values are one slice (a partition of each: sorting them all costs more)."""
    bounds = np.searchsorted(owner, np.arange(groups + 1))
    return np.array([median(values[bounds[k] : bounds[k + 1]]) for k in range(groups)])


def median(values: np.ndarray) -> float:
    """`float(np.median(values))` of a 1-D float array, by one partition: the same
    middle values and the same mean of the two, NaN when any value is NaN, without
    np.median's generic machinery, whose cost is paid a few times per cluster."""
    n = len(values)
    if n == 0:
        return math.nan
    half = n // 2
    part = np.partition(values, (half, n - 1) if n % 2 else (half - 1, half, n - 1))
    if np.isnan(part[-1]):  # NaN sorts last
        return math.nan
    return float(part[half]) if n % 2 else float((part[half - 1] + part[half]) / 2)
