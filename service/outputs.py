"""A run's outputs, shared by `treetraits replay` and the service: the store committed per
scan, and `trees.geojson` / `trees.csv` (found and missing trees) and `rejected.geojson`
(objects that are not trees) rewritten atomically (docs/architecture.md, "Outputs").

`RunWriter` owns the store and knows how to turn the mapper's trees into georeferenced
`Tree`s; when to export is the caller's choice (recorded time in a replay, wall time in
the service, both held to `output.export_max_share` of the wall time by
`next_export_after`). Failures to write come out as `OutputError` naming the file and the
cause, with the store's transaction rolled back, so a full disk never leaves a
half-written scan.
"""

from __future__ import annotations

import math
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from treetraits.errors import FileAccessError
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.fieldmap import FieldTree
from treetraits.pipeline.georef import (
    FieldMapIndex,
    RenderCache,
    georeference,
    missing_trees,
    utm_positions,
    write_trees_csv,
    write_trees_geojson,
)
from treetraits.pipeline.mapper import TreeMapper
from treetraits.pipeline.trees import Tree
from treetraits.service.config import OutputConfig
from treetraits.service.store import Observation, TraitStore
from treetraits.service.survey import ScanOutcome, SurveyProcessor

STORE_NAME = "traits.sqlite"
CSV_NAME = "trees.csv"
REJECTED_NAME = "rejected.geojson"
GEOJSON_NAME = "trees.geojson"


class OutputError(FileAccessError):
    """An output could not be written (disk full, I/O error); the file named is intact."""


def next_export_after(finished: float, took_s: float, every_s: float, max_share: float) -> float:
    """When the next export may start, on the clock `finished` is read from (seconds):
    `every_s` after this one finished, or later when this one took so long (`took_s`)
    that exports would take more than `max_share` of the time. An export rewrites every
    tree, so its cost grows with the survey while the scans' does not."""
    return finished + max(every_s, took_s * (1.0 / max_share - 1.0))


class RunWriter:
    """The store of one run plus the exports. `commit` after every processed scan,
    `export` when due, `close` at the end (idempotent)."""

    def __init__(
        self,
        out_dir: Path,
        processor: SurveyProcessor,
        field_map: Sequence[FieldTree] = (),
        gates: OutputConfig | None = None,
        *,
        facts: dict | None = None,
    ):
        """`gates`: the output section's `min_observations` and `match_gate_m`."""
        gates = gates or OutputConfig()
        self.out_dir = Path(out_dir)
        self.processor = processor
        self.field_map = list(field_map)
        self.min_observations = gates.min_observations
        self.match_gate_m = gates.match_gate_m
        self.missing_range_m = gates.missing_range_m
        # The robot's path, one point per metre driven (x, y, frame, t), for the field-map
        # trees it passed: a tree it never came near is not missing, just not surveyed.
        self._path: list[_PathPoint] = []
        self._anchor = None  # the processor's odom -> utm re-anchoring last seen
        self.store_path = self.out_dir / STORE_NAME
        self.scans = 0  # scans committed
        self.exports = 0
        try:
            self.store = TraitStore(self.store_path)
        except sqlite3.Error as exc:  # a full disk, a directory in its place
            raise OutputError(f"{self.store_path}: store not created: {_sqlite_text(exc)}") from exc
        self._field_index: FieldMapIndex | None = None
        self._approach: _Approach | None = None  # the field-map trees' nearest approach
        # Trees the mapper finalised (`tracking.retire_m`), georeferenced once when they
        # were: reported ones and rejected ones, by tree id. Exports take them as they
        # are and georeference only the trees still in memory.
        self._final: dict[str, Tree] = {}
        self._final_rejected: dict[str, Tree] = {}
        self._render = {name: RenderCache() for name in (CSV_NAME, GEOJSON_NAME, REJECTED_NAME)}
        self._closed = False
        if facts:
            self.set_facts(facts)

    def reported(self) -> list:
        """The mapper's trees seen often enough to report (a stray one-scan cluster is not)."""
        return [t for t in self.seen() if t.kind == TREE]

    def rejected(self) -> list:
        """Objects seen as often, that are not trees (each with its reason in `kind`)."""
        return [t for t in self.seen() if t.kind != TREE]

    def seen(self, ids: set[int] | None = None, *, retired: bool = True) -> list:
        """The mapper's trees seen in `min_observations` scans: every one, or `ids`
        among them, with or without those it finalised (`retired`)."""
        mapper = self.processor.mapper
        if isinstance(mapper, TreeMapper):
            trees = mapper.trees(ids, retired=retired)
        else:  # a mapper that keeps every tree in memory
            trees = [t for t in mapper.trees() if ids is None or t.tree_id in ids]
        return [t for t in trees if t.observations >= self.min_observations]

    def georeferenced(self, only: set[str] | None = None, trees: list | None = None) -> list[Tree]:
        """The reported trees (or `trees`, mapped trees) as output records (`only`: just
        these ids' records; matching weighs all of them)."""
        localizer = self.processor.localizer
        field_map = self._index() or self.field_map
        return georeference(
            self.reported() if trees is None else [t for t in trees if t.kind == TREE],
            localizer.grid,
            field_map,
            utm_from_odom=self.processor.utm_from_odom,
            gate_m=self.match_gate_m,
            only=only,
        )

    def commit(self, outcome: ScanOutcome) -> None:
        """One scan's observations and the trees it touched, in one transaction."""
        result = outcome.result
        observations = [
            Observation(
                result.t,
                str(c.tree_id),
                float(c.centroid[0]),
                float(c.centroid[1]),
                float(c.centroid[2]),
                result.frame,
                None,
                None,
                None if c.ndvi is None or c.ndvi != c.ndvi else float(c.ndvi),
                c.num_points,
            )
            for c in result.clusters
            if c.tree_id is not None
        ]
        self._follow(outcome)
        touched = {str(i) for i in (*result.created, *result.updated)}
        retired = list(getattr(result, "retired", ()))
        if self.processor.anchor is not self._anchor:
            # The map moved from odom to utm (a late first fix): every tree is placed anew.
            self._anchor = self.processor.anchor
            trees = self.georeferenced()
            final = {t.tree_id: t for t in trees if t.tree_id in self._final}
            rejected = self.georeferenced_rejected()
            final_rejected = {t.tree_id: t for t in rejected if t.tree_id in self._final_rejected}
        else:
            final, final_rejected = self._final, self._final_rejected
            # Matching weighs the trees in memory (a finalised tree is out of reach of any
            # tree the scan touched), with the ones finalised now.
            if touched or retired:
                live = self.seen(retired=False) + self.seen(set(retired))
                trees = self.georeferenced(touched | {str(i) for i in retired}, live)
            else:
                trees = []
        added, added_rejected = {}, {}
        if retired:
            gone = {str(i) for i in retired}
            added = {t.tree_id: t for t in trees if t.tree_id in gone}
            seen = self.seen(set(retired))
            added_rejected = {t.tree_id: t for t in self._georeferenced_rejected(seen)}
        try:
            self.store.commit_scan(observations, trees)
        except sqlite3.Error as exc:
            self._roll_back()
            raise OutputError(
                f"{self.store_path}: scan not committed: {_sqlite_text(exc)}"
            ) from exc
        # Added once the scan is in the store, so a failed commit leaves them as they were
        # (not by copying them all every scan: a cost that would grow with the survey).
        final.update(added)
        final_rejected.update(added_rejected)
        self._final, self._final_rejected = final, final_rejected
        self.scans += 1

    def export(self) -> Exported:
        """Rewrite trees.csv, trees.geojson (found and missing trees) and rejected.geojson
        (each atomically), and the store's missing trees and rejected objects."""
        live = self.seen(retired=False)
        found = _by_id(self.georeferenced(trees=live), self._final)
        missing = self.missing(found)
        rejected = _by_id(self._georeferenced_rejected(live), self._final_rejected)
        try:
            self.store.replace_unmatched(missing, rejected)
        except sqlite3.Error as exc:
            self._roll_back()
            raise OutputError(
                f"{self.store_path}: missing and rejected not written: {_sqlite_text(exc)}"
            ) from exc
        trees = found + missing
        for name, write, rows in (
            (CSV_NAME, write_trees_csv, trees),
            (GEOJSON_NAME, write_trees_geojson, trees),
            (REJECTED_NAME, write_trees_geojson, rejected),
        ):
            path = self.out_dir / name
            try:
                write(path, rows, self._render[name])
            except OSError as exc:
                raise OutputError(
                    f"{path}: not rewritten ({exc.strerror or exc}); the previous version stays"
                ) from exc
        self.exports += 1
        return Exported(found, missing, rejected)

    def georeferenced_rejected(self) -> list[Tree]:
        return self._georeferenced_rejected(self.seen())

    def _georeferenced_rejected(self, seen: list) -> list[Tree]:
        localizer = self.processor.localizer
        return georeference(
            [t for t in seen if t.kind != TREE],
            localizer.grid,
            (),
            utm_from_odom=self.processor.utm_from_odom,
        )

    def missing(self, found: list[Tree]) -> list[Tree]:
        """Field-map trees passed within `missing_range_m` that no found tree matched."""
        index = self._index()
        if index is None or not len(index) or not self._path:
            return []
        return missing_trees(index, found, self._passed(index), self.missing_range_m)

    def _passed(self, index: FieldMapIndex) -> np.ndarray:
        """Each field-map tree's nearest approach by the path so far (m; inf where the
        path never came within `missing_range_m`). The path points whose UTM place can no
        longer change (driven in `utm`, or in `odom` before the re-anchoring) are taken in
        once; the rest, in `odom` with no datum yet, are placed again each time."""
        anchor = self.processor.anchor
        state = self._approach
        if state is None or state.index is not index or state.anchor is not anchor:
            state = self._approach = _Approach(index, anchor, np.full(len(index), np.inf))
        settled = state.taken
        while settled < len(self._path) and _place_is_final(self._path[settled], anchor):
            settled += 1
        place = self.processor.utm_from_odom
        grid, reach = index.grid, self.missing_range_m
        index.approach(
            utm_positions(self._path[state.taken : settled], grid, place), reach, state.nearest
        )
        state.taken = settled
        if settled == len(self._path):
            return state.nearest
        passed = state.nearest.copy()
        index.approach(utm_positions(self._path[settled:], grid, place), reach, passed)
        return passed

    def path_utm(self) -> list[list[float]]:
        """The robot's path so far in UTM (easting, northing; cm), one point per metre
        driven: the run fact `path`, which `treetraits report` draws under the trees."""
        grid = self.processor.localizer.grid
        if grid is None or not self._path:
            return []
        xy = utm_positions(self._path, grid, self.processor.utm_from_odom)
        return [[round(float(e), 2), round(float(n), 2)] for e, n in xy if math.isfinite(e)]

    def _index(self) -> FieldMapIndex | None:
        """The field map in the run's UTM grid, built once per grid."""
        grid = self.processor.localizer.grid
        if not self.field_map or grid is None:
            return None
        if self._field_index is None or self._field_index.grid is not grid:
            self._field_index = FieldMapIndex(self.field_map, grid)
        return self._field_index

    def _follow(self, outcome: ScanOutcome) -> None:
        pose = outcome.pose
        if pose is None or pose.frame not in ("utm", "odom"):
            return
        last = self._path[-1] if self._path else None
        if (
            last is None
            or last.frame != pose.frame
            or math.hypot(pose.x - last.x, pose.y - last.y) >= 1.0
        ):
            self._path.append(_PathPoint(len(self._path), pose.x, pose.y, pose.frame, pose.t))

    def set_facts(self, facts: dict) -> None:
        try:
            self.store.set_run_facts(facts)
        except sqlite3.Error as exc:
            self._roll_back()
            raise OutputError(
                f"{self.store_path}: run facts not written: {_sqlite_text(exc)}"
            ) from exc

    def close(self) -> None:
        """Checkpoint and close the store. Idempotent; a failing checkpoint (disk full)
        leaves the WAL beside the database, which SQLite replays on the next open."""
        if self._closed:
            return
        self._closed = True
        try:
            self.store.close()
        except sqlite3.Error as exc:
            raise OutputError(
                f"{self.store_path}: not closed cleanly: {_sqlite_text(exc)}"
            ) from exc

    def _roll_back(self) -> None:
        # SQLite may leave the transaction open after SQLITE_FULL or SQLITE_IOERR on COMMIT;
        # the next BEGIN would then fail forever.
        self.store.rollback()


@dataclass(frozen=True)
class Exported:
    found: list[Tree]
    missing: list[Tree]  # field-map trees passed and not found
    rejected: list[Tree]  # objects that are not trees, each with its reason


@dataclass
class _Approach:
    """The field map's nearest approach by the path, taken in point by point (an export
    then looks at the points added since the last one, not at the whole path against the
    whole map). Valid for one field-map index and one re-anchoring of the map."""

    index: FieldMapIndex
    anchor: object  # SurveyProcessor.anchor when it was begun
    nearest: np.ndarray  # per field-map tree (m); inf: never within reach
    taken: int = 0  # path points taken in


def _place_is_final(point: _PathPoint, anchor) -> bool:
    """Its UTM place can no longer change: driven in `utm`, or in `odom` before the map
    was re-anchored (placed by that re-anchoring's transform for good)."""
    return point.frame == "utm" or (anchor is not None and point.last_seen <= anchor[0])


@dataclass(frozen=True)
class _PathPoint:
    """A point of the robot's path, shaped as georeferencing reads a mapped tree."""

    tree_id: int
    x: float
    y: float
    frame: str
    last_seen: int
    width_m: float = math.nan
    height_m: float = math.nan
    ndvi: float | None = None
    observations: int = 0
    first_seen: int = 0


def _by_id(live: list[Tree], final: dict[str, Tree]) -> list[Tree]:
    """The records of the trees in memory and of those finalised, by tree id (the order
    of the mapper's trees)."""
    if not final:
        return live
    return sorted([*live, *final.values()], key=lambda tree: int(tree.tree_id))


def _sqlite_text(exc: sqlite3.Error) -> str:
    name = getattr(exc, "sqlite_errorname", None)
    return f"{exc} ({name})" if name else str(exc)
