"""Burned-in overlays: logos, watermarks and captions that stand still in the picture while the
scene moves behind them. Found once in the first frames, painted over in every frame.

An overlay is no part of the scene. Left in, it is a patch of strong edges that keeps its
place in the image however the camera moves: to MONA a mover (its points do not follow the
camera's motion, so it is masked and its box crowds out the real movers' boxes), to the VO
corners at infinity turning with the camera. Online videos carry them more often than not
(a channel's logo, a platform's watermark, a caption).

The rule, on the first frames' grey images reduced to ``work_size`` (their longer side): a
pixel is still when the mean image has a strong edge there (gradient at least ``min_edge``
grey levels per pixel) and either its level moves by at most ``max_std`` (standard deviation over
the frames) or its edge is coherent: the mean image's gradient is at least ``min_coherence`` of
the frames' own mean gradient magnitude, so every frame has that edge, of that direction and
strength. A moving scene's edges blur out in the mean image and change level where they
pass; an opaque overlay's stay sharp and keep their level, and a semi-transparent one (a
platform's handle at 60 % opacity) keeps its edges while its level follows the scene behind it.
A blob's edges must also run in more than one direction (the smaller eigenvalue of its
structure tensor at least ``min_isotropy`` of the larger): an edge the camera moves along (a
horizon under a pan, the aperture problem) looks still at every pixel, letters and shapes do
not. When the level changes (by more than twice ``max_std``) over less than
``min_moving_area`` of the picture, the camera stands (or nothing moves): an overlay cannot be
told from the scene, and none is found. Still pixels closed into blobs (letters into words)
that hold at least ``min_pixels`` still pixels and lie within ``edge_band`` of the
picture from one of its sides, grown by ``grow_px``, are the overlay, unless they cover more
than ``max_area`` of the picture (a still scene, not an overlay). Overlays are put along the
frame's sides (a badge in a corner, a caption at the bottom), where they cover no subject; a
still blob inside the picture is more likely a mover the camera follows at its pace, which the
masks must keep (generated `mixed` seeds 209 and 105, a car followed: without the side rule
both were taken for overlays, and 105's mask J fell from 0.67 to 0.25). Each
frame's picture is then painted over there (OpenCV's Telea inpainting from the border): no
corner, no flow discontinuity, nothing still is left for masks or VO to see. Masks are never
set inside the overlay: it is in front of any mover.

Not found: overlays that change (a clock that ticks, captions that come and go within the
first frames), ones that appear after the first frames, faint ones whose edges are weaker
than ``min_edge``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Iterator

import cv2
import numpy as np

from mona_vo.conventions import working_size
from mona_vo.picture_area import PictureFrame

__all__ = ["OverlayConfig", "find_overlay", "overlay_ahead", "hide_overlay"]


@dataclass(frozen=True)
class OverlayConfig:
    work_size: int = 480          # longer side the test runs at, px
    min_edge: float = 24.0        # grey levels per pixel (Sobel of the mean image, per pixel)
    max_std: float = 4.0          # grey levels over the frames
    min_moving_area: float = 0.05  # of the picture whose level must change by 2 max_std;
                                   # below: a still camera (or nothing moves)
    max_area: float = 0.1         # of the picture an overlay may cover; above: not an overlay
    edge_band: float = 0.25       # an overlay lies within this share of the picture from one
                                  # of its sides (module docstring)
    min_pixels: int = 12          # still pixels a blob needs, at work_size
    grow_px: int = 3              # at work_size
    frames: int = 30              # read ahead
    step: int = 3                 # every third of them
    min_coherence: float = 0.98   # mean image's edge / frames' mean edge (module docstring)
    min_isotropy: float = 0.1     # a blob's structure tensor, smaller / larger eigenvalue


def _gradients(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(frames, H, W) x and y gradients of (frames, H, W) float32 grey images, grey levels per
    pixel."""
    gx = np.stack([cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) for g in stack]) / 4.0
    gy = np.stack([cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) for g in stack]) / 4.0
    return gx, gy


def find_overlay(images: Iterable[np.ndarray], config: OverlayConfig = OverlayConfig()
                 ) -> np.ndarray | None:
    """The (H, W) bool overlay of (H, W, 3) uint8 RGB ``images`` (a clip's first frames), None
    when there is none or it cannot be told (module docstring)."""
    images = [np.asarray(im, np.uint8) for im in images]
    if len(images) < 3:
        return None
    h, w = images[0].shape[:2]
    size = working_size(w, h, config.work_size)
    stack = np.stack([cv2.resize(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY), size,
                                 interpolation=cv2.INTER_AREA) for im in images]).astype(np.float32)
    std = stack.std(axis=0)
    gx, gy = _gradients(stack)
    mgx, mgy = gx.mean(axis=0), gy.mean(axis=0)   # the mean image's gradient
    edge = np.hypot(mgx, mgy)
    coherence = edge / np.maximum(np.hypot(gx, gy).mean(axis=0), 1e-6)
    still = (edge >= config.min_edge) & ((std <= config.max_std) | (coherence >= config.min_coherence))
    if not still.any() or np.mean(std > 2 * config.max_std) < config.min_moving_area:
        return None
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    blobs = cv2.morphologyEx(still.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(blobs, connectivity=8)
    counts = np.bincount(labels[still], minlength=n)
    x0, y0 = stats[:, 0], stats[:, 1]
    x1, y1 = x0 + stats[:, 2], y0 + stats[:, 3]
    bw, bh = config.edge_band * size[0], config.edge_band * size[1]
    by_an_edge = (y1 <= bh) | (y0 >= size[1] - bh) | (x1 <= bw) | (x0 >= size[0] - bw)
    # An edge that the camera moves along looks still (the aperture problem: a horizon under a
    # pan); an overlay's letters and shapes have edges of every direction. Isotropy: the smaller
    # eigenvalue of a blob's structure tensor over the larger.
    sxx = np.bincount(labels[still], (mgx * mgx)[still], minlength=n)
    syy = np.bincount(labels[still], (mgy * mgy)[still], minlength=n)
    sxy = np.bincount(labels[still], (mgx * mgy)[still], minlength=n)
    half_gap = np.sqrt(0.25 * (sxx - syy) ** 2 + sxy ** 2)
    isotropy = (0.5 * (sxx + syy) - half_gap) / np.maximum(0.5 * (sxx + syy) + half_gap, 1e-9)
    big = (counts >= config.min_pixels) & (isotropy >= config.min_isotropy)
    big[0] = False
    g = 2 * config.grow_px + 1
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (g, g))
    # The area test takes every still blob: a still part of the scene is not an overlay, and
    # those of its blobs that lie by a side are not either.
    if cv2.dilate(big[labels].astype(np.uint8), disk).mean() > config.max_area:
        return None
    keep = big & by_an_edge
    if not keep.any():
        return None
    region = cv2.dilate(keep[labels].astype(np.uint8), disk)
    return cv2.resize(region, (w, h), interpolation=cv2.INTER_LINEAR) > 0


def overlay_ahead(frames: Iterable, config: OverlayConfig = OverlayConfig()):
    """Read the first ``config.frames`` of ``frames`` and find the overlay in them. Returns (the
    whole stream again, the overlay or None)."""
    from data_tools.frames import read_ahead

    head, stream = read_ahead(frames, config.frames)
    return stream, find_overlay([f.image for f in head[::config.step]], config)


PAINT_SIZE = 640   # longer side, px, the overlay is painted over at (hide_overlay)


class hide_overlay:
    """``frames`` with ``overlay`` (picture-sized bool) painted over in each picture. Re-iterable
    when ``frames`` is."""

    def __init__(self, frames: Iterable, overlay: np.ndarray):
        self.frames = frames
        # Painted box by box (each part's box and the painting's reach), at most PAINT_SIZE px
        # on the picture's longer side: inpainting costs per pixel painted (55 ms for a 1080p
        # frame's logo and watermark at full size), and the fill is smooth anyway.
        h, w = overlay.shape
        self.scale = max(1, int(np.ceil(max(w, h) / PAINT_SIZE)))
        n, _, stats, _ = cv2.connectedComponentsWithStats(overlay.astype(np.uint8), connectivity=8)
        self.boxes = []
        pad = 4 * self.scale
        for x, y, bw, bh, _ in stats[1:]:
            x0, y0, x1, y1 = max(0, x - pad), max(0, y - pad), min(w, x + bw + pad), min(h, y + bh + pad)
            part = overlay[y0:y1, x0:x1]
            small = part if self.scale == 1 else cv2.resize(
                part.astype(np.uint8), (max(1, (x1 - x0) // self.scale), max(1, (y1 - y0) // self.scale)),
                interpolation=cv2.INTER_AREA) > 0
            self.boxes.append((slice(y0, y1), slice(x0, x1), part, small.astype(np.uint8)))

    def _paint(self, crop: np.ndarray, part: np.ndarray, small: np.ndarray) -> np.ndarray:
        if self.scale == 1:
            return cv2.inpaint(crop, small, 3, cv2.INPAINT_TELEA)
        h, w = crop.shape[:2]
        fill = cv2.inpaint(cv2.resize(crop, small.shape[::-1], interpolation=cv2.INTER_AREA),
                           small, 3, cv2.INPAINT_TELEA)
        out = crop.copy()
        out[part] = cv2.resize(fill, (w, h), interpolation=cv2.INTER_LINEAR)[part]
        return out

    def __iter__(self) -> Iterator[PictureFrame]:
        for f in self.frames:
            painted = f.image.copy()
            for rows, cols, part, small in self.boxes:
                painted[rows, cols] = self._paint(f.image[rows, cols], part, small)
            yield PictureFrame(f.index, f.timestamp, f.name, painted, getattr(f, "full", f.image))
