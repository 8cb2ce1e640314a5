"""The pieces of a bundle-adjustment factor graph shared by the sliding window
(:mod:`ba.sliding_window_ba`) and the global refinement (:mod:`ba.global_ba`): one robust pixel
noise model, one projection factor per observation (fixed per-keyframe calibration, or a shared
``Cal3f`` whose focal length is a variable), the custom focal and distance priors that fix what
GTSAM has no built-in factor for, one vectorised reprojection residual and one Levenberg-Marquardt
call. Everything here takes and returns plain arrays besides the GTSAM graph itself.
"""
from __future__ import annotations

import contextlib
import functools
import os
import sys

import gtsam
import numpy as np
from gtsam.symbol_shorthand import K, L, X


def robust_pixel_noise(pixel_sigma: float, robust_kernel: str, robust_k: float):
    """Noise model of one observation: ``pixel_sigma`` px in u and v, under a Huber or Cauchy
    kernel of width ``robust_k`` sigmas (``none``: plain Gaussian)."""
    pixel = gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma)  # pixel_sigma px in u and v
    if robust_kernel == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(robust_k), pixel)
    if robust_kernel == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(robust_k), pixel)
    return pixel


def focal_prior_error(focal0: float, this: gtsam.CustomFactor, values: gtsam.Values,
                      jacobians: list[np.ndarray] | None) -> np.ndarray:
    """Residual f - focal0 (px) of the shared Cal3f; GTSAM has no PriorFactorCal3f. Cal3f's local
    coordinate is f itself, so the Jacobian is 1."""
    f = values.atCal3f(this.keys()[0]).fx()
    if jacobians is not None:
        jacobians[0] = np.ones((1, 1))
    return np.array([f - focal0])


def distance_error(centre: np.ndarray, distance: float, this: gtsam.CustomFactor,
                   values: gtsam.Values, jacobians: list[np.ndarray] | None) -> np.ndarray:
    """Residual ||t - centre|| - distance (world units) of one Pose3's position: a scale prior.
    With GTSAM's retraction T * Exp([w, v]) the position moves by R v to first order, so the
    Jacobian is [0, 0, 0, u^T R] with u the unit direction from ``centre``."""
    pose = values.atPose3(this.keys()[0])
    d = pose.translation() - centre
    n = float(np.linalg.norm(d))
    if jacobians is not None:
        u = d / max(n, 1e-12)
        jacobians[0] = np.concatenate([np.zeros(3), u @ pose.rotation().matrix()]).reshape(1, 6)
    return np.array([n - distance])


def square_pixel_error(this: gtsam.CustomFactor, values: gtsam.Values,
                       jacobians: list[np.ndarray] | None) -> np.ndarray:
    """Residual fx - fy (px) of a Cal3_S2 (square pixels). Cal3_S2's local coordinates are
    (fx, fy, s, u0, v0) themselves, so the Jacobian is [1, -1, 0, 0, 0]."""
    cal = values.atCal3_S2(this.keys()[0])
    if jacobians is not None:
        jacobians[0] = np.array([[1.0, -1.0, 0.0, 0.0, 0.0]])
    return np.array([cal.fx() - cal.fy()])


def add_focal_variable(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, focal_start: float,
                       focal_prior: float, prior_sigma: float, cx: float, cy: float,
                       centre_sigma: float | None = None, centre_start=None) -> None:
    """Insert the shared ``K(0)`` = Cal3f(focal_start, cx, cy) and a prior f ~ N(focal_prior,
    prior_sigma^2) (px). Without rotation, focal length and depth trade off; the prior keeps f
    near the guess unless the observations clearly say otherwise.

    With ``centre_sigma`` (px) the principal point is freed too: ``K(0)`` is then a Cal3_S2
    (fx = fy held by a stiff factor, skew 0 held by its prior) whose principal point has a prior
    N((cx, cy), centre_sigma^2), starting from ``centre_start`` (default (cx, cy))."""
    if centre_sigma is None:
        values.insert(K(0), gtsam.Cal3f(float(focal_start), float(cx), float(cy)))
        f_noise = gtsam.noiseModel.Isotropic.Sigma(1, float(prior_sigma))  # px
        graph.add(gtsam.CustomFactor(f_noise, [K(0)], functools.partial(focal_prior_error, float(focal_prior))))
        return
    u0, v0 = (cx, cy) if centre_start is None else centre_start
    f0 = float(focal_start)
    values.insert(K(0), gtsam.Cal3_S2(f0, f0, 0.0, float(u0), float(v0)))
    sig = np.array([prior_sigma, prior_sigma, 1e-6, centre_sigma, centre_sigma], np.float64)
    graph.add(gtsam.PriorFactorCal3_S2(K(0), gtsam.Cal3_S2(float(focal_prior), float(focal_prior),
                                                           0.0, float(cx), float(cy)),
                                       gtsam.noiseModel.Diagonal.Sigmas(sig)))
    graph.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 1e-3), [K(0)],
                                 square_pixel_error))


def add_distance_prior(graph: gtsam.NonlinearFactorGraph, key: int, centre: np.ndarray,
                       distance: float, sigma: float) -> None:
    """The scale gauge: pose ``key`` stays ``distance`` (world units, sigma likewise) from ``centre``."""
    noise = gtsam.noiseModel.Isotropic.Sigma(1, float(sigma))  # world units
    graph.add(gtsam.CustomFactor(noise, [key], functools.partial(
        distance_error, np.asarray(centre, np.float64).copy(), float(distance))))


def add_projection_factors(graph: gtsam.NonlinearFactorGraph, noise, obs_uv: np.ndarray,
                           pose_ids: np.ndarray, lm_ids: np.ndarray, *,
                           calibrations: list | None = None, cal_index: np.ndarray | None = None,
                           shared_focal: bool = False, shared_centre: bool = False) -> None:
    """One projection factor X(pose_ids[i]) -- L(lm_ids[i]) per observation (obs_uv: (M, 2)
    float64 pixels x, y). With ``shared_focal`` the factors also connect the shared Cal3f K(0);
    otherwise observation i uses the fixed ``calibrations[cal_index[i]]`` (gtsam.Cal3_S2)."""
    uv = list(np.asarray(obs_uv, np.float64))
    # The keys as X(k) and L(j) make them, for all observations at once: a window adds
    # thousands of factors, and the per-factor Python calls were a quarter of its cost.
    xs, ls = symbol_keys("x", pose_ids), symbol_keys("l", lm_ids)
    add = graph.add
    if shared_focal and shared_centre:
        factor, k0 = gtsam.GeneralSFMFactor2Cal3_S2, K(0)
        for u, x, lm in zip(uv, xs, ls):
            add(factor(u, noise, x, lm, k0))
        return
    if shared_focal:
        factor, k0 = gtsam.GeneralSFMFactor2Cal3f, K(0)
        for u, x, lm in zip(uv, xs, ls):
            add(factor(u, noise, x, lm, k0))
        return
    factor = gtsam.GenericProjectionFactorCal3_S2
    cals = [calibrations[int(c)] for c in np.asarray(cal_index)]
    for u, x, lm, cal in zip(uv, xs, ls, cals):
        add(factor(u, noise, x, lm, cal))


def symbol_keys(char: str, indices: np.ndarray) -> list[int]:
    """GTSAM's keys ``gtsam.symbol(char, i)`` of many indices (the character in the top byte,
    the index below: what ``X(i)`` and ``L(i)`` return), as Python ints."""
    idx = np.asarray(indices, np.int64).ravel()
    if len(idx) and (idx.min() < 0 or idx.max() >= 1 << 56):
        raise ValueError(f"symbol indices must lie in [0, 2^56): {idx.min()}..{idx.max()}")
    return ((ord(char) << 56) + idx.astype(np.uint64)).tolist()


def second_stage(usable: np.ndarray, residual_px: np.ndarray, cfg) -> np.ndarray | None:
    """The observations to leave out of a second solve, or None when there is none to run.

    A robust kernel still feels gross outliers (a dragged track, a mover the masks missed): what
    the first solve cannot explain (residual above ``cfg.outlier_px``, or not finite) is removed
    and the problem solved again, from the first solution, under ``cfg.final_kernel``. Convex
    first, redescending second (graduated non-convexity in two steps): Cauchy's weight falls to
    zero for a mover's point where Huber's only falls as 1 / r, but started from a poor initial
    guess it can settle on the wrong inliers (generated fast rotation without masks, mixed seed
    107: 12.4 % of path with Cauchy alone, 2.0 % Huber alone, 2.4 % Huber then Cauchy). So the
    second solve runs whenever there are outliers or the final kernel differs from the first.
    Both bundle adjustments (window and global) follow this one rule."""
    gross = np.asarray(usable, bool) & ~(np.asarray(residual_px) <= cfg.outlier_px)
    if gross.any() or cfg.final_kernel != cfg.robust_kernel:
        return gross
    return None


@contextlib.contextmanager
def quiet_native_stdout():
    """GTSAM's GeneralSFMFactor2 prints a line to C++ stdout for every landmark behind a camera
    during Levenberg-Marquardt (its residual is then zeroed); those lines must not reach users."""
    sys.stdout.flush()
    saved = os.dup(1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def levenberg_marquardt(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                        max_iterations: int, *, quiet: bool = False,
                        relative_tol: float = 1e-4,
                        diagonal_damping: bool = False,
                        ordering: list[int] | None = None) -> tuple[gtsam.Values, int]:
    """Solve with Levenberg-Marquardt; returns (values, iterations). ``quiet`` silences the
    cheirality lines of GeneralSFMFactor2 (see :func:`quiet_native_stdout`).
    ``diagonal_damping`` damps by lambda * diag(J^T J) instead of lambda * I (as Ceres does): the
    step then scales with each variable's own units (rad, m, px of focal length), which a whole
    trajectory with a focal length far from its guess needs; with lambda * I the first steps
    overshoot and lambda hits its bound before any step is accepted. ``ordering``: elimination
    order of the keys (landmarks first is the Schur complement of BA: each point is eliminated
    alone, leaving the small camera system), else GTSAM's COLAMD."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    params.setRelativeErrorTol(relative_tol)
    params.setDiagonalDamping(bool(diagonal_damping))
    if ordering is not None:
        order = gtsam.Ordering()
        for key in ordering:
            order.push_back(int(key))
        params.setOrdering(order)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    with quiet_native_stdout() if quiet else contextlib.nullcontext():
        result = optimizer.optimize()
    return result, int(optimizer.iterations())


def reprojection_errors(T_world_cam: np.ndarray, points_world: np.ndarray, intrinsics: np.ndarray,
                        obs_uv: np.ndarray, focal: float | None = None) -> np.ndarray:
    """(M,) float64 reprojection error in px of M observations, vectorised.

    T_world_cam: (M, 4, 4) pose of each observation's camera; points_world: (M, 3) its landmark;
    intrinsics: (M, 4) fx, fy, cx, cy (px); obs_uv: (M, 2) observed pixels x, y. ``focal``
    overrides fx and fy (shared-focal refinement). Points at or behind a camera get inf.
    """
    R = T_world_cam[:, :3, :3]
    d = np.asarray(points_world, np.float64) - T_world_cam[:, :3, 3]
    Xc = np.einsum("mji,mj->mi", R, d)   # R^T (p - t): camera-frame point
    fx = intrinsics[:, 0] if focal is None else np.full(len(Xc), float(focal))
    fy = intrinsics[:, 1] if focal is None else fx
    z = Xc[:, 2]
    ok = z > 1e-9
    zs = np.where(ok, z, 1.0)
    u = fx * Xc[:, 0] / zs + intrinsics[:, 2]
    v = fy * Xc[:, 1] / zs + intrinsics[:, 3]
    e = np.hypot(u - obs_uv[:, 0], v - obs_uv[:, 1])
    e[~ok] = np.inf
    return e
