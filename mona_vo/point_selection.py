"""Where to put new tracks: one point per cell of a grid, the best-textured candidate of each cell
(LEAP-VO's rule, also MONA's anchor points), and uniformly random detection points (MONA).

Scores: ``gradient`` is LEAP-VO's image-gradient magnitude; ``min_eigen`` (default) is the smaller
eigenvalue of the structure tensor (Shi-Tomasi), which also rejects straight edges where a
Lucas-Kanade tracker slides along the edge (aperture problem).
"""
from __future__ import annotations

import cv2
import numpy as np


def texture_score(gray: np.ndarray, kind: str = "min_eigen") -> np.ndarray:
    """(H, W) float32 trackability score of a (H, W) uint8 grey image."""
    if kind == "min_eigen":
        return cv2.cornerMinEigenVal(gray, blockSize=5, ksize=3)
    if kind == "gradient":
        gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
        return cv2.GaussianBlur(cv2.magnitude(gx, gy), (5, 5), 0)
    raise ValueError(f"unknown texture score '{kind}' (min_eigen, gradient)")


TRACKABLE_SCORE = 1e-4  # min-eigen score of a trackable cell in a textured frame (grid_points)


def adaptive_min_score(score: np.ndarray, floor: float, quality: float) -> float:
    """The score a new point needs in this frame: :data:`TRACKABLE_SCORE`, lowered in a weakly
    textured frame (blur, fog, a bare wall) to ``quality`` times the frame's 99th-percentile
    score -- the relative rule of Shi-Tomasi's ``qualityLevel``, so a blurred frame still gets
    its best corners -- but never below ``floor``, the score image noise reaches by itself
    (a point there would track noise). The percentile is taken on every other pixel."""
    top = float(np.percentile(score[::2, ::2], 99)) if score.size else 0.0
    return max(float(floor), min(TRACKABLE_SCORE, float(quality) * top))


def seed_points(gray: np.ndarray, grid: int, kind: str, floor: float, quality: float, *,
                exclude: np.ndarray | None = None, occupied: np.ndarray | None = None) -> np.ndarray:
    """New points where the VO seeds them: on a ``grid`` x ``grid`` grid the best-scored pixel
    (:func:`texture_score` ``kind``) of each cell, at least the frame's
    :func:`adaptive_min_score` (``floor``, ``quality``); ``exclude`` and ``occupied`` as in
    :func:`grid_points`. Returns (N, 2) float32 pixels x, y."""
    score = texture_score(gray, kind)
    return grid_points(score, grid, grid, exclude=exclude, occupied=occupied,
                       min_score=adaptive_min_score(score, floor, quality))


def grid_points(score: np.ndarray, cols: int, rows: int, *, border: int = 8,
                exclude: np.ndarray | None = None, occupied: np.ndarray | None = None,
                min_score: float = TRACKABLE_SCORE) -> np.ndarray:
    """The highest-scoring pixel of every cell of a cols x rows grid.

    score:    (H, W) float32 from :func:`texture_score`.
    exclude:  optional (H, W) bool; pixels that may not be chosen (e.g. a moving-object mask).
    occupied: optional (M, 2) pixels of live tracks; cells holding one get no new point.
    Returns (N, 2) float32 pixels x, y, at most one per cell, each with score >= min_score (a
    textureless cell gets no point rather than an untrackable one).
    """
    h, w = score.shape
    s = score.copy()
    if exclude is not None:
        s[exclude] = -1.0
    s[:border] = -1.0
    s[h - border:] = -1.0
    s[:, :border] = -1.0
    s[:, w - border:] = -1.0
    xs = np.linspace(0, w, cols + 1).astype(int)
    ys = np.linspace(0, h, rows + 1).astype(int)
    taken = np.zeros((rows, cols), bool)
    if occupied is not None and len(occupied):
        occ = np.asarray(occupied)
        ci = np.clip(np.searchsorted(xs, occ[:, 0], side="right") - 1, 0, cols - 1)
        ri = np.clip(np.searchsorted(ys, occ[:, 1], side="right") - 1, 0, rows - 1)
        taken[ri, ci] = True
    # Each cell's maximum by reduceat over both axes; then, as argmax over the cell would take
    # it, the first pixel holding it in row-major order: the first row of the cell that holds
    # it, and in that row the first column. Cells of no pixel (more cells than pixels) drop out.
    ry, cx = np.diff(ys) > 0, np.diff(xs) > 0
    y0, x0 = ys[:-1][ry], xs[:-1][cx]
    hb, wb = np.diff(ys)[ry], np.diff(xs)[cx]
    if not len(y0) or not len(x0):
        return np.zeros((0, 2), np.float32)
    # Along x first: reduceat down the columns of a large image is ten times slower.
    best = np.maximum.reduceat(np.maximum.reduceat(s, x0, axis=1), y0, axis=0)
    at = s == np.repeat(np.repeat(best, hb, axis=0), wb, axis=1)
    in_row = np.logical_or.reduceat(at, x0, axis=1)                      # (h, cells across)
    row_in_cell = (np.arange(h) - np.repeat(y0, hb))[:, None]
    dy = np.minimum.reduceat(np.where(in_row, row_in_cell, h), y0, axis=0)  # (rows, cols)
    ys_best = y0[:, None] + np.minimum(dy, hb[:, None] - 1)
    cell_of = np.repeat(np.arange(len(x0)), wb)                           # column -> cell
    lines = at[ys_best] & (cell_of[None, None, :] == np.arange(len(x0))[None, :, None])
    xs_best = np.argmax(lines, axis=2)
    keep = (best >= min_score) & ~taken[np.ix_(ry, cx)]
    return np.stack([xs_best[keep], ys_best[keep]], axis=1).astype(np.float32).reshape(-1, 2)


def random_points(width: int, height: int, n: int, rng: np.random.Generator, *,
                  border: int = 8) -> np.ndarray:
    """(n, 2) float32 uniformly random integer pixels away from the border (MONA's detection
    points)."""
    x = rng.integers(border, width - border, n)
    y = rng.integers(border, height - border, n)
    return np.stack([x, y], axis=1).astype(np.float32)
