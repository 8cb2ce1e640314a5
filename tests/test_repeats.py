"""Repeated frames (pulldown, a stalled stream): told apart from motion by their blocks' grey
levels, not processed, and given the pose and mask of the frame they repeat."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from data_tools.frames import open_frames
from data_tools.masks_io import read_mask_png
from data_tools.repeats import shown_images, shown_order, write_stuttered_copy
from mona_vo.config import apply_overrides
from mona_vo.masks import compute_masks
from mona_vo.pipeline import PipelineConfig, estimate_trajectory
from mona_vo.repeats import RepeatDetector, block_difference


class _F:
    def __init__(self, index, image):
        self.index, self.timestamp, self.name, self.image = index, float(index), f"{index:05d}", image


def _texture(seed=0, h=128, w=192):
    g = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0, 255, (h, w)).astype(np.float32),
                         (0, 0), 1.5)
    g = cv2.normalize(g, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
    return np.repeat(g[:, :, None], 3, axis=2)


def _jpeg(image, q):
    return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, q])[1], cv2.IMREAD_UNCHANGED)


def test_a_repeat_differs_by_coding_noise_and_motion_by_far_more():
    img = _texture()
    assert block_difference(img, img) == 0.0
    # The same picture coded twice at different qualities (a coder's requantised repeat).
    assert block_difference(_jpeg(img, 90), _jpeg(img, 80)) <= 2.5
    # One pixel of camera motion, or a small mover alone in a still frame, is no repeat.
    assert block_difference(img, np.roll(img, 1, axis=1)) > 2.5 * 3
    moved = img.copy()
    moved[40:56, 60:72] = np.roll(img[40:56, 60:72], 2, axis=1)
    assert block_difference(img, moved) > 2.5


def test_repeats_are_judged_against_the_last_distinct_frame_and_never_flat_frames():
    img = _texture()
    det = RepeatDetector(2.5)
    step1, step2 = img.copy(), img.copy()
    step1[:48, :48] = np.clip(img[:48, :48].astype(int) + 2, 0, 255)
    step2[:48, :48] = np.clip(img[:48, :48].astype(int) + 4, 0, 255)
    # A slow drift: each frame 2 levels from the one before, the third 4 from the first.
    assert [det.is_repeat(f) for f in (img, step1, step2, step2)] == [False, True, False, True]
    flat = np.full_like(img, 128)
    # A blank stretch shows nothing of where the camera is: it repeats nothing.
    assert [det.is_repeat(f) for f in (flat, flat, flat)] == [False, False, False]
    assert not RepeatDetector(0.0).is_repeat(img) and not RepeatDetector(0.0).is_repeat(img)


def test_shown_orders_of_pulldown_and_stutter():
    assert shown_order(8, "pulldown") == [0, 1, 2, 3, 3, 4, 5, 6, 7, 7]
    assert shown_order(10, "stutter") == [0, 1, 2, 3, 3, 5, 6, 7, 8, 8]
    imgs = [_texture(s) for s in range(4)]
    coded = shown_images(imgs, "pulldown-jpeg")
    assert len(coded) == 5 and 0 < block_difference(coded[3], coded[4]) <= 2.5
    with pytest.raises(ValueError, match="repeat kind"):
        shown_order(4, "blend")


@pytest.fixture(scope="module")
def pulldown(small_scene):
    """The shared small scene (one-large, 384 x 164, 24 frames) and the same frames shown with
    every fourth twice."""
    folder, scene = small_scene
    frames = list(open_frames(folder))
    order = shown_order(len(frames), "pulldown")
    shown = [_F(k, frames[i].image) for k, i in enumerate(order)]
    return scene, frames, shown, order


def test_masks_of_repeats_are_their_frames_and_the_rest_as_without_repeats(pulldown):
    scene, frames, shown, order = pulldown
    plain = [mf.mask for mf in compute_masks(frames, intrinsics=scene.intrinsics)]
    out = list(compute_masks(shown, intrinsics=scene.intrinsics, repeat_max_diff=2.5))
    assert [mf.index for mf in out] == list(range(len(shown)))
    for k, mf in enumerate(out):
        assert np.array_equal(mf.mask, plain[order[k]])
        is_rep = k > 0 and order[k] == order[k - 1]
        assert mf.repeat_of == (k - 1 if is_rep else -1)
    assert any(m.any() for m in plain)


def test_a_clip_with_repeats_gets_the_trajectory_and_masks_of_its_distinct_frames(pulldown):
    # Central claim. Taken as repeats, the shown clip's distinct frames get exactly the poses
    # of the clip without repeats (MONA masks, true intrinsics), and its masks hold. Fed as
    # frames (repeat_max_diff=0), a repeat is a frame without motion between frames with
    # motion, and the masks lose the car: measured mean J over the shown frames 0.840 taken,
    # 0.087 fed. (The trajectory fed the repeats is not always worse: on the generated `mixed`
    # parts it is better on about half the sequences, README Results.)
    from eval.mask_metrics import region_similarity

    scene, frames, shown, order = pulldown
    gts = [r.mask for r in scene]
    plain = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks="mona")
    j = {"taken": [], "fed": []}
    taken = estimate_trajectory(shown, intrinsics=scene.intrinsics, masks="mona", on_frame=lambda o:
                                j["taken"].append(region_similarity(o.mask, gts[order[o.index]])))
    rep = taken.repeat_of
    assert list(np.flatnonzero(rep >= 0)) == [k for k in range(1, len(order)) if order[k] == order[k - 1]]
    np.testing.assert_array_equal(taken.vo.poses[rep < 0], plain.vo.poses)
    np.testing.assert_array_equal(taken.vo.poses[rep >= 0], taken.vo.poses[rep[rep >= 0]])
    assert taken.vo.is_keyframe.sum() == plain.vo.is_keyframe.sum()
    assert taken.vo.map_segments == [(0, len(shown) - 1)]
    np.testing.assert_array_equal(taken.vo.timestamps, np.arange(len(shown), dtype=float))

    fed = estimate_trajectory(shown, intrinsics=scene.intrinsics, masks="mona",
                              config=apply_overrides(PipelineConfig(), {"repeat_max_diff": 0}),
                              on_frame=lambda o: j["fed"].append(
                                  region_similarity(o.mask, gts[order[o.index]])))
    assert fed.repeat_of is not None and not (fed.repeat_of >= 0).any()
    jt, jf = float(np.mean(j["taken"])), float(np.mean(j["fed"]))
    assert jt > 0.7 and jf < 0.5 * jt, (jt, jf)


def test_a_clip_of_one_picture_stands_still_and_is_flagged():
    # A tripod on a still scene: every frame after the first is a repeat of it. Each gets the
    # first frame's pose (the VO's one frame: where the camera is, rotation-only) and is flagged.
    img = _texture()
    r = estimate_trajectory([_F(i, img) for i in range(5)], masks=None)
    assert list(r.repeat_of) == [-1, 0, 0, 0, 0]
    np.testing.assert_array_equal(r.vo.poses, np.repeat(np.eye(4)[None], 5, axis=0))
    assert r.vo.low_confidence.all() and not r.vo.is_keyframe.any()


def test_run_and_masks_report_repeats_of_a_stuttered_folder(small_scene, tmp_path):
    from data_tools.repeats import main
    from mona_vo.run import masks_only, run

    folder, scene = small_scene
    assert main([str(folder), str(tmp_path / "stutter")]) == 0
    k = scene.intrinsics
    report = run(tmp_path / "stutter", tmp_path / "run", calib=f"{k.fx},{k.fy},{k.cx},{k.cy}",
                 masks="mona", progress=False)
    names = [f.name for f in open_frames(folder)]
    expect = {names[i]: names[i - 1] for i in range(4, len(names), 5)}
    assert report["repeated_frames"] == expect
    saved = json.loads((tmp_path / "run" / "report.json").read_text())
    assert saved["repeated_frames"] == expect
    for held, source in expect.items():
        assert saved["frame_status"][held] == saved["frame_status"][source]
        assert np.array_equal(read_mask_png(tmp_path / "run" / "masks" / f"{held}.png"),
                              read_mask_png(tmp_path / "run" / "masks" / f"{source}.png"))
    only = masks_only(tmp_path / "stutter", tmp_path / "masks", progress=False)
    assert only["repeated_frames"] == expect and only["frames"] == len(names)
    assert main([str(tmp_path / "missing"), str(tmp_path / "x")]) == 1
