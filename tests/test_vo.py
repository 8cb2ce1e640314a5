"""mona_vo.vo end to end on small generated scenes: the mask policy in the factor graph, the
keyframe graph handed to the global refinement, and rotation-only as a measured conclusion."""
import dataclasses
import functools

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data_tools.synthetic import SceneConfig, SyntheticScene
from mona_vo.conventions import Intrinsics
from mona_vo.errors import ConfigError
from mona_vo.vo import VOConfig, VisualOdometry
from mona_vo.vo_map import LandmarkFlag


@pytest.fixture(scope="module")
def one_large(render):
    scene, rendered = render(SceneConfig(width=384, height=164, n_frames=24, preset="one-large", seed=0))
    return scene, [r.image for r in rendered], [r.mask for r in rendered]


def _run(scene, images, masks=None, **cfg):
    vo = VisualOdometry(VOConfig(**cfg), scene.config.width, scene.config.height, scene.intrinsics)
    for i, image in enumerate(images):
        vo.step(image, timestamp=float(i), mask=None if masks is None else masks[i])
    return vo, vo.finish()


def _generous(masks, first=8):
    """The true masks plus, from frame ``first`` on, a false-positive block over the left
    quarter of the picture, as an imprecise mask model's: the points already tracked there
    keep being tracked inside it."""
    out = []
    for i, m in enumerate(masks):
        m = m.copy()
        if i >= first:
            m[:, : m.shape[1] // 4] = True
        out.append(m)
    return out


def test_masked_observations_and_landmarks_leave_the_factor_graph(one_large):
    scene, images, masks = one_large
    masks = _generous(masks)
    assert np.mean([m.mean() for m in masks]) > 0.1
    vo_m, with_masks = _run(scene, images, masks, refine="none")
    _, without = _run(scene, images, None, refine="none")
    # Tracks continue through the masks; the graph leaves out what lies inside one.
    assert with_masks.drops.get("ba_masked_observations", 0) > 0
    assert with_masks.drops.get("ba_masked_landmarks", 0) > 0
    assert with_masks.drops.get("tracks_entering_masks", 0) > 0
    assert without.drops.get("ba_masked_observations", 0) == 0
    # No landmark seen inside a mask is usable for a pose, and none supports one now.
    lm = vo_m.map.landmarks
    masked_ids = np.flatnonzero(lm.flags & LandmarkFlag.MASKED)
    assert len(masked_ids) and not lm.usable(masked_ids).any()
    assert len(with_masks.poses) == len(images) and np.isfinite(with_masks.poses).all()


def test_every_keyframe_keeps_its_observations_for_the_global_graph(one_large):
    scene, images, masks = one_large
    vo, res = _run(scene, images, _generous(masks), refine="none", window_keyframes=3)
    g = vo.keyframe_graph()
    K = vo.map.keyframes.n
    assert K > 3 and len(g.kf_frames) == K and np.all(np.diff(g.kf_frames) > 0)
    # Keyframes that left the window still hold observations.
    assert set(np.unique(g.obs_kf).tolist()) == set(range(K))
    assert np.isin(g.obs_lm, g.lm_ids).all() and g.obs_masked.any()
    # Observations of landmarks seen inside a mask are handed over flagged.
    flagged = (vo.map.landmarks.flags[g.obs_lm] & LandmarkFlag.MASKED) > 0
    assert np.all(g.obs_masked[flagged])
    assert res.status.count("keyframe") == int(res.is_keyframe.sum())


def test_global_refinement_reattaches_every_frame(one_large):
    pytest.importorskip("ba.global_ba")
    scene, images, masks = one_large
    _, res = _run(scene, images, _generous(masks), refine="global")
    assert res.refine and res.refine["keyframes"] >= 2
    assert np.isfinite(res.poses).all() and np.isfinite(res.reprojection_rmse_px)
    assert res.drops.get("ba_masked_observations", 0) > 0


def _pan_frames(n, deg_per_frame, W=320, H=136):
    rng = np.random.default_rng(4)
    wide = cv2.resize(rng.integers(0, 255, (3 * H // 4, 3 * W // 4, 3), np.uint8), (3 * W, 3 * H),
                      interpolation=cv2.INTER_CUBIC)
    wide = cv2.GaussianBlur(wide, (3, 3), 0)
    f = float(0.5 * W / np.tan(np.radians(30.0)))
    K_out = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    K_src = np.array([[f, 0, (3 * W - 1) / 2], [0, f, (3 * H - 1) / 2], [0, 0, 1.0]])
    frames, rots = [], []
    for i in range(n):
        R = Rotation.from_euler("y", deg_per_frame * i, degrees=True).as_matrix()
        frames.append(cv2.warpPerspective(wide, K_src @ R @ np.linalg.inv(K_out), (W, H),
                                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP))
        rots.append(R)
    return frames, Intrinsics(f, f, (W - 1) / 2, (H - 1) / 2), rots


def test_a_pure_pan_is_concluded_rotation_only_with_its_evidence():
    frames, intr, rots = _pan_frames(30, 0.7)
    vo = VisualOdometry(VOConfig(refine="none"), 320, 136, intr)
    for i, f in enumerate(frames):
        vo.step(f, timestamp=float(i))
    res = vo.finish()
    assert set(res.status) == {"rotation-only"}
    p = res.parallax
    assert p["conclusion"] == "rotation-only" and p["ratio"] < p["translation_ratio"]
    assert p["noise_floor_px"] > 0 and p["baseline_frames"] > 0
    assert np.abs(res.poses[:, :3, 3]).max() < 1e-9
    err = [np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3].T @ R).as_rotvec()))
           for T, R in zip(res.poses, rots)]
    assert max(err) < 0.1


def test_fast_rotation_under_motion_blur_keeps_tracking_with_weak_texture_points(sequence):
    """Generated 'mixed' seed 3 (a tuning seed): low-texture walls, motion blur, 3-4.5 deg per
    frame and a walking camera. With the fixed point score (1e-4) tracking was lost after frame
    20 and the 18 frames after it got no map (12 % ATE; 5.3 % since lost frames carry the
    camera's velocity); the score relative to the frame's best keeps every frame tracked
    (5.0 %)."""
    from eval.metrics import Trajectory, evaluate_trajectory
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory
    from mona_vo.config import apply_overrides

    scene, frames, masks = sequence("mixed", 3, 40, 640, 272)
    gt = Trajectory(np.arange(40, dtype=float), scene.poses())
    out = {}
    for name, sets in (("relative", {}), ("fixed", {"vo.point_min_score": 1e-4})):
        cfg = apply_overrides(PipelineConfig(), {"vo.refine": "none", **sets})
        res = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                  config=cfg).vo
        out[name] = (sum(s in ("rotation-only", "extrapolated") for s in res.status),
                     evaluate_trajectory(gt, Trajectory(res.timestamps, res.poses)).ate_percent_of_path)
    assert out["fixed"][0] >= 10            # the failure this guards against still exists
    assert out["relative"][0] == 0
    assert out["relative"][1] < out["fixed"][1]


def test_frames_where_tracking_is_lost_carry_the_walk_on_until_a_new_map():
    """Three blank frames in a forward walk (generated 'mixed' seed 105, a validation seed,
    used here for its straight path): tracking is lost and a new map starts after them. The
    frames between keep the camera's usual body velocity; before, they kept the lost frame's
    position, and the new map started there, so the walk after it was offset by the gap
    (ATE 0.41 m against 0.17 m with the velocity carried)."""
    from eval.metrics import Trajectory, evaluate_trajectory
    from data_tools.frames import Frame
    from eval.vo_bench import render_sequence
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = render_sequence("mixed", 105, 30, 480, 204)
    for i in (12, 13, 14):
        frames[i] = Frame(i, float(i), frames[i].name, np.full_like(frames[i].image, 128))
    res = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                              config=PipelineConfig()).vo
    assert res.drops["tracking_lost"] >= 1
    gap = [i for i, s in enumerate(res.status) if s == "extrapolated"]
    assert gap and set(gap) <= {12, 13, 14}
    # Two maps, the gap on neither: the report says where the trajectory is joined.
    assert len(res.map_segments) == 2
    (a0, a1), (b0, b1) = res.map_segments
    assert a0 == 0 and a1 < gap[0] and b0 > gap[-1] and b1 == 29
    c = res.poses[:, :3, 3]
    usual = np.median(np.linalg.norm(np.diff(c[:11], axis=0), axis=1))
    steps = np.linalg.norm(np.diff(c[gap[0] - 1:16], axis=0), axis=1)
    assert np.all(steps > 0.5 * usual) and np.all(steps < 2.0 * usual)
    m = evaluate_trajectory(Trajectory(np.arange(30, dtype=float), scene.poses()),
                            Trajectory(res.timestamps, res.poses))
    assert m.ate_percent_of_path < 2.0


def test_frames_before_the_first_map_walk_back_along_its_first_velocity(monkeypatch):
    """Generated 'mixed' seed 203 (a tuning seed): a fast turn while walking, 0.08 m per frame,
    opening on a near-blank wall. The start waits (until frame 9 on stop 47's host, 15 on stop
    49's); the frames before have almost nothing to track and keep their rotation alone. Left
    where the map starts, they put their walk into the error; walked back along the map's first
    body velocity, they do not. Scored on the frames up to ten after the start, so that what the
    rest of this fast turn does (a chaotic run: the whole clip gave 6.0 -> 2.2 % of path on stop
    47's host, 13.6 -> 10.1 % on stop 49's) does not stand in for the walk-back: stop 49's host
    17.4 -> 2.8 %."""
    from eval.metrics import Trajectory, evaluate_trajectory
    from eval.vo_bench import render_sequence
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = render_sequence("mixed", 203, 40, 640, 272)
    gt = Trajectory(np.arange(40, dtype=float), scene.poses())

    def run():
        return estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                   config=PipelineConfig()).vo

    def early_ate(res, n):
        return evaluate_trajectory(Trajectory(gt.timestamps[:n], gt.poses_T_world_cam[:n]),
                                   Trajectory(res.timestamps[:n], res.poses[:n])).ate_percent_of_path

    res = run()
    first = next(i for i, s in enumerate(res.status) if s != "extrapolated")
    ate = early_ate(res, first + 11)
    assert first >= 5 and res.status[first] == "keyframe"
    c = res.poses[:, :3, 3]
    usual = np.median(np.linalg.norm(np.diff(c[first:first + 10], axis=0), axis=1))
    steps = np.linalg.norm(np.diff(c[:first + 1], axis=0), axis=1)
    assert np.all(steps > 0.5 * usual) and np.all(steps < 2.0 * usual)
    monkeypatch.setattr(VisualOdometry, "_start_walk_back", lambda self: {})
    still = run()
    assert still.status[:first] == ["rotation-only"] * first   # the case still arises
    assert ate < 0.5 * early_ate(still, first + 11)


def _turn_error_deg(poses_est, poses_gt):
    Re = poses_est[0, :3, :3].T @ poses_est[-1, :3, :3]
    Rg = poses_gt[0, :3, :3].T @ poses_gt[-1, :3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(Re.T @ Rg) - 1) / 2, -1, 1))))


def test_the_start_pair_refitted_on_many_matches_ends_a_slow_pans_rotation_bias(sequence):
    """Generated 'mixed' seeds 207 and 208 (tuning), true masks and intrinsics. 207, a slow pan
    drifting sideways: its start pair from the VO's 92 tracks was 1.2 deg off, and the whole
    clip turned 2.1 deg short of the true 12.8; refitted on about 600 matches, 0.13 deg. 208, a
    hand-held walk whose start pair was right (0.02 deg): the many matches slid (LK across
    eleven frames of shake) and would have started it 1.5 deg off; the chi-square test keeps
    the pair it had. Since stop 55 the start pair's fit at its tracks' own noise
    (vo.init_fit_scales=3) ends 207's bias by itself (measured 0.13 deg without the refit), so
    the refit is judged behind the one 1 px fit, where the bias still arises."""
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    err = {}
    for seed in (207, 208):
        scene, frames, masks = sequence("mixed", seed, 40, 640, 272)
        for dense in (1000, 0):
            cfg = apply_overrides(PipelineConfig(), {"vo.init_dense_points": dense,
                                                     "vo.init_fit_scales": 1})
            res = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                      config=cfg).vo
            err[seed, dense] = _turn_error_deg(res.poses, scene.poses())
    assert err[207, 0] > 1.5                      # the bias this guards against still exists
    assert err[207, 1000] < 0.5
    assert err[208, 1000] < err[208, 0] + 0.05    # a right start is not replaced


def test_a_map_is_not_started_on_a_pair_whose_translation_is_undetermined():
    """Generated 'mixed' seed 243 (a tuning seed): a walk turning 5 deg per frame past a street
    15 m deep. Frames 0 and 4 (19 deg apart, 0.8 deg of parallax) passed every other start
    test, but their translation was 108 deg off, and the map started there kept a distorted
    depth (near points 6x too far against far ones 2x) that no later bundle adjustment undid:
    10.4 % of path. Random halves of that pair disagree on the direction by 87 deg; with the
    check on (45 deg; off by default, it did not generalise to the validation seeds) the map
    waits for a pair whose halves agree (frames 8 and 11)."""
    from eval.metrics import Trajectory, evaluate_trajectory
    from eval.vo_bench import render_sequence
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = render_sequence("mixed", 243, 40, 640, 272)
    gt = Trajectory(np.arange(40, dtype=float), scene.poses())
    ate = {}
    for spread in (45.0, 180.0):
        cfg = apply_overrides(PipelineConfig(), {"vo.init_max_translation_spread_deg": spread})
        res = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                  config=cfg).vo
        assert "rotation-only" not in res.status
        ate[spread] = evaluate_trajectory(gt, Trajectory(res.timestamps, res.poses)).ate_percent_of_path
    assert ate[180.0] > 5.0                 # the failure this guards against still exists
    assert ate[45.0] < 0.2 * ate[180.0]


def test_global_refinement_poses_tracked_frames_again_on_the_refined_map(monkeypatch, render):
    # A slow creep (generator tuning seed 0): frames that only followed their keyframe kept the
    # pose PnP found on the window's map, errors and all; posed again on the refined map they
    # are nearer the truth (measured 0.41 -> 0.18 % of path).
    from eval.metrics import Trajectory, evaluate_trajectory

    scene, rendered = render(SceneConfig(width=640, height=272, n_frames=40, preset="creep", seed=0))
    images, masks = [r.image for r in rendered], [r.mask for r in rendered]
    t = np.arange(len(images), dtype=float)
    gt = Trajectory(t, scene.poses())
    vo, res = _run(scene, images, masks, refine="global")
    assert res.refine["frames_reposed"] >= 0.5 * res.status.count("tracked")
    monkeypatch.setattr(VisualOdometry, "_repose_frames", lambda self, *args: 0)
    _, follow = _run(scene, images, masks, refine="global")
    ate = evaluate_trajectory(gt, Trajectory(t, res.poses)).ate_percent_of_path
    ate_follow = evaluate_trajectory(gt, Trajectory(t, follow.poses)).ate_percent_of_path
    assert ate < 0.7 * ate_follow, (ate, ate_follow)


def test_without_intrinsics_the_global_refinement_corrects_a_wrong_focal_length(render):
    # A slow creep (generator tuning seed 0) started from a focal length 28 % too long, as the
    # estimate from the first frames gives on it: freed in the global refinement (Cal3f), the
    # focal length comes back near the truth and the trajectory with it (measured: +28 -> +6.9 %,
    # 0.45 -> 0.13 % of path). Intrinsics given per frame are never changed.
    from eval.metrics import Trajectory, evaluate_trajectory

    scene, rendered = render(SceneConfig(width=640, height=272, n_frames=40, preset="creep", seed=0))
    K = scene.intrinsics
    wrong = Intrinsics(1.28 * K.fx, 1.28 * K.fy, 319.5, 135.5)
    t = np.arange(len(rendered), dtype=float)
    gt = Trajectory(t, scene.poses())

    def run(given=None, **cfg):
        vo = VisualOdometry(VOConfig(**cfg), 640, 272, wrong, camera_known=False)
        for i, r in enumerate(rendered):
            vo.step(r.image, timestamp=float(i), mask=r.mask, intrinsics=given)
        res = vo.finish()
        return res, evaluate_trajectory(gt, Trajectory(t, res.poses)).ate_percent_of_path

    freed, ate_freed = run(global_camera="focal")
    held, ate_held = run(global_camera="none")
    assert held.focal == pytest.approx(wrong.fx)
    assert abs(freed.focal - K.fx) < 0.3 * abs(wrong.fx - K.fx), (freed.focal, K.fx)
    assert ate_freed < 0.7 * ate_held, (ate_freed, ate_held)
    given, _ = run(given=wrong, global_camera="focal")
    assert given.focal == pytest.approx(wrong.fx)


def test_tracks_sliding_along_depth_edges_are_dropped_and_the_trajectory_gains(monkeypatch, render):
    # A generated slow pan (mixed seed 207, a seed outside the validation seeds 100-111): corners
    # where a near edge crosses the far background track well but are no points of the scene.
    # The keyframe dissimilarity check drops them -- several times more often than the other
    # tracks, measured against the true depth edges -- and the ATE falls (measured 1.05 -> 0.67 %).
    # The smaller ray angle of a starved map (stop 48) is held off: with it this pan's map takes
    # more far points and the check's gain shrinks to 0.92 -> 0.81 %; the scenario is the check's.
    from eval.metrics import Trajectory, evaluate_trajectory

    scene, rendered = render(SceneConfig(width=640, height=272, n_frames=40, preset="mixed", seed=207))
    t = np.arange(len(rendered), dtype=float)
    gt = Trajectory(t, scene.poses())

    def depth_edges(r, radius=3):
        d = np.log(np.maximum(r.depth, 1e-3)).astype(np.float32)
        g = np.hypot(cv2.Sobel(d, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(d, cv2.CV_32F, 0, 1, ksize=3))
        k = 2 * radius + 1
        return cv2.dilate((g > 0.2).astype(np.uint8), np.ones((k, k), np.uint8)) > 0

    near_edge = {"dropped": [], "kept": []}
    original = VisualOdometry._drop_dissimilar

    def spy(self, gray, obs, T, intr):
        out = original(self, gray, obs, T, intr)
        edges = depth_edges(rendered[self.map.frames.n - 1])
        gone = ~np.isin(obs.ids, out.ids)
        xy = np.clip(np.rint(obs.uv).astype(int), 0, [edges.shape[1] - 1, edges.shape[0] - 1])
        on = edges[xy[:, 1], xy[:, 0]]
        near_edge["dropped"] += on[gone].tolist()
        near_edge["kept"] += on[~gone].tolist()
        return out

    monkeypatch.setattr(VisualOdometry, "_drop_dissimilar", spy)
    fixed_angle = {"triangulation_starved_angle_deg": 0.0}
    _, res = _run(scene, [r.image for r in rendered], [r.mask for r in rendered], **fixed_angle)
    assert res.drops["tracks_dissimilar"] > 0
    assert np.mean(near_edge["dropped"]) > 2 * np.mean(near_edge["kept"]), near_edge
    ate = evaluate_trajectory(gt, Trajectory(t, res.poses)).ate_percent_of_path
    monkeypatch.setattr(VisualOdometry, "_drop_dissimilar", original)
    _, off = _run(scene, [r.image for r in rendered], [r.mask for r in rendered],
                  patch_dissimilarity=0.0, **fixed_angle)
    ate_off = evaluate_trajectory(gt, Trajectory(t, off.poses)).ate_percent_of_path
    assert ate < 0.8 * ate_off, (ate, ate_off)


@functools.lru_cache(maxsize=1)
def _forward_follow_start():
    """The first 16 frames of generated 'mixed' seed 2 (a tuning seed: a forward follow with
    heavy JPEG), their true masks and poses."""
    scene = SyntheticScene(SceneConfig(width=640, height=272, n_frames=40, preset="mixed", seed=2))
    rendered = [scene.render(i) for i in range(16)]       # each frame alone: list(scene)[:16]
    return scene, [r.image for r in rendered], [r.mask for r in rendered], scene.poses()[:16]


@functools.lru_cache(maxsize=1)
def _forward_follow_one_fit():
    """The streaming VO over that start with the start pair's one 1 px fit: the baseline of
    both tests below (the same worker runs them, xdist group forward-follow-start)."""
    scene, images, masks, _ = _forward_follow_start()
    return _run(scene, images, masks, refine="none", init_fit_scales=1)[1]


@pytest.mark.xdist_group("forward-follow-start")
def test_the_start_pair_check_drops_tracks_sliding_along_depth_edges():
    # A tenth of the start pair's tracks slide along depth edges, and the essential matrix
    # fitted with them at 1 px puts the translation 60-76 deg off (a sideways camera for a
    # forward one). With the start pair's dissimilarity check (vo.init_drop_dissimilar) the
    # pair is fitted without them; measured: median per-frame translation direction error
    # 72.6 -> 10.0 deg. The one 1 px fit (vo.init_fit_scales=1) is what the check is judged on.
    from eval.metrics import heading_errors_deg

    scene, images, masks, G = _forward_follow_start()

    def direction_error(poses):
        return float(np.nanmedian(heading_errors_deg(G, poses)))

    _, on = _run(scene, images, masks, refine="none", init_drop_dissimilar=True,
                 init_fit_scales=1)
    off = _forward_follow_one_fit()
    assert on.drops["tracks_dissimilar"] > 0
    assert on.status[0] == "keyframe"    # the map still starts at the first frame
    e_on, e_off = direction_error(on.poses), direction_error(off.poses)
    assert e_on < 20.0 and e_on < 0.5 * e_off, (e_on, e_off)


@pytest.mark.xdist_group("forward-follow-start")
def test_the_start_pair_fitted_at_the_tracks_noise_travels_the_right_way():
    """The same start with every track kept: the sliding tracks hold the 1 px fit's wrong
    pose, the fit chosen at three times the tracks' own noise (vo.init_fit_scales,
    two_view.tighten_relative_pose) does not (measured: median per-frame translation direction
    error 72.6 -> 9.0 deg), and the map starts from the same frames."""
    from eval.metrics import heading_errors_deg

    scene, images, masks, G = _forward_follow_start()
    one = _forward_follow_one_fit()
    _, tight = _run(scene, images, masks, refine="none", init_fit_scales=3)
    e_one = float(np.nanmedian(heading_errors_deg(G, one.poses)))
    e_tight = float(np.nanmedian(heading_errors_deg(G, tight.poses)))
    assert e_one > 45.0 and e_tight < 15.0, (e_one, e_tight)
    # The pair that starts the map is the same (the gates judge the 1 px fit).
    assert list(np.flatnonzero(one.is_keyframe)[:2]) == list(np.flatnonzero(tight.is_keyframe)[:2])


def test_the_start_pair_check_leaves_a_start_alone_unless_its_refit_travels_another_way():
    """Generated 'mixed' seed 0 (a tuning seed, a hand-held walk, true masks): the start pair's
    refit without its dissimilar tracks moves the translation 1.9 deg. Taken, the dropped tracks
    change the map (on Bonn's draws, refits of 0.6-12 deg made the runs worse, stop 51); with
    the check on (an option) and below init_dissimilar_min_turn_deg the start is the one the
    check-free VO makes, to the bit."""
    from eval.vo_bench import render_sequence
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = render_sequence("mixed", 0, 24, 640, 272)

    def poses(**vo):
        cfg = apply_overrides(PipelineConfig(), {f"vo.{k}": v for k, v in vo.items()})
        return estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                   config=cfg).vo.poses

    off = poses(refine="none")
    assert np.array_equal(poses(init_drop_dissimilar=True, refine="none"), off)
    assert not np.array_equal(poses(init_drop_dissimilar=True, init_dissimilar_min_turn_deg=0.0,
                                    refine="none"), off)


def test_the_start_pair_check_takes_no_refit_that_a_large_unmasked_mover_holds(render):
    """The one-large scene of the central-claim tests (seed 0, a car over 28 % of the view), no
    masks, grid 17: once the start pair's dissimilar tracks are dropped, the car's points join
    the refit's consensus (64 % of its inliers were the start's) and turn it 103 deg: the run
    goes the wrong way (heading 49 deg, 18.9 % of path). vo.init_dissimilar_min_shared=0.8
    refuses that refit, and the run is the check-free VO's (stop 52)."""
    from eval.metrics import heading_errors_deg
    from eval.vo_bench import frames_of
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, rendered = render(SceneConfig(width=384, height=164, n_frames=24, preset="one-large",
                                         seed=0))
    frames, _ = frames_of(rendered)

    def poses(**vo):
        cfg = apply_overrides(PipelineConfig(), {"vo.grid_size": 17, "vo.refine": "none",
                                                 **{f"vo.{k}": v for k, v in vo.items()}})
        return estimate_trajectory(frames, intrinsics=scene.intrinsics, config=cfg).vo.poses

    gated = poses(init_drop_dissimilar=True)
    assert np.nanmedian(heading_errors_deg(scene.poses(), gated)) > 30
    shared = poses(init_drop_dissimilar=True, init_dissimilar_min_shared=0.8)
    assert np.array_equal(shared, poses())


def test_the_drift_test_drops_tracks_that_leave_their_static_point_and_lowers_the_error(monkeypatch):
    # A generated forward walk behind a car that keeps about the camera's pace (mixed seed 209,
    # a tuning seed), no masks. Some tracks fit the static map within a pixel or two after each
    # keyframe and then drift off it, never far enough for the two-strike test: the car's, and
    # static-scene tracks that slide along an outline against the far background. The drift
    # test (vo.drift_bound) drops them; measured: ATE 0.171 -> 0.088 % of path. What it drops
    # is judged against the renderer: a track is inconsistent when its first observation,
    # moved with the true depth and poses, lands more than 2 px from where it is tracked now.
    from eval.metrics import Trajectory, evaluate_trajectory

    scene = SyntheticScene(SceneConfig(width=640, height=272, n_frames=40, preset="mixed", seed=209))
    rendered = list(scene)
    images = [r.image for r in rendered]
    t = np.arange(len(images), dtype=float)
    G = scene.poses()
    K = scene.intrinsics.K
    first: dict[int, tuple[int, np.ndarray]] = {}
    judged = {"drifting": [], "kept": []}
    original = VisualOdometry._flag_dynamic

    def off_static_point(k, ids, uv):
        out = []
        for i, q in zip(ids, uv):
            k0, q0 = first[int(i)]
            depth = rendered[k0].depth
            u = np.clip(np.rint(q0).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
            X = np.linalg.solve(K, [q0[0], q0[1], 1.0]) * depth[u[1], u[0]]
            T = np.linalg.inv(G[k]) @ G[k0]
            p = K @ (T[:3, :3] @ X + T[:3, 3])
            out.append(np.hypot(*(p[:2] / p[2] - q)) > 2.0)
        return out

    def spy(self, obs, intr, T):
        k = self.map.frames.n - 1
        for i, q in zip(obs.ids, obs.uv):
            first.setdefault(int(i), (k, q.copy()))
        before = self.map.landmarks.flagged(obs.ids)
        drifting_before = self.drops["tracks_flagged_drifting"]
        original(self, obs, intr, T)
        new = self.map.landmarks.flagged(obs.ids) & ~before
        if self.drops["tracks_flagged_drifting"] > drifting_before:
            judged["drifting"] += off_static_point(k, obs.ids[new], obs.uv[new])
        if k % 5 == 0:
            keep = ~self.map.landmarks.flagged(obs.ids)
            judged["kept"] += off_static_point(k, obs.ids[keep], obs.uv[keep])

    monkeypatch.setattr(VisualOdometry, "_flag_dynamic", spy)
    _, on = _run(scene, images, None, drift_bound=12.0)
    monkeypatch.setattr(VisualOdometry, "_flag_dynamic", original)
    _, off = _run(scene, images, None, drift_bound=0.0)
    assert on.drops["tracks_flagged_drifting"] >= 10
    # The tracks it drops are far more often inconsistent with any static point than those kept.
    # (measured: 37 of 40 dropped, 27 % of those kept -- the car's unflagged tracks among them)
    assert np.mean(judged["drifting"]) > 0.75, judged["drifting"]
    assert np.mean(judged["drifting"]) > 2 * np.mean(judged["kept"]), (
        np.mean(judged["drifting"]), np.mean(judged["kept"]))
    ate_on = evaluate_trajectory(Trajectory(t, G), Trajectory(t, on.poses)).ate_percent_of_path
    ate_off = evaluate_trajectory(Trajectory(t, G), Trajectory(t, off.poses)).ate_percent_of_path
    assert ate_on < 0.7 * ate_off, (ate_on, ate_off)


def test_the_global_refinement_moves_a_wrong_map_much_and_a_good_one_little(render):
    """The verdict's self-check, without ground truth: on a fast turn whose scale slid (mixed
    seed 3, 4.5 deg per frame, motion blur) the global refinement moves the keyframes by
    several % of their path and the poses rested on few points, so `batch` calls the clip not
    usable; on a well-posed walk (seed 1) both stay quiet and it is usable. True masks and
    intrinsics, so only the VO is judged. The wrong map is the one started from the pair's one
    1 px fit (vo.init_fit_scales=1); from the default start seed 3 is still wrong (3.4 % of
    path) but less inconsistent (measured shift 0.54 %, a tenth of the poses on 32 points), and
    the verdict must still reject it."""
    from eval.metrics import Trajectory, score_trajectory
    from mona_vo.batch import clip_verdict

    out = {}
    for seed, sets in ((3, {"init_fit_scales": 1}), (3, {}), (1, {})):
        scene, rendered = render(SceneConfig(width=640, height=272, n_frames=40, preset="mixed", seed=seed))
        _, res = _run(scene, [r.image for r in rendered], [r.mask for r in rendered], **sets)
        ate = score_trajectory(Trajectory(np.arange(40.0), scene.poses()),
                               Trajectory(res.timestamps, res.poses)).ate_percent_of_path
        summary = {"frames": 40, "frames_with_pose": 40, "low_confidence_share": 0.0,
                   "reprojection_rmse_px": res.reprojection_rmse_px,
                   "global_shift_pct": res.refine["keyframe_shift_pct"],
                   "support_p10": res.pose_support()["inliers_p10"]}
        out[seed, bool(sets)] = ate, summary, clip_verdict(summary)
    ate, s, v = out[3, True]
    assert ate > 1.0 and s["global_shift_pct"] > 1.0 and s["support_p10"] < 40 and not v.usable
    ate, s, v = out[3, False]
    assert ate > 1.0 and not v.usable, (ate, s)
    ate, s, v = out[1, False]
    assert ate < 0.2 and s["global_shift_pct"] < 0.25 and s["support_p10"] > 100 and v.usable


def test_tracks_held_to_their_first_look_do_not_drift_and_the_trajectory_gains(monkeypatch, render):
    # A generated static scene (static seed 0, a tuning seed), true intrinsics. Frame-to-frame
    # Lucas-Kanade drifts (about 0.02 px per frame here); with vo.anchor_tracks (an option, off)
    # the VO fits every track's patch at each keyframe as first anchored (mona_vo.patch_align)
    # and moves the track there. Judged
    # against the renderer: a track's anchor pixel, moved with the true depth and poses, is
    # where the track should be. Measured, over the 490 moved tracks at least 10 frames past
    # their anchor: median error 0.210 -> 0.067 px; ATE 0.086 -> 0.045 % of path.
    from eval.metrics import Trajectory, evaluate_trajectory

    scene, rendered = render(SceneConfig(width=640, height=272, n_frames=40, preset="static", seed=0))
    images = [r.image for r in rendered]
    G = scene.poses()
    K = scene.intrinsics.K
    errors = {"before": [], "after": []}
    original = VisualOdometry._to_anchors

    def truth(k0, q0, k):
        depth = rendered[k0].depth
        u = np.clip(np.rint(q0).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
        X = np.linalg.solve(K, [q0[0], q0[1], 1.0]) * depth[u[1], u[0]]
        T = np.linalg.inv(G[k]) @ G[k0]
        p = K @ (T[:3, :3] @ X + T[:3, 3])
        return p[:2] / p[2]

    def spy(self, gray, obs, T_world_cam, intr):
        out = original(self, gray, obs, T_world_cam, intr)
        k = self.map.frames.n - 1
        a = self._anchors
        _, ia, io = np.intersect1d(a.ids, obs.ids, return_indices=True)
        for j, i in zip(ia, io):
            k0 = int(self.map.keyframes.frame[a.rows[j]])
            if k - k0 >= 10 and np.any(out.uv[i] != obs.uv[i]):
                q = truth(k0, a.uv[j], k)
                errors["before"].append(np.hypot(*(obs.uv[i] - q)))
                errors["after"].append(np.hypot(*(out.uv[i] - q)))
        return out

    # Measured before stop 40's landmarks found again, which lower this scene's error without
    # anchors (0.086 -> 0.069 %; with them 0.049 %): the option is judged on the VO it was
    # built on.
    before_stop_40 = dict(reacquire_keyframes=0, ba_outside_keyframes=0)
    monkeypatch.setattr(VisualOdometry, "_to_anchors", spy)
    _, on = _run(scene, images, None, anchor_tracks=True, **before_stop_40)
    monkeypatch.setattr(VisualOdometry, "_to_anchors", original)
    _, off = _run(scene, images, None, anchor_tracks=False, **before_stop_40)
    before, after = np.median(errors["before"]), np.median(errors["after"])
    assert len(errors["after"]) > 200 and after < 0.5 * before, (before, after)
    t = np.arange(len(images), dtype=float)
    ate_on = evaluate_trajectory(Trajectory(t, G), Trajectory(t, on.poses)).ate_percent_of_path
    ate_off = evaluate_trajectory(Trajectory(t, G), Trajectory(t, off.poses)).ate_percent_of_path
    assert ate_on < 0.7 * ate_off, (ate_on, ate_off)


def _passer_by(images, width, start=2, speed=18):
    """Frames of a static scene with a flat grey band (a passer-by, a quarter of the frame wide)
    sweeping from left to right across them from frame ``start``: every track it covers is lost."""
    out = []
    for i, im in enumerate(images):
        im = im.copy()
        x0 = -width // 4 + speed * i
        a, b = max(0, x0), min(width, x0 + width // 4)
        if i >= start and a < b:
            im[:, a:b] = 128
        out.append(im)
    return out


def test_landmarks_hidden_by_a_passer_by_are_found_again_where_they_are_and_the_error_falls(monkeypatch):
    # Static seeds 0-3 (480 x 204, 40 frames, true intrinsics) with a grey band sweeping across:
    # without the search by projection every landmark it passes over is gone for good, and the
    # pose rests on points seeded after it. With it (vo.reacquire_keyframes=20 and
    # vo.ba_outside_keyframes=8, the defaults) the landmarks are tracked again once it has passed. Judged
    # against the renderer (a landmark's pixel in the keyframe that last saw it, moved with the
    # true depth and poses). Measured: 50-115 landmarks found again per scene, median error
    # 0.04-0.19 px; ATE 0.073 / 0.284 / 0.124 / 0.126 -> 0.098 / 0.079 / 0.124 / 0.055 % of path
    # (geometric mean of the ratios 0.63; seed 0 loses).
    from eval.metrics import Trajectory, evaluate_trajectory

    original = VisualOdometry._reacquire
    errors: list[float] = []
    state = {}

    def spy(self, gray, obs, T_world_cam, intr, mask):
        out = original(self, gray, obs, T_world_cam, intr, mask)
        rendered, G, K = state["rendered"], state["G"], state["K"]
        k = self.map.frames.n - 1
        kf = self.map.keyframes
        for j, q in zip(out.ids[len(obs.ids):], out.uv[len(obs.ids):]):
            r = max(r for r in range(kf.n) if j in kf.observations(r)[0])
            ids_r, uv_r, _ = kf.observations(r)
            q0 = uv_r[np.flatnonzero(ids_r == j)[0]]
            k0 = int(kf.frame[r])
            depth = rendered[k0].depth
            u = np.clip(np.rint(q0).astype(int), 0, [depth.shape[1] - 1, depth.shape[0] - 1])
            X = np.linalg.solve(K, [q0[0], q0[1], 1.0]) * depth[u[1], u[0]]
            T = np.linalg.inv(G[k]) @ G[k0]
            p = K @ (T[:3, :3] @ X + T[:3, 3])
            errors.append(float(np.hypot(*(q - p[:2] / p[2]))))
        return out

    monkeypatch.setattr(VisualOdometry, "_reacquire", spy)
    ratios = []
    for seed in range(4):
        scene = SyntheticScene(SceneConfig(width=480, height=204, n_frames=40, preset="static",
                                           seed=seed))
        rendered = list(scene)
        state.update(rendered=rendered, G=scene.poses(), K=scene.intrinsics.K)
        images = _passer_by([r.image for r in rendered], 480)
        t = np.arange(len(images), dtype=float)
        ate = {}
        for name, cfg in (("off", dict(reacquire_keyframes=0, ba_outside_keyframes=0)),
                          ("on", dict(reacquire_keyframes=20, ba_outside_keyframes=8))):
            errors.clear()
            _, res = _run(scene, images, None, **cfg)
            ate[name] = evaluate_trajectory(Trajectory(t, state["G"]),
                                            Trajectory(t, res.poses)).ate_percent_of_path
            if name == "off":
                assert res.found_again == 0
            else:
                assert res.found_again == len(errors) >= 40, seed
                assert np.median(errors) < 0.25, (seed, np.median(errors))
        ratios.append(ate["on"] / ate["off"])
    assert np.exp(np.mean(np.log(ratios))) < 0.8, ratios
    # A tracker that cannot take a track back: no search, nothing found.
    from mona_vo.tracking import LKTracker

    class Fixed(LKTracker):
        takes_corrections = False

    vo = VisualOdometry(VOConfig(), scene.config.width, scene.config.height, scene.intrinsics,
                        tracker=Fixed())
    for i, image in enumerate(images):
        vo.step(image, timestamp=float(i))
    assert vo.finish().found_again == 0


def test_the_window_holds_its_landmarks_views_from_the_keyframes_before_it_fixed(one_large, monkeypatch):
    import mona_vo.vo as vo_module

    scene, images, masks = one_large
    problems = []
    original = vo_module.sliding_window_ba

    current = {}
    original_adjust = VisualOdometry._bundle_adjust

    def adjust(self, bootstrapping):
        current["window"] = list(self.map.window)
        return original_adjust(self, bootstrapping)

    def spy(problem, config, **kw):
        res = original(problem, config, **kw)
        problems.append((problem, res, current["window"]))
        return res

    monkeypatch.setattr(VisualOdometry, "_bundle_adjust", adjust)
    monkeypatch.setattr(vo_module, "sliding_window_ba", spy)
    vo, _ = _run(scene, images, masks, refine="none", window_keyframes=3, ba_outside_keyframes=4)
    outside_seen = 0
    for problem, res, window in problems:
        extra = sorted(set(problem.poses) - set(window))
        for r in extra:
            # Held fixed, and only their views of landmarks the window itself sees.
            assert r in problem.fixed
            assert np.allclose(res.poses[r], problem.poses[r], atol=1e-6)
            lm_r = problem.obs_lm[problem.obs_kf == r]
            assert len(lm_r) and np.isin(lm_r, problem.obs_lm[np.isin(problem.obs_kf, window)]).all()
        outside_seen += len(extra)
    assert outside_seen > 0
    problems.clear()
    _run(scene, images, masks, refine="none", window_keyframes=3, ba_outside_keyframes=0)
    assert all(set(p.poses) == set(w) for p, _, w in problems)


def test_the_accurate_preset_lowers_the_error_on_static_scenes(sequence):
    """`--preset accurate` (24 x 24 new points once a map exists, 16 x 16 at the start) against
    the default (16 x 16) on generated static scenes, true intrinsics, global refinement:
    measured 0.069 -> 0.055 and 0.031 -> 0.018 % of path on seeds 0 and 1 (README, Point
    density and the presets; the full 24 x 24 grid, start included, 0.051 and 0.011)."""
    from eval.metrics import Trajectory, evaluate_trajectory
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory
    from mona_vo.presets import PRESETS

    ratios = []
    for seed in (0, 1):
        scene, frames, masks = sequence("static", seed, 40, 640, 272)
        gt = Trajectory(np.arange(40, dtype=float), scene.poses())
        ate = {}
        for name in ("default", "accurate"):
            cfg = apply_overrides(PipelineConfig(), PRESETS[name])
            res = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                      config=cfg).vo
            assert "rotation-only" not in res.status
            ate[name] = evaluate_trajectory(gt, Trajectory(res.timestamps, res.poses)).ate_percent_of_path
        ratios.append(ate["accurate"] / ate["default"])
    assert max(ratios) < 0.9, ratios


def test_the_start_seeds_its_own_grid_and_the_map_the_denser_one(monkeypatch):
    """`vo.init_grid_size` while no map exists, `vo.grid_size` after: a start needs the pair's
    median parallax, which many far points hold down, and the map gains from more points. The
    grid each seeding used, read where the VO seeds, with the map's state at that moment; three
    blank frames then lose the map, and the new start is seeded at the start's density again."""
    import mona_vo.vo as vo_module
    from mona_vo.vo_map import VOState

    scene = SyntheticScene(SceneConfig(width=384, height=164, n_frames=30, preset="static", seed=0))
    images = [r.image for r in scene]
    for i in (16, 17, 18):
        images[i] = np.full_like(images[i], 128)
    seen = []
    real = vo_module.seed_points

    def spy(gray, grid, *args, **kwargs):
        pts = real(gray, grid, *args, **kwargs)
        seen.append((vo.map.state, grid, len(pts)))
        return pts

    monkeypatch.setattr(vo_module, "seed_points", spy)
    vo = VisualOdometry(VOConfig(init_grid_size=8, grid_size=20, refine="none"), 384, 164,
                        scene.intrinsics)
    for i, image in enumerate(images):
        vo.step(image, timestamp=float(i))
    res = vo.finish()
    states = [s for s, _, _ in seen]
    assert {g for s, g, _ in seen if s is VOState.INIT} == {8}
    assert {g for s, g, _ in seen if s is not VOState.INIT} == {20}
    assert max(n for s, _, n in seen if s is VOState.INIT) <= 64
    assert max(n for s, _, n in seen if s is not VOState.INIT) > 64
    # A map, then a loss, then a start again at the start's grid.
    first_map = states.index(VOState.TRACKING)
    assert res.drops["tracking_lost"] >= 1
    assert VOState.INIT in states[first_map:]
    # 0, the default, is the map's grid: every command that draws vo.grid_size keeps its runs.
    assert VOConfig(grid_size=14).start_grid == 14 and VOConfig().init_grid_size == 0
    with pytest.raises(ConfigError, match="'vo.init_grid_size'"):
        VOConfig(init_grid_size=1).validate()


def test_the_result_keeps_the_sliding_windows_trajectory_of_a_refined_run_to_the_bit():
    """One default run gives both VOs: ``poses_streaming`` is what vo.refine=none gives on the
    same frames, exactly (benchmarks and the central-claim tests read both from one run), and
    the refinement did move the poses (else the two would be the same array by accident)."""
    from eval.vo_bench import render_sequence
    from mona_vo.pipeline import PipelineConfig, estimate_trajectory

    scene, frames, masks = render_sequence("one-large", 1, 16, 320, 136)
    cfg = PipelineConfig()

    def run(refine):
        config = dataclasses.replace(cfg, vo=dataclasses.replace(cfg.vo, refine=refine))
        return estimate_trajectory(frames, intrinsics=scene.intrinsics, masks=list(masks),
                                   config=config).vo

    refined, streaming = run("global"), run("none")
    assert refined.refine and not streaming.refine
    np.testing.assert_array_equal(refined.poses_streaming, streaming.poses)
    np.testing.assert_array_equal(streaming.poses_streaming, streaming.poses)
    assert np.abs(refined.poses[:, :3, 3] - streaming.poses[:, :3, 3]).max() > 1e-6
