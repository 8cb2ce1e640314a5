"""Sliding-window bundle adjustment as a GTSAM factor graph, blind to moving objects.

Variables: ``X(k)`` the pose T_world_cam of window keyframe k (gtsam.Pose3), ``L(j)`` the world
position of landmark j (Point3), and, when a shared focal length is refined, ``K(0)`` (Cal3f).
Factors: one projection factor per observation with a robust kernel (Huber or Cauchy) on the
pixel residual; a prior on every *fixed* keyframe.

Gauge: monocular BA is free in 7 degrees of freedom (rotation, translation and scale of the
world). The caller fixes the oldest keyframe(s) of the window with priors; with a single fixed
keyframe, ``scale_anchor`` holds the distance from it to one more keyframe (a custom factor),
which removes the last degree of freedom without freezing that keyframe's direction of travel.
The fixed poses carry the world frame and scale that earlier windows established, so consecutive
windows agree. Keyframes that left the window are never touched again (the LEAP-VO/DPVO
fixed-lag scheme, instead of a marginal prior).

Masks: a per-keyframe boolean moving-object mask, or a per-observation flag (``obs_masked``, what
the VO passes: its tracks know whether they were inside a mask), may be given. An observation
inside a mask is not added, and a landmark observed inside a mask in *any* keyframe of the window
is dropped as a whole (its other observations are not added either). :class:`BAResult` counts
both.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import K, L, X

from ba.factors import (add_distance_prior, add_focal_variable, add_projection_factors,
                        distance_error, focal_prior_error, levenberg_marquardt, reprojection_errors,
                        robust_pixel_noise, second_stage)
from mona_vo.config import check_fields, setting
from mona_vo.conventions import Intrinsics, camera_depths, pixels_in_mask

__all__ = ["BAConfig", "BAProblem", "BAResult", "sliding_window_ba", "observations_in_masks",
           "reprojection_residuals", "focal_prior_error", "distance_error"]


@dataclass(frozen=True)
class BAConfig:
    pixel_sigma: float = setting(1.0, gt=0)  # px; standard deviation of a tracked point's position
    robust_kernel: str = setting("huber", choices=("huber", "cauchy", "none"))  # on the whitened
                                     # pixel residual (first solve of the window and of the
                                     # global refinement)
    final_kernel: str = setting("cauchy", choices=("huber", "cauchy", "none"))  # their second
                                     # solves, started from the first's solution
    robust_k: float = setting(1.5, gt=0)  # kernel width in sigmas (Huber's k, Cauchy's c)
    max_iterations: int = setting(8, ge=1)  # Levenberg-Marquardt iterations per window solve
    outlier_px: float = setting(3.0, gt=0)  # after solving, residuals above this are reported
                                     # outliers, px
    gauge_sigma: float = setting(1e-6, gt=0)  # rad and m; prior sigma that holds fixed keyframes
                                     # in place
    min_observations: int = setting(2, ge=2)  # landmarks with fewer usable observations are
                                     # left out
    focal_prior_ratio: float = setting(0.3, gt=0)  # with refine_focal: 1-sigma prior on f as a
                                     # fraction of f
    centre_prior_frac: float = setting(0.02, gt=0)  # with refine_centre (global refinement):
                                     # 1-sigma prior on the principal point's offset from where
                                     # it started, fraction of the image width (2 cx)
    resolve_without_outliers: bool = setting(True)  # second solve without observations > outlier_px
    min_depth_ratio: float = setting(1e-3, ge=0, lt=1)  # a landmark nearer to a window camera
                                     # than this x the window's median depth (or behind it) is
                                     # left out (degenerate: see _degenerate_landmarks)
    global_max_iterations: int = setting(30, ge=1)  # Levenberg-Marquardt iterations per
                                     # global-refinement solve

    def validate(self) -> None:
        check_fields(self, "vo.ba.")


@dataclass
class BAProblem:
    """One window's bundle-adjustment problem (plain arrays; nothing here is GTSAM).

    poses:        keyframe id -> 4x4 T_world_cam initial estimate.
    fixed:        keyframe ids held fixed (gauge and scale); must be keys of ``poses``.
    intrinsics:   keyframe id -> Intrinsics (per keyframe; shared focal only with refine_focal).
    landmarks:    landmark id -> (3,) world position initial estimate.
    obs_kf, obs_lm: (M,) int64 keyframe / landmark id of each observation.
    obs_uv:       (M, 2) float64 observed pixels x, y.
    masks:        keyframe id -> (H, W) bool moving-object mask (optional per keyframe).
    scale_anchor: optional (fixed keyframe id, other keyframe id, distance in world units).
    obs_masked:   optional (M,) bool, observations known to lie inside a moving-object mask
                  (the caller's per-observation flags; left out as the masks' are).
    """

    poses: dict[int, np.ndarray]
    fixed: set[int]
    intrinsics: dict[int, Intrinsics]
    landmarks: dict[int, np.ndarray]
    obs_kf: np.ndarray
    obs_lm: np.ndarray
    obs_uv: np.ndarray
    masks: dict[int, np.ndarray] = field(default_factory=dict)
    scale_anchor: tuple[int, int, float] | None = None
    obs_masked: np.ndarray | None = None


@dataclass
class BAResult:
    """Solved window. Residuals are reprojection errors in pixels after the solve (NaN for
    observations that were not in the graph)."""

    poses: dict[int, np.ndarray]
    landmarks: dict[int, np.ndarray]
    focal: float | None
    obs_used: np.ndarray
    obs_residual_px: np.ndarray
    outlier: np.ndarray
    masked_observations: int
    masked_landmark_ids: np.ndarray
    initial_rmse_px: float
    final_rmse_px: float
    iterations: int
    seconds: float
    degenerate_landmark_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def masked_landmarks(self) -> int:
        return int(len(self.masked_landmark_ids))


def observations_in_masks(obs_kf: np.ndarray, obs_uv: np.ndarray,
                          masks: dict[int, np.ndarray]) -> np.ndarray:
    """(M,) bool: observation lies on a True pixel of its keyframe's mask (nearest pixel centre)."""
    inside = np.zeros(len(obs_kf), bool)
    for kf, mask in masks.items():
        if mask is None:
            continue
        sel = np.flatnonzero(obs_kf == kf)
        if len(sel):
            inside[sel] = pixels_in_mask(mask, obs_uv[sel])
    return inside


def reprojection_residuals(poses: dict[int, np.ndarray], landmarks: dict[int, np.ndarray],
                           intrinsics: dict[int, Intrinsics], obs_kf: np.ndarray,
                           obs_lm: np.ndarray, obs_uv: np.ndarray,
                           focal: float | None = None) -> np.ndarray:
    """(M,) reprojection error in px of each observation (inf behind the camera, NaN when its
    landmark or keyframe is unknown): :func:`ba.factors.reprojection_errors`, the global
    refinement's, on the window's tables read per observation."""
    obs_kf = np.asarray(obs_kf, np.int64).reshape(-1)
    res = np.full(len(obs_kf), np.nan)
    T, have_kf = _gather(poses, obs_kf)
    xyz, have_lm = _gather(landmarks, obs_lm)
    cam, _ = _gather({k: (c.fx, c.fy, c.cx, c.cy) for k, c in intrinsics.items()}, obs_kf)
    sel = have_kf & have_lm
    if sel.any():
        res[sel] = reprojection_errors(T[sel], xyz[sel], cam[sel],
                                       np.asarray(obs_uv, np.float64).reshape(-1, 2)[sel], focal)
    return res


def _gather(table: dict[int, np.ndarray], keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``table[keys[i]]`` for all i at once, float64 (M, ...), and (M,) bool whether the key
    is in the table (rows where it is not hold another entry's value). A window reads its
    poses and landmarks per observation, thousands of times; one dict read each was most of
    the Python the window spent outside GTSAM."""
    keys = np.asarray(keys, np.int64).reshape(-1)
    if not table:
        return np.full((len(keys), 3), np.nan), np.zeros(len(keys), bool)
    ids = np.fromiter(table, np.int64, len(table))
    order = np.argsort(ids)
    values = np.array(list(table.values()), np.float64)[order]
    ids = ids[order]
    row = np.minimum(np.searchsorted(ids, keys), len(ids) - 1)
    return values[row], ids[row] == keys


def _constrained(obs_kf, obs_lm, usable, free_kf, min_observations):
    """Keep landmarks with enough observations, one of them in a free keyframe: any other
    landmark is unconstrained or only adds cost. Returns (usable mask, kept landmark ids)."""
    lm_ids, counts = np.unique(obs_lm[usable], return_counts=True)
    lm_free = np.unique(obs_lm[usable & np.isin(obs_kf, free_kf)])
    keep_lm = lm_ids[(counts >= min_observations) & np.isin(lm_ids, lm_free)]
    return usable & np.isin(obs_lm, keep_lm), keep_lm


def _degenerate_landmarks(problem: BAProblem, usable: np.ndarray, min_ratio: float) -> np.ndarray:
    """Ids of landmarks that lie behind a window camera that sees them, or nearer to it than
    ``min_ratio`` times the median depth of the window's observations. Such a point's
    projection Jacobian grows as 1 / depth: one landmark at 1e-6 of the median depth (left
    there by earlier windows, Bonn crowd) made J^T J about 1e13, no Levenberg-Marquardt step
    below GTSAM's damping bound reduced the error, and the window was returned unsolved
    (0 iterations, 40 px RMSE) four windows in a row."""
    sel = np.flatnonzero(usable)
    if not len(sel) or min_ratio <= 0:
        return np.zeros(0, np.int64)
    z = camera_depths(_gather(problem.poses, problem.obs_kf[sel])[0],
                      _gather(problem.landmarks, problem.obs_lm[sel])[0])
    ahead = z[z > 0]
    if not len(ahead):
        return np.unique(problem.obs_lm[sel])
    bad = z <= min_ratio * float(np.median(ahead))
    return np.unique(problem.obs_lm[sel][bad])


def _solve(problem: BAProblem, cfg: BAConfig, usable: np.ndarray, keep_lm: np.ndarray,
           refine_focal: bool, focal_start: float | None = None, kernel: str | None = None):
    """Build the factor graph of the usable observations and run Levenberg-Marquardt.
    ``kernel``: the robust kernel (default ``cfg.robust_kernel``).
    Returns (poses, landmarks, focal, iterations)."""
    obs_kf, obs_lm, obs_uv = problem.obs_kf, problem.obs_lm, problem.obs_uv
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    kf_ids = sorted(problem.poses)
    intr0 = problem.intrinsics[kf_ids[0]]
    focal0 = (focal_start or intr0.fx) if refine_focal else None
    if refine_focal:
        add_focal_variable(graph, values, focal0, intr0.fx, cfg.focal_prior_ratio * intr0.fx,
                           intr0.cx, intr0.cy)
    for k in kf_ids:
        values.insert(X(k), gtsam.Pose3(problem.poses[k]))
    gauge = gtsam.noiseModel.Isotropic.Sigma(6, cfg.gauge_sigma)  # rad (rotation first), then m
    for k in sorted(problem.fixed):
        graph.add(gtsam.PriorFactorPose3(X(k), gtsam.Pose3(problem.poses[k]), gauge))
    if problem.scale_anchor is not None:
        ka, kb, dist = problem.scale_anchor
        add_distance_prior(graph, X(kb), problem.poses[ka][:3, 3], dist, cfg.gauge_sigma)
    for j in keep_lm:
        values.insert(L(int(j)), np.asarray(problem.landmarks[int(j)], np.float64))
    sel = np.flatnonzero(usable)
    cal_keys = sorted(problem.intrinsics)
    cals = [gtsam.Cal3_S2(problem.intrinsics[k].fx, problem.intrinsics[k].fy, 0.0,
                          problem.intrinsics[k].cx, problem.intrinsics[k].cy) for k in cal_keys]
    cal_index = np.searchsorted(cal_keys, obs_kf[sel])
    noise = robust_pixel_noise(cfg.pixel_sigma, kernel or cfg.robust_kernel, cfg.robust_k)
    add_projection_factors(graph, noise, obs_uv[sel], obs_kf[sel], obs_lm[sel],
                           calibrations=cals, cal_index=cal_index, shared_focal=refine_focal)
    poses, landmarks = dict(problem.poses), dict(problem.landmarks)
    if not len(keep_lm):
        return poses, landmarks, focal0, 0
    result, iterations = levenberg_marquardt(graph, values, cfg.max_iterations, quiet=refine_focal)
    for k in kf_ids:
        poses[k] = result.atPose3(X(k)).matrix()
    for j in keep_lm:
        landmarks[int(j)] = result.atPoint3(L(int(j)))
    focal = float(result.atCal3f(K(0)).fx()) if refine_focal else None
    return poses, landmarks, focal, iterations


def sliding_window_ba(problem: BAProblem, cfg: BAConfig = BAConfig(), *,
                      refine_focal: bool = False) -> BAResult:
    """Solve one window. ``refine_focal`` estimates one focal length shared by all keyframes
    (principal points stay as given), starting from the first keyframe's fx."""
    t0 = time.perf_counter()
    obs_kf = np.asarray(problem.obs_kf, np.int64)
    obs_lm = np.asarray(problem.obs_lm, np.int64)
    obs_uv = np.asarray(problem.obs_uv, np.float64)
    in_window = np.isin(obs_kf, list(problem.poses)) & np.isin(obs_lm, list(problem.landmarks))

    masked_obs = observations_in_masks(obs_kf, obs_uv, problem.masks)
    if problem.obs_masked is not None:
        masked_obs |= np.asarray(problem.obs_masked, bool)
    masked_obs &= in_window
    masked_lms = np.unique(obs_lm[masked_obs])
    usable = in_window & ~np.isin(obs_lm, masked_lms)
    degenerate = _degenerate_landmarks(problem, usable, cfg.min_depth_ratio)
    usable &= ~np.isin(obs_lm, degenerate)
    free_kf = np.array([k for k in problem.poses if k not in problem.fixed], np.int64)
    usable, keep_lm = _constrained(obs_kf, obs_lm, usable, free_kf, cfg.min_observations)

    res0 = reprojection_residuals(problem.poses, problem.landmarks, problem.intrinsics,
                                  obs_kf[usable], obs_lm[usable], obs_uv[usable],
                                  problem.intrinsics[min(problem.poses)].fx if refine_focal else None)
    poses, landmarks, focal, iterations = _solve(problem, cfg, usable, keep_lm, refine_focal)
    if cfg.resolve_without_outliers and iterations:
        r = reprojection_residuals(poses, landmarks, problem.intrinsics, obs_kf, obs_lm, obs_uv, focal)
        gross = second_stage(usable, r, cfg)
        if gross is not None:
            usable, keep_lm = _constrained(obs_kf, obs_lm, usable & ~gross, free_kf,
                                           cfg.min_observations)
            warm = BAProblem(poses, problem.fixed, problem.intrinsics, landmarks, obs_kf, obs_lm,
                             obs_uv, scale_anchor=problem.scale_anchor)
            poses, landmarks, focal, more = _solve(warm, cfg, usable, keep_lm, refine_focal,
                                                   focal_start=focal, kernel=cfg.final_kernel)
            iterations += more
            usable_final = usable | gross
        else:
            usable_final = usable
    else:
        usable_final = usable

    res = np.full(len(obs_kf), np.nan)
    res[usable_final] = reprojection_residuals(poses, landmarks, problem.intrinsics,
                                               obs_kf[usable_final], obs_lm[usable_final],
                                               obs_uv[usable_final], focal)

    def rmse(r):
        r = r[np.isfinite(r)]
        return float(np.sqrt(np.mean(r ** 2))) if len(r) else float("nan")

    return BAResult(
        poses=poses, landmarks=landmarks, focal=focal, obs_used=usable, obs_residual_px=res,
        outlier=usable_final & ~(res <= cfg.outlier_px),
        masked_observations=int(masked_obs.sum()), masked_landmark_ids=masked_lms,
        initial_rmse_px=rmse(res0), final_rmse_px=rmse(res[usable]), iterations=iterations,
        seconds=time.perf_counter() - t0, degenerate_landmark_ids=degenerate)
