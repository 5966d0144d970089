"""The output contract, restated here (not imported from the code)."""

from __future__ import annotations

# trees.csv's first columns as docs/architecture.md fixes them (restated here, not imported
# from the code): never reordered or renamed. A new column is appended after them in
# pipeline/trees.py's table, and the tests check the header starts with these.
CONTRACT_CSV_COLUMNS = [
    "tree_id",
    "field_id",
    "row",
    "easting",
    "northing",
    "utm_zone",
    "lat",
    "lon",
    "width_m",
    "height_m",
    "ndvi",
    "observations",
    "first_seen",
    "last_seen",
    "status",  # appended after the contract's fourteen: found or missing
    "height_top_seen",  # appended: true, false (height a lower bound) or empty
    "width_sides_seen",  # appended: 2 (both sides), 1 (width a lower bound) or empty
]
