"""The visual odometry's steps as pure functions of arrays: pose by PnP, the dynamic test, the
keyframe decision, triangulation against the window, pose interpolation and the parallax
evidence that tells a turning camera from a translating one. :class:`mona_vo.vo.VisualOdometry`
calls them from a short ``step()``; each is tested alone on synthetic tracks
(tests/test_vo_steps.py)."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from mona_vo.conventions import Intrinsics, invert_pose, make_pose
from mona_vo.geometry import (aligned_rms, cauchy_dynamic_probability, homography_jacobians,
                              reprojection_errors)
from mona_vo.patch_align import align_patches, patch_offsets, patch_templates, sample_exact
from mona_vo.tracking import LKTracker, track_forward_backward
from mona_vo.two_view import pixel_homography, rotation_parallax_deg, triangulate


@dataclass(frozen=True)
class Observation:
    """One frame's visible tracks. ids: (N,) int64; uv: (N, 2) float64 pixels x, y; masked: (N,)
    bool inside the frame's moving-object mask."""

    ids: np.ndarray
    uv: np.ndarray
    masked: np.ndarray

    def subset(self, sel: np.ndarray) -> "Observation":
        return Observation(self.ids[sel], self.uv[sel], self.masked[sel])


@dataclass(frozen=True)
class PoseSettings:
    threshold_px: float      # RANSAC / final inlier gate, px
    min_inliers: int         # fewer supporting points: no pose
    guided_px: float         # first gate around the prediction, px
    guided_min_share: float  # the predicted pose needs this share of the points within the gate
    guided_support: float    # and wins unless RANSAC has 1 / this x its support


def predict_pose(T_before: np.ndarray | None, T_last: np.ndarray) -> np.ndarray:
    """Constant-velocity prediction T_last (T_before^-1 T_last); T_last without a second pose."""
    if T_before is None:
        return T_last.copy()
    return T_last @ (invert_pose(T_before) @ T_last)


def refine_pose(P: np.ndarray, q: np.ndarray, intr: Intrinsics, T_start: np.ndarray,
                gate_px: float, s: PoseSettings, min_share: float
                ) -> tuple[np.ndarray | None, int]:
    """Levenberg-Marquardt from T_start on the points within gate_px of their projection, then
    on those within s.threshold_px of the refined pose. P: (N, 3) world; q: (N, 2) px.
    Returns (T_world_cam or None, inlier count)."""
    T = T_start
    n_sel = 0
    for gate in (gate_px, s.threshold_px):
        sel = reprojection_errors(T, P, q, intr) < gate
        n_sel = int(sel.sum())
        if n_sel < max(s.min_inliers, min_share * len(P)):
            return None, n_sel
        Tcw = invert_pose(T)
        rvec, _ = cv2.Rodrigues(Tcw[:3, :3])
        rvec, tvec = cv2.solvePnPRefineLM(P[sel], q[sel], intr.K, None, rvec, Tcw[:3, 3].copy())
        R, _ = cv2.Rodrigues(rvec)
        T = invert_pose(make_pose(R, tvec.ravel()))
    return T, n_sel


def estimate_pose(P: np.ndarray, q: np.ndarray, intr: Intrinsics, T_guess: np.ndarray | None,
                  s: PoseSettings) -> tuple[np.ndarray | None, int]:
    """Pose of a frame from its static tracks with landmarks (P (N, 3) world, q (N, 2) px).

    With a prediction, first a robust refinement from it on the points it explains: a mover that
    keeps pace with the camera can hold RANSAC's largest consensus set, while under the
    prediction the static world is the part that still fits; that pose wins unless RANSAC
    (AP3P minimal samples, no guess needed) finds clearly more support."""
    if len(P) < max(6, s.min_inliers) or not np.isfinite(P).all():
        return None, len(P)
    guided = (None, 0)
    if T_guess is not None:
        guided = refine_pose(P, q, intr, T_guess, s.guided_px, s, s.guided_min_share)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        P, q, intr.K, None, iterationsCount=100, reprojectionError=s.threshold_px,
        confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
    ransac = (None, 0 if inl is None else len(inl))
    if ok and inl is not None and len(inl) >= s.min_inliers:
        R, _ = cv2.Rodrigues(rvec)
        ransac = refine_pose(P, q, intr, invert_pose(make_pose(R, tvec.ravel())), s.threshold_px,
                             s, 0.0)
    if guided[0] is not None and guided[1] >= s.guided_support * ransac[1]:
        return guided
    return ransac if ransac[0] is not None else (None, ransac[1])


def dynamic_test(residual_xy: np.ndarray, strikes: np.ndarray, scale_px: float, p_max: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Front-end dynamic test of tracks with landmarks: a static point's reprojection residual
    (``residual_xy``, (N, 2) px, :func:`mona_vo.geometry.reprojection_residuals`; NaN behind the
    camera) follows a Cauchy law of scale ``scale_px``
    (:func:`mona_vo.geometry.cauchy_dynamic_probability`); p > p_max twice in a row and the
    track is dynamic. strikes: (N,) previous counts.
    Returns (new strikes (N,) uint8, dynamic (N,) bool)."""
    r = np.array(residual_xy, np.float64).reshape(-1, 2)
    r[~np.isfinite(r).all(axis=1)] = np.inf
    p = cauchy_dynamic_probability(r, scale_px)
    new = np.where(p > p_max, np.minimum(strikes.astype(np.int64) + 1, 255), 0).astype(np.uint8)
    return new, new >= 2


def drift_test(residual_xy: np.ndarray, evidence: np.ndarray, noise_floor_px: float,
               breakeven: float, bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Sequential test (CUSUM) of tracks whose reprojection residual stays above the frame's
    noise: a mover slower than the gross test's few pixels, or one that keeps pace with the camera, is
    re-triangulated at every keyframe and then drifts off its landmark by a fraction of a pixel
    per frame, while its one-frame residual stays within the static points' tails.

    residual_xy: (N, 2) reprojection residuals, px (NaN: behind the camera); evidence: (N,) the
    tracks' running sums.
    The frame's noise is ``sigma = max(noise_floor_px, 1.4826 median(r))`` (most tracks are
    static); a frame adds the log-likelihood ratio ``0.5 (z^2 - breakeven^2)``, ``z = r /
    sigma``, capped at ``bound / 2`` (a mistracked jump needs a second frame), and the sum
    never falls below zero. Returns (new evidence (N,) float32, dynamic (N,) bool: sum >=
    bound)."""
    r = np.linalg.norm(np.asarray(residual_xy, np.float64).reshape(-1, 2), axis=1)
    finite = np.isfinite(r)
    sigma = noise_floor_px
    if finite.any():
        sigma = max(noise_floor_px, 1.4826 * float(np.median(r[finite])))
    z2 = np.where(finite, (r / sigma) ** 2, np.inf)
    llr = np.minimum(0.5 * (z2 - breakeven ** 2), 0.5 * bound)
    new = np.maximum(np.asarray(evidence, np.float64) + llr, 0.0)
    return new.astype(np.float32), new >= bound


def keyframe_needed(*, gap: int, max_gap: int, parallax_px: float, parallax_min_px: float,
                    lm_last: int, lm_now: int, min_tracked: float, min_landmarks: int,
                    falling: float) -> bool:
    """Keyframe policy. Rotation-free parallax (a fast pan moves every point but adds no
    baseline, and keyframes without baseline only add scale drift), the share of the last
    keyframe's landmarks still seen, and a landmark floor that applies only while landmarks are
    being lost (a pan), not to a scene that simply holds few (there it would make every frame a
    keyframe)."""
    if gap >= max_gap:
        return True
    base = max(lm_last, 1)
    return (parallax_px >= parallax_min_px or lm_now < min_tracked * base
            or (lm_now < falling * base and lm_now < min_landmarks))


def keyframe_shift_pct(before: np.ndarray, after: np.ndarray) -> float:
    """How far the global refinement moved the (K, 3) keyframe centres, as a self-check of the
    sliding window: the RMS distance left once the centres before are mapped onto those after by
    a similarity (scale, rotation, translation: the gauge a monocular map is free in), in percent
    of the refined keyframes' path. A window that kept a consistent map is moved little; one
    whose scale slid, or that built its map on a wrong start, is moved much, whichever way the
    global solution settles. NaN with fewer than three keyframes or no path."""
    after = np.asarray(after, np.float64).reshape(-1, 3)
    path = float(np.linalg.norm(np.diff(after, axis=0), axis=1).sum())
    if len(after) < 3 or not path > 0:
        return float("nan")
    return 100.0 * aligned_rms(before, after) / path


def rotation_free_parallax_px(uv_a: np.ndarray, uv_b: np.ndarray, intr_a: Intrinsics,
                              intr_b: Intrinsics, R_a_b: np.ndarray) -> float:
    """Median parallax (px at view b's focal length) of matched pixels once the rotation R_a_b
    between the two views is removed; inf with no points."""
    if not len(uv_a):
        return float("inf")
    ang = rotation_parallax_deg(uv_a, uv_b, intr_a, intr_b, R_a_b)
    return float(np.radians(np.median(ang)) * intr_b.fx)


# A map is short of landmarks when it has fewer in view than this share of the cells of the grid
# that new points are seeded on (one per cell, vo.grid_size).
STARVED_SHARE = 0.5


def triangulation_angle_deg(n_landmarks_seen: int, grid_size: int, min_angle_deg: float,
                            starved_angle_deg: float) -> float:
    """The ray angle a new landmark needs at a keyframe: ``min_angle_deg``, or the smaller
    ``starved_angle_deg`` (0: never) while fewer than ``STARVED_SHARE`` of the ``grid_size``
    x ``grid_size`` cells' worth of landmarks are in view.

    Why: a slow camera (the start of a walk, a creep, a pan with a little translation) gives its
    new tracks too little baseline for the fixed angle, so a keyframe adds almost no landmarks;
    the pose then rests on the few old ones, their errors bend it, and fewer new tracks agree
    with it at the next keyframe, until the map has a few dozen points and its scale drifts
    (Bonn crowd, frames 0-224, grid 15, no masks: 0-12 new landmarks per keyframe, PnP inliers
    80 -> 42, ATE 5.1 cm; with the smaller angle 186 inliers, 1.25 cm). Points just above the
    smaller angle still constrain the rotation, and every view that saw them must agree
    (:func:`triangulate_against`). A map with landmarks to spare keeps the stricter angle: a
    point with almost no parallax where the rest show plenty is far away or moves with the
    camera (a followed car: generated ``mixed`` seed 209, 0.09 -> 0.83 % of path with 0.1 deg
    everywhere, 0.08 % with it only while starved). The count cannot tell a slow start from a
    map that people walking with the camera have emptied, where the smaller angle acts too (the
    default MONA draw on Bonn's long part collapses after frame 360 with it, 5.62 cm against
    3.81 without; README, Real footage, stop 48)."""
    if starved_angle_deg > 0 and n_landmarks_seen < STARVED_SHARE * grid_size ** 2:
        return min(float(min_angle_deg), float(starved_angle_deg))
    return float(min_angle_deg)


def triangulate_against(views, ids: np.ndarray, uv: np.ndarray, intr: Intrinsics,
                        T_world_cam: np.ndarray, max_error_px: float, min_angle_deg: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    """New landmarks for tracks (ids (N,), uv (N, 2)) of a frame at T_world_cam, each from the
    oldest of ``views`` that saw it (the widest baseline) whose two rays meet within
    max_error_px at an angle >= min_angle_deg, and that every other view which saw it also
    sees within max_error_px. views: iterable of (T_world_cam, Intrinsics, ids, uv), oldest
    first. Returns (ids (K,), points (K, 3) world).

    Why every view: two rays almost always meet when the point moved along its epipolar line
    between the two frames (a person walking ahead of a camera that follows); a third view
    at another point of the camera's path rarely agrees. On Bonn crowd, such points were
    triangulated at a twentieth of the map's depth and took over the poses."""
    views = list(views)
    done = np.zeros(len(ids), bool)
    out_ids, out_X = [], []
    for i, (T_v, intr_v, ids_v, uv_v) in enumerate(views):
        _, ia, ib = np.intersect1d(ids_v, ids, return_indices=True)
        sel = ~done[ib]
        ia, ib = ia[sel], ib[sel]
        if not len(ib):
            continue
        X, err, ang = triangulate(T_v, T_world_cam, uv_v[ia], uv[ib], intr_v, intr)
        good = (err < max_error_px) & (ang >= min_angle_deg)
        for j, (T_o, intr_o, ids_o, uv_o) in enumerate(views):
            if j == i:
                continue
            _, ja, jb = np.intersect1d(ids_o, ids[ib], return_indices=True)
            if not len(jb):
                continue
            good[jb[~(reprojection_errors(T_o, X[jb], uv_o[ja], intr_o) < max_error_px)]] = False
        out_ids.append(ids[ib][good])
        out_X.append(X[good])
        done[ib[good]] = True
    if not out_ids:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    return np.concatenate(out_ids), np.concatenate(out_X)


def pair_matches(gray_a: np.ndarray, gray_b: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray,
                 mask_a: np.ndarray | None, mask_b: np.ndarray | None, n_points: int,
                 fb_px: float, lk: LKTracker | None = None) -> tuple[np.ndarray, np.ndarray]:
    """More matches between the two frames of a start pair than the (N, 2) tracks uv_a, uv_b
    they share: up to ``n_points`` Shi-Tomasi corners of frame a outside its mask, found in
    frame b by pyramidal Lucas-Kanade started where the homography of the shared tracks puts
    them, kept when tracking them back lands within ``fb_px`` of where they started and they
    fall inside frame b, outside its mask. Returns (K, 2) float64 pixels in a and b (K may be
    0). ``lk``: whose Lucas-Kanade window, levels and stopping criteria to use (the VO's
    tracker when it is one; default LKTracker's)."""
    empty = (np.zeros((0, 2)), np.zeros((0, 2)))
    h, w = gray_a.shape
    if n_points <= 0 or len(uv_a) < 8:
        return empty
    H, _ = pixel_homography(uv_a, uv_b)
    if H is None:
        return empty
    allowed = None if mask_a is None else (~np.asarray(mask_a, bool)).astype(np.uint8) * 255
    corners = cv2.goodFeaturesToTrack(gray_a, n_points, 0.005, max(3.0, 0.008 * w), mask=allowed)
    if corners is None:
        return empty
    pa = corners.reshape(-1, 1, 2).astype(np.float32)
    guess = cv2.perspectiveTransform(pa, H)
    lk = lk if lk is not None else LKTracker()
    pb, found, fb = track_forward_backward(gray_a, gray_b, pa, guess, lk.win, lk.levels, lk.criteria)
    pa = pa.reshape(-1, 2)
    ok = found & (fb < fb_px) & np.isfinite(pb).all(axis=1)
    ok &= (pb[:, 0] >= 0) & (pb[:, 0] <= w - 1) & (pb[:, 1] >= 0) & (pb[:, 1] <= h - 1)
    if mask_b is not None:
        ij = np.round(pb[ok]).astype(int)
        ok[np.flatnonzero(ok)[np.asarray(mask_b, bool)[ij[:, 1], ij[:, 0]]]] = False
    return pa[ok].astype(np.float64), pb[ok].astype(np.float64)


def typical_speed(frames: np.ndarray, positions: np.ndarray, recent: int) -> float | None:
    """The map's usual translation per frame: the median, over the last ``recent`` steps
    between consecutive keyframes ((K,) frame indices, (K, 3) camera centres, in time order),
    of the step's length over its frame gap; None without a step. A median over many
    keyframes, because tracking is lost after a few bad frames: on Bonn crowd the last step
    before a loss was 50 times shorter than the usual one, and a new map started at that
    speed kept its scale for the rest of the clip."""
    f = np.asarray(frames, np.float64)
    if len(f) < 2:
        return None
    steps = np.linalg.norm(np.diff(np.asarray(positions, np.float64), axis=0), axis=1)
    per_frame = steps / np.maximum(np.diff(f), 1.0)
    per_frame = per_frame[-recent:]
    per_frame = per_frame[per_frame > 0]
    return float(np.median(per_frame)) if len(per_frame) else None


def typical_velocity(frames: np.ndarray, T_world_cam: np.ndarray, recent: int
                     ) -> np.ndarray | None:
    """The map's usual translation per frame in the camera's own axes (its body velocity):
    over the last ``recent`` steps between consecutive keyframes ((K,) frame indices,
    (K, 4, 4) poses, in time order), each step is expressed in the axes of the keyframe it
    starts from; the velocity points along the mean of those steps' unit directions and has
    the length of :func:`typical_speed` (per frame, over the same steps). Body axes, because a walking or driving
    camera keeps moving forward while it turns; None without a step or without a common
    direction (a hand-held camera shaking about one place)."""
    f = np.asarray(frames, np.float64)
    T = np.asarray(T_world_cam, np.float64)
    speed = typical_speed(f, T[:, :3, 3], recent)
    if speed is None:
        return None
    d = np.einsum("kji,kj->ki", T[:-1, :3, :3], np.diff(T[:, :3, 3], axis=0))[-recent:]
    n = np.linalg.norm(d, axis=1)
    d = d[n > 0] / n[n > 0, None]
    mean = d.mean(axis=0)
    # Steps pointing every way (|mean| of unit vectors near 0) have no direction to carry.
    if np.linalg.norm(mean) < 0.5:
        return None
    return speed * mean / np.linalg.norm(mean)


def walk_back(T_first: np.ndarray, R_world_cam: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Poses of the frames before a map's first keyframe, given their measured rotations
    ((N, 3, 3) world-from-camera, in time order, the last one the frame just before the
    keyframe) and the map's first body velocity (:func:`typical_velocity`): each frame is one
    step of ``velocity``, in its own axes, behind the next, ending at ``T_first``'s centre.
    Returns (N, 4, 4) T_world_cam with those rotations."""
    R = np.asarray(R_world_cam, np.float64)
    n = len(R)
    out = np.zeros((n, 4, 4))
    c = np.asarray(T_first, np.float64)[:3, 3].copy()
    for i in range(n - 1, -1, -1):
        c = c - R[i] @ velocity
        out[i] = make_pose(R[i], c)
    return out


def segment_spans(frame_segment: np.ndarray) -> list[tuple[int, int]]:
    """(first frame, last frame) of each map segment, in the order the segments began, from the
    (N,) segment of each frame (-1: on no map; such frames belong to no span)."""
    seg = np.asarray(frame_segment, np.int64)
    spans = []
    for s in np.unique(seg[seg >= 0]):
        at = np.flatnonzero(seg == s)
        spans.append((int(at[0]), int(at[-1])))
    return sorted(spans)


def interpolate_pose(Ta: np.ndarray, Tb: np.ndarray, a: float) -> np.ndarray:
    """Pose a of the way from Ta to Tb (rotation by slerp, centre linearly)."""
    R = Slerp([0, 1], Rotation.from_matrix([Ta[:3, :3], Tb[:3, :3]]))(a).as_matrix()
    return make_pose(R, (1 - a) * Ta[:3, 3] + a * Tb[:3, 3])


# ------------------------------------------------------------------ parallax evidence

@dataclass(frozen=True)
class ParallaxEvidence:
    """Is there translation in the footage? Measured without trusting the focal length.

    The rotation-free parallax is the residual no homography explains between a reference frame
    and the current one (:func:`mona_vo.two_view.homography_parallax_px`): a turning camera maps
    one view onto the other by a homography whatever its focal length, translation before depth
    differences does not. The noise floor is what tracking noise alone gives over the same
    baseline: the per-frame residuals of consecutive frames, added as a random walk
    (sqrt of the sum of squares), as frame-to-frame tracking drift adds up. ``ratio`` is the
    largest parallax / floor seen; the footage translates when it reaches ``translation_ratio``.

    parallax_px, floor_px: at the frame where the ratio was largest; frames: that baseline.
    """

    parallax_px: float = 0.0
    floor_px: float = float("nan")
    ratio: float = 0.0
    frames: int = 0

    def updated(self, parallax_px: float, floor_px: float, frames: int) -> "ParallaxEvidence":
        if not (np.isfinite(parallax_px) and np.isfinite(floor_px)) or floor_px <= 0:
            return self
        r = parallax_px / floor_px
        if r > self.ratio:
            return ParallaxEvidence(float(parallax_px), float(floor_px), float(r), int(frames))
        return self

    def as_dict(self, translation_ratio: float, map_built: bool) -> dict:
        """The report's view: ``conclusion`` is the evidence's verdict (translation when the
        ratio reaches translation_ratio, else rotation-only), ``map_built`` what the VO did."""
        return {"rotation_free_parallax_px": round(self.parallax_px, 4),
                "noise_floor_px": None if not np.isfinite(self.floor_px) else round(self.floor_px, 4),
                "ratio": round(self.ratio, 3), "baseline_frames": self.frames,
                "translation_ratio": translation_ratio,
                "conclusion": "translation" if self.ratio >= translation_ratio else "rotation-only",
                "map_built": bool(map_built)}


def dissimilar_tracks(gray_a: np.ndarray, uv_a: np.ndarray, gray_b: np.ndarray,
                      uv_b: np.ndarray, H_b_a: np.ndarray, half: int, ratio: float,
                      floor: float = 0.02, min_tracks: int = 20) -> np.ndarray:
    """(N,) bool: tracks whose patch at uv_b in gray_b no longer looks as it did at uv_a in
    gray_a (1 - NCC, :func:`patch_similarity` through H_b_a, above ``ratio`` x the median over
    the tracks and above ``floor``). Relative to the median, so noise, blur and JPEG, which
    lower every patch's similarity, do not empty the map. None flagged with fewer than
    ``min_tracks`` tracks or comparable patches: the median would say nothing."""
    bad = np.zeros(len(uv_a), bool)
    if len(uv_a) < min_tracks:
        return bad
    d = 1.0 - patch_similarity(gray_a, uv_a, gray_b, uv_b, half, H_b_a)
    if np.isfinite(d).sum() < min_tracks:
        return bad
    with np.errstate(invalid="ignore"):
        return d > max(ratio * float(np.nanmedian(d)), floor)


def patch_similarity(gray_a: np.ndarray, uv_a: np.ndarray, gray_b: np.ndarray, uv_b: np.ndarray,
                     half: int, H_b_a: np.ndarray | None = None) -> np.ndarray:
    """(N,) normalised cross-correlation of the (2 half + 1)^2 patches around uv_b in gray_b
    and around uv_a in gray_a (sub-pixel, bilinear); NaN where a patch is flat or its local
    map cannot be inverted. Invariant to gain and offset, so exposure changes do not lower it.
    ``H_b_a`` (3, 3; pixels of a -> pixels of b, e.g. the rotation's K_b R K_a^-1): patch a is
    sampled through its local affine map, so a camera that turned or rolled between the two
    images does not lower it. All patches are sampled at once
    (:func:`mona_vo.patch_align.sample_exact`): one OpenCV call per track was about a tenth of
    a fast turn's VO time."""
    uv_a = np.asarray(uv_a, np.float64).reshape(-1, 2)
    uv_b = np.asarray(uv_b, np.float64).reshape(-1, 2)
    out = np.full(len(uv_a), np.nan)
    if not len(uv_a):
        return out
    du, dv, _ = patch_offsets(half)
    pb = sample_exact(gray_b, uv_b[:, :1] + du, uv_b[:, 1:] + dv)
    ok = np.ones(len(uv_a), bool)
    if H_b_a is None:
        pa = sample_exact(gray_a, uv_a[:, :1] + du, uv_a[:, 1:] + dv)
    else:
        # Patch pixel u of b's patch comes from p + A^-1 u in a, A the local affine map of H.
        jac = homography_jacobians(H_b_a, uv_a)
        det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
        ok = np.isfinite(det) & (np.abs(det) > 1e-12)
        Ainv = np.zeros_like(jac)
        Ainv[ok] = np.linalg.inv(jac[ok])
        pa = sample_exact(gray_a, uv_a[:, :1] + Ainv[:, 0, :1] * du + Ainv[:, 0, 1:] * dv,
                            uv_a[:, 1:] + Ainv[:, 1, :1] * du + Ainv[:, 1, 1:] * dv)
    pa = pa - pa.mean(axis=1, keepdims=True)
    pb = pb - pb.mean(axis=1, keepdims=True)
    den = np.sqrt(np.einsum("ij,ij->i", pa, pa) * np.einsum("ij,ij->i", pb, pb))
    ok &= den > 1e-6
    out[ok] = np.einsum("ij,ij->i", pa[ok], pb[ok]) / den[ok]
    return out


def find_by_projection(ref_gray: np.ndarray, uv_ref: np.ndarray, gray: np.ndarray,
                       uv_pred: np.ndarray, H_b_a: np.ndarray, *, half: int, max_px: float,
                       min_ncc: float) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks seen at ``uv_ref`` (N, 2) in the grey image ``ref_gray`` looked for in ``gray``
    where the pose puts them, ``uv_pred`` (N, 2): each (2 half + 1)^2 patch of the reference,
    deformed by the local affine map of ``H_b_a`` (the turn between the two views, K_b R K_a^-1),
    is fitted there by :func:`mona_vo.patch_align.align_patches` (affine, gain and offset).
    Returns (N, 2) float64 positions and (N,) bool found: the fit converged, correlates at
    least ``min_ncc`` with the reference, lies within ``max_px`` of the prediction (a wrong
    landmark or a look-alike further off is not taken) and its patch is inside the image."""
    uv_ref = np.asarray(uv_ref, np.float64).reshape(-1, 2)
    uv_pred = np.asarray(uv_pred, np.float64).reshape(-1, 2)
    if not len(uv_ref):
        return uv_pred.copy(), np.zeros(0, bool)
    templates = patch_templates(ref_gray, uv_ref, half)
    p, ncc, ok = align_patches(templates, gray, uv_pred, homography_jacobians(H_b_a, uv_ref),
                               half=half)
    h, w = gray.shape[:2]
    ok &= np.isfinite(p).all(axis=1) & (ncc >= min_ncc)
    ok &= np.linalg.norm(p - uv_pred, axis=1) <= max_px
    ok &= (p[:, 0] >= half) & (p[:, 0] <= w - 1 - half) & (p[:, 1] >= half) & (p[:, 1] <= h - 1 - half)
    return p, ok
