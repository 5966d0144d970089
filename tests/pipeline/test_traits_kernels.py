"""The outline's compiled steps (`traits._scan_cells`, `traits._merged_cells`) give the
bits of the NumPy formulation they replaced, on the clusters the mapper hands each tree's
outline on the twin drive past the 2 x 3 grid, and compile nothing beyond the warm-up;
the paper's width (`slice_width`, its bounds compiled) is that of every slice measured
on the same clusters."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from tests.helpers.kernels import assert_warm_ups_cover
from tests.helpers.traits import every_slice_width
from tests.helpers.twin import map_twin_drive_watching
from treetraits.drivers.records import row_items
from treetraits.pipeline import traits as traits_module
from treetraits.pipeline.config import MapperConfig, TraitsConfig
from treetraits.pipeline.traits import (
    RobustTraits,
    _pending_cells,
    _scan_cells,
    _unique_cells,
    _voxel_keys,
    slice_width,
)

CONFIG = TraitsConfig(method="robust")


@functools.cache
def outline_inputs() -> tuple[tuple[np.ndarray, ...], ...]:
    """Per tree, the returns (world frame) its outline was given scan by scan."""
    seen: dict[int, list[np.ndarray]] = {}

    def spy(observe):
        def recording(self, points_base, ring, ground_z, points_world=None, *args, **kwargs):
            if points_world is not None and len(points_world):
                seen.setdefault(id(self), []).append(np.array(points_world, dtype=float))
            return observe(self, points_base, ring, ground_z, points_world, *args, **kwargs)

        return recording

    map_twin_drive_watching(MapperConfig(traits=CONFIG), RobustTraits, "observe", spy)
    return tuple(tuple(clusters) for clusters in seen.values() if len(clusters) >= 5)


def numpy_inserted(at, *pairs):
    """`traits._inserted` (np.insert of each pair's values at `at`) before the kernel."""
    size = len(pairs[0][0]) + len(at)
    slots = at + np.arange(len(at))
    kept = np.ones(size, dtype=bool)
    kept[slots] = False
    out = []
    for grid, values in pairs:
        merged = np.empty((size, *grid.shape[1:]), dtype=grid.dtype)
        merged[slots] = values
        row_items(merged)[kept] = row_items(grid)
        out.append(merged)
    return out


class NumpyOutline(RobustTraits):
    """RobustTraits with the cell steps as NumPy computed them before the kernels."""

    def observe(self, points_base, ring, ground_z_base, points_world=None, *rest):
        points_world = np.asarray(points_world, dtype=float)
        keys, first = np.unique(_voxel_keys(points_world, self.voxel), return_index=True)
        self._pending.append((keys, points_world.take(first, axis=0)))
        self._pending_count += len(keys)
        if self._pending_count > max(len(self._keys), 5000):
            self._consolidate()

    def _consolidate(self) -> None:
        if not self._pending:
            return
        keys, points, hits = _pending_cells(self._pending, self._pending_count)
        self._pending, self._pending_count = [], 0
        at = np.searchsorted(self._keys, keys)
        if len(self._keys):
            known = self._keys.take(at, mode="clip") == keys
        else:
            known = np.zeros(len(keys), dtype=bool)
        new = ~known
        grid_at = at[known]
        before = self._hits[grid_at]
        after = before + hits[known]
        grid_hits = self._hits.copy()
        grid_hits[grid_at] = after
        need = self.config.min_hits
        new_points, new_hits = points.compress(new, axis=0), hits[new]
        reached = np.vstack(
            [
                self._points[grid_at[(before < need) & (after >= need)]],
                new_points[new_hits >= need],
            ]
        )
        keys, points, hits = numpy_inserted(
            at[new], (self._keys, keys[new]), (self._points, new_points), (grid_hits, new_hits)
        )
        coarsened = len(keys) > self.config.max_points
        while len(keys) > self.config.max_points:
            self.voxel *= 2.0
            keys, points, hits = _unique_cells(_voxel_keys(points, self.voxel), points, hits)
        self._keys, self._hits, self._points = keys, hits, points
        if coarsened:
            self._seen_count, self._seen_lo, self._seen_hi = (
                0,
                np.full(2, np.inf),
                np.full(2, -np.inf),
            )
            reached = points.compress(hits >= need, axis=0)
        if len(reached):
            self._seen_count += len(reached)
            self._seen_lo = np.minimum(self._seen_lo, reached[:, :2].min(axis=0))
            self._seen_hi = np.maximum(self._seen_hi, reached[:, :2].max(axis=0))


def state(outline: RobustTraits) -> tuple[bytes, ...]:
    points, hits = outline.cells()
    return (
        outline._keys.tobytes(),
        points.tobytes(),
        hits.tobytes(),
        np.float64(outline.voxel).tobytes(),
        np.int64(outline._seen_count).tobytes(),
        outline._seen_lo.tobytes(),
        outline._seen_hi.tobytes(),
    )


def centre_bytes(outline: RobustTraits) -> bytes | None:
    centre = outline.centre()
    return None if centre is None else centre.tobytes()


def test_the_twin_drive_gives_the_outlines_work():
    clusters = outline_inputs()
    assert len(clusters) >= 4 and sum(len(c) for c in clusters) > 100
    sizes = [len(points) for c in clusters for points in c]
    assert max(sizes) > 200


@pytest.mark.parametrize("voxel", [0.1, 0.4, 0.05])
def test_scan_cells_are_np_unique_of_the_voxel_keys(voxel):
    offsets = (np.zeros(3), np.array([-523.7, 1201.3, -3.2]))  # either side of the origin
    for points in (p for c in outline_inputs() for p in c):
        for offset in offsets:
            xyz = points + offset
            keys, first = np.unique(_voxel_keys(xyz, voxel), return_index=True)
            got_keys, got_rows = _scan_cells(xyz, voxel)
            assert got_keys.tobytes() == keys.tobytes()
            assert got_rows.tobytes() == xyz.take(first, axis=0).tobytes()


@pytest.mark.parametrize("max_points", [20000, 150])
@pytest.mark.parametrize("ask_every", [1, 3])
def test_outline_cells_are_those_numpy_kept(max_points, ask_every):
    """Scan by scan, the centre asked every scan (one scan's cells merged) or every third
    (several scans' cells pending together); with room enough or coarsening."""
    config = dataclasses.replace(CONFIG, max_points=max_points)
    for clusters in outline_inputs():
        got, want = RobustTraits(config), NumpyOutline(config)
        for k, points in enumerate(clusters):
            got.observe(None, None, 0.0, points, 0.0)
            want.observe(None, None, 0.0, points, 0.0)
            if k % ask_every == 0:
                assert centre_bytes(got) == centre_bytes(want)
                assert state(got) == state(want)
        assert state(got) == state(want)
        assert got._seen_count > 0
    if max_points < 20000:
        assert got.voxel > CONFIG.voxel_m  # the grid was coarsened


def test_absorbed_outlines_are_those_numpy_kept():
    clusters = outline_inputs()
    outlines = []
    for kind in (RobustTraits, NumpyOutline):
        one, two = kind(CONFIG), kind(CONFIG)
        for points in clusters[0]:
            one.observe(None, None, 0.0, points, 0.0)
        for points in clusters[1]:
            two.observe(None, None, 0.0, points, 0.0)
        one.centre()
        one.absorb(two)
        one.observe(None, None, 0.0, clusters[0][-1], 0.0)
        outlines.append(one)
    assert state(outlines[0]) == state(outlines[1])


def test_outlines_compile_nothing_beyond_the_warm_up():
    kernels = (traits_module._scan_cells, traits_module._merged_cells)

    def run() -> None:  # float32 and reversed: the layouts callers may pass
        outline = RobustTraits(CONFIG)
        for points in outline_inputs()[0]:
            outline.observe(None, None, 0.0, points.astype(np.float32)[::-1], 0.0)
            outline.centre()

    assert_warm_ups_cover(kernels, (traits_module.compile_kernels,), run)


def test_slice_width_of_the_twin_clusters_is_every_slice_measured():
    """The bounds skip slices only where they cannot win: on each cluster alone, and as
    the paper's traits call it scan after scan, with the width kept so far as the floor."""
    for clusters in outline_inputs():
        kept = 0.0
        for points in clusters:
            alone = every_slice_width(points, 10, 0.0)
            assert slice_width(points, 10) == alone
            assert slice_width(points, 10, kept) == every_slice_width(points, 10, kept)
            kept = max(kept, alone)


def test_slice_width_compiles_nothing_beyond_the_warm_up():
    def run() -> None:  # float32 and reversed: the layouts callers may pass
        for points in outline_inputs()[0]:
            slice_width(points.astype(np.float32)[::-1], 10)
            slice_width(points, 10, 0.5)

    assert_warm_ups_cover((traits_module._slice_bounds,), (traits_module.compile_kernels,), run)
