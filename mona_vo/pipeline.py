"""The one call: frames in, a pose for every frame out, with moving-object masks in between.

``estimate_trajectory(frames, intrinsics=..., masks=..., config=...)`` streams the frames once;
without intrinsics, when the global refinement moves the focal length by more than
``calibration.second_pass_change`` and the frames can be read again (a list, a
:class:`data_tools.frames.FrameSource`; not an iterator), the VO runs a second time with the
refined camera and the masks of the first pass (kept for it, a bit per pixel: 38 KB per
640 x 480 frame). Before that, a first pass that built no map although its parallax says the
camera translated runs once more with the start's ray-angle test taken at the widest field of
view the focal estimate considers (``_start_again``), and a later pass that builds no map never
replaces one that did.
Masks come from MONA (``masks="mona"``, computed on the fly with a short look-ahead), from the
caller (an iterable aligned with the frames, or a callable ``frame -> mask``), or not at all.
Nothing is written here; ``on_frame`` lets the caller store masks or draw overlays as frames
finish, so memory stays flat however long the video is (but for those packed masks).
"""
from __future__ import annotations

import dataclasses
import inspect
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import cv2
import numpy as np

from mona_vo.calibration import FocalConfig
from mona_vo.config import check_fields, setting
from mona_vo.conventions import DEFAULT_HFOV_DEG, Intrinsics
from mona_vo.tracking import TRACKERS
from mona_vo.errors import ConfigError, InputError
from mona_vo.lens import LensIntrinsics, Undistortion, undistort_frames
from mona_vo.overlays import hide_overlay, overlay_ahead
from mona_vo.picture_area import PictureArea, crop_frames, crop_to_picture
from mona_vo.repeats import RepeatDetector
from mona_vo.rolling_shutter import turn_rates, unroll_maps
from mona_vo.vo import VOConfig, VOResult, VisualOdometry


def _mask_config_default():
    from mona_vo.masks import MaskConfig

    return MaskConfig()


@dataclass(frozen=True)
class PipelineConfig:
    """The whole run: facts shared by the masks and the VO (one key each), then the stages."""

    tracker: str = setting("lk", choices=TRACKERS)  # point tracker of the masks and of the VO
                                            # (mona_vo.tracking.TRACKERS)
    tracker_checkpoint: str = setting("", text="a file path")  # checkpoint file of a neural
                                            # tracker; "" = from weights
    device: str = setting("cpu", pattern=r"cpu|cuda(:[0-9]+)?")  # torch device of the neural
                                            # back ends (classical ones run on the CPU)
    weights: str = setting("", text="a folder path")  # folder of neural checkpoints under their
                                            # documented names (mona_vo.neural.weights);
                                            # "" = $MONA_VO_WEIGHTS
    assumed_hfov_deg: float = setting(DEFAULT_HFOV_DEG, ge=10, le=170)  # field of view assumed
                                            # without --calib, degrees, across the longer side
                                            # (the width of a landscape frame); masks, VO, report
    crop_bars: bool = setting(True)         # find flat letterbox / pillarbox bars in the first
                                            # frames and run on the picture inside them
                                            # (mona_vo.picture_area); masks and intrinsics stay
                                            # in full-frame pixels
    hide_overlays: bool = setting(True)     # find burned-in logos and captions that stand
                                            # still in the first frames and paint them over
                                            # in every frame (mona_vo.overlays)
    repeat_max_diff: float = setting(2.5, ge=0, le=255)  # grey levels: a frame no 16 x 16
                                            # block of which differs more from the last
                                            # distinct frame (mean, both smoothed by 1 px) is a
                                            # repeat (pulldown, a stalled stream) and takes that
                                            # frame's pose and mask unprocessed
                                            # (mona_vo.repeats); 0 = off
    calibration: FocalConfig = field(default_factory=FocalConfig)  # focal length without
                                            # --calib (mona_vo.calibration)
    vo: VOConfig = field(default_factory=VOConfig)  # visual odometry
    masks: Any = field(default_factory=_mask_config_default)  # MONA moving-object masks
                                            # (mona_vo.masks.MaskConfig)

    def validate(self) -> None:
        check_fields(self)
        self.vo.validate()
        v = getattr(self.masks, "validate", None)
        if callable(v):
            v()

    def guessed_intrinsics(self, width: int, height: int) -> Intrinsics:
        """The pinhole guess of an uncalibrated width x height video (``assumed_hfov_deg``)."""
        return Intrinsics.default_for(width, height, self.assumed_hfov_deg)

    def build_tracker(self):
        """A new :class:`mona_vo.tracking.Tracker` of the ``tracker`` key (the masks and the VO
        each get their own: they track different points)."""
        from mona_vo.masks import build_tracker

        return build_tracker(self.tracker, self.device, self.tracker_checkpoint or self.weights)

    def masker_backends(self, detector=None) -> dict:
        """:class:`mona_vo.masks.MonaMasker`'s back ends, built from ``masks`` and the shared keys
        (tracker, device, weights); ``detector``, when given, in place of the one it names."""
        from mona_vo.masks import build_backends

        return build_backends(self.masks, self.device, self.weights, tracker=self.build_tracker(),
                              detector=detector)


@dataclass
class FrameOutput:
    """Handed to ``on_frame`` once a frame's mask is known (before the VO has seen it)."""

    index: int
    name: str
    timestamp: float
    image: np.ndarray               # (H, W, 3) uint8 RGB
    mask: np.ndarray | None         # (H, W) bool moving-object mask, None without masks
    mona: Any = None                # mona_vo.masks.MaskFrame when MONA computed the mask
    origin: tuple[int, int] = (0, 0)  # (x, y) of the picture MONA saw in this frame: its points
                                    # and boxes are in the picture's pixels (crop_bars)

    @property
    def vo_mask(self) -> np.ndarray | None:
        """The mask the VO was handed, full-frame pixels: MONA's only when reliable
        (MaskFrame.vo_mask), a caller's as given; None without one."""
        return self.mask if self.mona is None or self.mona.reliable else None


@dataclass
class RunResult:
    """Everything a run produced, in memory. ``vo`` holds the per-frame poses."""

    vo: VOResult
    names: list[str]
    width: int
    height: int
    intrinsics: Intrinsics          # of the first frame (per-frame ones were given by the caller)
    timings: dict[str, float]       # stage -> seconds (masks stages, VO stages, total)
    mask_coverage: np.ndarray       # (N,) fraction of each frame's pixels inside its mask
    calibration: Any = None         # mona_vo.calibration.FocalEstimate without given intrinsics
    picture: PictureArea | None = None  # the picture inside bars the run used (crop_bars)
    overlay: np.ndarray | None = None   # (H, W) bool burned-in overlay painted over
                                    # (hide_overlays), None when none was found
    repeat_of: np.ndarray | None = None  # (N,) int: the frame each frame repeats (its pose and
                                    # mask are that frame's), -1 for a distinct frame
    lens: dict | None = None        # a distorted camera: its coefficients and how far they
                                    # moved the pixels (mona_vo.lens), else None

    @property
    def n_frames(self) -> int:
        return len(self.names)

    @property
    def frames_per_second(self) -> float:
        total = self.timings.get("total", 0.0)
        return self.n_frames / total if total > 0 else float("nan")


def _intrinsics_for(intrinsics, frame, width, height) -> Intrinsics | None:
    if intrinsics is None or isinstance(intrinsics, Intrinsics):
        return intrinsics
    if callable(intrinsics):
        return intrinsics(frame)
    return intrinsics[frame.index]


def _intrinsics_in_picture(intrinsics, area: PictureArea):
    """The caller's full-frame intrinsics (any form :func:`_intrinsics_for` takes) as the
    picture's."""
    if intrinsics is None or isinstance(intrinsics, Intrinsics):
        return area.to_picture(intrinsics)
    return lambda frame: area.to_picture(_intrinsics_for(intrinsics, frame, *area.size))


class _CallerMasks:
    """Masks given by the caller: an iterable aligned with the frames, or a callable; in
    full-frame pixels, cut to the picture the run uses."""

    def __init__(self, masks, area: PictureArea | None = None, lens: Undistortion | None = None):
        self.fn = masks if callable(masks) else None
        self.it = None if callable(masks) else iter(masks)
        self.area, self.lens = area, lens

    def get(self, frame) -> np.ndarray | None:
        if self.fn is not None:
            m = self.fn(frame)
        else:
            try:
                m = next(self.it)
            except StopIteration:
                raise InputError(f"fewer masks than frames: none for frame {frame.name}") from None
        if m is None:
            return None
        m = np.asarray(m).astype(bool)
        full = getattr(frame, "full", frame.image)
        if m.shape != full.shape[:2]:
            raise InputError(f"mask for frame {frame.name} is {m.shape[1]} x {m.shape[0]}, "
                             f"the frame is {full.shape[1]} x {full.shape[0]}")
        m = m if self.area is None else self.area.crop(m)
        return m if self.lens is None else self.lens.mask(m)


def estimate_focal_ahead(frames: Iterable, config: "PipelineConfig"):
    """Read the first ``config.calibration.frames`` frames, estimate the focal length from them
    (:func:`mona_vo.calibration.estimate_focal`) and return (the whole stream again, estimate)."""
    from data_tools.frames import read_ahead
    from mona_vo.calibration import estimate_focal

    head, stream = read_ahead(frames, config.calibration.frames)
    if len(head) < 3:
        return stream, None
    h, w = head[0].image.shape[:2]
    est = estimate_focal([f.image for f in head], config.guessed_intrinsics(w, h), config.calibration)
    return stream, est


def camera_without_calib(estimate, config: "PipelineConfig", width: int, height: int) -> Intrinsics:
    """The one camera of a run without intrinsics, for the VO and the masks alike: the focal-length
    estimate (:func:`estimate_focal_ahead`; it holds the guess when it was not taken) when there
    is one, else the ``assumed_hfov_deg`` guess. MONA's epipolar test on a wrong focal length
    turns near parallax into motion, so the masks must not keep the guess the VO dropped."""
    return estimate.intrinsics_for(width, height) if estimate is not None \
        else config.guessed_intrinsics(width, height)


def camera_ahead(frames: Iterable, config: "PipelineConfig", width: int, height: int):
    """The camera a run without intrinsics uses for ``frames`` (width x height): the focal-length
    estimate from the first frames when ``calibration.mode`` is ``estimate``, else the guess.
    Returns (the whole stream again, the estimate or None, the camera)."""
    estimate = None
    if config.calibration.mode == "estimate":
        frames, estimate = estimate_focal_ahead(frames, config)
    return frames, estimate, camera_without_calib(estimate, config, width, height)


def _pass_progress(progress: Callable | None, name: str) -> Callable[[int], None] | None:
    """The caller's progress callback for a later VO pass over the same frames: called as
    ``progress(frames, name)`` when it takes a pass name (a bar that restarts under it), else as
    ``progress(frames)``, so a callback that only counts keeps working."""
    if progress is None:
        return None
    try:
        inspect.signature(progress).bind(0, name)
    except (TypeError, ValueError):
        return progress
    return lambda n: progress(n, name)


def _vo_again(source: Iterable, vo_masks: list, size, camera: Intrinsics, vo_config: VOConfig,
              config: PipelineConfig, timings: dict, occluded: np.ndarray | None,
              progress: Callable[[int], None] | None = None, *, camera_known: bool = False,
              intrinsics_of: Callable | None = None, transform: Callable | None = None):
    """The VO once more over ``source`` (the distinct frames again) with the masks the first pass
    saw, from ``camera`` (not known: the global refinement frees its focal length). Returns
    (the result, None), or (None, why) when the frames cannot be read again or do not come back
    the same: the first pass is a complete result and must not be lost to them. ``progress``:
    called with the frames this pass has finished (:func:`_pass_progress`). ``camera_known``:
    the camera was given (``intrinsics_of(frame)``, when given, is each frame's);
    ``transform(n, image, mask)`` -> (image, mask): what the VO sees of the n-th frame."""
    vo = VisualOdometry(vo_config, size[0], size[1], camera, tracker=config.build_tracker(),
                        camera_known=camera_known, occluded=occluded)
    n = 0
    try:
        for frame, packed in zip(source, vo_masks):
            mask = None if packed is None else \
                np.unpackbits(packed, count=size[0] * size[1]).reshape(size[1], size[0]).astype(bool)
            image = frame.image
            if transform is not None:
                image, mask = transform(n, image, mask)
            vo.step(image, timestamp=frame.timestamp, mask=mask,
                    intrinsics=None if intrinsics_of is None else intrinsics_of(frame))
            n += 1
            if progress is not None:
                progress(n)
    except InputError as exc:
        return None, f"reading the frames again failed ({exc})"
    if n != len(vo_masks):
        return None, f"the frames came back {n} instead of {len(vo_masks)}"
    result = vo.finish()
    for stage, sec in result.timings.items():
        timings[f"vo.{stage}"] = timings.get(f"vo.{stage}", 0.0) + sec
    return result, None


def _start_again(source: Iterable, first: VOResult, vo_masks: list, size, start: Intrinsics,
                 config: PipelineConfig, timings: dict, occluded: np.ndarray | None = None,
                 progress: Callable | None = None) -> tuple[VOResult, VOConfig]:
    """When the VO built no map while its parallax evidence says the camera translated (a slow
    creep), the VO again with the start's ray-angle test (``vo.init_min_parallax_deg``) taken as
    it would be at the widest field of view the focal estimate considers
    (``calibration.hfov_max_deg``). Without intrinsics that angle is measured with a focal length
    nobody confirmed (the guess, when the first frames moved too little to estimate it), and one
    too long makes every angle too small: generated creep 302 (true field of view 73 deg) built
    a map given its camera and none on the 60-degree guess, from the same frames. The start's
    other tests (inliers, the rotation-free parallax in pixels) are as before. Returns the result
    to keep (the first when the new one builds no map either) and the VO settings it ran with;
    ``refine['start_again']`` says what happened."""
    parallax = first.parallax or {}
    if not config.calibration.start_again or first.map_built \
            or parallax.get("conclusion") != "translation":
        return first, config.vo
    wide = Intrinsics.default_for(size[0], size[1], config.calibration.hfov_max_deg).fx
    if wide >= start.fx:
        return first, config.vo
    angle = config.vo.init_min_parallax_deg * wide / start.fx
    vo_config = dataclasses.replace(config.vo, init_min_parallax_deg=angle)
    why = (f"no map was built while the parallax said the camera translated (ratio "
           f"{parallax.get('ratio')}); the start's ray-angle test was taken at a "
           f"{config.calibration.hfov_max_deg:g}-degree field of view: "
           f"{config.vo.init_min_parallax_deg:g} -> {angle:.3f} deg")
    result, failed = _vo_again(source, vo_masks, size, start, vo_config, config, timings, occluded,
                               _pass_progress(progress, "start again"))
    if result is None or not result.map_built:
        first.refine = {**(first.refine or {}), "start_again": (
            f"no: {failed}" if failed else f"tried, no map either: {why}")}
        return first, config.vo
    result.refine = {**(result.refine or {}), "start_again": f"yes: {why}"}
    return result, vo_config


def _second_pass(source: Iterable, first: VOResult, vo_masks: list, size, start: Intrinsics,
                 config: PipelineConfig, timings: dict, occluded: np.ndarray | None = None,
                 vo_config: VOConfig | None = None, progress: Callable | None = None) -> VOResult:
    """The VO again over ``source``, starting from the camera the first pass's global
    refinement found (and refining it again at its end), with ``vo_config`` (default
    ``config.vo``). The first pass built its map on the
    first-frames estimate, and a map built on a focal length 27 % short keeps part of that
    error after the focal length is corrected: Bonn crowd frames 0-449 without calibration,
    10.6 cm ATE after one pass, 3.8 cm after two (3.99 cm with the refined focal length held,
    6.0 cm with the true calibration, one draw each). Holding the refined focal length in the
    second pass was worse on a generated creep (refined +6.8 %: 0.20 % of path against 0.12 %
    when it is refined again). Returns ``first`` unchanged when the focal length moved less
    than ``calibration.second_pass_change``, the frames do not come back the same, or the
    second pass builds no map where the first did; its ``refine`` then says why."""
    refine = dict(first.refine or {})
    f0, f1 = refine.get("focal_start_px"), refine.get("focal_px")
    if f0 is None or f1 is None:
        return first
    change = abs(f1 / f0 - 1.0)
    if change <= config.calibration.second_pass_change:
        refine["second_pass"] = (f"no: the focal length moved {100 * change:.1f} % (<= "
                                 f"{100 * config.calibration.second_pass_change:g} %)")
        first.refine = refine
        return first
    cx, cy = refine.get("centre_px", (start.cx, start.cy))
    result, failed = _vo_again(source, vo_masks, size, Intrinsics(f1, f1, cx, cy),
                               vo_config or config.vo, config, timings, occluded,
                               _pass_progress(progress, "second pass"))
    if result is None:
        refine["second_pass"] = f"no: {failed}"
        first.refine = refine
        return first
    if not result.map_built:
        refine["second_pass"] = (f"no: the focal length moved {100 * change:.1f} % but the VO "
                                 f"run again from it built no map")
        first.refine = refine
        return first
    result.refine = {**(result.refine or {}), "second_pass": (
        f"yes: the focal length moved {100 * change:.1f} % ({f0:.1f} -> {f1:.1f} px); the VO ran "
        f"again from it"), "first_pass": refine}
    if "start_again" in refine:     # how the pass before this one got its map
        result.refine["start_again"] = refine["start_again"]
    return result


def _unrolled_pass(source: Iterable, first: VOResult, vo_masks: list, size, camera: Intrinsics,
                   config: PipelineConfig, timings: dict, *, camera_known: bool,
                   intrinsics_of: Callable | None = None, occluded: np.ndarray | None = None,
                   vo_config: VOConfig | None = None, progress: Callable | None = None) -> VOResult:
    """The VO again over ``source`` with every frame unrolled: shown as the camera of its middle
    row saw it (:func:`mona_vo.rolling_shutter.unroll_maps`), at the readout the first pass's
    global refinement found and the turn rates of its trajectory, masks moved alike. Correcting
    only the global refinement's observations leaves the sliding window's map and tracks to the
    skewed frames (Bonn crowd frames 0-449, the default draw at a readout of 0.9: 3.35 -> 3.01
    cm; the frames unrolled and run again: 1.21 cm; README, Rolling shutter). Returns ``first`` when it found a global shutter, the
    frames do not come back the same, or the pass builds no map; ``refine`` says which."""
    refine = dict(first.refine or {})
    readout = float((refine.get("rolling_shutter") or {}).get("readout", 0.0))
    if readout <= 0:
        return first
    w, h = size
    segment = np.full(len(first.poses), -1, np.int64)
    for k, (a, b) in enumerate(first.map_segments):
        segment[a:b + 1] = k
    rates = turn_rates(first.poses, segment)
    fx = float(refine.get("focal_px", camera.fx))
    fy = fx if "focal_px" in refine else camera.fy
    cx, cy = refine.get("centre_px", (camera.cx, camera.cy))
    K = np.array([fx, fy, cx, cy])

    def unroll(n: int, image: np.ndarray, mask: np.ndarray | None):
        if not rates[n].any():
            return image, mask
        mx, my = unroll_maps(rates[n], readout, K, w, h)
        image = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if mask is not None:
            mask = cv2.remap(mask.astype(np.uint8), mx, my, cv2.INTER_NEAREST,
                             borderMode=cv2.BORDER_REPLICATE).astype(bool)
        return image, mask

    # The first estimate runs on skewed frames, whose tracks fit a global shutter better than
    # the truth does, so it falls short (README, Rolling shutter, stop 58): the second pass
    # looks for the readout left over.
    again = dataclasses.replace(vo_config or config.vo, rolling_shutter="residual",
                                rolling_shutter_readout=readout)
    start = camera if camera_known else Intrinsics(fx, fy, cx, cy)
    result, failed = _vo_again(source, vo_masks, size, start, again, config, timings, occluded,
                               _pass_progress(progress, "rolling shutter"),
                               camera_known=camera_known, intrinsics_of=intrinsics_of,
                               transform=unroll)
    why = f"readout {readout:g} of the frame interval"
    if result is None or not result.map_built:
        failed = failed or "the VO run again on the unrolled frames built no map"
        refine["unrolled_pass"] = f"no: {failed} ({why})"
        first.refine = refine
        return first
    left = dict((result.refine or {}).get("rolling_shutter") or {})
    residual = float(left.pop("readout", 0.0))
    shutter = {**refine["rolling_shutter"], "readout": round(readout + residual, 4),
               "first_estimate": readout, "residual": {"readout": residual, **left}}
    result.refine = {**(result.refine or {}), "rolling_shutter": shutter,
                     "unrolled_pass": f"yes: {why}; the VO ran again on the unrolled frames",
                     "before_unrolling": refine}
    return result


def _with_repeats(vo: VOResult, rows: np.ndarray, repeat_of: np.ndarray,
                  timestamps: list[float]) -> VOResult:
    """The VO's result (one row per distinct frame) as one row per input frame: a repeat
    takes its frame's pose and status, is no keyframe, and keeps its own timestamp."""
    segments = [(int(np.searchsorted(rows, a)), int(np.searchsorted(rows, b, side="right")) - 1)
                for a, b in vo.map_segments]
    return dataclasses.replace(vo, timestamps=np.asarray(timestamps, np.float64),
                               poses=vo.poses[rows], is_keyframe=vo.is_keyframe[rows] & (repeat_of < 0),
                               status=[vo.status[r] for r in rows], inliers=vo.inliers[rows],
                               map_segments=segments,
                               poses_streaming=None if vo.poses_streaming is None
                               else vo.poses_streaming[rows])


@dataclass
class Stream:
    """The frames as a run sees them (:func:`open_stream`)."""

    frames: Iterable            # what the run reads: each frame's picture, the head replayed
    source: Iterable            # the same frames to read again (a second pass)
    rereadable: bool            # whether ``source`` can be read again (not an iterator)
    picture: PictureArea | None  # the picture found (crop_bars; the whole frame without bars)
    intrinsics: Any             # the caller's intrinsics, in the picture's pixels (pinhole)
    calibration: Any            # the focal-length estimate without intrinsics, else None
    overlay: np.ndarray | None = None  # the picture's pixels painted over (hide_overlays)
    lens: Undistortion | None = None   # a distorted camera's frames resampled to its pinhole

    @property
    def cut(self) -> PictureArea | None:
        """The picture when bars were cut off, else None."""
        return self.picture if self.picture is not None and not self.picture.is_whole else None

    def full_mask(self, mask):
        """A mask of the run's picture as one of the frame as given (lens, then bars)."""
        if self.lens is not None:
            mask = self.lens.unmask(mask)
        return mask if self.cut is None or mask is None else self.cut.uncrop(mask)


def open_stream(frames: Iterable, intrinsics, config: PipelineConfig) -> Stream:
    """Find the picture inside bars, burned-in overlays in it and, without intrinsics, the focal
    length, each from the first frames (read ahead, then replayed): everything after sees the
    picture alone, overlays painted over."""
    source = frames
    rereadable = iter(source) is not source
    picture = None
    if config.crop_bars:
        # Everything from here on sees the picture alone: masks, focal-length estimate, VO.
        frames, picture = crop_to_picture(frames)
    if picture is not None and not picture.is_whole:
        source = crop_frames(source, picture)
        intrinsics = _intrinsics_in_picture(intrinsics, picture)
    lens = None
    if isinstance(intrinsics, LensIntrinsics) and not intrinsics.distortion.is_zero:
        # From here on the camera is a pinhole: the frames are resampled to it once.
        lens = Undistortion(intrinsics)
        frames, source = undistort_frames(frames, lens), undistort_frames(source, lens)
        intrinsics = lens.intr
    overlay = None
    if config.hide_overlays:
        frames, overlay = overlay_ahead(frames)
        if overlay is not None:
            frames, source = hide_overlay(frames, overlay), hide_overlay(source, overlay)
    calibration = None
    if intrinsics is None and config.calibration.mode == "estimate":
        # Without intrinsics the focal length comes from the first frames (read ahead, then
        # replayed); the VO uses it, the report says how it was found.
        frames, calibration = estimate_focal_ahead(frames, config)
    return Stream(frames, source, rereadable, picture, intrinsics, calibration, overlay, lens)


class _Recorder:
    """Takes each frame once its mask is known, in order: hands it to ``on_frame`` and to the VO
    (a repeat, :mod:`mona_vo.repeats`, only to ``on_frame``) and keeps what the result needs."""

    def __init__(self, config: PipelineConfig, stream: Stream, on_frame, progress, tracker):
        self.config, self.stream, self.on_frame, self.progress = config, stream, on_frame, progress
        self.tracker = tracker              # the VO's, built before the stream was opened
        self.vo: VisualOdometry | None = None
        self.first_intr: Intrinsics | None = None
        self.size: tuple[int, int] | None = None        # (W, H) of the picture
        self.names: list[str] = []
        self.coverage: list[float] = []
        self.stamps: list[float] = []
        self.rows: list[int] = []           # the VO row of each frame (a repeat: its frame's)
        self.repeat_of: list[int] = []      # the frame each frame repeats, -1: its own
        # Without intrinsics the VO may run twice (_second_pass); the masks it saw are kept for
        # that, packed to a bit per pixel.
        self.may_rerun = (stream.intrinsics is None and config.vo.refine == "global"
                          and config.vo.global_camera != "none" and stream.rereadable)
        # ... and again on the frames unrolled when the global refinement finds a rolling
        # shutter (_unrolled_pass; `residual` is that pass's own setting: its frames are
        # unrolled already).
        self.may_unroll = (config.vo.refine == "global"
                           and config.vo.rolling_shutter in ("estimate", "given")
                           and stream.rereadable)
        self.vo_masks: list = []

    def add(self, frame, repeat: bool, mask, mona=None, vo_mask=None) -> None:
        # vo_mask: what the VO sees; MONA's masks reach it only when reliable
        # (MaskFrame.reliable: not too large, not flickering), else the VO relies on its own
        # residual test for that frame. Caller masks are used as given.
        if mona is None:
            vo_mask = mask
        full_mask = self.stream.full_mask(mask)
        pic = self.stream.cut
        if self.on_frame is not None:
            self.on_frame(FrameOutput(frame.index, frame.name, frame.timestamp,
                                      getattr(frame, "full", frame.image), full_mask, mona,
                                      (pic.x0, pic.y0) if pic is not None else (0, 0)))
        if repeat:
            self.rows.append(self.rows[-1])
            last = self.repeat_of[-1]
            self.repeat_of.append(last if last >= 0 else len(self.names) - 1)
        else:
            self._step(frame, vo_mask)
            self.rows.append(self.rows[-1] + 1 if self.rows else 0)
            self.repeat_of.append(-1)
        self.stamps.append(frame.timestamp)
        self.names.append(frame.name)
        self.coverage.append(float(full_mask.mean()) if full_mask is not None else 0.0)
        if self.progress is not None:
            self.progress(len(self.names))

    def _step(self, frame, vo_mask) -> None:
        intr = _intrinsics_for(self.stream.intrinsics, frame, *self.size)
        if self.vo is None:
            self.first_intr = intr or camera_without_calib(self.stream.calibration, self.config,
                                                           *self.size)
            self.vo = VisualOdometry(self.config.vo, self.size[0], self.size[1], self.first_intr,
                                     tracker=self.tracker,
                                     camera_known=intr is not None, occluded=self.stream.overlay)
        self.vo.step(frame.image, timestamp=frame.timestamp, mask=vo_mask, intrinsics=intr)
        if self.may_rerun or self.may_unroll:
            self.vo_masks.append(None if vo_mask is None else np.packbits(vo_mask))

    def finish(self, timings: dict) -> VOResult:
        where = getattr(self.stream.source, "path", None)
        where = f"{where}: " if where is not None else ""
        if self.vo is None or len(self.names) < 2:
            raise InputError(f"{where}a trajectory needs at least 2 frames; the input has "
                             f"{len(self.names)}")
        result = self.vo.finish()
        for stage, sec in result.timings.items():
            timings[f"vo.{stage}"] = sec
        repeat_of = np.array(self.repeat_of, np.int64)

        def distinct():
            return (f for f, r in zip(self.stream.source, repeat_of) if r < 0)

        vo_config = self.config.vo
        if self.may_rerun:
            result, vo_config = _start_again(distinct(), result, self.vo_masks, self.size,
                                             self.first_intr, self.config, timings,
                                             occluded=self.stream.overlay, progress=self.progress)
            result = _second_pass(distinct(), result, self.vo_masks, self.size, self.first_intr,
                                  self.config, timings, occluded=self.stream.overlay,
                                  vo_config=vo_config, progress=self.progress)
        if self.may_unroll:
            known = self.stream.intrinsics is not None
            result = _unrolled_pass(
                distinct(), result, self.vo_masks, self.size, self.first_intr, self.config,
                timings, camera_known=known, occluded=self.stream.overlay, vo_config=vo_config,
                intrinsics_of=(lambda f: _intrinsics_for(self.stream.intrinsics, f, *self.size))
                if known else None, progress=self.progress)
        if (repeat_of >= 0).any():
            result = _with_repeats(result, np.array(self.rows), repeat_of, self.stamps)
        return result


def estimate_trajectory(frames: Iterable, *, intrinsics=None, masks=None,
                        config: PipelineConfig | None = None,
                        on_frame: Callable[[FrameOutput], None] | None = None,
                        progress: Callable[..., None] | None = None,
                        detector=None) -> RunResult:
    """Camera trajectory of a frame stream.

    frames:     iterable of objects with ``index``, ``timestamp``, ``name``, ``image`` ((H, W, 3)
                uint8 RGB), e.g. ``data_tools.frames.open_frames(path)``.
    intrinsics: None (a guess from ``config.assumed_hfov_deg``), one Intrinsics, a per-frame sequence or
                dict by frame index, or a callable ``frame -> Intrinsics``.
    masks:      None, ``"mona"``, an iterable of (H, W) bool aligned with the frames, or a
                callable ``frame -> mask``.
    on_frame:   called with a :class:`FrameOutput` for every frame, in order.
    progress:   called with the number of frames finished so far (for a progress bar), and
                during a later VO pass over the same frames (without intrinsics: ``_start_again``,
                ``_second_pass``) with the count from 0 again, as ``progress(frames, name)``
                when it takes a second argument.
    detector:   a :class:`mona_vo.detection.Detector` instance for MONA in place of the one
                ``config.masks.detector`` names (benchmarks: a detector that reads the truth).
    """
    config = config or PipelineConfig()
    config.validate()
    t_start = time.perf_counter()
    if isinstance(masks, str) and masks != "mona":
        raise ConfigError(f"masks must be 'mona', None, an iterable or a callable, not '{masks}'")
    use_mona = masks == "mona"
    # The back ends are built before a frame is read, so that a missing checkpoint fails at
    # once, not after the focal length was estimated from the first frames.
    backends = config.masker_backends(detector) if use_mona else None
    tracker = config.build_tracker()
    stream = open_stream(frames, intrinsics, config)
    caller = _CallerMasks(masks, stream.cut, stream.lens) if masks is not None and not use_mona \
        else None
    rec = _Recorder(config, stream, on_frame, progress, tracker)
    repeats = RepeatDetector(config.repeat_max_diff)
    timings: dict[str, float] = {}
    masker = None
    pending: deque = deque()   # (frame, repeat) waiting for its MONA mask

    def drain(mask_frames):
        for mf in mask_frames:
            frame, repeat = pending.popleft()
            if mf.index != frame.index:
                raise RuntimeError(f"mask for frame {mf.index} arrived for frame {frame.index}")
            for stage, sec in (getattr(mf, "seconds", None) or {}).items():
                key = f"masks.{stage}"
                timings[key] = timings.get(key, 0.0) + sec
            rec.add(frame, repeat, mf.mask, mf, getattr(mf, "vo_mask", mf.mask))

    full_size = None
    for frame in stream.frames:
        h, w = getattr(frame, "full", frame.image).shape[:2]
        if full_size is None:
            full_size = (w, h)
        elif full_size != (w, h):
            raise InputError(f"frame {frame.name} is {w} x {h}, earlier frames are "
                             f"{full_size[0]} x {full_size[1]}")
        h, w = frame.image.shape[:2]
        rec.size = (w, h)
        repeat = repeats.is_repeat(frame.image)
        if not use_mona:
            rec.add(frame, repeat, caller.get(frame) if caller is not None else None)
            continue
        if masker is None:
            from mona_vo.masks import MonaMasker

            # MONA's camera model uses the intrinsics when known, else the VO's camera.
            masker = MonaMasker(config.masks, _intrinsics_for(stream.intrinsics, frame, w, h)
                                or camera_without_calib(stream.calibration, config, w, h),
                                ignore=stream.overlay, **backends)
        pending.append((frame, repeat))
        drain(masker.push_repeat(frame.index) if repeat else masker.push(frame.index, frame.image))
    if masker is not None:
        drain(masker.flush())
    result = rec.finish(timings)
    timings["total"] = time.perf_counter() - t_start
    if stream.calibration is not None:
        timings["calibration"] = stream.calibration.seconds
    cut = stream.cut
    return RunResult(result, rec.names, full_size[0], full_size[1],
                     cut.to_frame(rec.first_intr) if cut is not None else rec.first_intr, timings,
                     np.array(rec.coverage), stream.calibration, stream.picture,
                     repeat_of=np.array(rec.repeat_of, np.int64),
                     overlay=stream.full_mask(stream.overlay),
                     lens=None if stream.lens is None else {
                         "distortion": stream.lens.lens.distortion.as_dict(),
                         "undistorted_shift_px": stream.lens.shift_px()})
