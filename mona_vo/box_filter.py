"""MONA's adaptive bounding-box filter (paper, section Methods, Moving Object Segmentation).

A detector cannot tell a parked car from a driving one; the dynamic points can. With
``D_i`` = number of dynamic points inside box ``b_i`` and a per-video count ``tau_0``:

    u     = argmin_{b in B, D_b >= tau_0} Area(b)          (the unit box)
    tau_i = tau_0 * Area(b_i) / Area(b_u)
    keep b_i  iff  D_i >= tau_i

so a box must hold as many dynamic points per unit area as the smallest box that holds
``tau_0`` of them: a large static box that happens to contain a few dynamic points is dropped,
while a box smaller than the unit box may be kept with fewer than ``tau_0`` points. When no box
holds ``tau_0`` dynamic points, no box is kept.

``unit="smallest-qualifying"`` is the paper's rule above (default). ``unit="smallest"`` is the
variant of MONA's public code: the unit is the smallest box of all, whatever its count, so every
``tau_i >= tau_0``.

Boxes (the convention of :class:`mona_vo.detection.Boxes`): ``(N, 4)`` float ``x0, y0, x1, y1``
in the pixel coordinates of :mod:`mona_vo.conventions` (pixel centres at integers). A box is the
closed rectangle ``x0 <= x <= x1, y0 <= y <= y1``: a point on an edge or a corner is inside.
``Area = (x1 - x0) * (y1 - y0)``. A box with a non-finite coordinate, ``x1 <= x0`` or
``y1 <= y0`` (zero or negative extent) is invalid: it is counted but never kept and never the
unit box (its area would make the threshold 0/0 or infinite). Ties for the unit box (equal areas) take the first such box; the thresholds do
not depend on which, since they depend on the area only.

Pure functions of numpy arrays; the inputs are not modified.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SMALLEST_QUALIFYING = "smallest-qualifying"
SMALLEST = "smallest"
UNIT_RULES = (SMALLEST_QUALIFYING, SMALLEST)


@dataclass(frozen=True, eq=False)
class BoxFilterResult:
    """Outcome of :func:`adaptive_box_filter` for N boxes.

    keep:        (N,) bool, the filtered boxes B_filtered.
    counts:      (N,) int64 D_i, dynamic points inside each box.
    thresholds:  (N,) float64 tau_i (inf for invalid boxes and when there is no unit box).
    areas:       (N,) float64 Area(b_i), pixels^2 (NaN where not finite).
    unit_index:  index of the unit box b_u, or None when there is none.
    """

    keep: np.ndarray
    counts: np.ndarray
    thresholds: np.ndarray
    areas: np.ndarray
    unit_index: int | None


def _as_boxes(xyxy) -> np.ndarray:
    b = np.asarray(xyxy, dtype=np.float64)
    if b.size == 0:
        return np.zeros((0, 4))
    if b.ndim != 2 or b.shape[1] != 4:
        raise ValueError(f"boxes must be (N, 4) x0, y0, x1, y1, got shape {b.shape}")
    return b


def _as_points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64) if points is not None else np.zeros((0, 2))
    if p.size == 0:
        return np.zeros((0, 2))
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points must be (N, 2) x, y, got shape {p.shape}")
    return p[np.isfinite(p).all(axis=1)]


def box_areas(xyxy) -> np.ndarray:
    """(N,) float64 ``(x1 - x0) * (y1 - y0)`` of (N, 4) boxes (negative for flipped boxes)."""
    b = _as_boxes(xyxy)
    with np.errstate(invalid="ignore", over="ignore"):
        return (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])


def valid_boxes(xyxy) -> np.ndarray:
    """(N,) bool: finite coordinates with x1 > x0 and y1 > y0 (a positive area)."""
    b = _as_boxes(xyxy)
    with np.errstate(invalid="ignore"):
        return np.isfinite(b).all(axis=1) & (b[:, 2] > b[:, 0]) & (b[:, 3] > b[:, 1])


def count_points_in_boxes(xyxy, points) -> np.ndarray:
    """(N,) int64 number of the (M, 2) points x, y inside each closed box (edges included);
    non-finite points are ignored."""
    b = _as_boxes(xyxy)
    p = _as_points(points)
    if len(b) == 0 or len(p) == 0:
        return np.zeros(len(b), np.int64)
    x, y = p[:, 0][None, :], p[:, 1][None, :]
    inside = ((x >= b[:, 0:1]) & (x <= b[:, 2:3]) & (y >= b[:, 1:2]) & (y <= b[:, 3:4]))
    return inside.sum(axis=1).astype(np.int64)


def adaptive_box_filter(xyxy, dynamic_points, tau0: float,
                        unit: str = SMALLEST_QUALIFYING) -> BoxFilterResult:
    """The paper's adaptive box filter (module docstring).

    xyxy:           (N, 4) boxes x0, y0, x1, y1, pixels.
    dynamic_points: (M, 2) pixels x, y of the frame's dynamic points.
    tau0:           dynamic points the unit box must hold (> 0).
    unit:           'smallest-qualifying' (paper) or 'smallest' (MONA public code).
    """
    if unit not in UNIT_RULES:
        raise ValueError(f"unknown unit rule '{unit}'; choose one of: {', '.join(UNIT_RULES)}")
    if not (np.isfinite(tau0) and tau0 > 0):
        raise ValueError(f"tau0 must be a positive number, got {tau0!r}")
    b = _as_boxes(xyxy)
    n = len(b)
    counts = count_points_in_boxes(b, dynamic_points)
    areas = box_areas(b)
    valid = valid_boxes(b)
    thresholds = np.full(n, np.inf)
    keep = np.zeros(n, bool)
    areas_out = np.where(np.isfinite(areas), areas, np.nan)
    if unit == SMALLEST_QUALIFYING:
        candidates = np.nonzero(valid & (counts >= tau0))[0]
    else:
        candidates = np.nonzero(valid)[0]
    if len(candidates) == 0:
        return BoxFilterResult(keep, counts, thresholds, areas_out, None)
    # argmin takes the first of equal areas: ties resolve to the lowest index.
    u = int(candidates[np.argmin(areas[candidates])])
    # tau0 * (A_i / A_u), not (tau0 * A_i) / A_u: the ratio is exactly 1 for the unit box (and
    # exact whenever it is representable), so D_u >= tau0 always keeps the unit box.
    thresholds[valid] = tau0 * (areas[valid] / areas[u])
    keep[valid] = counts[valid] >= thresholds[valid]
    return BoxFilterResult(keep, counts, thresholds, areas_out, u)
