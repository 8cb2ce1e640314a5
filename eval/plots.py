"""Trajectory pictures: top view (x-z, the ground plane of a camera looking along z) and side view
(z against -y, up is up in OpenCV's y-down frame), estimate against GT after Sim(3) alignment when
GT is known. Drawn with OpenCV: every `mona-vo run` writes one, and importing matplotlib for it
cost more than the rest of a short clip's run (about 1.1 of 2.6 s on a 12-frame clip, stop 52)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from data_tools.atomic import write_bytes_atomic
from mona_vo.geometry import align_similarity

_SIZE = (1100, 495)                      # width, height of the picture, px
_GT, _EST = (128, 128, 128), (180, 119, 31)          # BGR: grey, blue
_START, _LOW = (44, 160, 44), (40, 39, 214)          # green, red
_INK, _GRID = (40, 40, 40), (225, 225, 225)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def align_sim3(est_xyz: np.ndarray, gt_xyz: np.ndarray) -> np.ndarray:
    """Umeyama Sim(3) alignment of (N, 3) positions onto GT (for drawing; the metrics use evo)."""
    s, R, t = align_similarity(est_xyz, gt_xyz)
    return s * np.asarray(est_xyz, np.float64) @ R.T + t


def _ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round values (1, 2 or 5 times a power of ten apart) between lo and hi."""
    raw = max(hi - lo, 1e-12) / n
    mag = 10.0 ** np.floor(np.log10(raw))
    step = mag * min((m for m in (1, 2, 5, 10) if m * mag >= raw), default=10)
    ticks = np.arange(np.ceil(lo / step) * step, hi + 0.5 * step, step)
    return np.where(np.abs(ticks) < 1e-9 * step, 0.0, ticks)    # no "-0"


def _text(img, s: str, org, scale=0.45, color=_INK, anchor="left") -> None:
    (w, h), _ = cv2.getTextSize(s, _FONT, scale, 1)
    x, y = org
    x = x - w if anchor == "right" else x - w // 2 if anchor == "centre" else x
    cv2.putText(img, s, (int(x), int(y)), _FONT, scale, color, 1, cv2.LINE_AA)


def _panel(img, box, curves, name: str, xl: str, yl: str, legend: bool) -> None:
    """One view in ``box`` (x0, y0, x1, y1) px: ``curves`` is a list of (xy (N, 2), style,
    label); one scale on both axes, the data centred (matplotlib's equal aspect, 'datalim')."""
    x0, y0, x1, y1 = box
    pts = np.vstack([c[0] for c in curves if len(c[0])])
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = (pts.min(0), pts.max(0)) if len(pts) else (np.zeros(2), np.ones(2))
    span = np.maximum(hi - lo, 1e-9)
    scale = 0.9 * min((x1 - x0) / span[0], (y1 - y0) / span[1])
    mid = 0.5 * (lo + hi)
    half = 0.5 * np.array([x1 - x0, y1 - y0]) / scale         # data half-extent shown

    def px(xy):
        u = x0 + (xy[:, 0] - mid[0] + half[0]) * scale
        v = y1 - (xy[:, 1] - mid[1] + half[1]) * scale
        return np.stack([u, v], axis=1)

    cv2.rectangle(img, (x0, y0), (x1, y1), (255, 255, 255), -1)
    for t in _ticks(mid[0] - half[0], mid[0] + half[0]):
        u = int(round(px(np.array([[t, 0.0]]))[0, 0]))
        cv2.line(img, (u, y0), (u, y1), _GRID, 1)
        _text(img, f"{t:.3g}", (u, y1 + 16), 0.38, anchor="centre")
    for t in _ticks(mid[1] - half[1], mid[1] + half[1]):
        v = int(round(px(np.array([[0.0, t]]))[0, 1]))
        cv2.line(img, (x0, v), (x1, v), _GRID, 1)
        _text(img, f"{t:.3g}", (x0 - 5, v + 4), 0.38, anchor="right")
    cv2.rectangle(img, (x0, y0), (x1, y1), _INK, 1)
    for xy, (kind, color, size), _ in curves:
        finite = np.isfinite(xy).all(axis=1)
        if not finite.any():
            continue
        p = np.zeros((len(xy), 2), np.int32)
        p[finite] = np.round(px(xy[finite]) * 16).astype(np.int32)     # 4 fractional bits
        if kind == "line":        # a run of finite positions per polyline: a NaN pose breaks it
            cuts = np.flatnonzero(np.diff(finite.astype(int))) + 1
            runs = [r for r in np.split(np.arange(len(xy)), cuts) if finite[r[0]]]
            cv2.polylines(img, [p[r].reshape(-1, 1, 2) for r in runs], False, color, size,
                          cv2.LINE_AA, shift=4)
            continue
        p = p[finite]
        if kind == "dot":
            for q in p:
                cv2.circle(img, tuple(q), size * 16, color, -1, cv2.LINE_AA, shift=4)
        else:                                                  # "x"
            for q in p:
                cv2.drawMarker(img, tuple(int(c) for c in np.round(q / 16)), color,
                               cv2.MARKER_TILTED_CROSS, 2 * size, 1, cv2.LINE_AA)
    _text(img, name, ((x0 + x1) // 2, y0 - 8), 0.55, anchor="centre")
    _text(img, xl, ((x0 + x1) // 2, y1 + 34), 0.45, anchor="centre")
    _text(img, yl, (x0 - 8, y0 - 8), 0.45, anchor="right")
    if legend:
        y = y0 + 18
        for _, (kind, color, size), label in curves:
            if label is None:
                continue
            if kind == "line":
                cv2.line(img, (x0 + 10, y - 4), (x0 + 34, y - 4), color, size, cv2.LINE_AA)
            elif kind == "dot":
                cv2.circle(img, (x0 + 22, y - 4), size, color, -1, cv2.LINE_AA)
            else:
                cv2.drawMarker(img, (x0 + 22, y - 4), color, cv2.MARKER_TILTED_CROSS, 2 * size, 1)
            _text(img, label, (x0 + 40, y), 0.4)
            y += 17


def plot_trajectory(path: str | Path, est_xyz: np.ndarray, gt_xyz: np.ndarray | None = None, *,
                    title: str = "", low_confidence: np.ndarray | None = None,
                    labels: tuple[str, str] = ("estimate", "ground truth")) -> Path:
    """Write a PNG with top and side views. est_xyz / gt_xyz: (N, 3) camera centres (world)."""
    est = np.asarray(est_xyz, float)
    if gt_xyz is not None and len(gt_xyz) == len(est) and len(est) >= 3:
        est = align_sim3(est, np.asarray(gt_xyz, float))
    width, height = _SIZE
    img = np.full((height, width, 3), 255, np.uint8)
    if title:
        _text(img, title, (width // 2, 24), 0.6, anchor="centre")
    lc = np.zeros(len(est), bool) if low_confidence is None else np.asarray(low_confidence, bool)
    views = (("top view", 0, 2, "x", "z"), ("side view", 2, 1, "z", "up (-y)"))
    panel_w = (width - 3 * 80) // 2
    for k, (name, i, j, xl, yl) in enumerate(views):
        sign = -1.0 if j == 1 else 1.0

        def view(xyz):
            return np.stack([xyz[:, i], sign * xyz[:, j]], axis=1)

        curves = []
        if gt_xyz is not None:
            curves.append((view(np.asarray(gt_xyz, float)), ("line", _GT, 3), labels[1]))
        curves.append((view(est), ("line", _EST, 2), labels[0]))
        curves.append((view(est[:1]), ("dot", _START, 4), "start"))
        if lc.any():
            curves.append((view(est[lc]), ("x", _LOW, 5), "low confidence"))
        x0 = 80 + k * (panel_w + 80)
        _panel(img, (x0, 60, x0 + panel_w, height - 55), curves, name, xl, yl, legend=k == 0)
    ok, data = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError(f"could not encode {path}")
    path = Path(path)
    write_bytes_atomic(path, data.tobytes())
    return path
