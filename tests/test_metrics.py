"""eval.metrics: ATE/RPE equal evo's on real trajectories, and known answers on synthetic ones.

The reference numbers come from evo itself, run the way ``evo_ape`` / ``evo_rpe`` run:
``evo.tools.file_interface`` reads the files, ``traj_ref.sync_with`` associates TUM trajectories,
and the library functions behind the commands (``evo.main_ape.ape``, ``evo.main_rpe.rpe``) align
and compute, each on its own deep copies because they work in place.
"""
from __future__ import annotations

import copy
import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eval.metrics import (Alignment, Trajectory, TrajectoryMetrics, evaluate_trajectory,
                          heading_errors_deg, path_length, window_scales)
from mona_vo.conventions import make_pose, pose_from_tum_row
from mona_vo.errors import EvalError

DATA = Path("/work/shared/data/evo_trajectories")
needs_data = pytest.mark.skipif(not DATA.is_dir(),
                                reason=f"evo example trajectories absent ({DATA})")

TOL = 1e-6


# ----------------------------------------------------------------------------------------------
# evo reference
# ----------------------------------------------------------------------------------------------

def _evo_read(name: str):
    from evo.tools import file_interface

    path = DATA / name
    if name.startswith("KITTI"):
        return file_interface.read_kitti_poses_file(str(path))
    return file_interface.read_tum_trajectory_file(str(path))


def _evo_reference(gt_name: str, est_name: str, correct_scale: bool) -> dict:
    """ATE, RPE trans/rot, matched poses and Sim(3) scale as evo_ape/evo_rpe compute them with
    ``-a`` (and ``-s`` when ``correct_scale``), ``--delta 1 --delta_unit f --all_pairs``."""
    from evo.core import lie_algebra
    from evo.core.metrics import PoseRelation, Unit
    from evo.core.trajectory import PoseTrajectory3D
    from evo.main_ape import ape
    from evo.main_rpe import rpe

    ref, est = _evo_read(gt_name), _evo_read(est_name)
    if isinstance(ref, PoseTrajectory3D):
        ref, est = ref.sync_with(est, max_diff=0.01)
    res = ape(copy.deepcopy(ref), copy.deepcopy(est), PoseRelation.translation_part, align=True,
              correct_scale=correct_scale)
    out = {
        "ate": res.stats["rmse"],
        "n": ref.num_poses,
        "scale": lie_algebra.sim3_scale(res.np_arrays["alignment_transformation_sim3"]),
    }
    for key, relation in (("rpe_trans", PoseRelation.translation_part),
                          ("rpe_rot_deg", PoseRelation.rotation_angle_deg)):
        res = rpe(copy.deepcopy(ref), copy.deepcopy(est), relation, delta=1, delta_unit=Unit.frames,
                  rel_delta_tol=0.01, all_pairs=True, align=True, correct_scale=correct_scale)
        out[key] = res.stats["rmse"]
    return out


def _ours_from_evo_file(name: str) -> Trajectory:
    """Our Trajectory from evo's reading of a file (KITTI files have no time: frame numbers)."""
    traj = _evo_read(name)
    stamps = getattr(traj, "timestamps", None)
    return Trajectory.from_poses(np.array(traj.poses_se3), stamps)


def _read_tum_with_conventions(path: Path) -> Trajectory:
    """A reader independent of evo: mona-vo's own TUM row conversion."""
    rows = np.loadtxt(path, comments="#")
    stamps, poses = zip(*(pose_from_tum_row(r) for r in rows))
    return Trajectory(np.array(stamps), np.stack(poses))


REAL_CASES = [
    # (GT, estimate, alignment, associate by time)
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam_drift.txt", "sim3", True),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam_drift.txt", "se3", True),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB_kf_mono.txt", "sim3", True),
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt", "se3", False),
]


@needs_data
@pytest.mark.parametrize("gt_name, est_name, align, associate", REAL_CASES,
                         ids=["fr1_xyz-sim3", "fr1_xyz-se3", "fr2_desk_mono-sim3",
                              "kitti00_orb-se3"])
def test_metrics_equal_evo_on_real_trajectories(gt_name, est_name, align, associate):
    ref = _evo_reference(gt_name, est_name, correct_scale=align == "sim3")
    got = evaluate_trajectory(_ours_from_evo_file(gt_name), _ours_from_evo_file(est_name),
                              align=align, associate=associate)
    assert got.n_matched == ref["n"]
    assert got.ate == pytest.approx(ref["ate"], abs=TOL)
    assert got.rpe_trans == pytest.approx(ref["rpe_trans"], abs=TOL)
    assert got.rpe_rot_deg == pytest.approx(ref["rpe_rot_deg"], abs=TOL)
    assert got.scale == pytest.approx(ref["scale"], abs=TOL)
    assert got.alignment == align
    # Sanity of the protocol itself: errors well under the GT path length.
    assert 0 < got.ate_percent_of_path < 1.0


@needs_data
def test_tum_files_read_through_mona_conventions_give_evo_numbers():
    gt = _read_tum_with_conventions(DATA / "freiburg1_xyz-groundtruth.txt")
    est = _read_tum_with_conventions(DATA / "freiburg1_xyz-rgbdslam_drift.txt")
    ref = _evo_reference("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam_drift.txt",
                         correct_scale=True)
    got = evaluate_trajectory(gt, est, align="sim3")
    assert got.n_matched == ref["n"]
    for key in ("ate", "rpe_trans", "rpe_rot_deg", "scale"):
        assert getattr(got, key) == pytest.approx(ref[key], abs=TOL)


def _stored_evo_result(zip_name: str) -> tuple[dict, dict, np.ndarray]:
    """info.json, stats.json and the error array of an evo --save_results zip (2018 layout, the
    .npz member is a plain .npy array)."""
    with zipfile.ZipFile(DATA / "res_files" / zip_name) as zf:
        info = json.loads(zf.read("info.json"))
        stats = json.loads(zf.read("stats.json"))
        errors = np.load(io.BytesIO(zf.read("error_array.npz")))
    return info, stats, errors


@needs_data
@pytest.mark.parametrize("zip_name, est_name", [("orb_ape.zip", "KITTI_00_ORB.txt"),
                                                ("sptam_ape.zip", "KITTI_00_SPTAM.txt")])
def test_ate_equals_evo_stored_kitti_result(zip_name, est_name):
    info, stats, errors = _stored_evo_result(zip_name)
    # The stored runs must be what we compare with: APE translation, SE(3) Umeyama, these files.
    assert "translation part" in info["title"]
    assert "SE(3) Umeyama alignment" in info["title"]
    assert info["ref_name"].endswith("KITTI_00_gt.txt")
    assert info["est_name"].endswith(est_name)
    got = evaluate_trajectory(_ours_from_evo_file("KITTI_00_gt.txt"), _ours_from_evo_file(est_name),
                              align="se3", associate=False)
    assert got.n_matched == errors.shape[0] == 4541
    assert got.ate == pytest.approx(stats["rmse"], abs=TOL)
    assert got.ate == pytest.approx(float(np.sqrt(np.mean(errors ** 2))), abs=TOL)


# ----------------------------------------------------------------------------------------------
# synthetic trajectories
# ----------------------------------------------------------------------------------------------

def _helix(n: int = 60, seed: int = 0) -> Trajectory:
    """A non-collinear camera path (helix) with smoothly varying orientations, 10 Hz."""
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    positions = np.stack([np.cos(0.2 * k), np.sin(0.2 * k), 0.05 * k], axis=1) * 2.0
    rotvecs = np.cumsum(rng.normal(scale=0.03, size=(n, 3)), axis=0)
    poses = np.stack([make_pose(R, t) for R, t in
                      zip(Rotation.from_rotvec(rotvecs).as_matrix(), positions)])
    return Trajectory(timestamps=100.0 + 0.1 * k, poses_T_world_cam=poses)


def _sim3(R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    S = np.eye(4)
    S[:3, :3] = s * R
    S[:3, 3] = t
    return S


def _apply_sim3(traj: Trajectory, R: np.ndarray, t: np.ndarray, s: float) -> Trajectory:
    """Poses seen in a world moved by (R, t) and scaled by s: X' = s R X + t, R' = R R_cam."""
    S = _sim3(R, t, s)
    poses = []
    for T in traj.poses_T_world_cam:
        P = S @ T
        P[:3, :3] /= s  # keep the rotation orthonormal; the scale acts on positions only
        poses.append(P)
    return Trajectory(traj.timestamps, np.stack(poses))


def test_sim3_transformed_gt_gives_zero_ate_and_inverse_scale():
    gt = _helix()
    R = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    s = 0.37
    est = _apply_sim3(gt, R, np.array([3.0, -1.0, 0.5]), s)
    got = evaluate_trajectory(gt, est, align="sim3")
    assert got.n_matched == len(gt)
    assert got.ate == pytest.approx(0.0, abs=1e-9)
    assert got.rpe_trans == pytest.approx(0.0, abs=1e-9)
    assert got.rpe_rot_deg == pytest.approx(0.0, abs=1e-5)  # arccos near 1 loses precision
    assert got.scale == pytest.approx(1.0 / s, rel=1e-9)
    # SE(3) cannot undo the scale: a clearly non-zero error remains.
    assert evaluate_trajectory(gt, est, align="se3").ate > 0.1


def test_heading_needs_no_alignment_and_finds_a_wrong_direction_that_the_ate_hides():
    # A slow sideways drift while the camera pans (as generated mixed 207): the true camera
    # moves along -x of its own axes, a wrong one along +x with the same rotations. The path is
    # nearly a line, so a Sim(3) alignment turns the wrong one onto it: a small ATE.
    n = 40
    yaw = np.radians(0.33) * np.arange(n)
    R = Rotation.from_euler("y", yaw[:, None]).as_matrix()
    c = np.cumsum([Ri @ np.array([-0.01, 0.0, 0.004]) for Ri in R], axis=0)
    gt = Trajectory(np.arange(n, dtype=float), np.stack([make_pose(Ri, ci) for Ri, ci in zip(R, c)]))
    wrong_c = np.cumsum([Ri @ np.array([0.01, 0.0, 0.004]) for Ri in R], axis=0)
    wrong = Trajectory(gt.timestamps, np.stack([make_pose(Ri, ci) for Ri, ci in zip(R, wrong_c)]))
    m = evaluate_trajectory(gt, wrong)
    assert m.ate_percent_of_path < 2.0 and m.heading_deg > 130.0
    # Any similarity transform of the true path, scale included, keeps every heading at zero.
    Rs = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    same = _apply_sim3(gt, Rs, np.array([3.0, -1.0, 0.5]), 0.37)
    assert np.allclose(heading_errors_deg(gt.poses_T_world_cam, same.poses_T_world_cam), 0.0, atol=1e-6)
    assert evaluate_trajectory(gt, same).heading_deg == pytest.approx(0.0, abs=1e-6)
    # A step where either camera did not move has no direction.
    still = same.poses_T_world_cam.copy()
    still[5, :3, 3] = still[4, :3, 3]
    h = heading_errors_deg(gt.poses_T_world_cam, still)
    assert np.isnan(h[4]) and np.isfinite(np.delete(h, 4)).all()


def _with_constant_relative_error(gt: Trajectory, delta: np.ndarray) -> Trajectory:
    """Estimate whose every frame-to-frame motion is the GT motion followed by ``delta``:
    P_{k+1} = P_k Q_k^-1 Q_{k+1} delta, so the RPE matrix of every pair is exactly ``delta``."""
    Q = gt.poses_T_world_cam
    P = [Q[0].copy()]
    for k in range(len(Q) - 1):
        P.append(P[-1] @ np.linalg.inv(Q[k]) @ Q[k + 1] @ delta)
    return Trajectory(gt.timestamps, np.stack(P))


@pytest.mark.parametrize("align", ["none", "se3"])
def test_constant_per_frame_error_gives_analytic_rpe(align):
    gt = _helix()
    t_err = np.array([0.03, -0.04, 0.0])  # 5 cm per frame
    angle_deg = 0.5
    delta = make_pose(Rotation.from_euler("z", angle_deg, degrees=True).as_matrix(), t_err)
    est = _with_constant_relative_error(gt, delta)
    got = evaluate_trajectory(gt, est, align=align)
    # A rigid global alignment leaves relative motions unchanged, so both give the same RPE.
    assert got.rpe_trans == pytest.approx(0.05, abs=1e-9)
    assert got.rpe_rot_deg == pytest.approx(angle_deg, abs=1e-6)
    assert got.n_matched == len(gt)


def test_translation_offset_without_alignment_gives_offset_as_ate():
    gt = _helix()
    offset = np.array([0.0, 0.3, 0.4])
    poses = gt.poses_T_world_cam.copy()
    poses[:, :3, 3] += offset
    got = evaluate_trajectory(gt, Trajectory(gt.timestamps, poses), align="none")
    assert got.ate == pytest.approx(0.5, abs=1e-12)
    assert got.rpe_trans == pytest.approx(0.0, abs=1e-12)
    assert got.scale == 1.0
    assert got.ate_percent_of_path == pytest.approx(100 * 0.5 / got.path_length)


def test_timestamp_jitter_within_max_diff_associates_beyond_does_not():
    gt = _helix(n=40)
    rng = np.random.default_rng(1)
    jitter = rng.uniform(-0.009, 0.009, size=len(gt))
    near = Trajectory(gt.timestamps + jitter, gt.poses_T_world_cam)
    assert evaluate_trajectory(gt, near, max_diff=0.01).n_matched == len(gt)

    # Every other frame 0.02 s late (beyond 0.01 s, still nearer to its own GT frame than to the
    # next one, 0.1 s away): only the other half associates.
    shift = np.where(np.arange(len(gt)) % 2 == 0, 0.0, 0.02)
    half = Trajectory(gt.timestamps + shift, gt.poses_T_world_cam)
    assert evaluate_trajectory(gt, half, max_diff=0.01).n_matched == len(gt) // 2
    assert evaluate_trajectory(gt, half, max_diff=0.03).n_matched == len(gt)

    far = Trajectory(gt.timestamps + 0.02, gt.poses_T_world_cam)
    with pytest.raises(EvalError, match=r"only 0 .*max_diff=0\.01"):
        evaluate_trajectory(gt, far, max_diff=0.01)


def test_fewer_than_three_matches_is_an_error_naming_count_and_max_diff():
    gt = _helix(n=10)
    est = Trajectory(np.concatenate([gt.timestamps[:2], gt.timestamps[2:] + 5.0]),
                     gt.poses_T_world_cam)
    with pytest.raises(EvalError, match=r"only 2 .*max_diff=0\.01"):
        evaluate_trajectory(gt, est)


def test_index_matching_needs_equal_lengths_and_ignores_time():
    gt = _helix(n=30)
    est = Trajectory.from_poses(gt.poses_T_world_cam)  # frame numbers, unrelated to gt's time
    got = evaluate_trajectory(gt, est, associate=False, align="se3")
    assert got.n_matched == 30 and got.ate == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(EvalError, match="equal length"):
        evaluate_trajectory(gt, Trajectory.from_poses(gt.poses_T_world_cam[:20]), associate=False)


def test_caller_arrays_are_unchanged():
    gt = _helix()
    est = _apply_sim3(gt, Rotation.from_euler("z", 30, degrees=True).as_matrix(),
                      np.array([1.0, 2.0, 3.0]), 2.0)
    stamps = est.timestamps.copy()
    poses = est.poses_T_world_cam.copy()
    stamps_before, poses_before = stamps.copy(), poses.copy()
    est_obj = Trajectory(stamps, poses)
    gt_poses_before = gt.poses_T_world_cam.copy()
    evaluate_trajectory(gt, est_obj, align="sim3")
    np.testing.assert_array_equal(stamps, stamps_before)
    np.testing.assert_array_equal(poses, poses_before)
    np.testing.assert_array_equal(est_obj.poses_T_world_cam, poses_before)
    np.testing.assert_array_equal(gt.poses_T_world_cam, gt_poses_before)
    # The Trajectory holds its own read-only copy.
    assert not est_obj.poses_T_world_cam.flags.writeable
    assert not np.shares_memory(est_obj.poses_T_world_cam, poses)


def test_check_rejects_bad_trajectories():
    gt = _helix(n=5)
    poses = gt.poses_T_world_cam.copy()
    poses[3, :3, :3] *= 1.1  # scaled rotation
    with pytest.raises(EvalError, match="estimate: pose 3 .*not a rigid"):
        evaluate_trajectory(gt, Trajectory(gt.timestamps, poses))
    poses = gt.poses_T_world_cam.copy()
    poses[1, 0, 3] = np.nan
    with pytest.raises(EvalError, match="pose 1 .*not finite"):
        Trajectory(gt.timestamps, poses).check()
    with pytest.raises(EvalError, match="sorted"):
        Trajectory(gt.timestamps[::-1], gt.poses_T_world_cam).check()
    with pytest.raises(EvalError, match=r"shape \(5, 4, 4\)"):
        Trajectory(gt.timestamps, gt.poses_T_world_cam[:, :3, :]).check()
    with pytest.raises(EvalError, match="unknown alignment"):
        evaluate_trajectory(gt, gt, align="sim2")


def test_collinear_positions_make_alignment_fail_with_eval_error():
    n = 10
    poses = np.stack([make_pose(np.eye(3), [float(k), 0.0, 0.0]) for k in range(n)])
    straight = Trajectory.from_poses(poses)
    with pytest.raises(EvalError, match="collinear"):
        evaluate_trajectory(straight, straight, align="sim3")
    assert evaluate_trajectory(straight, straight, align="none").ate == 0.0


def test_window_scales_show_where_a_scale_collapsed():
    # After pose 30 the estimate keeps only 5 % of each step (a monocular VO whose scale
    # collapsed): the global ATE says little about where, the windows say exactly.
    gt = _helix(n=60)
    poses = gt.poses_T_world_cam.copy()
    c = poses[30, :3, 3].copy()
    poses[31:, :3, 3] = c + 0.05 * (poses[31:, :3, 3] - c)
    est = _apply_sim3(Trajectory(gt.timestamps, poses), np.eye(3), np.array([1.0, 2.0, 0.0]), 3.0)
    got = evaluate_trajectory(gt, est, align="sim3", scale_window=10)
    rows = got.window_scales
    assert [(r["first"], r["last"]) for r in rows] == [(0, 10), (10, 20), (20, 30), (30, 40),
                                                       (40, 50), (50, 59)]
    before = [r["ratio"] for r in rows[:3]]
    after = [r["ratio"] for r in rows[3:]]
    assert max(before) == pytest.approx(min(before), rel=1e-9)   # one similarity: one ratio
    for r in after:
        assert r == pytest.approx(0.05 * before[0], rel=1e-9)
    assert sum(r["gt_path"] for r in rows) == pytest.approx(got.path_length, rel=1e-12)
    json.dumps(got.to_dict()["window_scales"], allow_nan=False)
    # The same run with an unbroken scale: every window at 1 after the alignment.
    same = evaluate_trajectory(gt, _apply_sim3(gt, np.eye(3), np.zeros(3), 3.0), scale_window=25)
    assert all(r["ratio"] == pytest.approx(1.0, rel=1e-9) for r in same.window_scales)
    assert "window_scales" not in evaluate_trajectory(gt, est).to_dict()
    # A GT that stands still in a window has no ratio there.
    assert window_scales(np.zeros((3, 3)), np.ones((3, 3)), 5)[0]["ratio"] is None
    with pytest.raises(EvalError, match="scale window"):
        evaluate_trajectory(gt, est, scale_window=-1)


def test_path_length_and_to_dict_are_plain_numbers():
    assert path_length(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 12]])) == pytest.approx(17.0)
    assert path_length(np.zeros((1, 3))) == 0.0
    m = TrajectoryMetrics(ate=0.1, rpe_trans=0.01, rpe_rot_deg=0.2, n_matched=7, scale=1.0,
                          path_length=0.0, ate_percent_of_path=math.nan,
                          alignment=Alignment.SE3)
    d = m.to_dict()
    assert d["alignment"] == "se3" and d["ate_percent_of_path"] is None
    json.dumps(d, allow_nan=False)
    got = evaluate_trajectory(_helix(), _helix(), align="sim3").to_dict()
    assert all(type(v) in (float, int, str) for v in got.values())
    json.dumps(got, allow_nan=False)
