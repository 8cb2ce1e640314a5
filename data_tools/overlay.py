"""``--overlay``: a video of the frames with the moving-object mask tinted red, MONA's detection
points (red dynamic, green static), every detector box (thin grey) and the kept boxes (yellow).
Written frame by frame to an mp4 (OpenCV, mp4v), so memory stays flat."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def draw_overlay(image_rgb: np.ndarray, mask: np.ndarray | None, mona=None,
                 origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """(H, W, 3) uint8 RGB drawing of one frame's masks, points and boxes; ``origin``: where
    the picture MONA saw (the frame inside letterbox bars) starts in the frame, px."""
    out = image_rgb.copy()
    if mask is not None and mask.any():
        tint = out[mask].astype(np.float32) * 0.5 + np.array([255, 0, 0], np.float32) * 0.5
        out[mask] = tint.astype(np.uint8)
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, (255, 60, 60), 1)
    if mona is None:
        return out
    ox, oy = origin
    for box in np.asarray(getattr(getattr(mona, "boxes", None), "xyxy", np.zeros((0, 4)))):
        x0, y0, x1, y1 = (int(round(v)) for v in box + (ox, oy, ox, oy))
        cv2.rectangle(out, (x0, y0), (x1, y1), (170, 170, 170), 1)
    for box in np.asarray(getattr(getattr(mona, "kept_boxes", None), "xyxy", np.zeros((0, 4)))):
        x0, y0, x1, y1 = (int(round(v)) for v in box + (ox, oy, ox, oy))
        cv2.rectangle(out, (x0, y0), (x1, y1), (255, 220, 0), 2)
    dyn = getattr(mona, "dynamic_points", None)
    if dyn is not None and len(getattr(dyn, "points", ())):
        for (x, y), d in zip(np.asarray(dyn.points), np.asarray(dyn.is_dynamic)):
            cv2.circle(out, (int(round(x + ox)), int(round(y + oy))), 3, (255, 0, 0) if d else (0, 200, 0), -1)
    return out


class OverlayWriter:
    def __init__(self, path: str | Path, fps: float = 10.0):
        self.path = Path(path)
        self.fps = float(fps)
        self._writer = None

    def add(self, frame) -> None:
        """frame: a :class:`mona_vo.pipeline.FrameOutput`."""
        drawn = draw_overlay(frame.image, frame.mask, frame.mona, getattr(frame, "origin", (0, 0)))
        if self._writer is None:
            h, w = drawn.shape[:2]
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"),
                                           self.fps, (w, h))
        self._writer.write(cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
