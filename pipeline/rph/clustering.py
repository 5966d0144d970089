"""Euclidean clustering as PCL's `EuclideanClusterExtraction` does it: the connected
components of the graph that links every two points closer than the tolerance, clusters
outside [min_size, max_size] dropped.

Deterministic: clusters come largest first (as PCL sorts them), ties by their first point.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def component_labels(points: np.ndarray, tolerance: float) -> np.ndarray:
    """Label of each point's connected component (0..k-1, numbered by first point)."""
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n)
    )
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


def euclidean_clusters(
    points: np.ndarray, tolerance: float, min_size: int = 1, max_size: int | None = None
) -> list[np.ndarray]:
    """Index arrays (ascending) of the clusters of `points` (N x 3), largest first."""
    labels = component_labels(np.asarray(points, dtype=np.float64), tolerance)
    if len(labels) == 0:
        return []
    sizes = np.bincount(labels)
    order = np.argsort(labels, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    keep = sizes >= min_size
    if max_size is not None:
        keep &= sizes <= max_size
    # Labels are numbered by first point, so sorting by (-size, label) is deterministic.
    chosen = sorted(np.flatnonzero(keep), key=lambda k: (-sizes[k], k))
    return [order[starts[k] : starts[k] + sizes[k]] for k in chosen]
