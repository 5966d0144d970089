"""Single-linkage Euclidean clustering, shared by detection and its helpers."""

from __future__ import annotations

import numpy as np


def euclidean_clusters(xyz: np.ndarray, tolerance: float, method: str = "kdtree") -> np.ndarray:
    """Single-linkage clusters: two points closer than `tolerance` share a cluster.
    Labels 0.. numbered by each cluster's first point (deterministic)."""
    n = len(xyz)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if method == "dbscan":
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        labels = np.asarray(cloud.cluster_dbscan(tolerance, 1, print_progress=False))
        _, first, labels = np.unique(labels, return_index=True, return_inverse=True)
        rank = np.empty(len(first), dtype=np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(first))
        return rank[labels.ravel()]
    from scipy.spatial import cKDTree

    # Split at the midpoint, not the median: a quicker build for the same pairs (the
    # labels do not depend on the order they come in).
    pairs = cKDTree(xyz, balanced_tree=False).query_pairs(tolerance, output_type="ndarray")
    return connected_labels(n, pairs)


def connected_labels(n: int, pairs: np.ndarray) -> np.ndarray:
    """Connected components of n nodes linked by `pairs` (k x 2), labelled 0.. in the order
    of each component's lowest node: scipy's `connected_components` labels, at a fraction
    of its cost on the few hundred voxels a call gets (its graph checks and sparse
    conversions cost more than the search; bench: 1.7 -> 0.8 ms a call with the search).

    Union by the lower root, then pointer jumping until every node points at its root;
    repeated until no pair joins two roots. The root of a component is its lowest node."""
    parent = np.arange(n)
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        while True:
            pi, pj = parent[i], parent[j]
            differ = pi != pj
            if not differ.any():
                break
            pi, pj = pi[differ], pj[differ]
            np.minimum.at(parent, np.maximum(pi, pj), np.minimum(pi, pj))
            while True:
                up = parent[parent]
                if np.array_equal(up, parent):
                    break
                parent = up
    root = parent == np.arange(n)
    return (np.cumsum(root) - 1)[parent]


def attach(points: np.ndarray, anchors: np.ndarray, labels: np.ndarray, tolerance: float):
    """Label of the nearest anchor within `tolerance` for each point, -1 where none."""
    if len(points) == 0 or len(anchors) == 0:
        return np.full(len(points), -1, dtype=np.int64)
    from scipy.spatial import cKDTree

    distance, index = cKDTree(anchors).query(points, distance_upper_bound=tolerance)
    found = np.isfinite(distance)
    out = np.full(len(points), -1, dtype=np.int64)
    out[found] = labels[index[found]]
    return out


def stable_order(labels: np.ndarray) -> np.ndarray:
    """`np.argsort(labels, kind="stable")` of integer labels. Labels that fit in int16 (a
    scan's clusters do) are sorted as int16: NumPy sorts 16-bit integers stably by radix,
    ~8x faster than int64 on a scan's points, and a stable order is the same order."""
    if len(labels) and labels.min() >= -(2**15) and labels.max() < 2**15:
        return np.argsort(labels.astype(np.int16), kind="stable")
    return np.argsort(labels, kind="stable")
