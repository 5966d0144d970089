"""A small season store, written as `treetraits batch` writes one (without a batch)."""

from __future__ import annotations

from pathlib import Path

from treetraits.pipeline.linking import DEFAULT_LINK_GATE_M
from treetraits.pipeline.trees import Tree
from treetraits.season.store import SeasonStore, Survey

T0 = 1_778_605_200 * 10**9  # 2026-05-12T17:00:00Z


def found_tree(tree_id: str, east: float, north: float, width: float = 2.5) -> Tree:
    return Tree(tree_id, east, north, "11N", 33.96, -117.35, width, 2.4, 0.7, 20, T0, T0)


def small_season(path: Path, trees: int = 3) -> Path:
    """One survey of `trees` trees in a row, 5 m apart, linked: `season trees` lists them."""
    with SeasonStore(path) as store:
        survey = Survey("block", "a.mcap", "fingerprint-a", T0, "treetraits test", "key", "", False)
        row = [found_tree(f"R{i}", 467000.0 + 5 * i, 3758000.0) for i in range(trees)]
        store.add_survey(survey, row, "2026-05-12T18:00:00Z")
        store.relink("block", DEFAULT_LINK_GATE_M)
    return path
