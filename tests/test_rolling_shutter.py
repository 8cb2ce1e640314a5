"""Rolling shutter (mona_vo/rolling_shutter.py): the model, the readout estimate of the global
refinement, and the pipeline's pass over the unrolled frames."""
import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mona_vo.conventions import make_pose
from mona_vo.rolling_shutter import (best_readout, best_residual, corrected_pixels, turn_rates,
                                     unroll_maps, velocities)

K = np.array([500.0, 500.0, 319.5, 239.5])


def _turning(n, rate_deg, axis=(0.2, 1.0, 0.1)):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    return np.stack([make_pose(Rotation.from_rotvec(np.radians(rate_deg) * i * axis).as_matrix(),
                               np.array([0.01 * i, 0.0, 0.0])) for i in range(n)]), axis


def test_turn_rates_are_the_cameras_own_turn_per_frame_and_stop_at_a_new_map():
    T, axis = _turning(10, 0.8)
    rates = turn_rates(T, np.zeros(10, np.int64))
    np.testing.assert_allclose(rates, np.radians(0.8) * np.tile(axis, (10, 1)), atol=1e-9)
    # A new map (segment) has its own world: no difference is taken across it, frames on no
    # map get none, and a frame alone on its map gets none either.
    seg = np.array([0, 0, 0, 0, 1, 1, 1, -1, -1, 2])
    T2 = T.copy()
    T2[4:7] = np.einsum("ij,njk->nik", make_pose(Rotation.from_rotvec([0, 2.0, 0]).as_matrix(),
                                                 np.zeros(3)), T[4:7])
    r2 = turn_rates(T2, seg)
    np.testing.assert_allclose(r2[:7], rates[:7], atol=1e-9)
    assert not r2[7:].any()


def test_corrected_pixels_see_a_rolling_shutter_frame_as_its_middle_row_camera_does():
    """Points seen by a camera whose rows are read one after the other while it turns: each
    pixel's ray is the one of the camera at its row's time. The correction puts them where the
    middle row's camera sees them, to a small fraction of the skew it removes."""
    h, readout = 480, 0.9
    rate = np.radians([0.3, 1.5, 0.2])          # per frame interval, camera frame
    rng = np.random.default_rng(0)
    P = np.c_[rng.uniform(-3, 3, (300, 2)), rng.uniform(4, 12, 300)]   # mid-row camera frame

    def project(R):
        q = P @ R                                  # R maps the row's camera to the middle one
        return np.c_[K[0] * q[:, 0] / q[:, 2] + K[2], K[1] * q[:, 1] / q[:, 2] + K[3]]

    global_ = project(np.eye(3))
    rolled = global_.copy()
    for _ in range(5):                             # the row a point is read at depends on it
        s = readout * (rolled[:, 1] - (h - 1) / 2) / h
        rolled = np.stack([project(Rotation.from_rotvec(si * rate).as_matrix())[i]
                           for i, si in enumerate(s)])
    skew = np.linalg.norm(rolled - global_, axis=1)
    back = corrected_pixels(rolled, np.tile(rate, (len(P), 1)), readout, K, h)
    err = np.linalg.norm(back - global_, axis=1)
    assert np.median(skew) > 2.0
    assert err.max() < 0.01 * skew.max()
    np.testing.assert_array_equal(corrected_pixels(rolled, np.tile(rate, (300, 1)), 0.0, K, h),
                                  rolled)
    # The image maps are the same correction, one homography per row.
    mx, my = unroll_maps(rate, readout, K, 64, 48)
    ys, xs = np.mgrid[0:48, 0:64]
    grid = np.c_[xs.ravel(), ys.ravel()].astype(float)
    want = corrected_pixels(grid, np.tile(-rate, (len(grid), 1)), readout, K, 48)
    np.testing.assert_allclose(np.c_[mx.ravel(), my.ravel()], want, atol=1e-3)


def test_the_cameras_motion_within_the_readout_is_taken_out_at_each_points_depth():
    """A camera walking (0.1 m and 0.6 deg a frame) past points 2-8 m away: read over 0.8 of
    the frame interval, its motion moves near points by pixels, which the turn alone does not
    explain. Given each point's position in the middle row's camera and the frame's velocity
    (:func:`velocities`, the centre's central difference in the camera's frame), the
    correction puts every observation where the middle row's camera saw it."""
    h, readout = 480, 0.8
    rate = np.radians([0.1, 0.6, 0.0])
    vel = np.array([0.02, 0.0, 0.1])                 # camera frame, per frame interval
    rng = np.random.default_rng(1)
    P = np.c_[rng.uniform(-2, 2, (300, 2)), rng.uniform(2, 8, 300)]

    def project(Q):
        return np.c_[K[0] * Q[:, 0] / Q[:, 2] + K[2], K[1] * Q[:, 1] / Q[:, 2] + K[3]]

    global_ = project(P)
    rolled = global_.copy()
    for _ in range(6):
        s = readout * (rolled[:, 1] - (h - 1) / 2) / h
        # The row's camera: turned by s w and moved by s v from the middle row's.
        seen = (P - s[:, None] * vel)
        rolled = project(np.stack([Rotation.from_rotvec(-si * rate).apply(q)
                                   for si, q in zip(s, seen)]))
    rates, vels = np.tile(rate, (300, 1)), np.tile(vel, (300, 1))
    turn_only = np.linalg.norm(corrected_pixels(rolled, rates, readout, K, h) - global_, axis=1)
    both = np.linalg.norm(corrected_pixels(rolled, rates, readout, K, h, vels, P) - global_,
                          axis=1)
    assert np.max(turn_only) > 2.0
    assert np.max(both) < 0.02 * np.max(turn_only)
    # The velocity of a frame: its centre's central difference, in its own camera's frame.
    T, _ = _turning(5, 0.8)
    v = velocities(T, np.zeros(5, np.int64))
    for i in range(5):
        a, b = max(i - 1, 0), min(i + 1, 4)
        np.testing.assert_allclose(v[i], T[i, :3, :3].T @ (T[b, :3, 3] - T[a, :3, 3]) / (b - a),
                                   atol=1e-12)
    assert not velocities(T, np.full(5, -1)).any()


def test_the_refinements_observations_are_unrolled_at_the_depths_of_its_own_solution():
    """VisualOdometry._unrolled (vo.rolling_shutter_model): each observation of a keyframe
    graph moved by its frame's turn and, given velocities, by the camera's motion at the depth
    of the graph's own pose and landmark, the landmark found by id whatever the order (an
    observation of an unknown landmark is left to the turn alone)."""
    from ba.global_ba import KeyframeGraph
    from mona_vo.conventions import Intrinsics
    from mona_vo.vo import VisualOdometry, VOConfig

    h, readout = 480, 0.8
    T, _ = _turning(3, 0.6)
    rates = turn_rates(T, np.zeros(3, np.int64))
    vel = velocities(T, np.zeros(3, np.int64)) + np.array([0.0, 0.0, 0.08])
    rng = np.random.default_rng(2)
    X = np.c_[rng.uniform(-2, 2, (40, 2)), rng.uniform(2, 8, 40)]       # world = camera 0's
    ids = rng.permutation(1000)[:40]
    obs_kf = np.repeat([0, 1], 40)
    obs_lm = np.r_[ids, ids[::-1]]
    Xw = np.r_[X, X[::-1]]
    P = np.einsum("nji,nj->ni", T[[0, 2]][obs_kf, :3, :3], Xw - T[[0, 2]][obs_kf, :3, 3])
    truth = np.c_[K[0] * P[:, 0] / P[:, 2] + K[2], K[1] * P[:, 1] / P[:, 2] + K[3]]
    rolled = truth.copy()
    for _ in range(6):
        s = readout * (rolled[:, 1] - (h - 1) / 2) / h
        seen = P - s[:, None] * vel[[0, 2]][obs_kf]
        q = np.stack([Rotation.from_rotvec(-si * r).apply(v)
                      for si, r, v in zip(s, rates[[0, 2]][obs_kf], seen)])
        rolled = np.c_[K[0] * q[:, 0] / q[:, 2] + K[2], K[1] * q[:, 1] / q[:, 2] + K[3]]
    obs_lm[-1] = 5000                                  # a landmark the graph does not hold
    graph = KeyframeGraph(np.array([0, 2]), T[[0, 2]], np.tile(K, (2, 1)), obs_kf, obs_lm,
                          rolled, np.zeros(80, bool), ids, X)
    vo = VisualOdometry(VOConfig(), 640, h, Intrinsics(*K))
    both = vo._unrolled(graph, rates, readout, vel).obs_uv
    turn = vo._unrolled(graph, rates, readout).obs_uv
    err_both = np.linalg.norm(both - truth, axis=1)[:-1]
    err_turn = np.linalg.norm(turn - truth, axis=1)[:-1]
    assert err_turn.max() > 1.0 and err_both.max() < 0.02 * err_turn.max()
    np.testing.assert_allclose(both[-1], turn[-1])


def test_best_readout_takes_the_parabolas_lowest_point_within_one_frame_interval():
    r = np.array([0.0, 0.5, 1.0])
    assert best_readout(r, (r - 0.7) ** 2 + 1.0) == pytest.approx(0.7)
    assert best_readout(r, 1.0 + r) == 0.0                 # rising: a global shutter
    r4 = np.array([0.0, 0.5, 1.0, 1.25])
    assert best_readout(r4, (r4 - 0.95) ** 2) == pytest.approx(0.95)
    assert best_readout(r4, (r4 - 1.1) ** 2) == 1.0
    # Still falling beyond a whole frame interval, which no video's readout exceeds: the
    # readout is absorbing something else.
    assert best_readout(r4, (r4 - 3.0) ** 2) == 0.0


def test_best_residual_is_signed_and_stays_within_the_readouts_tried():
    r = np.array([-0.1, 0.0, 0.1, 0.2])
    assert best_residual(r, (r - 0.13) ** 2) == pytest.approx(0.13)
    assert best_residual(r, (r + 0.04) ** 2) == pytest.approx(-0.04)
    assert best_residual(r, (r - 0.5) ** 2) == 0.2          # still falling: the last one tried
    assert best_residual(r, (r + 0.5) ** 2) == -0.1
    assert best_residual(r, r ** 2) == pytest.approx(0.0, abs=1e-12)


def _rolled(scene, frames, masks, readout):
    """The generated frames as a rolling shutter reading its rows over ``readout`` frame
    intervals would have shown them (the scene's true turn rates)."""
    from data_tools.frames import Frame

    n = len(frames)
    rates = turn_rates(scene.poses(), np.zeros(n, np.int64))
    k = scene.intrinsics
    h, w = frames[0].image.shape[:2]
    out_f, out_m = [], []
    for i, (f, m) in enumerate(zip(frames, masks)):
        mx, my = unroll_maps(-rates[i], readout, np.array([k.fx, k.fy, k.cx, k.cy]), w, h)
        out_f.append(Frame(f.index, f.timestamp, f.name,
                           cv2.remap(f.image, mx, my, cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)))
        out_m.append(cv2.remap(m.astype(np.uint8), mx, my, cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_REPLICATE).astype(bool))
    return out_f, out_m


def test_the_pipeline_finds_a_rolling_shutter_unrolls_the_frames_and_leaves_a_global_one(sequence):
    """Generated static seed 0 (0.6 degrees of turn a frame) read by a rolling shutter over 0.8
    of the frame interval: the global refinement finds the readout, the VO runs again on the
    unrolled frames and the ATE falls back towards the global shutter's (measured 0.206 ->
    0.084 % of path; 0.069 % for the same frames with a global shutter). The same frames with
    a global shutter: the readout found is 0 and the run is the one without the estimate, to
    the bit."""
    from eval.metrics import Trajectory, score_trajectory
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = sequence("static", 0, 40, 640, 272)
    gt = Trajectory.from_poses(scene.poses())

    def run(fr, mode):
        cfg = apply_overrides(PipelineConfig(), {"vo.rolling_shutter": mode})
        res = estimate_trajectory(fr, intrinsics=scene.intrinsics, config=cfg)
        est = Trajectory.from_poses(res.vo.poses)
        return res.vo, score_trajectory(gt, est).ate_percent_of_path

    found, found_ate = run(frames, "estimate")
    plain, plain_ate = run(frames, "off")
    assert found.refine["rolling_shutter"]["readout"] == 0.0
    assert "unrolled_pass" not in found.refine
    np.testing.assert_array_equal(found.poses, plain.poses)

    rf, _ = _rolled(scene, frames, masks, 0.8)
    skewed, skewed_ate = run(rf, "off")
    unrolled, unrolled_ate = run(rf, "estimate")
    assert unrolled.refine["unrolled_pass"].startswith("yes")
    # The first estimate, on the skewed frames, falls short; the pass on the unrolled frames
    # finds what is left (measured: 0.62 + 0.12).
    shutter = unrolled.refine["rolling_shutter"]
    first, left = shutter["first_estimate"], shutter["residual"]["readout"]
    assert shutter["readout"] == pytest.approx(first + left)
    assert abs(shutter["readout"] - 0.8) < 0.1
    assert abs(shutter["readout"] - 0.8) < abs(first - 0.8) - 0.05
    assert unrolled_ate < 0.6 * skewed_ate
    assert unrolled_ate < 1.5 * plain_ate


@pytest.mark.parametrize("left, done, expect", [(0.2, 0.5, 0.2), (-0.2, 0.5, -0.2),
                                                (0.2, 0.9, 0.1)])
def test_the_readout_left_on_unrolled_frames_is_found_either_way_within_one_interval(
        sequence, left, done, expect):
    """vo.rolling_shutter=residual, as the unrolled pass runs it on frames unrolled at ``done``
    already: a skew of 0.2 left (unrolled too little) or of -0.2 (too much) is found with its
    sign (measured 0.13 and -0.22); after 0.9, no more than 0.1 is left, since a video reads its
    rows within one frame interval."""
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = sequence("static", 0, 40, 640, 272)
    rf, _ = _rolled(scene, frames, masks, left)
    cfg = apply_overrides(PipelineConfig(), {"vo.rolling_shutter": "residual",
                                             "vo.rolling_shutter_readout": done})
    res = estimate_trajectory(rf, intrinsics=scene.intrinsics, config=cfg)
    found = res.vo.refine["rolling_shutter"]["readout"]
    assert "unrolled_pass" not in res.vo.refine        # a residual is not unrolled again
    assert abs(found - expect) < 0.08, res.vo.refine["rolling_shutter"]
    assert found <= 1.0 - done + 1e-9
