"""Masks from prompts: one interface, back ends by name (``SEGMENTERS``).

MONA prompts SAM with the filtered boxes (or, in the paper's ablation, with the dynamic points
only). A :class:`Segmenter` takes box prompts, point prompts or both and returns one (H, W) bool
mask, the union of the objects prompted.

Default back end ``grabcut``: OpenCV GrabCut (colour GMMs + graph cut) at a reduced resolution,
initialised from motion and prompts, per prompt region:

* box prompt: the region of interest is the box grown by ``context_margin_frac``; its outermost
  pixels are background (``GC_BGD``), the ring around the box probable background (a box may cut
  its object; GrabCut may grow it there). Probable foreground seeds: inside the box, pixels whose
  motion-map value exceeds ``fg_factor * motion_theta`` and ``peak_frac`` times the box's
  95th-percentile motion; in the whole region, the previous frame's mask carried into this frame
  (``FrameContext.prior_mask``, eroded by one pixel; ``prior_seed``) and disks of radius
  ``point_seed_frac`` (of the diagonal) on the dynamic points inside the box. The prior and the
  points keep a mover whose motion runs along its epipolar lines for a few frames (the dense map
  misses it) segmented (measured: synthetic one-large IoU 0.85 -> 0.89, DAVIS dog J 0.56 ->
  0.64). When the seeds cover less than ``min_moving_frac`` of the box, the whole box is
  probable foreground, as in GrabCut's own rectangle initialisation (a box prompt says "an
  object is here", as for SAM; an inner rectangle, as before stop 31, left the box's rim to the
  background model, which then took the object's rim and colours from it: DAVIS J from the
  true boxes 0.512 / 0.500 -> 0.637 / 0.566, tuning / validation). When GrabCut keeps less than
  ``min_keep_frac`` of the seeds (colours shared with the background), the seeds are added back
  (for points: the inner disks); with accumulated evidence (``FrameContext.followed``) only
  this frame's motion seeds and the carried mask within the objects the evidence follows, not
  the carried mask's spill beyond them (stop 32: DAVIS J 0.487 / 0.483 -> 0.499 / 0.486).
  With ``fallback_static_frac`` > 0 (an option, off; README, Masks, stop 37) what comes back
  also leaves out the pixels whose nearest tracked point is static (:func:`static_point_zone`):
  the dense motion's bleed onto the background beside a mover. A box whose region lies inside
  a larger box's region is cut in the larger one's graph, not in a second one over the same
  pixels (:meth:`GrabCutSegmenter._cut_boxes`).
* point prompts (no boxes): points are grouped (single linkage, ``point_link_frac`` of the image
  diagonal) and each group is cut on its own. The mask stays within ``point_radius_frac`` (of the
  diagonal) of the points; disks of half that radius are probable foreground, the rest of the
  reach probable background; the motion map is not used (SAM sees only the image and the
  prompts: the ablation compares prompt types). So a points-only prompt gives smaller, local and
  often incomplete masks, as the paper's ablation reports for SAM.

Resolution: GrabCut runs on a reduced copy of the image, as its cost grows with the pixels it
cuts (about 1 microsecond per pixel and iteration on this project's 2-core machine), but at a
coarse one its masks keep less of each object and follow its outline less closely (DAVIS J 0.50
at 256 px across, 0.55 at 384). A frame is cut at ``work_size`` (its longer side) or finer, up
to ``fine_size``, as far as its prompt regions (boxes with their context ring) then hold at most
``fine_pixels`` pixels: as many as one 1024 x 436 frame has at 256 px across, the frame and
resolution the masks' 100 ms target is met at. So a frame costs at most what a region over that
whole frame costs (or, where its regions hold more pixels at ``work_size``, what they cost
there, as before), and a frame with smaller objects spends that budget on finer detail (README,
Masks, stop 39).

The mask is upsampled to the image size, its edge moved onto the image edges nearby by a guided
filter (``refine_radius_px``, ``refine_eps``), and dilated by ``dilate_px`` (masks feed a VO
that must not use a point on a mover: a slightly too large mask costs less than a missed rim).

Method ``motion`` is a cheaper alternative: the moving pixels inside the prompt regions, without
colour.

Neural back end ``sam`` (``mona_vo.neural.sam:SamSegmenter``) is imported only when chosen.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.detection import (Boxes, FrameContext, box_pixel_ranges, grow_boxes,
                               group_points, moving_region_mask)
from mona_vo.config import check_fields, setting
from mona_vo.conventions import scale_boxes, scale_pixels, working_size
from mona_vo.errors import ConfigError
from mona_vo.registry import Registry

SEGMENTERS = Registry("segmenter")


class Segmenter(ABC):
    """Prompted segmentation. Back ends are built by name from :data:`SEGMENTERS`; classical ones
    take ``config=`` (their frozen config dataclass), neural ones ``device=``."""

    @abstractmethod
    def segment(self, image: np.ndarray, boxes: Boxes | None = None,
                points: np.ndarray | None = None,
                context: FrameContext | None = None) -> np.ndarray:
        """(H, W) bool mask of the objects prompted in an (H, W, 3) uint8 RGB image.

        boxes:  :class:`~mona_vo.detection.Boxes` prompts (full-resolution pixels), or None.
        points: (N, 2) float32 positive point prompts x, y (pixels), or None. Used when no box
                is given (the paper's points-only ablation); ignored next to boxes.
        Returns an all-False mask when there is no prompt.
        """


@dataclass(frozen=True)
class GrabCutConfig:
    """Settings of the ``grabcut`` segmenter."""

    method: str = setting("grabcut", choices=("grabcut", "motion"))  # grabcut (colour + motion) | motion (moving pixels only)
    work_size: int = setting(256, ge=16)  # segmentation resolution: the image's longer side,
                                          # pixels (conventions.working_size)
    fine_size: int = setting(512, ge=16)  # finest resolution (longer side), for frames whose
                                          # prompt regions are small enough (fine_pixels)
    fine_pixels: int = setting(28000, ge=0)  # a frame is cut finer than work_size while its
                                          # regions hold at most this many pixels there (one
                                          # 1024 x 436 frame at 256 across; 0: always work_size)
    iterations: int = setting(1, ge=1)  # GrabCut iterations per region (2 measured no better)
    context_margin_frac: float = setting(0.25, ge=0)  # ring around a box used as background, fraction of size
    fg_factor: float = setting(1.0, gt=0)  # probable foreground where motion > fg_factor * motion_theta
    peak_frac: float = setting(0.25, ge=0, lt=1)  # ... and > peak_frac x the box's 95th-percentile motion
    point_radius_frac: float = setting(0.025, gt=0)  # points: reach of a point prompt, fraction of the diagonal
    point_link_frac: float = setting(0.08, ge=0)  # points closer than this (fraction of diagonal) group
    prior_seed: bool = setting(True)  # boxes: the previous mask carried here seeds the foreground
    point_seed_frac: float = setting(0.012, ge=0)  # boxes: disks of this radius (fraction of the diagonal) on
                                     # the dynamic points inside a box seed its foreground
    refine_radius_px: int = setting(8, ge=0)  # guided-filter radius moving the upsampled mask edge onto
                                     # image edges, full-resolution pixels (0: off)
    refine_eps: float = setting(0.01, gt=0)  # its ridge, (grey level / 255)^2: edges weaker than about
                                     # sqrt(eps) x 255 grey levels do not move the mask edge
    dilate_px: int = setting(2, ge=0)  # final mask dilation, full-resolution pixels
    max_regions: int = setting(8, ge=1)  # at most this many prompt regions are segmented
    min_moving_frac: float = setting(0.02, ge=0, le=1)  # a box with fewer moving pixels than this share is segmented
                                     # by colour from the whole box (a box means an object)
    seed: int = setting(0, ge=0)  # OpenCV RNG seed set before each GrabCut (reproducible)
    min_keep_frac: float = setting(0.3, ge=0, le=1)  # GrabCut keeping less than this share of a region's moving
                                     # (points: prompted) pixels is overruled: they are added
    fallback_static_frac: float = setting(0.0, ge=0)  # boxes: what is added back leaves out the
                                     # pixels whose nearest tracked point is static, its residual
                                     # at most this x theta_t (0: off; static_point_zone)
    fallback_static_reach: float = setting(0.03, gt=0)  # ... within this share of the diagonal

    def validate(self) -> None:
        check_fields(self, 'masks.grabcut.')


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float,
                  subsample: int = 1) -> np.ndarray:
    """He et al.'s guided filter (ECCV 2010): ``src`` (h, w) float32 smoothed so that its edges
    follow those of ``guide`` (h, w) float32 (same size): per window of ``(2 radius + 1)^2``
    pixels the output is ``a * guide + b`` fitted to ``src`` by least squares with the ridge
    ``eps`` (in guide units squared), the coefficients then averaged over the windows. With
    ``subsample`` s > 1 the coefficients are computed on images s times smaller and upsampled
    (He and Sun's fast guided filter, 2015)."""
    h, w = guide.shape
    s = max(int(subsample), 1)
    if s > 1 and min(h, w) >= 4 * s:
        size = (max(w // s, 1), max(h // s, 1))
        gi = cv2.resize(guide, size, interpolation=cv2.INTER_AREA)
        sp = cv2.resize(src, size, interpolation=cv2.INTER_AREA)
        r = max(radius // s, 1)
    else:
        gi, sp, r = guide, src, radius
    k = (2 * r + 1, 2 * r + 1)

    def box(x):
        return cv2.boxFilter(x, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)

    mean_i, mean_p = box(gi), box(sp)
    cov_ip = box(gi * sp) - mean_i * mean_p
    var_i = box(gi * gi) - mean_i * mean_i
    a = cov_ip / (var_i + eps)
    b = mean_p - a * mean_i
    a, b = box(a), box(b)
    if a.shape != (h, w):
        a = cv2.resize(a, (w, h), interpolation=cv2.INTER_LINEAR)
        b = cv2.resize(b, (w, h), interpolation=cv2.INTER_LINEAR)
    return a * guide + b


def refine_edges(image: np.ndarray, soft: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """(H, W) float32 ``soft`` (a mask upsampled from the segmentation resolution, values in
    [0, 1]) guided-filtered (fast variant, coefficients at a quarter resolution) with the grey of
    the (H, W, 3) uint8 RGB image as guide, within the mask's bounding box grown by the filter's
    reach (the rest is returned as given): the blocky edge of the upsampled mask moves onto the
    image edges nearby."""
    x, y, w, h = cv2.boundingRect((soft > 0.02).astype(np.uint8))
    if w == 0 or h == 0:
        return soft
    H, W = soft.shape
    pad = 2 * radius + 2
    r0, r1 = max(y - pad, 0), min(y + h + pad, H)
    c0, c1 = max(x - pad, 0), min(x + w + pad, W)
    gray = cv2.cvtColor(np.ascontiguousarray(image[r0:r1, c0:c1]),
                        cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    out = soft.copy()
    out[r0:r1, c0:c1] = guided_filter(gray, np.ascontiguousarray(soft[r0:r1, c0:c1]), radius, eps,
                                      subsample=4)
    return out


def static_point_zone(shape: tuple[int, int], points: np.ndarray, residual: np.ndarray,
                      static_px: float, reach_frac: float) -> np.ndarray:
    """(h, w) bool: the pixels of an image of ``shape`` whose nearest tracked point, within
    ``reach_frac`` of its diagonal, is static (residual at most ``static_px``, px per frame).
    ``points``: (N, 2) pixels of the frame's tracked points in that image
    (:func:`mona_vo.conventions.scale_pixels`); ``residual``: (N,) their residual motion over the track window.

    A dense flow smooths across a mover's outline, so its residual bleeds onto the background
    beside the mover; a point track follows its own patch. Where the nearest track is static,
    the dense motion is the bleed."""
    h, w = shape
    out = np.zeros((h, w), bool)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    r = np.asarray(residual, np.float64).reshape(-1)
    ok = np.isfinite(pts).all(axis=1) & np.isfinite(r)
    if not ok.any():
        return out
    c = np.clip(np.round(pts[ok]).astype(np.int64), 0, [w - 1, h - 1])
    still = r[ok] <= static_px

    def distance(sel):
        if not sel.any():
            return np.full((h, w), np.inf, np.float32)
        img = np.full((h, w), 255, np.uint8)
        img[c[sel, 1], c[sel, 0]] = 0
        return cv2.distanceTransform(img, cv2.DIST_L2, 3)

    d_still, d_other = distance(still), distance(~still)
    return (d_still < d_other) & (d_still <= reach_frac * np.hypot(w, h))


@SEGMENTERS.register("grabcut")
class GrabCutSegmenter(Segmenter):
    """Box- or point-prompted GrabCut at reduced resolution, seeded by motion (module docstring)."""

    def __init__(self, config: GrabCutConfig | None = None):
        self.config = config or GrabCutConfig()
        self.config.validate()

    # -- helpers -----------------------------------------------------------------------------
    def long_side(self, boxes: np.ndarray, width: int, height: int) -> int:
        """The longer side (pixels) a frame of ``width`` x ``height`` is cut at with the box
        prompts ``boxes`` (N, 4) (full-resolution pixels): the finest up to ``fine_size`` at
        which their regions hold at most ``fine_pixels`` pixels, never coarser than
        ``work_size`` (module docstring)."""
        cfg = self.config
        if cfg.fine_pixels <= 0 or cfg.fine_size <= cfg.work_size or not len(boxes):
            return cfg.work_size
        r = box_pixel_ranges(grow_boxes(np.asarray(boxes, np.float64).reshape(-1, 4),
                                        cfg.context_margin_frac), width, height)
        area = float(np.sum(np.clip(r[:, 2] - r[:, 0], 0, None)
                            * np.clip(r[:, 3] - r[:, 1], 0, None)))
        if area <= 0:
            return cfg.work_size
        finest = max(width, height) * np.sqrt(cfg.fine_pixels / area)
        return int(np.clip(np.floor(finest), cfg.work_size, cfg.fine_size))

    def _work(self, image: np.ndarray, long_side: int | None = None):
        """The image reduced to ``long_side`` (default ``work_size``) on its longer side, and
        the x and y scales from the image to it."""
        H, W = image.shape[:2]
        w, h = working_size(W, H, long_side or self.config.work_size)
        small = image if (w, h) == (W, H) else cv2.resize(image, (w, h),
                                                          interpolation=cv2.INTER_AREA)
        return small, w / W, h / H

    @staticmethod
    def _motion(context: FrameContext | None, w: int, h: int) -> np.ndarray | None:
        if context is None or context.motion_map is None:
            return None
        mm = context.motion_map
        if mm.shape != (h, w):
            mm = cv2.resize(mm, (w, h), interpolation=cv2.INTER_LINEAR)
        return mm

    @staticmethod
    def _at_size(mask: np.ndarray | None, w: int, h: int) -> np.ndarray | None:
        """A bool mask of the analysis resolution at the segmentation's (w, h), or None."""
        if mask is None or mask.shape == (h, w):
            return mask
        return cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0

    def _cut(self, small: np.ndarray, init: np.ndarray, roi: tuple[int, int, int, int],
             fallback: np.ndarray) -> np.ndarray:
        """GrabCut of the ``roi`` (c0, r0, c1, r1) of ``small`` with the initial labels ``init``
        (same shape as the roi); ``fallback`` (bool, roi shape) when GrabCut cannot run."""
        seg = self._graph_cut(small, init, roi)
        return fallback if seg is None else self._kept(seg, fallback)

    def _graph_cut(self, small: np.ndarray, init: np.ndarray,
                   roi: tuple[int, int, int, int]) -> np.ndarray | None:
        """GrabCut's foreground (bool, roi shape) from the initial labels ``init``, or None when
        it cannot run (method ``motion``, too few seeds on either side, an OpenCV error)."""
        fg = (init == cv2.GC_FGD) | (init == cv2.GC_PR_FGD)
        bg = (init == cv2.GC_BGD) | (init == cv2.GC_PR_BGD)
        if self.config.method == "motion" or fg.sum() < 2 or bg.sum() < 2:
            return None
        c0, r0, c1, r1 = roi
        labels = init.copy()
        bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
        # GrabCut seeds its colour models by k-means drawing from OpenCV's global RNG, whose
        # state depends on every earlier call: reseeded here, a region's mask depends on the
        # region only (measured: DAVIS J varied by up to 0.1 between runs otherwise).
        cv2.setRNGSeed(self.config.seed)
        try:
            cv2.grabCut(np.ascontiguousarray(small[r0:r1, c0:c1]), labels, None, bgd, fgd,
                        self.config.iterations, cv2.GC_INIT_WITH_MASK)
        except cv2.error:
            return None
        return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)

    def _kept(self, seg: np.ndarray, fallback: np.ndarray) -> np.ndarray:
        """GrabCut's ``seg``, with ``fallback`` added where it kept too little of it."""
        if seg.sum() < self.config.min_keep_frac * fallback.sum():
            # GrabCut dropped most of what moves or was prompted (colours shared with the
            # background): a missed mover costs the VO more than a rough mask.
            return seg | fallback
        return seg

    def _cut_boxes(self, small: np.ndarray, regions: list) -> np.ndarray:
        """Mask (small size) of the box regions ``regions``, each (roi, init, fallback) as
        :meth:`_box_region` gives it. A region whose roi lies inside a larger one's is cut
        with it, in one graph: its foreground seeds join the larger one's labels (its own rim
        of certain background does not: the larger region's cut decides there), and it gets
        its fallback back where that one cut kept too little of it. A frame-filling mover's
        box holds the smaller boxes beside it (Sintel alley_1: every frame; they were cut a
        second time, a fifth of the segmenter's work, and GrabCut kept nothing of them)."""
        h, w = small.shape[:2]
        out = np.zeros((h, w), bool)
        area = [(r[0][2] - r[0][0]) * (r[0][3] - r[0][1]) for r in regions]
        groups: list[list[int]] = []
        for i in sorted(range(len(regions)), key=lambda k: (-area[k], k)):
            a0, b0, a1, b1 = regions[i][0]
            for g in groups:
                c0, r0, c1, r1 = regions[g[0]][0]
                if c0 <= a0 and r0 <= b0 and a1 <= c1 and b1 <= r1:
                    g.append(i)
                    break
            else:
                groups.append([i])
        for g in groups:
            (c0, r0, c1, r1), init, fallback = regions[g[0]]
            if len(g) > 1:
                init = init.copy()
                for j in g[1:]:
                    (a0, b0, a1, b1), member, _ = regions[j]
                    sub = init[b0 - r0:b1 - r0, a0 - c0:a1 - c0]
                    sub[(member == cv2.GC_FGD) | (member == cv2.GC_PR_FGD)] = cv2.GC_PR_FGD
            seg = self._graph_cut(small, init, (c0, r0, c1, r1))
            for j in g:
                (a0, b0, a1, b1), member, fb = regions[j]
                part = fb if seg is None else self._kept(
                    seg[b0 - r0:b1 - r0, a0 - c0:a1 - c0], fb)
                part = part & (member != cv2.GC_BGD)
                out[b0:b1, a0:a1] |= part
        return out

    # -- prompts -----------------------------------------------------------------------------
    def _box_region(self, small, box_s, mm, theta, prior=None, pts_s=None, whole=False,
                    followed=None, static=None):
        """The GrabCut problem of one box given in small-image pixel coordinates: its roi
        (c0, r0, c1, r1) in the small image, initial labels and fallback (roi shape), or None
        for an empty box (:meth:`_cut_boxes` cuts it); ``prior`` (small
        size bool, or None) the previous mask carried here, ``pts_s`` (N, 2) the dynamic points
        in small-image pixels (or None); ``whole``: the box is an object detector's, around a
        whole object (module docstring); ``followed`` (small size bool, or None) the objects the
        accumulated evidence follows; ``static`` (small size bool, or None) where the nearest
        tracked point is static (:func:`static_point_zone`): not added back."""
        h, w = small.shape[:2]
        cfg = self.config
        grown = grow_boxes(np.asarray(box_s, np.float64).reshape(1, 4), cfg.context_margin_frac)
        c0, r0, c1, r1 = box_pixel_ranges(grown, w, h)[0]
        b0, q0, b1, q1 = box_pixel_ranges(np.asarray(box_s)[None], w, h)[0]
        if b1 <= b0 or q1 <= q0:
            return None
        # The ring around the box is probable background (the box may cut the object: GrabCut
        # may grow it there); only the region's outermost pixels are certain background.
        init = np.full((r1 - r0, c1 - c0), cv2.GC_PR_BGD, np.uint8)
        init[[0, -1], :] = cv2.GC_BGD
        init[:, [0, -1]] = cv2.GC_BGD
        inner = (slice(q0 - r0, q1 - r0), slice(b0 - c0, b1 - c0))
        # This frame's evidence of motion: what moves in the box, disks on the dynamic points.
        now = np.zeros((r1 - r0, c1 - c0), bool)
        if mm is not None:
            crop = mm[q0:q1, b0:b1]
            # Relative to the box's strongest motion too: a mover's box may hold weaker motion
            # (parallax, flow bleeding) that is not part of it.
            peak = float(np.quantile(crop, 0.95)) if crop.size else 0.0
            now[inner] = moving_region_mask(crop, max(cfg.fg_factor * theta,
                                                      cfg.peak_frac * peak), 0, 1)
        if pts_s is not None and len(pts_s):
            rad = max(int(round(cfg.point_seed_frac * np.hypot(w, h))), 1)
            inside = ((pts_s[:, 0] >= b0) & (pts_s[:, 0] < b1) & (pts_s[:, 1] >= q0)
                      & (pts_s[:, 1] < q1))
            disks = np.zeros(now.shape, np.uint8)
            for x, y in pts_s[inside]:
                cv2.circle(disks, (int(round(x - c0)), int(round(y - r0))), rad, 1, -1)
            now |= disks > 0
        now[init == cv2.GC_BGD] = False
        # Foreground seeds: that evidence and the previous mask carried here.
        seed = now.copy()
        if prior is not None and cfg.prior_seed:
            # Eroded: the carried mask was dilated (dilate_px) and its rim is the least sure.
            p = cv2.erode(prior[r0:r1, c0:c1].astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            seed |= p & (init != cv2.GC_BGD)
        moving = seed[inner].mean() >= cfg.min_moving_frac
        if whole or not moving:
            # A box around one object (or one in which nothing moves): its object by colour,
            # from the whole box.
            init[inner] = cv2.GC_PR_FGD
        if moving:
            init[seed] = cv2.GC_PR_FGD
            fallback = seed
            if followed is not None:
                # What GrabCut may not drop is the evidence: this frame's, and the objects it
                # follows over time. The carried mask beyond them is only a start; restored, a
                # mask that once spilt onto the background kept the spill in every later frame
                # (DAVIS parkour, a runner filmed from beside: GrabCut cut the runner out of a
                # blob several times his size, kept less than min_keep_frac of it, and the blob
                # came back).
                fallback = now | (seed & followed[r0:r1, c0:c1])
            if static is not None:
                # GrabCut kept too little, so the motion comes back; not its bleed onto the
                # background, where the point tracks say nothing moved.
                fallback = fallback & ~static[r0:r1, c0:c1]
        else:
            fallback = np.zeros(init.shape, bool)
            fallback[inner] = True
        return (c0, r0, c1, r1), init, fallback

    def _point_region(self, small, pts_s):
        """Mask (small size) of one group of point prompts in small-image pixels."""
        h, w = small.shape[:2]
        cfg = self.config
        rad = max(cfg.point_radius_frac * np.hypot(w, h), 1.0)
        lo, hi = pts_s.min(axis=0) - 2 * rad, pts_s.max(axis=0) + 2 * rad
        c0, r0, c1, r1 = box_pixel_ranges(np.r_[lo, hi][None], w, h)[0]
        if c1 <= c0 or r1 <= r0:
            return np.zeros((h, w), bool)
        # The mask stays within ``rad`` of the prompts (certain background beyond: a point says
        # "this pixel is on an object", not how far it reaches); the inner disks of half that
        # radius are probable foreground.
        init = np.full((r1 - r0, c1 - c0), cv2.GC_BGD, np.uint8)
        zone = np.zeros(init.shape, np.uint8)
        core = np.zeros(init.shape, np.uint8)
        for x, y in pts_s:
            centre = (int(round(x - c0)), int(round(y - r0)))
            cv2.circle(zone, centre, int(round(rad)), 1, -1)
            cv2.circle(core, centre, max(int(round(rad / 2)), 1), 1, -1)
        init[zone > 0] = cv2.GC_PR_BGD
        # Only the prompts seed the foreground (no motion map): as SAM sees only the image and
        # the points, the ablation compares prompt types, not extra cues.
        init[core > 0] = cv2.GC_PR_FGD
        seg = self._cut(small, init, (c0, r0, c1, r1), core > 0)
        seg[init == cv2.GC_BGD] = False
        out = np.zeros((h, w), bool)
        out[r0:r1, c0:c1] = seg
        return out

    def segment(self, image: np.ndarray, boxes: Boxes | None = None,
                points: np.ndarray | None = None,
                context: FrameContext | None = None) -> np.ndarray:
        H, W = image.shape[:2]
        cfg = self.config
        has_boxes = boxes is not None and len(boxes) > 0
        pts = np.zeros((0, 2)) if points is None else np.asarray(points, np.float64).reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(axis=1)]
        if not has_boxes and len(pts) == 0:
            return np.zeros((H, W), bool)
        long_side = cfg.work_size
        if has_boxes:
            order = np.argsort(-np.asarray(boxes.score))[:cfg.max_regions]
            long_side = self.long_side(np.asarray(boxes.xyxy, np.float64)[order], W, H)
        small, sx, sy = self._work(image, long_side)
        h, w = small.shape[:2]
        mm = self._motion(context, w, h)
        theta = float(context.motion_theta) if context is not None else 0.0
        acc = np.zeros((h, w), bool)
        if has_boxes:
            prior = self._at_size(context.prior_mask if context is not None else None, w, h)
            followed = self._at_size(context.followed if context is not None else None, w, h)
            dyn = None
            if context is not None and len(context.dynamic_points):
                dyn = scale_pixels(np.asarray(context.dynamic_points, np.float64), sx, sy)
            static = None
            if (cfg.fallback_static_frac > 0 and context is not None
                    and context.tracked_points is not None
                    and context.tracked_residual is not None):
                static = static_point_zone((h, w), scale_pixels(np.asarray(context.tracked_points,
                                                                        np.float64), sx, sy),
                                           context.tracked_residual,
                                           cfg.fallback_static_frac * context.theta_t,
                                           cfg.fallback_static_reach)
            whole = ~boxes.from_motion
            regions = [self._box_region(small, scale_boxes(b, sx, sy), mm, theta, prior, dyn,
                                        bool(object_box), followed, static)
                       for b, object_box in zip(np.asarray(boxes.xyxy, np.float64)[order],
                                                whole[order])]
            acc = self._cut_boxes(small, [r for r in regions if r is not None])
        else:
            ps = scale_pixels(pts, sx, sy)
            link = cfg.point_link_frac * np.hypot(w, h)
            for idx in group_points(ps, link)[:cfg.max_regions]:
                acc |= self._point_region(small, ps[idx])
        if (w, h) != (W, H):
            soft = cv2.resize(acc.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR)
            if cfg.refine_radius_px > 0 and acc.any():
                soft = refine_edges(image, soft, cfg.refine_radius_px, cfg.refine_eps)
            full = soft > 0.5
        else:
            full = acc
        if cfg.dilate_px > 0 and full.any():
            full = cv2.dilate(full.astype(np.uint8), cv2.getStructuringElement(
                cv2.MORPH_ELLIPSE, (2 * cfg.dilate_px + 1, 2 * cfg.dilate_px + 1))) > 0
        return full


SEGMENTERS.register("sam", "mona_vo.neural.sam:SamSegmenter")
