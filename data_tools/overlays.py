"""Burned-in overlays painted over frames, as online videos carry them: to measure what they cost
and what painting them out (``hide_overlays``, :mod:`mona_vo.overlays`) gives back.

Kinds: ``logo`` (a channel's badge: an opaque box with white lettering, top left), ``watermark``
(a platform's handle at 60 % opacity, bottom right), ``both``. Sizes follow the frame's width.

``python -m data_tools.overlays SRC DST [--kind logo]`` writes DST, a copy of the image folder
SRC with the overlay on every image (same names and format); the text files of a TUM-layout
folder (``rgb.txt``, ``groundtruth.txt``, ``calib.txt``) are copied with it.
"""
from __future__ import annotations

import cv2
import numpy as np

from data_tools.folder_copy import copy_tool_main, image_folder_copy, rewrite_image

KINDS = ("logo", "watermark", "both")


def add_overlay(image: np.ndarray, kind: str) -> np.ndarray:
    """A copy of (H, W, 3) uint8 ``image`` with the overlay ``kind`` burned in."""
    if kind not in KINDS:
        raise ValueError(f"overlay kind must be one of {', '.join(KINDS)}, not '{kind}'")
    out = np.array(image, np.uint8, copy=True)
    h, w = out.shape[:2]
    s = w / 640.0
    if kind in ("logo", "both"):
        x0, y0 = int(12 * s), int(12 * s)
        x1, y1 = x0 + int(120 * s), y0 + int(34 * s)
        cv2.rectangle(out, (x0, y0), (x1, y1), (150, 20, 20), -1)
        cv2.putText(out, "NEWS 24", (x0 + int(8 * s), y1 - int(9 * s)), cv2.FONT_HERSHEY_DUPLEX,
                    0.7 * s, (255, 255, 255), max(1, int(2 * s)), cv2.LINE_AA)
    if kind in ("watermark", "both"):
        layer = out.copy()
        cv2.putText(layer, "@somebody", (w - int(170 * s), h - int(16 * s)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.8 * s, (255, 255, 255), max(1, int(2 * s)),
                    cv2.LINE_AA)
        out = cv2.addWeighted(layer, 0.6, out, 0.4, 0)
    return out


def write_overlaid_copy(src, dst, kind: str = "logo") -> int:
    """Copy the image folder (or TUM-layout folder) ``src`` to ``dst`` with the overlay on every
    image; returns the number of images written."""
    files, out = image_folder_copy(src, dst)
    for p in files:
        rewrite_image(p, out / p.name, lambda im: add_overlay(im, kind))
    return len(files)


def main(argv=None) -> int:
    def write(args) -> str:
        n = write_overlaid_copy(args.src, args.dst, args.kind)
        return f"wrote {n} images with a {args.kind} to {args.dst}"

    return copy_tool_main(argv, "python -m data_tools.overlays", __doc__, write,
                          lambda ap: ap.add_argument("--kind", choices=KINDS, default="logo"))

if __name__ == "__main__":
    raise SystemExit(main())
