"""The ``grabcut`` segmenter's start labels: what a box prompt makes of an object whose parts
differ in colour."""
from __future__ import annotations

import cv2
import numpy as np

from mona_vo.detection import MOTION_LABEL, Boxes, FrameContext
from mona_vo.segmentation import GrabCutConfig, GrabCutSegmenter

H, W = 120, 256


def _scene(seed=0):
    """A grey textured background and a 60 x 60 object at (100, 30): its top half red, its
    bottom half blue (colours the background does not have)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(60, 200, (H, W)).astype(np.float32), (0, 0), 1.5)
    img = np.repeat(img[..., None], 3, axis=2).astype(np.uint8)
    obj = np.zeros((H, W), bool)
    obj[30:90, 100:160] = True
    img[30:60, 100:160] = (200, 30, 30)
    img[60:90, 100:160] = (30, 30, 200)
    return img, obj


def _iou(a, b):
    return (a & b).sum() / max((a | b).sum(), 1)


def _segmenter():
    # At the image's own size, no edge refinement or dilation: the cut's labels are the mask.
    return GrabCutSegmenter(GrabCutConfig(work_size=W, refine_radius_px=0, dilate_px=0))


def test_a_box_without_motion_keeps_the_object_out_to_its_rim():
    """A tight box and no motion (a detector's box, or the true box): the whole box is probable
    foreground, as GrabCut's rectangle start; an inner rectangle left the box's rim -- here the
    object's red top and blue bottom eighths -- to the background model."""
    img, obj = _scene()
    img[37:83, 100:160] = (30, 200, 30)               # a green core, red and blue rims
    box = Boxes(np.array([[100, 30, 159, 89]], np.float32), np.ones(1, np.float32),
                np.array(["person"]))
    mask = _segmenter().segment(img, box)
    assert mask[30:36, 102:158].mean() > 0.9 and mask[84:90, 102:158].mean() > 0.9
    assert _iou(mask, obj) > 0.85


def test_an_object_detectors_box_is_the_whole_object_and_a_motion_box_is_its_seeds():
    """Seeds only on the top (red) half, as when a walker's legs move and the body barely does.
    A box drawn around motion (``MOTION_LABEL``) may be loose: only its seeds are foreground to
    start with, and the unseeded blue half goes. An object detector's box (any other label) is
    around one whole object: the whole box starts as foreground and the blue half stays."""
    img, obj = _scene()
    motion = np.zeros((H, W), np.float32)
    motion[32:58, 102:158] = 3.0
    context = FrameContext(0, motion, 1.0, 1.0, np.zeros((0, 2), np.float32), 1.0)
    xyxy = np.array([[100, 30, 159, 89]], np.float32)
    masks = {label: _segmenter().segment(img, Boxes(xyxy, np.ones(1, np.float32),
                                                    np.array([label])), context=context)
             for label in (MOTION_LABEL, "person")}
    assert masks["person"][62:88, 102:158].mean() > 0.9 and _iou(masks["person"], obj) > 0.85
    assert masks[MOTION_LABEL][62:88, 102:158].mean() < 0.1


def test_a_carried_mask_that_spilt_is_not_restored_beyond_the_objects_followed():
    """The previous mask, carried here, spilt onto the background: a blob four times the
    object. GrabCut cuts the object out of it and so keeps less than ``min_keep_frac`` of the
    seeds. What it must not drop is the evidence -- this frame's motion and the objects the
    accumulated evidence follows -- not the spill: restoring the whole carried blob kept the
    spill in every later frame (DAVIS parkour)."""
    img, obj = _scene()
    img[30:90, 100:160] = (200, 30, 30)                 # one red object
    motion = np.zeros((H, W), np.float32)
    motion[40:80, 110:150] = 3.0                        # its middle moves in this frame
    blob = np.zeros((H, W), bool)
    blob[5:115, 50:210] = True                          # the carried mask and its spill
    followed = cv2.dilate(obj.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    box = Boxes(np.array([[50, 5, 209, 114]], np.float32), np.ones(1, np.float32),
                np.array([MOTION_LABEL]))

    def segment(followed):
        context = FrameContext(0, motion, 1.0, 1.0, np.zeros((0, 2), np.float32), 1.0,
                               prior_mask=blob, followed=followed)
        return _segmenter().segment(img, box, context=context)

    assert _iou(segment(followed), obj) > 0.85
    # Without accumulated evidence the carried mask is all there is to go on: it stays.
    assert segment(None)[blob].mean() > 0.9


def test_what_the_fallback_adds_back_leaves_out_the_bleed_where_the_tracks_are_static():
    """The dense motion bleeds across the object's outline onto the background: a blob twice
    its width. Where GrabCut keeps too little, the motion comes back (here always: the
    'motion' method is the fallback itself); with ``fallback_static_frac`` not where the
    nearest point track is static -- the tracks on the object move, those beside it do not."""
    img, obj = _scene()
    motion = np.zeros((H, W), np.float32)
    motion[10:110, 70:190] = 3.0                        # the object (30:90, 100:160) and its bleed
    box = Boxes(np.array([[70, 10, 189, 109]], np.float32), np.ones(1, np.float32),
                np.array([MOTION_LABEL]))
    pts, res = [], []
    for y in range(14, 110, 12):
        for x in range(74, 190, 12):
            inside = 100 <= x < 160 and 30 <= y < 90
            pts.append((x, y))
            res.append(3.0 if inside else 0.05)
    context = FrameContext(0, motion, 1.0, 1.0, np.zeros((0, 2), np.float32), 1.0,
                           tracked_points=np.asarray(pts, np.float32),
                           tracked_residual=np.asarray(res, np.float32))

    def segment(frac):
        cfg = GrabCutConfig(work_size=W, refine_radius_px=0, dilate_px=0, method="motion",
                            fallback_static_frac=frac, fallback_static_reach=0.05)
        return GrabCutSegmenter(cfg).segment(img, box, context=context)

    before, after = segment(0.0), segment(0.5)
    assert _iou(before, obj) < 0.4                      # the bleed comes back with the object
    assert _iou(after, obj) > 0.75 and after[obj].mean() > 0.9     # the grid: 12 px apart


def test_static_point_zone_is_where_the_nearest_track_is_static_within_reach():
    from mona_vo.segmentation import static_point_zone
    pts = np.array([[10.0, 50.0], [90.0, 50.0]])        # pixels of the 100 x 100 image
    res = np.array([0.05, 3.0])
    zone = static_point_zone((100, 100), pts, res, 0.5, 0.2)
    assert zone[50, 2:15].all() and not zone[50, 85:95].any()
    assert not static_point_zone((100, 100), pts, res, 0.5, 0.01)[50, 20]


def _box_around(mask: np.ndarray, label: str = "person") -> Boxes:
    ys, xs = np.nonzero(mask)
    return Boxes(np.array([[xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5]],
                          np.float32), np.ones(1, np.float32), np.array([label]))


def test_the_cut_is_finer_where_the_regions_leave_room_in_the_budget():
    """``long_side``: a frame is cut at ``work_size`` or finer, up to ``fine_size``, while its
    regions (boxes with their context ring) hold at most ``fine_pixels`` pixels; never coarser
    than ``work_size``, and no frame's cut exceeds the budget unless its regions exceed it at
    ``work_size`` already."""
    W2, H2 = 1024, 436
    seg = GrabCutSegmenter(GrabCutConfig())               # work_size 256, fine_size 512
    cfg = seg.config
    budget = cfg.fine_pixels
    sides = []
    for half in (10, 40, 80, 120, 160, 220, 400):         # a square box of side 2 x half
        box = np.array([[512 - half, 218 - half, 512 + half, 218 + half]], np.float64)
        side = seg.long_side(box, W2, H2)
        assert cfg.work_size <= side <= cfg.fine_size
        grown = 2 * half * (1 + 2 * cfg.context_margin_frac)     # its side with the ring
        region = min(grown, W2) * min(grown, H2)
        if side > cfg.work_size:                          # finer: within the budget
            assert region * (side / W2) ** 2 <= budget * 1.01
        sides.append(side)
    assert sides[0] == cfg.fine_size and sides[-1] == cfg.work_size
    assert all(a >= b for a, b in zip(sides, sides[1:])) and len(set(sides)) > 2
    assert GrabCutSegmenter(GrabCutConfig(fine_pixels=0)).long_side(box, W2, H2) == cfg.work_size


def test_a_small_object_is_cut_at_the_finer_resolution():
    """A 24 x 48 px object in a 1024 x 436 frame is 6 x 12 px at 256 across: its outline is
    off by a coarse pixel (4 full-resolution pixels) there. With the budget's finer cut it
    follows the object."""
    rng = np.random.default_rng(0)
    H2, W2 = 436, 1024
    img = cv2.GaussianBlur(rng.uniform(60, 200, (H2, W2)).astype(np.float32), (0, 0), 3)
    img = np.repeat(img[..., None], 3, axis=2).astype(np.uint8)
    obj = np.zeros((H2, W2), np.uint8)
    cv2.ellipse(obj, (512, 200), (12, 24), 15, 0, 360, 1, -1)
    obj = obj > 0
    img[obj] = (200, 40, 40)
    box = _box_around(obj)
    iou = {budget: _iou(GrabCutSegmenter(GrabCutConfig(fine_pixels=budget, dilate_px=0))
                        .segment(img, box), obj) for budget in (0, 28000)}
    assert iou[28000] > 0.98 and iou[28000] > iou[0] + 0.03


def test_a_box_inside_anothers_region_is_cut_in_the_same_graph():
    """A small mover beside a large one, its region inside the large one's: one GrabCut for
    both (the second was the same pixels again), and the small mover still masked; boxes whose
    regions only overlap are cut one by one."""
    img, obj = _scene()
    img[40:48, 164:172] = (30, 200, 30)               # a small green mover right of the object
    small_obj = np.zeros((H, W), bool)
    small_obj[40:48, 164:172] = True
    motion = np.zeros((H, W), np.float32)
    motion[obj | small_obj] = 3.0
    context = FrameContext(0, motion, 1.0, 1.0, np.zeros((0, 2), np.float32), 1.0)
    calls = []

    class Counting(GrabCutSegmenter):
        def _graph_cut(self, small, init, roi):
            calls.append(roi)
            return super()._graph_cut(small, init, roi)

    seg = Counting(_segmenter().config)
    labels = np.array([MOTION_LABEL, MOTION_LABEL])
    inside = Boxes(np.array([[100, 30, 159, 89], [164, 40, 171, 47]], np.float32),
                   np.array([1.0, 0.5], np.float32), labels)
    mask = seg.segment(img, inside, context=context)
    assert len(calls) == 1
    assert mask[small_obj].mean() > 0.9 and _iou(mask & ~small_obj, obj) > 0.85
    # The same small box alone: its mask is what the shared cut gave it.
    calls.clear()
    alone = seg.segment(img, inside.select(np.array([False, True])), context=context)
    assert len(calls) == 1 and _iou(alone, small_obj) > 0.8
    # Moved right, its region reaches past the large one's: cut on its own.
    img2 = img.copy()
    img2[40:48, 164:172] = img[40:48, 20:28]
    img2[40:48, 200:208] = (30, 200, 30)
    motion2 = np.zeros((H, W), np.float32)
    motion2[obj] = 3.0
    motion2[40:48, 200:208] = 3.0
    context2 = FrameContext(0, motion2, 1.0, 1.0, np.zeros((0, 2), np.float32), 1.0)
    apart = Boxes(np.array([[100, 30, 159, 89], [170, 40, 207, 47]], np.float32),
                  np.array([1.0, 0.5], np.float32), labels)
    calls.clear()
    seg.segment(img2, apart, context=context2)
    assert len(calls) == 2
