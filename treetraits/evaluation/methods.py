"""The methods `treetraits eval` compares. A module of their own, with no imports of ours:
the command line's parser lists them without loading the twin or the pipeline (a named
tuple, not a dataclass: `dataclasses` pulls `inspect` into every start)."""

from __future__ import annotations

from typing import NamedTuple


class Method(NamedTuple):
    name: str
    replay_method: str  # ReplayOptions.method
    traits: str  # ReplayOptions.traits
    description: str


METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("paper", "paper", "paper", "the paper's method and traits (keep the maximum)"),
        Method("robust", "paper", "robust", "the paper's detection and tracking, robust traits"),
        Method("rph", "rph", "paper", "RPH baseline as shipped (the one Table I compares)"),
        Method("rph-vlp16", "rph-vlp16", "paper", "RPH retuned for single VLP-16 scans"),
    )
}
DEFAULT_METHODS = ("paper", "robust", "rph")
