"""What lies under the crowns: trunks, hanging skirts, weeds, cover crop, drip lines.
It joins the tree above it, but it never links two crowns.

On the twin's cluttered grove (weeds, a drip line hung at 0.35 m along each row), the
drip line and the weeds between the trees linked whole rows into one cluster:
6.96 m for two trees 3.9 m apart. A grove's understorey ends below 0.6 m, where citrus
skirts have begun, so the crowns are clustered on the voxels that reach higher
(`ClusterConfig.bridge_min_height_m`). Each connected piece of what lies lower then
goes to the crown it touches:
- none: it is an object of its own (a weed clump, a drip line's span), judged like any
  other (`low`). A piece with no return clear of the ground band (green skirt points
  alone) starts nothing.
- one: all of it (a trunk with the weeds at its foot and the skirt over them).
- two or more, a bridge: each voxel goes to the crown within the clustering's reach
  (a skirt, the drip line under a crown's edge), and a trunk's voxels go to the crown
  nearest to them across (a trunk stands under its own crown). The rest of the bridge
  is an object of its own. So a row's drip line is cut between the trees and adds
  nothing beyond a crown's edge.
"""

from __future__ import annotations

import numpy as np

from treetraits.pipeline.clustering import attach, euclidean_clusters


def join_understorey(
    voxels: np.ndarray,
    crown_labels: np.ndarray,
    under: np.ndarray,
    starts: np.ndarray,
    trunk_like: np.ndarray,
    tolerance: float,
    next_label: int,
) -> np.ndarray:
    """Labels of the `under` voxels (boolean mask over `voxels`). `crown_labels`: each
    voxel's crown cluster (-1 for all but the crowns). `starts`: which voxels may start
    an object of their own (a return clear of the ground band). `trunk_like`: voxels of
    a trunk-band blob. New objects are numbered from `next_label`; -1: dropped."""
    index = np.flatnonzero(under)
    out = np.full(len(index), -1, dtype=np.int64)
    if len(index) == 0:
        return out
    crown_index = np.flatnonzero(crown_labels >= 0)
    # The crown each voxel touches (within the clustering's reach), -1 for none.
    touched = attach(voxels[index], voxels[crown_index], crown_labels[crown_index], tolerance)
    piece = euclidean_clusters(voxels[index], tolerance)
    for p in np.unique(piece):
        members = np.flatnonzero(piece == p)
        crowns = np.unique(touched[members][touched[members] >= 0])
        if len(crowns) == 1:
            out[members] = crowns[0]
            continue
        rest = members
        if len(crowns) > 1:
            out[members] = touched[members]
            trunks = members[(touched[members] < 0) & trunk_like[index[members]]]
            if len(trunks):
                out[trunks] = _nearest_across(voxels, crown_labels, crowns, index[trunks])
            rest = members[out[members] < 0]
        if len(rest) and starts[index[rest]].any():
            out[rest] = next_label
            next_label += 1
    return out


def _nearest_across(
    voxels: np.ndarray, crown_labels: np.ndarray, crowns: np.ndarray, which: np.ndarray
) -> np.ndarray:
    """The crown (among `crowns`) with the voxel nearest in x-y to each of `which`."""
    best = np.full(len(which), np.inf)
    label = np.full(len(which), -1, dtype=np.int64)
    for crown in crowns:
        cells = voxels[crown_labels == crown, :2]
        gaps = np.hypot(
            voxels[which, None, 0] - cells[None, :, 0], voxels[which, None, 1] - cells[None, :, 1]
        ).min(axis=1)
        closer = gaps < best
        best[closer], label[closer] = gaps[closer], crown
    return label
