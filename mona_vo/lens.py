"""Lens distortion, taken out of the frames where a run first reads them.

Everything after this module is a pinhole camera (:mod:`mona_vo.conventions`): tracks, masks,
the two-view geometry, PnP and the bundle adjustment all project with fx, fy, cx, cy alone. A
calibrated lens whose distortion is known (OpenCV's radial-tangential model: k1, k2, p1, p2,
k3, the order of OpenCV, DPVO's ``calib.txt`` and TUM's d0-d4) is therefore handled once, on the
images: each frame is resampled to the pinhole camera with the same K, and masks found on the
undistorted pictures are mapped back to the frames as given, so what a run writes lines up with
its input. Left in, Bonn's published k1, k2 move a pixel 0.7 px at the median and 3.8 px at the
corners, a systematic bend every track keeps (README, Known limits).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.conventions import Intrinsics
from mona_vo.picture_area import PictureFrame

COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Distortion:
    """OpenCV's radial-tangential distortion, in normalised image coordinates (so the same for
    any image scale or crop)."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @classmethod
    def from_numbers(cls, numbers) -> "Distortion":
        """From up to five numbers in OpenCV's order (the missing ones are 0)."""
        numbers = [float(v) for v in numbers]
        if len(numbers) > len(COEFFICIENTS):
            raise ValueError(f"at most {len(COEFFICIENTS)} distortion coefficients "
                             f"({' '.join(COEFFICIENTS)}), got {len(numbers)}")
        return cls(*numbers)

    @property
    def coeffs(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], np.float64)

    @property
    def is_zero(self) -> bool:
        return not np.any(self.coeffs)

    def check(self) -> list[str]:
        if not np.all(np.isfinite(self.coeffs)):
            return ["distortion coefficients are not finite numbers"]
        return []

    def as_dict(self) -> dict:
        return dict(zip(COEFFICIENTS, (float(v) for v in self.coeffs)))


@dataclass(frozen=True)
class LensIntrinsics(Intrinsics):
    """Intrinsics of a camera whose frames are distorted: the pinhole part and the lens. Anything
    that takes :class:`Intrinsics` takes these; :func:`mona_vo.pipeline.open_stream` undistorts
    the frames and hands the rest of the run the pinhole part (:meth:`pinhole`)."""

    distortion: Distortion = Distortion()

    def pinhole(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy)

    def check(self, width: int | None = None, height: int | None = None) -> list[str]:
        return super().check(width, height) or self.distortion.check()


def camera(intr: Intrinsics, distortion: Distortion | None) -> Intrinsics:
    """``intr`` with ``distortion``: a LensIntrinsics when there is any, else plain Intrinsics."""
    if distortion is None or distortion.is_zero:
        return Intrinsics(intr.fx, intr.fy, intr.cx, intr.cy)
    return LensIntrinsics(intr.fx, intr.fy, intr.cx, intr.cy, distortion)


class Undistortion:
    """Resampling between the frames as given (distorted) and the pinhole camera with the same K.
    The maps are made for the first size asked and kept (a run's frames share one size)."""

    def __init__(self, lens: LensIntrinsics):
        self.lens, self.intr = lens, lens.pinhole()
        self._size = None

    def maps(self, width: int, height: int):
        """(pinhole -> frame x, y; frame -> pinhole x, y) float32 maps for cv2.remap at this size."""
        if self._size != (width, height):
            K, D = self.intr.K, self.lens.distortion.coeffs
            # pinhole pixel -> distorted pixel: what each undistorted pixel samples
            self._fx, self._fy = cv2.initUndistortRectifyMap(K, D, None, K, (width, height),
                                                             cv2.CV_32FC1)
            # distorted pixel -> pinhole pixel: where each pixel of a frame as given lands
            grid = np.stack(np.meshgrid(np.arange(width, dtype=np.float64),
                                        np.arange(height, dtype=np.float64)), -1).reshape(-1, 1, 2)
            und = cv2.undistortPointsIter(grid, K, D, None, K, (cv2.TERM_CRITERIA_COUNT |
                                                              cv2.TERM_CRITERIA_EPS, 40, 1e-6))
            und = und.reshape(height, width, 2).astype(np.float32)
            self._bx, self._by = und[..., 0].copy(), und[..., 1].copy()
            self._size = (width, height)
        return self._fx, self._fy, self._bx, self._by

    def image(self, image: np.ndarray) -> np.ndarray:
        """A frame as given -> the pinhole camera's picture (bilinear; edge pixels repeated where
        the lens saw nothing)."""
        h, w = image.shape[:2]
        fx, fy, _, _ = self.maps(w, h)
        return cv2.remap(image, fx, fy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """A bool mask on a frame as given -> on the pinhole picture (nearest)."""
        h, w = mask.shape
        fx, fy, _, _ = self.maps(w, h)
        out = cv2.remap(mask.astype(np.uint8), fx, fy, cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out.astype(bool)

    def unmask(self, mask: np.ndarray | None) -> np.ndarray | None:
        """A bool mask on the pinhole picture -> on the frame as given (nearest)."""
        if mask is None:
            return None
        h, w = mask.shape
        _, _, bx, by = self.maps(w, h)
        out = cv2.remap(mask.astype(np.uint8), bx, by, cv2.INTER_NEAREST,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out.astype(bool)

    def distort(self, image: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`image`: a pinhole picture as this lens would have given it (for
        benchmarks and tests that render pinhole frames)."""
        h, w = image.shape[:2]
        _, _, bx, by = self.maps(w, h)
        return cv2.remap(image, bx, by, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def shift_px(self) -> dict | None:
        """How far the lens moves a pixel (median, 90th percentile, largest), px; None before
        the first frame."""
        if self._size is None:
            return None
        w, h = self._size
        d = np.hypot(self._fx - np.arange(w)[None, :], self._fy - np.arange(h)[:, None])
        return {"median": round(float(np.median(d)), 3),
                "p90": round(float(np.percentile(d, 90)), 3), "max": round(float(d.max()), 3)}


class undistort_frames:
    """``frames`` (objects with index, timestamp, name, image) on the pinhole camera, as
    :class:`PictureFrame` (``full``: the frame as given, what outputs line up with).
    Re-iterable when ``frames`` is, so a second VO pass reads the same pictures."""

    def __init__(self, frames, undistortion: Undistortion):
        self.frames, self.undistortion = frames, undistortion

    def __iter__(self):
        for f in self.frames:
            yield PictureFrame(f.index, f.timestamp, f.name, self.undistortion.image(f.image),
                               getattr(f, "full", f.image))
