"""DAVIS sequences and mask PNG files: real masks, round trips, folder checks."""
from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

from data_tools.davis import DavisSequence, list_sequences
from data_tools.masks_io import read_mask_folder, read_mask_png, write_mask_png
from mona_vo.errors import InputError


def test_real_davis_car_shadow(shared_subdir):
    root = shared_subdir("davis2016")
    assert list_sequences(root) == ["car-shadow", "dog"]
    seq = DavisSequence(root, "car-shadow")
    src = seq.frames()
    assert len(src) == 40 and (src.width, src.height) == (854, 480)
    assert src.names[0] == "00000" and src.timestamps[-1] == 39.0
    assert seq.mask_names == seq.names
    masks = seq.masks(size=(854, 480))
    assert len(masks) == 40
    raw = cv2.imread(str(masks.paths[20]), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(raw)) == {0, 255}  # binary on disk
    mask = masks[20]
    assert mask.dtype == bool and mask.shape == (480, 854)
    assert np.array_equal(mask, raw == 255)
    assert 0.01 < mask.mean() < 0.5  # the car: present, not the whole image


def test_davis_unknown_sequence_lists_known_ones(shared_subdir):
    with pytest.raises(InputError, match=r"no such sequence \(JPEGImages/480p has car-shadow, dog\)"):
        DavisSequence(shared_subdir("davis2016"), "cows")


def test_mask_png_round_trip_is_0_255_on_disk(tmp_path):
    mask = np.zeros((6, 9), bool)
    mask[2:4, 3:7] = True
    path = tmp_path / "sub" / "m.png"
    write_mask_png(path, mask)
    assert set(np.unique(cv2.imread(str(path), cv2.IMREAD_UNCHANGED))) == {0, 255}
    assert np.array_equal(read_mask_png(path), mask)


def test_any_nonzero_value_or_colour_is_foreground(tmp_path):
    grey = np.array([[0, 1], [7, 0]], np.uint8)
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    assert read_mask_png(tmp_path / "g.png").tolist() == [[False, True], [True, False]]
    colour = np.zeros((2, 2, 3), np.uint8)
    colour[0, 1] = (0, 0, 128)  # a DAVIS-2017 style object colour
    cv2.imwrite(str(tmp_path / "c.png"), colour)
    assert read_mask_png(tmp_path / "c.png").tolist() == [[False, True], [False, False]]


def test_unreadable_mask_names_the_file(tmp_path):
    bad = tmp_path / "m.png"
    bad.write_bytes(b"garbage")
    with pytest.raises(InputError, match=re.escape(f"{bad}: cannot decode mask")):
        read_mask_png(bad)
    with pytest.raises(InputError, match=re.escape(f"{tmp_path / 'x.png'}: cannot read mask")):
        read_mask_png(tmp_path / "x.png")


def test_write_mask_rejects_non_2d():
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        write_mask_png("unused.png", np.zeros((2, 2, 3), bool))


def make_masks(folder, names, size=(9, 6)):
    for name in names:
        write_mask_png(folder / f"{name}.png", np.ones((size[1], size[0]), bool))


def test_mask_folder_matches_frame_names_with_dots(tmp_path):
    names = ["1548339827.58438", "1548339827.6179"]
    make_masks(tmp_path, names)
    masks = read_mask_folder(tmp_path, names, size=(9, 6))
    assert [p.name for p in masks.paths] == ["1548339827.58438.png", "1548339827.6179.png"]
    assert all(m.all() and m.shape == (6, 9) for m in masks)


def test_mask_folder_problems_name_folder_and_files(tmp_path):
    names = [f"{i:05d}" for i in range(10)]
    make_masks(tmp_path, names[1:])
    with pytest.raises(InputError, match=re.escape(f"{tmp_path}: no mask for 1 of 10 frames: 00000.png")):
        read_mask_folder(tmp_path, names)
    with pytest.raises(InputError, match=re.escape(
            f"{tmp_path}: 7 masks match no frame: 00003.png, 00004.png, 00005.png, 00006.png, "
            "00007.png, ... (7 in all)")):
        read_mask_folder(tmp_path, names[1:3])
    assert len(read_mask_folder(tmp_path, names[1:3], allow_extra=True)) == 2
    with pytest.raises(InputError, match=re.escape(f"{tmp_path}: mask 00001.png is 9x6, the frames are 8x6")):
        read_mask_folder(tmp_path, names[1:], size=(8, 6))
    with pytest.raises(InputError, match="mask folder not found"):
        read_mask_folder(tmp_path / "none", names)


def test_mask_bench_davis_with_the_focal_length_run_estimates(shared_subdir):
    """By default (`--calib estimate`) the bench hands the masker the camera `mona-vo masks` and
    `run` would estimate (car-shadow: the reconstruction takes a focal length about 13 % below
    the 60-degree guess's 740 px); `--calib guess` the guess."""
    from eval.mask_bench import davis_rows

    root = shared_subdir("davis2016")
    guess, = davis_rows(root, ("car-shadow",), max_frames=6, calib="guess")
    est, = davis_rows(root, ("car-shadow",), max_frames=6)
    assert "focal_px" not in guess
    assert 500 < est["focal_px"] < 0.95 * 739.6
    assert 0.0 <= est["J"] <= 1.0 and est["frames"] == 6


def test_gt_box_prompts_measure_the_segmenter_alone():
    """`--modes gt-boxes`: the segmenter prompted with the true mask's part boxes. A flat disk on
    a textured ground is cut out from its box (IoU > 0.75; the segmenter dilates its masks by a few pixels); a frame without a mover gets
    an empty mask, and two parts get two boxes (both disks found)."""
    from eval.mask_bench import gt_box_masks
    from eval.mask_metrics import region_similarity
    from mona_vo.masks import MaskConfig

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (120, 160, 3), np.uint8)
    yy, xx = np.mgrid[:120, :160]
    one = (xx - 50) ** 2 + (yy - 60) ** 2 < 25 ** 2
    two = one | ((xx - 125) ** 2 + (yy - 40) ** 2 < 15 ** 2)
    painted = image.copy()
    painted[two] = (200, 40, 40)
    masks = gt_box_masks([painted, painted, image], [one, two, np.zeros_like(one)], MaskConfig())
    assert region_similarity(masks[0][:, :100], one[:, :100]) > 0.75
    assert region_similarity(masks[1], two) > 0.75
    assert not masks[2].any()


def test_gt_box_prompts_on_generated_scenes_measure_the_segmenter_alone():
    """The mask bench's generated part with `--modes gt-boxes`: the same frames and truth as
    the method's row, the segmenter prompted with the true boxes. On one-large seed 0 (a flat
    car, 8 frames) it cuts the car out (measured J 0.95 against the method's 0.82)."""
    from eval.mask_bench import synthetic_rows

    kw = dict(n_frames=8, width=320, height=136, calib="guess")   # the camera it was measured on
    oracle, = synthetic_rows(("one-large",), (0,), mode="gt-boxes", **kw)
    method, = synthetic_rows(("one-large",), (0,), **kw)
    assert oracle["frames"] == method["frames"] == 8
    assert oracle["gt_area"] == pytest.approx(method["gt_area"])
    assert oracle["J"] > 0.9 and oracle["fp_area"] < 0.03


def test_a_perfect_object_detector_through_the_method():
    """`--modes gt-detector`: the whole method with a detector that boxes every mover and
    nothing else, labelled as an object detector (``yolo``) labels its boxes: the paper's box
    filter still asks for dynamic points, the segmenter starts from the whole box and the
    motion evidence only keeps a box the filter drops while it holds an object followed.
    Measured (8 frames, 320 x 136): one-large seed 0 J 0.95 (the method's motion boxes 0.82),
    several seed 1 0.91 (the method finds none of its movers: 0.00)."""
    from eval.mask_bench import synthetic_rows

    kw = dict(n_frames=8, width=320, height=136, calib="guess")   # the camera it was measured on
    for preset, seed in (("one-large", 0), ("several", 1)):
        row, = synthetic_rows((preset,), (seed,), mode="gt-detector", **kw)
        assert row["J"] > 0.85 and row["fp_area"] < 0.03, row
    method, = synthetic_rows(("several",), (1,), **kw)
    assert method["J"] < 0.5


def test_the_generated_mask_bench_gives_the_masker_the_products_camera():
    """`python -m eval.mask_bench --parts synthetic` scores the masks a run without `--calib`
    makes: the masker gets the focal length estimated from the first frames, not the 60-degree
    guess. Generated `mixed` seed 5 has a 79-degree field of view (the guess is 41 % long);
    measured (16 frames, 320 x 136): estimate 1.6 % off the true focal length."""
    from eval.mask_bench import synthetic_rows

    row, = synthetic_rows(("mixed",), (5,), n_frames=16, width=320, height=136)
    assert abs(row["focal_error_pct"]) < 5.0
    guessed, = synthetic_rows(("mixed",), (5,), n_frames=16, width=320, height=136,
                              calib="guess")
    assert guessed["focal_error_pct"] > 30.0
    with pytest.raises(ValueError, match="calib"):
        synthetic_rows(("mixed",), (5,), n_frames=4, width=64, height=32, calib="true")


def test_generated_mask_rows_say_where_the_pixels_go():
    """The generated part's rows split a low J as DAVIS rows do (found, spill, apart) and say in
    how many of the frames with a mover the mask touches it at all, so that a mover never found
    is told from a mask found late or too large. `--calib given` hands the masker the scene's
    true camera (focal error 0), to tell a focal-length error from a missed mover. Measured (8
    frames, 320 x 136): the true boxes cut one-large seed 0's car in every frame (found 1.00,
    spill 0.05, apart 0); the method, given the true camera, finds none of several seed 1's
    movers in any frame (J 0.00, found 0.00)."""
    from eval.mask_bench import synthetic_rows

    kw = dict(n_frames=8, width=320, height=136)
    oracle, = synthetic_rows(("one-large",), (0,), mode="gt-boxes", **kw)
    assert oracle["frames_found"] == 1.0
    assert oracle["found"] > 0.9 and oracle["apart"] < 0.02
    missed, = synthetic_rows(("several",), (1,), calib="given", **kw)
    assert missed["focal_error_pct"] == 0.0
    assert missed["found"] < 0.05 and missed["frames_found"] < 0.2, missed


def test_the_generated_mask_bench_renders_without_the_effects_when_asked(monkeypatch):
    """`python -m eval.mask_bench --parts synthetic --effects off` scores the masks of the same
    scenes before their image effects (blur, noise, exposure, JPEG), to read what the effects
    cost the masks; the default keeps them."""
    from eval import mask_bench

    seen = []

    class Stop(Exception):
        pass

    def fake(**kw):
        seen.append(kw)
        raise Stop

    monkeypatch.setattr(mask_bench, "synthetic_rows", fake)
    base = ["--parts", "synthetic", "--presets", "mixed", "--seeds", "3", "--frames", "4", "--size", "64x32"]
    for extra, want in (([], True), (["--effects", "off"], False), (["--effects", "on"], True)):
        with pytest.raises(Stop):
            mask_bench.main(base + extra)
        assert seen[-1]["effects"] is want, (extra, seen[-1])


@pytest.mark.parametrize("flag,value", [("--seeds", "3-1"), ("--seeds", "a"), ("--size", "64"),
                                        ("--size", "8x8")])
def test_the_mask_bench_refuses_bad_seeds_and_sizes_in_one_line(flag, value, capsys):
    """A bad --seeds or --size is a one-line usage error naming the flag, before anything runs
    (it read the seeds with its own loop before, and a typo ended in a traceback)."""
    from eval import mask_bench

    argv = ["--parts", "synthetic", "--presets", "mixed", "--seeds", "3", "--size", "64x32"]
    argv[argv.index(flag) + 1] = value
    with pytest.raises(SystemExit) as exit_info:
        mask_bench.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("python -m eval.mask_bench: error: " + flag), err
    assert value in err[-1]
