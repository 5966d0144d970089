"""One output tree: the record georeferencing makes and every output writes."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Tree:
    """One mapped tree, as written to the outputs (trees.csv columns, docs/architecture.md).

    Position in the UTM zone of the run (`utm_zone` like `11N`) and in WGS84; None while
    the tree is only known in `odom` (seen before the first GNSS fix or in an outage).
    Times are ns since the Unix epoch.

    `status`: "found" (detected), "missing" (a field-map tree the robot passed within
    sensing range and did not find: its position is the map's, `tree_id` is empty, its
    traits NaN, no times) or "rejected" (an object seen as often as a tree that is not
    one: `reason` says why, see `pipeline.classify.REASONS`).

    `height_top_seen`: whether the LiDAR's beams passed over the crown's top in some scan
    (the height is then the top's); False: the crown went on above the top beam in every
    scan and `height_m` is a lower bound; None where nobody judged it (a missing tree,
    the baselines).
    """

    tree_id: str
    easting: float | None
    northing: float | None
    utm_zone: str | None
    lat: float | None
    lon: float | None
    width_m: float
    height_m: float
    ndvi: float | None
    observations: int
    first_seen: int | None
    last_seen: int | None
    field_id: str | None = None
    row: str | None = None
    status: str = "found"
    reason: str | None = None
    height_top_seen: bool | None = None
