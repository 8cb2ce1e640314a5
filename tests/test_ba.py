"""Sliding-window bundle adjustment on generated observations: accuracy, robustness to outliers,
moving-object masks really removing factors, the gauge, and the custom focal prior's Jacobian."""
import gtsam
import numpy as np
import pytest

from ba.sliding_window_ba import BAConfig, BAProblem, focal_prior_error, sliding_window_ba
from mona_vo.conventions import Intrinsics, invert_pose, make_pose, project, rotation_angle_deg, transform_points
from scipy.spatial.transform import Rotation

INTR = Intrinsics(500.0, 500.0, 319.5, 239.5)


def _scene(seed=0, n_kf=6, n_pts=200):
    rng = np.random.default_rng(seed)
    poses = {}
    for k in range(n_kf):
        R = Rotation.from_euler("yxz", [0.02 * k, 0.01 * np.sin(k), 0.0]).as_matrix()
        poses[k] = make_pose(R, [0.3 * k, 0.02 * np.sin(k), 0.05 * k])
    pts = rng.uniform([-6, -3, 6], [8, 3, 14], (n_pts, 3))
    obs_kf, obs_lm, obs_uv = [], [], []
    for k, T in poses.items():
        uv = project(transform_points(invert_pose(T), pts), INTR)
        ok = (uv[:, 0] > 0) & (uv[:, 0] < 639) & (uv[:, 1] > 0) & (uv[:, 1] < 479)
        for j in np.flatnonzero(ok):
            obs_kf.append(k)
            obs_lm.append(j)
            obs_uv.append(uv[j] + rng.normal(0, 0.5, 2))
    return poses, pts, np.array(obs_kf), np.array(obs_lm), np.array(obs_uv), rng


def _perturb(poses, pts, rng, fixed):
    noisy = {}
    for k, T in poses.items():
        if k in fixed:
            noisy[k] = T.copy()
            continue
        dR = Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix()
        noisy[k] = make_pose(dR @ T[:3, :3], T[:3, 3] + rng.normal(0, 0.05, 3))
    lms = {j: p + rng.normal(0, 0.2, 3) for j, p in enumerate(pts)}
    return noisy, lms


def _errors(est, gt):
    t = max(np.linalg.norm(est[k][:3, 3] - gt[k][:3, 3]) for k in gt)
    r = max(rotation_angle_deg(est[k][:3, :3].T @ gt[k][:3, :3]) for k in gt)
    return t, r


def test_ba_recovers_poses_despite_outliers():
    poses, pts, kf, lm, uv, rng = _scene()
    # 15 % gross outliers: points dragged 5-40 px, as a moving object or a bad track would.
    bad = rng.random(len(uv)) < 0.15
    uv = uv.copy()
    uv[bad] += rng.uniform(5, 40, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    fixed = {0, 1}
    init, lms = _perturb(poses, pts, rng, fixed)
    intr = {k: INTR for k in poses}
    res = sliding_window_ba(BAProblem(init, fixed, intr, lms, kf, lm, uv), BAConfig(max_iterations=30))
    # Oracle: the same problem without the outlier observations.
    g = ~bad
    oracle = sliding_window_ba(BAProblem(init, fixed, intr, lms, kf[g], lm[g], uv[g]),
                               BAConfig(max_iterations=30, robust_kernel="none"))
    t_err, r_err = _errors(res.poses, poses)
    t_best, r_best = _errors(oracle.poses, poses)
    t_before, _ = _errors(init, poses)
    assert t_before > 0.05
    assert t_err < 1.2 * t_best + 1e-3 and r_err < 1.2 * r_best + 0.01, (t_err, t_best, r_err, r_best)
    # The outliers are exactly what the residual test flags.
    flagged = res.outlier
    assert (flagged & bad).sum() >= 0.9 * bad.sum()
    assert (flagged & ~bad).sum() <= 0.02 * (~bad).sum()


def test_ba_without_robust_kernel_is_pulled_by_outliers():
    poses, pts, kf, lm, uv, rng = _scene(seed=1)
    bad = rng.random(len(uv)) < 0.15
    uv = uv.copy()
    uv[bad] += 30.0
    init, lms = _perturb(poses, pts, rng, {0, 1})
    intr = {k: INTR for k in poses}
    robust = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf, lm, uv), BAConfig(max_iterations=30))
    plain = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf, lm, uv),
                              BAConfig(max_iterations=30, robust_kernel="none"))
    assert _errors(robust.poses, poses)[0] < 0.5 * _errors(plain.poses, poses)[0]


def test_moving_points_excluded_from_ba():
    """Landmarks on a 'moving object' are displaced between keyframes. With their mask, the BA
    must drop them (and recover the poses); ignoring the mask would let them bend the solution."""
    poses, pts, kf, lm, uv, rng = _scene(seed=2, n_pts=150)
    mover = np.arange(150) < 60   # 40 % of the points move with the object
    uv = uv.copy()
    sel = mover[lm] & (kf >= 2)
    uv[sel] += np.stack([12.0 * (kf[sel] - 1), np.zeros(sel.sum())], axis=1)
    masks = {}
    for k in poses:
        m = np.zeros((480, 640), bool)
        on = uv[(kf == k) & mover[lm]]
        x = np.clip(np.rint(on[:, 0]).astype(int), 0, 639)
        y = np.clip(np.rint(on[:, 1]).astype(int), 0, 479)
        m[y, x] = True
        masks[k] = m
    init, lms = _perturb(poses, pts, rng, {0, 1})
    intr = {k: INTR for k in poses}
    cfg = BAConfig(max_iterations=30, robust_kernel="none")
    with_masks = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf, lm, uv, masks), cfg)
    without = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf, lm, uv), cfg)
    # Every observation of a masked landmark is gone from the graph, counted as dropped.
    assert not with_masks.obs_used[mover[lm]].any()
    # Static landmarks stay, but for the few that a single-pixel mask happens to cover.
    assert with_masks.obs_used[~mover[lm]].mean() > 0.95
    assert with_masks.masked_landmarks == len(np.unique(lm[mover[lm]]))
    assert with_masks.masked_observations == int((mover[lm]).sum())
    # The masked solve is the solve of the static observations alone, to the last digit...
    static = ~mover[lm] & with_masks.obs_used
    alone = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf[static], lm[static], uv[static]), cfg)
    for k in poses:
        assert np.allclose(with_masks.poses[k], alone.poses[k], atol=1e-9)
    # ...and ignoring the masks lets the movers bend the trajectory.
    t_masked, _ = _errors(with_masks.poses, poses)
    t_plain, _ = _errors(without.poses, poses)
    assert t_plain > 5 * t_masked


def test_per_observation_mask_flags_leave_the_graph_as_masks_do():
    """The VO passes per-observation flags (its tracks know whether they were inside a mask):
    one flagged observation takes its landmark's every observation out of the graph."""
    poses, pts, kf, lm, uv, rng = _scene(seed=2, n_pts=150)
    mover = np.arange(150) < 60
    uv = uv.copy()
    sel = mover[lm] & (kf >= 2)
    uv[sel] += np.stack([12.0 * (kf[sel] - 1), np.zeros(sel.sum())], axis=1)
    flagged = mover[lm] & (kf == 3)      # each mover seen inside a mask in one keyframe only
    init, lms = _perturb(poses, pts, rng, {0, 1})
    intr = {k: INTR for k in poses}
    cfg = BAConfig(max_iterations=30, robust_kernel="none")
    res = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf, lm, uv, obs_masked=flagged), cfg)
    seen = np.unique(lm[flagged])
    assert res.masked_observations == int(flagged.sum())
    assert set(res.masked_landmark_ids.tolist()) == set(seen.tolist())
    assert not res.obs_used[np.isin(lm, seen)].any()
    rest = ~np.isin(lm, seen)
    alone = sliding_window_ba(BAProblem(init, {0, 1}, intr, lms, kf[rest], lm[rest], uv[rest]), cfg)
    for k in poses:
        assert np.allclose(res.poses[k], alone.poses[k], atol=1e-9)


def test_fixed_keyframes_hold_the_gauge():
    poses, pts, kf, lm, uv, rng = _scene(seed=3)
    init, lms = _perturb(poses, pts, rng, {0, 1})
    res = sliding_window_ba(BAProblem(init, {0, 1}, {k: INTR for k in poses}, lms, kf, lm, uv))
    for k in (0, 1):
        assert np.allclose(res.poses[k], poses[k], atol=1e-5)


def test_focal_prior_jacobian_matches_numeric():
    key = gtsam.symbol("k", 0)
    noise = gtsam.noiseModel.Isotropic.Sigma(1, 10.0)
    from functools import partial
    factor = gtsam.CustomFactor(noise, [key], partial(focal_prior_error, 480.0))
    values = gtsam.Values()
    values.insert(key, gtsam.Cal3f(500.0, 320.0, 240.0))
    jac = [np.zeros((1, 1))]
    err = focal_prior_error(480.0, factor, values, jac)
    eps = 1e-4
    moved = gtsam.Values()
    moved.insert(key, values.atCal3f(key).retract(np.array([eps])))
    numeric = (focal_prior_error(480.0, factor, moved, None) - err) / eps
    assert err[0] == pytest.approx(20.0)
    assert jac[0][0, 0] == pytest.approx(numeric[0], rel=1e-6)


def test_shared_focal_is_refined_with_rotation_in_the_window():
    poses, pts, kf, lm, uv, rng = _scene(seed=4, n_kf=8)
    # Stronger rotation makes the focal length observable.
    for k in poses:
        R = Rotation.from_euler("yx", [0.08 * k, 0.05 * np.sin(k)]).as_matrix()
        poses[k] = make_pose(R, poses[k][:3, 3])
    uv = np.array([project(transform_points(invert_pose(poses[k]), pts[[j]]), INTR)[0]
                   for k, j in zip(kf, lm)]) + rng.normal(0, 0.3, (len(kf), 2))
    guess = Intrinsics(560.0, 560.0, INTR.cx, INTR.cy)
    init, lms = _perturb(poses, pts, rng, {0, 1})
    res = sliding_window_ba(BAProblem(init, {0, 1}, {k: guess for k in poses}, lms, kf, lm, uv),
                            BAConfig(max_iterations=50), refine_focal=True)
    assert abs(res.focal - 500.0) < abs(560.0 - 500.0) / 3


def test_distance_prior_jacobian_matches_numeric():
    from functools import partial

    from ba.sliding_window_ba import distance_error

    key = gtsam.symbol("x", 1)
    pose = gtsam.Pose3(gtsam.Rot3.Ypr(0.3, -0.2, 0.1), np.array([1.0, -2.0, 0.5]))
    centre = np.array([0.2, 0.1, -0.3])
    factor = gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 1.0), [key],
                                partial(distance_error, centre, 2.0))
    values = gtsam.Values()
    values.insert(key, pose)
    jac = [np.zeros((1, 6))]
    err = distance_error(centre, 2.0, factor, values, jac)
    numeric = np.zeros(6)
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-6
        moved = gtsam.Values()
        moved.insert(key, pose.retract(d))
        numeric[i] = (distance_error(centre, 2.0, factor, moved, None) - err)[0] / 1e-6
    assert np.allclose(jac[0].ravel(), numeric, atol=1e-5)


def test_one_fixed_keyframe_and_a_distance_fix_the_gauge_and_scale():
    poses, pts, kf, lm, uv, rng = _scene(seed=5)
    init, lms = _perturb(poses, pts, rng, {0})
    dist = float(np.linalg.norm(poses[1][:3, 3] - poses[0][:3, 3]))
    res = sliding_window_ba(BAProblem(init, {0}, {k: INTR for k in poses}, lms, kf, lm, uv,
                                      scale_anchor=(0, 1, dist)), BAConfig(max_iterations=30))
    assert np.allclose(res.poses[0], poses[0], atol=1e-5)
    got = np.linalg.norm(res.poses[1][:3, 3] - res.poses[0][:3, 3])
    assert abs(got - dist) < 1e-4
    t_err, r_err = _errors(res.poses, poses)
    assert t_err < 0.03 and r_err < 0.2


def _with_a_landmark_at_a_camera(seed=3):
    """A perturbed window in which one landmark sits 1e-4 in front of a free keyframe's centre
    (what earlier windows can leave behind), its observations unchanged."""
    poses, pts, kf, lm, uv, rng = _scene(seed=seed)
    fixed = {0, 1}
    init, lms = _perturb(poses, pts, rng, fixed)
    j = int(lm[kf == 3][0])
    T = init[3]
    lms[j] = T[:3, 3] + 1e-4 * (T[:3, :3] @ np.array([0.1, -0.05, 1.0]))
    uv = uv.copy()
    uv[(kf == 3) & (lm == j)] = project(transform_points(invert_pose(T), lms[j][None]), INTR)
    return BAProblem(init, fixed, {k: INTR for k in poses}, lms, kf, lm, uv), poses, j


def test_a_landmark_at_a_camera_centre_is_left_out_and_the_window_still_solves():
    problem, truth, j = _with_a_landmark_at_a_camera()
    res = sliding_window_ba(problem, BAConfig())
    assert list(res.degenerate_landmark_ids) == [j]
    assert res.iterations > 0 and res.final_rmse_px < 1.0
    t_err, r_err = _errors(res.poses, truth)
    assert t_err < 0.05 and r_err < 0.3
    # The gate is what removes it (min_depth_ratio 0 keeps it in the graph). On real footage
    # (Bonn crowd) such a landmark left the window unsolved, 0 iterations at 40 px RMSE: its
    # Jacobian (1 / depth) dwarfed every damping Levenberg-Marquardt may use.
    kept = sliding_window_ba(problem, BAConfig(min_depth_ratio=0.0))
    assert len(kept.degenerate_landmark_ids) == 0


def test_a_landmark_behind_a_camera_is_left_out():
    problem, _, j = _with_a_landmark_at_a_camera()
    T = problem.poses[3]
    problem.landmarks[j] = T[:3, 3] - 2.0 * T[:3, 2]
    res = sliding_window_ba(problem, BAConfig())
    assert list(res.degenerate_landmark_ids) == [j]


def test_second_solve_uses_the_final_kernel_from_the_first_solves_result():
    """Huber first (convex: safe from the PnP/triangulation guess), then the final kernel from
    its solution. With equal kernels and no gross outlier there is no second solve."""
    poses, pts, kf, lm, uv, rng = _scene(seed=2)
    init, lms = _perturb(poses, pts, rng, {0, 1})
    problem = BAProblem(init, {0, 1}, {k: INTR for k in poses}, lms, kf, lm, uv)
    one = sliding_window_ba(problem, BAConfig(robust_kernel="huber", final_kernel="huber"))
    two = sliding_window_ba(problem, BAConfig(robust_kernel="huber", final_kernel="cauchy"))
    assert two.iterations > one.iterations          # the Cauchy stage ran
    assert not np.allclose(two.poses[5], one.poses[5], atol=1e-9)
    for res in (one, two):
        t_err, r_err = _errors(res.poses, poses)
        assert t_err < 0.05 and r_err < 0.3


def test_second_stage_rule_is_one_for_both_bundle_adjustments():
    # ba.factors.second_stage: what the first solve cannot explain (above outlier_px, or not
    # finite) is left out of the second solve, which runs whenever there is such an observation
    # or the final kernel differs from the first.
    from ba.factors import second_stage

    usable = np.array([True, True, True, False])
    r = np.array([0.5, 7.0, np.nan, 9.0])
    same = BAConfig(robust_kernel="huber", final_kernel="huber", outlier_px=3.0)
    np.testing.assert_array_equal(second_stage(usable, r, same), [False, True, True, False])
    assert second_stage(usable, np.array([0.5, 1.0, 2.0, 9.0]), same) is None
    other = BAConfig(robust_kernel="huber", final_kernel="cauchy", outlier_px=3.0)
    np.testing.assert_array_equal(second_stage(usable, np.array([0.5, 1.0, 2.0, 9.0]), other),
                                  [False, False, False, False])


def test_symbol_keys_are_gtsams_keys_and_refuse_indices_out_of_range():
    from gtsam.symbol_shorthand import L, X

    from ba.factors import symbol_keys

    idx = np.array([0, 1, 7, 123456, 2 ** 40])
    assert symbol_keys("x", idx) == [X(int(i)) for i in idx]
    assert symbol_keys("l", idx) == [L(int(i)) for i in idx]
    with pytest.raises(ValueError, match="2\\^56"):
        symbol_keys("l", np.array([-1]))
