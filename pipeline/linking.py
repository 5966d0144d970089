"""Which tree of one survey is which tree of another: the season's tree identity
(docs/season.md, "Linking trees across surveys").

Pure functions on positions. A tree on the field map keeps its field id from survey to
survey; a tree off the map is linked by position: the assignment that minimises the summed
distance (Hungarian, `scipy.optimize.linear_sum_assignment`) among pairs closer than a
gate. The gate is physical: less than half the closest spacing of two trees of a block, so
one tree cannot be taken for its neighbour, and more than the position's error between
two surveys (GNSS noise, a tree's crown centre moving in the wind).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from treetraits.pipeline.trees import Tree

# Half of the closest in-row spacing the project models (hedgerows, 2.5 m) less a margin:
# two surveys' positions of one tree differ by the GNSS error (RTK: cm; DGPS: ~0.5 m)
# plus the crown centre's wobble (~0.2 m), far below it.
DEFAULT_LINK_GATE_M = 1.2


def link_by_position(
    known: np.ndarray, new: np.ndarray, gate_m: float = DEFAULT_LINK_GATE_M
) -> list[int | None]:
    """For each row of `new` (N x 2, metres), the index of the row of `known` (M x 2) it
    is, or None: a one-to-one assignment minimising the summed distance, pairs farther
    apart than `gate_m` left unlinked."""
    known = np.asarray(known, dtype=float).reshape(-1, 2)
    new = np.asarray(new, dtype=float).reshape(-1, 2)
    links: list[int | None] = [None] * len(new)
    if not len(known) or not len(new):
        return links
    from scipy.optimize import linear_sum_assignment

    distance = np.linalg.norm(new[:, None, :] - known[None, :, :], axis=2)
    # Pairs beyond the gate cost more than any set of gated pairs can: the assignment
    # never trades a gated pair for them, and they are dropped below.
    cost = np.where(distance <= gate_m, distance, gate_m * (len(new) + len(known) + 1))
    rows, cols = linear_sum_assignment(cost)
    for i, j in zip(rows, cols, strict=True):
        if distance[i, j] <= gate_m:
            links[i] = int(j)
    return links


def within_extent(points: np.ndarray, surveyed: np.ndarray, margin_m: float) -> np.ndarray:
    """Which `points` (N x 2) lie in the bounding box of `surveyed` (M x 2) grown by
    `margin_m`: where a survey without a field map looked, so a known tree there that it
    did not find is missing, and one outside it was simply not driven past."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    surveyed = np.asarray(surveyed, dtype=float).reshape(-1, 2)
    if not len(surveyed):
        return np.zeros(len(points), dtype=bool)
    low = surveyed.min(axis=0) - margin_m
    high = surveyed.max(axis=0) + margin_m
    return np.all((points >= low) & (points <= high), axis=1)


def growth_per_30_days(times_ns: Sequence[int], values: Sequence[float | None]) -> float | None:
    """The change of a trait per 30 days from its first to its last measured survey
    (None with fewer than two measured surveys or no time between them)."""
    measured = [(t, v) for t, v in zip(times_ns, values, strict=True) if v is not None]
    if len(measured) < 2:
        return None
    measured.sort()
    (t0, v0), (t1, v1) = measured[0], measured[-1]
    days = (t1 - t0) / 86400e9
    if days <= 0:
        return None
    return (v1 - v0) / days * 30.0


@dataclass
class LinkedTree:
    """One tree of the season: its id and its (survey id, status, the run's tree) visits."""

    tree_id: str
    field_id: str | None
    row: str | None
    utm_zone: str | None
    visits: list[tuple[int, str, Tree]] = field(default_factory=list)

    def found(self) -> list[Tree]:
        return [t for _, status, t in self.visits if status == "found" and t.easting is not None]

    def xy(self) -> tuple[float, float] | None:
        """Where the tree is: the mean of its found positions (the map's if never found)."""
        placed = self.found() or [t for _, _, t in self.visits if t.easting is not None]
        if not placed:
            return None
        return (
            sum(t.easting for t in placed) / len(placed),
            sum(t.northing for t in placed) / len(placed),
        )

    def position(self) -> tuple:
        """(easting, northing, utm_zone, lat, lon): the means of its found positions."""
        placed = self.found() or [t for _, _, t in self.visits if t.easting is not None]
        if not placed:
            return (None, None, self.utm_zone, None, None)
        east, north = self.xy()
        located = [t for t in placed if t.lat is not None]
        lat = sum(t.lat for t in located) / len(located) if located else None
        lon = sum(t.lon for t in located) / len(located) if located else None
        return (east, north, self.utm_zone, lat, lon)


def link_surveys(
    surveys: Sequence[tuple[int, Sequence[Tree]]],
    gate_m: float = DEFAULT_LINK_GATE_M,
    taken_ids: set[str] | frozenset[str] = frozenset(),
) -> list[LinkedTree]:
    """The season's trees of one block from its surveys' trees (`surveys` in date order:
    (survey id, the run's found and missing trees)).

    In each survey, a tree with a field id is the season tree of that id (its run matched
    it to the field map, or found it missing there). The others, found and placed in UTM,
    are linked by position (`link_by_position`, `gate_m`) to the season trees this survey
    has not yet claimed, in the same UTM zone; one left over is a new tree `pos-N`. A
    season tree this survey did not claim is missing in it when it lies where the survey
    looked (`within_extent` of its found trees, grown by `gate_m`); elsewhere the survey
    says nothing of it. Found trees with no UTM position (seen only in `odom`) cannot be
    linked and are left out. `taken_ids`: ids not to give to new trees."""
    trees: list[LinkedTree] = []
    by_field: dict[str, LinkedTree] = {}
    used = set(taken_ids)
    counter = 0

    def new_tree(field_id: str | None, row: str | None, zone: str | None) -> LinkedTree:
        nonlocal counter
        if field_id is not None:
            tree_id = field_id
        else:
            while True:
                counter += 1
                tree_id = f"pos-{counter}"
                if tree_id not in used:
                    break
        used.add(tree_id)
        tree = LinkedTree(tree_id, field_id, row, zone)
        trees.append(tree)
        if field_id is not None:
            by_field[field_id] = tree
        return tree

    for survey_id, run_trees in surveys:
        claimed: set[int] = set()  # id() of the season trees this survey claimed
        loose: list[Tree] = []
        for t in run_trees:
            if t.field_id is not None:
                tree = by_field.get(t.field_id) or new_tree(t.field_id, t.row, t.utm_zone)
                tree.visits.append((survey_id, t.status, t))
                claimed.add(id(tree))
            elif t.status == "found" and t.easting is not None and t.northing is not None:
                loose.append(t)
        for zone in sorted({t.utm_zone or "" for t in loose}):
            new = [t for t in loose if (t.utm_zone or "") == zone]
            candidates = [
                s
                for s in trees
                if id(s) not in claimed and (s.utm_zone or "") == zone and s.xy() is not None
            ]
            links = link_by_position(
                np.array([s.xy() for s in candidates]),
                np.array([(t.easting, t.northing) for t in new]),
                gate_m,
            )
            for t, j in zip(new, links, strict=True):
                tree = new_tree(None, t.row, t.utm_zone) if j is None else candidates[j]
                tree.visits.append((survey_id, "found", t))
                claimed.add(id(tree))
        looked = np.array(
            [
                (t.easting, t.northing)
                for t in run_trees
                if t.status == "found" and t.easting is not None
            ]
        )
        for tree in trees:
            if id(tree) in claimed or tree.xy() is None:
                continue
            if within_extent(np.array([tree.xy()]), looked, gate_m)[0]:
                east, north = tree.xy()
                placeholder = Tree(
                    "",
                    east,
                    north,
                    tree.utm_zone,
                    None,
                    None,
                    math.nan,
                    math.nan,
                    None,
                    0,
                    None,
                    None,
                    tree.field_id,
                    tree.row,
                    "missing",
                )
                tree.visits.append((survey_id, "missing", placeholder))
    return trees
