"""Moving-object evidence accumulated over time: a per-pixel log-odds map with hysteresis.

A mover must not be decided frame by frame: its motion may run along its epipolar lines for a
few frames (the dense test misses it there), and a patch of flow error or parallax may look like
motion in one frame. So the masker keeps one map ``L`` (analysis resolution, float32 log-odds
that the pixel is on a moving object) and changes it by small pure steps, one per frame:

``carry``      the previous map moved into this frame along the optical flow between them
               (forward splat: every pixel goes where its own flow vector takes it, the max kept
               where several land; background a mover uncovers starts with no evidence), so the
               evidence of a mover travels with it and does not trail behind it.
``observe``    this frame's log-likelihood ratio per pixel. Dense motion: ``z = r / theta`` (the
               residual of the flow against the camera-induced motion over the frame's
               threshold) gives ``2 log z`` -- the log-odds of the Cauchy dynamic probability
               ``1 - 1 / (1 + z^2)`` at scale theta, zero at the threshold -- clipped to
               ``[obs_min, obs_max]``; pixels without a valid residual (0 in the map) observe
               nothing. Positive values are weighted by ``s / (s + texture_ref)``, ``s`` the
               min-eigen texture score of the frame at the map's resolution: on a flat sky or
               wall the flow is interpolated from around it, not measured (Bonn crowd's first
               frames: a white wall's flow wanders 1-2 px per frame off the camera's, the same
               way forward and backward, and its mask held a fifth of the image). Connected
               positive pixels holding ``texture_exempt_points`` dynamic points keep their full
               value: a mover in flat clothes moves with its textured outline, where its tracks
               lie. The weight alone (stops 32-33, README Masks) cost exactly those people: a
               generated walker in a flat top lost his torso's mask (MONA 0.15 -> 2.06 % of
               path) and Bonn's MONA runs rose in every draw (4.53 -> 6.96 cm). A reference
               relative to the frame's median lost a generated red car smoother than the rock
               wall behind it for three frames.
               Dynamic points (judged over their whole track window, so they see a mover in
               frames where the dense test does not) add ``point_gain`` times their Cauchy
               probability within ``point_radius_frac`` of the image diagonal.
               With ``seeded_noise_factor`` > 0 (off by default), the dense map's components
               above its own noise floor (``seeded_noise_factor`` x 1.4826 x its median) that
               hold at least ``seeded_min_points`` dynamic points observe ``point_gain`` too
               (:func:`seeded_regions`): a slow mover (0.1-0.7 px per frame against a static
               floor of 0.03-0.07) stays below the frame's threshold, whose noise term comes
               from the track window's anchors (under a homography window, the parallax of
               near static points), while its long-term tracks are dynamic. Generated `mixed`
               J, tuning 0.236 -> 0.272, validation 0.286 -> 0.344, fresh 0.319 -> 0.342, no
               static scene's false-positive area changed; but DAVIS validation 0.483 -> 0.451
               (blackswan's rippling water is masked: 0.597 -> 0.441) and the Bonn MONA runs
               were worse on the mean of nine draws (5.72 -> 6.27 cm), one 53-frame clip run
               ending rotation-only (README, Masks).
``update``     ``L_t = clip(decay * carry(L_{t-1}) + observe_t, clamp_lo, clamp_hi)``: evidence
               rises within two or three frames of consistent motion and falls over a few frames
               without it (a one-frame spike on static ground starts from ``clamp_lo`` and does
               not reach the seed level).
``regions``    hysteresis, as Canny's, in space and time: the connected components of
               ``L > grow`` that hold a pixel of ``L > seed`` or of the previous frame's regions
               (carried along the flow), and at least ``min_area_frac`` of the map. These are
               the objects "found and not yet stopped": a new one needs ``seed``, one followed
               so far only ``grow``.

The masker uses the regions twice: their boxes are prompts (a mover once found stays prompted
while it is followed) and they bound the segmentation (``bound_px`` around ``L > grow``), so
GrabCut cannot spill onto background of similar colour where nothing moved.

Pure functions of numpy arrays; the masker holds the one map.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.config import check_fields, setting
from mona_vo.conventions import scale_pixels
from mona_vo.errors import ConfigError
from mona_vo.flow import flow_edges, forward_warp_values


@dataclass(frozen=True)
class EvidenceConfig:
    """Settings of the accumulated moving-object evidence (module docstring)."""

    enabled: bool = setting(True)  # accumulate evidence and use its regions ('boxes' mode)
    decay: float = setting(0.8, ge=0, lt=1)  # share of the carried log-odds kept per frame
    obs_min: float = setting(-0.7, le=0)  # per-frame log-likelihood ratio of the dense test:
                                  # floor (log-odds units)
    obs_max: float = setting(2.0, ge=0)  # ... and ceiling (log-odds units)
    point_gain: float = setting(2.0, ge=0)  # most log-odds a dynamic point adds around it
    point_strength: float = setting(2.0, ge=1)  # a point adds 2 log(r / (this x theta)),
                                  # clipped to [0, point_gain] (r its residual, px per frame)
    point_radius_frac: float = setting(0.02, ge=0)  # reach of a dynamic point, fraction of the
                                  # image diagonal
    clamp_lo: float = setting(-3.0, le=0)  # the map stays within [clamp_lo, clamp_hi] (log-odds)
    clamp_hi: float = setting(6.0, gt=0)   # see clamp_lo
    seed: float = setting(3.0, gt=0)  # a region needs a pixel above this (log-odds) ...
    grow: float = setting(1.0, ge=0)  # ... and is the connected pixels above this (log-odds)
    min_area_frac: float = setting(0.002, ge=0, lt=1)  # regions smaller than this share of the
                                  # image are dropped
    join_frac: float = setting(0.03, ge=0)  # parts of one object closer than this (fraction of
                                  # the diagonal) join before regions are labelled
    edge_change_px: float = setting(1.0, gt=0)  # carried evidence: a pixel within edge_radius
                                  # of a flow discontinuity larger than this (map pixels) carries
                                  # no positive evidence (its flow mixes two motions)
    edge_radius: int = setting(2, ge=0)  # see edge_change_px (map pixels; 0: only the pixel)
    texture_ref: float = setting(1e-4, ge=0)  # the dense test's positive evidence is weighted
                                  # by s / (s + this), s the min-eigen texture score of the
                                  # analysis-resolution grey image (0: unweighted; see observe)
    texture_exempt_points: int = setting(2, ge=0)  # ... except on connected pixels of positive
                                  # dense evidence holding at least this many dynamic points
                                  # (0: no exemption)
    seeded_noise_factor: float = setting(0.0, ge=0)  # dense components above this x the
                                  # map's robust spread, holding seeded_min_points dynamic
                                  # points, observe point_gain (0: off; see observe)
    seeded_min_points: int = setting(2, ge=1)  # see seeded_noise_factor
    bound_px: int = setting(5, ge=-1)  # segmentation stays within this many analysis pixels of
                                  # the regions' convex hulls (0: the hulls; -1: no bound)

    def validate(self) -> None:
        check_fields(self, "masks.evidence.")
        if not self.clamp_lo <= self.grow <= self.seed <= self.clamp_hi:
            raise ConfigError("config keys masks.evidence.*: need clamp_lo <= grow <= seed <= "
                              "clamp_hi")


def carry(logodds: np.ndarray, flow: np.ndarray | None, fill: float = 0.0,
          config: EvidenceConfig | None = None) -> np.ndarray:
    """(h, w) float32 log-odds of the previous frame moved into this frame along ``flow``
    ((h, w, 2) float32, previous -> this frame, pixels of the map): forward splat, max where
    several land; background a mover uncovers gets at most ``fill``
    (:func:`mona_vo.flow.forward_warp_values`); ``fill`` everywhere without a flow.

    Pixels at a flow discontinuity (``config.edge_change_px``, ``edge_radius``) carry at most
    ``fill``: a dense flow smooths across a mover's outline, so its rim pixels get vectors
    between the mover's and the background's and would land beside it. Carried at the
    saturated log-odds of the mover, they drew a trail behind it that took four frames to fade
    (DAVIS libby, a camera panning with a running dog: the trail held a fifth of the image
    width). The rim is re-decided by the frame's own observation instead."""
    L = np.asarray(logodds, np.float32)
    if flow is not None and flow.shape[:2] == L.shape:
        cfg = config or EvidenceConfig()
        rim = flow_edges(flow, cfg.edge_radius, cfg.edge_change_px)
        L = np.where(rim, np.minimum(L, np.float32(fill)), L)
    return forward_warp_values(L, flow, fill)


def map_pixels(points: np.ndarray, full_width: int, map_width: int) -> np.ndarray:
    """(N, 2) int64 map pixels (column, row) of (N, 2) full-resolution pixels x, y, the map
    being ``map_width / full_width`` of the image (pixel centres at integers at both scales)."""
    s = map_width / float(full_width)
    return np.round(scale_pixels(np.asarray(points, np.float64).reshape(-1, 2), s, s)).astype(np.int64)


def observe(motion_map: np.ndarray | None, theta: float, shape: tuple[int, int],
            points: np.ndarray, residual: np.ndarray, full_width: int,
            config: EvidenceConfig, texture: np.ndarray | None = None) -> np.ndarray:
    """(h, w) float32 log-likelihood ratio of one frame (module docstring).

    motion_map:  (h, w) float32 residual motion, px per frame, or None; 0 = no observation.
    theta:       the frame's motion threshold, px per frame.
    points:      (N, 2) float32 full-resolution pixels of the dynamic points.
    residual:    (N,) their residual motion, px per frame (judged over the track window).
    full_width:  the image width in pixels (the map is ``w / full_width`` of it).
    texture:     (h, w) float32 min-eigen texture score of the frame, or None; with
                 ``texture_ref`` > 0 the dense test's positive evidence is weighted by it.
    """
    h, w = shape
    out = np.zeros((h, w), np.float32)
    if motion_map is not None and theta > 0:
        mm = np.asarray(motion_map, np.float32)
        valid = mm > 0
        z = np.maximum(mm / float(theta), 1e-6)
        obs = np.clip(2.0 * np.log(z), config.obs_min, config.obs_max)
        if texture is not None and config.texture_ref > 0:
            s = np.maximum(np.asarray(texture, np.float32), 0.0)
            weight = s / (s + config.texture_ref)
            if config.texture_exempt_points > 0 and len(points):
                weight = np.where(holding_points(valid & (obs > 0), points, full_width,
                                                 config.texture_exempt_points), 1.0, weight)
            obs = np.where(obs > 0, obs * weight, obs)
        out[valid] = obs[valid]
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if config.point_gain > 0 and len(pts):
        rad = max(int(round(config.point_radius_frac * np.hypot(w, h))), 1)
        bump = np.zeros((h, w), np.float32)
        r = np.asarray(residual, np.float64).reshape(-1)
        gain = np.clip(2.0 * np.log(np.maximum(r, 1e-9) / (config.point_strength * max(theta, 1e-9))),
                       0.0, config.point_gain)
        ok = np.isfinite(pts).all(axis=1) & (gain > 0)
        for (cx, cy), g in zip(map_pixels(pts[ok], full_width, w), gain[ok]):
            cv2.circle(bump, (int(cx), int(cy)), rad, float(g), -1)
        # Points add to the dense test where it says "static" too: a track judged over its
        # window sees motion along the epipolar lines that one frame pair does not.
        out = np.where(bump > 0, np.maximum(out, 0.0) + bump, out)
    return out


def holding_points(region: np.ndarray, points: np.ndarray, full_width: int,
                   min_points: int) -> np.ndarray:
    """(h, w) bool: the 8-connected parts of the (h, w) bool ``region`` that hold at least
    ``min_points`` of the (N, 2) full-resolution ``points`` (non-finite ones left out, the
    others clipped to the map). A mover moves with the tracks that found it: a mover in flat
    clothes with its textured outline, a slow one with its long-term tracks; a flat wall whose
    flow wanders, or a rippling background, holds none."""
    out = np.zeros(region.shape, bool)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        return out
    _, labels = cv2.connectedComponents(np.asarray(region, np.uint8), connectivity=8)
    h, w = region.shape
    c = np.clip(map_pixels(pts, full_width, w), 0, [w - 1, h - 1])
    hit = labels[c[:, 1], c[:, 0]]
    ids, counts = np.unique(hit[hit > 0], return_counts=True)
    ids = ids[counts >= min_points]
    return np.isin(labels, ids) if len(ids) else out


def motion_spread(motion_map: np.ndarray) -> float:
    """Robust spread of a motion map, px per frame: 1.4826 x the median of its observed
    (non-zero) pixels, most of which are static; 0 when nothing was observed."""
    mm = np.asarray(motion_map)
    observed = mm[mm > 0]
    return 1.4826 * float(np.median(observed)) if observed.size else 0.0


def seeded_regions(motion_map: np.ndarray, points: np.ndarray, full_width: int,
                   config: EvidenceConfig, spread_px: float, max_share: float = 1.0) -> np.ndarray:
    """(h, w) bool: the 8-connected components of ``motion_map > seeded_noise_factor x
    spread_px`` (``spread_px``: the map's :func:`motion_spread`, its own noise, not the frame's
    threshold) that hold at least ``seeded_min_points`` of the dynamic ``points`` ((N, 2)
    full-resolution pixels); nothing when off, without points, or when those components cover
    more than ``max_share`` of the map (no object is that large; a rippling or flickering
    background is)."""
    mm = np.asarray(motion_map, np.float32)
    if config.seeded_noise_factor <= 0 or spread_px <= 0:
        return np.zeros(mm.shape, bool)
    out = holding_points(mm > config.seeded_noise_factor * spread_px, points, full_width,
                         config.seeded_min_points)
    if out.mean() > max_share:
        out[:] = False
    return out


def update(carried: np.ndarray, observation: np.ndarray, config: EvidenceConfig) -> np.ndarray:
    """``clip(decay * carried + observation, clamp_lo, clamp_hi)``, (h, w) float32."""
    return np.clip(config.decay * np.asarray(carried, np.float32) + observation,
                   config.clamp_lo, config.clamp_hi).astype(np.float32)


def _labels(logodds: np.ndarray, config: EvidenceConfig, follow: np.ndarray | None = None):
    """Components of ``L > grow`` (parts closer than ``join_frac`` joined) that hold a pixel of
    ``L > seed`` -- or of the followed regions ``follow`` -- and ``min_area_frac`` of the map:
    (labels, kept component ids)."""
    L = np.asarray(logodds, np.float32)
    grow = (L > config.grow).astype(np.uint8)
    if not grow.any():
        return None, []
    h, w = L.shape
    r = int(round(config.join_frac * np.hypot(w, h) / 2))
    joined = grow
    if r > 0:
        k = 2 * r + 1
        joined = cv2.morphologyEx(grow, cv2.MORPH_CLOSE,
                                  cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(joined, connectivity=8)
    seeds = L > config.seed
    if follow is not None and follow.shape == L.shape:
        seeds |= follow & (L > config.grow)
    seeded = np.unique(labels[seeds])
    min_area = config.min_area_frac * L.size
    keep = [int(k) for k in seeded if k != 0 and stats[k, cv2.CC_STAT_AREA] >= min_area]
    return labels, keep


def regions(logodds: np.ndarray, config: EvidenceConfig,
            follow: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: the hysteresis regions of the map (module docstring), parts of one object
    closer than ``join_frac`` of the diagonal joined. ``follow`` (h, w) bool: the previous
    frame's regions carried here; a region followed so far needs only ``L > grow`` to go on
    (an object once found is followed until its evidence falls, not re-found every frame)."""
    labels, keep = _labels(logodds, config, follow)
    if labels is None or not keep:
        return np.zeros(np.shape(logodds), bool)
    return np.isin(labels, keep)


def bound(logodds: np.ndarray, config: EvidenceConfig,
          follow: np.ndarray | None = None) -> np.ndarray | None:
    """(h, w) bool where segmentation may put mask pixels: the convex hull of each region (a
    mover's textureless middle may hold little evidence; its outline does), grown by
    ``bound_px``; None when unbounded (``bound_px < 0``)."""
    if config.bound_px < 0:
        return None
    labels, keep = _labels(logodds, config, follow)
    m = np.zeros(np.shape(logodds), np.uint8)
    for k in keep:
        ys, xs = np.nonzero(labels == k)
        hull = cv2.convexHull(np.stack([xs, ys], axis=1).astype(np.int32))
        cv2.fillConvexPoly(m, hull, 1)
    if config.bound_px > 0 and m.any():
        k = 2 * config.bound_px + 1
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return m > 0
