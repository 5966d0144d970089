"""What lies under the crowns: trunks, hanging skirts, weeds, cover crop, drip lines.
It joins the tree above it, but it never links two crowns.

On the twin's cluttered grove (weeds, a drip line hung at 0.35 m along each row), the
drip line and the weeds between the trees linked whole rows into one cluster:
6.96 m for two trees 3.9 m apart. A grove's understorey ends below 0.6 m, where citrus
skirts have begun, so the crowns are clustered on the voxels that reach higher
(`ClusterConfig.bridge_min_height_m`). What lies lower joins a crown
voxel by voxel, where it is within the clustering's reach of that crown (a skirt, the
weeds at a trunk's foot, the drip line under a crown's edge); the rest, in connected
pieces, are objects of their own (a weed clump, a drip line's span between two trees),
judged like any other (`low`). A piece with no return clear of the ground band (green
skirt points alone) starts nothing. So a row's drip line adds nothing beyond a crown's
edge, and a trunk the crown does not reach is found by the cut at trunks all the same
(`detection.split_at_trunks` looks under the crown, not only in it).
"""

from __future__ import annotations

import numpy as np

from treetraits.pipeline.clustering import attach, euclidean_clusters, stable_order


def join_understorey(
    voxels: np.ndarray,
    crown_labels: np.ndarray,
    under: np.ndarray,
    starts: np.ndarray,
    tolerance: float,
    next_label: int,
) -> np.ndarray:
    """Labels of the `under` voxels (boolean mask over `voxels`). `crown_labels`: each
    voxel's crown cluster (-1 for all but the crowns). `starts`: which voxels may start
    an object of their own (a return clear of the ground band). New objects are
    numbered from `next_label`; -1: dropped."""
    index = np.flatnonzero(under)
    if len(index) == 0:
        return np.zeros(0, dtype=np.int64)
    crown_index = np.flatnonzero(crown_labels >= 0)
    # The crown each voxel touches (within the clustering's reach), -1 for none.
    out = attach(voxels[index], voxels[crown_index], crown_labels[crown_index], tolerance)
    loose = np.flatnonzero(out < 0)
    if len(loose) == 0:
        return out
    piece = euclidean_clusters(voxels[index[loose]], tolerance)
    # Pieces in label order, each one's voxels in index order: one stable sort.
    order = stable_order(piece)
    for members in np.split(loose[order], np.flatnonzero(np.diff(piece[order])) + 1):
        if starts[index[members]].any():
            out[members] = next_label
            next_label += 1
    return out
