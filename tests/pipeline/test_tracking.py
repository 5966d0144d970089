"""The paper's association, piece by piece, against numbers worked out by hand: the
Kalman models, the percentage innovation, Mahalanobis distance, p = exp(-0.1 d), the
entropy gate, duplicate pairs, missing NDVI, the B-matrix motion and the merge."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline.config import TrackingConfig
from treetraits.pipeline.tracking import (
    Motion,
    Tracker,
    mahalanobis,
    motion_transform,
    normalised_entropy,
    normalised_innovation,
)

I4 = np.eye(4)
NAN = float("nan")


def tracker(**overrides) -> Tracker:
    return Tracker(TrackingConfig(**overrides))


def step(tr: Tracker, measurements, t=0, in_view=None):
    measurements = np.atleast_2d(np.asarray(measurements, dtype=float))
    view = np.ones(len(tr.tracks), dtype=bool) if in_view is None else np.asarray(in_view)
    return tr.step(measurements, I4, view, t)


def test_a_new_tree_starts_with_the_papers_models():
    tr = tracker()
    result = step(tr, [5.0, 2.0, 1.0, 300, 0.7], t=11)
    assert [d.outcome for d in result.decisions] == ["created"]
    assert math.isnan(result.decisions[0].p_max)  # nothing to compare with: first tree
    kf = tr.tracks[0].kf
    assert np.array_equal(kf.x[:, 0], [5.0, 2.0, 1.0, 300, 0.7])
    for matrix in (kf.P, kf.F, kf.H, kf.Q):
        assert np.array_equal(matrix, np.eye(5))
    assert np.array_equal(kf.R, 0.1 * np.eye(5))
    assert tr.tracks[0].first_seen == tr.tracks[0].last_seen == 11


def test_innovation_is_a_percentage_per_component_with_floors():
    config = TrackingConfig()
    measured = np.array([[5.5, 0.2, 0.9, 330.0, 0.77]])
    predicted = np.array([[5.0, 0.1, 0.5, 300.0, 0.70]])
    out = normalised_innovation(measured, predicted, measured[:, :3], predicted[:, :3], config)
    # x: 0.5/5 = 10 %; y: 0.1 over the 1 m floor = 10 %; z: 0.4 over 1 m = 40 %;
    # points: 30/300 = 10 %; NDVI: 0.07/0.7 = 10 %.
    assert out.shape == (1, 1, 5)
    assert out[0, 0] == pytest.approx([10, 10, 40, 10, 10])
    # Positions are compared in the frame given (the LiDAR's), not the map's.
    shifted = normalised_innovation(
        measured, predicted, measured[:, :3] + 100, predicted[:, :3] + 100, config
    )
    assert shifted[0, 0, :3] == pytest.approx([50 / 105, 10 / 100.1, 40 / 100.5])


def test_mahalanobis_uses_only_the_measured_components():
    innovation = np.array([[[3.0, 4.0, 0.0, 0.0, 12.0]]])
    S = np.diag([1.0, 1.0, 1.0, 1.0, 4.0])[None]
    full = mahalanobis(innovation, S, np.ones((1, 1, 5), dtype=bool))
    assert full[0, 0] == pytest.approx(math.sqrt(9 + 16 + 144 / 4))
    used = np.array([[[True, True, True, True, False]]])
    assert mahalanobis(innovation, S, used)[0, 0] == pytest.approx(5.0)
    # A full (non-diagonal) S is marginalised, not just cut.
    S = np.array([[2.0, 1.0], [1.0, 2.0]])
    big = np.eye(5)
    big[:2, :2] = S
    d = mahalanobis(np.array([[[1.0, 0, 0, 0, 0]]]), big[None], np.ones((1, 1, 5), bool))
    assert d[0, 0] == pytest.approx(math.sqrt(np.linalg.inv(S)[0, 0]))


def test_entropy_is_normalised_by_log_m():
    assert normalised_entropy(np.log([[0.5, 0.5]]))[0] == pytest.approx(1.0)
    assert normalised_entropy(np.log([[0.3, 0.3, 0.3]]))[0] == pytest.approx(1.0)
    assert normalised_entropy(np.array([[0.0, -1e4, -1e4]]))[0] == pytest.approx(0.0, abs=1e-9)
    assert normalised_entropy(np.array([[-5.0]]))[0] == 0.0  # M = 1: defined as 0
    # p = [0.9, 0.1] normalised: H = -(0.9 ln 0.9 + 0.1 ln 0.1) / ln 2.
    expected = -(0.9 * math.log(0.9) + 0.1 * math.log(0.1)) / math.log(2)
    assert normalised_entropy(np.log([[0.9, 0.1]]))[0] == pytest.approx(expected)
    # Far below float range (d in the thousands) still normalises: no 0/0.
    assert np.isfinite(normalised_entropy(np.array([[-900.0, -950.0, -2000.0]]))).all()


def test_probability_is_exp_minus_a_tenth_of_the_distance():
    tr = tracker()
    step(tr, [5.0, 2.0, 1.0, 300, 0.7])
    # After predict P = 2 I, so S = 2.1 I. Move x by 0.3 m: 6 % -> d = 6 / sqrt(2.1).
    result = step(tr, [5.3, 2.0, 1.0, 300, 0.7])
    d = 6.0 / math.sqrt(2.1)
    assert result.decisions[0].outcome == "updated"
    assert result.decisions[0].p_max == pytest.approx(math.exp(-0.1 * d))
    assert result.decisions[0].entropy == 0.0  # one tree in memory


def test_unlikely_clusters_start_trees_and_ambiguous_ones_too():
    tr = tracker(merge_distance_m=0)
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, -2.0, 1.0, 300, 0.7]])
    # 20 % off both in points: p = exp(-0.1 * 20 / sqrt(2.1)) = 0.25 < 0.5: new tree.
    result = step(tr, [[5.0, 2.0, 1.0, 360, 0.7]])
    assert result.decisions[0].outcome == "created"
    assert 0.2 < result.decisions[0].p_max < 0.3
    # Two identical trees: p is high but the entropy is 1 (log base 2): new tree.
    tr = tracker(merge_distance_m=0)
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, 2.0, 1.0, 300, 0.7]])
    result = step(tr, [[5.0, 2.0, 1.0, 300, 0.7]])
    assert result.decisions[0].outcome == "created"
    assert result.decisions[0].p_max > 0.9 and result.decisions[0].entropy == pytest.approx(1)


def test_thresholds_are_configurable():
    strict = tracker(th_p=0.9, merge_distance_m=0)
    step(strict, [5.0, 2.0, 1.0, 300, 0.7])
    assert step(strict, [5.3, 2.0, 1.0, 300, 0.7]).decisions[0].outcome == "created"


def test_two_clusters_claiming_one_tree_update_it_once():
    tr = tracker()
    step(tr, [5.0, 2.0, 1.0, 300, 0.7])
    # Equally likely (mirror images around the tree): the first keeps it, the second is
    # dropped - not updated, and not made a tree of its own.
    result = step(tr, [[5.1, 2.0, 1.0, 300, 0.7], [4.9, 2.0, 1.0, 300, 0.7]])
    assert [d.outcome for d in result.decisions] == ["updated", "duplicate"]
    assert result.decisions[0].tree_id == result.decisions[1].tree_id == 1
    assert len(tr.tracks) == 1 and tr.tracks[0].observations == 2
    # Unequal: the likelier one wins whatever its order.
    result = step(tr, [[5.3, 2.0, 1.0, 300, 0.7], [5.05, 2.0, 1.0, 300, 0.7]])
    assert [d.outcome for d in result.decisions] == ["duplicate", "updated"]


def test_update_is_the_kalman_update_with_r_a_tenth():
    tr = tracker()
    step(tr, [5.0, 2.0, 1.0, 300, 0.7])
    step(tr, [5.2, 2.0, 1.0, 310, 0.7])
    # P predicted 2, gain 2 / 2.1: x = 5 + 0.2 * 2 / 2.1; P = 2 * 0.1 / 2.1.
    state, P = tr.tracks[0].state, tr.tracks[0].kf.P
    assert state[0] == pytest.approx(5 + 0.2 * 2 / 2.1)
    assert state[3] == pytest.approx(300 + 10 * 2 / 2.1)
    assert np.allclose(P, np.eye(5) * 0.2 / 2.1)


def test_missing_ndvi_is_left_out_of_the_gate_and_the_update():
    tr = tracker()
    step(tr, [5.0, 2.0, 1.0, 300, NAN])
    assert not tr.tracks[0].has_ndvi and tr.tracks[0].state[4] == 0.0
    result = step(tr, [5.0, 2.0, 1.0, 300, 0.7])
    # The tree had no NDVI: its first NDVI starts that component (x = m, P = 1) and the
    # gate used the four other components.
    assert result.decisions[0].p_max == pytest.approx(1.0)
    assert tr.tracks[0].has_ndvi and tr.tracks[0].state[4] == pytest.approx(0.7)
    assert tr.tracks[0].kf.P[4, 4] == pytest.approx(1.0)
    # A cluster without NDVI (out of the camera's view) does not move the tree's NDVI.
    result = step(tr, [5.0, 2.0, 1.0, 300, NAN])
    assert result.decisions[0].outcome == "updated"
    assert tr.tracks[0].state[4] == pytest.approx(0.7)
    assert tr.tracks[0].kf.P[4, 4] == pytest.approx(2.0)  # predicted, not updated


def test_trees_out_of_view_are_not_predicted_nor_candidates():
    tr = tracker(merge_distance_m=0)
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, 2.0, 1.0, 300, 0.7]])
    result = step(tr, [[5.0, 2.0, 1.0, 300, 0.7]], in_view=[True, False])
    assert result.candidates == 1
    assert result.decisions[0].outcome == "updated" and result.decisions[0].tree_id == 1
    assert np.allclose(tr.tracks[1].kf.P, np.eye(5))  # frozen while unseen


def test_trees_born_in_a_scan_are_not_candidates_for_its_other_clusters():
    tr = tracker(merge_distance_m=0)
    result = step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, 2.0, 1.0, 300, 0.7]])
    assert [d.outcome for d in result.decisions] == ["created", "created"]


def test_merge_collapses_one_tree_seen_twice():
    tr = tracker()
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [9.0, 2.0, 1.0, 300, 0.7]], t=1)
    # A cluster 0.9 m off (18 %): the gate starts a new tree; it lies within 1.5 m of
    # tree 1, so tree 1 keeps its id and the two estimates are fused by their covariances:
    # tree 1 predicted to P = p0 + q = 2, the new tree at P = p0 = 1, so the fused x is
    # 5.0 + 0.9 * 2 / 3 and its variance 2 - 2 * 2 / 3. The decision names the tree that
    # remains; it was seen in two scans.
    result = step(tr, [[5.9, 2.0, 1.0, 300, 0.7]], t=2)
    assert result.decisions[0].outcome == "merged" and result.decisions[0].tree_id == 1
    assert result.merged == [(1, 3)]
    assert [t.tree_id for t in tr.tracks] == [1, 2]
    assert tr.tracks[0].state[0] == pytest.approx(5.6)
    assert tr.tracks[0].kf.P[0, 0] == pytest.approx(2 / 3)
    assert tr.tracks[0].observations == 2 and tr.tracks[0].last_seen == 2


def test_two_trees_known_apart_are_not_merged():
    """The same scans as above, with the mapper saying the two tracks are two trees (their
    trunks stand apart): no merge, the new track stays; asked about 1 and 3."""
    tr = tracker()
    asked = []
    tr.apart = lambda keep, drop: asked.append((keep.tree_id, drop.tree_id)) or True
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [9.0, 2.0, 1.0, 300, 0.7]], t=1)
    result = step(tr, [[5.9, 2.0, 1.0, 300, 0.7]], t=2)
    assert result.merged == [] and result.decisions[0].outcome == "created"
    assert [t.tree_id for t in tr.tracks] == [1, 2, 3] and asked == [(1, 3)]


def test_a_standing_object_beside_a_tree_is_not_merged_into_it():
    """A person 0.9 m from a tree's centre (a cluster judged a post or person: standing)
    starts a track the distance merge leaves apart; a second standing cluster beside the
    person's track merges with it as before."""
    tr = tracker()
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7]], t=1)
    person = np.array([[5.9, 2.0, 1.0, 300, 0.7]])
    result = tr.step(person, I4, np.ones(1, dtype=bool), 2, np.array([True]))
    assert result.decisions[0].outcome == "created" and result.merged == []
    assert [t.standing for t in tr.tracks] == [False, True]
    again = np.array([[6.6, 2.0, 1.0, 300, 0.7]])
    result = tr.step(again, I4, np.ones(2, dtype=bool), 3, np.array([True]))
    # 0.7 m from the person's track (14 %) and 1.6 m from the tree's: a new track,
    # folded at once into the person's, not into the tree's.
    assert result.merged == [(2, 3)] and result.decisions[0].outcome == "merged"
    assert [t.tree_id for t in tr.tracks] == [1, 2]


def test_a_merge_counts_a_scan_both_trees_were_seen_in_once():
    """Two pieces of one crown tracked apart in the same scans, then merged: the tree was
    seen in those scans once each (the paper's count would add the two)."""
    tr = tracker(merge_distance_m=0)
    for t in range(1, 4):
        step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, 4.0, 1.0, 300, 0.7]], t=t)
    assert [track.observations for track in tr.tracks] == [3, 3]
    tr.config = dataclasses.replace(tr.config, merge_distance_m=2.5)
    result = step(tr, [[5.0, 2.0, 1.0, 300, 0.7]], t=4)
    assert result.merged == [(1, 2)]
    assert len(tr.tracks) == 1 and tr.tracks[0].observations == 4


def test_clusters_and_trees_are_paired_as_a_whole():
    """Two clusters both likeliest for tree 1 (0 and 0.1 m from it), the second also within
    the gate of tree 2 (0.2 m): each cluster to its likeliest tree would give tree 1 the
    first and drop the second as its piece; the global assignment gives each tree one."""
    tr = tracker(merge_distance_m=0, max_association_m=1.5)
    # Eight more trees far off: with M = 10 a cluster torn between two trees still passes
    # the entropy gate (log base M), as in a grove.
    far = [[30.0 + 6 * i, -8.0, 1.0, 300, 0.7] for i in range(8)]
    step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, 2.3, 1.0, 300, 0.7], *far], t=1)
    result = step(tr, [[5.0, 2.0, 1.0, 300, 0.7], [5.0, 2.1, 1.0, 300, 0.7]], t=2)
    assert [(d.outcome, d.tree_id) for d in result.decisions] == [("updated", 1), ("updated", 2)]


def test_b_matrix_motion_keeps_standing_trees_standing():
    # Straight on at 0.5 m/s for 0.1 s: a tree 5 m ahead is 4.95 m ahead.
    moved = motion_transform(Motion(0.5, 0.0), 0.1, DEFAULT_T_BASE_LIDAR)
    assert moved @ [5.0, 1.0, 0.5, 1.0] == pytest.approx([4.95, 1.0, 0.5, 1.0])
    # A quarter turn on the spot (LiDAR 4 cm ahead of the axis) around base_link.
    turn = motion_transform(Motion(0.0, math.pi / 2), 1.0, DEFAULT_T_BASE_LIDAR)
    ahead = np.array([5.0, 0.0, 0.0, 1.0])  # lidar frame; 5.04 m ahead of base_link
    assert turn @ ahead == pytest.approx([-0.04, -5.04, 0.0, 1.0], abs=1e-9)
    # Applied to the tracker, the tree states move; covariance stays isotropic.
    tr = tracker()
    step(tr, [5.0, 1.0, 0.5, 300, 0.7])
    tr.move(moved)
    assert tr.tracks[0].state[:3] == pytest.approx([4.95, 1.0, 0.5])
    assert np.allclose(tr.tracks[0].kf.P, np.eye(5))
