"""data_tools.tum and data_tools.kitti: trajectory, frame-list and calibration files, real and round trip."""
from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data_tools.kitti import read_kitti_calib, read_kitti_poses, write_kitti_poses
from data_tools.tum import (TumSequence, format_timestamp, read_calib_txt, read_rgb_list,
                            read_tum_trajectory, write_tum_layout, write_tum_trajectory)
from mona_vo.conventions import Intrinsics, make_pose, rotation_angle_deg
from mona_vo.errors import InputError


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    return np.stack([make_pose(R[i], rng.normal(size=3) * 10) for i in range(n)])


# --- TUM trajectories ---------------------------------------------------------------------------

def test_real_tum_groundtruth_skips_comments(shared_subdir):
    stamps, poses = read_tum_trajectory(shared_subdir("evo_trajectories") / "freiburg1_xyz-groundtruth.txt")
    assert stamps.shape == (3000,) and poses.shape == (3000, 4, 4)
    assert stamps.dtype == np.float64 and stamps[0] == 1305031098.6659
    np.testing.assert_allclose(poses[0][:3, 3], [1.3563, 0.6305, 1.6380])


def test_real_tum_quaternion_is_read_scalar_last(shared_subdir):
    # First line: 1305031098.6659 1.3563 0.6305 1.6380 0.6132 0.5962 -0.3311 -0.3986 (qx qy qz qw).
    _, poses = read_tum_trajectory(shared_subdir("evo_trajectories") / "freiburg1_xyz-groundtruth.txt")
    q_xyzw = np.array([0.6132, 0.5962, -0.3311, -0.3986])
    x, y, z, w = q_xyzw / np.linalg.norm(q_xyzw)
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(poses[0][:3, :3], R, atol=1e-12)
    assert poses[0][2, 2] == pytest.approx(-0.46292, abs=1e-4)  # 1 - 2(qx^2 + qy^2), by hand


def test_tum_write_read_round_trip_keeps_unix_timestamps(tmp_path):
    stamps = 1548339827.584380 + np.arange(20) * 0.033512
    poses = random_poses(20)
    path = tmp_path / "sub" / "traj.txt"
    write_tum_trajectory(path, stamps, poses)
    t2, p2 = read_tum_trajectory(path)
    assert np.array_equal(t2, stamps)
    np.testing.assert_allclose(p2, poses, atol=1e-12)
    assert path.read_text().splitlines()[1].startswith("1548339827.584380 ")


def test_timestamps_are_written_to_the_microsecond_or_exactly():
    assert format_timestamp(1548339827.584380) == "1548339827.584380"
    assert format_timestamp(3) == "3.000000"
    assert float(format_timestamp(1 / 3)) == 1 / 3


def test_tum_reader_accepts_commas_and_tabs(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("# c\n\n1.0,0,0,0,0,0,0,1\n2.0\t1 2 3 0 0 0 1\n")
    stamps, poses = read_tum_trajectory(path)
    assert list(stamps) == [1.0, 2.0] and np.allclose(poses[1][:3, 3], [1, 2, 3])


@pytest.mark.parametrize("text, fragment", [
    ("1 0 0 0 0 0 0 1\n1 2 3\n", ":2: expected 8 numbers"),
    ("# only\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 x\n", ":3: not a number"),
    ("1 0 0 0 0 0 0 0\n", ":1: zero quaternion"),
    ("1 nan 0 0 0 0 0 1\n", ":1: non-finite"),
    ("# nothing\n", "no poses"),
])
def test_bad_tum_files_name_file_and_line(tmp_path, text, fragment):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=re.escape(f"{path}{fragment}" if fragment[0] == ":" else fragment)):
        read_tum_trajectory(path)


def test_missing_tum_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        read_tum_trajectory(tmp_path / "absent.txt")


# --- TUM sequences ------------------------------------------------------------------------------

def test_real_bonn_sequence(shared_subdir):
    seq = TumSequence(shared_subdir("bonn_crowd"))
    assert len(seq.frame_paths) == 53 and seq.timestamps[0] == 1548339827.58438
    assert seq.intrinsics() == Intrinsics(542.822841, 542.576870, 315.593520, 237.756098)
    gt_t, gt = seq.groundtruth()
    assert gt.shape == (112, 4, 4) and gt_t[0] == 1548339826.59457
    src = seq.frames(max_frames=2)
    assert src.timestamp_kind == "seconds" and src.timestamps == list(seq.timestamps[:2])
    frame = next(iter(src))
    assert frame.image.shape == (480, 640, 3) and frame.name == "1548339827.58438"


def test_rgb_list_of_real_sequence(shared_subdir):
    entries = read_rgb_list(shared_subdir("bonn_crowd") / "rgb.txt")
    assert len(entries) == 53 and entries[0] == (1548339827.58438, "rgb/1548339827.58438.png")


def test_tum_layout_round_trip(tmp_path):
    rng = np.random.default_rng(4)
    stamps = 1305031098.6659 + np.arange(4) / 30.0
    images = [rng.integers(0, 256, (24, 32, 3), np.uint8) for _ in stamps]
    poses = random_poses(4, seed=5)
    intr = Intrinsics(30.5, 31.25, 15.5, 11.5)
    write_tum_layout(tmp_path / "seq", stamps, iter(images), poses, intr)
    seq = TumSequence(tmp_path / "seq")
    assert np.array_equal(seq.timestamps, stamps)
    assert seq.intrinsics() == intr
    gt_t, gt = seq.groundtruth()
    assert np.array_equal(gt_t, stamps) and np.allclose(gt, poses, atol=1e-12)
    frames = list(seq.frames())
    assert all(np.array_equal(f.image, im) for f, im in zip(frames, images))
    assert [f.timestamp for f in frames] == list(stamps)


def test_tum_layout_rejects_image_count_mismatch(tmp_path):
    images = [np.zeros((4, 4, 3), np.uint8)] * 2
    with pytest.raises(ValueError, match="2 images for 3 timestamps"):
        write_tum_layout(tmp_path, [0.0, 1.0, 2.0], images, random_poses(3))
    assert not (tmp_path / "rgb.txt").exists()


def test_tum_sequence_names_missing_files(tmp_path):
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'rgb.txt'}: file not found")):
        TumSequence(tmp_path)
    (tmp_path / "rgb.txt").write_text("1.0 rgb/1.0.png\n")
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'rgb' / '1.0.png'}: listed in")):
        TumSequence(tmp_path)


def test_tum_sequence_without_groundtruth_says_so(tmp_path):
    write_tum_layout(tmp_path, [0.0, 1.0], [np.zeros((4, 4, 3), np.uint8)] * 2, random_poses(2))
    (tmp_path / "groundtruth.txt").unlink()
    seq = TumSequence(tmp_path)
    assert seq.intrinsics() is None
    with pytest.raises(InputError, match="groundtruth.txt: file not found"):
        seq.groundtruth()


def test_calib_txt_accepts_a_label_and_reads_the_lens_distortion(tmp_path):
    from mona_vo.lens import Distortion, LensIntrinsics

    path = tmp_path / "calib.txt"
    path.write_text("# fx fy cx cy k1 k2\nK: 500 501 320 240 0.1 -0.2\n")
    cam = read_calib_txt(path)
    # The distortion after fx fy cx cy is the lens's (OpenCV's order), kept for the run to
    # undistort the frames with, not dropped (it once was, silently).
    assert cam == LensIntrinsics(500.0, 501.0, 320.0, 240.0, Distortion(0.1, -0.2))
    assert cam.pinhole() == Intrinsics(500.0, 501.0, 320.0, 240.0)
    path.write_text("500 501 320 240 0 0 0 0 0\n")      # TUM's d0-d4, all zero: a pinhole
    assert read_calib_txt(path) == Intrinsics(500.0, 501.0, 320.0, 240.0)
    path.write_text("500 501 320 240 0.1 0 0 0 0 7\n")
    with pytest.raises(InputError, match=":1: expected 'fx fy cx cy' and at most 5 distortion"):
        read_calib_txt(path)
    path.write_text("500 -1 320 240\n")
    with pytest.raises(InputError, match=":1: focal length must be positive"):
        read_calib_txt(path)


# --- KITTI --------------------------------------------------------------------------------------

def test_real_kitti_00_groundtruth(shared_subdir):
    poses = read_kitti_poses(shared_subdir("evo_trajectories") / "KITTI_00_gt.txt")
    assert poses.shape == (4541, 4, 4) and poses.dtype == np.float64
    np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-6)
    np.testing.assert_allclose(poses[1][:3, 3], [-4.690294e-02, -2.839928e-02, 8.586941e-01])
    assert np.all(poses[:, 3] == [0, 0, 0, 1])


def test_real_kitti_06_relative_motion_matches_readme(shared_subdir):
    poses = read_kitti_poses(shared_subdir("kitti06") / "poses.txt")  # frames 12, 13, 14, 17, 435, 436
    assert poses.shape == (6, 4, 4)
    # Camera 13 in camera 12's frame. np.linalg.inv as in the README: with 7 printed digits the
    # rotations are orthonormal to ~1e-7 only, which moves a 0.12 deg trace-based angle by 2e-3 deg.
    rel = np.linalg.inv(poses[0]) @ poses[1]
    np.testing.assert_allclose(rel[:3, 3], [-0.004702, -0.027355, 1.193233], atol=2e-5)
    assert rotation_angle_deg(rel[:3, :3]) == pytest.approx(0.1173, abs=1e-4)


def test_real_kitti_calib(shared_subdir):
    intr = read_kitti_calib(shared_subdir("kitti06") / "calib.txt")
    assert intr == Intrinsics(707.0912, 707.0912, 601.8873, 183.1104)
    assert read_kitti_calib(shared_subdir("kitti06") / "calib.txt", camera="P2") == intr


def test_kitti_round_trip(tmp_path):
    poses = random_poses(30, seed=6)
    write_kitti_poses(tmp_path / "p.txt", poses)
    assert np.array_equal(read_kitti_poses(tmp_path / "p.txt"), poses)
    assert len((tmp_path / "p.txt").read_text().splitlines()[0].split()) == 12


def test_bad_kitti_files_name_file_and_line(tmp_path):
    path = tmp_path / "p.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match=re.escape(f"{path}:2: expected 12 numbers")):
        read_kitti_poses(path)
    calib = tmp_path / "calib.txt"
    calib.write_text("P0: 1 0 2 0 0 1 2 0 0 0 1\n")
    with pytest.raises(InputError, match=re.escape(f"{calib}:1: P0 needs 12 finite numbers, got 11")):
        read_kitti_calib(calib)
    with pytest.raises(InputError, match=r"no P5 line \(found: P0\)"):
        read_kitti_calib(calib, camera="P5")
