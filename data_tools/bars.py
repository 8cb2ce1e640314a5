"""Letterbox and pillarbox bars painted over frames, as online videos carry them: to measure
what they cost (``eval.vo_bench --bars``) and what cutting them off (``crop_bars``,
:mod:`mona_vo.picture_area`) gives back.

The bars cover part of the picture (they do not shrink it into the frame), so a run on barred
frames sees less of the scene than one on the originals; compare bars cut with bars kept.

``python -m data_tools.bars SRC DST [--kind letterbox] [--frac 0.12]`` writes DST, a copy of the
image folder SRC with bars on every image (same names and format); the text files of a TUM-layout
folder (``rgb.txt``, ``groundtruth.txt``, ``calib.txt``) are copied with it and its ``rgb/`` folder
gets the bars.
"""
from __future__ import annotations

import cv2
import numpy as np

from data_tools.folder_copy import copy_tool_main, image_folder_copy, rewrite_image
from mona_vo.errors import InputError

KINDS = ("letterbox", "pillarbox", "window", "letterbox-jpeg")


def add_bars(image: np.ndarray, kind: str, frac: float = 0.12) -> np.ndarray:
    """A copy of (H, W, 3) uint8 ``image`` with flat bars over ``frac`` of its height at top and
    bottom (letterbox), of its width left and right (pillarbox), both (window: 2/3 of ``frac``
    top and bottom), or a letterbox in video black (16) and the frame JPEG-coded at quality 60
    (letterbox-jpeg: the ringing of a re-encoded upload)."""
    if kind not in KINDS:
        raise ValueError(f"bars kind must be one of {', '.join(KINDS)}, not '{kind}'")
    out = np.array(image, np.uint8, copy=True)
    h, w = out.shape[:2]
    by, bx = int(frac * h), int(frac * w)
    if kind == "window":
        by = int(frac * h * 2 / 3)
    level = 16 if kind == "letterbox-jpeg" else 0
    if kind in ("letterbox", "window", "letterbox-jpeg") and by:
        out[:by] = level
        out[h - by:] = level
    if kind in ("pillarbox", "window") and bx:
        out[:, :bx] = level
        out[:, w - bx:] = level
    if kind == "letterbox-jpeg":
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, 60])
        out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return out


def write_barred_copy(src, dst, kind: str = "letterbox", frac: float = 0.12) -> int:
    """Copy the image folder (or TUM-layout folder) ``src`` to ``dst`` with bars on every image;
    returns the number of images written."""
    files, out = image_folder_copy(src, dst)
    for p in files:
        rewrite_image(p, out / p.name, lambda im: add_bars(im, kind, frac))
    return len(files)


def main(argv=None) -> int:
    def options(ap) -> None:
        ap.add_argument("--kind", choices=KINDS, default="letterbox")
        ap.add_argument("--frac", type=float, default=0.12)

    def write(args) -> str:
        if not 0 < args.frac < 0.5:
            raise InputError(f"--frac must lie in (0, 0.5), not {args.frac}")
        n = write_barred_copy(args.src, args.dst, args.kind, args.frac)
        return f"wrote {n} images with {args.kind} bars to {args.dst}"

    return copy_tool_main(argv, "python -m data_tools.bars", __doc__, write, options)

if __name__ == "__main__":
    raise SystemExit(main())
