"""DAVIS region similarity J and boundary F-measure F of binary moving-object masks.

Same semantics as the DAVIS benchmark code (``davis2017/metrics.py`` of
davisvideochallenge/davis2017-evaluation, itself from the DAVIS 2016 Python/Matlab code,
Perazzi et al., CVPR 2016), re-implemented with numpy and OpenCV:

J (``db_eval_iou``)
    ``|P & G| / |P | G|``; 1 when both masks are empty (nothing to find, nothing found).

F (``db_eval_boundary`` / ``f_measure``)
    1. Boundary maps with ``seg2bmap`` (D. Martin's BSDS code): a pixel is a boundary pixel when it
       differs from its right, lower or lower-right neighbour; outside the image counts as
       background, except that on the last row only the right neighbour is compared, on the last
       column only the lower one, and the bottom-right pixel never is a boundary. The resulting
       1-pixel boundary sits half a pixel towards the origin from the true contour, and a mask
       touching the bottom or right border gets no boundary along that border.
    2. Tolerance radius ``r = ceil(bound_th * hypot(H, W))`` pixels for ``bound_th < 1`` (DAVIS
       default 0.008: r = 8 at 854 x 480), else ``bound_th`` pixels (rounded up here; DAVIS
       never passes a non-integer pixel radius).
    3. Each boundary map is dilated by the disk ``x^2 + y^2 <= r^2`` (skimage's ``disk(r)``;
       OpenCV's MORPH_ELLIPSE differs from it in 16 pixels at r = 8, so the disk is built here).
       Precision = share of predicted boundary pixels within the dilated GT boundary, recall =
       share of GT boundary pixels within the dilated predicted boundary, ``F = 2PR / (P + R)``
       (0 when P + R = 0).
    4. Empty boundaries: none predicted and none in GT -> P = R = 1 (F = 1); none predicted but some
       in GT -> P = 1, R = 0 (F = 0); some predicted but none in GT -> P = 0, R = 1 (F = 0).

The binary DAVIS-2016 annotations have no void pixels, so none are handled here.
The semi-supervised evaluations (DAVIS-2016 Matlab ``eval_sequence``, davis2017-evaluation
``semi-supervised``) leave out the first and the last frame of each sequence, the unsupervised
davis2017 evaluation keeps all frames; all frames are scored by default, ``skip_first_last=True``
gives the semi-supervised rule.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from data_tools.masks_io import read_mask_png
from mona_vo.errors import EvalError, InputError

logger = logging.getLogger(__name__)

DEFAULT_BOUND_TH = 0.008  # DAVIS boundary tolerance, fraction of the image diagonal
_MASK_SUFFIX = ".png"  # masks must be lossless; DAVIS annotations and results are PNG
_N_LISTED = 5  # missing frame names quoted in an error message


def _as_mask(mask: np.ndarray, what: str) -> np.ndarray:
    """(H, W) bool foreground (any non-zero value) of a 2-D mask of any dtype."""
    m = np.asarray(mask)
    if m.ndim != 2:
        raise EvalError(f"{what} mask must be a 2-D (H, W) array, got shape {m.shape}")
    return m if m.dtype == bool else m != 0


def _pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p, g = _as_mask(pred, "predicted"), _as_mask(gt, "ground-truth")
    if p.shape != g.shape:
        raise EvalError(f"predicted mask {p.shape} and ground-truth mask {g.shape} differ in size")
    return p, g


def region_similarity(pred: np.ndarray, gt: np.ndarray) -> float:
    """DAVIS J: intersection over union of two (H, W) masks (non-zero = foreground).

    Returns a float in [0, 1]; 1.0 when both masks are empty, as DAVIS defines it.
    """
    p, g = _pair(pred, gt)
    union = np.count_nonzero(p | g)
    if union == 0:
        return 1.0
    return np.count_nonzero(p & g) / union


def boundary_map(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool 1-pixel boundary of a (H, W) mask, DAVIS/BSDS ``seg2bmap`` rule (see the module
    docstring): pixel (y, x) is a boundary pixel when it differs from (y, x+1), (y+1, x) or
    (y+1, x+1), with the last-row/last-column exceptions of the reference code."""
    m = _as_mask(mask, "input")
    h, w = m.shape
    # Neighbours read from a copy padded with background below and to the right.
    padded = np.zeros((h + 1, w + 1), dtype=bool)
    padded[:h, :w] = m
    right = padded[:h, 1:]
    below = padded[1:, :w]
    below_right = padded[1:, 1:]
    b = (m ^ right) | (m ^ below) | (m ^ below_right)
    # The reference overwrites the border lines: last row compares only with the right neighbour,
    # last column only with the lower one, and clears the corner.
    b[-1, :] = m[-1, :] ^ right[-1, :]
    b[:, -1] = m[:, -1] ^ below[:, -1]
    b[-1, -1] = False
    return b


def boundary_tolerance_px(shape: tuple[int, int], bound_th: float = DEFAULT_BOUND_TH) -> int:
    """Tolerance radius in pixels: ``ceil(bound_th * hypot(H, W))`` for ``bound_th < 1``, else
    ``bound_th`` pixels (rounded up; DAVIS only ever uses the fractional form)."""
    if not (math.isfinite(bound_th) and bound_th > 0):
        raise EvalError(f"bound_th must be a positive number, got {bound_th!r}")
    if bound_th >= 1:
        return int(math.ceil(bound_th))
    return int(math.ceil(bound_th * math.hypot(shape[0], shape[1])))


def _disk(radius: int) -> np.ndarray:
    """(2r+1, 2r+1) uint8 structuring element ``x^2 + y^2 <= r^2`` (skimage.morphology.disk)."""
    y, x = np.ogrid[-radius:radius + 1, -radius:radius + 1]
    return (x * x + y * y <= radius * radius).astype(np.uint8)


def boundary_f(pred: np.ndarray, gt: np.ndarray, bound_th: float = DEFAULT_BOUND_TH) -> float:
    """DAVIS F: boundary F-measure of two (H, W) masks (non-zero = foreground), in [0, 1].

    ``bound_th`` is the match tolerance as a fraction of the image diagonal (or pixels if >= 1).
    """
    p, g = _pair(pred, gt)
    radius = boundary_tolerance_px(p.shape, bound_th)  # validates bound_th even for empty masks
    p_b, g_b = boundary_map(p), boundary_map(g)
    n_p, n_g = np.count_nonzero(p_b), np.count_nonzero(g_b)
    if n_p == 0 or n_g == 0:
        # DAVIS' conventions: (P, R) = (1, 1) both empty, (1, 0) nothing predicted, (0, 1) nothing
        # to find; hence F is 1 only when both are empty.
        return 1.0 if n_p == n_g else 0.0
    kernel = _disk(radius)
    p_dil = cv2.dilate(p_b.view(np.uint8), kernel).view(bool)
    g_dil = cv2.dilate(g_b.view(np.uint8), kernel).view(bool)
    precision = np.count_nonzero(p_b & g_dil) / n_p
    recall = np.count_nonzero(g_b & p_dil) / n_g
    if precision + recall == 0:
        return 0.0
    return 2.0 * precision * recall / (precision + recall)


@dataclass(frozen=True, eq=False)
class MaskMetrics:
    """J and F of a mask sequence.

    Fields
        J: (T,) float64 region similarity per evaluated frame, in [0, 1].
        F: (T,) float64 boundary F-measure per evaluated frame, in [0, 1].
        J_mean, F_mean: means over the T frames.
        n_frames: T.
        frame_names: T frame names (file stems) when read from folders, else empty.
    """

    J: np.ndarray
    F: np.ndarray
    J_mean: float
    F_mean: float
    n_frames: int
    frame_names: tuple[str, ...] = ()

    @property
    def JF_mean(self) -> float:
        """(J_mean + F_mean) / 2, the DAVIS "J&F" score."""
        return 0.5 * (self.J_mean + self.F_mean)

    def to_dict(self) -> dict:
        """JSON-able dict: means, frame count and per-frame lists of Python floats."""
        return {
            "J_mean": float(self.J_mean),
            "F_mean": float(self.F_mean),
            "JF_mean": float(self.JF_mean),
            "n_frames": int(self.n_frames),
            "J": [float(v) for v in self.J],
            "F": [float(v) for v in self.F],
            "frame_names": list(self.frame_names),
        }


def error_parts(pred_masks: Sequence[np.ndarray], gt_masks: Sequence[np.ndarray]) -> dict:
    """Where a mask sequence's pixels go, each a share of all the true masks' pixels (not a
    DAVIS measure; it says what a low J is made of): ``found`` (predicted and true), ``missed``
    (true, not predicted; ``1 - found``), ``spill`` (predicted, not true, in a connected part of
    the prediction that touches the true mask: the mask too large around its object) and
    ``apart`` (predicted, in parts that touch no true pixel: false regions elsewhere). NaN
    shares when the true masks are empty."""
    counts = {"found": 0, "missed": 0, "spill": 0, "apart": 0}
    for pred, gt in zip(pred_masks, gt_masks):
        p, g = _pair(pred, gt)
        _, labels = cv2.connectedComponents(p.astype(np.uint8), connectivity=8)
        touching = np.unique(labels[p & g])
        attached = np.isin(labels, touching[touching > 0])
        counts["found"] += int(np.count_nonzero(p & g))
        counts["missed"] += int(np.count_nonzero(g & ~p))
        counts["spill"] += int(np.count_nonzero(attached & ~g))
        counts["apart"] += int(np.count_nonzero(p & ~attached))
    total = counts["found"] + counts["missed"]
    return {k: v / total if total else float("nan") for k, v in counts.items()}


def evaluate_mask_sequence(pred_masks: Sequence[np.ndarray], gt_masks: Sequence[np.ndarray], *,
                           bound_th: float = DEFAULT_BOUND_TH, skip_first_last: bool = False,
                           frame_names: Sequence[str] = ()) -> MaskMetrics:
    """J and F of each frame of a sequence of (H, W) masks (non-zero = foreground).

    Args:
        pred_masks, gt_masks: T masks each (a list or a (T, H, W) array), frame i against frame i.
        bound_th: boundary tolerance, see :func:`boundary_f`.
        skip_first_last: leave out frames 0 and T-1, as the official DAVIS evaluation does.
        frame_names: optional T names stored with the result (same frames as the masks).

    Raises:
        EvalError: different lengths, no frame left to evaluate, or a size mismatch in a frame.
    """
    if len(pred_masks) != len(gt_masks):
        raise EvalError(f"{len(pred_masks)} predicted masks for {len(gt_masks)} ground-truth masks")
    names = tuple(frame_names)
    if names and len(names) != len(gt_masks):
        raise EvalError(f"{len(names)} frame names for {len(gt_masks)} masks")
    idx = list(range(len(gt_masks)))
    if skip_first_last:
        idx = idx[1:-1]
    if not idx:
        raise EvalError(f"no frame to evaluate ({len(gt_masks)} masks"
                        f"{', first and last skipped' if skip_first_last else ''})")
    J = np.empty(len(idx))
    F = np.empty(len(idx))
    for k, i in enumerate(idx):
        try:
            p, g = _pair(pred_masks[i], gt_masks[i])
        except EvalError as exc:
            label = names[i] if names else str(i)
            raise EvalError(f"frame {label}: {exc}") from None
        J[k] = region_similarity(p, g)
        F[k] = boundary_f(p, g, bound_th)
    return MaskMetrics(J=J, F=F, J_mean=float(J.mean()), F_mean=float(F.mean()),
                       n_frames=len(idx), frame_names=tuple(names[i] for i in idx) if names else ())


def _frame_key(stem: str) -> tuple:
    """Numeric order for numbered frames (``9`` before ``10``), name order otherwise."""
    return (0, int(stem), stem) if stem.isdigit() else (1, 0, stem)


def _list_masks(folder: Path, role: str) -> dict[str, Path]:
    if not folder.is_dir():
        raise InputError(f"{role} mask folder not found: {folder}")
    files = {p.stem: p for p in folder.iterdir()
             if p.is_file() and p.suffix.lower() == _MASK_SUFFIX}
    if not files:
        raise InputError(f"no {_MASK_SUFFIX} masks in {role} folder {folder}")
    return files


def evaluate_mask_folders(pred_dir: str | Path, gt_dir: str | Path, *,
                          bound_th: float = DEFAULT_BOUND_TH,
                          skip_first_last: bool = False) -> MaskMetrics:
    """J and F of the PNG masks in ``pred_dir`` against those in ``gt_dir``, matched by file stem
    (``pred_dir/00012.png`` vs ``gt_dir/00012.png``), frames in numeric order.

    Every GT frame must have a prediction; predictions without GT are ignored (DAVIS scores only
    annotated frames). Non-zero pixels are foreground.

    Raises:
        InputError: a missing folder, no PNG masks, no common frame names, GT frames without a
            prediction (the first few are listed), an unreadable file, or a size mismatch.
    """
    pred_dir, gt_dir = Path(pred_dir), Path(gt_dir)
    gt_files = _list_masks(gt_dir, "ground-truth")
    pred_files = _list_masks(pred_dir, "predicted")
    names = sorted(gt_files, key=_frame_key)
    common = [n for n in names if n in pred_files]
    if not common:
        raise InputError(f"no common frame names between {pred_dir} and {gt_dir} (e.g. "
                         f"{names[0]}{_MASK_SUFFIX} vs {min(pred_files, key=_frame_key)}"
                         f"{_MASK_SUFFIX})")
    missing = [n for n in names if n not in pred_files]
    if missing:
        listed = ", ".join(missing[:_N_LISTED]) + (", ..." if len(missing) > _N_LISTED else "")
        raise InputError(f"{pred_dir} lacks {len(missing)} of the {len(names)} frames in "
                         f"{gt_dir}: {listed}")
    extra = len(pred_files) - len(common)
    if extra:
        logger.debug("ignoring %d predicted masks without ground truth in %s", extra, pred_dir)

    preds, gts = [], []
    for n in names:
        p, g = read_mask_png(pred_files[n]), read_mask_png(gt_files[n])
        if p.shape != g.shape:
            raise InputError(f"mask size mismatch for frame {n}: {pred_files[n]} is "
                             f"{p.shape[1]}x{p.shape[0]}, {gt_files[n]} is "
                             f"{g.shape[1]}x{g.shape[0]}")
        preds.append(p)
        gts.append(g)
    return evaluate_mask_sequence(preds, gts, bound_th=bound_th, skip_first_last=skip_first_last,
                                  frame_names=names)
