"""Single-linkage Euclidean clustering, shared by detection and its helpers."""

from __future__ import annotations

import numpy as np

from treetraits.jit import kernel, kernel_layout, warm_up


def euclidean_clusters(xyz: np.ndarray, tolerance: float, method: str = "kdtree") -> np.ndarray:
    """Single-linkage clusters of points (N x 2 or N x 3): two points closer than
    `tolerance` share a cluster. Labels 0.. numbered by each cluster's first point
    (deterministic). "kdtree" (the configs' name): the pairs the k-d tree would list
    (squared distances, compared as it compares them), found on a grid of cells
    (`_grid_labels`); the k-d tree itself where no grid fits."""
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
    points = kernel_layout(xyz)
    if tolerance > 0:
        labels = _grid_labels(points, float(tolerance))
        if len(labels) == n:
            return labels
    # No grid without a tolerance, nor one too wide for int64 cell keys.
    return kdtree_clusters(points, tolerance)


def kdtree_clusters(xyz: np.ndarray, tolerance: float) -> np.ndarray:
    """`euclidean_clusters` by the k-d tree's pairs and their connected components."""
    from scipy.spatial import cKDTree

    # Split at the midpoint, not the median: a quicker build for the same pairs (the
    # labels do not depend on the order they come in).
    pairs = cKDTree(xyz, balanced_tree=False).query_pairs(tolerance, output_type="ndarray")
    return connected_labels(len(xyz), pairs)


# `_grid_labels`' cells: a little narrower than the tolerance over the square root of the
# dimensions, so that any two points of one cell are within it (linked without a look),
# and a pair within it lies at most _REACH cells apart on each axis (tolerance / cell
# width: sqrt(2) or sqrt(3), under 2).
_REACH = 2
_NARROWER = 1 - 1e-6


@kernel
def _grid_labels(points: np.ndarray, tolerance: float) -> np.ndarray:
    """`euclidean_clusters` of `points` (N x D float64, C order; N > 0): the occupied
    cells of the grid are the nodes of a union-find, two of them joined by the first
    pair of their points within the tolerance, the cells in reach looked at from one
    side only and not at all once joined. Empty when the cell keys would not fit int64."""
    n, dims = points.shape
    size = tolerance / np.sqrt(dims) * _NARROWER
    low = np.empty(dims)
    for a in range(dims):
        low[a] = points[:, a].min()
    cell = np.empty((n, dims), dtype=np.int64)
    high = np.zeros(dims, dtype=np.int64)
    for i in range(n):
        for a in range(dims):
            c = np.int64(np.floor((points[i, a] - low[a]) / size))
            cell[i, a] = c
            high[a] = max(high[a], c)
    # Keys padded by the reach on each axis: no neighbour's key wraps into another row.
    stride = np.empty(dims, dtype=np.int64)
    span = 1
    for a in range(dims - 1, -1, -1):
        stride[a] = span
        width = high[a] + 1 + 2 * _REACH
        if float(span) * float(width) > 2.0**62:
            return np.empty(0, dtype=np.int64)
        span *= width
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        k = 0
        for a in range(dims):
            k += (cell[i, a] + _REACH) * stride[a]
        key[i] = k
    order = np.argsort(key)  # any order within a cell: it is linked whole
    # The occupied cells in key order: their keys and their points' range in `order`.
    cell_key = np.empty(n, dtype=np.int64)
    first = np.empty(n + 1, dtype=np.int64)
    cell_of = np.empty(n, dtype=np.int64)
    cells = 0
    for r in range(n):
        k = key[order[r]]
        if cells == 0 or k != cell_key[cells - 1]:
            cell_key[cells] = k
            first[cells] = r
            cells += 1
        cell_of[order[r]] = cells - 1
    first[cells] = n
    # Key steps to the cells in reach after a cell in key order (the other half sees it).
    offsets = np.empty(((2 * _REACH + 1) ** dims - 1) // 2, dtype=np.int64)
    found = 0
    for code in range((2 * _REACH + 1) ** dims):
        step, rest = 0, code
        for a in range(dims):
            step += (rest % (2 * _REACH + 1) - _REACH) * stride[a]
            rest //= 2 * _REACH + 1
        if step > 0:
            offsets[found] = step
            found += 1
    # For each step, the first cell whose key is not below the target: it only moves on.
    at = np.zeros(len(offsets), dtype=np.int64)
    parent = np.arange(cells)
    squared = tolerance * tolerance
    for c in range(cells):
        for o in range(len(offsets)):
            target = cell_key[c] + offsets[o]
            while at[o] < cells and cell_key[at[o]] < target:
                at[o] += 1
            d = at[o]
            if d == cells or cell_key[d] != target:
                continue
            root_c, root_d = _root(parent, c), _root(parent, d)
            if root_c != root_d and _any_pair_within(points, order, first, c, d, squared):
                parent[max(root_c, root_d)] = min(root_c, root_d)
    # Numbered by each cluster's first point.
    number = np.full(cells, -1, dtype=np.int64)
    labels = np.empty(n, dtype=np.int64)
    clusters = 0
    for i in range(n):
        root = _root(parent, cell_of[i])
        if number[root] < 0:
            number[root] = clusters
            clusters += 1
        labels[i] = number[root]
    return labels


@kernel
def _root(parent: np.ndarray, node: int) -> int:
    """Union-find's root of `node`, halving the path on the way."""
    while parent[node] != node:
        parent[node] = parent[parent[node]]
        node = parent[node]
    return node


@kernel
def _any_pair_within(
    points: np.ndarray, order: np.ndarray, first: np.ndarray, c: int, d: int, squared: float
) -> bool:
    """Whether a point of cell c and one of cell d are within the tolerance: the squared
    distance summed axis by axis from zero, as the k-d tree sums it, and compared <=."""
    for r in range(first[c], first[c + 1]):
        i = order[r]
        for s in range(first[d], first[d + 1]):
            j = order[s]
            total = 0.0
            for a in range(points.shape[1]):
                gap = points[i, a] - points[j, a]
                total += gap * gap
            if total <= squared:
                return True
    return False


@warm_up
def compile_kernels() -> None:
    """The clustering kernels compiled for the points a scan gives them (x-y and x-y-z).
    The helpers too: a caller loaded from the cache does not compile its callees."""
    for dims in (2, 3):
        _grid_labels(np.zeros((2, dims)), 0.5)
    index = np.arange(2)
    _root(index, 1)
    _any_pair_within(np.zeros((2, 3)), index, index, 0, 1, 0.25)
    _attached(np.zeros((1, 3)), np.zeros((2, 3)), index, 0.5)
    _nearest_labels(np.zeros((1, 2)), np.zeros((2, 2)), index)


def connected_labels(n: int, pairs: np.ndarray) -> np.ndarray:
    """Connected components of n nodes linked by `pairs` (k x 2), labelled 0.. in the order
    of each component's lowest node: scipy's `connected_components` labels, at a fraction
    of its cost on the few hundred voxels a call gets (its graph checks and sparse
    conversions cost more than the search; docs/performance.md).

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
    out, sure = _attached(
        kernel_layout(points),
        kernel_layout(anchors),
        kernel_layout(labels, np.int64),
        float(tolerance),
    )
    if sure:
        return out
    # A grid too wide for int64 keys, or anchors of two labels at the same distance: the
    # k-d tree's choice among them.
    from scipy.spatial import cKDTree

    distance, index = cKDTree(anchors).query(points, distance_upper_bound=tolerance)
    found = np.isfinite(distance)
    out = np.full(len(points), -1, dtype=np.int64)
    out[found] = labels[index[found]]
    return out


def nearest_label(points: np.ndarray, anchors: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Label of the nearest anchor for each point (a few points: a blob's centres)."""
    out, sure = _nearest_labels(
        kernel_layout(points), kernel_layout(anchors), kernel_layout(labels, np.int64)
    )
    if sure:
        return out
    from scipy.spatial import cKDTree  # anchors of two labels at the same distance

    return labels[cKDTree(anchors).query(points)[1]]


@kernel
def _attached(
    points: np.ndarray, anchors: np.ndarray, labels: np.ndarray, tolerance: float
) -> tuple[np.ndarray, bool]:
    """`attach` on a grid of cells a little wider than the tolerance: a point's anchors
    within it are in its cell or the next ones. Distances squared, summed axis by axis
    and compared < as the k-d tree's bounded query does. Not sure (False) when the cell
    keys would not fit int64 or anchors of two labels are nearest at once."""
    n, dims = points.shape
    out = np.full(n, -1, dtype=np.int64)
    size = tolerance * (1 + 1e-6)
    low = np.empty(dims)
    high = np.zeros(dims, dtype=np.int64)
    for a in range(dims):
        low[a] = anchors[:, a].min()
        high[a] = np.int64(np.floor((anchors[:, a].max() - low[a]) / size))
    stride = np.empty(dims, dtype=np.int64)
    span = 1
    for a in range(dims - 1, -1, -1):
        stride[a] = span
        if float(span) * float(high[a] + 1) > 2.0**62:
            return out, False
        span *= high[a] + 1
    key = np.zeros(len(anchors), dtype=np.int64)
    for k in range(len(anchors)):
        for a in range(dims):
            key[k] += np.int64(np.floor((anchors[k, a] - low[a]) / size)) * stride[a]
    order = np.argsort(key)
    sorted_key = key[order]
    squared = tolerance * tolerance
    cell = np.empty(dims, dtype=np.int64)
    for i in range(n):
        outside = False
        for a in range(dims):
            c = np.floor((points[i, a] - low[a]) / size)
            outside |= c < -1 or c > high[a] + 1
            cell[a] = np.int64(c) if not outside else 0
        if outside:
            continue
        best, best_label, tied = np.inf, np.int64(-1), False
        for code in range(3**dims):
            target, rest, valid = 0, code, True
            for a in range(dims):
                c = cell[a] + rest % 3 - 1
                rest //= 3
                valid &= 0 <= c <= high[a]
                target += c * stride[a]
            if not valid:
                continue
            r = np.searchsorted(sorted_key, target)
            while r < len(sorted_key) and sorted_key[r] == target:
                k = order[r]
                r += 1
                total = 0.0
                for a in range(dims):
                    gap = points[i, a] - anchors[k, a]
                    total += gap * gap
                if total < best:
                    best, best_label, tied = total, labels[k], False
                elif total == best and labels[k] != best_label:
                    tied = True
        if best < squared:
            if tied:
                return out, False
            out[i] = best_label
    return out, True


@kernel
def _nearest_labels(
    points: np.ndarray, anchors: np.ndarray, labels: np.ndarray
) -> tuple[np.ndarray, bool]:
    """`nearest_label` by every distance (squared, summed axis by axis as the k-d tree
    sums it). Not sure (False) when anchors of two labels are nearest at once."""
    out = np.empty(len(points), dtype=np.int64)
    for i in range(len(points)):
        best, best_label, tied = np.inf, np.int64(-1), False
        for k in range(len(anchors)):
            total = 0.0
            for a in range(points.shape[1]):
                gap = points[i, a] - anchors[k, a]
                total += gap * gap
            if total < best:
                best, best_label, tied = total, labels[k], False
            elif total == best and labels[k] != best_label:
                tied = True
        if tied:
            return out, False
        out[i] = best_label
    return out, True


def stable_order(labels: np.ndarray) -> np.ndarray:
    """`np.argsort(labels, kind="stable")` of integer labels. Labels that fit in int16 (a
    scan's clusters do) are sorted as int16: NumPy sorts 16-bit integers stably by radix,
    ~8x faster than int64 on a scan's points, and a stable order is the same order."""
    if len(labels) and labels.min() >= -(2**15) and labels.max() < 2**15:
        return np.argsort(labels.astype(np.int16), kind="stable")
    return np.argsort(labels, kind="stable")
