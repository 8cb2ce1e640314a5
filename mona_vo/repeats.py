"""Repeated frames: a frame that shows the last distinct frame again carries nothing new.

Online videos repeat frames: a 24 frame/s film shown at 30 repeats every fourth frame
(pulldown), a 25 frame/s clip at 30 every fifth, a stalled stream or screen capture holds one
for a while. Decoded, a repeat is the frame it repeats, up to the coder's requantisation. Fed
to the pipeline it is a frame without motion between two frames with motion: the VO's
constant-velocity prediction misses twice, and the masks' flow statistics and accumulated
evidence see a mover stop and start again. Measured on generated `mixed` scenes shown with
every fourth frame twice (Results, repeated frames in the README).

The rule: a frame is a repeat when no 16 x 16 block of its grey image differs from the last
distinct frame's by more than ``max_diff`` grey levels on the mean (absolute difference). A
repeat is not processed; it takes the pose and the mask of the frame it repeats. Measured on
real footage here, consecutive distinct frames differ by 14-100 grey levels in their most
changed block (the least: Bonn `crowd`, a hand-held camera at 30 frame/s; DAVIS clips 36-104,
Sintel alley 71), while the same frame coded again as JPEG at quality 95 / 85 / 75 differs by
0.2-1.6 / 1.6-3.9 / 0-5.7 and grey noise of sd 2 by 1.9. Two frames that no block tells apart
are the same view as far as any later stage can measure, so a frame of a still camera on a
still scene taken for a repeat loses nothing; the comparison is with the last distinct frame,
not the previous one, so a slow drift is never skipped for long. A flat frame (grey-level
standard deviation at most ``FLAT_STD``: a fade to black, a covered lens) repeats nothing: it
shows nothing of where the camera is, and the VO carries the camera's walk through such a
stretch rather than holding it still.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["BLOCK_PX", "FLAT_STD", "block_difference", "RepeatDetector"]

BLOCK_PX = 16   # the block a difference is averaged over: coding noise averages out in it, a
                # moving edge of a few pixels does not
FLAT_STD = 2.0  # grey-level sd at or below which a frame is flat (the bars' flatness,
                # mona_vo.picture_area)


def _grey(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def block_difference(a: np.ndarray, b: np.ndarray, block: int = BLOCK_PX) -> float:
    """The largest mean absolute grey-level difference of ``a`` and ``b`` (same-sized (H, W)
    grey or (H, W, 3) RGB uint8 images) over ``block`` x ``block`` blocks (the image's edge
    blocks may be smaller)."""
    d = cv2.absdiff(_grey(a), _grey(b))
    h, w = d.shape
    small = cv2.resize(d.astype(np.float32), (max(1, -(-w // block)), max(1, -(-h // block))),
                       interpolation=cv2.INTER_AREA)
    return float(small.max())


class RepeatDetector:
    """Tells, frame by frame, whether a frame repeats the last distinct one (module docstring).
    ``max_diff`` <= 0 turns the test off: every frame is distinct."""

    def __init__(self, max_diff: float):
        self.max_diff = float(max_diff)
        self._last: np.ndarray | None = None    # grey image of the last distinct frame

    def is_repeat(self, image: np.ndarray) -> bool:
        image = np.asarray(image)
        if self.max_diff <= 0 or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            return False    # off, or not an RGB frame: the stage it goes to says what is wrong
        grey = _grey(image)
        if self._last is not None and self._last.shape == grey.shape \
                and block_difference(self._last, grey) <= self.max_diff \
                and float(cv2.meanStdDev(grey)[1][0, 0]) > FLAT_STD:
            return True
        self._last = grey.copy()
        return False
