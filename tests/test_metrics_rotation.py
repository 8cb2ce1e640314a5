"""Rotation-only metrics for GT that never translates (a tripod pan), where Sim(3) ATE is undefined."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eval.metrics import (RotationMetrics, Trajectory, TrajectoryMetrics, evaluate_rotation,
                          evaluate_trajectory, gt_is_stationary, score_trajectory)
from mona_vo.errors import EvalError


def _pan(n=20, deg_per_frame=1.5, centre=(0.3, -0.1, 2.0)):
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_euler("y", (np.arange(n) * deg_per_frame)[:, None], degrees=True).as_matrix()
    T[:, :3, 3] = centre
    return Trajectory(np.arange(n, dtype=float), T)


def test_tripod_gt_is_stationary_and_sim3_ate_is_refused():
    gt = _pan()
    assert gt_is_stationary(gt)
    with pytest.raises(EvalError):
        evaluate_trajectory(gt, gt)


def test_rotation_error_ignores_a_global_rotation_and_measures_a_per_frame_one():
    gt = _pan()
    off = Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix()
    est = gt.poses_T_world_cam.copy()
    est[:, :3, :3] = off @ est[:, :3, :3]  # another world frame: no error
    est[:, :3, 3] = 0.0
    r = evaluate_rotation(gt, Trajectory(gt.timestamps, est))
    assert r.rot_rmse_deg < 1e-6 and r.rpe_rot_deg < 1e-6 and r.est_translation_extent == 0.0

    est[7, :3, :3] = est[7, :3, :3] @ Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    est[12, :3, 3] = [0.5, 0, 0]
    r = evaluate_rotation(gt, Trajectory(gt.timestamps, est))
    assert 1.7 < r.rot_max_deg < 2.1
    assert 0.3 < r.rot_rmse_deg < 0.6
    assert r.est_translation_extent == pytest.approx(0.5)
    assert r.n_matched == 20


def test_score_trajectory_chooses_rotation_errors_for_a_tripod_and_sim3_ate_otherwise():
    gt = _pan()
    est = gt.poses_T_world_cam.copy()
    est[5, :3, :3] = est[5, :3, :3] @ Rotation.from_euler("x", 1.0, degrees=True).as_matrix()
    est = Trajectory(gt.timestamps, est)
    r = score_trajectory(gt, est)
    assert isinstance(r, RotationMetrics)
    assert r.rot_max_deg == pytest.approx(evaluate_rotation(gt, est).rot_max_deg)

    walk = gt.poses_T_world_cam.copy()
    walk[:, :3, 3] = np.stack([np.arange(20) * 0.1, np.sin(np.arange(20)), np.zeros(20)], axis=1)
    walk = Trajectory(gt.timestamps, walk)
    noisy = walk.poses_T_world_cam.copy()
    noisy[3, :3, 3] += [0.05, 0.0, 0.0]
    m = score_trajectory(walk, Trajectory(gt.timestamps, noisy))
    assert isinstance(m, TrajectoryMetrics) and m.ate > 0.005
    assert m.ate == evaluate_trajectory(walk, Trajectory(gt.timestamps, noisy)).ate
