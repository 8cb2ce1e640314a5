"""eval.track_bench: the tracker judged against the renderer's truth, along and across motion."""
import numpy as np
import pytest

from eval import track_bench
from mona_vo.conventions import Intrinsics, make_pose


def test_true_pixels_follow_the_camera():
    # A fronto-parallel wall 4 m away; the camera steps 0.1 m right: every pixel moves
    # fx * 0.1 / 4 = 10 px left, and an unmoved camera leaves it in place.
    intr = Intrinsics(400.0, 400.0, 160.0, 120.0)
    depth = np.full((240, 320), 4.0, np.float32)
    uv = np.array([[40.0, 30.0], [160.0, 120.0], [300.5, 200.25]])
    T0 = np.eye(4)
    np.testing.assert_allclose(track_bench.true_pixels(depth, uv, T0, T0, intr), uv, atol=1e-9)
    T1 = make_pose(np.eye(3), np.array([0.1, 0.0, 0.0]))
    moved = track_bench.true_pixels(depth, uv, T0, T1, intr)
    np.testing.assert_allclose(moved, uv - [10.0, 0.0], atol=1e-9)


def test_motion_blur_costs_the_tracker_along_the_motion_not_across_it():
    # Generated `mixed` seed 3, a fast turn (about 50 px of image motion per frame) whose frames
    # carry motion blur (shutter 0.73): tracked on its frames before the effects the tracks stay
    # within a few tenths of a pixel in both directions after 8 frames; with the blur they slide
    # along the motion (measured 2.05 px against 0.71 across; clean 0.14 / 0.15). The bench has to
    # see the difference, and see it in the right direction.
    rows = track_bench.benchmark(["mixed"], [3], n_frames=17, width=640, height=272,
                                 effects=("on", "off"), starts=(0, 8), max_age=8, quiet=True)
    blurred, clean = rows
    assert (blurred["effects"], clean["effects"]) == ("on", "off")
    assert blurred["flow_px"] > 30 and blurred["tracks"] > 200
    assert clean["along_end"] < 0.3 and clean["across_end"] < 0.3, clean
    assert blurred["along_end"] > 5 * clean["along_end"], (blurred, clean)
    assert blurred["along_end"] > 2 * blurred["across_end"], blurred


@pytest.mark.parametrize("argv, needle", [
    (["--frames", "10", "--starts", "0,8", "--max-age", "8"], "--frames (10)"),
    (["--size", "640by272"], "--size and --starts take numbers"),
    (["--seeds", "3-1"], "--seeds"),
])
def test_track_bench_refuses_bad_arguments_in_one_line(argv, needle, capsys):
    assert track_bench.main(argv + ["--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err, err


def test_vo_bench_renders_the_same_geometry_without_the_effects():
    # eval.vo_bench --effects off: the frames the effects start from (image_clean), with the
    # same poses and masks, so a trajectory with and without blur and noise can be compared.
    from data_tools.synthetic import SceneConfig, SyntheticScene
    from eval.vo_bench import render_sequence

    scene, frames, masks = render_sequence("mixed", 3, 4, 160, 68, effects=False)
    _, blurred, masks_on = render_sequence("mixed", 3, 4, 160, 68)
    truth = list(SyntheticScene(SceneConfig(width=160, height=68, n_frames=4, preset="mixed", seed=3)))
    for f, b, r, m, m_on in zip(frames, blurred, truth, masks, masks_on):
        np.testing.assert_array_equal(f.image, r.image_clean)
        np.testing.assert_array_equal(b.image, r.image)
        np.testing.assert_array_equal(m, m_on)
        assert np.abs(f.image.astype(int) - b.image).mean() > 1.0
    np.testing.assert_array_equal(scene.poses(), SyntheticScene(SceneConfig(
        width=160, height=68, n_frames=4, preset="mixed", seed=3)).poses())
