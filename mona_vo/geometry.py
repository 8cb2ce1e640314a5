"""Geometry shared by the VO and MONA, written once: the essential-matrix estimator, the Cauchy
dynamic probability and the reprojection residual.

Essential matrix
    OpenCV's USAC_ACCURATE (GC-RANSAC with local optimisation), fixed seed inside OpenCV's
    UsacParams, so fits are reproducible. Chosen for both users because it keeps the background
    under a mover carrying a quarter of the points, where MAGSAC++ settled between the two (see
    :mod:`mona_vo.dynamic_points`).

Dynamic probability
    The MONA paper's product of an x and a y Cauchy term, normalised by its peak:
    ``p = 1 - 1 / ((1 + (rx / s)^2) (1 + (ry / s)^2))`` for a residual vector (rx, ry) of a point
    whose static residual has Cauchy scale s. p = 0 at zero residual; NaN residuals give 0.

Reprojection
    ``reprojection_residuals(T_world_cam, X, uv, intr)``: (N, 2) observed minus projected pixels,
    NaN behind the camera; built on :func:`mona_vo.conventions.reproject`.

Local affine map of a homography
    ``homography_jacobians(H, uv)``: how H turns, scales and shears a small patch around each
    pixel (for ``K_b R K_a^-1``, a camera's turn): the patch checks and fits of the VO.

Similarity alignment
    Umeyama's closed form (1991) for the scale, rotation and translation that best map one set
    of 3-D points onto another: what evo's Sim(3) alignment computes, for the VO's own
    consistency check (no ground truth) and for drawing.
"""
from __future__ import annotations

import cv2
import numpy as np

from mona_vo.conventions import Intrinsics, reproject

ESSENTIAL_METHOD = cv2.USAC_ACCURATE


def find_essential(pts_a: np.ndarray, pts_b: np.ndarray, K: np.ndarray, threshold: float,
                   confidence: float = 0.999, method: int = ESSENTIAL_METHOD
                   ) -> tuple[np.ndarray | None, np.ndarray]:
    """Robust essential matrix of (N, 2) matched points with x_b^T E x_a = 0.

    K: 3x3 calibration of the points' units (identity for normalised coordinates, then
    ``threshold`` is in those units too). Returns (E 3x3 or None, (N,) bool inliers)."""
    pa = np.ascontiguousarray(pts_a, np.float64).reshape(-1, 2)
    pb = np.ascontiguousarray(pts_b, np.float64).reshape(-1, 2)
    if len(pa) < 5:
        return None, np.zeros(len(pa), bool)
    E, inl = cv2.findEssentialMat(pa, pb, np.asarray(K, np.float64), method, confidence,
                                  float(threshold))
    if E is None or E.shape[0] < 3 or E.shape[1] != 3 or inl is None:
        return None, np.zeros(len(pa), bool)
    return E[:3], inl.ravel() > 0


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between 3-vectors a and b ((3,) or (N, 3), either may be broadcast),
    whatever their lengths; NaN where either is zero or not finite. atan2 of the sine and the
    cosine: exact near 0 and 180 deg, where arccos of a normalised dot product is not."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    sine = np.linalg.norm(np.cross(a, b), axis=-1)
    cosine = np.sum(a * b, axis=-1)
    zero = (np.linalg.norm(a, axis=-1) == 0) | (np.linalg.norm(b, axis=-1) == 0)
    return np.where(zero, np.nan, np.degrees(np.arctan2(sine, cosine)))


def homogeneous(p: np.ndarray) -> np.ndarray:
    """(N, 3) float64 homogeneous coordinates [x, y, 1] of (N, 2) pixels."""
    p = np.asarray(p, np.float64).reshape(-1, 2)
    return np.concatenate([p, np.ones((len(p), 1))], axis=1)


def sampson_residuals(F_b_a: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """(N, 2) float64 signed Sampson distance times the unit normal of the epipolar line
    ``F x_a`` in image b, pixels: the first-order deviation of (x_a, x_b) from the epipolar
    constraint, as a vector across the epipolar line. pts_a, pts_b: (N, 2) pixels."""
    F = np.asarray(F_b_a, np.float64)
    xa, xb = homogeneous(pts_a), homogeneous(pts_b)
    Fxa = xa @ F.T            # epipolar lines in b
    Ftxb = xb @ F             # epipolar lines in a
    num = np.sum(xb * Fxa, axis=1)
    den = Fxa[:, 0] ** 2 + Fxa[:, 1] ** 2 + Ftxb[:, 0] ** 2 + Ftxb[:, 1] ** 2
    d = num / np.sqrt(np.maximum(den, 1e-300))
    normal = Fxa[:, :2] / np.maximum(np.linalg.norm(Fxa[:, :2], axis=1)[:, None], 1e-300)
    return d[:, None] * normal


def cauchy_dynamic_probability(residual_xy: np.ndarray, scale: float) -> np.ndarray:
    """(N,) float64 ``1 - 1 / ((1 + (rx/scale)^2) (1 + (ry/scale)^2))`` of (N, 2) residual
    vectors; NaN residuals give probability 0, infinite ones 1."""
    r = np.nan_to_num(np.asarray(residual_xy, np.float64).reshape(-1, 2), nan=0.0,
                      posinf=1e12, neginf=-1e12) / float(scale)
    return 1.0 - 1.0 / ((1.0 + r[:, 0] ** 2) * (1.0 + r[:, 1] ** 2))


def reprojection_residuals(T_world_cam: np.ndarray, points_world: np.ndarray,
                           pixels: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 2) float64 observed minus projected pixels of world points (N, 3) seen at (N, 2)
    pixels from T_world_cam; rows of points at or behind the camera are NaN."""
    proj, z = reproject(T_world_cam, points_world, intr)
    r = np.asarray(pixels, np.float64) - proj
    r[~(z > 1e-9)] = np.nan
    return r


def reprojection_errors(T_world_cam: np.ndarray, points_world: np.ndarray, pixels: np.ndarray,
                        intr: Intrinsics) -> np.ndarray:
    """(N,) float64 reprojection error norms in pixels; inf behind the camera."""
    e = np.linalg.norm(reprojection_residuals(T_world_cam, points_world, pixels, intr), axis=1)
    e[~np.isfinite(e)] = np.inf
    return e


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R (3, 3) and translation t (3,) minimising the summed squared distance
    from s R src_i + t to dst_i over (N, 3) points (Umeyama 1991). A set with no spread maps
    with scale 1."""
    a, b = np.asarray(src, np.float64).reshape(-1, 3), np.asarray(dst, np.float64).reshape(-1, 3)
    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    a0, b0 = a - mu_a, b - mu_b
    U, S, Vt = np.linalg.svd(b0.T @ a0 / len(a))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var = float((a0 ** 2).sum()) / len(a)
    s = float(np.trace(np.diag(S) @ D)) / var if var > 0 else 1.0
    return s, R, mu_b - s * R @ mu_a


def aligned_rms(src: np.ndarray, dst: np.ndarray) -> float:
    """RMS distance between (N, 3) points dst and src mapped onto them by
    :func:`align_similarity`, in dst's units."""
    a, b = np.asarray(src, np.float64).reshape(-1, 3), np.asarray(dst, np.float64).reshape(-1, 3)
    s, R, t = align_similarity(a, b)
    return float(np.sqrt(np.mean(np.sum((s * a @ R.T + t - b) ** 2, axis=1))))


def homography_jacobians(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 2, 2) derivative of the homography ``H`` (3, 3) at the (N, 2) pixels ``uv``: the
    affine map it applies to a small patch around each point."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    h = np.c_[uv, np.ones(len(uv))] @ np.asarray(H, np.float64).T
    return (H[None, :2, :2] * h[:, 2, None, None]
            - h[:, :2, None] * H[None, 2:3, :2]) / h[:, 2, None, None] ** 2
