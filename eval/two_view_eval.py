"""Two-view initialisation on a real pair against ground truth (``mona-vo eval two-view``).

The VO's own steps, nothing else: points on the VO's start grid, ``start_grid`` squared (best
texture per cell above the VO's floor, :func:`mona_vo.point_selection.seed_points`), tracked from
image0 to image1 by the VO's default tracker (``lk``, :class:`mona_vo.tracking.LKTracker`, its
forward-backward check dropping lost tracks), then :func:`mona_vo.two_view.relative_pose`
(five-point RANSAC, unit-norm translation).

Ground truth: rows i and j of a KITTI pose file (``T_world_cam``, one per line), relative pose
``T_i_j = inv(T_world_i) T_world_j``. Errors:

- ``rotation_error_deg``: angle of ``R_est^T R_gt``, degrees;
- ``translation_direction_error_deg``: angle between the estimated and the GT translation
  directions (the monocular scale is unknown), degrees.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mona_vo.errors import EvalError
from mona_vo.geometry import angle_between_deg


@dataclass(frozen=True)
class TwoViewEvalResult:
    """Errors of the two-view relative pose of one pair (module docstring)."""

    rotation_error_deg: float               # angle of R_est^T R_gt, degrees
    translation_direction_error_deg: float  # angle between unit translations, degrees
    gt_rotation_deg: float                  # angle of the GT relative rotation, degrees
    gt_translation_m: float                 # length of the GT relative translation, metres
    points: int                             # grid points started in image0
    tracked: int                            # of them tracked into image1
    inliers: int                            # essential-matrix inliers in front of both views
    median_parallax_deg: float              # rotation-free ray angle of the inliers, degrees
    T_i_j_est: list                         # 4x4 estimate (translation of unit norm), row-major
    T_i_j_gt: list                          # 4x4 GT relative pose, metres

    def to_dict(self) -> dict:
        return asdict(self)


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle in degrees of the rotation between two 3x3 rotation matrices."""
    from mona_vo.conventions import rotation_angle_deg

    return rotation_angle_deg(np.asarray(R_est).T @ np.asarray(R_gt))


def direction_error_deg(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Angle in degrees between two 3-vectors (scale-free); EvalError for a zero vector."""
    a, b = np.asarray(t_est, float).ravel(), np.asarray(t_gt, float).ravel()
    if np.linalg.norm(a) == 0 or np.linalg.norm(b) == 0:
        raise EvalError("translation direction undefined for a zero translation")
    return float(angle_between_deg(a, b))


def track_grid(image0: np.ndarray, image1: np.ndarray, *, grid_size: int | None = None,
               point_score: str | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Grid points of image0, seeded as the VO seeds them, tracked into image1 with its tracker.

    image0, image1: (H, W, 3) uint8 RGB (or (H, W) grey). grid_size defaults to
    :class:`mona_vo.vo.VOConfig`'s start grid (``start_grid``), point_score to its own.
    Returns (N, 2) float64 pixels x, y in image0, the same
    points in image1, and the number of points started.
    """
    from mona_vo.point_selection import seed_points
    from mona_vo.tracking import to_gray
    from mona_vo.pipeline import PipelineConfig
    from mona_vo.vo import VOConfig

    cfg = VOConfig()
    k = grid_size or cfg.start_grid
    # The VO's own seeding rule (seed_points: its grid and its texture floor), so the pair
    # measured is the pair the VO would start from.
    pts = seed_points(to_gray(image0), k, point_score or cfg.point_score, cfg.point_min_score,
                      cfg.point_quality)
    tracker = PipelineConfig().build_tracker()
    tracker.step(image0)
    ids = tracker.add_points(pts)
    upd = tracker.step(image1)
    order = {int(i): n for n, i in enumerate(ids)}
    sel = [order[int(i)] for i in upd.ids[upd.visible]]
    return (pts[sel].astype(np.float64), upd.points[upd.visible].astype(np.float64), len(pts))


def evaluate_two_view(image0: str | Path, image1: str | Path, calib: str, gt_poses: str | Path,
                      rows: tuple[int, int], *, grid_size: int | None = None) -> TwoViewEvalResult:
    """Relative pose of image1 w.r.t. image0 by the VO's tracker and five-point solver, against
    rows ``(i, j)`` of the KITTI pose file ``gt_poses``. ``calib``: fx,fy,cx,cy or a file (a
    KITTI calib.txt gives camera P0)."""
    from data_tools.calibration import parse_calibration
    from data_tools.frames import decode_image
    from data_tools.kitti import read_kitti_poses
    from mona_vo.conventions import relative_pose as gt_relative, rotation_angle_deg
    from mona_vo.two_view import relative_pose

    im0, im1 = decode_image(Path(image0)), decode_image(Path(image1))
    if im0.shape != im1.shape:
        raise EvalError(f"{image0} and {image1} differ in size")
    h, w = im0.shape[:2]
    intr = parse_calibration(str(calib), w, h)
    poses = read_kitti_poses(gt_poses)
    i, j = rows
    for r in (i, j):
        if not 0 <= r < len(poses):
            raise EvalError(f"{gt_poses}: row {r} out of range (the file has {len(poses)} poses, "
                            "rows count from 0)")
    T_gt = gt_relative(poses[i], poses[j])
    pa, pb, n_started = track_grid(im0, im1, grid_size=grid_size)
    rel = relative_pose(pa, pb, intr, intr)
    if rel is None:
        raise EvalError(f"no relative pose: {len(pa)} of {n_started} grid points tracked, the "
                        "five-point RANSAC found no essential matrix")
    T_est = rel.T_a_b
    return TwoViewEvalResult(
        rotation_error_deg=rotation_error_deg(T_est[:3, :3], T_gt[:3, :3]),
        translation_direction_error_deg=direction_error_deg(T_est[:3, 3], T_gt[:3, 3]),
        gt_rotation_deg=rotation_angle_deg(T_gt[:3, :3]),
        gt_translation_m=float(np.linalg.norm(T_gt[:3, 3])),
        points=n_started, tracked=len(pa), inliers=rel.n_inliers,
        median_parallax_deg=rel.median_parallax_deg,
        T_i_j_est=np.round(T_est, 6).tolist(), T_i_j_gt=np.round(T_gt, 6).tolist())
