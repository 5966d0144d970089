"""Trees for the store of record (`service/store.py`)."""

from __future__ import annotations

from treetraits.pipeline.trees import Tree


def tree(i: int, observations: int = 1) -> Tree:
    return Tree(
        f"T{i}",
        467000.0 + i,
        3758000.0,
        "11N",
        33.96,
        -117.35,
        2.7,
        2.6,
        0.75,
        observations,
        1_000,
        2_000 + observations,
    )
