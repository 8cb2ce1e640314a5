"""MONA module 1, Dynamic Points Extraction, with a geometric (classical) dynamic test.

The paper (section Methods) selects ``n`` random detection points and ``m`` anchor points (the
highest-gradient pixel of each cell of a ``k x k`` grid) in the first frame of a window, tracks
them through the window, scores each detection point's motion against the anchors' (LEAP-VO's
learned anchor comparison with a Cauchy trajectory model) and calls a point dynamic in frame t
when that score exceeds ``theta_t = alpha * m_t``, ``m_t`` being the mean optical-flow magnitude
of frame t. Here the anchors' role -- telling what the camera alone would do to a point -- is
played by two-view geometry fitted robustly to the anchor tracks.

Window
    Frames ``s .. e`` (``L = window`` frames); consecutive windows share one frame (the last frame
    of a window is the first of the next), so every consecutive frame pair lies in exactly one
    window. At ``s`` all old tracks are dropped, ``m`` anchors (:func:`grid_points` on the
    gradient score, LEAP-VO/MONA's rule) and ``n`` detection points (:func:`random_points`,
    seeded by ``(seed, s)``) are added, and the :class:`~mona_vo.tracking.Tracker` carries them
    to ``e``. A track whose image velocity jumps (beyond the jump all tracks share) is ended
    there: an occluding mover that sweeps over a background point drags its track along, which
    would make the point look dynamic where it was still on the background. A window ends early
    (fewer than L frames) once fewer than ``min_tracked_frac`` of its points are still tracked:
    under a fast pan most points leave the image within a few frames, and a mover coming into
    view would get no detection point until the next window (measured on the fast-rotation
    scenes: mean IoU 0.47 -> 0.52). Memory: one window of tracks, ``L x (n + m) x 2`` floats.

Detection points are drawn uniformly at random, but candidates on blank surfaces (gradient
score below ``min_texture_frac`` of the frame's 90th percentile) are skipped: a point tracker
drifts there and the drift would look like motion (CoTracker's learned features need not).

Camera-induced motion of a frame pair (a, b), from the anchors visible in both
    * ``H``: homography, OpenCV USAC (``robust_method``, default USAC_ACCURATE), threshold
      ``model_threshold_px``.
    * ``F = K^-T E K^-1`` with ``E`` an essential matrix (same estimator, five-point) on the
      anchors normalised by intrinsics ``K`` (given, else a pinhole guess with
      the pipeline's ``assumed_hfov_deg``). The calibrated model has 5 degrees of freedom instead of F's 7, so a
      large mover carrying many anchors cannot pull it into a compromise between two motions
      (measured: it separated the movers of the synthetic scenes and of DAVIS car-shadow clearly
      better than a free F).
    * Model choice: with ``theta_ab = max(alpha * mean(m_a .. m_{b-1}), theta_min)`` the
      homography is used when the anchors within ``theta_ab * (b - a)`` pixels of it number at
      least ``homography_min_ratio`` times those within that distance of the epipolar geometry
      (it explains the anchors about as well: pure rotation, a distant or planar scene); then a
      point's whole 2-D deviation is evidence, and a mover that slides along its epipolar line
      (a car the panning camera follows) is still caught. Otherwise the epipolar model is used
      and only the deviation across the epipolar line is (a static point may slide along its
      line by its unknown depth).

Residual of a point tracked from x_a to x_b (2-vector, pixels, in image b)
    * homography: ``r = x_b - H x_a`` (the transfer error);
    * epipolar:   ``r = d_S * n``, ``d_S = x_b^T F x_a / sqrt((F x_a)_1^2 + (F x_a)_2^2 +
      (F^T x_b)_1^2 + (F^T x_b)_2^2)`` the signed Sampson distance and ``n`` the unit normal of
      the epipolar line ``F x_a`` in image b; replaced by ``x_b - x_inf`` (``x_inf = H_inf x_a``,
      ``H_inf = K R K^-1`` from E's decomposition) when that is longer and the point moved along
      its epipolar line in the direction no static point in front of the camera can move (a
      negative inverse depth, :func:`cheirality_residuals`; e.g. a car overtaking a forward-moving
      camera). This sign test is only used when the anchors fix the translation (their own
      sign-test failures at most 2 %, median parallax at least 4 model thresholds).

Aggregation over the window (a point moving along its epipolar line in one pair is caught in
another, and long gaps average tracking noise down)
    ``rho_i = r_ab,i / (b - a)`` (pixels per frame) for the pairs ``(s, last_i)``, ``(s, c)`` and
    ``(c, e)`` with ``c = s + (L - 1) // 2`` and ``last_i`` the last frame where point i is
    visible, keeping those where the point is visible at both ends; the point's residual vector
    ``rho_i`` is the one of largest norm. It describes the whole track and is reported in every
    frame of the window where the point is visible (as LEAP-VO labels whole tracks). The anchors'
    residuals are aggregated the same way; ``sigma_w = 1.4826 * median_anchors |rho|`` is the
    window's noise level (robust: movers among the anchors are a minority). The window's model,
    used by the masker for the dense motion maps of its frames, is the homography when at least
    ``window_homography_frac`` of its pairs chose it, else the epipolar geometry. With
    ``window_model_for_pairs`` every pair's residuals use the window's model (the pair's own fit
    of it): one camera does not switch between turning and translating within a few frames,
    while a short pair's choice is easily swayed (measured on a static street: a two-frame pair
    chose the homography at ratio 0.65, and its parallax made 31 static points dynamic).

Dynamic probability (the paper's product of an x and a y Cauchy term, normalised by its peak)
    ``p_i = 1 - 1 / ((1 + (rho_x / gamma)^2) * (1 + (rho_y / gamma)^2))`` with ``gamma =
    cauchy_scale_px`` (px per frame), the scale of a static point's residual. ``p = 0`` for a
    residual of zero; the heavy tails make ``p`` grow slowly, so one bad track in a noisy pair
    does not saturate it.

Adaptive threshold (paper, with two floors)
    ``theta_t = max(alpha * m_t, theta_min, kappa * sigma_w)``; detection point i is a dynamic
    point of frame t when it is visible at t and ``|rho_i| > theta_t``. ``alpha * m_t`` is the
    paper's threshold: it follows the frame's camera motion, because the model misfit of static
    points (parallax left by a homography, tracking drift, rolling shutter) grows with the image
    motion; the same residual is dynamic under a slow camera and static under a fast one.
    ``theta_min`` keeps a nearly still camera (``m_t`` near 0) from turning sub-pixel tracking
    noise into dynamic points. ``kappa * sigma_w`` (``noise_factor``; 0 gives the paper's rule
    with its floor) adapts to how well the frames are tracked at all: the static residuals of
    real footage (JPEG, blur, rolling shutter, DAVIS: 90th percentile 0.8-1.2 px per frame) are
    several times those of rendered frames (0.2 px), which no single ``alpha`` covers.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.config import check_fields, setting
from mona_vo.conventions import DEFAULT_HFOV_DEG, Intrinsics
from mona_vo.errors import ConfigError
from mona_vo.flow import vector_lengths
from mona_vo.geometry import (cauchy_dynamic_probability, find_essential, homogeneous,
                              sampson_residuals)
from mona_vo.point_selection import grid_points, random_points, texture_score
from mona_vo.tracking import Tracker, to_gray

HOMOGRAPHY, EPIPOLAR, NO_MODEL = "homography", "epipolar", "none"

# Robust estimators by config name. USAC_ACCURATE (GC-RANSAC with local optimisation) is the
# default: on a synthetic frame where a crossing car carried 25 % of the anchors, MAGSAC++ settled
# on a compromise between car and background (static anchors' median Sampson error 0.37 px,
# car's 0.30 px) while USAC_ACCURATE found the background (0.05 px; car 2.2 px). The USAC
# estimators seed their own sampler (OpenCV's UsacParams, fixed seed), so fits are reproducible
# without touching OpenCV's global RNG; plain 'ransac' draws from that global RNG.
ROBUST_METHODS = {
    "usac_accurate": cv2.USAC_ACCURATE,
    "usac_default": cv2.USAC_DEFAULT,
    "magsac": cv2.USAC_MAGSAC,
    "ransac": cv2.RANSAC,
}


@dataclass(frozen=True)
class DynamicPointsConfig:
    """Settings of MONA's Dynamic Points Extraction (see the module docstring for the formulas)."""

    n_detection: int = setting(300, ge=0)  # n: random detection points per window
    anchor_grid: int = setting(12, ge=2)  # k: one anchor per cell of a k x k grid (m <= k^2)
    anchor_score: str = setting("gradient", choices=("gradient", "min_eigen"))  # anchor choice:
                                      # gradient (paper) | min_eigen (Shi-Tomasi)
    border_px: int = setting(8, ge=0)  # no point closer than this to the image border, pixels
    min_texture_frac: float = setting(0.1, ge=0)  # detection points need texture >= this x the
                                      # 90th percentile
    oversample: int = setting(3, ge=1)  # random candidates drawn per detection point kept
    window: int = setting(9, ge=2)    # L: frames per window; masks lag by L - 1 frames
    min_tracked_frac: float = setting(0.5, ge=0, le=1)  # a window ends early when fewer than
                                      # this share of its points are still tracked (a fast
                                      # pan: new points are due)
    capture_change_px: float = setting(1.5, ge=0)  # a track whose step jumps by more than this
                                      # (px, beyond the common jump) + capture_change_frac x
                                      # its relative step ends
    capture_change_frac: float = setting(0.5, ge=0)  # see capture_change_px (0: off)
    alpha: float = setting(0.02, ge=0)  # theta_t = alpha * m_t (dimensionless)
    theta_min_px: float = setting(0.4, ge=0)  # floor of theta_t, pixels per frame
    noise_factor: float = setting(4.0, ge=0)  # kappa: theta_t >= kappa * sigma_w (anchors' spread)
    cauchy_scale_px: float = setting(0.5, gt=0)  # gamma of the Cauchy model, pixels per frame
    model_threshold_px: float = setting(0.5, gt=0)  # inlier threshold of the robust H and E
                                      # fits, pixels
    robust_method: str = setting("usac_accurate", choices=tuple(ROBUST_METHODS))  # robust
                                      # estimator of those fits
    homography_min_ratio: float = setting(0.6, gt=0)  # H is used when it explains this share of
                                      # what E does
    window_homography_frac: float = setting(0.5, gt=0, le=1)  # window model H when this share
                                      # of its pairs chose H
    window_model_for_pairs: bool = setting(True)  # every pair of a window uses the window's model
    homography_min_turn_deg: float = setting(1.3, ge=0)  # the masker's dense map takes a
                                      # homography window's model only when m_t >= fx tan(this)
                                      # (a camera turning at least this fast, degrees per
                                      # frame), else epipolar
    min_anchors: int = setting(12, ge=8)  # fewer anchors in a pair: all tracked points fit the
                                      # model
    # The field of view assumed without intrinsics is PipelineConfig's `assumed_hfov_deg`.
    seed: int = setting(0, ge=0)      # seed of the detection points (with the window's start)

    def validate(self) -> None:
        check_fields(self, "masks.dynamic_points.")


# --------------------------------------------------------------------------- camera-induced motion

@dataclass(frozen=True, eq=False)
class CameraMotion:
    """Camera-induced motion from frame a to frame b (see the module docstring).

    model:                'homography', 'epipolar' or 'none' (too few correspondences).
    H_b_a:                (3, 3) float64 homography, pixels of a -> pixels of b, or None.
    F_b_a:                (3, 3) float64 fundamental matrix, ``x_b^T F x_a = 0``, or None.
    n_anchors:            correspondences the models were fitted to.
    homography_ratio:     anchors within the inlier distance of H over those within it of E
                          (NaN when the model was imposed: not both were fitted).
    H_inf_b_a:            (3, 3) float64 ``K R K^-1``: where a point at infinity of a is seen in
                          b (the rotation part of the essential matrix), or None.
    epipole_b:            (3,) float64 ``K t`` (homogeneous; x_b ~ H_inf x_a + t_scale/Z * K t
                          for a static point at depth Z > 0 in a), or None.
    """

    model: str
    H_b_a: np.ndarray | None
    F_b_a: np.ndarray | None
    n_anchors: int
    homography_ratio: float
    H_inf_b_a: np.ndarray | None = None
    epipole_b: np.ndarray | None = None


def _dehomogenise(q: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return q[:, :2] / q[:, 2:3]


def transfer_residuals(H_b_a: np.ndarray, pts_a: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """(N, 2) float64 ``x_b - H x_a`` in pixels of image b (inf where H sends x_a to infinity)."""
    q = homogeneous(pts_a) @ np.asarray(H_b_a, np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        proj = q[:, :2] / q[:, 2:3]
    out = np.asarray(pts_b, np.float64).reshape(-1, 2) - proj
    out[~np.isfinite(out).all(axis=1)] = np.inf
    return out


def cheirality_residuals(H_inf_b_a: np.ndarray, epipole_b: np.ndarray, pts_a: np.ndarray,
                         pts_b: np.ndarray) -> np.ndarray:
    """(N, 2) float64 displacement along the epipolar line that no static point in front of
    the cameras can make, pixels of image b.

    A static point at inverse depth ``lam >= 0`` is seen at ``x_b(lam) = (h + lam e)_{12} /
    (h + lam e)_3`` with ``h = H_inf x_a``, ``e`` the epipole: it moves from the infinity point
    ``h_{12} / h_3`` along the epipolar line, in one direction only. ``lam`` is solved by least
    squares from ``x_b (h_3 + lam e_3) = h_{12} + lam e_{12}``; where ``lam < 0`` the point moved
    the wrong way (e.g. a car overtaking a forward-moving camera, or a car the panning camera
    follows) and its displacement from the infinity point counts; elsewhere zero."""
    xa, xb = homogeneous(pts_a), np.asarray(pts_b, np.float64).reshape(-1, 2)
    h = xa @ np.asarray(H_inf_b_a, np.float64).T
    e = np.asarray(epipole_b, np.float64)
    a = xb * e[2] - e[:2]
    b = h[:, :2] - xb * h[:, 2:3]
    lam = np.sum(a * b, axis=1) / np.maximum(np.sum(a * a, axis=1), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_inf = h[:, :2] / h[:, 2:3]
    d = xb - x_inf
    out = np.where((lam < 0)[:, None] & np.isfinite(d).all(axis=1)[:, None], d, 0.0)
    return out


def motion_residuals(motion: CameraMotion, pts_a: np.ndarray, pts_b: np.ndarray) -> np.ndarray:
    """(N, 2) float64 residual vectors (pixels, image b) of correspondences under ``motion``;
    NaN when the motion has no model. Epipolar model: the Sampson vector across the epipolar
    line, replaced by the whole displacement from the infinity point where the point moved
    the wrong way along its line (:func:`cheirality_residuals`), when that is longer."""
    if motion.model == HOMOGRAPHY:
        return transfer_residuals(motion.H_b_a, pts_a, pts_b)
    if motion.model == EPIPOLAR:
        r = sampson_residuals(motion.F_b_a, pts_a, pts_b)
        if motion.H_inf_b_a is not None:
            c = cheirality_residuals(motion.H_inf_b_a, motion.epipole_b, pts_a, pts_b)
            longer = np.sum(c * c, axis=1) > np.sum(r * r, axis=1)
            r[longer] = c[longer]
        return r
    return np.full((len(np.asarray(pts_a).reshape(-1, 2)), 2), np.nan)


def _fit_homography(pa: np.ndarray, pb: np.ndarray, flag: int,
                    threshold_px: float) -> np.ndarray | None:
    """(3, 3) float64 homography fitted robustly to the correspondences, or None."""
    H, _ = cv2.findHomography(pa, pb, flag, threshold_px, maxIters=2000, confidence=0.999)
    return H if H is not None and H.shape == (3, 3) else None


def _fit_epipolar(pa: np.ndarray, pb: np.ndarray, K: np.ndarray, flag: int, threshold_px: float,
                  cheirality: bool, max_wrong_frac: float, min_parallax: float):
    """(F, H_inf, epipole) of an essential matrix fitted robustly (see
    :func:`fit_camera_motion`); Nones for what could not be fitted or determined."""
    E, inl_ok = find_essential(pa, pb, K, threshold_px, 0.999, flag)   # mona_vo.geometry
    if E is None or E.shape[0] < 3 or E.shape[1] != 3:
        return None, None, None
    E = E[:3]
    Ki = np.linalg.inv(K)
    F = Ki.T @ E @ Ki
    F = F / max(np.linalg.norm(F), 1e-300)
    if not cheirality:
        return F, None, None
    # recoverPose picks, of E's four (R, t), the one placing most inliers in front of both
    # cameras: x_b ~ K (R X_a + t).
    inl = inl_ok.astype(np.uint8).reshape(-1, 1)
    _, R, t, _ = cv2.recoverPose(E, pa, pb, K, mask=inl.copy())
    H_inf = K @ R @ Ki
    epipole = (K @ t).ravel()
    # The sign test needs a translation the anchors determine: most of them must show
    # parallax, on the side of the infinity point a static point can reach.
    sel = inl.ravel() > 0
    wrong = np.any(cheirality_residuals(H_inf, epipole, pa[sel], pb[sel]) != 0, axis=1)
    parallax = np.linalg.norm(pb[sel] - _dehomogenise(homogeneous(pa[sel]) @ H_inf.T), axis=1)
    if not (len(wrong) and wrong.mean() <= max_wrong_frac
            and np.median(parallax) >= min_parallax * threshold_px):
        return F, None, None
    return F, H_inf, epipole


def fit_camera_motion(pts_a: np.ndarray, pts_b: np.ndarray, intrinsics: Intrinsics, *,
                      threshold_px: float, inlier_px: float, homography_min_ratio: float = 0.6,
                      method: str = "usac_accurate", cheirality: bool = True,
                      cheirality_max_wrong_frac: float = 0.02, cheirality_min_parallax: float = 4.0,
                      model: str | None = None) -> CameraMotion:
    """Camera-induced motion between frames a and b from anchor correspondences (N, 2) pixels.

    A homography and an essential matrix (intrinsics given) are fitted robustly (``method``, a
    :data:`ROBUST_METHODS` name, inlier threshold ``threshold_px``). The homography is chosen
    when the anchors within ``inlier_px`` of it number at least ``homography_min_ratio`` times
    those within ``inlier_px`` of the epipolar geometry (it explains the anchors about as well:
    rotation, distant or planar scene); else the epipolar model. With ``cheirality`` the
    epipolar model also carries the rotation and epipole of E's decomposition, for the sign test
    of :func:`cheirality_residuals`, when the anchors determine the translation: at most
    ``cheirality_max_wrong_frac`` of E's inliers fail the test themselves and their median
    parallax (distance from the infinity point) is at least ``cheirality_min_parallax *
    threshold_px``. ``model`` ('homography' or 'epipolar') imposes the choice, e.g. the one the
    sparse anchors chose for the same frames: then only that model is fitted (the other only
    when it cannot be: a fit costs milliseconds, and the masker fits every frame), and
    ``homography_ratio`` is NaN.
    """
    pa = np.ascontiguousarray(pts_a, np.float64).reshape(-1, 2)
    pb = np.ascontiguousarray(pts_b, np.float64).reshape(-1, 2)
    n = len(pa)
    if n < 8:
        return CameraMotion(NO_MODEL, None, None, n, 0.0)
    flag = ROBUST_METHODS[method]

    def homography():
        return _fit_homography(pa, pb, flag, threshold_px)

    def epipolar():
        return _fit_epipolar(pa, pb, intrinsics.K, flag, threshold_px, cheirality,
                             cheirality_max_wrong_frac, cheirality_min_parallax)

    H = homography() if model != EPIPOLAR else None
    F, H_inf, epipole = epipolar() if model != HOMOGRAPHY else (None, None, None)
    if model == EPIPOLAR and F is None:
        H = homography()
    elif model == HOMOGRAPHY and H is None:
        F, H_inf, epipole = epipolar()
    if H is None and F is None:
        return CameraMotion(NO_MODEL, None, None, n, 0.0)
    if model is None:
        h_in = float(np.mean(np.linalg.norm(transfer_residuals(H, pa, pb), axis=1) <= inlier_px)) \
            if H is not None else 0.0
        f_in = float(np.mean(np.linalg.norm(sampson_residuals(F, pa, pb), axis=1) <= inlier_px)) \
            if F is not None else 0.0
        ratio = h_in / max(f_in, 1e-9)
        use_h = ratio >= homography_min_ratio
    else:
        ratio, use_h = float("nan"), model == HOMOGRAPHY
    if H is not None and (F is None or use_h):
        return CameraMotion(HOMOGRAPHY, H, F, n, ratio, H_inf, epipole)
    return CameraMotion(EPIPOLAR, H, F, n, ratio, H_inf, epipole)


def residual_map(motion: CameraMotion, flow: np.ndarray,
                 valid: np.ndarray | None = None) -> np.ndarray:
    """(h, w) float32 residual magnitudes, pixels, of the correspondences ``x -> x + flow(x)``
    of a dense (h, w, 2) flow field under ``motion`` (fitted in the same pixel units). Zero where
    the optional (h, w) bool ``valid`` is False, and everywhere when the motion has no model."""
    h, w = flow.shape[:2]
    out = np.zeros((h, w), np.float32)
    if motion.model == NO_MODEL:
        return out
    # Only the valid pixels are computed (the masker asks for a few of them at times).
    ys, xs = np.nonzero(np.ones((h, w), bool) if valid is None else valid)
    p0 = np.stack([xs, ys], axis=1).astype(np.float64)
    p1 = p0 + flow[ys, xs]
    r = vector_lengths(motion_residuals(motion, p0, p1))
    r[~np.isfinite(r)] = 0.0
    out[ys, xs] = r
    return out


# --------------------------------------------------------------------------- probability, threshold

# cauchy_dynamic_probability (the paper's product formula) lives in mona_vo.geometry, shared
# with the VO's dynamic test; imported above.


def adaptive_threshold(mean_flow_px: float, alpha: float, theta_min_px: float,
                       noise_px: float = 0.0, noise_factor: float = 0.0) -> float:
    """The paper's per-frame threshold with floors: ``max(alpha * m_t, theta_min,
    noise_factor * noise)``, pixels (per frame when m_t and noise are)."""
    return max(float(alpha) * float(mean_flow_px), float(theta_min_px),
               float(noise_factor) * float(noise_px))


# --------------------------------------------------------------------------- windows of tracks

@dataclass(frozen=True, eq=False)
class TrackWindow:
    """Anchor and detection tracks of one window.

    frame_indices: (L,) int64 frame indices s .. e (consecutive).
    points:        (L, N, 2) float32 pixels x, y; NaN where the point is not visible.
    n_anchors:     the first n_anchors of the N points are anchors, the rest detection points.
    track_ids:     (N,) int64 tracker ids.
    """

    frame_indices: np.ndarray
    points: np.ndarray
    n_anchors: int
    track_ids: np.ndarray

    @property
    def start(self) -> int:
        return int(self.frame_indices[0])

    def __len__(self) -> int:
        return len(self.frame_indices)


@dataclass(frozen=True, eq=False)
class DynamicPoints:
    """Dynamic-point output of one frame (detection points visible in it).

    frame_index:  the frame.
    points:       (N, 2) float32 pixels x, y of the detection points in this frame.
    residual:     (N,) float32 |rho_i|, residual motion, pixels per frame.
    probability:  (N,) float32 Cauchy dynamic probability in [0, 1).
    is_dynamic:   (N,) bool, residual > theta_t.
    theta_t:      threshold of this frame, pixels per frame.
    m_t:          mean optical-flow magnitude of this frame, pixels.
    noise_px:     the window's noise level sigma_w (anchors' residual spread), px per frame.
    camera_model: the window's model: 'homography' when at least ``window_homography_frac``
                  of its pairs chose it, else 'epipolar' ('none' when no pair was fitted).
    residual_xy:  (N, 2) float32 rho_i, the residual vectors (x, y) whose lengths are
                  ``residual``, pixels per frame in the image of their pair's later frame; None
                  when not computed.
    """

    frame_index: int
    points: np.ndarray
    residual: np.ndarray
    probability: np.ndarray
    is_dynamic: np.ndarray
    theta_t: float
    m_t: float
    noise_px: float = 0.0
    camera_model: str = NO_MODEL
    residual_xy: np.ndarray | None = None

    @property
    def dynamic_points(self) -> np.ndarray:
        """(M, 2) float32 pixels of the dynamic points (the paper's x_d)."""
        return self.points[self.is_dynamic]

    @classmethod
    def empty(cls, frame_index: int, theta_t: float = 0.0, m_t: float = 0.0) -> "DynamicPoints":
        return cls(frame_index, np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
                   np.zeros(0, np.float32), np.zeros(0, bool), float(theta_t), float(m_t))


def turning_fast(mean_flow_px: float, intrinsics: Intrinsics, min_deg: float) -> bool:
    """True when a mean image motion of ``mean_flow_px`` pixels per frame is at least the
    motion of a camera turning by ``min_deg`` degrees per frame (``fx * tan(min_deg)``)."""
    return mean_flow_px >= intrinsics.fx * np.tan(np.radians(min_deg))


def default_intrinsics(width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> Intrinsics:
    """Pinhole guess for uncalibrated video: horizontal field of view ``hfov_deg`` (the
    pipeline passes its ``assumed_hfov_deg``), centred principal point."""
    return Intrinsics.default_for(width, height, hfov_deg)


def classify_window(window: TrackWindow, mean_flow_px: np.ndarray, config: DynamicPointsConfig,
                    intrinsics: Intrinsics) -> list[DynamicPoints]:
    """Dynamic points of every frame of a window (see the module docstring for the formulas).

    mean_flow_px: (L,) m_t of the window's frames, pixels.
    Returns L :class:`DynamicPoints`, in frame order.
    """
    L = len(window)
    P = window.points
    na = window.n_anchors
    N = P.shape[1]
    m = np.asarray(mean_flow_px, np.float64).reshape(L)
    visible = np.isfinite(P).all(axis=2)              # (L, N)
    # Last frame where each point is visible (tracks are never revived).
    last = np.where(visible.any(axis=0), L - 1 - np.argmax(visible[::-1], axis=0), 0)
    c = (L - 1) // 2
    pairs = {(0, int(j)) for j in np.unique(last) if j > 0}
    if c > 0:
        pairs.add((0, c))
    if 0 < c < L - 1:
        pairs.add((c, L - 1))
    best = np.zeros((N, 2))
    best_norm = np.full(N, -1.0)
    motions = {}
    for a, b in sorted(pairs):
        gap = b - a
        both = visible[a] & visible[b]
        fit_sel = both.copy()
        fit_sel[na:] = False
        if fit_sel.sum() < config.min_anchors:
            fit_sel = both      # too few anchors: every tracked point (mostly static) fits
        theta_ab = adaptive_threshold(m[a:b].mean(), config.alpha, config.theta_min_px)
        motions[a, b] = fit_camera_motion(P[a][fit_sel], P[b][fit_sel], intrinsics,
                                          threshold_px=config.model_threshold_px,
                                          inlier_px=theta_ab * gap,
                                          homography_min_ratio=config.homography_min_ratio,
                                          method=config.robust_method)
    # The window's model: the homography when at least window_homography_frac of the fitted
    # pairs chose it (the camera mostly turned). With ``window_model_for_pairs`` every pair
    # uses it: one camera over a few frames does not switch between turning and translating,
    # while one short pair's choice is easily swayed (measured on a static street: a two-frame
    # pair chose H at ratio 0.65 and its parallax made 31 static points "dynamic").
    fitted = [mo for mo in motions.values() if mo.model != NO_MODEL]
    n_homography = sum(mo.model == HOMOGRAPHY for mo in fitted)
    window_model = NO_MODEL if not fitted else (
        HOMOGRAPHY if n_homography >= config.window_homography_frac * len(fitted) else EPIPOLAR)
    for (a, b), motion in motions.items():
        gap = b - a
        both = visible[a] & visible[b]
        long_pair = (a, b) in ((0, c), (c, L - 1))
        use = both & ((last == b) | long_pair)
        if not use.any() or motion.model == NO_MODEL:
            continue
        if config.window_model_for_pairs and motion.model != window_model and (
                motion.H_b_a if window_model == HOMOGRAPHY else motion.F_b_a) is not None:
            motion = dataclasses.replace(motion, model=window_model)
        r = motion_residuals(motion, P[a][use], P[b][use]) / gap
        norm = np.linalg.norm(r, axis=1)
        idx = np.nonzero(use)[0]
        better = norm > best_norm[idx]
        best[idx[better]] = r[better]
        best_norm[idx[better]] = norm[better]
    has = best_norm >= 0
    resid = np.where(has, best_norm, 0.0)
    # The anchors' residuals, aggregated exactly like the detection points', are mostly those
    # of static points: their robust spread is the window's noise level.
    anchor_res = resid[:na][has[:na]]
    noise = 1.4826 * float(np.median(anchor_res)) if len(anchor_res) else 0.0
    thetas = [adaptive_threshold(v, config.alpha, config.theta_min_px, noise,
                                 config.noise_factor) for v in m]
    prob = np.where(has, cauchy_dynamic_probability(best, config.cauchy_scale_px), 0.0)
    det_vis = visible[:, na:]
    has_d, resid_d, prob_d = has[na:], resid[na:], prob[na:]
    out = []
    for j in range(L):
        v = det_vis[j]
        dyn = has_d[v] & (resid_d[v] > thetas[j])
        out.append(DynamicPoints(int(window.frame_indices[j]), P[j, na:][v].astype(np.float32),
                                 resid_d[v].astype(np.float32), prob_d[v].astype(np.float32),
                                 dyn, float(thetas[j]), float(m[j]), noise, window_model,
                                 best[na:][v].astype(np.float32)))
    return out


class DynamicPointsTracker:
    """Streams frames through a :class:`~mona_vo.tracking.Tracker` and cuts them into windows.

    ``push(frame_index, image)`` returns the :class:`TrackWindow` that this frame completes (or
    None); ``flush()`` returns the open window at the end of the input (None when it holds only
    the frame it shares with the previous window). Memory: the current window's tracks only.
    """

    def __init__(self, config: DynamicPointsConfig, tracker: Tracker):
        config.validate()
        self.config = config
        self.tracker = tracker
        self._indices: list[int] = []
        self._rows: list[np.ndarray] = []     # per frame (N, 2) float32, NaN = not visible
        self._ids = np.zeros(0, np.int64)
        self._n_anchors = 0
        self._closed_any = False

    def _start(self, frame_index: int, image: np.ndarray) -> None:
        cfg = self.config
        live = self.tracker.live().ids
        if len(live):
            self.tracker.remove(live)
        gray = to_gray(image)
        h, w = gray.shape
        score = texture_score(gray, cfg.anchor_score)
        k = cfg.anchor_grid
        anchors = grid_points(score, k, k, border=cfg.border_px)
        rng = np.random.default_rng([cfg.seed, frame_index])
        border = min(cfg.border_px, max((min(w, h) - 1) // 2, 0))
        detection = random_points(w, h, cfg.oversample * cfg.n_detection, rng, border=border)
        if cfg.min_texture_frac > 0 and len(detection):
            # A point-tracker follows texture: random points on blank surfaces (asphalt, sky,
            # walls) drift and would look like movers, so candidates below a share of the
            # frame's strong texture are skipped (CoTracker's learned features need not).
            floor = cfg.min_texture_frac * float(np.quantile(score, 0.9))
            ij = detection.astype(int)
            detection = detection[score[ij[:, 1], ij[:, 0]] >= floor]
        detection = detection[:cfg.n_detection]
        pts = np.concatenate([anchors, detection]).astype(np.float32)
        self._ids = self.tracker.add_points(pts) if len(pts) else np.zeros(0, np.int64)
        self._n_anchors = len(anchors)
        self._indices = [int(frame_index)]
        self._rows = [pts]

    def _captured(self, row: np.ndarray) -> np.ndarray:
        """(N,) bool: tracks whose step jumped, beyond the jump common to all tracks (camera
        shake), by more than ``capture_change_px + capture_change_frac * |previous step|``.
        A point on a surface keeps a smooth image velocity; a window that an occluding mover
        sweeps over drags the track onto the mover (it would then look dynamic in frames where
        it was still on the background), so such a track ends here."""
        cfg = self.config
        step = row - self._rows[-1]
        prev = self._rows[-1] - self._rows[-2]
        change = step - prev
        ok = np.isfinite(change).all(axis=1)
        out = np.zeros(len(row), bool)
        if ok.sum() < 3:
            return out
        change = change - np.median(change[ok], axis=0)
        prev_len = np.linalg.norm(prev - np.median(prev[ok], axis=0), axis=1)
        limit = cfg.capture_change_px + cfg.capture_change_frac * prev_len
        out[ok] = np.linalg.norm(change[ok], axis=1) > limit[ok]
        return out

    def _window(self) -> TrackWindow:
        return TrackWindow(np.asarray(self._indices, np.int64), np.stack(self._rows),
                           self._n_anchors, self._ids.copy())

    def push(self, frame_index: int, image: np.ndarray) -> TrackWindow | None:
        update = self.tracker.step(image)
        if not self._indices:
            self._start(frame_index, image)
            return None
        row = np.full((len(self._ids), 2), np.nan, np.float32)
        pos = {int(i): k for k, i in enumerate(self._ids)}
        for i, p, v in zip(update.ids, update.points, update.visible):
            k = pos.get(int(i))
            if k is not None and v:
                row[k] = p
        # A track lost earlier never comes back: keep it NaN even if an id were reused.
        row[~np.isfinite(self._rows[-1]).all(axis=1)] = np.nan
        if len(self._rows) >= 2 and self.config.capture_change_px > 0:
            row[self._captured(row)] = np.nan
        self._indices.append(int(frame_index))
        self._rows.append(row)
        tracked = float(np.isfinite(row).all(axis=1).mean()) if len(row) else 1.0
        if len(self._indices) < self.config.window and tracked >= self.config.min_tracked_frac:
            return None
        done = self._window()
        self._closed_any = True
        self._start(frame_index, image)
        return done

    def flush(self) -> TrackWindow | None:
        if not self._indices or (len(self._indices) == 1 and self._closed_any):
            self._indices, self._rows = [], []
            return None
        done = self._window()
        self._indices, self._rows = [], []
        return done
