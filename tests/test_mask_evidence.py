"""Accumulated moving-object evidence: hysteresis over time, carried along the flow, bounds."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from mona_vo import mask_evidence as ev
from mona_vo.errors import ConfigError
from mona_vo.mask_evidence import EvidenceConfig

CFG = EvidenceConfig()
H, W = 40, 64
THETA = 1.0
NO_POINTS = np.zeros((0, 2), np.float32)
NO_RES = np.zeros(0, np.float32)


def _map(block=None, value=4.0, floor=0.3):
    """Motion map: ``floor`` px/frame everywhere (static, below theta), ``value`` in block."""
    m = np.full((H, W), floor, np.float32)
    if block is not None:
        r0, r1, c0, c1 = block
        m[r0:r1, c0:c1] = value
    return m


STILL = np.zeros((H, W, 2), np.float32)


def _step(L, mmap, flow=STILL, config=CFG):
    obs = ev.observe(mmap, THETA, (H, W), NO_POINTS, NO_RES, W, config)
    if L is None:
        return ev.update(obs, obs, dataclasses.replace(config, decay=0.999))
    return ev.update(ev.carry(L, flow, 0.0), obs, config)


def test_a_one_frame_spike_on_static_ground_is_not_a_region():
    L = None
    for _ in range(5):
        L = _step(L, _map())
    spike = (10, 20, 10, 20)
    L = _step(L, _map(spike))
    assert not ev.regions(L, CFG).any()
    # ... while the same motion seen in three consecutive frames becomes one.
    L = _step(_step(L, _map(spike)), _map(spike))
    assert ev.regions(L, CFG)[12:18, 12:18].all()


def test_a_mover_stays_found_for_a_few_frames_without_evidence_then_stops():
    L = None
    block = (10, 20, 10, 20)
    for _ in range(6):
        L = _step(L, _map(block))
    found = ev.regions(L, CFG)
    kept = 0
    for k in range(10):             # the mover now moves along its epipolar lines: no evidence
        L = _step(L, _map())
        found = ev.regions(L, CFG, follow=found)      # still flow: carried in place
        if found[15, 15]:
            kept = k + 1
    assert 2 <= kept <= 6          # followed through a short gap, dropped once it stopped
    # Not followed (each frame decided alone), the same map loses it sooner.
    L2 = None
    for _ in range(6):
        L2 = _step(L2, _map(block))
    alone = 0
    for k in range(10):
        L2 = _step(L2, _map())
        if ev.regions(L2, CFG)[15, 15]:
            alone = k + 1
    assert alone < kept


def test_evidence_travels_with_the_mover_along_the_flow():
    L = None
    flow = np.zeros((H, W, 2), np.float32)
    c0 = 5
    for k in range(6):
        L = _step(L, _map((10, 20, c0 + 3 * k, c0 + 3 * k + 10)), flow)
        flow = np.zeros((H, W, 2), np.float32)
        flow[10:20, c0 + 3 * k:c0 + 3 * k + 10, 0] = 3.0     # the block moves 3 px right
    carried = ev.carry(L, flow, 0.0)
    cols = np.nonzero(carried[15] > CFG.seed)[0]
    assert cols.min() >= c0 + 18 and cols.max() <= c0 + 18 + 10
    assert ev.carry(L, None, -1.0).max() == -1.0           # no flow: nothing is carried


def _follow_a_still_mover(config, frames=8):
    """Regions after ``frames`` frames of a 14-px block standing still in the image while the
    background slides 4 px left behind it, the flow blurred across its outline as a dense flow
    is (the rim's vectors lie between the block's and the background's)."""
    flow = np.zeros((H, W, 2), np.float32)
    flow[..., 0] = -4.0
    flow[10:20, 28:42, 0] = 0.0
    flow[..., 0] = cv2.blur(flow[..., 0], (5, 1))
    block = (10, 20, 28, 42)

    def step(L, mmap):
        obs = ev.observe(mmap, THETA, (H, W), NO_POINTS, NO_RES, W, config)
        if L is None:
            return ev.update(obs, obs, dataclasses.replace(config, decay=0.999))
        return ev.update(ev.carry(L, flow, 0.0, config), obs, config)

    L = step(None, _map(block))
    for _ in range(frames):
        L = step(L, _map(block))
    return ev.regions(L, config)


def test_evidence_of_a_mover_the_camera_follows_does_not_trail_behind_it():
    found = _follow_a_still_mover(CFG)
    cols = np.nonzero(found[15])[0]
    assert cols.min() >= 26 and cols.max() <= 43        # the block, 28-41, and its rim
    assert found[15, 31:39].all()
    # Carried from the rim too (no flow edge is ever large enough), the evidence trails the
    # block by the rim's motion every frame.
    trail = _follow_a_still_mover(dataclasses.replace(CFG, edge_change_px=1e9))
    assert np.nonzero(trail[15])[0].min() < 24


def test_strong_dynamic_points_add_evidence_weak_ones_do_not():
    pts = np.array([[32.0, 20.0]], np.float32)
    strong = ev.observe(None, THETA, (H, W), pts, np.array([8.0], np.float32), W, CFG)
    weak = ev.observe(None, THETA, (H, W), pts, np.array([1.5], np.float32), W, CFG)
    assert strong[20, 32] == pytest.approx(CFG.point_gain)
    assert weak.max() == 0.0       # 1.5 theta: parallax of near static structure, not a mover


def test_with_texture_ref_a_residual_where_the_image_is_flat_is_weak_evidence():
    # The same residual on a textured patch, on one textured just at texture_ref and on a flat
    # one (sky, a bare wall: the flow there is interpolated from around it, not measured).
    cfg = dataclasses.replace(CFG, texture_ref=1e-4)
    mmap = _map((5, 15, 5, 15), value=4.0)
    mmap[25:35, 40:50] = 4.0
    mmap[25:35, 5:15] = 4.0
    texture = np.full((H, W), 100 * cfg.texture_ref, np.float32)
    texture[25:35, 5:15] = cfg.texture_ref
    texture[25:35, 40:50] = 1e-3 * cfg.texture_ref
    obs = ev.observe(mmap, THETA, (H, W), NO_POINTS, NO_RES, W, cfg, texture)
    plain = ev.observe(mmap, THETA, (H, W), NO_POINTS, NO_RES, W, cfg)
    assert obs[10, 10] == pytest.approx(plain[10, 10], rel=0.02)
    assert obs[30, 10] == pytest.approx(0.5 * plain[30, 10])
    assert obs[30, 45] < 0.01 * plain[30, 45]
    # Evidence against motion (residual below theta) is not weakened.
    assert obs[0, 0] == pytest.approx(plain[0, 0])
    off = ev.observe(mmap, THETA, (H, W), NO_POINTS, NO_RES, W,
                     dataclasses.replace(CFG, texture_ref=0.0), texture)          # 0: off
    np.testing.assert_array_equal(off, plain)


def test_flat_motion_that_holds_dynamic_points_is_exempt_from_the_texture_weight():
    # Two flat patches moving alike: a mover in a plain shirt, its tracks on its outline (two
    # dynamic points in the patch's connected motion), and a bare wall whose flow wanders (none).
    cfg = dataclasses.replace(CFG, texture_ref=1e-4, texture_exempt_points=2, point_gain=0.0)
    mmap = _map((5, 20, 5, 20), value=4.0)
    mmap[5:20, 40:55] = 4.0
    texture = np.full((H, W), 1e-3 * cfg.texture_ref, np.float32)
    weak = np.full(3, 10.0, np.float32)
    outline = np.array([[6.0, 6.0], [18.0, 19.0], [47.0, 12.0]], np.float32)  # map px = full px
    obs = ev.observe(mmap, THETA, (H, W), outline, weak, W, cfg, texture)
    plain = ev.observe(mmap, THETA, (H, W), outline, weak, W, cfg)
    assert obs[12, 12] == pytest.approx(plain[12, 12])          # two points: the mover
    assert obs[12, 47] < 0.01 * plain[12, 47]                    # one point: not enough
    none = ev.observe(mmap, THETA, (H, W), outline, weak, W,
                      dataclasses.replace(cfg, texture_exempt_points=0), texture)
    assert none[12, 12] < 0.01 * plain[12, 12]                   # no exemption: both weak


def test_segmentation_bound_is_the_grown_convex_hull_of_the_regions():
    L = np.full((H, W), CFG.clamp_lo, np.float32)
    L[10:30, 10:14] = CFG.clamp_hi          # two arms of one object (an L shape) ...
    L[26:30, 10:40] = CFG.clamp_hi
    L[2:5, 55:58] = CFG.grow + 0.5          # ... and an unseeded blob
    b = ev.bound(L, dataclasses.replace(CFG, bound_px=0))
    assert b[20, 20]                        # inside the hull, between the arms
    assert not b[3, 56]                     # never seeded: no segmentation there
    assert not b[5, 35]                     # outside the hull
    assert ev.bound(L, dataclasses.replace(CFG, bound_px=-1)) is None


def test_bad_evidence_settings_fail_with_the_key():
    with pytest.raises(ConfigError, match="decay"):
        EvidenceConfig(decay=1.5).validate()
    with pytest.raises(ConfigError, match="grow"):
        EvidenceConfig(grow=4.0, seed=3.0).validate()


def test_seeded_regions_grow_a_weak_mover_from_its_dynamic_points_only():
    # A slow mover: 0.5 px/frame, far below theta but ten robust sigmas above the static floor.
    rng = np.random.default_rng(0)
    mmap = np.abs(rng.normal(0.0, 0.04, (H, W))).astype(np.float32) + 1e-3
    mmap[10:20, 30:42] = 0.5
    cfg = dataclasses.replace(CFG, seeded_noise_factor=6.0)
    on_it = np.array([[33.0, 12.0], [38.0, 17.0]], np.float32)      # full res = map res here
    spread = ev.motion_spread(mmap)
    grown = ev.seeded_regions(mmap, on_it, W, cfg, spread)
    assert grown[10:20, 30:42].all() and grown.sum() < 1.5 * 120
    # One point is not enough; points on the static floor grow nothing; off by default.
    assert not ev.seeded_regions(mmap, on_it[:1], W, cfg, spread).any()
    assert not ev.seeded_regions(mmap, np.array([[5.0, 30.0], [6.0, 31.0]]), W, cfg, spread).any()
    assert not ev.seeded_regions(mmap, on_it, W, CFG, spread).any()
    # A region larger than the share allowed is no object (rippling water, a flickering wall).
    assert not ev.seeded_regions(mmap, on_it, W, cfg, spread, max_share=0.02).any()
