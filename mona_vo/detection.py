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
not merged with an adjacent patch of parallax.

Neural back end ``yolo`` (``mona_vo.neural.yolo:YoloDetector``) is imported only when chosen.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.errors import ConfigError
from mona_vo.registry import Registry

DETECTORS = Registry("detector")


@dataclass(frozen=True, eq=False)
class Boxes:
    """N detected boxes.

    xyxy:  (N, 4) float32 x0, y0, x1, y1, pixels (closed rectangles, module docstring).
    score: (N,) float32 detector confidence (motion detector: mean motion / motion_theta).
    label: (N,) str class names ('moving-region' for the motion detector).
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
    """

    frame_index: int
    motion_map: np.ndarray | None
    theta_t: float
    m_t: float
    dynamic_points: np.ndarray
    motion_theta: float


class Detector(ABC):
    """Object detector. Back ends are built by name from :data:`DETECTORS`; classical ones take
    ``config=`` (their frozen config dataclass), neural ones ``device=``."""

    @abstractmethod
    def detect(self, image: np.ndarray, context: FrameContext | None = None) -> Boxes:
        """Boxes (full-resolution pixels) in an (H, W, 3) uint8 RGB image."""


@dataclass(frozen=True)
class MotionDetectorConfig:
    """Settings of the ``motion`` detector (thresholds relative to the frame's motion_theta)."""

    threshold_factor: float = 1.0   # a pixel is moving where motion_map > factor * motion_theta
    open_px: int = 1                # opening radius, analysis pixels (removes specks)
    close_px: int = 2               # closing radius, analysis pixels (fills holes, joins parts)
    min_area_frac: float = 0.0015   # components smaller than this fraction of the image: dropped
    box_margin_frac: float = 0.1    # each box grows by this fraction of its size on every side
    max_boxes: int = 12             # at most this many boxes, the highest-scoring ones
    peak_frac: float = 0.25         # a region keeps its pixels above this x its 95th percentile

    def validate(self) -> None:
        if self.threshold_factor <= 0:
            raise ConfigError("motion.threshold_factor must be > 0")
        if self.open_px < 0 or self.close_px < 0:
            raise ConfigError("motion.open_px and motion.close_px must be >= 0")
        if not 0 <= self.min_area_frac < 1:
            raise ConfigError("motion.min_area_frac must be in [0, 1)")
        if self.box_margin_frac < 0:
            raise ConfigError("motion.box_margin_frac must be >= 0")
        if self.max_boxes < 1:
            raise ConfigError("motion.max_boxes must be >= 1")
        if not 0 <= self.peak_frac < 1:
            raise ConfigError("motion.peak_frac must be in [0, 1)")


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


@DETECTORS.register("motion")
class MotionDetector(Detector):
    """Class-agnostic boxes around regions whose flow disagrees with the camera's motion."""

    def __init__(self, config: MotionDetectorConfig | None = None):
        self.config = config or MotionDetectorConfig()
        self.config.validate()

    def detect(self, image: np.ndarray, context: FrameContext | None = None) -> Boxes:
        if context is None or context.motion_map is None:
            return Boxes.empty()
        cfg = self.config
        H, W = image.shape[:2]
        mm = context.motion_map
        h, w = mm.shape
        theta = max(float(context.motion_theta), 1e-6)
        region = moving_region_mask(mm, cfg.threshold_factor * theta, cfg.open_px, cfg.close_px)
        min_area = max(int(round(cfg.min_area_frac * h * w)), 1)
        if cfg.peak_frac > 0 and region.any():
            region = split_by_peak(mm, region, cfg.peak_frac)
        xyxy, labels = mask_to_boxes(region, min_area)
        if len(xyxy) == 0:
            return Boxes.empty()
        score = np.array([mm[labels == k].mean() / theta
                          for k in np.unique(labels) if k != 0], np.float32)
        sx, sy = W / w, H / h
        # Analysis pixel edges -> full-resolution pixel edges (x_full + 0.5 = (x_small + 0.5) * s).
        full = np.empty_like(xyxy)
        full[:, [0, 2]] = (xyxy[:, [0, 2]] + 0.5) * sx - 0.5
        full[:, [1, 3]] = (xyxy[:, [1, 3]] + 0.5) * sy - 0.5
        bw, bh = full[:, 2] - full[:, 0], full[:, 3] - full[:, 1]
        full[:, 0] -= cfg.box_margin_frac * bw
        full[:, 2] += cfg.box_margin_frac * bw
        full[:, 1] -= cfg.box_margin_frac * bh
        full[:, 3] += cfg.box_margin_frac * bh
        order = np.argsort(-score)[:cfg.max_boxes]
        boxes = Boxes(full[order], score[order], np.full(len(order), "moving-region"))
        return boxes.clipped(W, H)


DETECTORS.register("yolo", "mona_vo.neural.yolo:YoloDetector")
