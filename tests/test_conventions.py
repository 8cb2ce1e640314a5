"""mona_vo.conventions: quaternion order, pose inversion, projection and pixel centres."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mona_vo.conventions import (Intrinsics, invert_pose, make_pose, pose_from_tum_row, project,
                                 quat_wxyz_from_rotation, rotation_from_quat_wxyz, tum_row, unproject)

RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 deg about z


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    return np.stack([make_pose(R[i], rng.normal(size=3) * 5) for i in range(n)])


def test_quaternion_wxyz_of_90deg_about_z_is_scalar_first():
    s = np.sqrt(0.5)
    np.testing.assert_allclose(quat_wxyz_from_rotation(RZ90), [s, 0.0, 0.0, s], atol=1e-12)


def test_quaternion_rotation_round_trip_and_positive_w():
    for T in random_poses(50):
        q = quat_wxyz_from_rotation(T[:3, :3])
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(rotation_from_quat_wxyz(q), T[:3, :3], atol=1e-12)


def test_tum_row_stores_quaternion_scalar_last():
    s = np.sqrt(0.5)
    row = tum_row(12.5, make_pose(RZ90, [1.0, 2.0, 3.0]))
    np.testing.assert_allclose(row, [12.5, 1.0, 2.0, 3.0, 0.0, 0.0, s, s], atol=1e-12)
    t, T = pose_from_tum_row([12.5, 1.0, 2.0, 3.0, 0.0, 0.0, s, s])
    assert t == 12.5
    np.testing.assert_allclose(T, make_pose(RZ90, [1, 2, 3]), atol=1e-12)


def test_tum_row_round_trip_on_random_poses():
    for i, T in enumerate(random_poses(20, seed=1)):
        t, T2 = pose_from_tum_row(tum_row(float(i), T))
        assert t == float(i)
        np.testing.assert_allclose(T2, T, atol=1e-12)


def test_invert_pose_gives_identity_both_ways():
    for T in random_poses(10, seed=2):
        np.testing.assert_allclose(T @ invert_pose(T), np.eye(4), atol=1e-12)
        np.testing.assert_allclose(invert_pose(T) @ T, np.eye(4), atol=1e-12)


def test_project_unproject_round_trip():
    intr = Intrinsics(500.0, 480.0, 319.5, 239.5)
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(-2, 2, 100), rng.uniform(-1, 1, 100), rng.uniform(1, 20, 100)])
    px = project(pts, intr)
    np.testing.assert_allclose(unproject(px, pts[:, 2], intr), pts, atol=1e-9)


def test_point_on_optical_axis_projects_to_principal_point():
    intr = Intrinsics(500.0, 500.0, 300.25, 200.75)
    np.testing.assert_allclose(project(np.array([[0.0, 0.0, 4.0]]), intr), [[300.25, 200.75]])


def test_default_intrinsics_put_principal_point_at_image_centre():
    intr = Intrinsics.default_for(640, 480)
    assert (intr.cx, intr.cy) == (319.5, 239.5)
    assert intr.fx == pytest.approx(320.0 / np.tan(np.radians(30.0)))


def test_guessed_field_of_view_spans_the_longer_side():
    # A portrait frame is a landscape camera turned (a phone held upright): same focal length.
    upright = Intrinsics.default_for(480, 640)
    assert upright.fx == Intrinsics.default_for(640, 480).fx
    assert (upright.cx, upright.cy) == (239.5, 319.5)


@pytest.mark.parametrize("scale", [0.5, 2.0, 0.25])
def test_scaled_intrinsics_keep_pixel_centres(scale):
    intr = Intrinsics.default_for(640, 480)
    small = intr.scaled(scale)
    # The image centre maps to the centre of the resized image.
    assert (small.cx, small.cy) == ((640 * scale - 1) / 2, (480 * scale - 1) / 2)
    # Any point lands where resizing moves its pixel: x' = (x + 0.5) * s - 0.5.
    pts = np.array([[0.3, -0.2, 2.0], [-1.0, 0.5, 5.0]])
    np.testing.assert_allclose(project(pts, small), (project(pts, intr) + 0.5) * scale - 0.5)


def test_reproject_inverts_unproject_and_reports_depth():
    from mona_vo.conventions import Intrinsics, make_pose, reproject, transform_points, unproject
    from scipy.spatial.transform import Rotation

    intr = Intrinsics(500.0, 480.0, 319.5, 239.5)
    T = make_pose(Rotation.from_euler("xyz", [0.1, -0.3, 0.2]).as_matrix(), [1.0, -2.0, 0.5])
    pix = np.array([[0.0, 0.0], [319.5, 239.5], [639.0, 479.0]])
    depth = np.array([2.0, 5.0, 11.0])
    world = transform_points(T, unproject(pix, depth, intr))
    got, z = reproject(T, world, intr)
    assert np.allclose(got, pix) and np.allclose(z, depth)
    _, z_behind = reproject(T, transform_points(T, np.array([[0.0, 0.0, -1.0]])), intr)
    assert z_behind[0] < 0


def test_pixels_in_mask_uses_the_nearest_pixel_centre():
    from mona_vo.conventions import pixels_in_mask

    mask = np.zeros((4, 5), bool)
    mask[1, 2] = True
    # Pixel (x=2, y=1) covers [1.5, 2.5) x [0.5, 1.5) around its integer centre.
    inside = pixels_in_mask(mask, np.array([[2.0, 1.0], [2.4, 1.4], [1.6, 0.6], [2.6, 1.0], [2.0, 1.6],
                                            [-3.0, 1.0], [9.0, 9.0]]))
    assert inside.tolist() == [True, True, True, False, False, False, False]


def test_camera_depths_are_reprojects_depths_pose_by_pose():
    from mona_vo.conventions import camera_depths, reproject

    poses = random_poses(6, seed=3)
    pts = np.random.default_rng(3).normal(size=(6, 3)) * 4
    expected = np.array([reproject(T, p[None], Intrinsics(1, 1, 0, 0))[1][0] for T, p in zip(poses, pts)])
    np.testing.assert_allclose(camera_depths(poses, pts), expected)


def test_working_size_reduces_the_longer_side_so_portrait_frames_match_their_landscape_turn():
    from mona_vo.conventions import working_size

    assert working_size(640, 272, 256) == (256, 109)
    assert working_size(272, 640, 256) == (109, 256)          # the same frame, turned
    assert working_size(200, 100, 256) == (200, 100)          # never enlarged
    assert working_size(854, 480, 256) == (256, 144)          # as before for landscape widths
    assert working_size(5000, 3, 256) == (256, 1)             # each side at least one pixel


def test_masks_and_segmenter_work_on_a_portrait_frame_as_on_its_landscape_turn():
    from mona_vo.masks import MaskConfig, MonaMasker
    from mona_vo.segmentation import GrabCutSegmenter

    m = MonaMasker(MaskConfig(), None)
    m._size = (272, 640)
    assert m._analysis_size() == (109, 256)
    small, sx, sy = GrabCutSegmenter()._work(np.zeros((640, 272, 3), np.uint8))
    assert small.shape[:2] == (256, 109)


def test_pixels_and_boxes_rescale_by_their_edges():
    from mona_vo.conventions import scale_boxes, scale_pixels

    # The image's outer edges map onto the rescaled image's: x = -0.5 and x = W - 0.5.
    W, H, w, h = 640, 272, 256, 109
    edges = np.array([[-0.5, -0.5], [W - 0.5, H - 0.5]])
    assert scale_pixels(edges, w / W, h / H) == pytest.approx(np.array([[-0.5, -0.5], [w - 0.5, h - 0.5]]))
    pts = np.array([[10.0, 20.0], [300.25, 100.5]])
    back = scale_pixels(scale_pixels(pts, w / W, h / H), W / w, H / h)
    assert back == pytest.approx(pts)
    # A box is its two corners.
    box = np.array([[10.0, 20.0, 300.25, 100.5]], np.float32)
    out = scale_boxes(box, 0.5, 0.25)
    assert out.dtype == np.float32 and out.shape == (1, 4)
    assert out[0] == pytest.approx(scale_pixels(pts, 0.5, 0.25).ravel())
    assert scale_pixels(np.array([[1, 2]]), 2.0, 2.0).dtype == np.float64
