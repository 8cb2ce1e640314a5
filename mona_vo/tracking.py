"""Point tracks: one interface, back ends by name (``TRACKERS``).

A tracker is fed one frame at a time (frames stream, memory stays flat). It owns a set of live
tracks, each with a stable integer id. ``add_points`` starts tracks at the current frame;
``step(image)`` advances every live track to the new frame and returns where they are. A track
that the tracker judges lost (occluded, left the image, failed its visibility check) is reported
once with ``visible=False`` and then forgotten.

Default back end ``lk``: pyramidal Lucas-Kanade with a forward-backward check as the visibility
test, started from each track's constant-velocity prediction so that fast pans (tens of pixels
per frame) stay inside LK's capture range.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.registry import Registry

TRACKERS = Registry("tracker")


@dataclass(frozen=True)
class TrackUpdate:
    """Where the live tracks are in the current frame.

    ids:     (N,) int64 track ids.
    points:  (N, 2) float32 pixels x, y (pixel centres at integers).
    visible: (N,) bool; False marks a track lost at this frame (it is dropped afterwards).
    error:   (N,) float32 tracking uncertainty in pixels (LK: forward-backward distance).
    """

    ids: np.ndarray
    points: np.ndarray
    visible: np.ndarray
    error: np.ndarray


def to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image from (H, W, 3) uint8 RGB (or pass a grey image through)."""
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


_GAIN_STEP = 4   # brightness maps are 4x smaller than the image, then 7 x 7 box means (~28 px)


def brightness_map(gray: np.ndarray) -> np.ndarray:
    """Local mean grey levels of an (H, W) image, 4x downsampled, for :func:`exposure_gain`
    (computed once per frame: each frame is the next one's reference)."""
    h, w = gray.shape
    size = (max(w // _GAIN_STEP, 1), max(h // _GAIN_STEP, 1))
    return cv2.blur(cv2.resize(gray.astype(np.float32), size, interpolation=cv2.INTER_AREA), (7, 7))


def exposure_gain(prev_map: np.ndarray, now_map: np.ndarray, pts_prev: np.ndarray,
                  pts_now: np.ndarray, *, min_points: int = 20) -> float:
    """Brightness ratio now / prev of the same surfaces: the median over points tracked from
    ``pts_prev`` (in prev) to about ``pts_now`` (in now; a prediction is enough) of the ratio of
    the local mean grey levels around them (:func:`brightness_map` of each frame; boxes of about
    28 px, so a few pixels of prediction error do not matter). Measured on matched points, not
    on whole images, so that a pan onto brighter scenery is not taken for an exposure change;
    the median ignores movers and saturated or dark spots. 1.0 with fewer than ``min_points``
    usable points."""
    def at(m, pts):
        c = np.clip((pts[:, 0] / _GAIN_STEP).astype(int), 0, m.shape[1] - 1)
        r = np.clip((pts[:, 1] / _GAIN_STEP).astype(int), 0, m.shape[0] - 1)
        return m[r, c].astype(np.float64)

    a, b = at(prev_map, pts_prev), at(now_map, pts_now)
    ok = (a > 8) & (a < 247) & (b > 8) & (b < 247)
    if ok.sum() < min_points:
        return 1.0
    return float(np.median(b[ok] / a[ok]))


def track_forward_backward(prev: np.ndarray, nxt: np.ndarray, pts: np.ndarray, guess: np.ndarray,
                           win: tuple[int, int], levels: int, criteria: tuple
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade of the (N, 2) ``pts`` of ``prev`` into ``nxt``, started at
    ``guess``, and back again (started where they landed). Returns their (N, 2) float32
    positions in ``nxt``, (N,) bool found both ways, and (N,) float32 distance from where the
    backward track lands to where it started (px): what a tracker's forward-backward check
    compares with its bound."""
    p0 = np.asarray(pts, np.float32).reshape(-1, 1, 2)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, nxt, p0, np.asarray(guess, np.float32).reshape(-1, 1, 2),
                                          winSize=win, maxLevel=levels, criteria=criteria,
                                          flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    p0b, st2, _ = cv2.calcOpticalFlowPyrLK(nxt, prev, p1, None, winSize=win, maxLevel=levels,
                                           criteria=criteria)
    p1 = p1.reshape(-1, 2)
    fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1).astype(np.float32)
    return p1, (st1.ravel() == 1) & (st2.ravel() == 1), fb


class Tracker(ABC):
    """Frame-to-frame point tracker with persistent track ids. ``takes_corrections``: the back
    end chains its tracks from frame to frame, :meth:`move` puts them where a caller measured
    them better and :meth:`revive` starts a lost one again (False: both change nothing)."""

    takes_corrections = False

    @abstractmethod
    def step(self, image: np.ndarray) -> TrackUpdate:
        """Advance to the next frame ((H, W, 3) uint8 RGB or (H, W) grey). The first call only
        sets the frame and returns an empty update."""

    @abstractmethod
    def add_points(self, points: np.ndarray) -> np.ndarray:
        """Start tracks at (N, 2) pixels of the current frame; returns their (N,) int64 ids."""

    @abstractmethod
    def remove(self, ids: np.ndarray) -> None:
        """Stop tracking these ids."""

    @abstractmethod
    def live(self) -> TrackUpdate:
        """The live tracks at the current frame."""

    def move(self, ids: np.ndarray, points: np.ndarray) -> bool:
        """Put live tracks at corrected (N, 2) pixels of the current frame (a caller that
        measured them better, mona_vo.patch_align). Returns ``takes_corrections``: False,
        changing nothing, when the back end cannot take corrections."""
        return False

    def revive(self, ids: np.ndarray, points: np.ndarray) -> bool:
        """Start tracks again under earlier ids (not live now) at (N, 2) pixels of the current
        frame: a landmark found again where its track had been lost (an occluder passed).
        Returns ``takes_corrections``: False, changing nothing, when the back end cannot."""
        return False


@TRACKERS.register("lk")
class LKTracker(Tracker):
    """Pyramidal Lucas-Kanade (OpenCV) with forward-backward consistency as visibility.

    win_size:     LK window side, pixels.
    levels:       pyramid levels above the base; motion up to ~win_size * 2**levels px is caught.
    fb_max_px:    a track whose backward-tracked point lands further than this from its start is
                  lost (occlusion, drift onto another surface, aperture problem).
    border_px:    tracks closer than this to the image border are lost (LK windows get clipped).
    gain:         compensate a global exposure change (:func:`exposure_gain`) before tracking:
                  LK assumes constant brightness, auto exposure scales the whole image, and a
                  gain stays a gain after gamma encoding.
    """

    GAIN_TOLERANCE = 0.01   # smaller brightness changes are left alone: a rescaled 8-bit image
                             # is requantised, which costs more than a 1 % change
    takes_corrections = True

    def __init__(self, win_size: int = 21, levels: int = 3, fb_max_px: float = 0.7,
                 border_px: float = 4.0, iterations: int = 30, gain: bool = True):
        self.win = (int(win_size), int(win_size))
        self.levels = int(levels)
        self.fb_max_px = float(fb_max_px)
        self.border_px = float(border_px)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, int(iterations), 0.01)
        self.gain = bool(gain)
        self._pyr = None
        self._map = None       # brightness_map of the current frame, the next one's reference
        self._shape = None
        self._ids = np.zeros(0, np.int64)
        self._pts = np.zeros((0, 2), np.float32)
        self._err = np.zeros(0, np.float32)
        self._vel = np.zeros((0, 2), np.float32)   # last image motion of each track, px/frame
        self._next_id = 0

    def live(self) -> TrackUpdate:
        return TrackUpdate(self._ids.copy(), self._pts.copy(), np.ones(len(self._ids), bool),
                           self._err.copy())

    def add_points(self, points: np.ndarray) -> np.ndarray:
        points = np.asarray(points, np.float32).reshape(-1, 2)
        ids = np.arange(self._next_id, self._next_id + len(points), dtype=np.int64)
        self._next_id += len(points)
        self._append(ids, points)
        return ids

    def _append(self, ids: np.ndarray, points: np.ndarray) -> None:
        self._ids = np.concatenate([self._ids, ids])
        self._pts = np.concatenate([self._pts, points])
        self._err = np.concatenate([self._err, np.zeros(len(points), np.float32)])
        # A new track starts with the typical motion of the others (the camera's, mostly).
        v0 = np.median(self._vel, axis=0) if len(self._vel) else np.zeros(2, np.float32)
        self._vel = np.concatenate([self._vel, np.tile(v0, (len(points), 1)).astype(np.float32)])

    def remove(self, ids: np.ndarray) -> None:
        keep = ~np.isin(self._ids, ids)
        self._ids, self._pts, self._err = self._ids[keep], self._pts[keep], self._err[keep]
        self._vel = self._vel[keep]

    def move(self, ids: np.ndarray, points: np.ndarray) -> bool:
        _, i, j = np.intersect1d(self._ids, np.asarray(ids, np.int64), return_indices=True)
        self._pts[i] = np.asarray(points, np.float32).reshape(-1, 2)[j]
        return True

    def revive(self, ids: np.ndarray, points: np.ndarray) -> bool:
        ids = np.asarray(ids, np.int64)
        if np.isin(ids, self._ids).any() or (len(ids) and ids.max() >= self._next_id):
            raise ValueError("revive takes ids this tracker handed out that are not live")
        self._append(ids, np.asarray(points, np.float32).reshape(-1, 2))
        return True

    def step(self, image: np.ndarray) -> TrackUpdate:
        # OpenCV's Python binding cannot take prebuilt pyramids, so each call builds its own.
        gray = to_gray(image)
        prev, self._pyr = self._pyr, gray
        if self.gain:
            prev_map, self._map = self._map, brightness_map(gray)
        pyr = gray
        if prev is None or self._shape != gray.shape or len(self._ids) == 0:
            self._shape = gray.shape
            if prev is not None and len(self._ids) and self._shape != gray.shape:
                self.remove(self._ids)
            return self.live()
        p0 = self._pts.reshape(-1, 1, 2)
        guess = (self._pts + self._vel).reshape(-1, 1, 2)
        if self.gain:
            g = exposure_gain(prev_map, self._map, self._pts, guess.reshape(-1, 2))
            # The brighter image is scaled down, so that no grey level clips at 255.
            if g > 1.0 + self.GAIN_TOLERANCE:
                pyr = cv2.convertScaleAbs(gray, alpha=1.0 / g)
            elif g < 1.0 - self.GAIN_TOLERANCE:
                prev = cv2.convertScaleAbs(prev, alpha=g)
        p1, found, fb = track_forward_backward(prev, pyr, p0, guess, self.win, self.levels,
                                               self.criteria)
        h, w = gray.shape
        b = self.border_px
        inside = (p1[:, 0] >= b) & (p1[:, 0] <= w - 1 - b) & (p1[:, 1] >= b) & (p1[:, 1] <= h - 1 - b)
        ok = found & (fb <= self.fb_max_px) & inside
        ok &= np.isfinite(p1).all(axis=1)
        update = TrackUpdate(self._ids.copy(), p1.astype(np.float32), ok, fb)
        self._vel = (p1 - self._pts)[ok].astype(np.float32)
        self._ids, self._pts, self._err = self._ids[ok], p1[ok].astype(np.float32), fb[ok]
        return update


TRACKERS.register("cotracker", "mona_vo.neural.cotracker:CoTrackerTracker")
