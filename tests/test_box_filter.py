"""The paper's adaptive box filter on hand-made boxes and points."""
from __future__ import annotations

import numpy as np
import pytest

from mona_vo.box_filter import (SMALLEST, SMALLEST_QUALIFYING, adaptive_box_filter, box_areas,
                                count_points_in_boxes)


def grid_points_in(box, n_x, n_y):
    """n_x * n_y points strictly inside box (x0, y0, x1, y1)."""
    x0, y0, x1, y1 = box
    xs = np.linspace(x0, x1, n_x + 2)[1:-1]
    ys = np.linspace(y0, y1, n_y + 2)[1:-1]
    return np.array([(x, y) for x in xs for y in ys], float)


def test_large_box_needs_proportionally_more_points():
    small = (0, 0, 10, 10)        # area 100, 3 points: the unit box (tau0 = 3)
    large = (50, 50, 70, 70)      # area 400 -> tau = 12; holds 8: dropped
    larger = (100, 0, 120, 20)    # area 400 -> tau = 12; holds 12: kept
    pts = np.concatenate([grid_points_in(small, 3, 1), grid_points_in(large, 4, 2),
                          grid_points_in(larger, 4, 3)])
    res = adaptive_box_filter([small, large, larger], pts, tau0=3)
    assert res.unit_index == 0
    np.testing.assert_array_equal(res.counts, [3, 8, 12])
    np.testing.assert_allclose(res.thresholds, [3, 12, 12])
    np.testing.assert_array_equal(res.keep, [True, False, True])


def test_no_box_reaches_tau0_keeps_none():
    boxes = [(0, 0, 10, 10), (20, 20, 40, 40)]
    pts = np.array([[5, 5], [6, 6], [30, 30]], float)
    res = adaptive_box_filter(boxes, pts, tau0=3)
    assert res.unit_index is None
    assert not res.keep.any()
    assert np.isinf(res.thresholds).all()


def test_box_smaller_than_unit_is_kept_with_fewer_than_tau0_points():
    # The paper's threshold scales down below the unit area: a quarter-size box with one dynamic
    # point passes tau = 4 * 25 / 100 = 1.
    unit = (0, 0, 10, 10)
    tiny = (20, 0, 25, 5)
    pts = np.concatenate([grid_points_in(unit, 2, 2), [[22, 2]]])
    res = adaptive_box_filter([unit, tiny], pts, tau0=4)
    assert res.unit_index == 0
    np.testing.assert_allclose(res.thresholds, [4.0, 1.0])
    np.testing.assert_array_equal(res.keep, [True, True])


def test_ties_in_unit_area_do_not_depend_on_order():
    a = (0, 0, 10, 10)
    b = (20, 0, 30, 10)           # same area as a, both qualify
    c = (40, 0, 60, 10)           # twice the area, 5 points < tau = 6
    pts = np.concatenate([grid_points_in(a, 3, 1), grid_points_in(b, 4, 1),
                          grid_points_in(c, 5, 1)])
    boxes = np.array([a, b, c], float)
    res = adaptive_box_filter(boxes, pts, tau0=3)
    assert res.unit_index == 0     # first of the equal areas
    for perm in ([2, 1, 0], [1, 0, 2], [2, 0, 1]):
        res_p = adaptive_box_filter(boxes[perm], pts, tau0=3)
        np.testing.assert_array_equal(res_p.keep, res.keep[perm])
        np.testing.assert_allclose(res_p.thresholds, res.thresholds[perm])
    np.testing.assert_array_equal(res.keep, [True, True, False])


def test_points_on_edges_and_corners_are_inside():
    box = (0.0, 0.0, 10.0, 10.0)
    pts = np.array([[0, 0], [10, 10], [0, 10], [10, 0], [5, 0], [10, 5],   # 6 on the border
                    [10.0001, 5], [5, -0.0001]])                           # 2 just outside
    assert count_points_in_boxes([box], pts)[0] == 6
    res = adaptive_box_filter([box], pts, tau0=6)
    assert res.keep[0] and res.unit_index == 0


def test_zero_area_and_invalid_boxes_are_never_kept_nor_unit():
    line = (5, 0, 5, 10)                  # zero width, its points lie on it
    flipped = (10, 10, 0, 0)              # negative extent
    nan_box = (np.nan, 0, 10, 10)
    good = (0, 20, 20, 40)                # area 400
    pts = np.concatenate([np.array([[5, 1], [5, 2], [5, 3], [5, 4]]),
                          grid_points_in(good, 2, 2)])
    res = adaptive_box_filter([line, flipped, nan_box, good], pts, tau0=3)
    assert res.counts[0] == 4             # counted ...
    assert res.unit_index == 3            # ... but never the unit
    np.testing.assert_array_equal(res.keep, [False, False, False, True])
    assert np.isinf(res.thresholds[:3]).all()
    np.testing.assert_allclose(box_areas([line, flipped]), [0.0, 100.0])


def test_smallest_unit_variant_uses_the_smallest_box_of_all():
    tiny = (0, 0, 5, 5)                   # area 25, no dynamic point
    mid = (10, 0, 20, 10)                 # area 100, 3 points
    pts = grid_points_in(mid, 3, 1)
    paper = adaptive_box_filter([tiny, mid], pts, tau0=3, unit=SMALLEST_QUALIFYING)
    public = adaptive_box_filter([tiny, mid], pts, tau0=3, unit=SMALLEST)
    assert paper.unit_index == 1 and public.unit_index == 0
    np.testing.assert_array_equal(paper.keep, [False, True])
    # Public-code rule: mid needs 3 * 100 / 25 = 12 points.
    np.testing.assert_allclose(public.thresholds, [3, 12])
    np.testing.assert_array_equal(public.keep, [False, False])
    assert (public.thresholds >= 3).all()


def test_inputs_are_not_modified_and_empty_inputs_work():
    boxes = np.array([[0, 0, 10, 10]], np.float32)
    pts = np.array([[1, 1], [2, 2], [np.nan, 3]], np.float32)
    b0, p0 = boxes.copy(), pts.copy()
    res = adaptive_box_filter(boxes, pts, tau0=2)
    np.testing.assert_array_equal(boxes, b0)
    np.testing.assert_array_equal(pts, p0)
    assert res.counts[0] == 2 and res.keep[0]
    empty = adaptive_box_filter(np.zeros((0, 4)), pts, tau0=2)
    assert empty.keep.shape == (0,) and empty.unit_index is None
    none = adaptive_box_filter(boxes, np.zeros((0, 2)), tau0=2)
    assert not none.keep.any()


def test_bad_arguments_raise():
    with pytest.raises(ValueError):
        adaptive_box_filter([(0, 0, 1, 1)], [[0, 0]], tau0=0)
    with pytest.raises(ValueError):
        adaptive_box_filter([(0, 0, 1, 1)], [[0, 0]], tau0=1, unit="largest")
    with pytest.raises(ValueError):
        adaptive_box_filter([(0, 0, 1)], [[0, 0]], tau0=1)


def test_grow_boxes_widens_each_side_by_a_share_of_the_box_and_keeps_the_dtype():
    """The one box growth the detector's margin, the evidence boxes and the segmenter's context
    ring share."""
    from mona_vo.detection import grow_boxes
    b = np.array([[10, 20, 30, 60], [0, 0, 4, 2]], np.float32)
    g = grow_boxes(b, 0.25)
    assert g.dtype == np.float32 and b[0, 0] == 10            # a new array
    np.testing.assert_allclose(g, [[5, 10, 35, 70], [-1, -0.5, 5, 2.5]])
    np.testing.assert_array_equal(grow_boxes(b, 0.0), b)
