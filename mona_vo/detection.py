"""Object boxes: one interface, back ends by name (``DETECTORS``).

MONA's second module starts from detector boxes (YOLO in the paper); the adaptive box filter
(:mod:`mona_vo.box_filter`) then keeps the boxes of objects that move. A detector may and should
propose boxes around static objects too: telling them apart is the filter's job.

Box convention (the only place it is defined): :class:`Boxes` ``xyxy`` is (N, 4) float32
``x0, y0, x1, y1`` in the pixel coordinates of :mod:`mona_vo.conventions` (pixel centres at
integers, so an image of width W spans x in [-0.5, W - 0.5]). A box is the closed rectangle
``x0 <= x <= x1, y0 <= y <= y1``; the box around pixel columns c0..c1 and rows r0..r1 is
``(c0 - 0.5, r0 - 0.5, c1 + 0.5, r1 + 0.5)``, whose area is the pixel count. Detectors that use
the "top-left pixel spans [0, 1]" convention (YOLO, torchvision) subtract 0.5 from every
coordinate.

Default back end ``motion``: a class-agnostic motion-region proposer. It thresholds the frame's
motion map (the residual of the dense optical flow against the camera-induced motion, see
:func:`mona_vo.dynamic_points.residual_map`, computed once per frame by the masker and passed in
the :class:`FrameContext`) at ``threshold_factor * motion_theta`` (the frame's theta_t, or the
motion map's noise floor when higher), cleans the binary map with a morphological opening and
closing, and turns connected components into boxes (grown by ``box_margin_frac``). Regions of
static structure with strong parallax or flow errors are proposed too; the box filter rejects
them when they hold too few dynamic points. Within a region, pixels below ``peak_frac`` of the
region's 95th-percentile motion are dropped first (:func:`split_by_peak`), so a fast mover is
not merged with an adjacent patch of parallax. Two more sources propose boxes:

* groups of dynamic points (single linkage at ``point_link_frac`` of the image diagonal) of at
  least ``point_min_count`` points, in whose extent at least ``point_min_share`` of the tracked
  points are dynamic and whose median residual is at least ``point_min_strength`` times
  theta_t, grown by ``point_pad_frac`` of the diagonal: a track is judged over its whole
  window, so the points see a mover in frames where its motion runs along its epipolar lines
  and the dense map misses it (measured: a car driving ahead of the camera for 4 frames,
  synthetic one-large seed 0, mean IoU 0.85 -> 0.96; on DAVIS car-shadow the car is found this
  way only). The count and share keep a few drifting tracks on a blank floor from proposing a
  box (a static street stayed at 0 false positives); the strength keeps out the parallax of
  near static structure that a homography window leaves (DAVIS dog: a bush at 2-3 px per
  frame, theta_t 1.1; J 0.58 -> 0.80);
* the components of ``FrameContext.prior_mask`` (the previous mask carried into this frame)
  holding at least ``prior_min_support`` dynamic points.

Boxes that overlap by more than ``merge_overlap`` of the smaller one are merged into their union
(one object proposed by several sources, or in pieces).

Neural back end ``yolo`` (``mona_vo.neural.yolo:YoloDetector``) is imported only when chosen.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from mona_vo.box_filter import count_points_in_boxes
from mona_vo.config import check_fields, setting
from mona_vo.conventions import scale_boxes
from mona_vo.errors import ConfigError
from mona_vo.registry import Registry

DETECTORS = Registry("detector")

# The label of boxes drawn around motion (the ``motion`` detector, the masker's evidence
# regions); any other label is an object detector's class: a box around a whole object.
MOTION_LABEL = "moving-region"


@dataclass(frozen=True, eq=False)
class Boxes:
    """N detected boxes.

    xyxy:  (N, 4) float32 x0, y0, x1, y1, pixels (closed rectangles, module docstring).
    score: (N,) float32 detector confidence (motion detector: mean motion / motion_theta).
    label: (N,) str class names (:data:`MOTION_LABEL` for boxes drawn around motion).
    """

    xyxy: np.ndarray
    score: np.ndarray
    label: np.ndarray

    def __post_init__(self):
        n = len(self.xyxy)
        if np.asarray(self.xyxy).reshape(-1, 4).shape[0] != n or len(self.score) != n \
                or len(self.label) != n:
            raise ValueError("Boxes: xyxy (N, 4), score (N,) and label (N,) must agree in N")

    def __len__(self) -> int:
        return len(self.xyxy)

    @classmethod
    def empty(cls) -> "Boxes":
        return cls(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, dtype=str))

    @classmethod
    def from_arrays(cls, xyxy, score=None, label=None) -> "Boxes":
        xyxy = np.asarray(xyxy, np.float32).reshape(-1, 4)
        n = len(xyxy)
        score = np.ones(n, np.float32) if score is None else np.asarray(score, np.float32)
        label = np.full(n, "object") if label is None else np.asarray(label)
        return cls(xyxy, score, label)

    @property
    def from_motion(self) -> np.ndarray:
        """(N,) bool: the boxes drawn around motion (:data:`MOTION_LABEL`); the others are an
        object detector's, each around a whole object."""
        return np.asarray(self.label) == MOTION_LABEL

    def select(self, keep: np.ndarray) -> "Boxes":
        """The boxes where the (N,) bool ``keep`` is True (copies)."""
        keep = np.asarray(keep, bool)
        return Boxes(self.xyxy[keep].copy(), self.score[keep].copy(), self.label[keep].copy())

    def clipped(self, width: int, height: int) -> "Boxes":
        """Boxes clipped to the image [-0.5, width - 0.5] x [-0.5, height - 0.5]."""
        b = self.xyxy.copy()
        b[:, [0, 2]] = np.clip(b[:, [0, 2]], -0.5, width - 0.5)
        b[:, [1, 3]] = np.clip(b[:, [1, 3]], -0.5, height - 0.5)
        return Boxes(b, self.score.copy(), self.label.copy())


def grow_boxes(xyxy: np.ndarray, frac: float) -> np.ndarray:
    """(K, 4) boxes, each grown by ``frac`` of its width (height) on its left and right (top and
    bottom) sides; a new array of the same dtype."""
    b = np.asarray(xyxy)
    bw, bh = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    out = b.copy()
    out[:, 0] -= frac * bw
    out[:, 2] += frac * bw
    out[:, 1] -= frac * bh
    out[:, 3] += frac * bh
    return out


def box_pixel_ranges(xyxy: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N, 4) int64 ``c0, r0, c1, r1`` (end exclusive, for slicing) of the pixels whose centres
    lie in each box, clipped to the image; empty ranges have c1 <= c0 or r1 <= r0."""
    b = np.asarray(xyxy, np.float64).reshape(-1, 4)
    c0 = np.clip(np.ceil(b[:, 0]), 0, width)
    r0 = np.clip(np.ceil(b[:, 1]), 0, height)
    c1 = np.clip(np.floor(b[:, 2]) + 1, 0, width)
    r1 = np.clip(np.floor(b[:, 3]) + 1, 0, height)
    return np.stack([c0, r0, c1, r1], axis=1).astype(np.int64)


def mask_to_boxes(mask: np.ndarray, min_area_px: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of the 8-connected components of an (h, w) bool mask, in its pixel coordinates.

    Returns ((K, 4) float32 xyxy, (h, w) int32 component labels, 0 = background); components
    smaller than ``min_area_px`` pixels are dropped (label 0)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    boxes = []
    for k in range(1, n):
        x, y, w, h, area = stats[k]
        if area < min_area_px:
            labels[labels == k] = 0
            continue
        boxes.append((x - 0.5, y - 0.5, x + w - 0.5, y + h - 0.5))
    return np.asarray(boxes, np.float32).reshape(-1, 4), labels


@dataclass(frozen=True, eq=False)
class FrameContext:
    """What the masker knows about a frame besides its image; back ends use what they need.

    frame_index:    the frame.
    motion_map:     (h, w) float32 residual motion of each pixel against the camera-induced
                    motion, full-resolution pixels per frame, at the analysis resolution (h, w
                    smaller than the image; ``motion_map.shape[1] / image width`` is the scale);
                    None when no flow was computed.
    theta_t:        the frame's adaptive threshold of dynamic points, pixels per frame.
    m_t:            the frame's mean optical-flow magnitude, pixels.
    dynamic_points: (M, 2) float32 pixels of the frame's dynamic points (may be empty).
    motion_theta:   the threshold for ``motion_map``, pixels per frame: theta_t raised to the
                    map's own noise floor (``noise_factor`` x its robust spread) when higher.
    tracked_points: (N, 2) float32 pixels of all the frame's detection points, dynamic or not
                    (the dynamic ones among them), or None when unknown.
    prior_mask:     (h, w) bool, analysis resolution like ``motion_map``: the previous frame's
                    mask carried into this frame along the flow, or None.
    dynamic_residual: (M,) float32 residual motion of each dynamic point, pixels per frame
                    (:attr:`mona_vo.dynamic_points.DynamicPoints.residual`), or None.
    followed:       (h, w) bool, analysis resolution: the objects the accumulated evidence
                    follows in this frame (:func:`mona_vo.mask_evidence.regions`), or None when
                    no evidence is accumulated.
    tracked_residual: (N,) float32 residual motion of each of ``tracked_points``, pixels per
                    frame over its track window, or None.
    """

    frame_index: int
    motion_map: np.ndarray | None
    theta_t: float
    m_t: float
    dynamic_points: np.ndarray
    motion_theta: float
    tracked_points: np.ndarray | None = None
    prior_mask: np.ndarray | None = None
    dynamic_residual: np.ndarray | None = None
    followed: np.ndarray | None = None
    tracked_residual: np.ndarray | None = None


class Detector(ABC):
    """Object detector. Back ends are built by name from :data:`DETECTORS`; classical ones take
    ``config=`` (their frozen config dataclass), neural ones ``device=``. ``draws_motion``: its
    boxes are drawn around motion (:data:`MOTION_LABEL`), not around whole objects; the masker
    then adds the boxes of the objects it follows (``mona_vo.masks``)."""

    draws_motion = False

    @abstractmethod
    def detect(self, image: np.ndarray, context: FrameContext | None = None) -> Boxes:
        """Boxes (full-resolution pixels) in an (H, W, 3) uint8 RGB image."""


@dataclass(frozen=True)
class MotionDetectorConfig:
    """Settings of the ``motion`` detector (thresholds relative to the frame's motion_theta)."""

    threshold_factor: float = setting(1.0, gt=0)  # a pixel is moving where motion_map > factor * motion_theta
    open_px: int = setting(1, ge=0)  # opening radius, analysis pixels (removes specks)
    close_px: int = setting(2, ge=0)  # closing radius, analysis pixels (fills holes, joins parts)
    min_area_frac: float = setting(0.0015, ge=0, lt=1)  # components smaller than this fraction of the image: dropped
    box_margin_frac: float = setting(0.1, ge=0)  # each box grows by this fraction of its size on every side
    max_boxes: int = setting(12, ge=1)  # at most this many boxes, the highest-scoring ones
    peak_frac: float = setting(0.25, ge=0, lt=1)  # a region keeps its pixels above this x its 95th percentile
    point_link_frac: float = setting(0.08, ge=0)  # dynamic points closer than this x the image diagonal group
    point_min_count: int = setting(5, ge=1)  # a group of fewer dynamic points proposes no box (count)
    point_pad_frac: float = setting(0.02, ge=0)  # a group's box grows by this x the image diagonal per side
    point_min_share: float = setting(0.5, ge=0, le=1)  # ... and only when at least this share of the tracked points
                                    # in the group's extent are dynamic (a mover's are, mostly)
    point_min_strength: float = setting(3.0, ge=0)  # ... and the group's median residual is at least this x
                                    # theta_t
    prior_min_support: int = setting(1, ge=0)  # a component of the prior mask proposes a box when it holds
                                    # this many dynamic points (0: always)
    merge_overlap: float = setting(0.5, gt=0, le=1)  # boxes whose intersection exceeds this share of the smaller
                                    # box are merged into their union (1: never)

    def validate(self) -> None:
        check_fields(self, 'masks.motion.')


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def moving_region_mask(motion_map: np.ndarray, threshold: float, open_px: int,
                       close_px: int) -> np.ndarray:
    """(h, w) bool cleaned ``motion_map > threshold`` (opening, then closing, analysis px)."""
    m = (motion_map > threshold).astype(np.uint8)
    if open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(open_px))
    if close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(close_px))
    return m > 0


def split_by_peak(motion_map: np.ndarray, region: np.ndarray, peak_frac: float) -> np.ndarray:
    """(h, w) bool ``region`` with, in each 8-connected component, only the pixels whose motion
    exceeds ``peak_frac`` times the component's 95th percentile: a fast mover touching a patch of
    weaker apparent motion (parallax of a near surface, flow noise) is cut from it, and each keeps
    its own core."""
    n, labels = cv2.connectedComponents(region.astype(np.uint8), connectivity=8)
    out = np.zeros_like(region)
    for k in range(1, n):
        comp = labels == k
        peak = float(np.quantile(motion_map[comp], 0.95))
        out |= comp & (motion_map > peak_frac * peak)
    return out


def group_points(points: np.ndarray, link_px: float) -> list[np.ndarray]:
    """Single-linkage groups of (N, 2) points: two points closer than ``link_px`` share a group.
    Returns index arrays, largest group first (ties: lowest first index first)."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    n = len(p)
    if n == 0:
        return []
    near = np.linalg.norm(p[:, None] - p[None], axis=2) <= link_px
    _, labels = connected_components(csr_matrix(near), directed=False)
    groups = [np.nonzero(labels == k)[0] for k in np.unique(labels)]
    return sorted(groups, key=lambda g: (-len(g), g[0]))


def point_group_boxes(points: np.ndarray, link_px: float, min_count: int, pad_px: float,
                      all_points: np.ndarray | None = None, min_share: float = 0.0,
                      strength: np.ndarray | None = None,
                      min_strength: float = 0.0) -> np.ndarray:
    """(K, 4) float32 boxes (pixels) around the single-linkage groups (``link_px``) of the (N, 2)
    points holding at least ``min_count`` points, each grown by ``pad_px`` on every side (the
    outermost points of a sparse sample lie inside their object, about half a spacing from its
    edge). With ``all_points`` (M, 2), the superset the points were picked from, a group also
    needs at least ``min_share`` of the ``all_points`` inside its (ungrown) box; with ``strength``
    (N,), a median strength of at least ``min_strength``."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    ok = np.isfinite(p).all(axis=1)
    p = p[ok]
    st = None if strength is None else np.asarray(strength, np.float64).reshape(-1)[ok]
    q = None if all_points is None else np.asarray(all_points, np.float64).reshape(-1, 2)
    out = []
    for idx in group_points(p, link_px):
        if len(idx) < min_count or (st is not None and np.median(st[idx]) < min_strength):
            continue
        lo, hi = p[idx].min(axis=0), p[idx].max(axis=0)
        if q is not None and min_share > 0:
            inside = np.sum(np.all((q >= lo) & (q <= hi), axis=1))
            if len(idx) < min_share * max(inside, len(idx)):
                continue
        lo, hi = lo - pad_px, hi + pad_px
        out.append((lo[0], lo[1], hi[0], hi[1]))
    return np.asarray(out, np.float32).reshape(-1, 4)


def merge_boxes(xyxy: np.ndarray, score: np.ndarray,
                min_overlap: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N, 4) merged into their union while two of them intersect by more than
    ``min_overlap`` of the smaller one's area (one object proposed twice, or in pieces); the
    merged box keeps the higher score. Returns (K, 4) float32 boxes and (K,) float32 scores."""
    b = [np.asarray(x, np.float64) for x in np.asarray(xyxy, np.float64).reshape(-1, 4)]
    sc = [float(v) for v in np.asarray(score, np.float64).reshape(-1)]
    merged = True
    while merged and len(b) > 1:
        merged = False
        for i in range(len(b)):
            for j in range(i + 1, len(b)):
                ix = min(b[i][2], b[j][2]) - max(b[i][0], b[j][0])
                iy = min(b[i][3], b[j][3]) - max(b[i][1], b[j][1])
                if ix <= 0 or iy <= 0:
                    continue
                small = min((b[i][2] - b[i][0]) * (b[i][3] - b[i][1]),
                            (b[j][2] - b[j][0]) * (b[j][3] - b[j][1]))
                if ix * iy > min_overlap * max(small, 1e-12):
                    b[i] = np.r_[np.minimum(b[i][:2], b[j][:2]), np.maximum(b[i][2:], b[j][2:])]
                    sc[i] = max(sc[i], sc[j])
                    del b[j], sc[j]
                    merged = True
                    break
            if merged:
                break
    return (np.asarray(b, np.float32).reshape(-1, 4), np.asarray(sc, np.float32))


@DETECTORS.register("motion")
class MotionDetector(Detector):
    """Class-agnostic boxes around regions whose flow disagrees with the camera's motion."""

    draws_motion = True

    def __init__(self, config: MotionDetectorConfig | None = None):
        self.config = config or MotionDetectorConfig()
        self.config.validate()

    def detect(self, image: np.ndarray, context: FrameContext | None = None) -> Boxes:
        if context is None:
            return Boxes.empty()
        cfg = self.config
        H, W = image.shape[:2]
        xyxy = np.zeros((0, 4), np.float32)
        score = np.zeros(0, np.float32)
        theta = max(float(context.motion_theta), 1e-6)
        mm = context.motion_map
        if mm is not None:
            h, w = mm.shape
            region = moving_region_mask(mm, cfg.threshold_factor * theta, cfg.open_px,
                                        cfg.close_px)
            min_area = max(int(round(cfg.min_area_frac * h * w)), 1)
            if cfg.peak_frac > 0 and region.any():
                region = split_by_peak(mm, region, cfg.peak_frac)
            small, labels = mask_to_boxes(region, min_area)
            if len(small):
                score = np.array([mm[labels == k].mean() / theta
                                  for k in np.unique(labels) if k != 0], np.float32)
                xyxy = grow_boxes(scale_boxes(small, W / w, H / h), cfg.box_margin_frac)
        # Groups of dynamic points propose boxes too: the tracks, judged over their whole window,
        # see movers that the dense map misses in frames where they move along their epipolar
        # lines (measured: a car driving ahead of the camera for 4 frames).
        dyn = np.asarray(context.dynamic_points, np.float64).reshape(-1, 2)
        if len(dyn) >= cfg.point_min_count:
            diag = float(np.hypot(W, H))
            strength = None
            if cfg.point_min_strength > 0 and context.dynamic_residual is not None:
                strength = np.asarray(context.dynamic_residual) / max(context.theta_t, 1e-6)
            pts = point_group_boxes(dyn, cfg.point_link_frac * diag, cfg.point_min_count,
                                    cfg.point_pad_frac * diag, context.tracked_points,
                                    cfg.point_min_share, strength, cfg.point_min_strength)
            xyxy = np.concatenate([xyxy, pts])
            score = np.concatenate([score, np.ones(len(pts), np.float32)])
        # The previous frame's mask, carried along the flow: a mover stays proposed in frames
        # where it moves along its epipolar lines (the box filter still asks for its dynamic
        # points).
        if context.prior_mask is not None and context.prior_mask.any():
            ph, pw = context.prior_mask.shape
            small, labels = mask_to_boxes(context.prior_mask,
                                          max(int(round(cfg.min_area_frac * ph * pw)), 1))
            if len(small):
                prior = scale_boxes(small, W / pw, H / ph)
                if cfg.prior_min_support > 0:
                    support = count_points_in_boxes(prior, dyn)
                    prior = prior[support >= cfg.prior_min_support]
                xyxy = np.concatenate([xyxy, prior])
                score = np.concatenate([score, np.ones(len(prior), np.float32)])
        if len(xyxy) == 0:
            return Boxes.empty()
        if cfg.merge_overlap < 1:
            xyxy, score = merge_boxes(xyxy, score, cfg.merge_overlap)
        order = np.argsort(-score)[:cfg.max_boxes]
        boxes = Boxes(xyxy[order], score[order], np.full(len(order), MOTION_LABEL))
        return boxes.clipped(W, H)


DETECTORS.register("yolo", "mona_vo.neural.yolo:YoloDetector")
