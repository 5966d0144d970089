"""A season of surveys, offline: `treetraits batch` (`batch`, Dask tasks), the season store
linking trees across surveys (`store`), its exports (`export`) and the HTML report
(`report`); docs/season.md. Needs the `season` extra (Dask, matplotlib); nothing on the
robot imports it.
"""
