"""A run's outputs, shared by `treetraits replay` and the service: the store committed per
scan, and `trees.geojson` / `trees.csv` rewritten atomically (docs/architecture.md, "Outputs").

`RunWriter` owns the store and knows how to turn the mapper's trees into georeferenced
`Tree`s; when to export is the caller's choice (recorded time in a replay, wall time in
the service). Failures to write come out as `OutputError` naming the file and the cause,
with the store's transaction rolled back, so a full disk never leaves a half-written scan.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Sequence
from pathlib import Path

from treetraits.drivers.records import Tree
from treetraits.errors import TreetraitsError
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.fieldmap import FieldTree
from treetraits.pipeline.georef import (
    FieldMapIndex,
    georeference,
    write_trees_csv,
    write_trees_geojson,
)
from treetraits.service.config import OutputConfig
from treetraits.service.store import Observation, TraitStore
from treetraits.service.survey import ScanOutcome, SurveyProcessor

STORE_NAME = "traits.sqlite"
CSV_NAME = "trees.csv"
GEOJSON_NAME = "trees.geojson"


class OutputError(TreetraitsError):
    """An output could not be written (disk full, I/O error); the file named is intact."""


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
        self.store_path = self.out_dir / STORE_NAME
        self.scans = 0  # scans committed
        self.exports = 0
        self.store = TraitStore(self.store_path)
        self._field_index: FieldMapIndex | None = None
        self._closed = False
        if facts:
            self.set_facts(facts)

    def reported(self) -> list:
        """The mapper's trees seen often enough to report (a stray one-scan cluster is not)."""
        return [t for t in self.seen() if t.kind == TREE]

    def rejected(self) -> list:
        """Objects seen as often, that are not trees (each with its reason in `kind`)."""
        return [t for t in self.seen() if t.kind != TREE]

    def seen(self) -> list:
        return [t for t in self.processor.mapper.trees() if t.observations >= self.min_observations]

    def georeferenced(self, only: set[str] | None = None) -> list[Tree]:
        """The reported trees as output records (`only`: just these ids' records)."""
        localizer = self.processor.localizer
        field_map = self.field_map
        if field_map and localizer.grid is not None:
            # The field map in UTM once per run, not after every scan.
            if self._field_index is None or self._field_index.grid is not localizer.grid:
                self._field_index = FieldMapIndex(self.field_map, localizer.grid)
            field_map = self._field_index
        return georeference(
            self.reported(),
            localizer.grid,
            field_map,
            utm_from_odom=localizer.utm_from_odom,
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
        touched = {str(i) for i in (*result.created, *result.updated)}
        trees = self.georeferenced(only=touched) if touched else []
        try:
            self.store.commit_scan(observations, trees)
        except sqlite3.Error as exc:
            self._roll_back()
            raise OutputError(
                f"{self.store_path}: scan not committed: {_sqlite_text(exc)}"
            ) from exc
        self.scans += 1

    def export(self, trees: list[Tree] | None = None) -> list[Tree]:
        """Rewrite trees.csv and trees.geojson (each atomically); returns the trees written."""
        trees = self.georeferenced() if trees is None else trees
        for name, write in ((CSV_NAME, write_trees_csv), (GEOJSON_NAME, write_trees_geojson)):
            path = self.out_dir / name
            try:
                write(path, trees)
            except OSError as exc:
                raise OutputError(
                    f"{path}: not rewritten ({exc.strerror or exc}); the previous version stays"
                ) from exc
        self.exports += 1
        return trees

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


def _sqlite_text(exc: sqlite3.Error) -> str:
    name = getattr(exc, "sqlite_errorname", None)
    return f"{exc} ({name})" if name else str(exc)
