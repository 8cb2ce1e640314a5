"""eval.mask_metrics: DAVIS J and F on hand-made masks (values derived by hand from the DAVIS
reference rules) and on the DAVIS-2016 clips in /work/shared/data/davis2016."""
from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage

from eval.mask_metrics import (MaskMetrics, boundary_f, boundary_map, boundary_tolerance_px,
                               error_parts, evaluate_mask_folders, evaluate_mask_sequence,
                               region_similarity)
from mona_vo.errors import EvalError, InputError

DAVIS = Path("/work/shared/data/davis2016/Annotations/480p")
needs_davis = pytest.mark.skipif(not DAVIS.is_dir(), reason=f"DAVIS-2016 clips absent ({DAVIS})")
SEQUENCES = ["car-shadow", "dog"]


def _square(shape=(64, 64), top=10, left=10, size=20) -> np.ndarray:
    m = np.zeros(shape, dtype=bool)
    m[top:top + size, left:left + size] = True
    return m


# ----------------------------------------------------------------------------------------------
# hand-made masks
# ----------------------------------------------------------------------------------------------

def test_identical_masks_score_one():
    m = _square()
    assert region_similarity(m, m) == 1.0
    assert boundary_f(m, m) == 1.0


def test_disjoint_masks_score_zero():
    a = _square(top=2, left=2, size=10)
    b = _square(top=40, left=40, size=10)
    assert region_similarity(a, b) == 0.0
    assert boundary_f(a, b) == 0.0


def test_square_shifted_by_one_pixel():
    gt = _square(size=20)
    pred = np.roll(gt, 1, axis=1)
    # Overlap 20 x 19 over a union of 20 x 21.
    assert region_similarity(pred, gt) == pytest.approx(19 / 21)
    # Tolerance ceil(0.008 * hypot(64, 64)) = 1 px: every boundary pixel has a match 1 px away.
    assert boundary_tolerance_px(gt.shape) == 1
    assert boundary_f(pred, gt) == 1.0


def test_empty_mask_cases_follow_davis():
    empty = np.zeros((32, 32), dtype=np.uint8)
    full = _square((32, 32), 5, 5, 10).astype(np.uint8) * 255
    assert region_similarity(empty, empty) == 1.0
    assert boundary_f(empty, empty) == 1.0  # P = R = 1
    assert region_similarity(empty, full) == 0.0
    assert boundary_f(empty, full) == 0.0  # nothing predicted: P = 1, R = 0
    assert boundary_f(full, empty) == 0.0  # nothing to find: P = 0, R = 1


def test_boundary_map_follows_seg2bmap():
    # A 4 x 4 square away from the border: the boundary is the 5 x 5 ring shifted half a pixel
    # towards the origin (last row/column of the square plus the row/column before it), 16 px.
    m = _square((10, 10), 3, 3, 4)
    expected = np.zeros((10, 10), dtype=bool)
    expected[2:7, 2:7] = True
    expected[3:6, 3:6] = False
    np.testing.assert_array_equal(boundary_map(m), expected)

    # Touching the bottom border: the last image row only compares with its right neighbour, so
    # the square's bottom edge gives no boundary, only its two side pixels do: 13 px.
    m = np.zeros((10, 10), dtype=bool)
    m[6:10, 3:7] = True
    expected = np.zeros((10, 10), dtype=bool)
    expected[5, 2:7] = True
    expected[6:10, 2] = True
    expected[6:10, 6] = True
    np.testing.assert_array_equal(boundary_map(m), expected)


def test_diagonal_shift_reproduces_davis_value_by_hand():
    """4 x 4 square shifted by (1, 1) in a 10 x 10 image. DAVIS tolerance ceil(0.008 * 14.14) = 1
    px, and skimage's disk(1) is the 4-neighbour cross (no diagonals). The boundaries are the 16-px
    rings of boxes [2..6]^2 and [3..7]^2; all but one pixel of each ring (the far corners (7, 7) and
    (2, 2)) have a ring pixel of the other at distance <= 1, so P = R = 15/16 and F = 15/16.
    J = 9 / (16 + 16 - 9) = 9/23."""
    gt = _square((10, 10), 3, 3, 4)
    pred = _square((10, 10), 4, 4, 4)
    assert region_similarity(pred, gt) == pytest.approx(9 / 23)
    assert boundary_f(pred, gt) == pytest.approx(15 / 16)
    # A 2-px tolerance reaches the diagonal neighbours.
    assert boundary_f(pred, gt, bound_th=2) == 1.0


def test_error_parts_tell_spill_around_the_object_from_false_regions_apart():
    gt = _square()                                   # 400 true pixels, rows/cols 10-29
    pred = _square(top=10, left=10, size=25)         # the object and 225 pixels of spill
    pred[50:60, 50:60] = True                        # and a false region apart, 100 pixels
    pred[10:14, 10:30] = False                       # 80 true pixels missed
    parts = error_parts([pred, np.zeros_like(gt)], [gt, gt])
    assert parts["found"] == pytest.approx(320 / 800)
    assert parts["missed"] == pytest.approx(480 / 800)
    assert parts["spill"] == pytest.approx(225 / 800)
    assert parts["apart"] == pytest.approx(100 / 800)
    assert np.isnan(error_parts([pred], [np.zeros_like(gt)])["spill"])


def test_invalid_inputs_raise_eval_error():
    with pytest.raises(EvalError, match="differ in size"):
        region_similarity(np.zeros((4, 4)), np.zeros((4, 5)))
    with pytest.raises(EvalError, match="2-D"):
        boundary_f(np.zeros((2, 4, 4)), np.zeros((2, 4, 4)))
    with pytest.raises(EvalError, match="bound_th"):
        boundary_f(np.zeros((4, 4)), np.zeros((4, 4)), bound_th=0.0)
    with pytest.raises(EvalError, match="3 predicted masks for 2"):
        evaluate_mask_sequence([np.zeros((4, 4))] * 3, [np.zeros((4, 4))] * 2)


def test_sequence_metrics_and_skip_first_last():
    gt = [_square(), _square(), _square(), _square()]
    pred = [_square(), np.roll(_square(), 1, axis=1), np.zeros((64, 64), bool), _square()]
    res = evaluate_mask_sequence(pred, gt)
    np.testing.assert_allclose(res.J, [1.0, 19 / 21, 0.0, 1.0])
    np.testing.assert_allclose(res.F, [1.0, 1.0, 0.0, 1.0])
    assert res.n_frames == 4 and res.J_mean == pytest.approx((2 + 19 / 21) / 4)
    inner = evaluate_mask_sequence(pred, gt, skip_first_last=True)
    assert inner.n_frames == 2 and inner.F_mean == pytest.approx(0.5)
    d = res.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["JF_mean"] == pytest.approx((res.J_mean + res.F_mean) / 2)


# ----------------------------------------------------------------------------------------------
# DAVIS-2016 clips
# ----------------------------------------------------------------------------------------------

def _read_gt(seq: str) -> tuple[list[str], list[np.ndarray]]:
    files = sorted((DAVIS / seq).glob("*.png"))
    return [f.stem for f in files], [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) > 0 for f in files]


def _dilate_euclidean(mask: np.ndarray, radius: float) -> np.ndarray:
    """Dilation by a disk via the Euclidean distance transform (independent of OpenCV)."""
    return ndimage.distance_transform_edt(~mask) <= radius


def _f_by_distance_transform(pred: np.ndarray, gt: np.ndarray, radius: int) -> float:
    """F from the definition: a boundary pixel matches when the other boundary lies within
    ``radius`` px (Euclidean), which is what dilating by the disk x^2 + y^2 <= r^2 tests."""
    pb, gb = boundary_map(pred), boundary_map(gt)
    precision = np.mean(ndimage.distance_transform_edt(~gb)[pb] <= radius)
    recall = np.mean(ndimage.distance_transform_edt(~pb)[gb] <= radius)
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


@needs_davis
@pytest.mark.parametrize("seq", SEQUENCES)
def test_davis_gt_against_itself_scores_one(seq):
    res = evaluate_mask_folders(DAVIS / seq, DAVIS / seq)
    assert res.n_frames == 40
    assert res.frame_names[0] == "00000" and res.frame_names[-1] == "00039"
    np.testing.assert_array_equal(res.J, 1.0)
    np.testing.assert_array_equal(res.F, 1.0)


@needs_davis
@pytest.mark.parametrize("seq", SEQUENCES)
def test_davis_gt_dilated_gives_independent_j(seq, tmp_path):
    names, gts = _read_gt(seq)
    radius = 3
    expected_j = []
    for name, gt in zip(names, gts):
        dil = _dilate_euclidean(gt, radius)
        cv2.imwrite(str(tmp_path / f"{name}.png"), dil.astype(np.uint8) * 255)
        expected_j.append(gt.sum() / dil.sum())  # GT lies inside its dilation: |G| / |D|
    res = evaluate_mask_folders(tmp_path, DAVIS / seq)
    np.testing.assert_allclose(res.J, expected_j, rtol=0, atol=1e-12)
    assert 0.8 < res.J_mean < 1.0
    # A 3-px shift of the contour is well inside the 8-px DAVIS tolerance at 854 x 480.
    assert boundary_tolerance_px(gts[0].shape) == 8
    assert res.F_mean > 0.97


@needs_davis
def test_davis_boundary_f_equals_distance_transform_definition():
    names, gts = _read_gt("dog")
    rng = np.random.default_rng(0)
    for gt in gts[::8]:
        for pred in (np.roll(gt, tuple(rng.integers(-12, 13, size=2)), axis=(0, 1)),
                     _dilate_euclidean(gt, 10.0),
                     ndimage.binary_erosion(gt, iterations=6)):
            assert boundary_f(pred, gt) == pytest.approx(_f_by_distance_transform(pred, gt, 8),
                                                         abs=1e-12)


@needs_davis
def test_davis_frame_j_and_f_take_a_few_milliseconds():
    _, gts = _read_gt("car-shadow")
    preds = [np.roll(g, 5, axis=1) for g in gts[:10]]
    start = time.perf_counter()
    for p, g in zip(preds, gts[:10]):
        region_similarity(p, g)
        boundary_f(p, g)
    per_frame = (time.perf_counter() - start) / 10
    assert per_frame < 0.02, f"J and F took {per_frame * 1e3:.1f} ms per 854x480 frame"


# ----------------------------------------------------------------------------------------------
# folder errors
# ----------------------------------------------------------------------------------------------

def _write_masks(folder: Path, names, shape=(16, 16)) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        cv2.imwrite(str(folder / f"{n}.png"), _square(shape, 4, 4, 6).astype(np.uint8) * 255)


def test_folder_errors_name_the_problem(tmp_path):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _write_masks(gt, ["00000", "00001", "00002"])
    with pytest.raises(InputError, match="predicted mask folder not found"):
        evaluate_mask_folders(pred, gt)
    _write_masks(pred, ["frame_a"])
    with pytest.raises(InputError, match="no common frame names"):
        evaluate_mask_folders(pred, gt)
    _write_masks(pred, ["00000"])
    with pytest.raises(InputError, match=r"lacks 2 of the 3 frames .*00001, 00002"):
        evaluate_mask_folders(pred, gt)
    _write_masks(pred, ["00001", "00002"], shape=(16, 20))
    with pytest.raises(InputError, match="size mismatch for frame 00001"):
        evaluate_mask_folders(pred, gt)
    _write_masks(pred, ["00001", "00002"])
    res = evaluate_mask_folders(pred, gt)  # extra pred 'frame_a' is ignored
    assert isinstance(res, MaskMetrics) and res.n_frames == 3 and res.J_mean == 1.0
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no .png masks"):
        evaluate_mask_folders(pred, empty)


def test_colour_and_numbered_masks_are_read_in_frame_order(tmp_path):
    gt, pred = tmp_path / "gt", tmp_path / "pred"
    _write_masks(gt, ["9", "10"])
    pred.mkdir()
    for n in ("9", "10"):
        colour = np.zeros((16, 16, 3), np.uint8)
        colour[4:10, 4:10] = (0, 0, 128)  # DAVIS palette red, as OpenCV returns indexed PNGs
        cv2.imwrite(str(pred / f"{n}.png"), colour)
    res = evaluate_mask_folders(pred, gt)
    assert res.frame_names == ("9", "10")
    assert res.J_mean == 1.0 and res.F_mean == 1.0
