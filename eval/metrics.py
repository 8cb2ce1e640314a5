"""Camera-trajectory metrics (ATE, RPE) that equal evo's numbers on the same input.

The maths is evo's own (``evo.core``: timestamp association, Umeyama alignment, APE, RPE); this
module only fixes the protocol of REFERENCE.md section 4 (MPI Sintel, as in LEAP-VO's and
ParticleSfM's scripts) and converts mona-vo's arrays to evo's objects and back:

- association: ``evo.core.sync.associate_trajectories(gt, est, max_diff)`` (nearest timestamp,
  starting from the shorter trajectory), exactly as ``evo_ape tum GT EST`` does;
- alignment: one global Umeyama alignment of the estimate onto the GT positions, Sim(3)
  (``-a -s``), SE(3) (``-a``) or none;
- ATE: APE of the translation part, RMSE, after the alignment;
- RPE: ``delta=1 frames, all_pairs=True`` (``rel_delta_tol=0.01`` is irrelevant for frames),
  translation part and rotation angle in degrees, RMSE, computed on the *same globally aligned*
  estimate. That is what ``evo_rpe ... -a -s`` does: ``evo.main_rpe.rpe`` aligns the whole
  estimate with ``traj_est.align(traj_ref, correct_scale)`` before ``metrics.RPE``. A rigid
  alignment does not change an RPE, the Sim(3) scale does: after it the relative translations of
  the estimate are in GT units (metres);
- window scales (mona-vo's, not evo's; on request): the aligned estimate's path length over the
  GT's per run of N matched steps, which places a monocular scale collapse in time;
- heading (mona-vo's, not evo's): the median over matched steps of the angle between the
  estimated and the true direction of travel, each in its own camera's axes at the step's start
  (:func:`heading_errors_deg`). It needs no alignment and no scale, but it needs GT poses in
  the camera's own axes (generated scenes, Sintel, KITTI; not Bonn's, whose GT is a motion-
  capture marker's frame turned about 178 deg from the camera's). ATE can hide a wrong
  direction: on a short, nearly straight path a Sim(3) alignment turns a camera that went the
  wrong way onto the true line (generated slow pan, mixed 207: 0.81 % of path with its
  translation 133 deg off).

Only ``evo.core`` is imported (``evo.tools`` pulls rosbags and matplotlib), lazily inside the
functions so that importing this module stays cheap. Nothing here touches files.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from enum import Enum, unique

import numpy as np

from mona_vo.errors import EvalError

logger = logging.getLogger(__name__)

# Matched poses needed for a metric: Umeyama in 3-D needs >= 3 non-collinear points, and RPE needs
# at least one pair.
MIN_MATCHED_POSES = 3


@unique
class Alignment(str, Enum):
    """Global alignment of the estimate onto the GT before the errors are taken.

    A ``str`` enum: ``Alignment.SIM3 == "sim3"`` holds, so plain strings are accepted everywhere.
    """

    SIM3 = "sim3"  # rotation, translation and scale (monocular VO; evo_ape -a -s)
    SE3 = "se3"  # rotation and translation (metric VO, stereo/RGB-D; evo_ape -a)
    NONE = "none"  # compare as given


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timestamped camera poses, mona-vo conventions (see ``mona_vo.conventions``).

    Fields
        timestamps: (N,) float64, seconds (TUM) or frame numbers (Sintel, KITTI: ``arange(N)``);
            non-decreasing (equal neighbours occur in real mocap GT, e.g. TUM fr2/desk, and evo
            accepts them).
        poses_T_world_cam: (N, 4, 4) float64 camera-to-world rigid transforms; ``[:, :3, 3]`` are
            the camera centres in the world frame (metres for GT, arbitrary units for monocular VO).

    The constructor stores read-only float64 copies, so the trajectory cannot change after it is
    built and the caller's arrays are never shared. Shapes and values are validated by
    :meth:`check`, not on construction, so a reader can build first and report problems after.
    """

    timestamps: np.ndarray
    poses_T_world_cam: np.ndarray

    def __post_init__(self) -> None:
        for name in ("timestamps", "poses_T_world_cam"):
            arr = np.array(getattr(self, name), dtype=np.float64, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @classmethod
    def from_poses(cls, poses_T_world_cam: np.ndarray, timestamps: np.ndarray | None = None
                   ) -> "Trajectory":
        """Trajectory of (N, 4, 4) camera-to-world poses; timestamps default to ``arange(N)``
        (frame numbers, for formats without time such as KITTI)."""
        poses = np.asarray(poses_T_world_cam, dtype=np.float64)
        if timestamps is None:
            timestamps = np.arange(len(poses), dtype=np.float64)
        return cls(timestamps=timestamps, poses_T_world_cam=poses)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0]) if self.timestamps.ndim == 1 else 0

    @property
    def positions_xyz(self) -> np.ndarray:
        """(N, 3) float64 camera centres in the world frame (a read-only view)."""
        return self.poses_T_world_cam[:, :3, 3]

    def check(self, name: str = "trajectory", rigid_tol: float = 1e-5) -> None:
        """Raise :class:`EvalError` (one line, naming ``name``) unless the trajectory is usable.

        Checks: shapes (N,) and (N, 4, 4) with N >= 1, finite values, sorted (non-decreasing)
        timestamps, and rigid poses: ``|R R^T - I| <= rigid_tol``, ``|det R - 1| <= rigid_tol``,
        last row ``0 0 0 1``. The default tolerance accepts rotations written with float32
        precision (KITTI files of ORB-SLAM reach 8e-7) and still rejects scaled or sheared ones.
        """
        ts, poses = self.timestamps, self.poses_T_world_cam
        if ts.ndim != 1 or ts.shape[0] == 0:
            raise EvalError(f"{name}: timestamps must be a non-empty (N,) array, got shape "
                            f"{ts.shape}")
        if poses.shape != (ts.shape[0], 4, 4):
            raise EvalError(f"{name}: poses must have shape ({ts.shape[0]}, 4, 4) to match "
                            f"{ts.shape[0]} timestamps, got {poses.shape}")
        bad = np.flatnonzero(~np.isfinite(ts))
        if bad.size:
            raise EvalError(f"{name}: timestamp {bad[0]} is not finite")
        bad = np.flatnonzero(~np.isfinite(poses).all(axis=(1, 2)))
        if bad.size:
            raise EvalError(f"{name}: pose {bad[0]} (t={ts[bad[0]]:.6f}) is not finite")
        # evo's association assumes sorted stamps (binary search) and silently switches to a
        # different matching otherwise; an unsorted file is almost always a writer bug, so refuse.
        bad = np.flatnonzero(np.diff(ts) < 0)
        if bad.size:
            i = bad[0] + 1
            raise EvalError(f"{name}: timestamps must be sorted, timestamp {i} ({ts[i]:.6f}) "
                            f"comes after {ts[i - 1]:.6f}")
        R = poses[:, :3, :3]
        ortho_err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
        det_err = np.abs(np.linalg.det(R) - 1.0)
        row_err = np.abs(poses[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
        bad = np.flatnonzero((ortho_err > rigid_tol) | (det_err > rigid_tol)
                             | (row_err > rigid_tol))
        if bad.size:
            i = bad[0]
            raise EvalError(f"{name}: pose {i} (t={ts[i]:.6f}) is not a rigid transform "
                            f"(|R R^T - I| = {ortho_err[i]:.2g}, |det R - 1| = {det_err[i]:.2g}, "
                            f"last row {poses[i, 3].tolist()})")


@dataclass(frozen=True)
class TrajectoryMetrics:
    """Errors of an estimated trajectory against GT, in GT units (metres) unless stated."""

    ate: float  # APE translation RMSE after alignment, GT units
    rpe_trans: float  # RPE translation RMSE, delta 1 frame, all pairs, GT units
    rpe_rot_deg: float  # RPE rotation-angle RMSE, delta 1 frame, all pairs, degrees
    n_matched: int  # poses associated between GT and estimate (evo's rule)
    scale: float  # Sim(3) scale applied to the estimate; 1.0 for se3/none
    path_length: float  # GT path length over the matched poses, GT units
    ate_percent_of_path: float  # 100 * ate / path_length; NaN when the GT does not move
    alignment: Alignment  # 'sim3' | 'se3' | 'none'
    window_scales: tuple = ()  # :func:`window_scales` rows, when asked for (scale_window > 0)
    heading_deg: float = float("nan")  # median direction-of-travel error, degrees
                                       # (:func:`heading_errors_deg`); NaN without a moving step

    def to_dict(self) -> dict:
        """JSON-able dict: Python floats and ints, the alignment as its string, NaN as None."""
        def num(x: float) -> float | None:
            return None if not math.isfinite(x) else float(x)

        return {
            "ate": num(self.ate),
            "rpe_trans": num(self.rpe_trans),
            "rpe_rot_deg": num(self.rpe_rot_deg),
            "n_matched": int(self.n_matched),
            "scale": num(self.scale),
            "path_length": num(self.path_length),
            "ate_percent_of_path": num(self.ate_percent_of_path),
            "alignment": Alignment(self.alignment).value,
            "heading_deg": num(self.heading_deg),
            **({"window_scales": [dict(w) for w in self.window_scales]}
               if self.window_scales else {}),
        }


def path_length(positions: np.ndarray) -> float:
    """Arc length of a polyline: sum of the distances between consecutive (N, 3) positions,
    in their units. 0.0 for fewer than two positions. Same value as evo's ``path_length``."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def window_scales(gt_xyz: np.ndarray, est_xyz: np.ndarray, window: int) -> list[dict]:
    """Where a monocular estimate's scale drifts: for consecutive runs of ``window`` steps
    between matched poses ((N, 3) GT and aligned estimate positions, same order), the estimate's
    path length over the GT's. After a Sim(3) alignment 1 is the run's own scale; a value near 0
    means the estimate stopped translating while the camera moved (a scale collapse), a large
    one a jump. One global ATE cannot say where either happened.

    Rows: ``first`` and ``last`` (matched-pose indices, each window sharing its ends with the
    next), ``gt_path`` and ``est_path`` (GT units) and ``ratio`` (None where the GT did not
    move). The last window may be shorter."""
    if window < 1:
        raise EvalError(f"the scale window must be at least 1 step, got {window}")
    g = np.asarray(gt_xyz, np.float64)
    e = np.asarray(est_xyz, np.float64)
    rows = []
    for a in range(0, len(g) - 1, window):
        b = min(a + window, len(g) - 1)
        gp, ep = path_length(g[a:b + 1]), path_length(e[a:b + 1])
        rows.append({"first": a, "last": b, "gt_path": gp, "est_path": ep,
                     "ratio": ep / gp if gp > 0 else None})
    return rows


def heading_errors_deg(gt_T: np.ndarray, est_T: np.ndarray, min_step: float = 1e-9) -> np.ndarray:
    """(N-1,) angle in degrees between the estimated and the true direction of travel of each
    step i -> i+1 of matched camera-to-world poses (N, 4, 4), each direction in the axes of its
    own camera at i: ``R_i^T (c_{i+1} - c_i)``. A similarity transform of either world leaves it
    unchanged, so it needs no alignment. NaN where either step is shorter than ``min_step`` (its
    own units): a camera that did not move has no direction."""
    from mona_vo.geometry import angle_between_deg

    def directions(T):
        T = np.asarray(T, np.float64)
        d = np.einsum("nji,nj->ni", T[:-1, :3, :3], T[1:, :3, 3] - T[:-1, :3, 3])
        return np.where((np.linalg.norm(d, axis=1) > min_step)[:, None], d, np.nan)
    return angle_between_deg(directions(gt_T), directions(est_T))


def _to_evo(traj: Trajectory, name: str):
    """evo ``PoseTrajectory3D`` over *copies* of the poses: evo's align/transform replace its
    pose list, but copying keeps the caller's data out of reach whatever evo version runs."""
    from evo.core.trajectory import PoseTrajectory3D

    poses = np.array(traj.poses_T_world_cam, dtype=np.float64, copy=True)
    return PoseTrajectory3D(poses_se3=list(poses),
                            timestamps=np.array(traj.timestamps, dtype=np.float64, copy=True),
                            name=name)


def _match(gt_evo, est_evo, *, associate: bool, max_diff: float):
    """GT and estimate reduced to the matched poses, same length and order."""
    from evo.core import sync

    if associate:
        try:
            gt_m, est_m = sync.associate_trajectories(gt_evo, est_evo, max_diff=max_diff)
        except sync.SyncException:
            n = 0
        else:
            n = gt_m.num_poses
        if n < MIN_MATCHED_POSES:
            raise EvalError(f"only {n} estimated poses matched a GT timestamp within "
                            f"max_diff={max_diff:g} (GT {gt_evo.num_poses} poses, estimate "
                            f"{est_evo.num_poses}); at least {MIN_MATCHED_POSES} are needed")
        return gt_m, est_m
    if gt_evo.num_poses != est_evo.num_poses:
        raise EvalError(f"index matching (associate=False) needs trajectories of equal length, "
                        f"got GT {gt_evo.num_poses} and estimate {est_evo.num_poses} poses")
    if gt_evo.num_poses < MIN_MATCHED_POSES:
        raise EvalError(f"only {gt_evo.num_poses} poses matched by index (associate=False); at "
                        f"least {MIN_MATCHED_POSES} are needed")
    return gt_evo, est_evo


def evaluate_trajectory(gt: Trajectory, est: Trajectory, *, align: Alignment | str = "sim3",
                        max_diff: float = 0.01, associate: bool = True,
                        scale_window: int = 0) -> TrajectoryMetrics:
    """ATE and RPE of ``est`` against ``gt`` with the Sintel protocol, equal to evo's numbers.

    Args:
        gt: ground truth, camera-to-world, metres.
        est: estimate, camera-to-world, any scale when ``align='sim3'``.
        align: ``'sim3'`` (``evo_ape -a -s``), ``'se3'`` (``-a``) or ``'none'``.
        max_diff: largest timestamp difference for a GT/estimate pair, in timestamp units
            (seconds; frames for Sintel/KITTI numbering). evo's default 0.01.
        associate: True associates by nearest timestamp (evo's ``associate_trajectories``);
            False pairs pose i with pose i and needs equal lengths (KITTI pose files).
        scale_window: > 0 adds :func:`window_scales` over this many steps of the aligned
            estimate (``TrajectoryMetrics.window_scales``).

    Returns:
        :class:`TrajectoryMetrics`. ``gt`` and ``est`` are not modified.

    Raises:
        EvalError: invalid trajectory, unknown alignment, fewer than 3 matched poses, or a
            degenerate alignment (e.g. all matched GT positions on one line).
    """
    from evo.core import geometry, metrics
    from evo.core.metrics import PoseRelation, StatisticsType, Unit

    try:
        alignment = Alignment(align)
    except ValueError:
        raise EvalError(f"unknown alignment {align!r}; choose one of "
                        f"{', '.join(a.value for a in Alignment)}") from None
    try:
        max_diff = float(max_diff)
    except (TypeError, ValueError):
        raise EvalError(f"max_diff must be a number, got {max_diff!r}") from None
    if not (math.isfinite(max_diff) and max_diff >= 0):
        raise EvalError(f"max_diff must be a finite number >= 0, got {max_diff!r}")
    gt.check("ground truth")
    est.check("estimate")

    gt_m, est_m = _match(_to_evo(gt, "ground truth"), _to_evo(est, "estimate"),
                         associate=associate, max_diff=max_diff)
    n = gt_m.num_poses
    length = path_length(gt_m.positions_xyz)

    scale = 1.0
    if alignment is not Alignment.NONE:
        try:
            # In place on est_m, which is already a copy (association or _to_evo made it).
            _, _, s = est_m.align(gt_m, correct_scale=alignment is Alignment.SIM3)
        except geometry.GeometryException as exc:
            raise EvalError(f"{alignment.value} alignment of {n} matched poses failed: {exc} "
                            f"(the matched positions are collinear or all the same)"
                            ) from None
        scale = float(s)

    ape = metrics.APE(PoseRelation.translation_part)
    ape.process_data((gt_m, est_m))
    ate = float(ape.get_statistic(StatisticsType.rmse))

    rpe = {}
    for relation in (PoseRelation.translation_part, PoseRelation.rotation_angle_deg):
        metric = metrics.RPE(relation, delta=1, delta_unit=Unit.frames, rel_delta_tol=0.01,
                             all_pairs=True)
        metric.process_data((gt_m, est_m))
        rpe[relation] = float(metric.get_statistic(StatisticsType.rmse))

    percent = 100.0 * ate / length if length > 0 else float("nan")
    heading = heading_errors_deg(np.array(gt_m.poses_se3), np.array(est_m.poses_se3))
    heading = heading[np.isfinite(heading)]
    logger.debug("evaluated %d matched poses (%s): ATE %.6g, RPE %.6g / %.6g deg, scale %.6g",
                 n, alignment.value, ate, rpe[PoseRelation.translation_part],
                 rpe[PoseRelation.rotation_angle_deg], scale)
    return TrajectoryMetrics(ate=ate, rpe_trans=rpe[PoseRelation.translation_part],
                             rpe_rot_deg=rpe[PoseRelation.rotation_angle_deg], n_matched=int(n),
                             scale=scale, path_length=length, ate_percent_of_path=percent,
                             alignment=alignment,
                             heading_deg=float(np.median(heading)) if len(heading) else float("nan"),
                             window_scales=tuple(window_scales(
                                 gt_m.positions_xyz, est_m.positions_xyz, scale_window))
                             if scale_window else ())


@dataclass(frozen=True)
class RotationMetrics:
    """Errors of a trajectory whose GT camera centre never moves (a tripod pan), where ATE after
    Sim(3) alignment is undefined: there is no GT translation to fix a scale or a position."""

    rot_rmse_deg: float  # orientation error RMSE after the best global rotation, degrees
    rot_max_deg: float  # the largest per-pose orientation error, degrees
    rpe_rot_deg: float  # RPE rotation-angle RMSE, delta 1 frame, degrees (evo's metric)
    n_matched: int  # poses associated between GT and estimate (evo's rule)
    est_translation_extent: float  # largest distance of an estimated centre from the first, est units

    def to_dict(self) -> dict:
        return {k: (float(v) if isinstance(v, float) else int(v)) for k, v in self.__dict__.items()}


def gt_is_stationary(gt: Trajectory, tol: float = 1e-9) -> bool:
    """True when every GT camera centre lies within ``tol`` (GT units) of the first one."""
    p = np.asarray(gt.poses_T_world_cam, dtype=np.float64)[:, :3, 3]
    return bool(len(p) and np.linalg.norm(p - p[0], axis=1).max() <= tol)


def evaluate_rotation(gt: Trajectory, est: Trajectory, *, max_diff: float = 0.01,
                      associate: bool = True) -> RotationMetrics:
    """Orientation errors of ``est`` against ``gt`` after the one rotation that best aligns them
    (the chordal mean of ``R_gt_i R_est_i^T``, projected onto SO(3)), for GT that only rotates.
    Association as :func:`evaluate_trajectory`; ``gt`` and ``est`` are not modified."""
    from evo.core import metrics
    from evo.core.metrics import PoseRelation, StatisticsType, Unit

    gt.check("ground truth")
    est.check("estimate")
    gt_m, est_m = _match(_to_evo(gt, "ground truth"), _to_evo(est, "estimate"),
                         associate=associate, max_diff=float(max_diff))
    R_gt = np.array([T[:3, :3] for T in gt_m.poses_se3])
    R_est = np.array([T[:3, :3] for T in est_m.poses_se3])
    U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", R_gt, R_est))
    R_align = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    E = np.einsum("nji,jk,nkl->nil", R_gt, R_align, R_est)  # R_gt^T R_align R_est
    from scipy.spatial.transform import Rotation

    err = np.degrees(Rotation.from_matrix(E).magnitude())  # exact near zero, unlike arccos
    rpe = metrics.RPE(PoseRelation.rotation_angle_deg, delta=1, delta_unit=Unit.frames,
                      rel_delta_tol=0.01, all_pairs=True)
    rpe.process_data((gt_m, est_m))
    c = est_m.positions_xyz
    return RotationMetrics(rot_rmse_deg=float(np.sqrt(np.mean(err ** 2))), rot_max_deg=float(err.max()),
                           rpe_rot_deg=float(rpe.get_statistic(StatisticsType.rmse)),
                           n_matched=int(gt_m.num_poses),
                           est_translation_extent=float(np.linalg.norm(c - c[0], axis=1).max()))


def score_trajectory(gt: Trajectory, est: Trajectory, *, max_diff: float = 0.01,
                     associate: bool = True) -> TrajectoryMetrics | RotationMetrics:
    """The errors that exist for this GT, the one choice every benchmark makes here: a GT whose
    camera never translates (a tripod pan, :func:`gt_is_stationary`) has no Sim(3) ATE -- no
    translation fixes a scale or a position -- so it gets :func:`evaluate_rotation` (orientation
    errors, and how far the estimate wandered); any other GT :func:`evaluate_trajectory` with
    Sim(3) alignment. Raises :class:`EvalError` as those do."""
    if gt_is_stationary(gt):
        return evaluate_rotation(gt, est, max_diff=max_diff, associate=associate)
    return evaluate_trajectory(gt, est, max_diff=max_diff, associate=associate)
