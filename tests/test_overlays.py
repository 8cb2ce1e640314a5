"""Burned-in overlays (logos, watermarks): found standing still in the first frames while the
picture moves, painted over before masks and VO, and reported."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from data_tools.frames import open_frames
from data_tools.overlays import KINDS, add_overlay, main, write_overlaid_copy
from mona_vo.config import apply_overrides
from mona_vo.overlays import find_overlay, hide_overlay
from mona_vo.pipeline import PipelineConfig, estimate_trajectory


class _F:
    def __init__(self, index, image):
        self.index, self.timestamp, self.name, self.image = index, float(index), f"{index:05d}", image


def _pan(n=10, h=160, w=320, step=6, seed=0):
    """A textured picture panning ``step`` px per frame."""
    g = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0, 255, (h, w + n * step)).astype(np.float32),
                         (0, 0), 2.0)
    g = cv2.normalize(g, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
    return [np.repeat(g[:, i * step:i * step + w, None], 3, axis=2) for i in range(n)]


def _truth(image, kind):
    return np.abs(add_overlay(image, kind).astype(int) - image).max(axis=2) > 0


def test_a_logo_is_found_where_it_is_and_nothing_else():
    frames = _pan()
    assert find_overlay(frames) is None                       # no overlay, none found
    logo = [add_overlay(f, "logo") for f in frames]
    ov = find_overlay(logo)
    truth = _truth(frames[0], "logo")
    assert ov is not None and ov[truth].mean() > 0.6          # most of the badge
    near = cv2.dilate(truth.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    assert not (ov & ~near).any()                             # nothing away from it


def test_a_semi_transparent_watermark_is_found_by_its_edges_not_its_level():
    # 60 % opacity: the scene shows through, so the mark's level follows the texture passing
    # behind it; its edges stay the same in every frame.
    import dataclasses
    from mona_vo.overlays import OverlayConfig

    frames = [add_overlay(f, "watermark") for f in _pan()]
    truth = _truth(_pan(n=1)[0], "watermark")
    ov = find_overlay(frames)
    assert ov is not None and ov[truth].mean() > 0.8
    near = cv2.dilate(truth.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    assert not (ov & ~near).any()
    level_only = dataclasses.replace(OverlayConfig(), min_coherence=1.01)
    missed = find_overlay(frames, level_only)
    assert missed is None or missed[truth].mean() < 0.3        # the level test alone misses it


def test_an_edge_the_camera_moves_along_is_not_an_overlay():
    # A pan along a horizontal stripe (a horizon, a kerb): every pixel of it stays the same, as
    # an overlay's would, but its edges have one direction (the aperture problem).
    import dataclasses
    from mona_vo.overlays import OverlayConfig

    frames = _pan()
    for f in frames:
        f[12:18] = 240
    assert find_overlay(frames) is None
    found = find_overlay(frames, dataclasses.replace(OverlayConfig(), min_isotropy=0.0))
    assert found is not None and found[12:18].any()            # without the isotropy test


def test_no_overlay_is_told_from_a_still_camera_or_a_still_half_of_the_picture():
    still = [add_overlay(_pan(n=1)[0], "logo")] * 10         # a tripod: the scene stands too
    assert find_overlay(still) is None
    frames = [add_overlay(f, "logo") for f in _pan()]
    for f in frames:
        f[:, :120] = frames[0][:, :120]                       # a third of the picture stands
    assert find_overlay(frames) is None                       # too large for an overlay


def test_a_still_blob_inside_the_picture_is_a_followed_mover_not_an_overlay():
    frames = _pan()
    patch = _pan(n=1, h=40, w=60, seed=3)[0]
    for f in frames:
        f[60:100, 130:190] = patch                            # a car the camera keeps pace with
    assert find_overlay(frames) is None
    ov = find_overlay([add_overlay(f, "logo") for f in frames])
    assert ov is not None and not ov[60:100, 130:190].any() and ov[_truth(frames[0], "logo")].any()


def test_painted_over_the_logo_leaves_no_corner_there_and_keeps_the_frame():
    frames = [_F(i, add_overlay(f, "logo")) for i, f in enumerate(_pan())]
    ov = find_overlay([f.image for f in frames])
    hidden = list(hide_overlay(frames, ov))
    grey = cv2.cvtColor(hidden[3].image, cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(grey, 500, 0.01, 3)
    inside = [c for c in corners.reshape(-1, 2) if ov[int(c[1]), int(c[0])]]
    assert len(corners) > 50 and not inside
    assert np.array_equal(hidden[3].full, frames[3].image)
    assert np.array_equal(hidden[3].image[~ov], frames[3].image[~ov])


@pytest.fixture(scope="module")
def small_scene_frames(small_scene):
    folder, scene = small_scene
    return scene, [(f, m) for f, m in zip(open_frames(folder), (r.mask for r in scene))]


def test_overlays_painted_over_give_the_masks_back(small_scene_frames):
    # Central claim. The small scene (one-large, 384 x 164, MONA masks, true intrinsics) with a
    # badge and a watermark burned in: MONA takes the standing badge for a mover. Measured mean
    # J 0.090 (false positives 5.5 %) left in, 0.519 painted over; 0.839 without the overlays.
    # Until stop 30 only the badge was found (0.721): the car passes under the watermark, and
    # masks are not set inside an overlay, so painting the watermark too costs its pixels there
    # (the watermark alone: 0.875 left in, 0.720 painted over).
    from eval.mask_metrics import region_similarity

    scene, pairs = small_scene_frames
    frames = [_F(f.index, add_overlay(f.image, "both")) for f, _ in pairs]
    truth = [m for _, m in pairs]
    j = {}
    for hide in (True, False):
        js = []
        r = estimate_trajectory(frames, intrinsics=scene.intrinsics, masks="mona",
                                config=apply_overrides(PipelineConfig(), {"hide_overlays": hide}),
                                on_frame=lambda o: js.append(region_similarity(o.mask, truth[o.index])))
        j[hide] = float(np.mean(js))
        assert (r.overlay is not None) == hide
    assert j[True] > 0.45 and j[False] < 0.25 * j[True], j


def test_run_and_masks_report_the_overlay_and_copies_carry_it(small_scene, tmp_path):
    from mona_vo.run import masks_only, run

    folder, scene = small_scene
    assert write_overlaid_copy(folder, tmp_path / "logo", "logo") == 24
    k = scene.intrinsics
    report = run(tmp_path / "logo", tmp_path / "run", calib=f"{k.fx},{k.fy},{k.cx},{k.cy}",
                 masks="mona", progress=False)
    ov = report["overlay"]
    assert ov is not None and 0 < ov["area"] < 0.05
    x0, y0, x1, y1 = ov["boxes"][0]
    assert x0 < 20 and y0 < 20 and 60 < x1 < 110 and 20 < y1 < 45     # the badge, top left
    assert json.loads((tmp_path / "run" / "report.json").read_text())["overlay"] == ov
    only = masks_only(tmp_path / "logo", tmp_path / "masks", progress=False)
    assert only["overlay"] == ov
    plain = run(folder, tmp_path / "plain", calib=f"{k.fx},{k.fy},{k.cx},{k.cy}", masks="none",
                progress=False)
    assert plain["overlay"] is None
    assert main([str(tmp_path / "missing"), str(tmp_path / "x")]) == 1 and not (tmp_path / "x").exists()
    with pytest.raises(ValueError, match="overlay kind"):
        add_overlay(np.zeros((8, 8, 3), np.uint8), "clock")
    assert set(KINDS) == {"logo", "watermark", "both"}


def test_the_vo_ends_tracks_under_an_overlay_and_flags_none():
    # An overlay is an occluder fixed in the image, not a mover: a track that reaches it ends
    # (as at the frame's border) and none starts there. Flagged as a mask's would be, every
    # landmark that passed under it was left out of the map for good.
    from mona_vo.conventions import pixels_in_mask
    from mona_vo.vo import VisualOdometry, VOConfig
    from mona_vo.vo_map import LandmarkFlag

    frames = _pan(n=12, step=4)
    occluded = np.zeros(frames[0].shape[:2], bool)
    occluded[:, 200:240] = True                      # the pan carries every point across it
    vo = VisualOdometry(VOConfig(), frames[0].shape[1], frames[0].shape[0], occluded=occluded)
    for i, f in enumerate(frames):
        vo.step(f, timestamp=float(i))
        live = vo.tracker.live()
        assert not pixels_in_mask(occluded, live.points[live.visible]).any()
    assert vo.drops["tracks_under_overlay"] > 0
    assert not (vo.map.landmarks.flags & np.uint8(LandmarkFlag.MASKED)).any()
