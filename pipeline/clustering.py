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


# Below this many points the k-d tree's pair search is the cheaper (bench on the demo's
# and a cluttered field drive's trunk bands: 0.05-0.24 ms against 0.09-0.29 ms up to 500
# points, even around 800); above it the pairs grow with the density (a wall, a vehicle
# or a hedge's skirt in the band: 1-4 ms for 1000-2500 points) and the grid wins
# (0.6-0.9 ms).
_GRID_FROM = 800

# `planar_clusters`' grid: cells a third of the tolerance wide. Two points in cells next
# to each other (the 3 x 3 block) are at most sqrt(8)/3 = 0.94 tolerance apart, linked
# without a look at them; a pair within the tolerance is at most 3 cells apart on each
# axis. The other half of the 7 x 7 block is the same pairs seen from the far side.
_REACH = 3
_HALF = np.array(
    [(di, dj) for di in range(_REACH + 1) for dj in range(-_REACH, _REACH + 1) if di or dj > 0]
)
_SURE = (np.abs(_HALF) <= 1).all(axis=1)


def planar_clusters(xy: np.ndarray, tolerance: float) -> np.ndarray:
    """`euclidean_clusters` of x-y points (N x 2), the same labels. Many points (a dense
    band) are linked cell by cell on a grid: only the cells 2-3 apart that the nearer
    cells did not already join have their points' distances looked at, where the k-d tree
    lists every pair within the tolerance (tens of thousands on a wall)."""
    if len(xy) < _GRID_FROM:
        return euclidean_clusters(xy, tolerance)
    ij = np.floor((xy - xy.min(axis=0)) / (tolerance / _REACH * (1 + 1e-6))).astype(np.int64)
    width = int(ij[:, 1].max()) + 2 * _REACH + 1  # no neighbour wraps into the next row
    key = ij[:, 0] * width + ij[:, 1]
    order = np.argsort(key, kind="stable")
    cells, start, count = np.unique(key[order], return_index=True, return_counts=True)
    # Each occupied cell's index in a dense table, padded by the reach: every cell's
    # neighbours read at once.
    table = np.full((int(ij[:, 0].max()) + 1 + _REACH) * width, -1, dtype=np.int64)
    table[cells] = np.arange(len(cells))
    offsets = _HALF[:, 0] * width + _HALF[:, 1]
    cell_label = connected_labels(len(cells), _cell_pairs(table, cells, offsets[_SURE]))
    # Farther cells: only those in two groups yet, by their points' distances (squared,
    # as the k-d tree compares them).
    far = _cell_pairs(table, cells, offsets[~_SURE])
    far = far[cell_label[far[:, 0]] != cell_label[far[:, 1]]]
    if len(far):
        sizes = count[far[:, 0]] * count[far[:, 1]]
        pair = np.repeat(np.arange(len(far)), sizes)
        rank = np.arange(len(pair)) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        across = count[far[pair, 1]]
        gap = xy[order[start[far[pair, 0]] + rank // across]]
        gap -= xy[order[start[far[pair, 1]] + rank % across]]
        close = gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1] <= tolerance * tolerance
        linked = far[np.unique(pair[close])]
        if len(linked):
            groups = int(cell_label.max()) + 1
            cell_label = connected_labels(groups, cell_label[linked])[cell_label]
    labels = np.empty(len(xy), dtype=np.int64)
    labels[order] = np.repeat(cell_label, count)
    # Numbered by each cluster's first point, as `connected_labels` numbers them.
    _, lead = np.unique(labels, return_index=True)
    rank = np.empty(len(lead), dtype=np.int64)
    rank[np.argsort(lead)] = np.arange(len(lead))
    return rank[labels]


def _cell_pairs(table: np.ndarray, cells: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(k, 2) indices of the occupied cells `offsets` (flat keys) from each occupied cell."""
    near = table[(offsets[:, None] + cells[None, :]).ravel()]
    found = np.flatnonzero(near >= 0)
    return np.stack([found % len(cells), near[found]], axis=1)


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
