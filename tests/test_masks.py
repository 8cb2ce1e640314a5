"""The streamed MONA mask pipeline: prompt modes, streaming order and memory, real DAVIS data."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from mona_vo.detection import (Boxes, Detector, FrameContext, MotionDetector,
                               MotionDetectorConfig, merge_boxes)
from mona_vo.errors import ConfigError, InputError
from mona_vo.flow import DISFlow
from mona_vo.masks import MaskConfig, MonaMasker, compute_masks
from mona_vo.segmentation import Segmenter, refine_edges

W, H = 256, 112
BG_STEP = np.array([3.0, 1.0])        # the camera pans: the background moves by -BG_STEP
MOVER_STEP = np.array([2.0, 1.0])     # the mover's own image motion, px per frame
MOVER0 = np.array([40.0, 30.0])       # mover's top-left corner at frame 0
MOVER_SIZE = (44, 40)                 # w, h
STATIC0 = np.array([170.0, 50.0])     # static object's top-left corner at frame 0
STATIC_SIZE = (36, 34)


def _texture(h, w, seed, tint=None):
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, 3)).astype(np.float32), (0, 0), 1.2)
    img = (img - img.min()) / (img.max() - img.min())
    if tint is None:
        return (60 + 140 * img).astype(np.uint8)
    return np.clip(np.asarray(tint, np.float32) * (0.55 + 0.45 * img), 0, 255).astype(np.uint8)


def pan_scene(n_frames, with_mover=True, seed=0):
    """A panning camera over a textured wall holding a blue static object, and a red textured
    mover with its own motion. Returns (frames, mover boxes, static-object boxes, mover masks);
    boxes in the pixel convention of :class:`Boxes` (pixel-edge extents)."""
    big = _texture(H + 80, W + 120, seed)
    static_tex = _texture(STATIC_SIZE[1], STATIC_SIZE[0], seed + 1, tint=(40, 70, 220))
    mover_tex = _texture(MOVER_SIZE[1], MOVER_SIZE[0], seed + 2, tint=(230, 50, 40))
    sx, sy = int(STATIC0[0]) + 10, int(STATIC0[1]) + 10   # static object painted on the wall
    big[sy:sy + STATIC_SIZE[1], sx:sx + STATIC_SIZE[0]] = static_tex
    frames, mover_boxes, static_boxes, masks = [], [], [], []
    for k in range(n_frames):
        ox, oy = (10 + BG_STEP * k).astype(int)
        img = big[oy:oy + H, ox:ox + W].copy()
        s = STATIC0 + 10 - np.array([ox, oy])
        static_boxes.append((s[0] - 0.5, s[1] - 0.5, s[0] + STATIC_SIZE[0] - 0.5,
                             s[1] + STATIC_SIZE[1] - 0.5))
        mask = np.zeros((H, W), bool)
        if with_mover:
            mx, my = (MOVER0 + MOVER_STEP * k).astype(int)
            img[my:my + MOVER_SIZE[1], mx:mx + MOVER_SIZE[0]] = mover_tex
            mask[my:my + MOVER_SIZE[1], mx:mx + MOVER_SIZE[0]] = True
            mover_boxes.append((mx - 0.5, my - 0.5, mx + MOVER_SIZE[0] - 0.5,
                                my + MOVER_SIZE[1] - 0.5))
        frames.append(img)
        masks.append(mask)
    return frames, mover_boxes, static_boxes, masks


class ListDetector(Detector):
    """Proposes known boxes per frame, like a class-aware detector (moving and parked 'cars')."""

    def __init__(self, per_frame):
        self.per_frame = per_frame

    def detect(self, image, context: FrameContext | None = None) -> Boxes:
        return Boxes.from_arrays(self.per_frame[context.frame_index],
                                 label=np.full(len(self.per_frame[context.frame_index]), "car"))


def box_mask(box):
    m = np.zeros((H, W), bool)
    x0, y0, x1, y1 = box
    m[int(np.ceil(y0)):int(np.floor(y1)) + 1, int(np.ceil(x0)):int(np.floor(x1)) + 1] = True
    return m


SMALL = MaskConfig(dynamic_points=dataclasses.replace(MaskConfig().dynamic_points, window=5,
                                                      n_detection=400))


def run(frames, config, **backends):
    masker = MonaMasker(config, **backends)
    out = []
    for k, f in enumerate(frames):
        out += masker.push(k, f)
    return out + masker.flush()


def test_prompt_modes_differ_when_a_static_object_is_proposed():
    frames, mover_boxes, static_boxes, masks = pan_scene(10)
    detector = ListDetector({k: [mover_boxes[k], static_boxes[k]] for k in range(10)})
    results = {mode: run(frames, dataclasses.replace(SMALL, prompt=mode), detector=detector)
               for mode in ("boxes", "raw-boxes", "points")}
    k = 4
    static = box_mask(static_boxes[k])
    mover = masks[k]
    area = {mode: r[k].mask.sum() for mode, r in results.items()}
    cover = {mode: (r[k].mask & static).mean() / static.mean() for mode, r in results.items()}
    hit = {mode: (r[k].mask & mover).sum() / mover.sum() for mode, r in results.items()}
    assert cover["raw-boxes"] > 0.6                    # raw boxes segment the parked object too
    assert cover["boxes"] < 0.05                       # the filter drops its box
    assert hit["boxes"] > 0.8 and hit["raw-boxes"] > 0.8
    # Points only (paper, Fig. 3b: "incomplete masks and incorrect segmentations"): the mover
    # is only partly covered, and the disks of dynamic points tracked along its rim spill over.
    assert 0.3 < hit["points"] < hit["boxes"] - 0.1
    spill = {mode: (r[k].mask & ~mover).sum() for mode, r in results.items()}
    assert spill["points"] > spill["boxes"]
    assert area["points"] > 0
    filt = results["boxes"][k].box_filter
    np.testing.assert_array_equal(filt.keep, [True, False])
    assert len(results["points"][k].kept_boxes) == 0


def test_default_pipeline_masks_the_mover_and_nothing_on_a_static_scene():
    frames, _, _, masks = pan_scene(12)
    out = run(frames, SMALL)
    ious = [(o.mask & m).sum() / (o.mask | m).sum() for o, m in zip(out, masks)]
    assert np.mean(ious) > 0.6
    still, _, _, _ = pan_scene(12, with_mover=False)
    out = run(still, SMALL)
    assert max(o.mask.mean() for o in out) < 0.01


def test_streaming_gives_one_mask_per_frame_in_order_with_bounded_buffers():
    frames, _, _, _ = pan_scene(23)
    masker = MonaMasker(SMALL)
    indices = [100 + 2 * k for k in range(len(frames))]     # any increasing frame indices
    out, most = [], 0
    for i, f in zip(indices, frames):
        out += masker.push(i, f)
        most = max(most, masker.buffered_frames(), len(masker._flows), len(masker._dyn))
    out += masker.flush()
    assert [o.index for o in out] == indices
    assert most <= SMALL.lag + 1
    assert all(o.mask.shape == (H, W) and o.mask.dtype == bool for o in out)
    assert set(out[3].seconds) >= {"flow", "tracking", "dynamic_points", "motion_map",
                                   "detection", "box_filter", "segmentation"}


def test_segmenting_on_a_worker_changes_when_masks_arrive_not_what_they_are():
    # The worker segments frame t while the caller analyses frame t + 1 (and the VO steps): the
    # masks, their stability and reliability must equal the synchronous ones, repeats included,
    # and each arrives exactly one push later.
    frames, _, _, _ = pan_scene(14)
    stream = [(k, f) for k, f in enumerate(frames)]
    stream.insert(6, (6, frames[5]))                  # frame 6 repeats frame 5
    stream = [(i, f) for i, (_, f) in enumerate(stream)]
    got, arrival = {}, {}
    for flag in (False, True):
        masker = MonaMasker(dataclasses.replace(SMALL, segment_async=flag))
        out, when = [], []
        for n, (i, f) in enumerate(stream):
            new = masker.push_repeat(i) if i == 6 else masker.push(i, f)
            out += new
            when += [n] * len(new)
        out += masker.flush()
        got[flag], arrival[flag] = out, when
    sync, asyn = got[False], got[True]
    assert [o.index for o in asyn] == [o.index for o in sync] == list(range(len(stream)))
    assert sync[6].repeat_of == 5 and asyn[6].repeat_of == 5
    assert sum(o.mask.any() for o in sync) >= 8       # the comparison is of masks, not blanks
    for a, b in zip(sync, asyn):
        assert np.array_equal(a.mask, b.mask)
        assert a.reliable == b.reliable
        assert a.stability == b.stability or (np.isnan(a.stability) and np.isnan(b.stability))
    later = [b - a for a, b in zip(arrival[False], arrival[True])]
    assert later and set(later) == {1}


class _FailingSegmenter(Segmenter):
    """Fails on the given frame, as a neural back end does on a bad checkpoint or input."""

    def __init__(self, fail_at):
        self.fail_at = fail_at

    def segment(self, image, boxes=None, points=None, context=None):
        if context is not None and context.frame_index == self.fail_at:
            raise InputError(f"frame {self.fail_at}: the segmenter cannot read this image")
        return np.zeros(image.shape[:2], bool)


def test_an_error_on_the_worker_reaches_the_caller_with_its_message():
    frames, mover_boxes, _, _ = pan_scene(12)
    detector = ListDetector({k: [mover_boxes[k]] for k in range(12)})
    masker = MonaMasker(dataclasses.replace(SMALL, prompt="raw-boxes"), detector=detector,
                        segmenter=_FailingSegmenter(2))
    got = []
    with pytest.raises(InputError, match="frame 2: the segmenter"):
        for k, f in enumerate(frames):
            got += masker.push(k, f)
        got += masker.flush()
    assert [o.index for o in got] == [0, 1]      # the frames before it came out, in order


def test_compute_masks_takes_frame_objects_or_pairs_and_short_inputs():
    frames, _, _, _ = pan_scene(3)
    got = list(compute_masks([(7, frames[0])], SMALL))
    assert [g.index for g in got] == [7] and not got[0].mask.any()
    got = list(compute_masks(list(enumerate(frames)), SMALL))
    assert [g.index for g in got] == [0, 1, 2]


def test_bad_config_and_inputs_fail_clearly():
    with pytest.raises(ConfigError):
        MonaMasker(dataclasses.replace(SMALL, prompt="everything"))
    with pytest.raises(ConfigError):
        MonaMasker(dataclasses.replace(SMALL, detector="nonexistent"))
    masker = MonaMasker(SMALL)
    masker.push(0, np.zeros((H, W, 3), np.uint8))
    with pytest.raises(InputError):
        masker.push(1, np.zeros((H + 1, W, 3), np.uint8))


# Measured with this configuration (DAVIS car-shadow and dog, frames 0-19 at half resolution,
# 427 x 240, default back ends): J 0.57 and 0.78. The floor sits 0.1 below the lower one: a
# regression that loses the mover in a few more frames fails it.
DAVIS_J_FLOOR = 0.47


@pytest.mark.parametrize("seq", ["car-shadow", "dog"])
def test_davis_region_similarity_above_measured_floor(shared_subdir, seq):
    from data_tools.davis import DavisSequence
    from eval.mask_metrics import evaluate_mask_sequence

    ds = DavisSequence(shared_subdir("davis2016"), seq)
    frames = [cv2.resize(f.image, (427, 240), interpolation=cv2.INTER_AREA)
              for f in ds.frames(max_frames=20)]
    gts = [cv2.resize(m.astype(np.uint8), (427, 240), interpolation=cv2.INTER_NEAREST) > 0
           for m, _ in zip(ds.masks(), range(20))]
    out = run(frames, MaskConfig())
    J = evaluate_mask_sequence([o.mask for o in out], gts).J_mean
    assert J > DAVIS_J_FLOOR


def test_texture_ref_keeps_flat_sky_from_seeding_movers_on_davis_parkour(shared_subdir):
    """With ``evidence.texture_ref`` (the default since stop 49) a residual where the image is
    flat is weak evidence unless its connected motion holds dynamic points
    (``texture_exempt_points``). Measured on parkour (a tuning sequence: a camera following a
    runner past a wall under a flat sky), with the camera `mona-vo masks` estimates, against
    ``texture_ref=0``: false-positive area 6.7 -> 4.8 % of the image, recall 0.93 -> 0.95 (the
    weight without the exemption, stop 33: 7.7 -> 3.5 %, recall 0.90 -> 0.87)."""
    from data_tools.davis import DavisSequence
    from mona_vo.pipeline import PipelineConfig, camera_ahead

    ds = DavisSequence(shared_subdir("davis2016_more"), "parkour")
    head = ds.frames()
    _, _, camera = camera_ahead(head, PipelineConfig(), head.width, head.height)
    frames = [f.image for f in ds.frames()]
    gts = list(ds.masks())
    stats = {}
    for ref in (0.0, MaskConfig().evidence.texture_ref):
        cfg = MaskConfig()
        cfg = dataclasses.replace(cfg, evidence=dataclasses.replace(cfg.evidence, texture_ref=ref))
        masks = [o.mask for o in compute_masks(list(enumerate(frames)), cfg, camera)]
        fp = np.mean([(m & ~g).mean() for m, g in zip(masks, gts)])
        recall = sum((m & g).sum() for m, g in zip(masks, gts)) / sum(g.sum() for g in gts)
        stats[ref] = fp, recall
    (fp_off, rec_off), (fp_on, rec_on) = stats.values()
    assert fp_on < 0.8 * fp_off
    assert rec_on > max(0.85, rec_off - 0.03)


def _context(motion_map=None, dynamic=(), tracked=None, prior=None, theta=0.5, residual=None):
    dyn = np.asarray(dynamic, np.float32).reshape(-1, 2)
    res = np.full(len(dyn), 10 * theta, np.float32) if residual is None else residual
    return FrameContext(0, motion_map, theta, 5.0, dyn, theta,
                        None if tracked is None else np.asarray(tracked, np.float32), prior, res)


def test_a_group_of_strong_dynamic_points_proposes_a_box_where_the_motion_map_is_blank():
    rng = np.random.default_rng(0)
    image = np.zeros((H, W, 3), np.uint8)
    blank = np.zeros((H // 2, W // 2), np.float32)     # the mover moves along its epipolar lines
    static = np.stack([rng.uniform(0, W, 200), rng.uniform(0, H, 200)], axis=1)
    mover = np.stack([rng.uniform(100, 140, 12), rng.uniform(40, 80, 12)], axis=1)
    static = static[~((static[:, 0] > 95) & (static[:, 0] < 145) & (static[:, 1] > 35)
                      & (static[:, 1] < 85))]
    det = MotionDetector(MotionDetectorConfig())
    boxes = det.detect(image, _context(blank, mover, np.concatenate([static, mover])))
    assert len(boxes) == 1
    x0, y0, x1, y1 = boxes.xyxy[0]
    assert x0 < mover[:, 0].min() and x1 > mover[:, 0].max()
    assert y0 < mover[:, 1].min() and y1 > mover[:, 1].max()
    # Four points are too few; and a dozen drifting tracks scattered among many static ones
    # (a minority of the tracked points where they are) propose nothing.
    assert len(det.detect(image, _context(blank, mover[:4], np.concatenate([static, mover])))) == 0
    scattered = static[:12]
    assert len(det.detect(image, _context(blank, scattered, static))) == 0
    # Points barely above theta_t (parallax of near static structure under a homography, as a
    # bush on DAVIS dog: 2-3 px per frame at theta 1.1) propose nothing either.
    weak = np.full(len(mover), 2.0 * 0.5, np.float32)
    assert len(det.detect(image, _context(blank, mover, np.concatenate([static, mover]),
                                          residual=weak))) == 0


def test_the_carried_mask_is_proposed_only_where_dynamic_points_support_it():
    image = np.zeros((H, W, 3), np.uint8)
    prior = np.zeros((H // 2, W // 2), bool)
    prior[20:40, 50:70] = True                        # analysis pixels: full-res x 100..140
    det = MotionDetector(MotionDetectorConfig())
    inside = [(120.0, 60.0)]
    assert len(det.detect(image, _context(None, inside, prior=prior))) == 1
    assert len(det.detect(image, _context(None, [(10.0, 10.0)], prior=prior))) == 0


def test_overlapping_boxes_merge_into_their_union():
    xyxy = [(0, 0, 10, 10), (4, 0, 20, 10), (30, 30, 40, 40), (39, 39, 60, 60)]
    boxes, score = merge_boxes(np.array(xyxy, np.float32), np.array([1, 3, 2, 1], np.float32),
                               0.5)
    np.testing.assert_array_equal(boxes, [(0, 0, 20, 10), (30, 30, 40, 40), (39, 39, 60, 60)])
    np.testing.assert_array_equal(score, [3, 2, 1])   # corners touching 1 % stay apart


def test_guided_refinement_moves_a_blocky_mask_edge_onto_the_image_edge():
    image = np.full((60, 80, 3), 40, np.uint8)
    image[:, 37:] = 220                               # the object: columns 37 and right
    for offset in (4, -4):                            # upsampled mask edge 4 px off, each side
        edge = 37 + offset
        soft = np.zeros((60, 80), np.float32)
        soft[:, edge + 1:] = 1.0
        soft[:, edge - 1:edge + 1] = 0.5
        out = refine_edges(image, soft, radius=8, eps=0.01) > 0.5
        cols = np.nonzero(out[30])[0]
        assert abs(cols.min() - 37) <= 1 and cols.max() == 79


def test_seeded_evidence_finds_slow_movers_the_frame_threshold_misses_and_no_static_motion(render):
    """``masks.evidence.seeded_noise_factor`` (off by default): generated tuning scene mixed 4,
    a creeping camera and two people walking slowly across (0.1-0.5 px per frame against a
    frame threshold of 0.7): measured J 0.00 -> 0.37. Static scene 207, a street walk where a
    homography window leaves 86 parallax points "dynamic": the false-positive area must not
    grow (measured 4.0 % either way, the default's own false positives)."""
    from data_tools.synthetic import SceneConfig
    from eval.mask_metrics import region_similarity
    from mona_vo.pipeline import PipelineConfig

    cfg = MaskConfig()
    seeded = dataclasses.replace(cfg, evidence=dataclasses.replace(cfg.evidence,
                                                                   seeded_noise_factor=6.0))
    guess = PipelineConfig().guessed_intrinsics(640, 272)    # the camera it was measured on

    def scores(preset, seed):
        """J and false-positive area of both configs, as eval.mask_bench.synthetic_rows gives
        them, on one rendering of the scene."""
        _, frames = render(SceneConfig(width=640, height=272, n_frames=24, preset=preset,
                                       seed=seed))
        out = {}
        for name, config in (("base", cfg), ("grown", seeded)):
            masks = [m.mask for m in compute_masks(((f.index, f.image) for f in frames), config,
                                                   guess)]
            out[name] = {"J": np.mean([region_similarity(m, f.mask) for m, f in zip(masks, frames)]),
                         "fp_area": np.mean([np.mean(m & ~f.mask) for m, f in zip(masks, frames)])}
        return out["base"], out["grown"]

    base, grown = scores("mixed", 4)
    assert grown["J"] > base["J"] + 0.2
    assert grown["fp_area"] < 0.02
    base, grown = scores("static", 207)
    assert grown["fp_area"] <= base["fp_area"] + 1e-3


def test_an_object_detectors_box_stays_while_the_evidence_follows_its_object():
    """With an object detector (here one that boxes the true mover, labelled as ``yolo`` labels
    its boxes), a box the paper's filter drops in a frame (too few dynamic points on it there)
    stays while the accumulated evidence still follows its object. Measured on one-large seed
    0 (16 frames, 320 x 136): frames 8-10 lose the filter's vote and keep the car (IoU 0.95);
    without this rule DAVIS J with a perfect detector fell from 0.653 / 0.591 to 0.542 / 0.574
    (tuning / validation)."""
    from data_tools.synthetic import SceneConfig, SyntheticScene
    from eval.mask_bench import TrueBoxDetector

    scene = SyntheticScene(SceneConfig(width=320, height=136, n_frames=16, preset="one-large",
                                       seed=0))
    rendered = [scene.render(i) for i in range(len(scene))]
    truth = {i: f.mask for i, f in enumerate(rendered)}
    out = list(compute_masks(((i, f.image) for i, f in enumerate(rendered)),
                             MaskConfig(), detector=TrueBoxDetector(truth)))
    held = [o for o in out if o.box_filter.keep.sum() == 0 and len(o.kept_boxes)]
    assert len(held) >= 2
    for o in held:
        gt = truth[o.index]
        assert np.count_nonzero(o.mask & gt) / np.count_nonzero(o.mask | gt) > 0.9


class _WanderingFlow(DISFlow):
    """DIS flow, but forward in time a patch of static wall gets 3 px per frame of motion that
    is not there, as a flat region's flow can wander; the flow back in time is DIS's own."""

    PATCH = (slice(70, 100), slice(150, 200))   # rows, columns of the full-size frame

    def __init__(self):
        super().__init__()
        self._order: list[int] = []

    def _rank(self, image) -> int:
        key = id(image)
        if key not in self._order:
            self._order.append(key)
        return self._order.index(key)

    def compute_resized(self, image0, image1, width, height):
        flow, m_t = super().compute_resized(image0, image1, width, height)
        if self._rank(image0) < self._rank(image1):
            sx, sy = width / image0.shape[1], height / image0.shape[0]
            rows, cols = self.PATCH
            r = slice(int(rows.start * sy), int(rows.stop * sy))
            c = slice(int(cols.start * sx), int(cols.stop * sx))
            flow = flow.copy()
            flow[r, c, 1] += 3.0 * sy
        return flow, m_t


def test_the_flow_check_gives_no_motion_where_the_flow_does_not_come_back():
    frames, _, _, masks = pan_scene(12)
    rows, cols = _WanderingFlow.PATCH
    patch = np.zeros((H, W), bool)
    patch[rows, cols] = True
    assert not any((m & patch).any() for m in masks)      # the patch is static wall
    plain = run(frames, SMALL, flow=_WanderingFlow())
    checked = run(frames, dataclasses.replace(SMALL, flow_check_px=1.0), flow=_WanderingFlow())
    spill = [max((o.mask & patch).sum() / patch.sum() for o in out) for out in (plain, checked)]
    assert spill[0] > 0.3 and spill[1] < 0.05
    ious = [(o.mask & m).sum() / (o.mask | m).sum() for o, m in zip(checked, masks)]
    assert np.mean(ious) > 0.6                              # the mover is still found
