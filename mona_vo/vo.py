"""Monocular visual odometry, LEAP-VO style, on a CPU: multi-frame point tracks, keyframes and a
sliding-window bundle adjustment (:mod:`ba.sliding_window_ba`), then optionally one global
bundle adjustment over every keyframe (:mod:`ba.global_ba`, ``vo.refine``).

Usage: ``vo = VisualOdometry(config, width, height, intrinsics)``, then ``vo.step(image, ...)``
per frame, then ``vo.finish()`` -> :class:`VOResult` with a pose for every frame.

State: one :class:`mona_vo.vo_map.VOMap` of arrays (landmarks by track id with flags, a keyframe
table that keeps every keyframe's observations for the whole run, a frame table whose statuses
are written once, the window, an Enum state). The steps are pure functions in
:mod:`mona_vo.vo_steps`.

Per frame: track all points (the given :class:`mona_vo.tracking.Tracker`, LK by default); tracks continue through moving-object masks
(as LEAP-VO's long-term tracks do) but a landmark seen inside a mask is flagged and never used
for a pose; the pose comes from PnP on the unmasked tracks with landmarks, predicted by a
constant-velocity model; two tests on the residuals flag points the masks missed: a Cauchy test
of one frame's residual (a gross jump, twice in a row) and a sequential test of residuals above
the frame's noise summed over frames (a track that drifts off its static point by a fraction of
a pixel per frame: a slow mover, one keeping pace, a corner sliding along an outline). On a
keyframe: drop the tracks whose patch no longer looks as at the last keyframe (corners on depth
edges, which slide between two surfaces), triangulate new landmarks, top the grid up with new
tracks, and solve the window's bundle adjustment, which leaves out observations inside a mask and
landmarks seen inside one. Without known intrinsics the global refinement frees the focal length.

Before the map exists, frames wait (their status is written once the map exists or the clip
ends): the first keyframe of the attempt is kept as long as enough tracks survive, so parallax
accumulates over the longest baseline the tracks allow, and every frame that waited is posed by
PnP on the new map once it exists. Rotation-only poses are a measured conclusion:
``VOResult.parallax`` gives the rotation-free parallax found and the noise floor it was compared
with. Lost tracking re-initialises a new map chained to the last pose; the frames until it
exists keep the camera's usual body velocity (extrapolated). Every frame gets a pose and a
status.
"""
from __future__ import annotations

import dataclasses
import time
from collections import defaultdict
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ba.sliding_window_ba import BAConfig, BAProblem, sliding_window_ba
from mona_vo.config import check_fields, setting
from mona_vo.conventions import Intrinsics, invert_pose, make_pose, pixels_in_mask, reproject
from mona_vo.errors import ConfigError
from mona_vo.geometry import homography_jacobians, reprojection_residuals
from mona_vo.patch_align import Anchors, align_patches
from mona_vo.point_selection import seed_points
from mona_vo.rolling_shutter import (best_readout, best_residual, corrected_pixels,
                                     turn_rates, velocities)
from mona_vo.tracking import LKTracker, Tracker, to_gray
from mona_vo.two_view import (homography_parallax_px, judge_pose, relative_pose, rotation_only,
                              rotation_parallax_deg, shared_inliers, tighten_relative_pose,
                              translation_angle_deg, translation_spread_deg, triangulate)
from mona_vo.vo_map import LOW_CONFIDENCE as _LOW, FrameStatus, LandmarkFlag, VOMap, VOState
from mona_vo.vo_steps import (Observation, ParallaxEvidence, PoseSettings, dissimilar_tracks,
                              drift_test, dynamic_test, estimate_pose, find_by_projection,
                              interpolate_pose, keyframe_needed, keyframe_shift_pct, pair_matches,
                              predict_pose, refine_pose, rotation_free_parallax_px, segment_spans,
                              triangulate_against, triangulation_angle_deg, typical_speed,
                              typical_velocity, walk_back)


def turn_homography(intr_b: Intrinsics, R_b_a: np.ndarray, intr_a: Intrinsics) -> np.ndarray:
    """(3, 3) ``K_b R_b_a K_a^-1``: where camera a's pixels at infinity are seen by camera b,
    turned by R_b_a (a's axes -> b's) since; the warp of a patch by the camera's turn alone."""
    return intr_b.K @ R_b_a @ np.linalg.inv(intr_a.K)


# Per-frame status strings (FrameStatus values), from most to least trustworthy.
KEYFRAME, TRACKED, BOOTSTRAP, ROTATION_ONLY, INTERPOLATED, EXTRAPOLATED = (
    s.value for s in FrameStatus)
LOW_CONFIDENCE = tuple(s.value for s in FrameStatus if s in _LOW)
_OUT = np.uint8(LandmarkFlag.DYNAMIC | LandmarkFlag.REJECTED)   # never handed to a BA
ROLLING_SHUTTER_MIN_GAIN = 0.01  # a readout is kept when it lowers the global refinement's
                                 # capped squared error by at least this share (Bonn crowd: 0.13;
                                 # the generator's global shutter: every readout raises it)
RESIDUAL_STEP = 0.1       # the readout left over on unrolled frames is searched in steps of
RESIDUAL_MAX = 0.3        # this share of the frame interval, up to this far either way: the
                          # first estimate falls short by 0.1-0.25 on the generator's rolled
                          # frames (README, Rolling shutter, stop 58), and 0.5, the first
                          # estimate's own step, fits worse than 0 there
REACQUIRE_HALF_PX = 10   # half side of the patch a lost landmark is looked for with: the
                         # tracker's 21 x 21 window
_CHI2_5DOF_99 = 15.086   # scipy.stats.chi2.ppf(0.99, 5): the start pair's test (_densify_pair)


@dataclass(frozen=True)
class VOConfig:
    # The point tracker (its back end, device and checkpoint) is PipelineConfig's `tracker`,
    # shared with the masks; the VO is handed a Tracker instance.
    grid_size: int = setting(16, ge=2)      # k: new points on a k x k grid, one per cell
    init_grid_size: int = setting(0, ge=2, zero=True)  # ... and this k while no map exists
                                            # (the start, and again after tracking is lost);
                                            # 0: grid_size. The start needs a median parallax,
                                            # which many far points hold down (--preset
                                            # accurate: 16, map 24)
    point_score: str = setting("min_eigen", choices=("min_eigen", "gradient"))
                                            # min_eigen (Shi-Tomasi) | gradient (LEAP-VO)
    point_quality: float = setting(0.1, ge=0, le=1)  # in a weakly textured frame a new point
                                            # needs this share of the frame's 99th-percentile
                                            # texture score (Shi-Tomasi's relative rule) ...
    point_min_score: float = setting(3e-5, ge=0)  # ... and at least this min-eigen score (what
                                            # grey-level noise of sigma 2 scores by itself)
    mask_dilate_px: int = setting(5, ge=0)  # no new points this close to a moving-object mask, px
    init_min_parallax_deg: float = setting(0.5, ge=0, le=45)  # median ray angle needed to
                                            # initialise the map, degrees
    init_min_inliers: int = setting(40, ge=5)  # essential-matrix inliers needed to initialise
    init_min_rotation_free_px: float = setting(2.0, gt=0)  # and the median parallax left after
                                            # the best homography rotation, px (a pan leaves tracking
                                            # noise: up to ~1 px with blur and noise; measured in
                                            # pixels, it does not depend on the focal length)
    init_max_translation_spread_deg: float = setting(180.0, gt=0, le=180)  # and random halves
                                            # of the pair's points must agree on the direction
                                            # of its translation within this, degrees
                                            # (two_view.translation_spread_deg; 180: no check).
                                            # Off: 45 lowered the tuning fast turns (mean 3.8
                                            # -> 2.4 % of path, true masks) but raised the
                                            # validation 'mixed' seeds (0.60 -> 1.11 %)
    init_dense_points: int = setting(0, ge=0)  # the start pair's pose is fitted again on
                                            # up to this many corners of its first frame
                                            # matched into the second (vo_steps.pair_matches)
                                            # and kept when it explains them better (0: off,
                                            # the default: on the central-claim scene it helps
                                            # the run without masks more than those with them,
                                            # which then fall 18 % behind it; README)
    init_dense_fb_px: float = setting(0.5, gt=0)  # those matches must track back within this, px
    init_drop_dissimilar: bool = setting(False)  # the keyframes' patch dissimilarity check
                                            # (patch_dissimilarity) on the start pair too, once
                                            # it would start a map. Off: generated wrong-way
                                            # starts are mended (stop 51, true masks: 3 -> 1 of
                                            # 16 tuning, 3 -> 1 of 20 held out), but on every
                                            # start Bonn's draws lose (MONA 2.88 -> 3.68 cm), and
                                            # gated (below), the one-large scene's runs without
                                            # masks go the wrong way on 2 of 5 draws (0.16 ->
                                            # 18.7 % of path): a car on 28 % of the view tips
                                            # the refit; README
    init_dissimilar_min_turn_deg: float = setting(30.0, ge=0, le=180)  # with the check on, its
                                            # refit is taken only when it turns the start's
                                            # translation by at least this, degrees (0: always,
                                            # stop 23's option; Bonn's refits moved its start
                                            # 0.6-12 deg, the generated wrong-way starts 79-126)
    init_dissimilar_min_shared: float = setting(0.0, ge=0, le=1)  # and only when at least this
                                            # share of the refit's inliers were inliers of the
                                            # start it replaces (two_view.shared_inliers; 0:
                                            # the turn alone decides, stop 51's gate)
    init_fit_scales: int = setting(3, ge=1, le=6)  # the start pair's pose is fitted at this
                                            # many inlier thresholds (1 px, halved each time)
                                            # and the one that explains its tracks best at
                                            # three times their noise starts the map
                                            # (two_view.tighten_relative_pose; 1: one fit, the
                                            # default before stop 55). 3 mends generated
                                            # wrong-way starts, tuning and held out alike
                                            # (README, stops 54 and 55)
    init_keyframes: int = setting(4, ge=2)  # keyframes of the first window (two-view pair included)
    keyframe_parallax_px: float = setting(12.0, gt=0)  # median rotation-free track motion since
                                            # the last keyframe, px
    keyframe_min_tracked: float = setting(0.6, ge=0, le=1)  # keyframe when this share of its
                                            # landmarks remains
    keyframe_max_gap: int = setting(6, ge=1)  # at most this many frames between keyframes
    keyframe_min_landmarks: int = setting(60, ge=0)  # keyframe when fewer landmarks than this
                                            # are tracked
    keyframe_falling: float = setting(0.9, ge=0, le=1)  # ... and fewer than this share of the
                                            # last keyframe's
    window_keyframes: int = setting(8, ge=2)  # keyframes in the bundle-adjustment window
    fixed_keyframes: int = setting(2, ge=1)  # oldest window keyframes held fixed (gauge, scale)
    gauge: str = setting("fixed", choices=("fixed", "distance"))  # fixed: hold fixed_keyframes;
                                            # distance: hold the oldest keyframe and only its
                                            # distance to the next one
    reinit_speed_keyframes: int = setting(20, ge=1)  # a map started after tracking was lost
                                            # continues the median speed of the last map's last
                                            # this many keyframe steps; frames before the first
                                            # map walk back along its first this many
    pnp_threshold_px: float = setting(2.0, gt=0)  # RANSAC inlier threshold for per-frame poses, px
    pnp_min_inliers: int = setting(12, ge=4)  # fewer PnP inliers means tracking is lost
    pnp_guided_px: float = setting(6.0, ge=0)  # points this close to the constant-velocity
                                            # prediction seed the pose before RANSAC is tried, px
    pnp_guided_min_share: float = setting(0.3, ge=0, le=1)  # ... if they are at least this share
                                            # of the landmarks
    pnp_guided_support: float = setting(0.8, gt=0, le=1)  # and keep that pose unless RANSAC's
                                            # has 1/0.8 x the inliers
    triangulation_min_angle_deg: float = setting(0.3, ge=0, lt=90)  # rays closer than this give
                                            # no landmark, degrees
    triangulation_max_error_px: float = setting(2.0, gt=0)  # nor do rays that miss each other
                                            # by more, px
    triangulation_starved_angle_deg: float = setting(0.1, ge=0, lt=90)  # ... but this, when
                                            # fewer landmarks than half the grid's cells are
                                            # in view (vo_steps.triangulation_angle_deg); 0: off
    dynamic_scale_px: float = setting(1.44, gt=0)  # Cauchy scale of a static point's residual,
                                            # px (geometry's 2-D formula: 1.44 puts p = 0.9 at
                                            # 3 px along a diagonal, 4.3 px along an axis)
    dynamic_prob_max: float = setting(0.9, gt=0, le=1)  # tracks above this dynamic probability
                                            # twice are dropped
    drift_bound: float = setting(12.0, ge=0)  # drift test (vo_steps.drift_test): a track whose
                                            # summed log-likelihood ratio of residuals above the
                                            # frame's noise reaches this is dropped (0: off)
    drift_breakeven: float = setting(3.0, gt=0)  # a residual of this many times the frame's
                                            # noise neither adds nor removes drift evidence
    drift_noise_floor_px: float = setting(0.3, gt=0)  # the frame's noise is at least this, px
    refine_focal: bool = setting(False)     # refine one shared focal length while the first window
                                            # fills (needs rotation; see README's measurements)
    patch_dissimilarity: float = setting(5.0, ge=0)  # at a keyframe, a track whose patch no
                                            # longer looks as at the last keyframe (1 - NCC above
                                            # this x the keyframe's median, and above 0.02) is
                                            # dropped with its landmark (0: off)
    patch_half_px: int = setting(4, ge=1)   # half size of that patch, px
    anchor_tracks: bool = setting(False)    # at each keyframe, fit every track's patch as first
                                            # anchored (affine, mona_vo.patch_align) and move
                                            # the track there, so frame-to-frame drift does
                                            # not add up. Off: on stop 40's VO Bonn gains in
                                            # both halves (stop 41), but the masks then no
                                            # longer lower the ATE of the central claim's
                                            # test scene; creeps lose; README
    anchor_min_ncc: float = setting(0.8, ge=-1, le=1)  # ... when the fitted patch correlates
                                            # with its first look at least this much
    anchor_max_shift_px: float = setting(2.0, gt=0)  # ... and moves the track by at most this, px
    anchor_half_px: int = setting(10, ge=1)  # half size of that patch, px (10: the tracker's
                                            # 21 x 21 window; at 7, noisy frames fitted worse
                                            # than six frame-to-frame steps)
    reacquire_keyframes: int = setting(20, ge=0)  # at a keyframe, landmarks whose tracks were
                                            # lost and that one of the last this many keyframes
                                            # saw are looked for where the pose puts them and
                                            # tracked again when found (a passer-by hid them;
                                            # search by projection). 0: off. With
                                            # ba_outside_keyframes, Bonn crowd's held-out half
                                            # 5.62 -> 3.50 cm (MONA, nine draws); README
    reacquire_px: float = setting(2.0, gt=0)  # ... found within this of that place, px
    reacquire_min_ncc: float = setting(0.8, ge=-1, le=1)  # ... looking as they did there
                                            # (normalised cross-correlation of the patch)
    ba_outside_keyframes: int = setting(8, ge=0)  # the window's bundle adjustment also holds
                                            # the observations of its landmarks by up to this
                                            # many keyframes before the window, those keyframes
                                            # fixed (as ORB-SLAM's local BA: a landmark keeps the
                                            # views that fixed its depth). 0: off
    refine: str = setting("global", choices=("global", "none"))  # after the sliding window, one
                                            # bundle adjustment over all keyframes (global) or
                                            # none (streaming)
    global_camera: str = setting("focal", choices=("none", "focal", "focal+centre"))
                                            # without intrinsics, the global refinement also
                                            # refines one shared focal length (and principal
                                            # point)
    rolling_shutter: str = setting("estimate", choices=("off", "estimate", "given", "residual"))
                                            # the global refinement sees each observation as
                                            # the camera of its frame's middle row would have
                                            # (mona_vo.rolling_shutter), with the readout it
                                            # finds lowest in reprojection error (estimate, 0
                                            # for a global shutter) or rolling_shutter_readout
                                            # (given); the pipeline then runs the VO again on
                                            # the frames unrolled, where the readout left over,
                                            # signed and small, is estimated (residual; README,
                                            # rolling shutter)
    rolling_shutter_readout: float = setting(0.0, ge=0, le=1)  # the share of the frame
                                            # interval the rows' readout takes, top row first
                                            # (with rolling_shutter=given; with residual, the
                                            # readout the frames were unrolled at already: what
                                            # is left keeps the sum within [0, 1])
    rolling_shutter_model: str = setting("rotation", choices=("rotation", "rotation+translation"))
                                            # what moves the camera within the readout for
                                            # the global refinement: its turn only, or its
                                            # turn and its centre's motion too (each point
                                            # moved at its depth in the refinement's start;
                                            # the frames are unrolled by the turn alone)
    ba: BAConfig = field(default_factory=BAConfig)  # bundle adjustment (window and global)

    @property
    def start_grid(self) -> int:
        """k of the k x k grid new points are seeded on while no map exists."""
        return self.init_grid_size or self.grid_size

    def validate(self) -> None:
        check_fields(self, "vo.")
        if self.window_keyframes <= self.fixed_keyframes:
            raise ConfigError(f"config keys 'vo.window_keyframes' ({self.window_keyframes}) and "
                              f"'vo.fixed_keyframes' ({self.fixed_keyframes}): the window must "
                              f"hold more keyframes than it fixes")
        self.ba.validate()


@dataclass
class VOResult:
    """Output of :meth:`VisualOdometry.finish`.

    timestamps:  (N,) float64, as given to step().
    poses:       (N, 4, 4) float64 T_world_cam, one per input frame (world = first keyframe).
    is_keyframe: (N,) bool.
    status:      list of N strings (keyframe, tracked, bootstrap, rotation-only, interpolated,
                 extrapolated); the last three are low-confidence.
    inliers:     (N,) int, points that supported each frame's pose.
    timings:     stage -> seconds (tracking, pose, mapping, ba, global_ba).
    drops:       counters of what the masks and the dynamic test removed.
    focal:       the focal length used at the end (px).
    map_points:  (M, 3) float64 landmarks of the last window (for a PLY export).
    parallax:    the translation evidence (:meth:`mona_vo.vo_steps.ParallaxEvidence.as_dict`).
    reprojection_rmse_px: RMSE of the last bundle adjustment (the global one with
                 vo.refine=global), px; NaN when none ran.
    refine:      what the global refinement did ({} when it did not run).
    found_again: landmarks tracked again where a keyframe's pose put them after their tracks
                 had been lost (VisualOdometry._reacquire).
    map_segments: (first frame, last frame) of each map: a new one starts where tracking was
                 lost (a blank stretch, a cut between shots). Each has its own scale, and the
                 pose from one to the next is not measured (the walk is carried on), so a
                 clip with more than one is one trajectory only up to those joins.
    poses_streaming: (N, 4, 4) the poses before the global refinement: the trajectory
                 vo.refine=none gives on the same frames, to the bit (equal to ``poses`` when
                 no refinement ran), so one run measures both VOs.
    """

    timestamps: np.ndarray
    poses: np.ndarray
    is_keyframe: np.ndarray
    status: list[str]
    inliers: np.ndarray
    timings: dict[str, float]
    drops: dict[str, int]
    focal: float
    map_points: np.ndarray
    parallax: dict = field(default_factory=dict)
    reprojection_rmse_px: float = float("nan")
    refine: dict = field(default_factory=dict)
    map_segments: list = field(default_factory=list)
    found_again: int = 0
    poses_streaming: np.ndarray | None = None

    @property
    def map_built(self) -> bool:
        """Whether the run built a map at all (else every pose is its rotation alone)."""
        return bool(self.map_segments)

    @property
    def low_confidence(self) -> np.ndarray:
        return np.array([s in LOW_CONFIDENCE for s in self.status], bool)

    def pose_support(self) -> dict:
        """How many map points held the poses up, over the frames posed on the map: the 10th
        percentile and the median of their PnP inliers (None without such frames). A clip
        whose tenth percentile is low crossed a stretch where the pose rested on a few points
        (a fast turn, a blank wall), where a wrong pose is seldom caught."""
        n = np.asarray(self.inliers, np.float64)[~self.low_confidence]
        if not len(n):
            return {"frames": 0, "inliers_p10": None, "inliers_median": None}
        return {"frames": int(len(n)), "inliers_p10": float(np.percentile(n, 10)),
                "inliers_median": float(np.median(n))}


@dataclass
class _Waiting:
    """A frame waiting for the map: its tracks and its provisional rotation-only pose."""

    frame: int
    obs: Observation
    intr: Intrinsics
    T_world_cam: np.ndarray


@dataclass
class _Attempt:
    """An initialisation attempt: its first keyframe (the ``waiting[0]`` frame) and the frames
    that wait for its map."""

    first: _Waiting
    waiting: list[_Waiting]
    gray: np.ndarray   # the first keyframe's image (the start pair's checks)
    mask: np.ndarray | None  # and its moving-object mask


@dataclass
class _Probe:
    """The translation evidence's reference frame (its static tracks), the previous frame's,
    and the running noise floor (sum of squared frame-to-frame residuals) since the reference."""

    frame: int
    ref: Observation
    prev: Observation
    floor_sq: float = 0.0


TRANSLATION_RATIO = 3.0   # parallax / noise floor that proves translation (vo_steps.ParallaxEvidence)


class VisualOdometry:
    def __init__(self, config: VOConfig, width: int, height: int,
                 intrinsics: Intrinsics | None = None, *, tracker: Tracker | None = None,
                 camera_known: bool | None = None, occluded: np.ndarray | None = None):
        """``intrinsics``: the camera (None: the default field-of-view guess). ``camera_known``
        (default: whether ``intrinsics`` was given) says whether they are the true camera; when
        not, and no frame brings its own, the global refinement may refine them
        (``global_camera``). ``occluded``: (H, W) bool pixels that are no part of the scene in
        any frame (a burned-in overlay painted over): a track that reaches them ends there, as
        at the frame's border, and none starts there."""
        config.validate()
        self.cfg = config
        self.width, self.height = int(width), int(height)
        self.default_intr = intrinsics or Intrinsics.default_for(width, height)
        self.tracker = tracker if tracker is not None else LKTracker()
        # An overlay is not a mover: a track under it is not flagged (a mask's landmark is left
        # out for good), it ends. Flagged, the floor points a forward walk carries through a
        # watermark in a corner were lost to the map (Bonn crowd, README Results).
        self._occluded = None if occluded is None or not np.any(occluded) else np.asarray(occluded, bool)
        self.map = VOMap()
        self.timings = defaultdict(float)
        self.drops = defaultdict(int)
        self.found_again = 0        # landmarks tracked again after their tracks were lost
        self.evidence = ParallaxEvidence()
        self._attempt: _Attempt | None = None
        self._probe: _Probe | None = None
        self._focal_fixed: float | None = None
        self._camera_known = intrinsics is not None if camera_known is None else bool(camera_known)
        # Tracks are held to their first look only by a tracker that takes corrections.
        takes = config.anchor_tracks and self.tracker.takes_corrections
        self._anchors = Anchors(config.anchor_half_px) if takes else None
        self._kf_grays: dict[int, np.ndarray] = {}   # keyframe row -> grey image, the last
                                    # vo.reacquire_keyframes keyframes' (_reacquire)
        self._last_kf_view = None   # (gray, track ids, uv, T_world_cam, intrinsics) of the
                                    # last keyframe made while tracking (_drop_dissimilar)
        self._speed_hint: float | None = None       # map units/frame before a re-initialisation
        self._velocity_hint: np.ndarray | None = None  # body velocity carried while re-initialising
        self._rmse = float("nan")
        self._pose_settings = PoseSettings(config.pnp_threshold_px, config.pnp_min_inliers,
                                           config.pnp_guided_px, config.pnp_guided_min_share,
                                           config.pnp_guided_support)

    # ----------------------------------------------------------------- public API
    def step(self, image: np.ndarray, *, timestamp: float | None = None,
             mask: np.ndarray | None = None, intrinsics: Intrinsics | None = None) -> None:
        """Process the next frame. image: (H, W, 3) uint8 RGB or (H, W) grey. mask: optional
        (H, W) bool moving-object mask. intrinsics: this frame's (defaults to the constructor's)."""
        t = self.map.frames.n
        self._camera_known |= intrinsics is not None
        intr = intrinsics or self.default_intr
        if self._focal_fixed is not None and intrinsics is None:
            intr = Intrinsics(self._focal_fixed, self._focal_fixed, intr.cx, intr.cy)
        gray = to_gray(image)
        if gray.shape != (self.height, self.width):
            raise ConfigError(f"frame {t} is {gray.shape[1]} x {gray.shape[0]}, expected "
                              f"{self.width} x {self.height}")
        self.map.frames.append(float(t if timestamp is None else timestamp))
        obs = self._track(gray, mask)
        self._measure_parallax(t, obs)
        if self.map.state is VOState.INIT:
            self._step_init(t, gray, obs, intr, mask)
        else:
            self._step_tracking(t, gray, obs, intr, mask)

    def finish(self) -> VOResult:
        if self._attempt is not None:
            # The clip ended before a map: the waiting frames keep their rotation-only poses
            # (with the carried velocity after a loss).
            for w in self._attempt.waiting:
                self._write_absolute(w.frame, self._unmapped_status, len(w.obs.ids), w.T_world_cam)
            self._attempt = None
        fr = self.map.frames
        for t in range(fr.n):
            if not fr.written(t):   # cannot happen; a pose for every frame regardless
                self._write_absolute(t, FrameStatus.ROTATION_ONLY, 0, np.eye(4))
        refine, streaming = {}, None
        if self.cfg.refine == "global" and self.map.keyframes.n >= 2:
            # The sliding window's trajectory as vo.refine=none gives it (to the bit), kept
            # beside the refined one: a benchmark reads both VOs from one run.
            streaming = self._with_start_walked_back(self.map.all_poses())
            refine = self._refine_global()
        for u, T in self._start_walk_back().items():
            fr.backfill(u, T)
        n = fr.n
        poses = self.map.all_poses()
        kf = self.map.keyframes
        iskf = np.zeros(n, bool)
        iskf[[f for k, f in enumerate(kf.frame[:kf.n]) if fr.ref_kf[f] == k]] = True
        status = [fr.status_of(t).value for t in range(n)]
        window_ids = np.unique(np.concatenate(
            [kf.observations(k)[0] for k in self.map.window] or [np.zeros(0, np.int64)]))
        pts = self.map.landmarks.positions(window_ids[self.map.landmarks.usable(window_ids)])
        focal = self._focal_fixed or self.default_intr.fx
        spans = segment_spans(self.map.frame_segments())
        return VOResult(fr.timestamp[:n].copy(), poses, iskf, status, fr.inliers[:n].copy(),
                        dict(self.timings), dict(self.drops), float(focal), pts.reshape(-1, 3),
                        self.evidence.as_dict(TRANSLATION_RATIO, bool(spans)), float(self._rmse),
                        refine, spans, self.found_again,
                        poses.copy() if streaming is None else streaming)

    def _with_start_walked_back(self, poses: np.ndarray) -> np.ndarray:
        for u, T in self._start_walk_back().items():
            poses[u] = T
        return poses

    def _start_walk_back(self) -> dict[int, np.ndarray]:
        """Frames before the first map that kept their rotation alone (the start waited for
        parallax, and their tracks were gone before it came, or they had nothing to track)
        get a translation: the first map's body velocity, walked back from the first frame
        posed on it. Left where the map starts, the whole distance they covered went into the
        error (generated fast turn, mixed 203, opening on a blank wall: nine frames at 0.08 m
        each).
        A camera that only turned builds no map and is not touched; one whose first steps
        point every way (shaking in place) has no velocity to carry (typical_velocity).
        Returns frame -> T_world_cam of the frames to fill in (status extrapolated); reads the
        map, changes nothing."""
        kf, fr = self.map.keyframes, self.map.frames
        rows = np.flatnonzero(kf.segment[:kf.n] == 0)[:self.cfg.reinit_speed_keyframes + 1]
        if len(rows) < 2:
            return {}
        velocity = typical_velocity(kf.frame[rows], kf.T_world_cam[rows], len(rows) - 1)
        if velocity is None:
            return {}
        poses = self.map.all_poses()
        fill = {}
        t = int(kf.frame[rows[0]])
        while t > 0:
            end = t
            while t > 0 and fr.status_of(t - 1) is FrameStatus.ROTATION_ONLY:
                t -= 1
            if t < end:
                fill.update(zip(range(t, end), walk_back(poses[end], poses[t:end, :3, :3], velocity)))
            else:
                t -= 1
        return fill

    # ----------------------------------------------------------------- small helpers
    def _write_absolute(self, t, status: FrameStatus, inliers: int, T_world_cam) -> None:
        self.map.frames.write(t, status, int(inliers), T=T_world_cam)

    def _write_relative(self, t, status: FrameStatus, inliers: int, kf_row: int, T_world_cam) -> None:
        T_kf = self.map.keyframes.T_world_cam[kf_row]
        self.map.frames.write(t, status, int(inliers), ref_kf=kf_row, T=invert_pose(T_kf) @ T_world_cam)

    def _keep_for_repose(self, t: int, obs: Observation) -> None:
        """Frame t's static tracks, for the global refinement to pose it again (_repose_frames);
        nothing is kept when no refinement will run."""
        if self.cfg.refine == "global":
            s = self._static(obs)
            self.map.frames.add_observations(t, s.ids, s.uv)

    def _static(self, obs: Observation) -> Observation:
        """Tracks that may support a pose: outside the mask and never flagged."""
        return obs.subset(~obs.masked & ~self.map.landmarks.flagged(obs.ids))

    def _pnp(self, obs: Observation, intr: Intrinsics, T_guess=None):
        s = self._static(obs)
        have = self.map.landmarks.usable(s.ids)
        return estimate_pose(self.map.landmarks.positions(s.ids[have]), s.uv[have], intr, T_guess,
                             self._pose_settings)

    # ----------------------------------------------------------------- tracking
    def _track(self, gray, mask) -> Observation:
        t0 = time.perf_counter()
        upd = self.tracker.step(gray)
        vis = upd.visible
        ids, uv = upd.ids[vis].astype(np.int64), upd.points[vis].astype(np.float64)
        if self._occluded is not None:
            under = pixels_in_mask(self._occluded, uv)
            if under.any():
                self.tracker.remove(ids[under])
                self.drops["tracks_under_overlay"] += int(under.sum())
                ids, uv = ids[~under], uv[~under]
        masked = pixels_in_mask(mask, uv) if mask is not None else np.zeros(len(ids), bool)
        if masked.any():
            self.drops["tracks_entering_masks"] += self.map.landmarks.flag(ids[masked],
                                                                           LandmarkFlag.MASKED)
        self.timings["tracking"] += time.perf_counter() - t0
        return Observation(ids, uv, masked)

    def _measure_parallax(self, t: int, obs: Observation) -> None:
        """Translation evidence over the whole clip, whatever the map does: the parallax no
        homography explains between a reference frame and this one, against the noise floor of
        the frame-to-frame residuals over the same frames (:class:`ParallaxEvidence`). The
        reference moves on when fewer than half of its tracks remain."""
        t0 = time.perf_counter()
        s = self._static(obs)
        p = self._probe
        if p is None or len(s.ids) < 8:
            self._probe = _Probe(t, s, s) if len(s.ids) >= 8 else None
            return
        _, ia, ib = np.intersect1d(p.prev.ids, s.ids, return_indices=True)
        step_px, _ = homography_parallax_px(p.prev.uv[ia], s.uv[ib])
        if np.isfinite(step_px):
            p.floor_sq += step_px ** 2
        p.prev = s
        _, ia, ib = np.intersect1d(p.ref.ids, s.ids, return_indices=True)
        base_px, _ = homography_parallax_px(p.ref.uv[ia], s.uv[ib])
        self.evidence = self.evidence.updated(base_px, float(np.sqrt(p.floor_sq)), t - p.frame)
        if len(ia) < max(20, 0.5 * len(p.ref.ids)):
            self._probe = _Probe(t, s, s)
        self.timings["parallax"] += time.perf_counter() - t0

    def _new_points(self, gray, obs: Observation, mask) -> tuple[np.ndarray, np.ndarray]:
        exclude = self._occluded
        if mask is not None and mask.any():
            k = 2 * self.cfg.mask_dilate_px + 1
            exclude = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
            exclude = exclude if self._occluded is None else exclude | self._occluded
        k_grid = self.cfg.start_grid if self.map.state is VOState.INIT else self.cfg.grid_size
        pts = seed_points(gray, k_grid, self.cfg.point_score, self.cfg.point_min_score,
                          self.cfg.point_quality, exclude=exclude, occupied=self._static(obs).uv)
        new_ids = self.tracker.add_points(pts) if len(pts) else np.zeros(0, np.int64)
        return np.asarray(new_ids, np.int64), pts.astype(np.float64)

    def _step_tracking(self, t, gray, obs: Observation, intr, mask) -> None:
        t0 = time.perf_counter()
        m = self.map
        T_guess = predict_pose(m.pose_of(t - 2) if t >= 2 else None, m.pose_of(t - 1))
        T, n_inl = self._pnp(obs, intr, T_guess)
        if T is None:
            # Lost: keep a pose (extrapolated), remember the speed, start a new map here.
            self.drops["tracking_lost"] += 1
            kf = m.keyframes
            rows = np.flatnonzero(kf.segment[:kf.n] == m.segment)
            speed = typical_speed(kf.frame[rows], kf.T_world_cam[rows, :3, 3],
                                  self.cfg.reinit_speed_keyframes)
            self._speed_hint = speed or self._speed_hint
            self._velocity_hint = typical_velocity(kf.frame[rows], kf.T_world_cam[rows],
                                                   self.cfg.reinit_speed_keyframes)
            self._write_absolute(t, FrameStatus.EXTRAPOLATED, n_inl, T_guess)
            m.state = VOState.INIT
            self._start_attempt(t, gray, obs, intr, mask, T_guess)
            self.timings["pose"] += time.perf_counter() - t0
            return
        self._flag_dynamic(obs, intr, T)
        self.timings["pose"] += time.perf_counter() - t0
        last = m.window[-1]
        if self._needs_keyframe(t, last, obs, intr, T):
            self._make_keyframe(t, gray, obs, intr, mask, T, n_inl)
        else:
            self._write_relative(t, FrameStatus.TRACKED, n_inl, last, T)
            self._keep_for_repose(t, obs)

    def _flag_dynamic(self, obs: Observation, intr, T) -> None:
        lm = self.map.landmarks
        s = self._static(obs)
        have = lm.usable(s.ids)
        ids = s.ids[have]
        r = reprojection_residuals(T, lm.positions(ids), s.uv[have], intr)
        strikes, dynamic = dynamic_test(r, lm.strikes[ids], self.cfg.dynamic_scale_px,
                                        self.cfg.dynamic_prob_max)
        lm.strikes[ids] = strikes
        # The tracks tested are usable, so none is flagged yet: the counts are the new flags.
        self.drops["tracks_flagged_dynamic"] += int(np.count_nonzero(dynamic))
        if self.cfg.drift_bound > 0:
            lm.drift[ids], drifting = drift_test(r, lm.drift[ids], self.cfg.drift_noise_floor_px,
                                                 self.cfg.drift_breakeven, self.cfg.drift_bound)
            self.drops["tracks_flagged_drifting"] += int(np.count_nonzero(drifting & ~dynamic))
            dynamic = dynamic | drifting
        if dynamic.any():
            lm.flag(ids[dynamic], LandmarkFlag.DYNAMIC)
            self.tracker.remove(ids[dynamic])

    def _needs_keyframe(self, t, last: int, obs: Observation, intr, T) -> bool:
        kf = self.map.keyframes
        lm = self.map.landmarks
        ids_k, uv_k, _ = kf.observations(last)
        s = self._static(obs)
        _, i0, i1 = np.intersect1d(ids_k, s.ids, return_indices=True)
        R = (invert_pose(kf.T_world_cam[last]) @ T)[:3, :3]
        parallax = rotation_free_parallax_px(uv_k[i0], s.uv[i1], kf.intrinsics(last), intr, R)
        return keyframe_needed(
            gap=t - int(kf.frame[last]), max_gap=self.cfg.keyframe_max_gap, parallax_px=parallax,
            parallax_min_px=self.cfg.keyframe_parallax_px,
            lm_last=int(lm.usable(ids_k).sum()), lm_now=int(lm.usable(s.ids[i1]).sum()),
            min_tracked=self.cfg.keyframe_min_tracked, min_landmarks=self.cfg.keyframe_min_landmarks,
            falling=self.cfg.keyframe_falling)

    # ----------------------------------------------------------------- initialisation
    def _start_attempt(self, t, gray, obs: Observation, intr, mask, T_world_cam) -> None:
        """Make frame t the first keyframe of a map to be. Live tracks carry on, so frames that
        waited for an earlier attempt still share points with the map once it exists."""
        new_ids, new_uv = self._new_points(gray, obs, mask)
        full = Observation(np.concatenate([obs.ids, new_ids]), np.concatenate([obs.uv, new_uv]),
                           np.concatenate([obs.masked, np.zeros(len(new_ids), bool)]))
        first = _Waiting(t, full, intr, T_world_cam)
        waiting = [] if self.map.frames.written(t) else [first]
        if self._attempt is not None:
            waiting = [w for w in self._attempt.waiting if w.frame != t] + waiting
        self._attempt = _Attempt(first, waiting, gray, mask)
        self._settle_unreachable()

    @property
    def _unmapped_status(self) -> FrameStatus:
        """What a frame no map could pose is: its rotation alone, or, while a lost map is
        re-made, its rotation and the carried velocity."""
        return FrameStatus.ROTATION_ONLY if self._velocity_hint is None else \
            FrameStatus.EXTRAPOLATED

    def _settle_unreachable(self) -> None:
        """Waiting frames that share too few live tracks can never be posed on a map built
        later (its landmarks are tracks alive then): they keep their rotation-only pose now."""
        live = self.tracker.live().ids
        keep = []
        for w in self._attempt.waiting:
            if w.frame != self._attempt.first.frame and \
                    np.isin(w.obs.ids, live).sum() < self.cfg.pnp_min_inliers:
                self._write_absolute(w.frame, self._unmapped_status, len(w.obs.ids), w.T_world_cam)
            else:
                keep.append(w)
        self._attempt.waiting = keep

    def _step_init(self, t, gray, obs: Observation, intr, mask) -> None:
        t0 = time.perf_counter()
        att = self._attempt
        if att is None:
            self._start_attempt(t, gray, obs, intr, mask, np.eye(4))
            self.timings["pose"] += time.perf_counter() - t0
            return
        k0 = att.first
        s0, s = self._static(k0.obs), self._static(obs)
        common, i0, i1 = np.intersect1d(s0.ids, s.ids, return_indices=True)
        ro = rotation_only(s0.uv[i0], s.uv[i1], k0.intr, intr) if len(common) >= 6 else None
        R = None if ro is None else ro[0]
        rel = self._start_pair(s0.uv[i0], s.uv[i1], k0.intr, intr, R)
        if rel is not None:
            rel = self._densify_pair(rel, att, gray, mask, s0.uv[i0], s.uv[i1], k0.intr, intr)
        if rel is not None and R is not None and self.cfg.init_drop_dissimilar and \
                self.cfg.patch_dissimilarity > 0:
            # The keyframes' dissimilarity check (_drop_dissimilar) on the start pair too, once
            # it would start a map: tracks that slide along a depth edge can fit a wrong
            # essential matrix better than the true one. On a generated forward follow (mixed
            # seed 2) the check drops a tenth of the pair's tracks, most of them on a true
            # depth edge; with them the translation came out 61-76 deg off, without them 2-9
            # deg. Once, not on every waiting frame: repeated, each frame's worst few add up,
            # and a slow pan's start pair lost two thirds of its tracks.
            # Only a refit that travels another way is taken: one that moves the translation
            # a few degrees mends nothing the map's bundle adjustments would not, and the tracks
            # it drops change the map, which a real clip then answers chaotically (Bonn's
            # draws lost at stop 51; their refits moved the start 0.6-12 deg, where the
            # generated wrong-way starts moved 79-126 deg).
            # And, when asked, only a refit that explains the same points another way: at stop
            # 52 the mended wrong-way starts kept 84-100 % of its inliers from the start it
            # replaced, the refits that went the wrong way on a scene whose car was not masked
            # 64-74 % (the car's points had joined the consensus).
            sel = self._dissimilar(att.gray, s0.uv[i0], k0.intr, gray, s.uv[i1], intr, R.T)
            if sel.any():
                kept0, kept = s0.uv[i0][~sel], s.uv[i1][~sel]
                refit = self._refit_pair(rel, kept0, kept, k0.intr, intr)
                if refit is not None and translation_angle_deg(rel.T_a_b, refit.T_a_b) >= \
                        self.cfg.init_dissimilar_min_turn_deg and \
                        (self.cfg.init_dissimilar_min_shared <= 0 or
                         shared_inliers(rel.T_a_b, refit.inliers, kept0, kept, k0.intr, intr) >=
                         self.cfg.init_dissimilar_min_shared):
                    obs = self._reject(obs, common[sel])
                    common, rel = common[~sel], refit
                # else the pair starts as it is: the check may improve a start, never block
                # one (the tracks it would drop held the pair above init_min_inliers)
        if rel is not None and self._initialise(t, gray, obs, intr, mask, rel,
                                                common[rel.inliers]):
            self.timings["pose"] += time.perf_counter() - t0
            return
        # While a lost map is re-made, the camera keeps its usual velocity (a walk does not
        # stop because tracking did); before the first map nothing says it moved.
        step = np.zeros(3) if self._velocity_hint is None else \
            (t - k0.frame) * self._velocity_hint
        T = k0.T_world_cam @ make_pose(R if R is not None else np.eye(3), step)
        att.waiting.append(_Waiting(t, obs, intr, T))
        if len(common) < max(self.cfg.init_min_inliers, 0.3 * len(s0.ids)):
            # The view changed too much for this first keyframe: a new attempt from this frame,
            # its rotation chained to the old one's.
            self._start_attempt(t, gray, obs, intr, mask, T)
        self.timings["pose"] += time.perf_counter() - t0

    def _start_pair(self, uv0, uv, intr0, intr, R):
        """The pair's relative pose (:func:`relative_pose`) when it may start a map (enough
        inliers, parallax, parallax left after the best rotation R, and, when asked, a
        translation whose direction random halves agree on); else None."""
        cfg = self.cfg
        if len(uv0) < max(8, cfg.init_min_inliers):
            return None
        rel = relative_pose(uv0, uv, intr0, intr)
        if rel is None or rel.n_inliers < cfg.init_min_inliers or \
                rel.median_parallax_deg < cfg.init_min_parallax_deg:
            return None
        ua, ub = uv0[rel.inliers], uv[rel.inliers]
        if R is not None:
            # Near a pure rotation the essential matrix is ill-posed and its "parallax" is noise;
            # the parallax left after the best homography rotation tells the truth.
            par_h = rotation_parallax_deg(ua, ub, intr0, intr, R)
            if np.radians(float(np.median(par_h))) * intr.fx < cfg.init_min_rotation_free_px:
                return None
        if cfg.init_max_translation_spread_deg < 180 and \
                translation_spread_deg(ua, ub, intr0, intr) > cfg.init_max_translation_spread_deg:
            return None
        # The gates above judge the 1 px fit, so when a map starts does not change; only which
        # pose starts it (a tighter fit's parallax is often smaller: asked of it, a generated
        # slow pan with MONA masks never started). One fit (init_fit_scales=1) is the 1 px fit.
        tight = tighten_relative_pose(rel, uv0, uv, intr0, intr, scales=cfg.init_fit_scales)
        return tight if tight.n_inliers >= cfg.init_min_inliers else rel

    def _densify_pair(self, rel, att: "_Attempt", gray, mask, uv0, uv, intr0, intr):
        """The start pair's pose fitted again on many more matches of its two frames
        (pair_matches), taken when it explains them better than the pose of the shared tracks
        and the shared tracks do not reject it: their summed squared epipolar distance grows by
        less than the 99 % point of chi-square with 5 degrees of freedom (a relative pose's)
        times their own noise (that sum over their inliers under their own fit). Its inliers
        are then those of the shared tracks under it.

        The first map inherits the pair's rotation: near a pure turn a hundred tracks leave
        rotation and translation free to trade (the bas-relief ambiguity); a slow pan (mixed
        207) started 1.2 deg off from its 92 tracks, 0.06 deg off from 600 matches, and kept
        turning 15 % short for the rest of the clip. The test keeps matches that slid (LK
        across ten frames of a hand-held shake or a forward walk, mixed 208 and 202: the
        shared tracks' sum grew by 68-73 px^2 against a bound of 1-2) from replacing a pair
        that was right."""
        cfg = self.cfg
        lk = self.tracker if isinstance(self.tracker, LKTracker) else None
        ua, ub = pair_matches(att.gray, gray, uv0, uv, att.mask, mask, cfg.init_dense_points,
                              cfg.init_dense_fb_px, lk)
        if len(ua) <= len(uv0):
            return rel
        dense = relative_pose(ua, ub, intr0, intr)
        if dense is None:
            return rel
        _, cost_dense = judge_pose(dense.T_a_b, ua, ub, intr0, intr)
        _, cost_shared = judge_pose(rel.T_a_b, ua, ub, intr0, intr)
        if cost_dense >= cost_shared:
            return rel
        judged, on_shared = judge_pose(dense.T_a_b, uv0, uv, intr0, intr)
        _, own = judge_pose(rel.T_a_b, uv0, uv, intr0, intr)
        noise = own / max(rel.n_inliers, 1)
        if on_shared - own > _CHI2_5DOF_99 * noise or judged.n_inliers < cfg.init_min_inliers:
            return rel
        return judged

    def _refit_pair(self, rel, uv0, uv, intr0, intr):
        """The start pair again, on the tracks left after the dissimilarity check: the pose
        fitted to them or the one fitted before, whichever explains them better (MSAC cost,
        :func:`judge_pose`), if it keeps enough inliers. A new fit alone is a new RANSAC draw:
        on a noisy creep (mixed seed 108) it fell from 171 inliers to 103 and started the map
        100 deg off. The parallax gates are not asked again: the pair met them with all its
        tracks, and the tracks that slid had inflated them (asked again, a generated slow pan,
        mixed seed 207, never started its map)."""
        if len(uv0) < max(8, self.cfg.init_min_inliers):
            return None
        judged = [judge_pose(rel.T_a_b, uv0, uv, intr0, intr)]
        new = relative_pose(uv0, uv, intr0, intr)
        if new is not None:
            judged.append(judge_pose(new.T_a_b, uv0, uv, intr0, intr))
        best = min(judged, key=lambda j: j[1])[0]
        return best if best.n_inliers >= self.cfg.init_min_inliers else None

    def _initialise(self, t, gray, obs: Observation, intr, mask, rel, inlier_ids) -> bool:
        att = self._attempt
        k0 = att.first
        # Scale: unit baseline for the first map; later maps continue the last known speed.
        scale = self._speed_hint * max(1, t - k0.frame) if self._speed_hint else 1.0
        T_0_1 = rel.T_a_b.copy()
        T_0_1[:3, 3] *= scale
        T1 = k0.T_world_cam @ T_0_1
        s0, s = self._static(k0.obs), self._static(obs)
        _, ia, ib = np.intersect1d(s0.ids, s.ids, return_indices=True)
        sel = np.isin(s0.ids[ia], inlier_ids)
        ia, ib = ia[sel], ib[sel]
        X, err, ang = triangulate(k0.T_world_cam, T1, s0.uv[ia], s.uv[ib], k0.intr, intr)
        good = (err < self.cfg.triangulation_max_error_px) & (ang > 0.5 * self.cfg.triangulation_min_angle_deg)
        if good.sum() < self.cfg.init_min_inliers:
            return False
        m = self.map
        m.landmarks.set_positions(s0.ids[ia][good], X[good])
        m.segment += 1
        m.window = []
        m.state = VOState.TRACKING
        row0 = self._add_keyframe(k0.frame, k0.T_world_cam, k0.intr, k0.obs)
        if not m.frames.written(k0.frame):
            m.frames.write(k0.frame, FrameStatus.KEYFRAME, int(good.sum()), ref_kf=row0, T=np.eye(4))
        elif m.frames.ref_kf[k0.frame] < 0:
            # A re-start from the frame where tracking was lost (extrapolated): that frame is
            # this map's first keyframe, so it must follow it when the global refinement moves
            # the keyframes (left behind, it showed as a 7.8 deg jump on Bonn).
            m.frames.attach(k0.frame, row0, k0.T_world_cam)
        # Every frame that waited gets a real pose now, by PnP on the new landmarks; one that
        # sees too few of them keeps its provisional pose (between the two keyframes:
        # interpolated; before the first: rotation-only).
        posed, rest = [], []
        for w in att.waiting:
            if w.frame == k0.frame:
                continue
            T, n = self._pnp(w.obs, w.intr)
            (posed if T is not None else rest).append((w, T, n))
        self._attempt = None
        # Like LEAP-VO's 8-frame start, a few of those frames join the first window: two views
        # of a near-planar or low-parallax scene leave the structure ambiguous, more views fix it.
        after = [p for p in posed if p[0].frame > k0.frame]
        n_mid = max(0, self.cfg.init_keyframes - 2)
        mids = set()
        if after and n_mid:
            pick = np.unique(np.linspace(0, len(after) - 1, n_mid + 2).round().astype(int)[1:-1])
            for w, T, n in (after[i] for i in pick):
                row = self._add_keyframe(w.frame, T, w.intr, w.obs)
                m.frames.write(w.frame, FrameStatus.KEYFRAME, n, ref_kf=row, T=np.eye(4))
                mids.add(w.frame)
        for w, T, n in posed:
            if w.frame not in mids:
                self._write_relative(w.frame, FrameStatus.BOOTSTRAP, n, row0, T)
                self._keep_for_repose(w.frame, w.obs)
        for w, _, n in rest:
            if w.frame > k0.frame:
                a = (w.frame - k0.frame) / max(t - k0.frame, 1)
                self._write_relative(w.frame, FrameStatus.INTERPOLATED, 0, row0,
                                     interpolate_pose(k0.T_world_cam, T1, a))
            else:
                # Before the first keyframe: its rotation was measured against it, so it
                # follows it too.
                self._write_relative(w.frame, self._unmapped_status, n, row0, w.T_world_cam)
        self._velocity_hint = None
        self._make_keyframe(t, gray, obs, intr, mask, T1, int(good.sum()), bootstrapping=True)
        return True

    # ----------------------------------------------------------------- mapping
    def _add_keyframe(self, frame, T_world_cam, intr, obs: Observation) -> int:
        row = self.map.keyframes.add(frame, T_world_cam, intr, self.map.segment, obs.ids, obs.uv,
                                     obs.masked)
        self.map.window.append(row)
        return row

    def _make_keyframe(self, t, gray, obs: Observation, intr, mask, T_world_cam, n_inl,
                       bootstrapping: bool = False) -> None:
        t0 = time.perf_counter()
        m = self.map
        kf = m.keyframes
        obs = self._drop_dissimilar(gray, obs, T_world_cam, intr)
        # After the dissimilarity check, which needs the tracker's own positions: a track that
        # slides along an outline still looks changed there, and fitted to its first look it
        # would not (tuning creeps 0-5, true masks: ATE geometric mean 0.117 before the check,
        # 0.108 after it, 0.104 without anchors).
        self.timings["mapping"] += time.perf_counter() - t0
        obs = self._to_anchors(gray, obs, T_world_cam, intr)
        obs = self._reacquire(gray, obs, T_world_cam, intr, mask)
        t0 = time.perf_counter()
        s = self._static(obs)
        need = ~m.landmarks.has_position(s.ids)
        views = []
        for k in m.window:
            ids_k, uv_k, masked_k = kf.observations(k)
            ok = ~masked_k & ~m.landmarks.flagged(ids_k)
            views.append((kf.T_world_cam[k], kf.intrinsics(k), ids_k[ok], uv_k[ok]))
        # s holds no flagged track, so its tracks with a position are the landmarks in view.
        min_angle = triangulation_angle_deg(int(np.count_nonzero(~need)), self.cfg.grid_size,
                                            self.cfg.triangulation_min_angle_deg,
                                            self.cfg.triangulation_starved_angle_deg)
        new_ids, X = triangulate_against(views, s.ids[need], s.uv[need], intr, T_world_cam,
                                         self.cfg.triangulation_max_error_px, min_angle)
        m.landmarks.set_positions(new_ids, X)
        seed_ids, seed_uv = self._new_points(gray, obs, mask)
        full = Observation(np.concatenate([obs.ids, seed_ids]), np.concatenate([obs.uv, seed_uv]),
                           np.concatenate([obs.masked, np.zeros(len(seed_ids), bool)]))
        row = self._add_keyframe(t, T_world_cam, intr, full)
        if self._anchors is not None:
            self._anchors.keep(full.ids)
            self._anchors.add(full.ids, full.uv, row, gray)
        if self.cfg.patch_dissimilarity > 0:
            self._last_kf_view = (gray, full.ids, full.uv, T_world_cam, intr)
        if self.cfg.reacquire_keyframes > 0:
            self._kf_grays[row] = gray
            for r in [r for r in self._kf_grays if r <= row - self.cfg.reacquire_keyframes]:
                del self._kf_grays[r]
        m.frames.write(t, FrameStatus.KEYFRAME, int(n_inl), ref_kf=row, T=np.eye(4))
        self.timings["mapping"] += time.perf_counter() - t0
        self._bundle_adjust(bootstrapping)
        while len(m.window) > self.cfg.window_keyframes:
            m.window.pop(0)   # the keyframe and its observations stay in the table

    def _to_anchors(self, gray, obs: Observation, T_world_cam, intr) -> Observation:
        """Every track with an anchor is fitted to its first look (mona_vo.patch_align) and
        moved there, in this keyframe's observations and in the tracker, when the fit
        converged, correlates at least ``anchor_min_ncc`` and moves it by at most
        ``anchor_max_shift_px``. The patch's start deformation is the turn since the anchor's
        keyframe (same map segment), so a rolled or panned patch need not be found by the fit."""
        a = self._anchors
        if a is None or not len(a.ids):
            return obs
        t0 = time.perf_counter()
        _, ia, io = np.intersect1d(a.ids, obs.ids, return_indices=True)
        kf = self.map.keyframes
        deform = np.tile(np.eye(2), (len(ia), 1, 1))
        for row in np.unique(a.rows[ia]):
            if kf.segment[row] == self.map.segment:
                sel = a.rows[ia] == row
                H = self._turn_since(row, T_world_cam, intr)
                deform[sel] = homography_jacobians(H, a.uv[ia[sel]])
        p, ncc, ok = align_patches(a.templates[ia], gray, obs.uv[io], deform, half=a.half)
        h, w = gray.shape
        ok &= (ncc >= self.cfg.anchor_min_ncc) & np.isfinite(p).all(axis=1)
        ok &= np.linalg.norm(p - obs.uv[io], axis=1) <= self.cfg.anchor_max_shift_px
        ok &= (p[:, 0] >= 0) & (p[:, 0] <= w - 1) & (p[:, 1] >= 0) & (p[:, 1] <= h - 1)
        uv = obs.uv.copy()
        uv[io[ok]] = p[ok]
        self.tracker.move(obs.ids[io[ok]], p[ok])
        self.timings["anchoring"] += time.perf_counter() - t0
        return Observation(obs.ids, uv, obs.masked)

    def _turn_since(self, row: int, T_world_cam, intr) -> np.ndarray:
        """(3, 3) ``K R K_row^-1``: where keyframe ``row``'s pixels at infinity are seen from
        the camera at T_world_cam, the turn a patch of that keyframe is deformed by."""
        kf = self.map.keyframes
        R = (invert_pose(T_world_cam) @ kf.T_world_cam[row])[:3, :3]
        return turn_homography(intr, R, kf.intrinsics(row))

    def _reacquire(self, gray, obs: Observation, T_world_cam, intr, mask) -> Observation:
        """Landmarks whose tracks were lost, seen unmasked by one of the last
        ``reacquire_keyframes`` keyframes of this map, looked for where this keyframe's pose
        puts them (:func:`find_by_projection`, from the last keyframe that saw each) and tracked
        again under their own ids when found. People walking past a following camera hide the
        background's landmarks; without this their tracks end for good, and once the people
        have passed the pose rests on new landmarks alone, whose scale drifts (README, Known
        limits: Bonn crowd). A landmark is not looked for inside a mask or an overlay, nor
        within ``reacquire_px`` of a live track (the same corner tracked under a new id)."""
        cfg = self.cfg
        if (cfg.reacquire_keyframes <= 0 or not self._kf_grays
                or not self.tracker.takes_corrections):   # it could not take them back
            return obs
        t0 = time.perf_counter()
        kf, lm = self.map.keyframes, self.map.landmarks
        rows = [r for r in sorted(self._kf_grays) if kf.segment[r] == self.map.segment]
        idx = kf.observation_index(rows)
        seen = ~kf.obs_masked[idx]
        ids, uv = kf.obs_lm[idx][seen], kf.obs_uv[idx][seen].astype(np.float64)
        row = kf.observation_rows(rows)[seen]
        # The last sighting of each landmark (rows are oldest first).
        _, first = np.unique(ids[::-1], return_index=True)
        last = len(ids) - 1 - first
        ids, uv, row = ids[last], uv[last], row[last]
        # obs holds every live track (the tracker ends the others), masked ones included.
        sel = lm.usable(ids) & ~np.isin(ids, obs.ids)
        ids, uv, row = ids[sel], uv[sel], row[sel]
        proj, z = reproject(T_world_cam, lm.positions(ids), intr)
        h, w = gray.shape
        b = REACQUIRE_HALF_PX + 1
        with np.errstate(invalid="ignore"):
            sel = (z > 0) & (proj[:, 0] >= b) & (proj[:, 0] <= w - 1 - b) \
                & (proj[:, 1] >= b) & (proj[:, 1] <= h - 1 - b)
        for m in (mask, self._occluded):
            if m is not None and sel.any():
                sel[sel] = ~pixels_in_mask(m, proj[sel])
        if sel.any() and len(obs.uv):
            sel[sel] = cKDTree(obs.uv).query(proj[sel])[0] > cfg.reacquire_px
        ids, uv, row, proj = ids[sel], uv[sel], row[sel], proj[sel]
        found_ids, found_uv = [np.zeros(0, np.int64)], [np.zeros((0, 2))]
        for r in np.unique(row):
            sel = row == r
            H = self._turn_since(r, T_world_cam, intr)
            p, ok = find_by_projection(self._kf_grays[r], uv[sel], gray, proj[sel], H,
                                       half=REACQUIRE_HALF_PX, max_px=cfg.reacquire_px,
                                       min_ncc=cfg.reacquire_min_ncc)
            found_ids.append(ids[sel][ok])
            found_uv.append(p[ok])
        self.timings["reacquire"] += time.perf_counter() - t0
        fid, fuv = np.concatenate(found_ids), np.concatenate(found_uv)
        if not len(fid) or not self.tracker.revive(fid, fuv):
            return obs
        lm.strikes[fid] = 0
        lm.drift[fid] = 0.0
        self.found_again += len(fid)
        return Observation(np.concatenate([obs.ids, fid]), np.concatenate([obs.uv, fuv]),
                           np.concatenate([obs.masked, np.zeros(len(fid), bool)]))

    def _drop_dissimilar(self, gray, obs: Observation, T_world_cam, intr) -> Observation:
        """Tracks whose patch no longer looks as it did at the last keyframe are dropped with
        their landmarks (Shi and Tomasi's feature-dissimilarity check, 1994). A corner where a
        near edge crosses the far background (a T-junction) is the strongest corner a detector
        finds and tracks well from frame to frame, but it is no point of the scene: its track
        slides between the two surfaces, lagging the near one. On a generated slow pan (mixed
        seed 207) leaving out the true depth edges took the ATE from 1.05 to 0.38 % of path;
        this check, without ground truth, to 0.67 %. The keyframe's patch is first warped by
        the rotation between the two poses (K R K^-1), so a camera that turned or rolled does
        not lower the similarity; the threshold is relative to the keyframe's median
        dissimilarity, so noise, blur and JPEG, which lower every patch's, do not empty the
        map."""
        if self.cfg.patch_dissimilarity <= 0 or self._last_kf_view is None:
            return obs
        g0, ids0, uv0, T0, intr0 = self._last_kf_view
        _, i0, i1 = np.intersect1d(ids0, obs.ids, return_indices=True)
        R = (invert_pose(T_world_cam) @ T0)[:3, :3]        # last keyframe's camera -> this one
        sel = self._dissimilar(g0, uv0[i0], intr0, gray, obs.uv[i1], intr, R)
        return self._reject(obs, obs.ids[i1[sel]])

    def _dissimilar(self, g0, uv0, intr0, gray, uv, intr, R_b_a) -> np.ndarray:
        """(N,) bool :func:`dissimilar_tracks` of tracks seen at uv0 in an earlier image g0 and
        at uv now, the camera having turned by R_b_a (earlier axes -> this frame's) since."""
        H = turn_homography(intr, R_b_a, intr0)
        return dissimilar_tracks(g0, uv0, gray, uv, H, self.cfg.patch_half_px,
                                 self.cfg.patch_dissimilarity)

    def _reject(self, obs: Observation, bad: np.ndarray) -> Observation:
        """Dissimilar tracks out for good: their landmarks flagged, their tracks ended."""
        if not len(bad):
            return obs
        self.drops["tracks_dissimilar"] += self.map.landmarks.flag(bad, LandmarkFlag.REJECTED)
        self.tracker.remove(bad)
        return obs.subset(~np.isin(obs.ids, bad))

    def _bundle_adjust(self, bootstrapping: bool) -> None:
        m = self.map
        if len(m.window) < 2:
            return
        t0 = time.perf_counter()
        kf, lm = m.keyframes, m.landmarks
        rows = list(m.window)
        obs_kf, obs_lm, obs_uv, obs_masked = m.window_observations()
        keep = lm.has_position(obs_lm)
        keep[keep] = (lm.flags[obs_lm[keep]] & _OUT) == 0
        obs_kf, obs_lm, obs_uv, obs_masked = obs_kf[keep], obs_lm[keep], obs_uv[keep], obs_masked[keep]
        minimal_gauge = bootstrapping or self.cfg.gauge == "distance"
        extra = []
        if not minimal_gauge:
            o_kf, o_lm, o_uv = self._views_before_window(rows[0], obs_lm)
            obs_kf = np.concatenate([obs_kf, o_kf])
            obs_lm = np.concatenate([obs_lm, o_lm])
            obs_uv = np.concatenate([obs_uv, o_uv])
            obs_masked = np.concatenate([obs_masked, np.zeros(len(o_kf), bool)])
            extra = sorted(set(o_kf.tolist()))
        # A landmark seen inside a mask at any frame counts as seen inside one here too.
        obs_masked = obs_masked | ((lm.flags[obs_lm] & np.uint8(LandmarkFlag.MASKED)) > 0)
        anchor = None
        if minimal_gauge:
            # The first window (built on the essential matrix) always takes the minimal gauge:
            # freezing two of its keyframes would freeze any error of the two-view solution.
            fixed = {rows[0]}
            d = float(np.linalg.norm(kf.T_world_cam[rows[1], :3, 3] - kf.T_world_cam[rows[0], :3, 3]))
            anchor = (rows[0], rows[1], d)
        else:
            # The views from before the window are held where they are, as its oldest are.
            fixed = set(rows[:min(self.cfg.fixed_keyframes, len(rows) - 1)]) | set(extra)
        rows_all = rows + extra
        uniq = np.unique(obs_lm)
        P = lm.positions(uniq)
        problem = BAProblem(
            poses={r: kf.T_world_cam[r].copy() for r in rows_all}, fixed=fixed,
            intrinsics={r: kf.intrinsics(r) for r in rows_all},
            landmarks={int(j): P[i] for i, j in enumerate(uniq)},
            obs_kf=obs_kf, obs_lm=obs_lm, obs_uv=obs_uv, scale_anchor=anchor,
            obs_masked=obs_masked)
        refine = self.cfg.refine_focal and self._focal_fixed is None
        res = sliding_window_ba(problem, self.cfg.ba, refine_focal=refine)
        for r in rows:
            kf.T_world_cam[r] = res.poses[r]
        used = np.unique(obs_lm[res.obs_used])
        if len(used):
            lm.set_positions(used, np.array([res.landmarks[int(j)] for j in used]))
        # Landmarks the BA could not explain are dynamic or mistracked: out for good.
        out_lm, counts = np.unique(obs_lm[res.outlier], return_counts=True)
        if len(out_lm):
            worst = np.array([np.nanmax(res.obs_residual_px[obs_lm == j]) for j in out_lm])
            bad = out_lm[(counts >= 2) | (worst > 3 * self.cfg.ba.outlier_px)]
            self.drops["landmarks_rejected_by_ba"] += lm.flag(bad, LandmarkFlag.REJECTED)
            self.tracker.remove(bad)
        if len(res.degenerate_landmark_ids):
            # At or behind a camera: a triangulation the window's poses no longer support.
            bad = np.asarray(res.degenerate_landmark_ids, np.int64)
            self.drops["landmarks_rejected_by_ba"] += lm.flag(bad, LandmarkFlag.REJECTED)
            self.tracker.remove(bad)
        if len(res.masked_landmark_ids):
            lm.flag(res.masked_landmark_ids, LandmarkFlag.MASKED)
        self.drops["ba_masked_observations"] += res.masked_observations
        self.drops["ba_masked_landmarks"] += res.masked_landmarks
        if np.isfinite(res.final_rmse_px):
            self._rmse = res.final_rmse_px
        if refine and res.focal is not None and len(m.window) >= self.cfg.window_keyframes:
            self._focal_fixed = res.focal
        self.timings["ba"] += time.perf_counter() - t0

    def _views_before_window(self, first_row: int, window_lm: np.ndarray):
        """(rows, landmark ids, pixels float64) of the unmasked observations of the landmarks
        ``window_lm`` by the ``ba_outside_keyframes`` keyframes of this map before the window's
        first keyframe ``first_row``: the window's bundle adjustment holds them with those
        keyframes fixed, so a landmark keeps the views that fixed its depth."""
        kf = self.map.keyframes
        before = [r for r in range(max(0, first_row - self.cfg.ba_outside_keyframes), first_row)
                  if kf.segment[r] == self.map.segment]
        idx = kf.observation_index(before)
        rows = kf.observation_rows(before)
        sel = np.isin(kf.obs_lm[idx], window_lm) & ~kf.obs_masked[idx]
        return rows[sel], kf.obs_lm[idx][sel], kf.obs_uv[idx][sel].astype(np.float64)

    # ----------------------------------------------------------------- global refinement
    def keyframe_graph(self):
        """The whole run's keyframes and landmarks as a :class:`ba.global_ba.KeyframeGraph`
        (observations of flagged-out landmarks left out; those of landmarks seen inside a mask
        kept with ``obs_masked`` so the graph drops and counts them)."""
        from ba.global_ba import KeyframeGraph

        kf, lm = self.map.keyframes, self.map.landmarks
        K, M = kf.n, kf.m
        obs_kf = kf.observation_rows(np.arange(K))
        obs_lm = kf.obs_lm[:M]
        keep = lm.has_position(obs_lm)
        keep[keep] = (lm.flags[obs_lm[keep]] & _OUT) == 0
        obs_masked = kf.obs_masked[:M][keep]
        obs_lm, obs_kf, obs_uv = obs_lm[keep], obs_kf[keep], kf.obs_uv[:M][keep].astype(np.float64)
        obs_masked = obs_masked | ((lm.flags[obs_lm] & np.uint8(LandmarkFlag.MASKED)) > 0)
        lm_ids = np.unique(obs_lm)
        return KeyframeGraph(kf.frame[:K].copy(), kf.T_world_cam[:K].copy(), kf.intr[:K].copy(),
                             obs_kf.astype(np.int64), obs_lm.astype(np.int64), obs_uv, obs_masked,
                             lm_ids.astype(np.int64), lm.positions(lm_ids).copy())

    def _refine_global(self) -> dict:
        from ba.global_ba import refine_global

        t0 = time.perf_counter()
        graph = self.keyframe_graph()
        if not len(graph.lm_ids):
            return {}
        # Without intrinsics the focal length is a guess or an estimate from the first frames'
        # few keyframes; the whole run's keyframes hold more rotation and parallax, so it is
        # freed here (one shared Cal3f, its weak prior at the start value) and every keyframe
        # takes it (generated creep from a focal 28 % too long: +6.9 % after, 0.45 -> 0.13 % of
        # path). Where the clip does not constrain it, the prior keeps the start value.
        free = self.cfg.global_camera != "none" and not self._camera_known
        centres_before = graph.T_world_cam[:, :3, 3].copy()
        rates, vel, readout = None, None, 0.0
        if self.cfg.rolling_shutter != "off":
            poses, segments = self.map.all_poses(), self.map.frame_segments()
            rates = turn_rates(poses, segments)
            if self.cfg.rolling_shutter_model == "rotation+translation":
                vel = velocities(poses, segments)
        if self.cfg.rolling_shutter == "given":
            readout = self.cfg.rolling_shutter_readout
            graph = self._unrolled(graph, rates, readout, vel)
        res = refine_global(graph, self.cfg.ba, refine_focal=free)
        shutter = {}
        many = len(graph.kf_frames) > self.cfg.window_keyframes
        if self.cfg.rolling_shutter == "estimate" and many:
            readout, shutter, unrolled = self._estimate_readout(graph, rates, res, free, vel)
            if readout > 0:
                graph, res = unrolled
        elif self.cfg.rolling_shutter == "residual" and many:
            readout, shutter, unrolled = self._estimate_residual(graph, rates, res, free, vel)
            if readout != 0:
                graph, res = unrolled
        elif self.cfg.rolling_shutter in ("estimate", "residual"):
            # One window of keyframes or fewer: the refinement is the window's own problem, and
            # a readout trades off against a few frames' poses (an 8-frame generated clip with
            # an unmasked car, a global shutter, found one).
            shutter = {"not_estimated": f"{len(graph.kf_frames)} keyframes, one window or fewer"}
        if free and self.cfg.global_camera == "focal+centre" and res.focal is not None:
            # The principal point from the focal-only solution: freed together from the start,
            # the two trade off and the focal length stays where it began.
            intr = np.array(graph.intrinsics, np.float64)
            intr[:, :2] = res.focal
            valid = np.asarray(res.lm_valid, bool)
            graph = dataclasses.replace(graph, T_world_cam=res.T_world_cam, intrinsics=intr,
                                        lm_xyz=np.where(valid[:, None], res.lm_xyz, graph.lm_xyz))
            res = refine_global(graph, self.cfg.ba, refine_focal=True, refine_centre=True)
        kf, lm = self.map.keyframes, self.map.landmarks
        focal = {}
        if free and res.focal is not None and np.isfinite(res.focal):
            focal = {"focal_start_px": float(kf.intr[0, 0]), "focal_px": float(res.focal)}
            kf.intr[:kf.n, :2] = res.focal
            self._focal_fixed = float(res.focal)
            if res.centre is not None and np.isfinite(res.centre).all():
                focal["centre_px"] = [float(c) for c in res.centre]
                kf.intr[:kf.n, 2:4] = res.centre
        # Every frame tied to a keyframe follows it (re-attached by its relative pose); tracked and
        # bootstrap frames are then posed again on the refined map (_repose_frames).
        kf.T_world_cam[:kf.n] = res.T_world_cam
        valid = np.asarray(res.lm_valid, bool)
        lm.set_positions(graph.lm_ids[valid], np.asarray(res.lm_xyz)[valid])
        self.drops["ba_masked_observations"] += int(res.masked_observations)
        self.drops["ba_masked_landmarks"] += int(res.masked_landmarks)
        if np.isfinite(res.rmse_px):
            self._rmse = float(res.rmse_px)
        reposed = self._repose_frames(rates if readout != 0 else None, readout)
        self.timings["global_ba"] += time.perf_counter() - t0
        shift = keyframe_shift_pct(centres_before, kf.T_world_cam[:kf.n, :3, 3])
        return {"keyframes": int(kf.n), "landmarks": int(valid.sum()), "keyframe_shift_pct": shift,
                "observations_used": int(res.n_observations_used),
                "rmse_px": float(res.rmse_px), "seconds": float(res.seconds),
                "frames_reposed": reposed, **focal,
                **({"rolling_shutter": {"readout": readout, **shutter}}
                   if self.cfg.rolling_shutter != "off" else {})}

    def _unrolled(self, graph, rates: np.ndarray, readout: float,
                  velocity: np.ndarray | None = None):
        """``graph`` with every observation moved to where its frame's middle-row camera saw it
        (:func:`mona_vo.rolling_shutter.corrected_pixels`); with ``velocity`` (per frame) the
        camera's motion within the readout taken out too, at the depths of ``graph``'s own
        keyframe poses and landmarks."""
        frames = graph.kf_frames[graph.obs_kf]
        points = None
        if velocity is not None:
            row, known = graph.landmark_rows()
            T = graph.T_world_cam[graph.obs_kf]
            points = np.einsum("nji,nj->ni", T[:, :3, :3], graph.lm_xyz[row] - T[:, :3, 3])
            points[~known] = np.nan                  # no depth: the turn alone
        return dataclasses.replace(graph, obs_uv=corrected_pixels(
            graph.obs_uv, rates[frames], readout, graph.intrinsics[graph.obs_kf], self.height,
            None if velocity is None else velocity[frames], points))

    def _readout_solver(self, graph, rates: np.ndarray, first, free: bool,
                        velocity: np.ndarray | None):
        """(solve, solved) for the readout searches: ``solve(r)`` solves the global refinement
        from the global-shutter solution ``first`` with the observations corrected for readout
        r and records (graph, result, cost) in ``solved`` (readout 0: ``first`` itself). The
        cost is the mean squared reprojection error, capped at ``vo.ba.outlier_px``, over the
        observations ``first`` used (a landmark the candidate dropped counts at the cap)."""
        from ba.global_ba import refine_global
        from ba.factors import reprojection_errors

        cap = self.cfg.ba.outlier_px
        common = np.asarray(first.obs_used, bool)
        row, _ = graph.landmark_rows()
        warm = dataclasses.replace(graph, T_world_cam=first.T_world_cam, lm_xyz=np.where(
            np.asarray(first.lm_valid, bool)[:, None], first.lm_xyz, graph.lm_xyz))

        def cost(g, res) -> float:
            intr = np.array(g.intrinsics, np.float64)
            if res.focal is not None:
                intr[:, :2] = res.focal
            e = reprojection_errors(res.T_world_cam[g.obs_kf], res.lm_xyz[row], intr[g.obs_kf],
                                    g.obs_uv)
            e = np.where(np.asarray(res.lm_valid, bool)[row] & np.isfinite(e), e, cap)
            return float(np.mean(np.minimum(e[common], cap) ** 2)) if common.any() else np.inf

        solved = {0.0: (graph, first, cost(graph, first))}

        def solve(r: float) -> float:
            if r not in solved:
                g = self._unrolled(warm, rates, r, velocity)
                res = refine_global(g, self.cfg.ba, refine_focal=free)
                solved[r] = (g, res, cost(g, res))
            return solved[r][2]

        return solve, solved

    @staticmethod
    def _readout_found(best: float, solved: dict):
        """(readout, what was found for the report, (graph, result) of that readout): ``best``
        kept only when it fits at least ``ROLLING_SHUTTER_MIN_GAIN`` better than 0."""
        if solved[best][2] > (1.0 - ROLLING_SHUTTER_MIN_GAIN) * solved[0.0][2]:
            best = 0.0
        found = {"cost_px2": {f"{r:g}": round(c, 5) for r, (_, _, c) in sorted(solved.items())}}
        return best, found, solved[best][:2]

    def _estimate_readout(self, graph, rates: np.ndarray, first, free: bool,
                          velocity: np.ndarray | None = None):
        """The readout (share of the frame interval) under which the global refinement fits
        its observations best, from the global-shutter solution ``first``
        (:meth:`_readout_solver`). Readouts 0, 0.5 and 1.0 (and 1.25 when 1.0 fits better
        than 0.5) are solved and a parabola's lowest point taken
        (:func:`mona_vo.rolling_shutter.best_readout`); where 0.5 fits no better than 0, the
        shutter is global and nothing else is solved. Returns :meth:`_readout_found`'s
        triple."""
        solve, solved = self._readout_solver(graph, rates, first, free, velocity)
        best = 0.0
        if solve(0.5) < solved[0.0][2]:
            if solve(1.0) < solved[0.5][2]:
                solve(1.25)
            tried = sorted(solved)
            best = round(best_readout(tried, [solved[r][2] for r in tried]), 2)
            solve(best)
        return self._readout_found(best, solved)

    def _estimate_residual(self, graph, rates: np.ndarray, first, free: bool,
                           velocity: np.ndarray | None = None):
        """The readout left over on frames unrolled already at a first estimate
        (``vo.rolling_shutter_readout``), signed (a first estimate too long leaves a negative
        one): readouts of +-``RESIDUAL_STEP`` are solved, then further steps the way that fits
        better while the cost falls, up to ``RESIDUAL_MAX`` and never beyond a whole readout
        of 0 or 1 (a video reads its rows within one frame interval), and a parabola's lowest
        point taken (:func:`mona_vo.rolling_shutter.best_residual`). Returns
        :meth:`_readout_found`'s triple."""
        done = self.cfg.rolling_shutter_readout
        lo, hi = max(-RESIDUAL_MAX, -done), min(RESIDUAL_MAX, 1.0 - done)

        def step(r: float, way: float) -> float:
            return round(float(np.clip(r + way, lo, hi)), 2)

        solve, solved = self._readout_solver(graph, rates, first, free, velocity)
        ways = [w for w in (RESIDUAL_STEP, -RESIDUAL_STEP) if step(0.0, w) != 0.0]
        best = 0.0
        if ways:
            way = min(ways, key=lambda w: solve(step(0.0, w)))
            r = step(0.0, way)
            if solved[r][2] < solved[0.0][2]:
                while step(r, way) != r and solve(step(r, way)) < solved[r][2]:
                    r = step(r, way)
                tried = sorted(solved)
                best = round(best_residual(tried, [solved[t][2] for t in tried]), 2)
                solve(best)
        return self._readout_found(best, solved)

    def _repose_frames(self, rates: np.ndarray | None = None, readout: float = 0.0) -> int:
        """Every tracked frame, and every frame posed by PnP when the first map was built
        (bootstrap), posed again on the refined map from where its keyframe took it. Moving a
        frame with its keyframe keeps the relative pose PnP found on the map as it was then, in
        that window's scale and with that window's errors; on a following shot (mixed 103) the
        frames between keyframes drifted to 5x the keyframes' error. Returns the number of
        frames re-posed (the others keep the pose they followed)."""
        m, lm, kf = self.map, self.map.landmarks, self.map.keyframes
        n = 0
        for t, ids, uv in m.frames.observation_groups():
            ref = int(m.frames.ref_kf[t])
            have = lm.usable(ids)
            if ref < 0 or have.sum() < self.cfg.pnp_min_inliers:
                continue
            ps = self._pose_settings
            intr = kf.intrinsics(ref)
            if rates is not None:
                uv = corrected_pixels(uv, np.broadcast_to(rates[t], (len(uv), 3)), readout,
                                      np.array([intr.fx, intr.fy, intr.cx, intr.cy]), self.height)
            T, _ = refine_pose(lm.positions(ids[have]), uv[have], intr, m.pose_of(t),
                               ps.guided_px, ps, ps.guided_min_share)
            if T is not None:
                m.frames.repose(t, invert_pose(kf.T_world_cam[ref]) @ T)
                n += 1
        return n
