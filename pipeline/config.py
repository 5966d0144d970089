"""Settings of the tree pipeline (detection, tracking, traits), each with the reason for
its default. One frozen dataclass per step; each step gets only its own section.

The paper fixes the Kalman models, the association gates and the trait definitions; it
gives no number for the spatial filter, the ground fit, the voxel grid or the clustering.
Those are chosen here from VLP-16 geometry and measured on the digital twin (the sweep
is in docs/pipeline.md). VLP-16 facts used below: 16 rings 2 deg apart (two adjacent
rings hit a surface 0.035 r m apart at range r), 0.2 deg between firings along a ring at
600 rpm (0.0035 r m), +-3 cm range noise, mounted 0.38-0.44 m above the ground on a
Jackal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from treetraits.errors import ConfigError
from treetraits.pipeline.methods import METHODS, TRAIT_METHODS  # noqa: F401  (re-exported)

CLUSTERING_METHODS = ("kdtree", "dbscan")
GROUND_METHODS = ("numpy", "open3d")
GROUND_MODELS = ("terrain", "plane")


@dataclass(frozen=True)
class CropConfig:
    """The spatial filter: an axis-aligned box in `base` (base_footprint: x forward, y left,
    z up from the ground under the robot)."""

    # +-15 m: the height rule needs the crown top in view, and the top ring (+15 deg)
    # clears a 2.7 m citrus crown only from ~9 m away; past ~15 m rings are > 0.5 m
    # apart, more than the cluster tolerance, so a tree falls apart into ring slivers.
    x_m: tuple[float, float] = (-15.0, 15.0)
    y_m: tuple[float, float] = (-15.0, 15.0)
    # From below any ground a 10 % slope puts within the box to above tall trees.
    z_m: tuple[float, float] = (-2.0, 8.0)
    # Returns within this horizontal distance of the LiDAR are the robot itself (a Jackal
    # is 0.51 x 0.43 m; the VLP-16 reports nothing nearer than ~0.4 m anyway).
    min_range_m: float = 0.6


@dataclass(frozen=True)
class GroundConfig:
    """The ground model and the ground band."""

    # "terrain": the elevation grid grown from the footprint (`detection.terrain`), which
    # follows slopes, undulation and beds. "plane": one RANSAC plane per scan (the keys
    # below), kept to compare with: on sloped, undulating ground it leaves ground above
    # the plane that clusters into false trees.
    model: str = "terrain"
    # Points offered to RANSAC: within this height of the robot's own footprint plane.
    # The ground is the lowest surface and passes through z = 0 under the robot; a 3 deg
    # slope rises 0.5 m in 10 m, enough for the plane's tilt to be fitted.
    candidate_window_m: float = 0.5
    # RANSAC inlier distance: VLP-16 range noise (+-3 cm) seen at grazing angles plus
    # soil roughness.
    distance_m: float = 0.08
    # Three-point hypotheses. With a share w of ground among the candidates, all of k
    # draws miss it with probability (1 - w^3)^k: 1e-7 for w = 0.6 and k = 100.
    iterations: int = 100
    # Cap on the points given to RANSAC (an even stride through the candidates): the
    # near rings oversample the ground. 1000 points with +-3 cm noise pin the refitted
    # plane's tilt to ~0.1 deg and its height to ~1 mm; RANSAC's cost is points x draws.
    max_points: int = 1000
    seed: int = 0  # the RANSAC draws: same scan -> same plane
    # "numpy": our seeded RANSAC (deterministic). "open3d": `segment_plane`, whose
    # threads share one RNG, so a scan's plane can differ between two runs.
    method: str = "numpy"
    # A fitted plane tilted more than this, or with fewer inliers, is not the ground
    # (a wall, a canopy skirt): fall back to z = 0 of base_footprint.
    max_tilt_deg: float = 15.0
    min_inliers: int = 200
    # Points lower than this above the plane are ground candidates. Above RANSAC's band
    # (range noise) and below the lowest citrus skirts (trunks are bare to ~0.3 m in
    # pruned groves); RPH uses 0.2 m for the same job.
    clearance_m: float = 0.15
    # The NDVI check (the paper's "projection on the image"): a ground candidate at least
    # `skirt_min_height_m` above the plane whose NDVI is at least `skirt_min_ndvi` is
    # foliage (a skirt hanging to the ground), not soil. Such a point never starts or
    # joins clusters on its own: it is given to the nearest cluster within the cluster
    # tolerance, else dropped, so a green cover crop cannot bridge two trees.
    # 0.4: between bare soil (0.1-0.2) and citrus foliage (0.5-0.8); the paper's
    # vegetation mask (-0.3, 1.0] is a frame-level mask and passes soil too.
    skirt_min_ndvi: float = 0.4
    skirt_min_height_m: float = 0.05


@dataclass(frozen=True)
class TerrainConfig:
    """The elevation grid under each scan (`pipeline.terrain`), grown from the footprint.
    VLP-16 on a Jackal (0.38-0.44 m up): on flat ground its rings below the horizon land
    at 1.5, 1.7, 2.1, 2.5, 3.3, 4.6, 7.6 and 23 m, dense along each ring, sparse across."""

    # 0.5 m: several returns of one ring per cell along the ring at any range in the box,
    # and half the gap between the nearest rings; finer cells leave most cells empty.
    cell_m: float = 0.5
    # Ground height changes less than this between two cells next to each other, beyond
    # the slope: range noise (+-3 cm) plus furrows and undulation of +-10 cm. A citrus
    # skirt hangs 0.3-0.7 m above the ground at the crown's edge: it is not reached.
    step_tolerance_m: float = 0.15
    # The steepest ground, rise over run, over the distance to the nearest accepted
    # ground: 15 % along a row with 8 % across is 17 %; 0.2 leaves a little for bumps.
    max_slope: float = 0.2
    # Ground is not looked for beyond this distance from ground already accepted: the
    # widest gap between the rings' ground arcs inside the crop (4.6 -> 7.6 m) plus one
    # metre for a pitched robot.
    max_gap_m: float = 4.0
    # Across a gap (more than two cells from accepted ground) a candidate needs this many
    # other candidates within `support_radius_m`: a ring's arc on open ground gives
    # dozens; a trunk or post hit by a level ring gives one or two.
    min_support_cells: int = 4
    support_radius_m: float = 1.0
    # The ground is seeded within this distance of the robot, where the rings below the
    # horizon land five times (1.5-4.6 m on a Jackal): from the lowest extensive surface
    # there (the footprint itself has no returns). A LiDAR mounted higher lands its
    # lowest ring farther out, and the disc reaches past it (`terrain.seed_radius`).
    seed_radius_m: float = 6.0
    # A cell's ground height: the mean of its returns within this height of its lowest
    # one (the lowest alone is ~2 sigma of the range noise low).
    lowest_layer_m: float = 0.05
    # Ground under a crown or in a shadow is filled from the ground around it, weighted
    # by a Gaussian of this width: about a crown radius.
    fill_sigma_m: float = 1.0


@dataclass(frozen=True)
class ClusterConfig:
    """Voxel grid, then single-linkage Euclidean clustering."""

    # 0.2 m: the ring spacing at 5-6 m, mid-range for a tree beside a row. Along a ring
    # the VLP-16 samples every 0.0035 r (2 cm at 5 m), ten times denser than across
    # rings; the grid evens that out, so near trees do not swamp the point budget and
    # `num_points` follows surface area. Traits use every return, not the voxels, so
    # the grid costs them nothing; 0.1 m found the same trees on the twin, with 1-2
    # duplicates more and ~1.3x the time (docs).
    voxel_m: float = 0.2
    # Two points closer than this are in one cluster. It must bridge the gap between
    # adjacent rings on a crown (0.035 r: 0.35 m at 10 m) or a far tree falls into one
    # cluster per ring, and stay below the gap between neighbouring crowns (> 1 m in
    # groves planted 4-6 m apart). Swept 0.3-0.6 in docs/pipeline.md.
    tolerance_m: float = 0.5
    # A return lying between two surfaces a jump of more than `tolerance_m` apart on its
    # ring, this far off each (three times the VLP-16's 3 cm range accuracy), with each
    # surface going on beyond it, is a mixed return (a beam half on an edge, half behind
    # it) and is left out before clustering: it linked an object to the wall behind it
    # on a real indoor capture (`pipeline.mixed`). 0 keeps every return.
    mixed_offset_m: float = 0.1
    # Size limits in voxels. 10: a far crown seen by two rings is ~30 voxels; a post,
    # a trunk alone, a few leaves are fewer. 20000: far above one tree's visible side
    # (300-600 for a 2.7 m crown), only a wall or a building is bigger.
    min_points: int = 10
    max_points: int = 20000
    # Touching crowns (a hedgerow) are cut at their trunks (`detection.split_at_trunks`).
    # Trunks are looked for in this band above the terrain: above the soil's roughness,
    # below the skirts of pruned citrus (0.35-0.6 m; the LiDAR, 0.4 m up, sees it level).
    trunk_band_m: tuple[float, float] = (0.08, 0.32)
    # A trunk seen from one side: 0.05-0.35 m thick; more is a skirt or a weed in the band.
    max_trunk_width_m: float = 0.5
    min_trunk_points: int = 4
    # Trees closer than this are not planted: citrus in-row spacing is 2.5 m at its
    # densest (hedgerows), less 0.2 m of planting error. Clusters shorter than twice
    # this are never cut.
    min_tree_spacing_m: float = 2.3
    # Posts, poles and people beside or between crowns are cut out of the scan before
    # clustering (`pipeline.stems`): a blob in the trunk band with a smooth column over
    # it, no gap, up to at least `min_stem_height_m`, within `stem_radius_m` of its axis.
    # 0.35 m: half a person's shoulders (0.45-0.5 m) and a post's 0.1 m with margin, less
    # than a crown's near surface is from its trunk (a young crown's 0.4 m radius and up).
    stem_radius_m: float = 0.35
    # 1.2 m: trellis posts stand 1.5-2.2 m, people 1.5-1.9 m; weeds and cover crop end
    # at 0.6 m and a citrus trunk is hidden by its skirt from 0.35-0.6 m up. 0 turns the
    # cut off.
    min_stem_height_m: float = 1.2
    # The column is judged smooth or rough on its returns above this height: citrus
    # skirts start by 0.6 m, so higher up a tree's column is foliage (seen through
    # gaps in the crown) while a post's is still wood and a person's clothes. Below it,
    # a trunk is as smooth as a post.
    stem_judged_from_m: float = 0.6
    # A stem stands clear: between `stem_radius_m` and this, over the column's height,
    # at most `max_stem_surround_share` as many returns as in the column itself. 0.5 m:
    # a person between two trees has a hand's breadth of air to either crown; a trunk
    # has its crown around it and a weed under a skirt the crown's side. A post or a
    # person pressed into the foliage stays part of the crown (nothing tells them apart).
    stem_clearance_m: float = 0.5
    max_stem_surround_share: float = 0.25
    # Crowns are clustered on the voxels that reach this high above the terrain; what
    # lies lower joins the crown it touches and never links two (`pipeline.understorey`).
    # 0.6 m: weeds and cover crop end there, a drip line hangs at 0.3-0.4 m, and citrus
    # skirts have begun by then; the youngest trees mapped (1.0 m) reach above it.
    bridge_min_height_m: float = 0.6
    # A cluster's top is seen when the beam above the highest ring that hit it passed
    # over every bearing the cluster spans, widened by this on each side
    # (`pipeline.visibility`): the VLP-16 fires every 0.1-0.4 deg (5-20 Hz), so 1 deg
    # holds 5-20 firings of that beam and an object just past the cluster's edge that
    # hides its top is not missed.
    top_window_deg: float = 1.0
    # "kdtree" (the name kept for configs): pairs within the tolerance found on a grid of
    # cells by a compiled kernel, scipy's cKDTree where no grid fits; "dbscan": open3d
    # `cluster_dbscan(eps, min_points=1)`. Same clusters; see docs for the timing.
    method: str = "kdtree"


@dataclass(frozen=True)
class ClassifyConfig:
    """Tree or not (`pipeline.classify`): the crop profile and the shape rules. Defaults:
    citrus, from young trees of 1.0-1.5 m to old ones of 5 m, planted 2.5-7 m apart."""

    # Shorter than this above the terrain is not a tree: weeds and cover crop reach
    # 0.6 m, drip lines 0.4 m; the youngest trees mapped are 1.0 m (a far scan misses a
    # tree's top by up to one ring gap, so a young tree is judged on its near scans).
    min_height_m: float = 0.8
    # Taller than an old citrus tree (5 m) with room to spare: a building, a mast.
    max_height_m: float = 8.0
    # A tree stands on the ground: its trunk, or a skirt hanging to 0.3-0.7 m, is in
    # view of a LiDAR mounted this low. A cluster whose lowest return is higher than
    # this is a ceiling, a roof's edge or a fragment of a crown.
    max_base_m: float = 1.0
    # Narrower than this is a post (0.1 m), a pole, a trunk alone or a person seen from
    # the side (0.3-0.5 m); a young tree's crown is 0.8 m and up.
    min_width_m: float = 0.6
    # Width over height. A citrus crown is about as wide as it is tall (0.8-1.2, young
    # trees included); a standing person is 0.45 m / 1.75 m = 0.26, a post 0.05.
    min_aspect: float = 0.4
    # Wider than this is not one tree: an old tree's crown is 4-5 m; a hedgerow's
    # touching crowns are split at their trunks before they are judged (`tracking`).
    max_width_m: float = 7.0
    # A stem's column or a trunk's bark is smooth along a ring (`classify.roughness`,
    # consecutive firings): clothes, wood, concrete and steel measured 0.004-0.03 m on
    # the real indoor captures (the range noise). Used to tell posts, people and bark from
    # foliage at trunk level (`pipeline.stems`, `detection.cluster_trunks`), not whether
    # a crown is vegetation (real canopy measured 0.011-0.037 m: the cues below decide).
    min_roughness_m: float = 0.04
    # Vegetation evidence (`pipeline.vegetation`, docs/pipeline.md "Vegetation evidence"):
    # texture, the off-midpoint distance of returns this far apart along a ring. Leaves
    # are 3-10 cm, so at 5 cm neighbours lie on different leaves.
    texture_step_m: float = 0.05
    # Real apple canopy 0.055-0.112 m (10th-90th percentile), real walls, furniture and
    # people 0.006-0.023 m: between them on a log scale. One unit of evidence per doubling.
    texture_pivot_m: float = 0.04
    texture_weight: float = 1.0
    # Planarity: patches of this size, flat within the VLP-16's range noise (1 sigma about
    # 1 cm; +-3 cm accuracy).
    planar_patch_m: float = 0.3
    planar_noise_m: float = 0.02
    # Real canopy 0.11-0.60 of its patches flat (10th-90th percentile), real indoor objects
    # 0.73-1.0. One unit of evidence per 0.3 of share; half a texture's weight.
    planar_pivot: float = 0.4
    planar_scale: float = 0.3
    planar_weight: float = 0.5
    min_ndvi: float = 0.3
    ndvi_scale: float = 0.15
    ndvi_weight: float = 2.0
    # Intensity (the VLP-16's calibrated reflectivity, 0-100 % diffuse): leaves reflect
    # 40-50 % at 905 nm, and real canopy's crowns measured a median of 12-26 (partial hits
    # on leaf edges lower it); black plastic, tyres and dark cloth under 10 % (real indoor
    # dark objects 3-11); but a far crown's sparse top, hit on leaf edges, measured 6-8:
    # it weighs nothing by default (recorded; `calibrate classify` may weigh it where an
    # orchard shows a margin).
    intensity_pivot: float = 10.0
    intensity_scale: float = 10.0
    intensity_weight: float = 0.0
    # A weak echo's range is noisy, and noise looks like leaves to the surface cues: their
    # evidence for foliage counts nothing at this median intensity or below and in full
    # from `clear_intensity` (real dark objects, 3-11: texture 0.02-0.09 m; real walls,
    # 34-71: 0.005-0.01 m; real canopy's crowns 12-26).
    dark_intensity: float = 8.0
    clear_intensity: float = 15.0
    # A track is a tree when at least this share of its verdicts that judge the object
    # (all but `low` and `floating`, which a piece of a crown gets) say tree, and this
    # share of all of them (see `classify.Votes`).
    min_tree_share: float = 0.5
    min_tree_share_all: float = 0.25


@dataclass(frozen=True)
class DetectionConfig:
    """Per scan: the spatial filter, the ground, the clusters (`detection.detect`)."""

    crop: CropConfig = field(default_factory=CropConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    classify: ClassifyConfig = field(default_factory=ClassifyConfig)

    def __post_init__(self) -> None:
        _validate_detection(self)


@dataclass(frozen=True)
class TrackingConfig:
    """One Kalman filter per tree over m_k = [centroid x y z, num_points, mean NDVI]."""

    # The paper's models: F = H = Q = I5, R = 0.1 I5, a new tree starts with P = I5.
    q: float = 1.0
    r: float = 0.1
    p0: float = 1.0
    # p = exp(-prob_scale * d) with d the Mahalanobis distance of the normalised innovation.
    prob_scale: float = 0.1
    # Associate when p_max > th_p and the entropy (log base M) < th_h.
    th_p: float = 0.5
    th_h: float = 0.8
    # "Normalised to reflect the percentage change": each component of m_k - Hx divided
    # by |Hx| of that component, in percent (x 100), positions in the LiDAR frame as in
    # the paper. In fractions (x 1) a 5 m jump is d ~ 1, p ~ 0.9 for every tree, the
    # entropy is ~1 and no cluster was ever associated on the twin (docs).
    percent: float = 100.0
    # Guards for the division, per component (x, y, z in m; points; NDVI): a tree just
    # beside the LiDAR has x ~ 0, a crown centroid z ~ 0.5 m, NDVI of dry canopy ~ 0.
    floor: tuple[float, float, float, float, float] = (1.0, 1.0, 1.0, 10.0, 0.1)
    # Trees that cannot be seen are left out of the association (not predicted, not in
    # M): a tree counts as in view when it lies inside the crop box grown by this margin
    # (a crown radius and a bit: its near side can be in the box while its centre is not).
    view_margin_m: float = 2.0
    # Two trees whose centres come closer than this are one tree seen twice (the
    # paper's field-map matching collapses them; without a map we merge, keeping the
    # older). 0 turns it off. 1.5 m: half the closest planting distance in citrus (3 m).
    merge_distance_m: float = 1.5
    # Ours, on top of the paper's gate: a cluster may update a tree only if its x-y
    # centroid lies within this distance of the tree's predicted centre. Trees do not
    # move; the paper's relative ("percentage") innovation is loose for far trees and let
    # a neighbour 5 m away pull a tree over on the twin's 23 m drive, after which the
    # merge folded two real trees into one. 0 turns it off (the paper exactly).
    max_association_m: float = 1.5
    # A tree whose centre is farther than this from the robot is finalised (its traits
    # measured, its record written) and dropped from memory, so a scan's cost and the
    # memory stay flat over a survey of any size. A tree seen again after that starts
    # anew (a serpentine's return lane along rows longer than this). 0 keeps every tree.
    # At least the view's reach (the crop box's corner plus view_margin_m) plus 3 m.
    retire_m: float = 50.0
    # A track takes its side in the Voronoi cut (`mapper._Centres`) once seen in this many
    # scans, as the outputs report an object (`output.min_observations`): a post, a person
    # or a wall in view is seen scan after scan, while a stray cluster, or a tree's trunk
    # cut off its crown in one scan and seen alone, is seen once, and its track, never
    # seen again, would take the returns nearer to it from every later cluster there (the
    # twin's irregular orchard: a trunk seen alone once held 0.02 m of its tree's width).
    # 1: every track claims from its first scan.
    claim_min_scans: int = 3

    def __post_init__(self) -> None:
        _validate_tracking(self)


@dataclass(frozen=True)
class TraitsConfig:
    method: str = "paper"  # "paper" (max over scans) or "robust" (accumulated cells)
    slices: int = 10  # the paper's z-slices for the width
    # paper: the width is the largest that at least this many scans reached, not the
    # largest of one. A crown's widest view lasts more than a scan (at 10 Hz and up to
    # 2 m/s the view moves at most 0.2 m from one scan to the next), while a neighbour's
    # crown joined for one scan (touching crowns, a trunk hidden for a moment) or a
    # passer-by is a one-scan event: on the twin's hedgerow every width over 4 m (4.6 to
    # 5.1 m against a true 3.1-3.4) came from one scan, the next largest within 0.3 m of
    # the truth. 1 is the paper's plain maximum.
    width_confirm_scans: int = 2
    # robust: each tree's returns in the world frame on a grid of this cell size, with
    # the number of scans that hit each cell. 0.1 m: a leaf cluster; fine enough that the
    # crown outline moves by < 1 % of a 2.7 m width, coarse enough that one surface patch
    # is hit again from scan to scan (0.05 m measured slightly worse, docs).
    voxel_m: float = 0.1
    # A cell counts when at least this many scans hit it: stray returns (mixed pixels
    # at crown edges, dust, a leaf blown out) are hit once; 3 kept 2 % stray returns out
    # of the widths on the twin where 2 let one tree grow 11 % (docs).
    min_hits: int = 3
    # Cells per tree before the grid coarsens (x 2): a 2.7 m crown fills ~3000 at 0.1 m,
    # so only a tree mapped for a very long time or a hedge hits it; ~0.5 MB a tree.
    max_points: int = 20000
    # The width is the largest horizontal extent over this many bearings (5 deg: the
    # largest extent is missed by at most 1 - cos 2.5 deg = 0.1 %).
    directions: int = 36
    # robust: a scan taken while the robot turns faster than this (rad/s) adds nothing to
    # the accumulated cells. Turning at the paper's 1 rad/s the sensor sweeps 5.7 deg in
    # one 0.1 s scan (a crown edge 5 m away moves 0.5 m while the scan is taken) and a
    # skid steer's odometry heading is at its worst: on the twin's N path such scans
    # smeared the crowns to 4.5-6.4 m against a true 2.8 m.
    max_yaw_rate: float = 0.2
    # Where a tree stands is its trunk (a field map's point is the planting spot). When
    # a trunk was seen under the crown in at least this many scans, a majority of its
    # sightings agreeing within `trunk_agree_m` (`mapper.trunk_position`), the tree's
    # position is their mean; else the crown outline's centre, which a lobed or
    # one-sided crown puts decimetres off the trunk. 3: a weed clump or a neighbour's
    # trunk taken for it in a scan or two does not move a tree. 0: never.
    trunk_min_scans: int = 3
    # Sightings of one trunk agree within this: its axis is found within a few cm
    # (the LiDAR's range noise; the radius correction of `detection.BandBlob.axis`),
    # plus the pose's error between the scans (RTK: cm; float: decimetres over minutes).
    # 0.25 m: a trunk's own width, well under a tree spacing.
    trunk_agree_m: float = 0.25
    # The agreeing sightings are at least this share of the scans that observed the tree.
    # A trunk under a crown in view is in the trunk band's reach in most of them (the
    # rings below the horizon cross 0.08-0.32 m from 0.3 m out to 18 m): on the twin's
    # cluttered grove, where weed clumps hide it in most scans, the trunks were still
    # sighted in 8-15 % of their trees' scans, while a clump glimpsed between others now
    # and then took 2 % (tuning seeds 0 and 5 of field-clutter-n).
    trunk_min_share: float = 0.05
    # A trunk stands under its crown: its place must lie within this share of the
    # crown's width from the outline's centre (0.5: the crown's edge).
    trunk_reach_share: float = 0.5
    # A height is called measured (`height_top_seen`) when the crown's top is bracketed
    # within this share of it: below the second lowest of the rays that passed over it
    # (the beam above its highest ring, in each scan that had its top in view, where the
    # tree stands and where its highest return is) and above the height measured, that
    # gap and the foot's (above the lowest ground seen under it) together. 2 deg
    # between a VLP-16's beams is 0.35 m at 10 m, so one scan brackets no 3 m crown to
    # 5 %; an approach or a drive away, scan after scan, lowers the rays onto the top.
    # The share a grower asks of a height.
    top_tolerance: float = 0.05

    def __post_init__(self) -> None:
        _validate_traits(self)


@dataclass(frozen=True)
class MapperConfig:
    detection: DetectionConfig = field(default_factory=DetectionConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    traits: TraitsConfig = field(default_factory=TraitsConfig)

    def __post_init__(self) -> None:
        reach = retire_reach_m(self)
        _need(
            self.tracking.retire_m == 0 or self.tracking.retire_m >= reach,
            f"tracking.retire_m must be 0 or at least {reach:.1f} m with this crop box and "
            f"view margin (a tree finalised must be out of view for good)",
        )


def retire_reach_m(config: MapperConfig) -> float:
    """The least `tracking.retire_m`: the farthest a tree in view can be from the robot
    (the crop box's far corner grown by the view margin) plus 3 m (a crown's reach into
    the neighbours' Voronoi cut)."""
    crop, margin = config.detection.crop, config.tracking.view_margin_m
    x = max(abs(v) for v in crop.x_m) + margin
    y = max(abs(v) for v in crop.y_m) + margin
    return math.hypot(x, y) + 3.0


def _need(ok: bool, what: str) -> None:
    if not ok:
        raise ConfigError(what)


def _validate_detection(d: DetectionConfig) -> None:
    c, g, k, e = d.crop, d.ground, d.cluster, d.terrain
    for name, (lo, hi) in (("x_m", c.x_m), ("y_m", c.y_m), ("z_m", c.z_m)):
        _need(lo < hi, f"detection.crop.{name} must be [low, high] with low < high, got {(lo, hi)}")
    _need(c.min_range_m >= 0, "detection.crop.min_range_m must be >= 0")
    _need(g.distance_m > 0 and g.iterations > 0, "detection.ground: distance_m, iterations > 0")
    _need(g.max_points >= 3, "detection.ground.max_points must be >= 3")
    _need(0 < g.max_tilt_deg < 90, "detection.ground.max_tilt_deg must be in (0, 90)")
    _need(g.method in GROUND_METHODS, f"detection.ground.method must be one of {GROUND_METHODS}")
    _need(g.clearance_m > 0, "detection.ground.clearance_m must be > 0")
    _need(g.model in GROUND_MODELS, f"detection.ground.model must be one of {GROUND_MODELS}")
    _need(e.cell_m > 0 and e.step_tolerance_m > 0, "detection.terrain: cell_m, step > 0")
    _need(0 < e.max_slope < 2, "detection.terrain.max_slope must be in (0, 2)")
    _need(e.max_gap_m >= e.cell_m, "detection.terrain.max_gap_m must be >= cell_m")
    _need(e.min_support_cells >= 0, "detection.terrain.min_support_cells must be >= 0")
    _need(e.support_radius_m > 0, "detection.terrain.support_radius_m must be > 0")
    _need(e.seed_radius_m > 0, "detection.terrain.seed_radius_m must be > 0")
    _need(e.lowest_layer_m >= 0, "detection.terrain.lowest_layer_m must be >= 0")
    _need(e.fill_sigma_m > 0, "detection.terrain.fill_sigma_m must be > 0")
    f = d.classify
    _need(0 <= f.min_height_m < f.max_height_m, "detection.classify: 0 <= min < max height")
    _need(f.max_base_m > 0, "detection.classify.max_base_m must be > 0")
    _need(0 <= f.min_width_m < f.max_width_m, "detection.classify: 0 <= min < max width")
    _need(f.min_aspect >= 0, "detection.classify.min_aspect must be >= 0")
    _need(f.min_roughness_m >= 0, "detection.classify.min_roughness_m must be >= 0")
    _need(-1 <= f.min_ndvi <= 1, "detection.classify.min_ndvi must be in [-1, 1]")
    for name in ("texture_step_m", "texture_pivot_m", "planar_patch_m", "planar_noise_m"):
        _need(getattr(f, name) > 0, f"detection.classify.{name} must be > 0")
    for name in ("planar_scale", "ndvi_scale", "intensity_scale"):
        _need(getattr(f, name) > 0, f"detection.classify.{name} must be > 0")
    for name in ("texture_weight", "planar_weight", "ndvi_weight", "intensity_weight"):
        _need(getattr(f, name) >= 0, f"detection.classify.{name} must be >= 0")
    _need(
        0 <= f.dark_intensity < f.clear_intensity,
        "detection.classify: 0 <= dark_intensity < clear_intensity",
    )
    _need(0 < f.min_tree_share <= 1, "detection.classify.min_tree_share must be in (0, 1]")
    _need(0 <= f.min_tree_share_all <= 1, "detection.classify.min_tree_share_all: [0, 1]")
    _need(k.voxel_m > 0 and k.tolerance_m > 0, "detection.cluster: voxel_m, tolerance_m > 0")
    _need(1 <= k.min_points <= k.max_points, "detection.cluster: 1 <= min_points <= max_points")
    _need(k.trunk_band_m[0] < k.trunk_band_m[1], "detection.cluster.trunk_band_m: low < high")
    _need(k.max_trunk_width_m > 0, "detection.cluster.max_trunk_width_m must be > 0")
    _need(k.min_trunk_points >= 1, "detection.cluster.min_trunk_points must be >= 1")
    _need(k.min_tree_spacing_m > 0, "detection.cluster.min_tree_spacing_m must be > 0")
    _need(k.bridge_min_height_m >= 0, "detection.cluster.bridge_min_height_m must be >= 0")
    _need(k.stem_radius_m > 0, "detection.cluster.stem_radius_m must be > 0")
    _need(0 < k.top_window_deg <= 10, "detection.cluster.top_window_deg must be in (0, 10]")
    _need(k.min_stem_height_m >= 0, "detection.cluster.min_stem_height_m must be >= 0")
    _need(k.stem_judged_from_m >= 0, "detection.cluster.stem_judged_from_m must be >= 0")
    _need(
        k.stem_clearance_m > k.stem_radius_m,
        "detection.cluster.stem_clearance_m must be > stem_radius_m",
    )
    _need(
        k.max_stem_surround_share >= 0,
        "detection.cluster.max_stem_surround_share must be >= 0",
    )
    _need(
        k.method in CLUSTERING_METHODS,
        f"detection.cluster.method must be one of {CLUSTERING_METHODS}",
    )


def _validate_tracking(t: TrackingConfig) -> None:
    _need(t.q >= 0 and t.r > 0 and t.p0 > 0, "tracking: need q >= 0, r > 0, p0 > 0")
    _need(0 <= t.th_p <= 1 and 0 <= t.th_h <= 1, "tracking.th_p and th_h must be in [0, 1]")
    _need(len(t.floor) == 5 and min(t.floor) > 0, "tracking.floor: five positive numbers")
    _need(t.percent > 0 and t.prob_scale > 0, "tracking.percent and prob_scale must be > 0")
    _need(math.isfinite(t.view_margin_m), "tracking.view_margin_m must be finite")
    _need(t.merge_distance_m >= 0, "tracking.merge_distance_m must be >= 0 (0: off)")
    _need(t.max_association_m >= 0, "tracking.max_association_m must be >= 0 (0: off)")
    _need(t.retire_m >= 0, "tracking.retire_m must be >= 0 (0: keep every tree)")
    _need(t.claim_min_scans >= 1, "tracking.claim_min_scans must be >= 1")


def _validate_traits(r: TraitsConfig) -> None:
    _need(r.method in TRAIT_METHODS, f"traits.method must be one of {TRAIT_METHODS}")
    _need(r.slices >= 1 and r.directions >= 2, "traits: slices >= 1, directions >= 2")
    _need(r.width_confirm_scans >= 1, "traits.width_confirm_scans must be >= 1")
    _need(r.min_hits >= 1, "traits.min_hits must be >= 1")
    _need(r.voxel_m > 0 and r.max_points > 0, "traits.voxel_m and max_points must be > 0")
    _need(r.max_yaw_rate > 0, "traits.max_yaw_rate must be > 0")
    _need(r.trunk_min_scans >= 0, "traits.trunk_min_scans must be >= 0 (0: never)")
    _need(r.trunk_agree_m > 0, "traits.trunk_agree_m must be > 0")
    _need(r.trunk_reach_share > 0, "traits.trunk_reach_share must be > 0")
    _need(0 <= r.trunk_min_share <= 1, "traits.trunk_min_share must be within 0..1")
    _need(r.top_tolerance >= 0, "traits.top_tolerance must be >= 0")
