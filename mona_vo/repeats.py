"""Repeated frames: a frame that shows the last distinct frame again carries nothing new.

Online videos repeat frames: a 24 frame/s film shown at 30 repeats every fourth frame
(pulldown), a 25 frame/s clip at 30 every fifth, a stalled stream or screen capture holds one
for a while. Decoded, a repeat is the frame it repeats, up to the coder's requantisation. Fed
to the pipeline it is a frame without motion between two frames with motion: the VO's
constant-velocity prediction misses twice, and the masks' flow statistics and accumulated
evidence see a mover stop and start again. Measured on generated `mixed` scenes shown with
every fourth frame twice (Results, repeated frames in the README).

The rule: a frame is a repeat when no 16 x 16 block of its grey image, smoothed by a Gaussian
of 1 px, differs from the last distinct frame's by more than ``max_diff`` grey levels on the
mean (absolute difference; ``repeat_max_diff``, 2.5). The smoothing keeps a coder's
requantisation out (it is fine-grained; motion moves coarser structure too). Chosen on the
tuning parts: generated `mixed` seeds 0-5 and 200-211 shown with pulldown, the repeat coded
again at JPEG quality 80 after quality 90 (a harsher coder than a real one, which repeats a
frame as a skipped frame, exactly), differ by at most 1.68 in their most changed block and
their distinct frames by at least 3.98 (unsmoothed: 7.14 and 6.20, no threshold between);
DAVIS car-shadow, dog, libby, parkour and Bonn `crowd` frames 0-224 at least 9.18. 2.5 lies
between (their geometric mean, rounded). Checked on the validation parts: seeds 100-111
repeats at most 1.65, distinct frames at least 4.43; DAVIS blackswan, cows, goat,
scooter-black and Bonn frames 225-449 at least 30.2; seeds 300-311 1.68 / 4.77, Sintel alley_1
and the Bonn clip 55.0: every repeat found and no distinct frame taken. One picture coded
again at quality 95 down to 50 differs by 0.2-1.7, grey noise of sd 2 by about 1. Two frames
that no block tells apart are the same view as far as any later stage can measure, so a frame
of a still camera on a still scene taken for a repeat loses nothing; the comparison is with
the last distinct frame, not the previous one, so a slow drift is never skipped for long.

A flat frame (grey-level standard deviation at most ``FLAT_STD``: a fade to black, a covered
lens) repeats nothing: it shows nothing of where the camera is, and the VO carries the
camera's walk through such a stretch rather than holding it still.
"""
from __future__ import annotations

import cv2
import numpy as np

__all__ = ["BLOCK_PX", "BLUR_SIGMA", "FLAT_STD", "block_difference", "RepeatDetector"]

BLOCK_PX = 16   # the block a difference is averaged over: coding noise averages out in it, a
                # moving edge of a few pixels does not
BLUR_SIGMA = 1.0  # px: a coder's requantisation noise is fine-grained, motion moves the
                  # picture's coarser structure too (module docstring)
FLAT_STD = 2.0  # grey-level sd at or below which a frame is flat (the bars' flatness,
                # mona_vo.picture_area)


def _grey(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _smooth(grey: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(grey, (0, 0), BLUR_SIGMA)


def _largest_block_mean(d: np.ndarray, block: int) -> float:
    h, w = d.shape
    small = cv2.resize(d.astype(np.float32), (max(1, -(-w // block)), max(1, -(-h // block))),
                       interpolation=cv2.INTER_AREA)
    return float(small.max())


def block_difference(a: np.ndarray, b: np.ndarray, block: int = BLOCK_PX) -> float:
    """The largest mean absolute grey-level difference of ``a`` and ``b`` (same-sized (H, W)
    grey or (H, W, 3) RGB uint8 images), each smoothed by a Gaussian of ``BLUR_SIGMA`` px, over
    ``block`` x ``block`` blocks (the image's edge blocks may be smaller)."""
    return _largest_block_mean(cv2.absdiff(_smooth(_grey(a)), _smooth(_grey(b))), block)


class RepeatDetector:
    """Tells, frame by frame, whether a frame repeats the last distinct one (module docstring).
    ``max_diff`` <= 0 turns the test off: every frame is distinct."""

    def __init__(self, max_diff: float):
        self.max_diff = float(max_diff)
        self._last: np.ndarray | None = None    # smoothed grey image of the last distinct frame

    def is_repeat(self, image: np.ndarray) -> bool:
        image = np.asarray(image)
        if self.max_diff <= 0 or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            return False    # off, or not an RGB frame: the stage it goes to says what is wrong
        smooth = _smooth(_grey(image))
        if self._last is not None and self._last.shape == smooth.shape \
                and _largest_block_mean(cv2.absdiff(self._last, smooth), BLOCK_PX) <= self.max_diff \
                and float(cv2.meanStdDev(smooth)[1][0, 0]) > FLAT_STD:
            return True
        self._last = smooth
        return False
