"""MONA's Dynamic Points Extraction: geometry-based residuals, Cauchy probability, the adaptive
threshold, and the streaming track windows."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from mona_vo.conventions import Intrinsics
from mona_vo.dynamic_points import (EPIPOLAR, HOMOGRAPHY, DynamicPointsConfig,
                                    DynamicPointsTracker, TrackWindow, adaptive_threshold,
                                    cauchy_dynamic_probability, classify_window,
                                    fit_camera_motion, residual_map)
from mona_vo.tracking import LKTracker

W, H = 256, 112
INTR = Intrinsics(200.0, 200.0, 127.5, 55.5)
PATCH = (100, 40, 150, 80)   # x0, y0, x1, y1 of the independently moving patch, frame 0


def _rot_y(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def parallax_window(n_frames=5, patch_motion_px=(0.0, 1.5), noise_px=0.1, seed=0):
    """A window of exact tracks: a static 3-D scene (depths 4-20 m) seen by a camera moving
    sideways and forward while turning, plus detection points on a patch that also moves by
    ``patch_motion_px`` per frame in the image. Returns (window, is_patch (n_det,), m_t (L,))."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.linspace(12, W - 12, 12), np.linspace(8, H - 8, 12))
    anchors = np.stack([xs.ravel(), ys.ravel()], axis=1)
    det = np.stack([rng.uniform(8, W - 8, 300), rng.uniform(8, H - 8, 300)], axis=1)
    pix0 = np.concatenate([anchors, det])
    depth = rng.uniform(4.0, 20.0, len(pix0))
    x0, y0, x1, y1 = PATCH
    on_patch = (pix0[:, 0] >= x0) & (pix0[:, 0] <= x1) & (pix0[:, 1] >= y0) & (pix0[:, 1] <= y1)
    on_patch[:len(anchors)] = False          # anchors are static here
    depth[on_patch] = 8.0
    X = np.stack([(pix0[:, 0] - INTR.cx) / INTR.fx * depth,
                  (pix0[:, 1] - INTR.cy) / INTR.fy * depth, depth], axis=1)
    frames = []
    for k in range(n_frames):
        R = _rot_y(0.3 * k)                   # camera turns 0.3 deg per frame
        c = np.array([0.2, 0.0, 0.3]) * k     # and moves sideways and forward, metres
        Xc = (X - c) @ R                       # world -> camera k (R is camera-to-world)
        p = np.stack([INTR.fx * Xc[:, 0] / Xc[:, 2] + INTR.cx,
                      INTR.fy * Xc[:, 1] / Xc[:, 2] + INTR.cy], axis=1)
        p[on_patch] += np.asarray(patch_motion_px) * k
        p += rng.normal(0.0, noise_px, p.shape) * (k > 0)
        frames.append(p)
    P = np.stack(frames).astype(np.float32)
    m = np.linalg.norm(np.diff(P[:, ~on_patch], axis=0), axis=2).mean(axis=1)
    m = np.append(m, m[-1])
    window = TrackWindow(np.arange(n_frames), P, len(anchors), np.arange(len(pix0)))
    return window, on_patch[len(anchors):], m


def test_patch_moving_against_parallax_field_is_dynamic_background_is_not():
    window, is_patch, m = parallax_window()
    out = classify_window(window, m, DynamicPointsConfig(), INTR)
    assert len(out) == len(window)
    first = out[0]
    assert is_patch.sum() >= 20
    assert first.is_dynamic[is_patch].all()
    assert first.is_dynamic[~is_patch].mean() <= 0.02
    assert (first.probability[is_patch] > 0.5).all()
    assert first.camera_model == EPIPOLAR
    # Every frame reports the visible detection points with the same per-track decision.
    for d in out:
        np.testing.assert_array_equal(d.is_dynamic, first.is_dynamic)


def test_same_residual_is_dynamic_under_slow_and_static_under_fast_camera():
    window, is_patch, _ = parallax_window(patch_motion_px=(0.0, 1.0), noise_px=0.0)
    # The epipolar model in both runs (the model choice also looks at theta): same residuals.
    cfg = DynamicPointsConfig(alpha=0.025, theta_min_px=0.2, noise_factor=0.0,
                              homography_min_ratio=10.0)
    slow = classify_window(window, np.full(len(window), 10.0), cfg, INTR)[0]   # theta 0.25
    fast = classify_window(window, np.full(len(window), 80.0), cfg, INTR)[0]   # theta 2.0
    np.testing.assert_allclose(slow.residual, fast.residual)
    assert slow.theta_t == pytest.approx(0.25) and fast.theta_t == pytest.approx(2.0)
    # The patch's 1 px/frame, seen across the epipolar lines (part of it runs along them).
    assert 0.4 < np.median(slow.residual[is_patch]) < 1.1
    assert slow.is_dynamic[is_patch].all()
    assert not fast.is_dynamic[is_patch].any()


def test_theta_min_keeps_a_still_camera_from_flagging_small_residuals():
    assert adaptive_threshold(0.0, 0.05, 0.3) == pytest.approx(0.3)
    assert adaptive_threshold(100.0, 0.05, 0.3) == pytest.approx(5.0)
    assert adaptive_threshold(1.0, 0.05, 0.3, noise_px=0.5, noise_factor=3) == pytest.approx(1.5)
    window, is_patch, _ = parallax_window(patch_motion_px=(0.0, 0.2), noise_px=0.0)
    cfg = DynamicPointsConfig(alpha=0.05, theta_min_px=0.3, noise_factor=0.0)
    still = classify_window(window, np.zeros(len(window)), cfg, INTR)[0]
    assert still.theta_t == pytest.approx(0.3)
    assert not still.is_dynamic.any()       # 0.2 px/frame of motion is below the floor
    cfg_low = DynamicPointsConfig(alpha=0.05, theta_min_px=0.1, noise_factor=0.0)
    assert classify_window(window, np.zeros(len(window)), cfg_low, INTR)[0] \
        .is_dynamic[is_patch].mean() > 0.9


def test_cauchy_probability_is_the_normalised_product_of_x_and_y_terms():
    r = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0], [1.0, 1.0], [10.0, 0.0], [np.nan, 0.0]])
    p = cauchy_dynamic_probability(r, scale=1.0)
    np.testing.assert_allclose(p[:5], [0.0, 0.5, 0.8, 0.75, 1 - 1 / 101])
    assert p[5] == 0.0
    assert (np.diff(cauchy_dynamic_probability(np.c_[np.linspace(0, 5, 20), np.zeros(20)],
                                               0.5)) > 0).all()


def test_camera_motion_model_choice():
    rng = np.random.default_rng(3)
    pa = np.stack([rng.uniform(0, W, 150), rng.uniform(0, H, 150)], axis=1)
    K, Ki = INTR.K, np.linalg.inv(INTR.K)
    Hrot = K @ _rot_y(2.0).T @ Ki                 # pure rotation: a homography explains all
    q = np.c_[pa, np.ones(len(pa))] @ Hrot.T
    pb = q[:, :2] / q[:, 2:3] + rng.normal(0, 0.05, pa.shape)
    rot = fit_camera_motion(pa, pb, INTR, threshold_px=0.5, inlier_px=0.5)
    assert rot.model == HOMOGRAPHY
    window, _, _ = parallax_window(noise_px=0.05)
    P = window.points
    par = fit_camera_motion(P[0, :144], P[4, :144], INTR, threshold_px=0.5, inlier_px=0.5 * 4)
    assert par.model == EPIPOLAR


def test_an_imposed_model_fits_only_that_model_with_the_same_residuals():
    window, _, _ = parallax_window(noise_px=0.05)
    pa, pb = window.points[0, :144], window.points[4, :144]
    free = fit_camera_motion(pa, pb, INTR, threshold_px=0.5, inlier_px=2.0)
    flow = np.random.default_rng(1).normal(0, 2, (H, W, 2)).astype(np.float32)
    valid = np.ones((H, W), bool)
    valid[:, :20] = False
    for model in (HOMOGRAPHY, EPIPOLAR):
        imposed = fit_camera_motion(pa, pb, INTR, threshold_px=0.5, inlier_px=2.0, model=model)
        assert imposed.model == model and np.isnan(imposed.homography_ratio)
        assert (imposed.F_b_a is None) == (model == HOMOGRAPHY)
        assert (imposed.H_b_a is None) == (model == EPIPOLAR)
        reference = residual_map(dataclasses.replace(free, model=model), flow, valid)
        np.testing.assert_array_equal(residual_map(imposed, flow, valid), reference)
        assert not reference[:, :20].any() and reference[:, 20:].all()


def textured(h, w, seed=0):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, 3)).astype(np.float32), (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def test_track_windows_share_one_frame_and_flush_only_new_frames():
    big = textured(H + 40, W + 60)
    frames = [big[20:20 + H, 2 * k:2 * k + W].copy() for k in range(8)]
    cfg = DynamicPointsConfig(window=4, n_detection=50)
    tr = DynamicPointsTracker(cfg, LKTracker())
    got = [tr.push(k, f) for k, f in enumerate(frames[:7])]
    closed = [w for w in got if w is not None]
    assert [list(w.frame_indices) for w in closed] == [[0, 1, 2, 3], [3, 4, 5, 6]]
    assert tr.flush() is None                 # only the shared frame 6 is open
    w = closed[0]
    assert w.points.shape[0] == 4 and w.n_anchors > 0
    vis = np.isfinite(w.points).all(axis=2)
    shift = np.nanmedian(w.points[3, vis[3]] - w.points[0, vis[3]], axis=0)
    np.testing.assert_allclose(shift, [-6.0, 0.0], atol=0.2)
    tr2 = DynamicPointsTracker(cfg, LKTracker())
    for k, f in enumerate(frames):
        tr2.push(k, f)
    last = tr2.flush()
    assert list(last.frame_indices) == [6, 7]


class _LosingTracker(LKTracker):
    """An LK tracker that loses the given share of its tracks at the given frames (a fast pan
    carrying points out of the image)."""

    def __init__(self, lose_at):
        super().__init__()
        self.lose_at, self.k = lose_at, 0

    def step(self, image):
        update = super().step(image)
        share = self.lose_at.get(self.k, 0.0)
        self.k += 1
        if share and len(update.ids):
            n = int(round(share * len(update.ids)))
            vis = update.visible.copy()
            vis[:n] = False
            self.remove(update.ids[:n])
            update = dataclasses.replace(update, visible=vis)
        return update


def test_window_ends_early_when_most_tracks_are_lost():
    big = textured(H + 40, W + 60)
    frames = [big[20:20 + H, 2 * k:2 * k + W].copy() for k in range(8)]
    cfg = DynamicPointsConfig(window=6, n_detection=50, min_tracked_frac=0.5)
    tr = DynamicPointsTracker(cfg, _LosingTracker({2: 0.7}))
    closed = [w for w in (tr.push(k, f) for k, f in enumerate(frames)) if w is not None]
    # Frame 2 keeps 30 % of the window's tracks: the window closes there, the next one starts.
    assert [list(w.frame_indices) for w in closed][0] == [0, 1, 2]
    tr = DynamicPointsTracker(dataclasses.replace(cfg, min_tracked_frac=0.0),
                              _LosingTracker({2: 0.7}))
    closed = [w for w in (tr.push(k, f) for k, f in enumerate(frames)) if w is not None]
    assert [list(w.frame_indices) for w in closed][0] == [0, 1, 2, 3, 4, 5]


def test_every_pair_of_a_window_uses_the_window_model():
    # A translating camera over a deep scene: the window is epipolar; the residual vectors of
    # the static detection points then stay small in every pair, the patch's do not.
    window, is_patch, m = parallax_window(n_frames=7, noise_px=0.05)
    out = classify_window(window, m, DynamicPointsConfig(), INTR)
    assert all(o.camera_model == EPIPOLAR for o in out)
    res = out[0].residual_xy
    assert res.shape == (len(out[0].points), 2)
    np.testing.assert_allclose(np.linalg.norm(res, axis=1), out[0].residual, rtol=1e-5)
    assert np.median(out[0].residual[~is_patch]) < 0.1 < np.median(out[0].residual[is_patch])
