"""JSON read with an explicit nesting limit, for the files a user hands us (calibration,
field map, a recording's metadata and attachment).

Python's `json` recurses once per level and fails at its recursion limit (about 1000
levels) with a RecursionError that names nothing; a file nested that deep is no
calibration or field map. `loads_limited` measures the depth first (brackets outside
strings, linear time, no recursion) and refuses a deeper text with `JsonTooDeepError`, which each
loader turns into its own typed error naming the file.
"""

from __future__ import annotations

import json
import re
from typing import Any

# Our formats nest at most 5 levels (a GeoJSON FeatureCollection: features, a feature,
# its geometry, coordinates); 32 leaves room for extra properties a GIS tool adds and
# stays far below Python's recursion limit.
MAX_DEPTH = 32

_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.S)
_NOT_BRACKET = re.compile(r"[^\[\]{}]+")


class JsonTooDeepError(ValueError):
    """JSON nested deeper than the limit."""

    def __init__(self, depth: int, limit: int):
        super().__init__(f"JSON nested {depth}+ levels deep (at most {limit} are read)")
        self.depth = depth
        self.limit = limit


def json_depth(text: str, stop_after: int | None = None) -> int:
    """The deepest nesting of arrays and objects in `text` (brackets inside strings do not
    count); stops counting once past `stop_after`."""
    brackets = _NOT_BRACKET.sub("", _STRING.sub("", text))
    depth = deepest = 0
    for char in brackets:
        if char in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if stop_after is not None and deepest > stop_after:
                    break
        else:
            depth -= 1
    return deepest


def loads_limited(text: str | bytes, max_depth: int = MAX_DEPTH) -> Any:
    """`json.loads(text)`; a text nested deeper than `max_depth` is refused
    (`JsonTooDeepError`)."""
    if isinstance(text, bytes | bytearray):
        text = text.decode("utf-8")
    depth = json_depth(text, stop_after=max_depth)
    if depth > max_depth:
        raise JsonTooDeepError(depth, max_depth)
    return json.loads(text)
