"""The one call: frames in, a pose for every frame out, with moving-object masks in between.

``estimate_trajectory(frames, intrinsics=..., masks=..., config=...)`` streams the frames once.
Masks come from MONA (``masks="mona"``, computed on the fly with a short look-ahead), from the
caller (an iterable aligned with the frames, or a callable ``frame -> mask``), or not at all.
Nothing is written here; ``on_frame`` lets the caller store masks or draw overlays as frames
finish, so memory stays flat however long the video is.
"""
from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from mona_vo.conventions import Intrinsics
from mona_vo.errors import ConfigError, InputError
from mona_vo.vo import VOConfig, VOResult, VisualOdometry


def _mask_config_default():
    from mona_vo.masks import MaskConfig

    return MaskConfig()


@dataclass(frozen=True)
class PipelineConfig:
    vo: VOConfig = field(default_factory=VOConfig)
    masks: Any = field(default_factory=_mask_config_default)  # mona_vo.masks.MaskConfig

    def validate(self) -> None:
        self.vo.validate()
        v = getattr(self.masks, "validate", None)
        if callable(v):
            v()


@dataclass
class FrameOutput:
    """Handed to ``on_frame`` once a frame's mask is known (before the VO has seen it)."""

    index: int
    name: str
    timestamp: float
    image: np.ndarray               # (H, W, 3) uint8 RGB
    mask: np.ndarray | None         # (H, W) bool moving-object mask, None without masks
    mona: Any = None                # mona_vo.masks.MaskFrame when MONA computed the mask


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


class _CallerMasks:
    """Masks given by the caller: an iterable aligned with the frames, or a callable."""

    def __init__(self, masks):
        self.fn = masks if callable(masks) else None
        self.it = None if callable(masks) else iter(masks)

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
        if m.shape != frame.image.shape[:2]:
            raise InputError(f"mask for frame {frame.name} is {m.shape[1]} x {m.shape[0]}, "
                             f"the frame is {frame.image.shape[1]} x {frame.image.shape[0]}")
        return m


def estimate_trajectory(frames: Iterable, *, intrinsics=None, masks=None,
                        config: PipelineConfig | None = None,
                        on_frame: Callable[[FrameOutput], None] | None = None,
                        progress: Callable[[int], None] | None = None) -> RunResult:
    """Camera trajectory of a frame stream.

    frames:     iterable of objects with ``index``, ``timestamp``, ``name``, ``image`` ((H, W, 3)
                uint8 RGB), e.g. ``data_tools.frames.open_frames(path)``.
    intrinsics: None (a 60-degree field-of-view guess), one Intrinsics, a per-frame sequence or
                dict by frame index, or a callable ``frame -> Intrinsics``.
    masks:      None, ``"mona"``, an iterable of (H, W) bool aligned with the frames, or a
                callable ``frame -> mask``.
    on_frame:   called with a :class:`FrameOutput` for every frame, in order.
    progress:   called with the number of frames finished so far (for a progress bar).
    """
    config = config or PipelineConfig()
    config.validate()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    vo: VisualOdometry | None = None
    names: list[str] = []
    coverage: list[float] = []
    first_intr: Intrinsics | None = None
    size = None

    masker = None
    use_mona = False
    caller = None
    if isinstance(masks, str):
        if masks != "mona":
            raise ConfigError(f"masks must be 'mona', None, an iterable or a callable, not '{masks}'")
        use_mona = True
    elif masks is not None:
        caller = _CallerMasks(masks)

    pending: deque = deque()   # frames waiting for their MONA mask

    def feed(frame, mask, mona=None):
        nonlocal vo, first_intr
        intr = _intrinsics_for(intrinsics, frame, *size)
        if vo is None:
            first_intr = intr or Intrinsics.default_for(*size)
            vo = VisualOdometry(config.vo, size[0], size[1], first_intr)
        if on_frame is not None:
            on_frame(FrameOutput(frame.index, frame.name, frame.timestamp, frame.image, mask, mona))
        vo.step(frame.image, timestamp=frame.timestamp, mask=mask, intrinsics=intr)
        names.append(frame.name)
        coverage.append(float(mask.mean()) if mask is not None else 0.0)
        if progress is not None:
            progress(len(names))

    def drain(mask_frames):
        for mf in mask_frames:
            frame = pending.popleft()
            if mf.index != frame.index:
                raise RuntimeError(f"mask for frame {mf.index} arrived for frame {frame.index}")
            for stage, sec in (getattr(mf, "seconds", None) or {}).items():
                key = f"masks.{stage}"
                timings[key] = timings.get(key, 0.0) + sec
            feed(frame, mf.mask, mf)

    for frame in frames:
        h, w = frame.image.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise InputError(f"frame {frame.name} is {w} x {h}, earlier frames are {size[0]} x {size[1]}")
        if use_mona:
            if masker is None:
                from mona_vo.masks import MonaMasker

                # MONA's camera model uses the intrinsics when known (a guess otherwise).
                masker = MonaMasker(config.masks, _intrinsics_for(intrinsics, frame, w, h))
            pending.append(frame)
            drain(masker.push(frame.index, frame.image))
        else:
            feed(frame, caller.get(frame) if caller is not None else None)
    if masker is not None:
        drain(masker.flush())
    if vo is None or len(names) < 2:
        where = getattr(frames, "path", None)
        raise InputError(f"{str(where) + ': ' if where is not None else ''}a trajectory needs at "
                         f"least 2 frames; the input has {len(names)}")
    result = vo.finish()
    for stage, sec in result.timings.items():
        timings[f"vo.{stage}"] = sec
    timings["total"] = time.perf_counter() - t_start
    return RunResult(result, names, size[0], size[1], first_intr, timings, np.array(coverage))
