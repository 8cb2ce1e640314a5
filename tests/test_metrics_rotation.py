"""Rotation-only metrics for GT that never translates (a tripod pan), where Sim(3) ATE is undefined."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eval.metrics import Trajectory, evaluate_rotation, evaluate_trajectory, gt_is_stationary
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
