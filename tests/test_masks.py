"""The streamed MONA mask pipeline: prompt modes, streaming order and memory, real DAVIS data."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from mona_vo.detection import Boxes, Detector, FrameContext
from mona_vo.errors import ConfigError, InputError
from mona_vo.masks import MaskConfig, MonaMasker, compute_masks

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
# 427 x 240, default back ends): J 0.52 and 0.43. The floor sits 0.1 below the lower one: a
# regression that loses the mover in a few more frames fails it.
DAVIS_J_FLOOR = 0.33


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
