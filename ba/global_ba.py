"""Global refinement: one bundle adjustment over every keyframe and landmark of a run, in GTSAM.

The VO hands over its whole keyframe graph (:class:`KeyframeGraph`, plain arrays) once the
sliding window has finished; :func:`refine_global` returns refined poses and points.

Variables: ``X(k)`` the pose T_world_cam of keyframe row k (gtsam.Pose3), ``L(j)`` the world
position of landmark row j (Point3), and with ``refine_focal`` ``K(0)``, one focal length shared by
every keyframe (Cal3f; principal points stay as given), with ``refine_centre`` as well one shared
principal point (K(0) a Cal3_S2 with square pixels and zero skew). Factors: one projection factor
per usable observation under the sliding window's robust kernel
(:func:`ba.factors.robust_pixel_noise`), the gauge priors below, and with ``refine_focal`` a weak
prior on f (``focal_prior_ratio``), with ``refine_centre`` one on the principal point
(``centre_prior_frac`` of the image width about where it started).

Same policies as the sliding window (:mod:`ba.sliding_window_ba`):
- masks: an observation flagged ``obs_masked`` is not added, and a landmark observed inside a mask
  in any keyframe is dropped as a whole; both are counted;
- outliers: after the first solve, observations with a residual above ``outlier_px`` are removed
  and the problem is solved again from the first solution, under ``final_kernel`` (Cauchy by
  default: a mover the masks missed then weighs nothing, where Huber's weight only falls as 1/r;
  started from the Huber solution, as in the window, so the non-convex kernel starts near the
  right inliers);
- landmarks with fewer than ``min_observations`` usable observations are left out.

Gauge: monocular BA is free in 7 degrees of freedom (rotation, translation and scale of the
world). Per connected part of the graph (keyframes linked by shared landmarks; a VO that lost
tracking and restarted leaves parts with no landmark in common), the first keyframe's pose is held
by a prior, and the distance from it to the part's farthest keyframe by a distance prior (scale).
That keeps the VO's world frame and scale, without freezing any other keyframe. A keyframe with
too few usable observations to be placed (fewer than ``MIN_POSE_OBSERVATIONS``) is held where the
VO put it, as is every keyframe of a part without baseline (rotation only: its scale is undefined).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import K, L, X
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ba.factors import (add_distance_prior, add_focal_variable, add_projection_factors,
                        levenberg_marquardt, reprojection_errors, robust_pixel_noise,
                        second_stage)
from ba.sliding_window_ba import BAConfig

log = logging.getLogger(__name__)

MIN_POSE_OBSERVATIONS = 6   # a pose has 6 unknowns; with fewer points it is held, not solved
RELATIVE_TOL = 1e-5         # stop when an iteration lowers the cost by less than this share
# Sigma of the scale prior as a share of its distance. The reprojection cost does not change with
# the world's scale, so at the optimum the prior holds exactly whatever its sigma; a stiff one
# (gauge_sigma) would only make every Gauss-Newton step fail on the distance's curvature.
SCALE_PRIOR_SHARE = 1e-2


@dataclass
class KeyframeGraph:
    """Everything the global BA needs, as arrays.

    kf_frames:   (K,) int64 frame index of each keyframe, increasing.
    T_world_cam: (K, 4, 4) float64 camera-to-world pose of each keyframe.
    intrinsics:  (K, 4) float64 fx, fy, cx, cy (px) of each keyframe.
    obs_kf:      (M,) int64 row in the keyframe arrays of each observation.
    obs_lm:      (M,) int64 landmark id (a value of ``lm_ids``; others are ignored).
    obs_uv:      (M, 2) float64 observed pixels x, y.
    obs_masked:  (M,) bool inside a moving-object mask (the graph leaves these out).
    lm_ids:      (L,) int64 landmark ids, unique.
    lm_xyz:      (L, 3) float64 world positions (initial estimate).
    """

    kf_frames: np.ndarray
    T_world_cam: np.ndarray
    intrinsics: np.ndarray
    obs_kf: np.ndarray
    obs_lm: np.ndarray
    obs_uv: np.ndarray
    obs_masked: np.ndarray
    lm_ids: np.ndarray
    lm_xyz: np.ndarray

    def check(self) -> None:
        """Raise ValueError naming the first inconsistent array."""
        n_kf, n_obs, n_lm = len(self.kf_frames), len(self.obs_kf), len(self.lm_ids)
        shapes = {"T_world_cam": (self.T_world_cam, (n_kf, 4, 4)),
                  "intrinsics": (self.intrinsics, (n_kf, 4)),
                  "obs_lm": (self.obs_lm, (n_obs,)), "obs_uv": (self.obs_uv, (n_obs, 2)),
                  "obs_masked": (self.obs_masked, (n_obs,)), "lm_xyz": (self.lm_xyz, (n_lm, 3))}
        for name, (arr, shape) in shapes.items():
            if np.shape(arr) != shape:
                raise ValueError(f"KeyframeGraph.{name} has shape {np.shape(arr)}, expected {shape}")
        if n_obs and (np.min(self.obs_kf) < 0 or np.max(self.obs_kf) >= n_kf):
            raise ValueError("KeyframeGraph.obs_kf refers to a keyframe row outside 0..K-1")
        if len(np.unique(self.lm_ids)) != n_lm:
            raise ValueError("KeyframeGraph.lm_ids are not unique")

    def landmark_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(M,) int64 row in ``lm_ids`` / ``lm_xyz`` of each observation's landmark (0 where it
        has none) and (M,) bool whether it has one."""
        n_lm = len(self.lm_ids)
        if not n_lm:
            return np.zeros(len(self.obs_kf), np.int64), np.zeros(len(self.obs_kf), bool)
        order = np.argsort(self.lm_ids)
        pos = np.minimum(np.searchsorted(self.lm_ids, self.obs_lm, sorter=order), n_lm - 1)
        known = self.lm_ids[order[pos]] == self.obs_lm
        return np.where(known, order[pos], 0).astype(np.int64), known


@dataclass
class GlobalResult:
    """Refined graph. Rows match the :class:`KeyframeGraph` given.

    T_world_cam: (K, 4, 4) float64 refined keyframe poses (held ones unchanged).
    lm_xyz:      (L, 3) float64 refined landmarks (unchanged where ``lm_valid`` is False).
    lm_valid:    (L,) bool landmark was in the final solve (not masked, not an outlier, enough views).
    focal:       the shared focal length (px) with refine_focal, else None.
    centre:      the shared principal point (cx, cy) px with refine_centre, else None.
    rmse_px:     reprojection RMSE of the observations in the final solve, px.
    initial_rmse_px: the same observations before refinement, px.
    n_observations_used: observations in the final solve.
    masked_observations: observations flagged inside a mask (left out).
    masked_landmarks:    landmarks dropped whole because one observation was inside a mask.
    outlier_observations: observations removed after the first solve (residual > outlier_px).
    obs_used:    (M,) bool observation in the final solve.
    held_keyframes: keyframe rows held at the VO's pose (too few observations / no baseline).
    components:  connected parts of the graph, each with its own gauge.
    gauge:       one line per part saying what fixes its gauge.
    iterations:  Levenberg-Marquardt iterations, both solves.
    seconds:     wall time.
    """

    T_world_cam: np.ndarray
    lm_xyz: np.ndarray
    lm_valid: np.ndarray
    focal: float | None
    rmse_px: float
    n_observations_used: int
    masked_observations: int
    masked_landmarks: int
    seconds: float
    initial_rmse_px: float = float("nan")
    outlier_observations: int = 0
    obs_used: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    held_keyframes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    components: int = 0
    gauge: list[str] = field(default_factory=list)
    iterations: int = 0
    centre: tuple[float, float] | None = None


def _rmse(r: np.ndarray) -> float:
    r = r[np.isfinite(r)]
    return float(np.sqrt(np.mean(r ** 2))) if len(r) else float("nan")


def _constrained(obs_lm_row: np.ndarray, usable: np.ndarray, n_lm: int, min_obs: int) -> np.ndarray:
    """Usable observations of landmarks that keep at least ``min_obs`` of them."""
    counts = np.bincount(obs_lm_row[usable], minlength=n_lm)
    return usable & (counts[obs_lm_row] >= min_obs)


def _gauge(T: np.ndarray, obs_kf: np.ndarray, lm_row: np.ndarray, n_lm: int, usable: np.ndarray):
    """Connected parts of the keyframe-landmark graph of the usable observations and, per part,
    what fixes its gauge at the poses T (K, 4, 4). Returns (held keyframe rows as a (K,) bool,
    [(first row, far row, distance)], number of parts, one reason per part)."""
    n_kf = len(T)
    per_kf = np.bincount(obs_kf[usable], minlength=n_kf)
    held = per_kf < MIN_POSE_OBSERVATIONS
    active = np.flatnonzero(~held)
    sel = usable & ~held[obs_kf]
    # Bipartite adjacency keyframes | landmarks; a part is a set of keyframes sharing landmarks.
    adj = coo_matrix((np.ones(sel.sum()), (obs_kf[sel], n_kf + lm_row[sel])),
                     shape=(n_kf + n_lm, n_kf + n_lm))
    _, label = connected_components(adj, directed=False)
    anchors, reasons = [], []
    parts = list(dict.fromkeys(label[active].tolist()))   # in keyframe order
    for p in parts:
        rows = active[label[active] == p]
        first = int(rows[0])
        dist = np.linalg.norm(T[rows, :3, 3] - T[first, :3, 3], axis=1)
        far = int(rows[np.argmax(dist)])
        if len(rows) == 1 or dist.max() <= 1e-9:
            held[rows] = True
            reasons.append(f"keyframes {rows.tolist()[:3]}...: no baseline (rotation only), held")
            continue
        anchors.append((first, far, float(dist.max())))
        reasons.append(f"part of {len(rows)} keyframes: pose of keyframe {first} held, scale by its "
                       f"distance {dist.max():.4g} to keyframe {far}")
    return held, anchors, len(parts), reasons


def _with_centre(intrinsics: np.ndarray, centre) -> np.ndarray:
    """(M, 4) fx, fy, cx, cy rows with the refined principal point, when there is one."""
    if centre is None:
        return intrinsics
    out = np.array(intrinsics, np.float64)
    out[:, 2:4] = centre
    return out


def _solve(g: KeyframeGraph, cfg: BAConfig, usable, lm_row, held, anchors, T0, P0,
           refine_focal: bool, focal_start: float | None, max_iterations: int,
           kernel: str | None = None, refine_centre: bool = False, centre_start=None):
    """One Levenberg-Marquardt solve. Returns (T, P, focal, centre, iterations); focal (px) with
    ``refine_focal``, centre (cx, cy) with ``refine_centre`` as well, else None."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    lm_used = np.unique(lm_row[usable])
    kf_used = np.unique(g.obs_kf[usable])
    refine_centre = refine_centre and refine_focal
    if refine_focal:
        f_guess = float(g.intrinsics[0, 0])
        cx, cy = float(g.intrinsics[0, 2]), float(g.intrinsics[0, 3])
        add_focal_variable(graph, values, focal_start or f_guess, f_guess,
                           cfg.focal_prior_ratio * f_guess, cx, cy,
                           centre_sigma=cfg.centre_prior_frac * 2 * cx if refine_centre else None,
                           centre_start=centre_start)
    for k in kf_used:
        values.insert(X(int(k)), gtsam.Pose3(T0[k]))
    # Gauge and scale: see the module docstring. Held keyframes get the same tight prior.
    gauge = gtsam.noiseModel.Isotropic.Sigma(6, cfg.gauge_sigma)  # rad (rotation first), then m
    anchored = {a[0] for a in anchors}
    inserted = set(kf_used.tolist())
    for k in kf_used:
        if held[k] or int(k) in anchored:
            graph.add(gtsam.PriorFactorPose3(X(int(k)), gtsam.Pose3(T0[k]), gauge))
    for first, far, dist in anchors:
        if far in inserted:
            add_distance_prior(graph, X(far), T0[first, :3, 3], dist, SCALE_PRIOR_SHARE * dist)
    for j in lm_used:
        values.insert(L(int(j)), np.asarray(P0[j], np.float64))
    sel = np.flatnonzero(usable)
    cal_rows, cal_index = np.unique(g.intrinsics[g.obs_kf[sel]], axis=0, return_inverse=True)
    cals = [gtsam.Cal3_S2(r[0], r[1], 0.0, r[2], r[3]) for r in cal_rows]
    noise = robust_pixel_noise(cfg.pixel_sigma, kernel or cfg.robust_kernel, cfg.robust_k)
    add_projection_factors(graph, noise, g.obs_uv[sel], g.obs_kf[sel], lm_row[sel],
                           calibrations=cals, cal_index=cal_index.ravel(), shared_focal=refine_focal,
                           shared_centre=refine_centre)
    T, P = T0.copy(), P0.copy()
    if not len(sel):
        return T, P, focal_start, centre_start, 0
    # Landmarks first (Schur complement), then poses and the focal length.
    ordering = [L(int(j)) for j in lm_used] + [X(int(k)) for k in kf_used] + ([K(0)] if refine_focal else [])
    result, iterations = levenberg_marquardt(graph, values, max_iterations, quiet=refine_focal,
                                             relative_tol=RELATIVE_TOL, diagonal_damping=True,
                                             ordering=ordering)
    for k in kf_used:
        T[k] = result.atPose3(X(int(k))).matrix()
    for j in lm_used:
        P[j] = result.atPoint3(L(int(j)))
    focal = centre = None
    if refine_centre:
        cal = result.atCal3_S2(K(0))
        focal, centre = float(cal.fx()), (float(cal.px()), float(cal.py()))
    elif refine_focal:
        focal = float(result.atCal3f(K(0)).fx())
    return T, P, focal, centre, iterations


def refine_global(graph: KeyframeGraph, config: BAConfig = BAConfig(), *,
                  refine_focal: bool = False, refine_centre: bool = False) -> GlobalResult:
    """One bundle adjustment over all keyframes and landmarks of ``graph`` (see the module
    docstring). ``refine_focal`` frees one focal length shared by all keyframes, starting from
    keyframe 0's fx. The graph is not modified."""
    t0 = time.perf_counter()
    graph.check()
    g = graph
    obs_kf = np.asarray(g.obs_kf, np.int64)
    n_lm = len(g.lm_ids)
    lm_row, known = g.landmark_rows()

    masked_obs = np.asarray(g.obs_masked, bool) & known
    masked_lm = np.zeros(n_lm, bool)
    masked_lm[lm_row[masked_obs]] = True
    T0 = np.asarray(g.T_world_cam, np.float64)
    P0 = np.asarray(g.lm_xyz, np.float64)
    intr_obs = np.asarray(g.intrinsics, np.float64)[obs_kf]
    r0 = reprojection_errors(T0[obs_kf], P0[lm_row], intr_obs, g.obs_uv)
    # Behind a camera or not finite at the start: nothing a projection factor can use.
    usable = known & ~masked_lm[lm_row] & np.isfinite(r0) & np.isfinite(P0[lm_row]).all(axis=1)
    usable = _constrained(lm_row, usable, n_lm, config.min_observations)
    held, anchors, n_parts, reasons = _gauge(T0, obs_kf, lm_row, n_lm, usable)

    focal_guess = float(g.intrinsics[0, 0]) if refine_focal and len(g.intrinsics) else None
    T, P, focal, centre, iterations = _solve(g, config, usable, lm_row, held, anchors, T0, P0,
                                             refine_focal, focal_guess, config.global_max_iterations,
                                             refine_centre=refine_centre)
    n_outliers = 0
    if config.resolve_without_outliers and iterations:
        r = reprojection_errors(T[obs_kf], P[lm_row], _with_centre(intr_obs, centre), g.obs_uv, focal)
        gross = second_stage(usable, r, config)
        if gross is not None:
            n_outliers = int(gross.sum())
            usable = _constrained(lm_row, usable & ~gross, n_lm, config.min_observations)
            # Removing outliers can leave a keyframe too few points: place the gauge again.
            held, anchors, n_parts, reasons = _gauge(T, obs_kf, lm_row, n_lm, usable)
            T, P, focal, centre, more = _solve(g, config, usable, lm_row, held, anchors, T, P,
                                               refine_focal, focal, config.global_max_iterations,
                                               kernel=config.final_kernel,
                                               refine_centre=refine_centre, centre_start=centre)
            iterations += more
    r = reprojection_errors(T[obs_kf], P[lm_row], _with_centre(intr_obs, centre), g.obs_uv, focal)
    lm_valid = np.zeros(n_lm, bool)
    lm_valid[lm_row[usable]] = True
    P[~lm_valid] = P0[~lm_valid]
    res = GlobalResult(
        T_world_cam=T, lm_xyz=P, lm_valid=lm_valid, focal=focal, centre=centre,
        rmse_px=_rmse(r[usable]),
        n_observations_used=int(usable.sum()), masked_observations=int(masked_obs.sum()),
        masked_landmarks=int(masked_lm.sum()), seconds=time.perf_counter() - t0,
        initial_rmse_px=_rmse(r0[usable]), outlier_observations=n_outliers, obs_used=usable,
        held_keyframes=np.flatnonzero(held), components=n_parts, gauge=reasons,
        iterations=iterations)
    log.info("global BA: %d keyframes, %d landmarks, %d observations used (%d masked, %d masked "
             "landmarks, %d outliers), rmse %.3f -> %.3f px, %d iterations, %.2f s%s",
             len(T), int(lm_valid.sum()), res.n_observations_used, res.masked_observations,
             res.masked_landmarks, n_outliers, res.initial_rmse_px, res.rmse_px, iterations,
             res.seconds, f", focal {focal:.1f} px" if focal is not None else "")
    return res
