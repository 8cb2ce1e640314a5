"""Monocular visual odometry, LEAP-VO style, on a CPU: multi-frame point tracks, keyframes and a
sliding-window bundle adjustment (:mod:`ba.sliding_window_ba`) that never sees a tracked point
inside a moving-object mask.

Usage: ``vo = VisualOdometry(config, width, height)``, then ``vo.step(image, ...)`` per frame, then
``vo.finish()`` -> :class:`VOResult` with a pose for every frame.

Per frame: track all points (``config.tracker``); drop every track that enters the frame's
moving-object mask (for good: a landmark seen inside a mask is dynamic); estimate the pose by PnP
with RANSAC on tracks that have landmarks, predicted by a constant-velocity model; score every
track's residual with a Cauchy model to flag points the masks missed. On a keyframe: triangulate
new landmarks, top the grid up with new tracks, and solve the window's bundle adjustment.

Before the map exists, the first keyframe waits for enough parallax (essential matrix + median ray
angle). Footage without parallax (static or purely rotating camera) gets rotation-only poses; lost
tracking re-initialises a new map chained to the last pose. Every frame gets a pose and a status.
"""
from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field

import cv2
import numpy as np

from ba.sliding_window_ba import BAConfig, BAProblem, sliding_window_ba
from mona_vo.conventions import Intrinsics, invert_pose, make_pose, pixels_in_mask, reproject
from mona_vo.errors import ConfigError
from mona_vo.point_selection import grid_points, texture_score
from mona_vo.tracking import TRACKERS, to_gray
from mona_vo.two_view import relative_pose, rotation_only, rotation_parallax_deg, triangulate

# Per-frame status, from most to least trustworthy.
KEYFRAME, TRACKED, BOOTSTRAP, ROTATION_ONLY, INTERPOLATED, EXTRAPOLATED = (
    "keyframe", "tracked", "bootstrap", "rotation-only", "interpolated", "extrapolated")
LOW_CONFIDENCE = (ROTATION_ONLY, INTERPOLATED, EXTRAPOLATED)


@dataclass(frozen=True)
class VOConfig:
    tracker: str = "lk"                     # point tracker back end (mona_vo.tracking.TRACKERS)
    tracker_device: str = "cpu"             # torch device of a neural tracker
    tracker_checkpoint: str = ""            # its checkpoint file or weights folder; "" = $MONA_VO_WEIGHTS
    grid_size: int = 16                     # k: new points on a k x k grid, one per cell
    point_score: str = "min_eigen"          # min_eigen (Shi-Tomasi) | gradient (LEAP-VO)
    mask_dilate_px: int = 5                 # no new points this close to a moving-object mask
    init_min_parallax_deg: float = 0.5      # median ray angle needed to initialise the map
    init_min_inliers: int = 40              # essential-matrix inliers needed to initialise
    init_max_frames: int = 20               # frames to wait for parallax before rotation-only poses
    init_keyframes: int = 4                 # keyframes of the first window (two-view pair included)
    keyframe_parallax_px: float = 12.0      # median rotation-free track motion since the last keyframe, px
    keyframe_min_tracked: float = 0.6       # keyframe when this share of its landmarks remains
    keyframe_max_gap: int = 6               # at most this many frames between keyframes
    keyframe_min_landmarks: int = 60        # keyframe when fewer landmarks than this are tracked
    keyframe_falling: float = 0.9           # ... and fewer than this share of the last keyframe's
    window_keyframes: int = 8               # keyframes in the bundle-adjustment window
    fixed_keyframes: int = 2                # oldest window keyframes held fixed (gauge, scale)
    gauge: str = "fixed"                    # fixed: hold fixed_keyframes; distance: hold the oldest
                                            # keyframe and only its distance to the next one
    pnp_threshold_px: float = 2.0           # RANSAC inlier threshold for per-frame poses
    pnp_min_inliers: int = 12               # fewer PnP inliers means tracking is lost
    pnp_guided_px: float = 6.0              # points this close to the constant-velocity prediction
                                            # seed the pose before RANSAC is tried, px
    pnp_guided_min_share: float = 0.3       # ... if they are at least this share of the landmarks
    pnp_guided_support: float = 0.8         # and keep that pose unless RANSAC's has 1/0.8 x the inliers
    triangulation_min_angle_deg: float = 0.3  # rays closer than this give no landmark
    triangulation_max_error_px: float = 2.0   # nor do rays that miss each other by more
    dynamic_scale_px: float = 1.0           # Cauchy scale of a static point's residual, px
    dynamic_prob_max: float = 0.9           # tracks above this dynamic probability twice are dropped
    refine_focal: bool = False              # refine one shared focal length while the first window
                                            # fills (needs rotation; see README's measurements)
    refine: str = "global"                  # after the sliding window, one bundle adjustment over all
                                            # keyframes (global) or none (streaming)
    ba: BAConfig = field(default_factory=BAConfig)

    def validate(self) -> None:
        TRACKERS.check(self.tracker)
        if self.grid_size < 2:
            raise ConfigError("vo.grid_size must be at least 2")
        if self.fixed_keyframes < 1 or self.window_keyframes <= self.fixed_keyframes:
            raise ConfigError("vo.window_keyframes must exceed vo.fixed_keyframes >= 1")
        if self.point_score not in ("min_eigen", "gradient"):
            raise ConfigError("vo.point_score must be min_eigen or gradient")
        if self.refine not in ("global", "none"):
            raise ConfigError(f"config key 'vo.refine': expected global or none, got {self.refine!r}")
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
    timings:     stage -> seconds (tracking, pose, mapping, ba).
    drops:       counters of what the masks and the dynamic test removed.
    focal:       the focal length used at the end (px).
    map_points:  (M, 3) float64 landmarks of the last window (for a PLY export).
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

    @property
    def low_confidence(self) -> np.ndarray:
        return np.array([s in LOW_CONFIDENCE for s in self.status], bool)


@dataclass
class _Keyframe:
    frame: int
    T_world_cam: np.ndarray
    intr: Intrinsics
    ids: np.ndarray          # (N,) track ids observed
    uv: np.ndarray           # (N, 2) their pixels
    mask: np.ndarray | None


class VisualOdometry:
    def __init__(self, config: VOConfig, width: int, height: int,
                 intrinsics: Intrinsics | None = None):
        config.validate()
        self.cfg = config
        self.width, self.height = int(width), int(height)
        self.default_intr = intrinsics or Intrinsics.default_for(width, height)
        from mona_vo.masks import build_tracker

        self.tracker = build_tracker(config.tracker, config.tracker_device, config.tracker_checkpoint)
        self.timings = defaultdict(float)
        self.drops = defaultdict(int)
        # Per frame, filled as frames arrive.
        self._stamps: list[float] = []
        self._ref_kf: list[int | None] = []      # keyframe the relative pose refers to
        self._T_kf_frame: list[np.ndarray] = []   # pose relative to that keyframe
        self._abs: dict[int, np.ndarray] = {}     # absolute poses of frames not tied to a keyframe
        self._status: list[str] = []
        self._inliers: list[int] = []
        # Map state.
        self.keyframes: dict[int, _Keyframe] = {}  # by frame index; the window plus finished ones
        self.window: list[int] = []                # frame indices of window keyframes
        self.landmarks: dict[int, np.ndarray] = {}  # track id -> world point
        self.bad: set[int] = set()                  # tracks excluded for good (masked / dynamic)
        self.strikes: dict[int, int] = {}
        self.state = "init"
        self._init_kf: _Keyframe | None = None
        self._pending: list[tuple[int, np.ndarray, np.ndarray, Intrinsics]] = []
        self._focal_fixed: float | None = None
        self._bootstrapping = False
        self._speed_hint: float | None = None       # metres/frame before a re-initialisation
        self._last_gray = None

    # ----------------------------------------------------------------- public API
    def step(self, image: np.ndarray, *, timestamp: float | None = None,
             mask: np.ndarray | None = None, intrinsics: Intrinsics | None = None) -> None:
        """Process the next frame. image: (H, W, 3) uint8 RGB or (H, W) grey. mask: optional
        (H, W) bool moving-object mask. intrinsics: this frame's (defaults to the constructor's)."""
        t = len(self._stamps)
        self._stamps.append(float(t if timestamp is None else timestamp))
        intr = intrinsics or self.default_intr
        if self._focal_fixed is not None and intrinsics is None:
            intr = Intrinsics(self._focal_fixed, self._focal_fixed, intr.cx, intr.cy)
        gray = to_gray(image)
        if gray.shape != (self.height, self.width):
            raise ConfigError(f"frame {t} is {gray.shape[1]} x {gray.shape[0]}, expected "
                              f"{self.width} x {self.height}")
        t0 = time.perf_counter()
        upd = self.tracker.step(gray)
        vis = upd.visible
        ids, uv = upd.ids[vis], upd.points[vis].astype(np.float64)
        for i in upd.ids[~vis]:
            self.strikes.pop(int(i), None)
        if mask is not None:
            inside = pixels_in_mask(mask, uv)
            newly = [int(i) for i in ids[inside] if int(i) not in self.bad]
            self.drops["tracks_entering_masks"] += len(newly)
            self.bad.update(newly)
        keep = np.array([int(i) not in self.bad for i in ids], bool)
        ids, uv = ids[keep], uv[keep]
        self.timings["tracking"] += time.perf_counter() - t0
        self._last_gray = gray

        if self.state == "init":
            self._step_init(t, gray, ids, uv, intr, mask)
        else:
            self._step_track(t, gray, ids, uv, intr, mask)

    def finish(self) -> VOResult:
        n = len(self._stamps)
        poses = np.zeros((n, 4, 4))
        for t in range(n):
            ref = self._ref_kf[t]
            if ref is not None:
                poses[t] = self.keyframes[ref].T_world_cam @ self._T_kf_frame[t]
            else:
                poses[t] = self._abs.get(t, np.eye(4))
        iskf = np.array([t in self.keyframes and self._ref_kf[t] == t for t in range(n)], bool)
        pts = np.array([self.landmarks[i] for i in self._window_landmark_ids() if i in self.landmarks])
        focal = self._focal_fixed or self.default_intr.fx
        return VOResult(np.array(self._stamps), poses, iskf, list(self._status),
                        np.array(self._inliers, int), dict(self.timings), dict(self.drops),
                        float(focal), pts.reshape(-1, 3))

    # ----------------------------------------------------------------- frame bookkeeping
    def _record(self, t: int, status: str, inliers: int, *, ref: int | None = None,
                T_kf_frame: np.ndarray | None = None, T_world_cam: np.ndarray | None = None):
        if t == len(self._status):
            self._status.append(status)
            self._inliers.append(inliers)
            self._ref_kf.append(ref)
            self._T_kf_frame.append(np.eye(4) if T_kf_frame is None else T_kf_frame)
        else:
            self._status[t], self._inliers[t], self._ref_kf[t] = status, inliers, ref
            self._T_kf_frame[t] = np.eye(4) if T_kf_frame is None else T_kf_frame
        if ref is None:
            self._abs[t] = T_world_cam
        else:
            self._abs.pop(t, None)

    def _pose_of(self, t: int) -> np.ndarray:
        ref = self._ref_kf[t]
        if ref is not None:
            return self.keyframes[ref].T_world_cam @ self._T_kf_frame[t]
        return self._abs[t]

    def _window_landmark_ids(self) -> set[int]:
        out: set[int] = set()
        for k in self.window:
            out.update(int(i) for i in self.keyframes[k].ids)
        return out & set(self.landmarks)

    # ----------------------------------------------------------------- initialisation
    def _new_points(self, gray, ids_uv: np.ndarray, mask) -> tuple[np.ndarray, np.ndarray]:
        score = texture_score(gray, self.cfg.point_score)
        exclude = None
        if mask is not None and mask.any():
            k = 2 * self.cfg.mask_dilate_px + 1
            exclude = cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
        k = self.cfg.grid_size
        pts = grid_points(score, k, k, exclude=exclude, occupied=ids_uv)
        new_ids = self.tracker.add_points(pts) if len(pts) else np.zeros(0, np.int64)
        return new_ids, pts.astype(np.float64)

    def _start_init(self, t, gray, ids, uv, intr, mask, T_world_cam: np.ndarray) -> None:
        """Make frame t the first keyframe of a map to be. Live tracks carry on, so frames that
        waited for an earlier attempt still share points with the map once it exists."""
        if self._init_kf is not None:
            old = self._init_kf
            self._pending.append((old.frame, old.ids, old.uv, old.intr))
        self._pending = self._pending[-self.cfg.init_max_frames * 3:]
        new_ids, new_uv = self._new_points(gray, uv, mask)
        self._init_kf = _Keyframe(t, T_world_cam, intr, np.concatenate([ids, new_ids]),
                                  np.concatenate([uv, new_uv]), mask)
        self._record(t, ROTATION_ONLY, len(ids), T_world_cam=T_world_cam)

    def _step_init(self, t, gray, ids, uv, intr, mask) -> None:
        t0 = time.perf_counter()
        if self._init_kf is None:
            start = self._predict(t) if t > 0 else np.eye(4)
            self._start_init(t, gray, ids, uv, intr, mask, start)
            self.timings["pose"] += time.perf_counter() - t0
            return
        kf0 = self._init_kf
        common, i0, i1 = np.intersect1d(kf0.ids, ids, return_indices=True)
        self._pending.append((t, ids, uv, intr))
        rel = None
        if len(common) >= max(8, self.cfg.init_min_inliers):
            rel = relative_pose(kf0.uv[i0], uv[i1], kf0.intr, intr)
        ro = rotation_only(kf0.uv[i0], uv[i1], kf0.intr, intr) if len(common) >= 6 else None
        R = None if ro is None else ro[0]
        ok = (rel is not None and rel.n_inliers >= self.cfg.init_min_inliers
              and rel.median_parallax_deg >= self.cfg.init_min_parallax_deg)
        if ok and R is not None:
            # Near a pure rotation the essential matrix is ill-posed and its "parallax" is noise;
            # the parallax left after the best homography rotation tells the truth.
            par_h = rotation_parallax_deg(kf0.uv[i0][rel.inliers], uv[i1][rel.inliers], kf0.intr, intr, R)
            ok = float(np.median(par_h)) >= 0.5 * self.cfg.init_min_parallax_deg
        if ok and self._initialise(t, gray, ids, uv, intr, mask, rel, common[rel.inliers]):
            self.timings["pose"] += time.perf_counter() - t0
            return
        # Not yet: a provisional rotation-only pose relative to the first keyframe.
        T = kf0.T_world_cam @ make_pose(R if R is not None else np.eye(3), np.zeros(3))
        self._record(t, ROTATION_ONLY, len(common), T_world_cam=T)
        too_long = t - kf0.frame >= self.cfg.init_max_frames
        too_few = len(common) < max(self.cfg.init_min_inliers, 0.3 * len(kf0.ids))
        if too_long or too_few:
            # No parallax for a long time (static or rotating camera) or the view changed too
            # much: restart from this frame, keeping its rotation-only pose.
            self._start_init(t, gray, ids, uv, intr, mask, T)
        self.timings["pose"] += time.perf_counter() - t0

    def _initialise(self, t, gray, ids, uv, intr, mask, rel, inlier_ids) -> bool:
        kf0 = self._init_kf
        # Scale: unit baseline for the first map; later maps continue the last known speed.
        scale = 1.0
        if self._speed_hint:
            scale = self._speed_hint * max(1, t - kf0.frame)
        T_0_1 = rel.T_a_b.copy()
        T_0_1[:3, 3] *= scale
        T1 = kf0.T_world_cam @ T_0_1
        sel0 = np.isin(kf0.ids, inlier_ids)
        sel1 = np.isin(ids, inlier_ids)
        o0 = np.argsort(kf0.ids[sel0])
        o1 = np.argsort(ids[sel1])
        tid = kf0.ids[sel0][o0]
        X, err, ang = triangulate(kf0.T_world_cam, T1, kf0.uv[sel0][o0], uv[sel1][o1], kf0.intr, intr)
        good = (err < self.cfg.triangulation_max_error_px) & (ang > 0.5 * self.cfg.triangulation_min_angle_deg)
        if good.sum() < self.cfg.init_min_inliers:
            return False
        for i, p in zip(tid[good], X[good]):
            self.landmarks[int(i)] = p
        k0 = _Keyframe(kf0.frame, kf0.T_world_cam, kf0.intr, kf0.ids, kf0.uv, kf0.mask)
        # A new map after tracking was lost hangs on its first keyframe's provisional pose
        # (extrapolated or rotation-only): that junction keeps its low-confidence status.
        junction = self._status[k0.frame] if self.keyframes else KEYFRAME
        self.keyframes[k0.frame] = k0
        self.window.append(k0.frame)
        self._record(k0.frame, junction, int(good.sum()), ref=k0.frame)
        self._init_kf = None
        self.state = "track"
        # Every frame that waited for the map gets a real pose now, by PnP on the new landmarks;
        # one that sees too few of them keeps its provisional pose (between the two keyframes:
        # interpolated; before the first: rotation-only).
        posed = []
        for (tp, pids, puv, pintr) in self._pending[:-1]:
            T, n = self._pnp(pids, puv, pintr)
            if T is not None and tp > k0.frame:
                posed.append((tp, pids, puv, pintr, T, n))
            status = BOOTSTRAP
            if T is None and tp > k0.frame:
                T, n, status = self._interpolate(k0.frame, t, tp, T1), 0, INTERPOLATED
            if T is not None:
                self._record(tp, status, n, ref=k0.frame,
                             T_kf_frame=invert_pose(k0.T_world_cam) @ T)
        self._pending = []
        # Like LEAP-VO's 8-frame start, a few of those frames join the first window: two views
        # of a near-planar or low-parallax scene leave the structure ambiguous, more views fix it.
        n_mid = max(0, self.cfg.init_keyframes - 2)
        if posed and n_mid:
            pick = np.unique(np.linspace(0, len(posed) - 1, n_mid + 2).round().astype(int)[1:-1])
            for tp, pids, puv, pintr, T, n in (posed[i] for i in pick):
                self.keyframes[tp] = _Keyframe(tp, T, pintr, pids, puv, None)
                self.window.append(tp)
                self._record(tp, KEYFRAME, n, ref=tp)
        self._bootstrapping = True
        self._make_keyframe(t, gray, ids, uv, intr, mask, T1, int(good.sum()))
        self._bootstrapping = False
        return True

    def _interpolate(self, ka: int, kb: int, t: int, Tb: np.ndarray) -> np.ndarray:
        from scipy.spatial.transform import Rotation, Slerp

        Ta = self._pose_of(ka)
        a = (t - ka) / max(kb - ka, 1)
        R = Slerp([0, 1], Rotation.from_matrix([Ta[:3, :3], Tb[:3, :3]]))(a).as_matrix()
        return make_pose(R, (1 - a) * Ta[:3, 3] + a * Tb[:3, 3])

    # ----------------------------------------------------------------- tracking
    def _predict(self, t: int) -> np.ndarray:
        """Constant-velocity prediction of frame t's pose from the two frames before it."""
        if t >= 2:
            T1, T2 = self._pose_of(t - 2), self._pose_of(t - 1)
            return T2 @ (invert_pose(T1) @ T2)
        return self._pose_of(t - 1) if t >= 1 else np.eye(4)

    def _pnp(self, ids, uv, intr, T_guess: np.ndarray | None = None) -> tuple[np.ndarray | None, int]:
        """Pose of a frame from its tracks with landmarks. With a prediction, first a robust
        refinement from it on the points it explains; RANSAC (AP3P) when that fails."""
        have = np.array([int(i) in self.landmarks for i in ids], bool)
        if have.sum() < max(6, self.cfg.pnp_min_inliers):
            return None, int(have.sum())
        P = np.array([self.landmarks[int(i)] for i in ids[have]])
        q = uv[have]
        guided = (None, 0)
        if T_guess is not None:
            # A mover that keeps pace with the camera can hold the largest consensus set, and
            # RANSAC would follow it; under the constant-velocity prediction the static world is
            # the part that still fits. That pose wins unless RANSAC finds clearly more support.
            guided = self._refine_pose(P, q, intr, T_guess, self.cfg.pnp_guided_px)
        # Minimal AP3P samples need no initial guess (frames far from the prediction, e.g. those
        # waiting for the map, still work); the LM refinement restores full accuracy.
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            P, q, intr.K, None, iterationsCount=100, reprojectionError=self.cfg.pnp_threshold_px,
            confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        ransac = (None, 0 if inl is None else len(inl))
        if ok and inl is not None and len(inl) >= self.cfg.pnp_min_inliers:
            T_r, _ = cv2.Rodrigues(rvec)
            ransac = self._refine_pose(P, q, intr, invert_pose(make_pose(T_r, tvec.ravel())),
                                       self.cfg.pnp_threshold_px, min_share=0.0)
        if guided[0] is not None and guided[1] >= self.cfg.pnp_guided_support * ransac[1]:
            return guided
        return ransac if ransac[0] is not None else (None, ransac[1])

    def _refine_pose(self, P, q, intr, T_start, gate_px,
                     min_share: float | None = None) -> tuple[np.ndarray | None, int]:
        """Levenberg-Marquardt from T_start on the points within gate_px of their prediction,
        then again on the points within pnp_threshold_px of the refined pose."""
        T = T_start
        share = self.cfg.pnp_guided_min_share if min_share is None else min_share
        for gate in (gate_px, self.cfg.pnp_threshold_px):
            proj, z = reproject(T, P, intr)
            sel = (z > 0) & (np.hypot(proj[:, 0] - q[:, 0], proj[:, 1] - q[:, 1]) < gate)
            if sel.sum() < max(self.cfg.pnp_min_inliers, share * len(P)):
                return None, int(sel.sum())
            if not np.isfinite(P[sel]).all():
                return None, 0
            Tcw = invert_pose(T)
            rvec, _ = cv2.Rodrigues(Tcw[:3, :3])
            rvec, tvec = cv2.solvePnPRefineLM(P[sel], q[sel], intr.K, None, rvec, Tcw[:3, 3].copy())
            R, _ = cv2.Rodrigues(rvec)
            T = invert_pose(make_pose(R, tvec.ravel()))
        return T, int(sel.sum())

    def _residuals(self, ids, uv, intr, T_world_cam) -> np.ndarray:
        """(N,) reprojection residual of tracks with landmarks (NaN for the others)."""
        r = np.full(len(ids), np.nan)
        have = np.array([int(i) in self.landmarks for i in ids], bool)
        if not have.any():
            return r
        P = np.array([self.landmarks[int(i)] for i in ids[have]])
        proj, z = reproject(T_world_cam, P, intr)
        e = np.hypot(proj[:, 0] - uv[have, 0], proj[:, 1] - uv[have, 1])
        e[~(z > 0)] = np.inf
        r[have] = e
        return r

    def _flag_dynamic(self, ids, residual) -> None:
        """Front-end dynamic test: a static point's residual follows a Cauchy law of scale
        ``dynamic_scale_px``; p_dyn = r^2 / (r^2 + s^2). Two strikes in a row and the track is out."""
        s2 = self.cfg.dynamic_scale_px ** 2
        with np.errstate(invalid="ignore"):
            p = residual ** 2 / (residual ** 2 + s2)
        for i, pi in zip(ids, p):
            if not np.isfinite(pi):
                continue
            i = int(i)
            if pi > self.cfg.dynamic_prob_max:
                self.strikes[i] = self.strikes.get(i, 0) + 1
                if self.strikes[i] >= 2:
                    self.bad.add(i)
                    self.landmarks.pop(i, None)
                    self.drops["tracks_flagged_dynamic"] += 1
            else:
                self.strikes.pop(i, None)

    def _step_track(self, t, gray, ids, uv, intr, mask) -> None:
        t0 = time.perf_counter()
        T_guess = self._predict(t)
        T, n_inl = self._pnp(ids, uv, intr, T_guess)
        if T is None:
            # Lost: keep a pose (extrapolated), remember the speed, start a new map here.
            self.drops["tracking_lost"] += 1
            prev = self._pose_of(t - 1)
            step = np.linalg.norm((invert_pose(self._pose_of(t - 2)) @ prev)[:3, 3]) if t >= 2 else 0.0
            self._speed_hint = step if step > 0 else self._speed_hint
            self.state = "init"
            self._start_init(t, gray, ids, uv, intr, mask, T_guess)
            self._status[t] = EXTRAPOLATED
            self.timings["pose"] += time.perf_counter() - t0
            return
        self._flag_dynamic(ids, self._residuals(ids, uv, intr, T))
        keep = np.array([int(i) not in self.bad for i in ids], bool)
        ids, uv = ids[keep], uv[keep]
        self.timings["pose"] += time.perf_counter() - t0

        last = self.keyframes[self.window[-1]]
        if self._needs_keyframe(t, last, ids, uv, intr, T):
            self._make_keyframe(t, gray, ids, uv, intr, mask, T, n_inl)
        else:
            self._record(t, TRACKED, n_inl, ref=last.frame,
                         T_kf_frame=invert_pose(last.T_world_cam) @ T)

    def _needs_keyframe(self, t, last: _Keyframe, ids, uv, intr, T_world_cam) -> bool:
        if t - last.frame >= self.cfg.keyframe_max_gap:
            return True
        common, i0, i1 = np.intersect1d(last.ids, ids, return_indices=True)
        if len(common) == 0:
            return True
        # Parallax after removing the rotation since the keyframe: a fast pan moves every point
        # but adds no baseline, and keyframes without baseline only add scale drift.
        R = (invert_pose(last.T_world_cam) @ T_world_cam)[:3, :3]
        ang = rotation_parallax_deg(last.uv[i0], uv[i1], last.intr, intr, R)
        parallax_px = np.radians(np.median(ang)) * intr.fx
        lm_last = sum(int(i) in self.landmarks for i in last.ids)
        lm_now = sum(int(i) in self.landmarks for i in common)
        # The floor applies while landmarks are being lost (a pan), not to a scene that simply
        # holds few (a poorly textured room): there it would make every frame a keyframe, and
        # windows without baseline drift in scale.
        falling = lm_now < self.cfg.keyframe_falling * max(lm_last, 1)
        return (parallax_px >= self.cfg.keyframe_parallax_px
                or lm_now < self.cfg.keyframe_min_tracked * max(lm_last, 1)
                or (falling and lm_now < self.cfg.keyframe_min_landmarks))

    # ----------------------------------------------------------------- mapping
    def _make_keyframe(self, t, gray, ids, uv, intr, mask, T_world_cam, n_inl) -> None:
        t0 = time.perf_counter()
        self._triangulate_new(ids, uv, intr, T_world_cam)
        new_ids, new_uv = self._new_points(gray, uv, mask)
        kf = _Keyframe(t, T_world_cam, intr, np.concatenate([ids, new_ids]),
                       np.concatenate([uv, new_uv]), mask)
        self.keyframes[t] = kf
        self.window.append(t)
        self._record(t, KEYFRAME, n_inl, ref=t)
        self.timings["mapping"] += time.perf_counter() - t0
        self._bundle_adjust()
        self._slide_window()

    def _triangulate_new(self, ids, uv, intr, T_world_cam) -> None:
        need = np.array([int(i) not in self.landmarks for i in ids], bool)
        if not need.any() or not self.window:
            return
        todo_ids, todo_uv = ids[need], uv[need]
        # For each track, the oldest window keyframe that saw it gives the widest baseline.
        done = np.zeros(len(todo_ids), bool)
        for k in self.window:
            kf = self.keyframes[k]
            common, ia, ib = np.intersect1d(kf.ids, todo_ids, return_indices=True)
            sel = ~done[ib]
            ia, ib = ia[sel], ib[sel]
            if not len(ib):
                continue
            X, err, ang = triangulate(kf.T_world_cam, T_world_cam, kf.uv[ia], todo_uv[ib], kf.intr, intr)
            good = (err < self.cfg.triangulation_max_error_px) & (ang >= self.cfg.triangulation_min_angle_deg)
            for i, p in zip(todo_ids[ib][good], X[good]):
                self.landmarks[int(i)] = p
            done[ib[good]] = True

    def _bundle_adjust(self) -> None:
        if len(self.window) < 2:
            return
        t0 = time.perf_counter()
        kfs = [self.keyframes[k] for k in self.window]
        anchor = None
        if self._bootstrapping or self.cfg.gauge == "distance":
            # The first window (built on the essential matrix) always takes the minimal gauge:
            # freezing two of its keyframes would freeze any error of the two-view solution.
            fixed = {kfs[0].frame}
            d = float(np.linalg.norm(kfs[1].T_world_cam[:3, 3] - kfs[0].T_world_cam[:3, 3]))
            anchor = (kfs[0].frame, kfs[1].frame, d)
        else:
            fixed = {kf.frame for kf in kfs[:min(self.cfg.fixed_keyframes, len(kfs) - 1)]}
        obs_kf = np.concatenate([np.full(len(kf.ids), kf.frame) for kf in kfs])
        obs_lm = np.concatenate([kf.ids for kf in kfs])
        obs_uv = np.concatenate([kf.uv for kf in kfs])
        have = np.array([int(i) in self.landmarks for i in obs_lm], bool)
        obs_kf, obs_lm, obs_uv = obs_kf[have], obs_lm[have], obs_uv[have]
        lms = {int(i): self.landmarks[int(i)] for i in np.unique(obs_lm)}
        problem = BAProblem(
            poses={kf.frame: kf.T_world_cam for kf in kfs}, fixed=fixed,
            intrinsics={kf.frame: kf.intr for kf in kfs}, landmarks=lms,
            obs_kf=obs_kf, obs_lm=obs_lm, obs_uv=obs_uv,
            masks={kf.frame: kf.mask for kf in kfs if kf.mask is not None}, scale_anchor=anchor)
        refine = self.cfg.refine_focal and self._focal_fixed is None
        res = sliding_window_ba(problem, self.cfg.ba, refine_focal=refine)
        for kf in kfs:
            kf.T_world_cam = res.poses[kf.frame]
        for j in np.unique(obs_lm[res.obs_used]):
            self.landmarks[int(j)] = res.landmarks[int(j)]
        # Landmarks the BA could not explain are dynamic or mistracked: out for good.
        out_lm, counts = np.unique(obs_lm[res.outlier], return_counts=True)
        for j, c in zip(out_lm, counts):
            worst = np.nanmax(res.obs_residual_px[obs_lm == j])
            if c >= 2 or worst > 3 * self.cfg.ba.outlier_px:
                self.bad.add(int(j))
                self.landmarks.pop(int(j), None)
                self.drops["landmarks_rejected_by_ba"] += 1
        for j in res.masked_landmark_ids:
            self.bad.add(int(j))
            self.landmarks.pop(int(j), None)
        self.drops["ba_masked_observations"] += res.masked_observations
        self.drops["ba_masked_landmarks"] += res.masked_landmarks
        if refine and res.focal is not None and len(self.window) >= self.cfg.window_keyframes:
            self._focal_fixed = res.focal
        self.timings["ba"] += time.perf_counter() - t0

    def _slide_window(self) -> None:
        while len(self.window) > self.cfg.window_keyframes:
            old = self.keyframes[self.window.pop(0)]
            # Observations are no longer needed once a keyframe leaves the window; the pose stays.
            old.ids = old.ids[:0]
            old.uv = old.uv[:0]
            old.mask = None
        # Forget landmarks that neither a window keyframe nor a live track refers to.
        live = set(self.tracker.live().ids.tolist())
        keep = self._window_landmark_ids() | live
        for j in [j for j in self.landmarks if j not in keep]:
            del self.landmarks[j]
        self.bad = {j for j in self.bad if j in live or j in keep}
