"""The detection worker in a second process (`detection_process`): a twin scan of a tree
detected there as the mapper detects it here, scans handed back in their order, and a
detection's error raised in the caller."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tests.helpers.scans import scan_of
from treetraits.pipeline.mapper import TreeMapper
from treetraits.service.detection_worker import detection_process
from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh


def _tree_scan(x: float, seed: int):
    spec = TreeSpec("T1", "1", x, 2.5, 0.45, 0.08, 1.35, 1.1)
    return scan_of(tree_mesh(spec, Ground(), np.random.default_rng(seed)), seed=seed)


def test_a_process_detects_as_the_mapper_does_and_in_order():
    mapper = TreeMapper()
    scans = [_tree_scan(4.0, 1), _tree_scan(6.0, 2)]
    worker = detection_process(mapper)
    try:
        for i, scan in enumerate(scans):
            worker.submit(scan, None, i)
        detected = list(worker.done(wait=True))
    finally:
        worker.close()
    assert [context for _, context in detected] == [0, 1]
    for (there, _), scan in zip(detected, scans, strict=True):
        here = mapper.detect_scan(scan)
        assert here.t == there.t and here.ndvi_reason == there.ndvi_reason
        assert len(there.detection.clusters) == len(here.detection.clusters) >= 1
        for a, b in zip(here.detection.clusters, there.detection.clusters, strict=True):
            assert np.array_equal(a.points, b.points) and a.top_seen == b.top_seen


def test_a_detection_error_in_the_process_is_raised_in_the_caller():
    """A scan whose points lack the fields the detection reads fails there; the error
    comes back with the scan, in the caller's thread, and the worker closes."""
    scan = _tree_scan(4.0, 1)
    broken = dataclasses.replace(scan, points=np.zeros(10, dtype=[("x", "f4")]))
    worker = detection_process(TreeMapper())
    try:
        worker.submit(broken, None, "broken")
        with pytest.raises((ValueError, KeyError)):
            list(worker.done(wait=True))
    finally:
        worker.close()


def test_the_process_outlives_a_sigterm_to_the_services_group():
    """`systemctl stop` signals the service's whole cgroup: the detecting process ignores
    it, so the service maps the scans it holds before it closes the worker."""
    import os
    import signal

    worker = detection_process(TreeMapper())
    try:
        worker.submit(_tree_scan(4.0, 1), None, 0)
        assert len(list(worker.done(wait=True))) == 1
        (child,) = worker._pool._processes.values()
        os.kill(child.pid, signal.SIGTERM)
        child.join(1.0)
        assert child.is_alive()
        worker.submit(_tree_scan(6.0, 2), None, 1)
        assert [context for _, context in worker.done(wait=True)] == [1]
    finally:
        worker.close()
    assert not child.is_alive()
