"""Two-view geometry for initialisation and mapping: relative pose from an essential matrix
(:func:`mona_vo.geometry.find_essential`, the estimator MONA uses too), triangulation, a
rotation-only fit for footage without parallax, and the homography-transfer parallax that tells
the two apart without trusting the focal length.

Points are matched pixel arrays (N, 2); they are normalised with each view's intrinsics first,
so the two views may have different calibrations (Sintel's focal length changes per frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.conventions import Intrinsics, invert_pose, make_pose, reproject
from mona_vo.geometry import angle_between_deg, find_essential, sampson_residuals


def normalize(pixels: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 2) float64 normalised image coordinates ((x - cx) / fx, (y - cy) / fy)."""
    p = np.asarray(pixels, np.float64)
    return np.stack([(p[:, 0] - intr.cx) / intr.fx, (p[:, 1] - intr.cy) / intr.fy], axis=1)


def bearings(pixels: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """(N, 3) unit rays in the camera frame."""
    n = normalize(pixels, intr)
    b = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


@dataclass(frozen=True)
class RelativePose:
    """Result of :func:`relative_pose`.

    T_a_b:        4x4 pose of view b in view a's frame; translation has unit norm (scale unknown).
    inliers:      (N,) bool, points consistent with the essential matrix and in front of both views.
    parallax_deg: (N,) angle between the two rays of each point after removing the rotation.
    """

    T_a_b: np.ndarray
    inliers: np.ndarray
    parallax_deg: np.ndarray

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())

    @property
    def median_parallax_deg(self) -> float:
        p = self.parallax_deg[self.inliers]
        return float(np.median(p)) if len(p) else 0.0


def relative_pose(pts_a: np.ndarray, pts_b: np.ndarray, intr_a: Intrinsics, intr_b: Intrinsics,
                  *, threshold_px: float = 1.0, confidence: float = 0.999) -> RelativePose | None:
    """Relative pose of view b w.r.t. view a from >= 8 matched pixels; None when RANSAC fails."""
    if len(pts_a) < 8:
        return None
    na, nb = normalize(pts_a, intr_a), normalize(pts_b, intr_b)
    f = 0.5 * (intr_a.fx + intr_a.fy + intr_b.fx + intr_b.fy) / 2.0
    E, inl = find_essential(na, nb, np.eye(3), threshold_px / f, confidence)
    if E is None:
        return None
    mask = inl.astype(np.uint8).reshape(-1, 1)
    # The short overload of recoverPose drops points beyond 50 baselines as if they were
    # outliers; with the small parallax of consecutive video frames that is most of them.
    _, R, t, mask_pose, _ = cv2.recoverPose(E, na, nb, np.eye(3), distanceThresh=1e9,
                                             mask=mask.copy())
    # recoverPose gives x_b = R x_a + t, i.e. T_b_a.
    T_a_b = invert_pose(make_pose(R, t.ravel() / max(np.linalg.norm(t), 1e-12)))
    inliers = mask_pose.ravel() > 0
    return RelativePose(T_a_b, inliers,
                        rotation_parallax_deg(pts_a, pts_b, intr_a, intr_b, T_a_b[:3, :3]))


def tighten_relative_pose(first: RelativePose, pts_a: np.ndarray, pts_b: np.ndarray,
                          intr_a: Intrinsics, intr_b: Intrinsics, *, scales: int,
                          threshold_px: float = 1.0) -> RelativePose:
    """The relative pose that explains the matches best at three times their own noise, from
    ``first`` (:func:`relative_pose` at ``threshold_px``) and the fits at ``scales - 1`` tighter
    thresholds (halved each time): the one with the smallest MSAC cost at 3 sigma, sigma the
    robust spread (1.4826 x median Sampson distance) under the fit that leaves the smallest
    one. A tighter fit that wins gets its inliers at ``threshold_px`` (:func:`judge_pose`);
    ``scales=1`` returns ``first``.

    Why: near a pure turn, or with a narrow field of view, rotation and translation trade (the
    bas-relief ambiguity) and a handful of tracks that slid (along a mover's outline, across a
    depth edge) can hold a wrong pose at 1 px, ten times the noise of sharp frames: on
    generated starts that went the wrong way the true pose put the tracks' median 0.04-0.07 px
    from their epipolar lines and the chosen one 0.13-0.17 px, the slid tracks 1.6-3 px off the
    true pose and within 0.6 px of the wrong one. The choice's threshold follows the noise, so
    on noisy tracks it is as wide as the 1 px fit's (choosing by the median distance alone
    took the tight fits' overfitted poses at 0.3-0.5 px of noise)."""
    fits = [first]
    for k in range(1, int(scales)):
        rel = relative_pose(pts_a, pts_b, intr_a, intr_b, threshold_px=threshold_px / 2 ** k)
        if rel is not None:
            fits.append(rel)
    if len(fits) == 1:
        return first
    dist = [sampson_distances_px(f.T_a_b, pts_a, pts_b, intr_a, intr_b) for f in fits]
    tau = 3.0 * 1.4826 * min(float(np.median(d)) for d in dist)
    best = int(np.argmin([np.sum(np.minimum(d, tau) ** 2) for d in dist]))
    if best == 0:
        return first
    return judge_pose(fits[best].T_a_b, pts_a, pts_b, intr_a, intr_b, threshold_px=threshold_px)[0]


def sampson_distances_px(T_a_b: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray,
                         intr_a: Intrinsics, intr_b: Intrinsics) -> np.ndarray:
    """(N,) Sampson distance (pixels) of each match from the epipolar geometry of the relative
    pose T_a_b (view b in view a's frame); inf where it is not finite."""
    T_b_a = invert_pose(T_a_b)
    t = T_b_a[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    F = np.linalg.inv(intr_b.K).T @ tx @ T_b_a[:3, :3] @ np.linalg.inv(intr_a.K)
    d = np.linalg.norm(sampson_residuals(F, pts_a, pts_b), axis=1)
    d[~np.isfinite(d)] = np.inf
    return d


def judge_pose(T_a_b: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray, intr_a: Intrinsics,
               intr_b: Intrinsics, *, threshold_px: float = 1.0) -> tuple[RelativePose, float]:
    """A relative pose (view b in view a's frame) judged on matched pixels: as a
    :class:`RelativePose` whose inliers are the points within ``threshold_px`` (Sampson
    distance) of their epipolar lines and in front of both views, and its MSAC cost, the sum
    of min(d, threshold)^2 / threshold^2 over all points (lower is better; two poses judged on
    the same points compare by it, whatever set either was fitted on)."""
    d = sampson_distances_px(T_a_b, pts_a, pts_b, intr_a, intr_b)
    _, err, _ = triangulate(np.eye(4), T_a_b, pts_a, pts_b, intr_a, intr_b)
    inliers = (d < threshold_px) & np.isfinite(err)
    cost = float(np.sum(np.minimum(d, threshold_px) ** 2)) / threshold_px ** 2
    par = rotation_parallax_deg(pts_a, pts_b, intr_a, intr_b, T_a_b[:3, :3])
    return RelativePose(T_a_b, inliers, par), cost


def shared_inliers(T_a_b: np.ndarray, inliers: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray,
                   intr_a: Intrinsics, intr_b: Intrinsics) -> float:
    """The share of ``inliers`` (a bool mask over the matched pixels pts_a, pts_b, those of
    another pose) that are also inliers of the pose T_a_b (:func:`judge_pose`); 0 when there are
    none. A second fit of the same matches that explains the same points another way shares
    nearly all of them; one that found a new consensus, such as a large mover's once the points
    that held the first fit were dropped, shares fewer."""
    inliers = np.asarray(inliers, bool)
    n = int(inliers.sum())
    if n == 0:
        return 0.0
    was, _ = judge_pose(T_a_b, pts_a, pts_b, intr_a, intr_b)
    return float((was.inliers & inliers).sum()) / n


def translation_angle_deg(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Angle (degrees) between the translation directions of two relative poses (4, 4); 180
    when either has none."""
    angle = float(angle_between_deg(np.asarray(T_a)[:3, 3], np.asarray(T_b)[:3, 3]))
    return 180.0 if np.isnan(angle) else angle


def translation_spread_deg(pts_a: np.ndarray, pts_b: np.ndarray, intr_a: Intrinsics,
                           intr_b: Intrinsics, *, splits: int = 3, seed: int = 0) -> float:
    """How well matched pixels determine the direction of the translation between two views:
    the median, over ``splits`` random halvings of the matches, of the angle (degrees) between
    the translation directions of :func:`relative_pose` on each half; 180 when a half cannot be
    posed. When the rotation dwarfs the parallax (a fast turn, a far scene) a sideways
    translation with a slightly different rotation explains the matches almost as well as the
    true one (the bas-relief ambiguity), and tracking noise then picks the direction: on a
    generated walk turning 19 deg with 0.6 deg of parallax the halves disagreed by 21-110 deg
    and the full set was 108 deg off, where well-posed pairs agree within 1.5 deg."""
    n = len(pts_a)
    if n < 16:
        return 180.0
    rng = np.random.default_rng(seed)
    angles = []
    for _ in range(splits):
        perm = rng.permutation(n)
        halves = [relative_pose(pts_a[h], pts_b[h], intr_a, intr_b) for h in (perm[::2], perm[1::2])]
        if any(r is None for r in halves):
            angles.append(180.0)
            continue
        angles.append(translation_angle_deg(halves[0].T_a_b, halves[1].T_a_b))
    return float(np.median(angles))


def projection_matrix(T_world_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """3x4 K [R|t] world-to-image."""
    T_cam_world = invert_pose(T_world_cam)
    return intr.K @ T_cam_world[:3]


def triangulate(T_world_a: np.ndarray, T_world_b: np.ndarray, pts_a: np.ndarray,
                pts_b: np.ndarray, intr_a: Intrinsics, intr_b: Intrinsics
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of matched pixels seen from two posed views.

    Returns points (N, 3) world, max reprojection error (N,) px over both views (inf where the
    point lies behind a camera), and the ray angle (N,) in degrees.
    """
    Pa, Pb = projection_matrix(T_world_a, intr_a), projection_matrix(T_world_b, intr_b)
    Xh = cv2.triangulatePoints(Pa, Pb, np.asarray(pts_a, np.float64).T,
                               np.asarray(pts_b, np.float64).T)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = (Xh[:3] / Xh[3]).T
    err = np.full(len(X), np.inf)
    ok = np.isfinite(X).all(axis=1)
    errs = []
    for T, intr, pts in ((T_world_a, intr_a, pts_a), (T_world_b, intr_b, pts_b)):
        proj, z = reproject(T, X, intr)
        e = np.hypot(proj[:, 0] - pts[:, 0], proj[:, 1] - pts[:, 1])
        e[~(z > 0)] = np.inf
        errs.append(e)
    err[ok] = np.maximum(errs[0], errs[1])[ok]
    ca, cb = T_world_a[:3, 3], T_world_b[:3, 3]
    ra, rb = X - ca, X - cb
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.sum(ra * rb, axis=1) / (np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1))
    angle = np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0)))
    return X, err, angle


def rotation_parallax_deg(pts_a: np.ndarray, pts_b: np.ndarray, intr_a: Intrinsics,
                          intr_b: Intrinsics, R_a_b: np.ndarray) -> np.ndarray:
    """(N,) angle between each point's two rays once the rotation R_a_b is removed: what is left
    is parallax from translation (plus tracking noise)."""
    ba_, bb = bearings(pts_a, intr_a), bearings(pts_b, intr_b)
    cos = np.clip(np.sum(ba_ * (bb @ R_a_b.T), axis=1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def pixel_homography(pts_a: np.ndarray, pts_b: np.ndarray, threshold_px: float = 2.0):
    """(H_b_a, inliers) of a robust (USAC MAGSAC) homography mapping the (N, 2) pixels pts_a onto
    pts_b, inliers an (N,) bool; (None, None) when it cannot be fitted. The one homography fit of
    the pixel-only tests here (rotation, leftover parallax) and of the calibration's rotation
    model."""
    H, mask = cv2.findHomography(pts_a, pts_b, cv2.USAC_MAGSAC, threshold_px)
    if H is None or H.shape != (3, 3):
        return None, None
    return H, mask.ravel() > 0


def rotation_only(pts_a: np.ndarray, pts_b: np.ndarray, intr_a: Intrinsics, intr_b: Intrinsics,
                  *, threshold_px: float = 2.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Rotation R_a_b of a camera turning without translation (or seeing only far points), from
    a robust homography between normalised points projected onto SO(3). Returns (R_a_b, inliers)
    or None. Used where the essential matrix is degenerate."""
    if len(pts_a) < 6:
        return None
    na, nb = normalize(pts_a, intr_a), normalize(pts_b, intr_b)
    f = 0.5 * (intr_a.fx + intr_b.fx)
    # Fitted in pixel units of a virtual camera of focal f (centred): USAC's thresholds and
    # scoring misbehave in normalised units (measured: 11 of 190 inliers on an exact pan).
    H, inliers = pixel_homography(nb * f, na * f, threshold_px)
    if H is None or inliers.sum() < 3:
        return None
    # H maps b -> a, so for a pure rotation it is R_a_b. The rotation itself is the least-squares
    # fit of the inliers' rays (Kabsch), not H's nearest rotation: H's extra freedoms absorb
    # part of the motion that a rotation has to explain.
    return kabsch_rotation(bearings(pts_a[inliers], intr_a), bearings(pts_b[inliers], intr_b)), inliers


def kabsch_rotation(rays_a: np.ndarray, rays_b: np.ndarray) -> np.ndarray:
    """The rotation R_a_b that best maps the (N, 3) rays_b onto rays_a (least squares, Kabsch)."""
    U, _, Vt = np.linalg.svd(rays_a.T @ rays_b)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def homography_parallax_px(pts_a: np.ndarray, pts_b: np.ndarray, *, threshold_px: float = 2.0
                           ) -> tuple[float, int]:
    """Parallax no homography explains, in pixels, between matched (N, 2) pixels of two views.

    A camera that only turns (whatever its focal length) or sees only a far plane maps one view
    onto the other by a homography; translation in front of depth variation leaves residuals
    that grow with the baseline. Returns (median transfer residual of the homography's own fit
    over all points, px; number of points), with no intrinsics involved: (nan, n) when there
    are fewer than 8 points or the fit fails. Movers inflate it: pass static points."""
    pa = np.ascontiguousarray(pts_a, np.float64).reshape(-1, 2)
    pb = np.ascontiguousarray(pts_b, np.float64).reshape(-1, 2)
    if len(pa) < 8:
        return float("nan"), len(pa)
    H, _ = pixel_homography(pa, pb, threshold_px)
    if H is None:
        return float("nan"), len(pa)
    q = np.concatenate([pa, np.ones((len(pa), 1))], axis=1) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.linalg.norm(q[:, :2] / q[:, 2:3] - pb, axis=1)
    r = r[np.isfinite(r)]
    return (float(np.median(r)) if len(r) else float("nan")), len(pa)
