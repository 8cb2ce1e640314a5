"""Repeated frames, as online videos carry them: to measure what they cost and what taking
them as repeats (``repeat_max_diff``, :mod:`mona_vo.repeats`) gives back.

Two kinds:

``pulldown``   every fourth frame shown twice (24 frame/s film at 30): the shown clip has 5/4
               as many frames, and the second showing has the first's pose; on its distinct
               frames it is the original clip. ``pulldown-jpeg``: every frame JPEG-coded at
               quality 90 and the second showing coded again from the picture at quality 80,
               as a video coder requantises a repeated frame.
``stutter``    every fifth frame replaced by the one before it (a stalled stream, frames
               dropped and the last one held): same frame count and timestamps, so a copy of a
               dataset with ground truth stays aligned; the held frame's true pose is one frame
               on from what it shows.

``python -m data_tools.repeats SRC DST`` writes DST, a copy of the image folder SRC with every
fifth image replaced by the one before it (``stutter``, same names and format); the text files of
a TUM-layout folder (``rgb.txt``, ``groundtruth.txt``, ``calib.txt``) are copied with it.
"""
from __future__ import annotations

import cv2
import numpy as np

from data_tools.atomic import write_bytes_atomic
from data_tools.folder_copy import copy_tool_main, image_folder_copy, rewrite_image

KINDS = ("pulldown", "pulldown-jpeg", "stutter")


def shown_order(n: int, kind: str) -> list[int]:
    """For a clip of ``n`` frames, the original frame each shown frame is (``kind`` as in the
    module docstring)."""
    if kind not in KINDS:
        raise ValueError(f"repeat kind must be one of {', '.join(KINDS)}, not '{kind}'")
    if kind == "stutter":
        return [i - 1 if i % 5 == 4 else i for i in range(n)]
    return [i for i in range(n) for _ in range(2 if i % 4 == 3 else 1)]


def _jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)


def shown_images(images: list[np.ndarray], kind: str) -> list[np.ndarray]:
    """The clip ``images`` (uint8 arrays) as shown with repeats of ``kind``."""
    order = shown_order(len(images), kind)
    if kind != "pulldown-jpeg":
        return [images[i] for i in order]
    return [_jpeg(images[i], 80 if k > 0 and order[k - 1] == i else 90)
            for k, i in enumerate(order)]


def write_stuttered_copy(src, dst) -> int:
    """Copy the image folder (or TUM-layout folder) ``src`` to ``dst`` with every fifth image
    replaced by the one before it (``stutter``); returns the number of images written."""
    files, out = image_folder_copy(src, dst)
    for p, i in zip(files, shown_order(len(files), "stutter")):
        # The held frame is the file before it, coded as that file is: a byte copy when the
        # formats agree, so it is the exact repeat a decoder gives.
        shown = files[i]
        if shown.suffix.lower() == p.suffix.lower():
            write_bytes_atomic(out / p.name, shown.read_bytes())
        else:
            rewrite_image(shown, out / p.name, lambda im: im)
    return len(files)


def main(argv=None) -> int:
    def write(args) -> str:
        n = write_stuttered_copy(args.src, args.dst)
        return f"wrote {n} images, every fifth holding the one before it, to {args.dst}"

    return copy_tool_main(argv, "python -m data_tools.repeats", __doc__, write)

if __name__ == "__main__":
    raise SystemExit(main())
