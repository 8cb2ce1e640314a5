"""MONA moving-object masks, streamed: frames -> tracks -> dynamic points -> boxes -> masks.

:class:`MonaMasker` is fed one frame at a time (``push``) and returns the masks that became
ready; ``flush`` returns the rest at the end of the input. Every input frame gets exactly one
:class:`MaskFrame`, in input order, at most ``lag`` frames after it was pushed
(``lag = max(dynamic_points.window - 1, motion_gap)``, plus one with ``segment_async``): a frame's
dynamic points need the rest of its track window, and its motion map looks ``motion_gap`` frames
ahead. Only those frames' images, flows and track windows are held, so memory does not grow with
the input length.

Per frame t (stages timed in ``MaskFrame.seconds``):

``flow``            optical flow t -> t+1 (``config.flow``); ``m_t`` its mean magnitude; the
                    flow is kept at the analysis resolution (``analysis_size``).
``tracking``        anchor and detection points through the window (``config.tracker``).
``dynamic_points``  camera motion per window pair, residuals, Cauchy probabilities and the
                    adaptive threshold (:mod:`mona_vo.dynamic_points`).
``motion_map``      the flows t -> t+G chained (G: the fewest frames whose mean flow adds up
                    to ``motion_travel_px``, at most ``motion_gap``, fewer at the end; a chain
                    whose step jumps -- an occlusion -- falls back to the single step), the
                    camera motion fitted robustly to that flow at the frame's max-texture grid
                    points (the anchor rule, on a finer grid; homography or epipolar as the
                    frame's track window chose, except that a homography window gives way to the
                    epipolar model while the camera turns slower than
                    ``dynamic_points.homography_min_turn_deg``: then the translation's parallax
                    of near static structure -- a road, a bush -- is no small share of the image
                    motion, and a homography would turn it into "motion"; measured on DAVIS
                    car-shadow, J 0.49 -> 0.58), and each pixel's residual against it, in
                    pixels per frame (:func:`mona_vo.dynamic_points.residual_map`). With
                    ``motion_memory`` > 0 the previous frame's map, carried along the flow and
                    scaled by it, is a floor (a mover stays found in a frame where its motion
                    happens to run along its epipolar lines). The map is thresholded at
                    ``motion_theta = max(theta_t, noise_factor * 1.4826 * median)``, the median over
                    the map's non-zero pixels.
``detection``       boxes (``config.detector``; ``motion`` uses the motion map, the groups of
                    dynamic points and the prior below). With ``mask_prior`` the previous frame's
                    mask, carried into this frame along the flow
                    (:func:`mona_vo.flow.forward_warp_mask`), is passed as
                    ``FrameContext.prior_mask``: a mover
                    found once stays proposed and seeded while it moves along its epipolar lines,
                    and the box filter still asks for its dynamic points. Not in 'points' mode,
                    which prompts with the points only.
``box_filter``      the paper's adaptive filter with ``tau0`` (:mod:`mona_vo.box_filter`).
``evidence``        ('boxes' mode, :mod:`mona_vo.mask_evidence`) the frame's motion map and
                    strong dynamic points update a log-odds map carried along the flow; its
                    hysteresis regions (objects found and not yet stopped, followed from frame
                    to frame) are the prior of the detector and the segmenter. With the motion
                    detector (``Detector.draws_motion``) their boxes are kept as prompts beside
                    the filtered ones (a filtered box outside every region's bound is dropped),
                    and the mask stays within the regions' grown convex hulls (no spill onto
                    still background of similar colour). With an object detector (``yolo``),
                    whose boxes each hold a whole object, a box the filter drops in a frame
                    stays while it overlaps an object followed, and the box bounds its mask.
``segmentation``    the prompts (``config.prompt``) to ``config.segmenter``. With
                    ``segment_async`` it runs on a worker thread while the caller goes on
                    (the next frame's flow, tracks, motion map and evidence; the VO's step on
                    the frame before). Only the next frame's prompts need this frame's mask
                    (their prior), so they wait for it there, and the output is the same. A
                    frame's mask then arrives one push later.

Do no harm: each :class:`MaskFrame` says whether the VO should use it (``reliable``): a mask
covering more than ``vo_max_coverage`` of the frame, or one whose IoU with the previous mask
carried here is below ``vo_min_stability`` (flicker), is not handed to the VO
(:attr:`MaskFrame.vo_mask` is None), which then relies on its own robust residual test for
that frame.

Prompt modes (the paper's ablation, Fig. 3): ``boxes`` (the method: filtered boxes),
``raw-boxes`` (every detector box, no filter), ``points`` (the dynamic points only).
"""
from __future__ import annotations

import dataclasses
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Iterable, Iterator, NamedTuple

import cv2
import numpy as np

from mona_vo.box_filter import UNIT_RULES, BoxFilterResult, adaptive_box_filter
from mona_vo.config import check_fields, setting
from mona_vo.conventions import Intrinsics, scale_boxes, working_size
from mona_vo.detection import (DETECTORS, MOTION_LABEL, Boxes, Detector, FrameContext,
                               MotionDetectorConfig, box_pixel_ranges, grow_boxes,
                               mask_to_boxes, merge_boxes)
from mona_vo.dynamic_points import (EPIPOLAR, HOMOGRAPHY, NO_MODEL, DynamicPoints,
                                    DynamicPointsConfig, DynamicPointsTracker,
                                    adaptive_threshold, classify_window, default_intrinsics,
                                    fit_camera_motion, residual_map, turning_fast)
from mona_vo.errors import ConfigError, InputError
from mona_vo.flow import (FLOWS, DISFlowConfig, Flow, chain_flows, forward_backward_mismatch,
                          forward_warp_mask)
from mona_vo import mask_evidence
from mona_vo.mask_evidence import EvidenceConfig
from mona_vo.point_selection import grid_points, texture_score
from mona_vo.segmentation import SEGMENTERS, GrabCutConfig, Segmenter
from mona_vo.tracking import TRACKERS, Tracker, to_gray

PROMPT_MODES = ("boxes", "points", "raw-boxes")
STAGES = ("flow", "tracking", "dynamic_points", "motion_map", "evidence", "detection",
          "box_filter", "segmentation")


@dataclass(frozen=True)
class MaskConfig:
    """Settings of the mask pipeline; back ends by registry name, one section per classical one."""

    # The point tracker, the device and the weights folder are PipelineConfig's `tracker`,
    # `device` and `weights` (shared with the VO); the masker is handed them.
    flow: str = setting("dis", choices=FLOWS)  # optical flow back end (mona_vo.flow.FLOWS)
    detector: str = setting("motion", choices=DETECTORS)  # box detector back end
                                            # (mona_vo.detection.DETECTORS)
    segmenter: str = setting("grabcut", choices=SEGMENTERS)  # segmenter back end
                                            # (mona_vo.segmentation.SEGMENTERS)
    flow_checkpoint: str = setting("", text="a file path")  # checkpoint file of a neural flow;
                                            # "" = from weights
    detector_checkpoint: str = setting("", text="a file path")  # checkpoint file of a neural
                                            # detector; "" = from weights
    segmenter_checkpoint: str = setting("", text="a file path")  # checkpoint file of a neural
                                            # segmenter; "" = from weights
    prompt: str = setting("boxes", choices=PROMPT_MODES)  # boxes (filtered; the method) | points
                                            # | raw-boxes
    tau0: float = setting(3.0, gt=0)        # dynamic points the unit box must hold (count)
    box_filter_unit: str = setting("smallest-qualifying", choices=UNIT_RULES)  # unit box rule:
                                            # smallest-qualifying | smallest
    analysis_size: int = setting(256, ge=16)  # longer side of the motion map, pixels
                                            # (conventions.working_size)
    motion_gap: int = setting(8, ge=1)      # G_max: motion map from the flow t -> t+G, frames
    motion_travel_px: float = setting(24.0, ge=0)  # G is the fewest frames whose m_t add up to
                                            # this, px
    motion_memory: float = setting(0.5, ge=0, lt=1)  # the previous map, moved along the flow
                                            # and times this (0: off), is a floor of the next one
    chain_change_px: float = setting(1.0, ge=0)  # a chained step may differ from the one before
                                            # by this (full-res px) + chain_change_frac x its
                                            # length, else the chain counts as broken (occlusion)
    chain_change_frac: float = setting(0.3, ge=0)  # see chain_change_px
    flow_check_px: float = setting(0.0, ge=0)  # a pixel whose flow to the next frame and that
                                            # frame's flow back disagree by more than this
                                            # (analysis pixels, plus flow.FB_RELATIVE of the
                                            # vectors' lengths) gives no motion observation
                                            # (0: no check; costs a second flow per frame)
    motion_grid_cols: int = setting(24, ge=2)  # motion-map camera fit: grid columns (anchor rule)
    motion_grid_rows: int = setting(10, ge=2)  # motion-map camera fit: grid rows
    motion_model_threshold_px: float = setting(0.25, gt=0)  # robust-fit threshold of that fit,
                                            # analysis pixels
    motion_model: str = setting("window", choices=("window", "epipolar", "homography"))
                                            # model of that fit: window (the one the frame's
                                            # track window chose; epipolar when the camera
                                            # turns slowly: dynamic_points.
                                            # homography_min_turn_deg) | epipolar | homography
    mask_prior: bool = setting(True)        # the previous frame's mask, carried along the flow,
                                            # is a prior of the detector and the segmenter
                                            # (not in 'points' mode: prompts only)
    vo_max_coverage: float = setting(0.4, gt=0, le=1)  # a mask covering more of the frame
                                            # than this is not handed to the VO (unreliable)
    vo_min_stability: float = setting(0.3, ge=0, le=1)  # nor one whose IoU with the previous
                                            # mask, carried here by the flow, is below this
                                            # (flicker; a first mask after none passes)
    segment_async: bool = setting(True)     # segment on a worker thread, beside the next
                                            # frame's analysis (same masks; module docstring)
    dynamic_points: DynamicPointsConfig = field(default_factory=DynamicPointsConfig)  # module 1
    dis: DISFlowConfig = field(default_factory=DISFlowConfig)            # 'dis' flow settings
    motion: MotionDetectorConfig = field(default_factory=MotionDetectorConfig)  # 'motion' detector
    grabcut: GrabCutConfig = field(default_factory=GrabCutConfig)        # 'grabcut' segmenter
    evidence: EvidenceConfig = field(default_factory=EvidenceConfig)     # accumulated evidence

    def validate(self) -> None:
        check_fields(self, "masks.")
        self.dynamic_points.validate()
        self.dis.validate()
        self.motion.validate()
        self.grabcut.validate()
        self.evidence.validate()

    @property
    def lag(self) -> int:
        """Frames a mask waits for after its frame was pushed (at most)."""
        return max(self.dynamic_points.window - 1, self.motion_gap) + int(self.segment_async)


@dataclass(frozen=True, eq=False)
class MaskFrame:
    """The masker's output for one frame.

    index:          the frame index given to ``push``.
    mask:           (H, W) bool, True on moving objects.
    dynamic_points: the frame's :class:`~mona_vo.dynamic_points.DynamicPoints`.
    boxes:          every detector box (:class:`~mona_vo.detection.Boxes`, pixels).
    kept_boxes:     the boxes used as prompts (filtered in 'boxes' mode, all in 'raw-boxes',
                    none in 'points').
    box_filter:     the filter's details (counts, thresholds, unit box), None unless 'boxes'.
    motion_map:     (h, w) float32 residual motion, pixels per frame, analysis resolution.
    seconds:        stage name -> seconds spent on this frame (see the module docstring).
    evidence:       (h, w) float32 accumulated log-odds of motion, analysis resolution
                    (:mod:`mona_vo.mask_evidence`), or None when not accumulated.
    stability:      IoU of this mask with the previous frame's mask carried here along the
                    flow (analysis resolution); NaN when either is empty.
    reliable:       whether the VO should use the mask: coverage at most
                    ``vo_max_coverage`` and stability (when defined) at least
                    ``vo_min_stability``; else the VO relies on its own residual test.
    repeat_of:      the index of the frame this one repeats (``push_repeat``: its mask and all
                    else are that frame's), -1 for a frame analysed.
    """

    index: int
    mask: np.ndarray
    dynamic_points: DynamicPoints
    boxes: Boxes
    kept_boxes: Boxes
    box_filter: BoxFilterResult | None
    motion_map: np.ndarray | None
    seconds: dict[str, float]
    evidence: np.ndarray | None = None
    stability: float = float("nan")
    reliable: bool = True
    repeat_of: int = -1

    @property
    def vo_mask(self) -> np.ndarray | None:
        """The mask the VO should use: the mask when reliable, else None."""
        return self.mask if self.reliable else None


def _build(registry, name: str, section, device: str, checkpoint: str = ""):
    """A back end: classical ones get their config section, neural ones the device and their
    checkpoint (a file or a weights folder; None lets them look in $MONA_VO_WEIGHTS)."""
    cls = registry.get(name)
    return cls(config=section) if section is not None else cls(device=device, checkpoint=checkpoint or None)


def build_tracker(name: str, device: str = "cpu", checkpoint: str = "") -> Tracker:
    """The classical tracker takes no arguments; neural ones take device and checkpoint."""
    if name == "lk":
        return TRACKERS.create(name)
    return TRACKERS.create(name, device=device, checkpoint=checkpoint or None)


def build_segmenter(config: MaskConfig, device: str = "cpu", weights: str = "") -> Segmenter:
    """``config.segmenter``: the classical one with its section, a neural one on ``device``
    with ``config.segmenter_checkpoint`` (or, when empty, from ``weights``)."""
    return _build(SEGMENTERS, config.segmenter,
                  config.grabcut if config.segmenter == "grabcut" else None,
                  device, config.segmenter_checkpoint or weights)


def build_backends(config: MaskConfig, device: str = "cpu", weights: str = "", *,
                   flow: Flow | None = None, tracker: Tracker | None = None,
                   detector: Detector | None = None, segmenter: Segmenter | None = None) -> dict:
    """MonaMasker's four back ends: those given as they are, the others built from ``config``
    (the classical tracker ``lk`` when none is given). Neural ones find their checkpoints here,
    so a caller that builds them before reading frames fails on a missing one at once."""
    return {"flow": flow or _build(FLOWS, config.flow, config.dis if config.flow == "dis" else None,
                                   device, config.flow_checkpoint or weights),
            "tracker": tracker or build_tracker("lk"),
            "detector": detector or _build(DETECTORS, config.detector,
                                           config.motion if config.detector == "motion" else None,
                                           device, config.detector_checkpoint or weights),
            "segmenter": segmenter or build_segmenter(config, device, weights)}


class MonaMasker:
    """Streaming MONA masks (module docstring).

    ``intrinsics``: the camera's, when known (the pipeline passes its guess from
    ``assumed_hfov_deg`` otherwise; None here: conventions' DEFAULT_HFOV_DEG). Back ends may be
    passed in as instances (tests, or a caller sharing one flow network; the pipeline passes the
    tracker built from its ``tracker`` key, None: the classical ``lk``); otherwise they are built
    from ``config`` (classical ones with their config section, neural ones on ``device`` with
    checkpoints from ``weights``, the pipeline's keys of those names).
    """

    def __init__(self, config: MaskConfig | None = None, intrinsics: Intrinsics | None = None, *,
                 flow: Flow | None = None, tracker: Tracker | None = None,
                 detector: Detector | None = None, segmenter: Segmenter | None = None,
                 device: str = "cpu", weights: str = "", ignore: np.ndarray | None = None):
        self.config = config or MaskConfig()
        self.config.validate()
        cfg = self.config
        self.intrinsics = intrinsics
        built = build_backends(cfg, device, weights, flow=flow, tracker=tracker, detector=detector,
                               segmenter=segmenter)
        self.flow, self.tracker = built["flow"], built["tracker"]
        self.detector, self.segmenter = built["detector"], built["segmenter"]
        self._points = DynamicPointsTracker(cfg.dynamic_points, self.tracker)
        self._size: tuple[int, int] | None = None      # (W, H)
        self._n = 0                                     # frames pushed
        self._next_out = 0                              # position of the next frame to emit
        self._index: dict[int, int] = {}                # position -> frame index given
        self._images: dict[int, np.ndarray] = {}        # position -> image, until emitted
        self._flows: dict[int, np.ndarray] = {}         # position p -> flow p -> p+1, analysis
        self._unsure: dict[int, np.ndarray] = {}        # position p -> pixels failing the
                                                        # flow check (flow_check_px)
        self._m: dict[int, float] = {}                  # position -> m_t
        self._dyn: dict[int, DynamicPoints] = {}        # position -> dynamic points
        self._reserve: DynamicPoints | None = None      # last frame of the last closed window
        self._seconds: dict[int, dict[str, float]] = {}
        self._prev_map: np.ndarray | None = None        # motion map of the last frame emitted
        self._prev_flow: np.ndarray | None = None       # and its flow to the next frame
        self._prev_small: np.ndarray | None = None      # and its mask, analysis resolution
                                                        # (None when empty)
        self._last_image: np.ndarray | None = None      # the last frame pushed
        self._prev_image: np.ndarray | None = None      # the one before it
        self._logodds: np.ndarray | None = None         # accumulated evidence, last frame emitted
        self._found: np.ndarray | None = None           # and its regions (objects followed)
        self._repeats: dict[int, list[int]] = {}        # position -> indices of the frames that
                                                        # repeat it (push_repeat), until emitted
        self._last_out: MaskFrame | None = None         # the last mask emitted
        self._pending: tuple | None = None              # (analysis, future, boxes, kept, box
                                                        # filter) of the frame being segmented
        self._pool: ThreadPoolExecutor | None = None    # its worker (segment_async)
        # Pixels that are no part of the scene (a burned-in overlay painted over,
        # mona_vo.overlays): the painting changes with the scene around it but does not move
        # as it does, so no motion evidence, no dynamic point and no mask there.
        self._ignore = None if ignore is None or not np.any(ignore) else np.asarray(ignore, bool)
        if self._ignore is not None:
            # The flow of the pixels around the painting mixes in its non-motion (DIS's patches
            # and smoothing reach across its border): a band of IGNORE_MARGIN analysis pixels
            # around it is left out too. Measured on generated mixed seed 1 (tuning) with a
            # badge, 640 x 272: without the band a ring of mask around the badge in every
            # frame, J 0.12 (0.79 without the badge); with 3 / 6 / 9 analysis pixels 0.64 /
            # 0.79 / 0.79.
            h, w = self._ignore.shape
            r = int(np.ceil(IGNORE_MARGIN * max(w, h) / cfg.analysis_size))
            disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            self._ignore = cv2.dilate(self._ignore.astype(np.uint8), disk) > 0
        self._ignore_small: np.ndarray | None = None

    # ------------------------------------------------------------------ buffers (for tests)
    def buffered_frames(self) -> int:
        """Images currently held (bounded by ``config.lag + 1``)."""
        return len(self._images)

    # ------------------------------------------------------------------ public API
    def push(self, frame_index: int, image_rgb: np.ndarray) -> list[MaskFrame]:
        """Feed the next frame ((H, W, 3) uint8 RGB); returns the masks that became ready, in
        frame order (possibly none)."""
        image = np.asarray(image_rgb)
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise InputError(f"frame {frame_index}: expected an (H, W, 3) uint8 RGB image, got "
                             f"{image.shape} {image.dtype}")
        H, W = image.shape[:2]
        if self._size is None:
            self._size = (W, H)
            if self.intrinsics is None:
                self.intrinsics = default_intrinsics(W, H)
        elif self._size != (W, H):
            raise InputError(f"frame {frame_index} is {W} x {H}, the earlier frames are "
                             f"{self._size[0]} x {self._size[1]}")
        p = self._n
        self._n += 1
        self._index[p] = int(frame_index)
        self._images[p] = image
        self._seconds[p] = {s: 0.0 for s in STAGES}
        if p > 0:
            self._add_flow(p - 1, self._last_image, image)
        self._prev_image, self._last_image = self._last_image, image
        t0 = time.perf_counter()
        window = self._points.push(p, image)
        self._seconds[p]["tracking"] += time.perf_counter() - t0
        if window is not None:
            self._classify(window, final=False)
        return self._emit_ready(final=False)

    def push_repeat(self, frame_index: int) -> list[MaskFrame]:
        """Feed a frame that repeats the last one pushed (:mod:`mona_vo.repeats`): it is not
        analysed, and gets that frame's mask (a copy of its MaskFrame under its own index, with
        no seconds spent) right after it. Returns the masks that became ready."""
        if self._n == 0:
            raise InputError(f"frame {frame_index}: a repeat needs a frame before it")
        source = self._n - 1
        if source < self._next_out:     # already emitted (only after a flush)
            return [self._copy_for(self._last_out, frame_index)]
        self._repeats.setdefault(source, []).append(int(frame_index))
        return []

    @staticmethod
    def _copy_for(mf: MaskFrame, frame_index: int) -> MaskFrame:
        return dataclasses.replace(mf, index=int(frame_index), seconds={},
                                   repeat_of=mf.index if mf.repeat_of < 0 else mf.repeat_of)

    def flush(self) -> list[MaskFrame]:
        """Masks of every frame not yet returned (call once, at the end of the input)."""
        if self._n == 0:
            return []
        last = self._n - 1
        if last > 0 and last not in self._flows and last in self._images:
            # The last frame has no successor: its flow goes backwards, to the frame before.
            self._add_flow(last, self._last_image, self._prev_image, check=False)
        window = self._points.flush()
        if window is not None:
            self._classify(window, final=True)
        elif last not in self._dyn and self._reserve is not None:
            self._dyn[last] = self._reserve
        out = self._emit_ready(final=True)
        self._reserve = None
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        return out

    # ------------------------------------------------------------------ stages
    def _analysis_size(self) -> tuple[int, int]:
        return working_size(*self._size, self.config.analysis_size)

    def _add_flow(self, p: int, image0, image1, check: bool = True) -> None:
        """Flow of frame p (image0) to image1, kept at the analysis resolution, and its m_t;
        with ``flow_check_px`` (and ``check``) also the pixels whose flow back disagrees."""
        t0 = time.perf_counter()
        w, h = self._analysis_size()
        self._flows[p], self._m[p] = self.flow.compute_resized(image0, image1, w, h)
        if check and self.config.flow_check_px > 0:
            back, _ = self.flow.compute_resized(image1, image0, w, h)
            self._unsure[p] = forward_backward_mismatch(self._flows[p], back,
                                                        self.config.flow_check_px)
        self._seconds[p]["flow"] += time.perf_counter() - t0

    def _classify(self, window, final: bool) -> None:
        t0 = time.perf_counter()
        pos = [int(q) for q in window.frame_indices]
        # m_t of a window's last frame may not be known yet (it needs the next frame); the frame
        # before stands in (it only matters for a window's last frame at the end of the input).
        m = np.array([self._m.get(q, self._m.get(q - 1, 0.0)) for q in pos])
        results = classify_window(window, m, self.config.dynamic_points, self.intrinsics)
        keep = len(pos) if final else len(pos) - 1
        share = (time.perf_counter() - t0) / max(keep, 1)
        for q, r in zip(pos[:keep], results[:keep]):
            self._dyn[q] = r
            if q in self._seconds:
                self._seconds[q]["dynamic_points"] += share
        # A window's last frame is the next window's first; its result is kept in case the input
        # ends there (then the next window never gets a second frame).
        self._reserve = None if final else results[-1]

    def _motion_map(self, p: int, last: int, model: str | None,
                    grey: np.ndarray) -> np.ndarray | None:
        """Residual motion of frame p, full-resolution pixels per frame, analysis resolution
        (``grey``: frame p's grey image at that resolution)."""
        cfg = self.config
        W, _ = self._size
        w, _ = self._analysis_size()
        scale = w / W
        if p < last:
            gap = min(cfg.motion_gap, last - p)
            # Chain only until the image has moved enough to show parallax: longer chains
            # drift and smear (background pixels later covered by a mover inherit its flow).
            travelled = np.cumsum([self._m[q] for q in range(p, p + gap)])
            gap = int(min(gap, np.searchsorted(travelled, cfg.motion_travel_px) + 1))
            # No observation where a step's flow fails its own check (flow_check_px, off by
            # default): occlusions and flow fitted to noise.
            cum, valid = chain_flows([self._flows[q] for q in range(p, p + gap)],
                                     max_change_px=cfg.chain_change_px * scale,
                                     max_change_frac=cfg.chain_change_frac,
                                     unsure=[self._unsure.get(q) for q in range(p, p + gap)])
            m_pair = float(np.mean([self._m[q] for q in range(p, p + gap)]))
        elif p in self._flows:           # the last frame: flow to the previous frame
            gap = 1
            cum, valid = chain_flows([self._flows[p]])
            m_pair = self._m[p]
        else:
            return None
        score = texture_score(grey, cfg.dynamic_points.anchor_score)
        out = self._residual(p, score, cum, valid, gap, m_pair, model)
        if gap > 1 and not valid.all():
            # Pixels whose chain left the image: the single-step flow still sees them.
            first, valid1 = chain_flows([self._flows[p]], unsure=[self._unsure.get(p)])
            short = self._residual(p, score, first, valid1, 1, self._m[p], model,
                                   where=valid1 & ~valid)
            out = np.where(valid, out, short)
        return out

    def _residual(self, p, score, cum, valid, gap, m_pair, model, where=None) -> np.ndarray:
        """Residual map (full-resolution px per frame) of the flow ``cum`` over ``gap`` frames,
        the camera motion fitted at the ``valid`` pixels; computed at the pixels ``where``
        (default: the valid ones), zero elsewhere."""
        cfg = self.config
        dp = cfg.dynamic_points
        h, w = cum.shape[:2]
        scale = w / self._size[0]
        anchors = grid_points(score, cfg.motion_grid_cols, cfg.motion_grid_rows, border=2,
                              exclude=~valid)
        if len(anchors) < 8:
            return np.zeros((h, w), np.float32)
        ij = np.round(anchors).astype(int)
        pb = anchors + cum[ij[:, 1], ij[:, 0]]
        theta_pair = adaptive_threshold(m_pair, dp.alpha, dp.theta_min_px)
        motion = fit_camera_motion(anchors, pb, self.intrinsics.scaled(scale),
                                   threshold_px=cfg.motion_model_threshold_px,
                                   inlier_px=theta_pair * gap * scale,
                                   homography_min_ratio=dp.homography_min_ratio,
                                   method=dp.robust_method, model=model)
        return residual_map(motion, cum, valid if where is None else where) / (gap * scale)

    def _carry_forward(self, prev_map: np.ndarray) -> np.ndarray:
        """The previous frame's motion map moved into this frame along the flow between them,
        as the evidence is (:func:`mona_vo.mask_evidence.carry`: forward splat, nothing carried
        from a flow discontinuity or onto background a mover uncovered); zeros without a flow."""
        return mask_evidence.carry(prev_map, self._prev_flow, 0.0, self.config.evidence)

    def _carry_prior(self) -> np.ndarray:
        """The previous frame's mask at the analysis resolution, carried into this frame along
        the flow between them."""
        return forward_warp_mask(self._prev_small, self._prev_flow)

    def _analysis_mask(self, mask: np.ndarray) -> np.ndarray | None:
        """A full-resolution mask at the analysis resolution (area average > 0.5), None when
        the mask is empty."""
        if not mask.any():
            return None
        w, h = self._analysis_size()
        return cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5

    def _emit_ready(self, final: bool) -> list[MaskFrame]:
        out = []
        last = self._n - 1
        while self._next_out <= last:
            p = self._next_out
            if p not in self._dyn:
                break
            if not final and p + self.config.motion_gap > last:
                break
            analysis = self._analyse(p, last)
            out += self._resolve()
            self._emit(analysis)
            self._next_out += 1
        if final or not self.config.segment_async:
            out += self._resolve()
        return out

    def _analyse(self, p: int, last: int) -> _Analysis:
        """Frame ``p``'s motion map and accumulated evidence: they need no earlier frame's mask,
        so with ``segment_async`` this runs while the frame before is still being segmented."""
        cfg = self.config
        sec = self._seconds.pop(p)
        image = self._images[p]
        dyn = self._dyn.pop(p)
        t0 = time.perf_counter()
        # The dense fit takes the model (homography or epipolar) the frame's track window chose:
        # its long-baseline, precisely tracked anchors decide it more reliably.
        model = dyn.camera_model if dyn.camera_model != NO_MODEL else None
        if cfg.motion_model != "window":
            model = cfg.motion_model
        elif model == HOMOGRAPHY and not turning_fast(
                self._m.get(p, self._m.get(p - 1, 0.0)), self.intrinsics,
                cfg.dynamic_points.homography_min_turn_deg):
            model = EPIPOLAR
        grey = cv2.resize(to_gray(image), self._analysis_size(), interpolation=cv2.INTER_AREA)
        mmap = self._motion_map(p, last, model, grey)
        if self._ignore is not None:
            mmap, dyn = self._without_ignored(mmap, dyn)
        if mmap is not None and cfg.motion_memory > 0 and self._prev_map is not None:
            mmap = np.maximum(mmap, cfg.motion_memory * self._carry_forward(self._prev_map))
        m_t = self._m.get(p, self._m.get(p - 1, 0.0))
        theta = adaptive_threshold(m_t, cfg.dynamic_points.alpha, cfg.dynamic_points.theta_min_px)
        theta = max(theta, dyn.theta_t)
        motion_theta = theta
        spread = 0.0
        if mmap is not None and mmap.any():
            spread = mask_evidence.motion_spread(mmap)
            motion_theta = max(theta, cfg.dynamic_points.noise_factor * spread)
        t_ev = time.perf_counter()
        use_evidence = cfg.evidence.enabled and cfg.prompt == "boxes" and mmap is not None
        logodds = found = allowed = None
        if use_evidence:
            texture = texture_score(grey, "min_eigen") if cfg.evidence.texture_ref > 0 else None
            logodds = self._accumulate(mmap, motion_theta, spread, dyn, texture)
            follow = None
            if self._found is not None and self._prev_flow is not None and self._found.any():
                follow = forward_warp_mask(self._found, self._prev_flow)
            found = mask_evidence.regions(logodds, cfg.evidence, follow)
            allowed = mask_evidence.bound(logodds, cfg.evidence, follow)
        sec["motion_map"] += t_ev - t0
        sec["evidence"] += time.perf_counter() - t_ev
        return _Analysis(p, sec, image, dyn, mmap, theta, m_t, motion_theta, use_evidence,
                         logodds, found, allowed)

    def _emit(self, a: _Analysis) -> None:
        """Frame ``a.p``'s prompts, and its segmentation started (``_resolve`` returns its
        MaskFrame); the frame before must be resolved (its mask is this one's prior)."""
        cfg = self.config
        p, sec, image, dyn, mmap = a.p, a.sec, a.image, a.dyn, a.mmap
        found, allowed = a.found, a.allowed
        t0 = time.perf_counter()
        dyn_xy = dyn.dynamic_points
        carried_prev = None
        if self._prev_small is not None and self._prev_flow is not None:
            carried_prev = self._carry_prior()
        prior = carried_prev if cfg.mask_prior and cfg.prompt != "points" else None
        if a.use_evidence:
            # The objects followed so far are the prior of the detector and the segmenter.
            prior = found if prior is None or allowed is None else (found | (prior & allowed))
        t1b = time.perf_counter()
        sec["motion_map"] += t1b - t0
        context = FrameContext(self._index[p], mmap, a.theta, a.m_t, dyn_xy, a.motion_theta,
                               dyn.points, prior, dyn.residual[dyn.is_dynamic], found,
                               tracked_residual=dyn.residual)
        boxes = Boxes.empty() if cfg.prompt == "points" else self.detector.detect(image, context)
        t2 = time.perf_counter()
        filt = None
        if cfg.prompt == "boxes":
            filt = adaptive_box_filter(boxes.xyxy, dyn_xy, cfg.tau0, cfg.box_filter_unit)
            keep = filt.keep
            if a.use_evidence and not self.detector.draws_motion and found.any():
                # An object's box that the filter drops in this frame (too few dynamic points
                # on it now) stays while it holds an object followed.
                keep = keep | self._holds(boxes, found, image.shape[:2])
            kept = boxes.select(keep)
            if a.use_evidence and self.detector.draws_motion:
                kept = self._with_evidence(kept, found, allowed, image.shape[:2])
        elif cfg.prompt == "raw-boxes":
            kept = boxes
        else:
            kept = Boxes.empty()
        t3 = time.perf_counter()
        sec["detection"] += t2 - t1b
        sec["box_filter"] += t3 - t2
        job = (image, kept, dyn_xy, context, allowed, carried_prev)
        if cfg.segment_async:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix="mona-segment")
            done = self._pool.submit(self._segment, *job)
        else:
            done = Future()
            done.set_result(self._segment(*job))
        # Release what no later frame needs: later motion maps chain flows from p + 1 on, and
        # later frames' m_t are their own (or, for the last frame, its backward flow's).
        self._prev_map, self._prev_flow = mmap, self._flows.pop(p, None)
        self._unsure.pop(p, None)
        self._logodds, self._found = a.logodds, found
        self._m.pop(p - 1, None)
        self._pending = (a, done, boxes, kept, filt)

    def _segment(self, image, kept, dyn_xy, context, allowed, carried_prev):
        """The frame's mask from its prompts, at full and analysis resolution, its stability and
        reliability, and the seconds spent (on the worker thread with ``segment_async``: it
        reads only its arguments, settings fixed before the first frame, and the segmenter,
        which nothing else uses)."""
        cfg = self.config
        t0 = time.perf_counter()
        if cfg.prompt == "points":
            mask = self.segmenter.segment(image, None, dyn_xy, context)
        elif len(kept):
            mask = self.segmenter.segment(image, kept, None, context)
            if allowed is not None and self.detector.draws_motion:
                # Regions drawn around motion stay within the evidence's bound; an object
                # detector's box bounds its object's mask itself.
                mask &= self._upsample(allowed, image.shape[:2])
        else:
            mask = np.zeros(image.shape[:2], bool)
        if self._ignore is not None:
            mask &= ~self._ignore
        # Reduced once: this frame's stability and the next frame's prior both use it.
        small = self._analysis_mask(mask)
        stability, reliable = self._reliability(mask, small, carried_prev)
        return mask, small, stability, reliable, time.perf_counter() - t0

    def _resolve(self) -> list[MaskFrame]:
        """The MaskFrame of the frame whose segmentation is under way (waiting for it), and
        the copies for the frames that repeat it; none when no frame is under way."""
        if self._pending is None:
            return []
        a, done, boxes, kept, filt = self._pending
        self._pending = None
        mask, small, stability, reliable, seconds = done.result()
        a.sec["segmentation"] += seconds
        self._prev_small = small
        del self._images[a.p]
        index = self._index.pop(a.p)
        self._last_out = MaskFrame(index, mask, a.dyn, boxes, kept, filt, a.mmap, a.sec,
                                   a.logodds, stability, reliable)
        return [self._last_out] + [self._copy_for(self._last_out, i)
                                   for i in self._repeats.pop(a.p, ())]

    def _without_ignored(self, mmap: np.ndarray | None, dyn: DynamicPoints):
        """The motion map and dynamic points with nothing inside the ignored pixels."""
        if self._ignore.shape != self._size[::-1]:
            raise InputError(f"the region to ignore is {self._ignore.shape[1]} x "
                             f"{self._ignore.shape[0]}, the frames {self._size[0]} x {self._size[1]}")
        if mmap is not None:
            if self._ignore_small is None:
                self._ignore_small = cv2.resize(self._ignore.astype(np.uint8), mmap.shape[::-1],
                                                interpolation=cv2.INTER_NEAREST) > 0
            mmap = np.where(self._ignore_small, 0.0, mmap).astype(mmap.dtype)
        if len(dyn.points):
            xy = np.clip(np.round(dyn.points).astype(int), 0, [self._size[0] - 1, self._size[1] - 1])
            inside = self._ignore[xy[:, 1], xy[:, 0]]
            if (inside & dyn.is_dynamic).any():
                dyn = dataclasses.replace(dyn, is_dynamic=dyn.is_dynamic & ~inside)
        return mmap, dyn

    def _reliability(self, mask: np.ndarray, small: np.ndarray | None,
                     carried_prev: np.ndarray | None) -> tuple[float, bool]:
        """(stability, reliable) of a frame's mask (see :class:`MaskFrame`); ``small``: the mask
        at the analysis resolution (:meth:`_analysis_mask`)."""
        cfg = self.config
        coverage = float(mask.mean())
        stability = float("nan")
        if carried_prev is not None and carried_prev.any() and small is not None:
            union = np.count_nonzero(small | carried_prev)
            stability = np.count_nonzero(small & carried_prev) / union if union else float("nan")
        reliable = coverage <= cfg.vo_max_coverage and not (
            np.isfinite(stability) and stability < cfg.vo_min_stability)
        return stability, bool(reliable)

    def _accumulate(self, mmap: np.ndarray, motion_theta: float, spread: float,
                    dyn: DynamicPoints, texture: np.ndarray | None) -> np.ndarray:
        """This frame's log-odds map: the last one carried along the flow, decayed, plus this
        frame's observation (:mod:`mona_vo.mask_evidence`; ``spread``: the map's
        :func:`~mona_vo.mask_evidence.motion_spread`). The first frame counts its
        observation twice (as if seen one frame before): a mover in view from the start is
        found there, a one-frame spike still is not (obs_max x 2 stays below clamp_hi)."""
        ev = self.config.evidence
        dyn_sel = dyn.is_dynamic
        obs = mask_evidence.observe(mmap, motion_theta, mmap.shape, dyn.points[dyn_sel],
                                    dyn.residual[dyn_sel], self._size[0], ev, texture)
        if ev.seeded_noise_factor > 0:
            seeded = mask_evidence.seeded_regions(mmap, dyn.points[dyn_sel], self._size[0], ev,
                                                  spread, self.config.vo_max_coverage)
            obs = np.where(seeded, np.maximum(obs, ev.point_gain), obs)
        if self._logodds is None or self._logodds.shape != mmap.shape:
            return mask_evidence.update(obs, obs, dataclasses.replace(ev, decay=0.999))
        carried = mask_evidence.carry(self._logodds, self._prev_flow, 0.0, ev)
        return mask_evidence.update(carried, obs, ev)

    @staticmethod
    def _holds(boxes: Boxes, found: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """(N,) bool: the boxes that overlap the (h, w) bool regions ``found`` (analysis
        resolution) of a frame of ``shape`` (H, W)."""
        H, W = shape
        h, w = found.shape
        ranges = box_pixel_ranges(scale_boxes(np.asarray(boxes.xyxy, np.float64), w / W, h / H),
                                  w, h)
        return np.array([found[r0:r1, c0:c1].any() for c0, r0, c1, r1 in ranges], bool)

    def _with_evidence(self, kept: Boxes, found: np.ndarray, allowed: np.ndarray | None,
                       shape: tuple[int, int]) -> Boxes:
        """Filtered boxes (drawn around motion) that overlap the evidence bound, plus the boxes
        of the evidence regions (the objects followed), merged where they overlap."""
        H, W = shape
        h, w = found.shape
        if allowed is not None and len(kept):
            kept = kept.select(self._holds(kept, allowed, shape))
        small, _ = mask_to_boxes(found, 1)
        if not len(small):
            return kept
        xyxy = grow_boxes(scale_boxes(small, W / w, H / h), self.config.motion.box_margin_frac)
        all_xyxy = np.concatenate([kept.xyxy, xyxy.astype(np.float32)])
        score = np.concatenate([kept.score, np.ones(len(xyxy), np.float32)])
        all_xyxy, score = merge_boxes(all_xyxy, score, self.config.motion.merge_overlap)
        return Boxes(all_xyxy, score, np.full(len(score), MOTION_LABEL)).clipped(W, H)

    @staticmethod
    def _upsample(small: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        H, W = shape
        return cv2.resize(small.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR) > 0.5


class _Analysis(NamedTuple):
    """A frame's analysis before its prompts (MonaMasker._analyse)."""
    p: int
    sec: dict
    image: np.ndarray
    dyn: DynamicPoints
    mmap: np.ndarray | None
    theta: float
    m_t: float
    motion_theta: float
    use_evidence: bool
    logodds: np.ndarray | None
    found: np.ndarray | None
    allowed: np.ndarray | None


IGNORE_MARGIN = 6   # analysis pixels left out around ignored pixels (MonaMasker's ``ignore``)


def compute_masks(frames: Iterable, config: MaskConfig | None = None,
                  intrinsics: Intrinsics | None = None, *, repeat_max_diff: float = 0.0,
                  **backends) -> Iterator[MaskFrame]:
    """Masks of a stream of frames (objects with ``index`` and ``image`` attributes, e.g.
    :class:`data_tools.frames.Frame`, or ``(index, image)`` pairs), one per frame, in order.
    ``repeat_max_diff`` > 0: a frame that repeats the last distinct one within that many grey
    levels (:class:`mona_vo.repeats.RepeatDetector`) is not analysed and gets its mask.
    ``backends``: MonaMasker's keyword arguments (tracker, device, weights, ...)."""
    from mona_vo.repeats import RepeatDetector

    masker = MonaMasker(config, intrinsics, **backends)
    repeats = RepeatDetector(repeat_max_diff)
    for frame in frames:
        if isinstance(frame, tuple):
            index, image = frame
        else:
            index, image = frame.index, frame.image
        if repeats.is_repeat(image):
            yield from masker.push_repeat(index)
        else:
            yield from masker.push(index, image)
    yield from masker.flush()
