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
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(xyz).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs), dtype=bool), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels.astype(np.int64)


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
