"""The Voronoi cut's compiled steps (`mapper._own_distances`, `mapper._nearer`) give what
the NumPy formulation they replaced gave, on the clusters and trunks the mapper cuts on
the twin drive past the 2 x 3 grid, with the neighbours it had and with more, nearer
ones; so do the trunk's crowded places (`mapper._cell_means`) on the sightings the
mapper gathers there; and they compile nothing beyond the warm-up."""

from __future__ import annotations

import functools

import numpy as np

from tests.helpers.kernels import assert_warm_ups_cover
from tests.helpers.twin import map_twin_drive_watching
from treetraits.pipeline import mapper as mapper_module
from treetraits.pipeline.config import MapperConfig
from treetraits.pipeline.mapper import _Centres, _crowded_places


def numpy_nearest_is(centres: _Centres, xy: np.ndarray, tree_id: int) -> np.ndarray:
    """`_Centres.nearest_is` as NumPy computed it before its kernels."""
    own = centres.xy[np.flatnonzero(centres.ids == tree_id)[0]]
    x, y = xy[:, 0], xy[:, 1]
    dx, dy = x - own[0], y - own[1]
    own_d2 = dx * dx + dy * dy
    reach = float(np.sqrt(own_d2.max())) if len(xy) else 0.0
    gap = centres.xy - own
    near = centres.claims & (centres.ids != tree_id) & (np.hypot(gap[:, 0], gap[:, 1]) < 2 * reach)
    if not near.any():
        return np.ones(len(xy), dtype=bool)
    others = centres.xy[near]
    dx, dy = x[:, None] - others[:, 0], y[:, None] - others[:, 1]
    other_d2 = (dx * dx + dy * dy).min(axis=1)
    return own_d2 <= other_d2


@functools.cache
def cuts() -> tuple[tuple[_Centres, np.ndarray, int], ...]:
    """Every (centres, x-y points, tree) the mapper cut on the twin drive: clusters, and
    trunk sightings (their centres with the claims the trunk was cut by)."""
    seen = []

    def spy(nearest_is):
        def recording(self, xy, tree_id, claims):
            cut = object.__new__(_Centres)
            cut.__dict__.update(vars(self), claims=claims)
            seen.append((cut, np.array(xy), tree_id))
            return nearest_is(self, xy, tree_id, claims)

        return recording

    map_twin_drive_watching(MapperConfig(), _Centres, "_nearest_is", spy)
    return tuple(seen)


def crowded(centres: _Centres, tree_id: int, seed: int) -> _Centres:
    """The same centres and a claiming neighbour 0.3-1.5 m from each: the cut has work."""
    rng = np.random.default_rng(seed)
    out = object.__new__(_Centres)
    n = len(centres.ids)
    out.ids = np.concatenate([centres.ids, centres.ids.max() + 1 + np.arange(n)])
    out.rows = {int(i): k for k, i in enumerate(out.ids)}
    out.claims = np.concatenate([centres.claims, np.ones(n, dtype=bool)])
    angle = rng.uniform(0, 2 * np.pi, n)
    step = rng.uniform(0.3, 1.5, n)[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    out.xy = np.vstack([centres.xy, centres.xy + step])
    return out


def test_the_mapper_s_cuts_are_numpy_s():
    calls = cuts()
    assert len(calls) > 200 and any(len(xy) == 1 for _, xy, _ in calls)  # trunks too
    for centres, xy, tree_id in calls:
        want = numpy_nearest_is(centres, xy, tree_id)
        assert centres.nearest_is(xy, tree_id).tobytes() == want.tobytes()
        # A strided view (the mapper passes world[:, :2]) gives the same.
        wide = np.column_stack([xy, np.zeros(len(xy))])
        assert centres.nearest_is(wide[:, :2], tree_id).tobytes() == want.tobytes()


def test_crowded_cuts_are_numpy_s():
    cut = 0
    for k, (centres, xy, tree_id) in enumerate(cuts()[::5]):
        crowd = crowded(centres, tree_id, k)
        points = xy.copy()
        if k % 7 == 0 and len(points) > 2:
            points[1] = np.nan  # NaN through the max, the min and <=
        with np.errstate(invalid="ignore"):
            want = numpy_nearest_is(crowd, points, tree_id)
        got = crowd.nearest_is(points, tree_id)
        assert got.tobytes() == want.tobytes()
        cut += int((~want).sum())
    assert cut > 100  # points given back to the nearer neighbours


def test_cuts_compile_nothing_beyond_the_warm_up():
    kernels = (mapper_module._own_distances, mapper_module._nearer, mapper_module._cell_means)

    def run() -> None:  # reversed: strided views, as callers may pass them
        for centres, xy, tree_id in cuts()[:50]:
            crowded(centres, tree_id, 0).nearest_is(np.asarray(xy)[::-1], tree_id)
        for xy, cell in sightings()[:50]:
            _crowded_places(xy[::-1], cell)

    assert_warm_ups_cover(kernels, (mapper_module.compile_kernels,), run)


def test_a_point_halfway_stays_with_the_tree_as_numpy_kept_it():
    centres = object.__new__(_Centres)
    centres.ids, centres.rows = np.array([1, 2]), {1: 0, 2: 1}
    centres.claims = np.array([True, True])
    centres.xy = np.array([[0.0, 0.0], [1.0, 0.0]])
    points = np.array([[0.5, 0.0], [0.5, 3.0], [0.75, 0.1], [0.2, 0.1]])
    want = numpy_nearest_is(centres, points, 1)
    assert want.tolist() == [True, True, False, True]  # ties: its own
    assert centres.nearest_is(points, 1).tobytes() == want.tobytes()


def numpy_crowded_places(xy: np.ndarray, cell: float, places: int = 8) -> np.ndarray:
    """`mapper._crowded_places` as NumPy computed it before its kernel."""
    cells = np.floor(xy / cell).astype(np.int64)
    keys = (cells[:, 0] << 32) + cells[:, 1]
    order = np.argsort(keys)
    ordered = keys[order]
    new = np.empty(len(keys), dtype=bool)
    new[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=new[1:])
    inverse = np.empty(len(keys), dtype=np.intp)
    inverse[order] = np.cumsum(new) - 1
    counts = np.bincount(inverse)
    top = np.argsort(-counts, kind="stable")[:places]
    sums = np.bincount((2 * inverse[:, None] + np.arange(2)).ravel(), weights=xy.ravel())
    return sums.reshape(-1, 2)[top] / counts[top, None]


@functools.cache
def sightings() -> tuple[tuple[np.ndarray, float], ...]:
    """Every (trunk sightings, cell) the mapper placed a trunk from on the twin drive."""
    seen = []

    def spy(crowded_places):
        def recording(xy, cell, *args):
            seen.append((np.array(xy), cell))
            return crowded_places(xy, cell, *args)

        return recording

    map_twin_drive_watching(MapperConfig(), mapper_module, "_crowded_places", spy, trees=True)
    return tuple(seen)


def test_trunk_places_are_numpy_s():
    calls = sightings()
    assert len(calls) > 50 and max(len(xy) for xy, _ in calls) > 20
    for xy, cell in calls:
        assert _crowded_places(xy, cell).tobytes() == numpy_crowded_places(xy, cell).tobytes()
    # Sightings spread over more cells than places, with ties, far from the origin and
    # either side of it (negative cells), one cell size after another.
    rng = np.random.default_rng(2)
    for k in range(300):
        n = int(rng.integers(1, 300))
        xy = rng.normal(0, rng.uniform(0.05, 2.0), (n, 2)) + rng.uniform(-600, 600, 2)
        if k % 3 == 0:
            xy = np.vstack([xy, xy[: n // 2]])
        cell = float(rng.choice([0.3, 0.25, 0.5]))
        got, want = _crowded_places(xy, cell), numpy_crowded_places(xy, cell)
        assert got.tobytes() == want.tobytes()
