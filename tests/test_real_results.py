"""The real-data results of docs/RESULTS.md, in small: flow end-point error on the real Sintel pair,
two-view initialisation on KITTI 06 frames 12 -> 13, the prompt-strip picture, and a slow real start
that must not starve the VO's map (Bonn crowd). Skipped with a reason when the shared real data is
absent."""
import json
import os
import subprocess

import numpy as np
import pytest

# Measured with `mona-vo eval flow` on alley_1 0002 -> 0003 (clean), the default dis back end
# (medium preset at half resolution): EPE 0.47 px over the valid non-occluded pixels, 0.52 px
# over all valid pixels; the GT flow's mean length is 2.98 px. The bounds leave 0.1 px of room.
DIS_EPE_NOC_MAX_PX = 0.6
DIS_EPE_ALL_MAX_PX = 0.65
# The VO issue's two-view initialisation target on KITTI 06 12 -> 13 (1.19 m ahead, 0.12 deg).
INIT_ROTATION_MAX_DEG = 1.0
INIT_DIRECTION_MAX_DEG = 5.0


def cli(exe, *args, env=None):
    return subprocess.run([exe, "-q", *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)


@pytest.fixture(scope="module")
def sintel_pair(shared_subdir):
    root = shared_subdir("sintel_clip_alley") / "training"
    files = {"image0": root / "clean/alley_1/frame_0002.png",
             "image1": root / "clean/alley_1/frame_0003.png",
             "gt": root / "flow/alley_1/frame_0002.flo",
             "occlusions": root / "occlusions/alley_1/frame_0002.png",
             "invalid": root / "invalid/alley_1/frame_0002.png"}
    missing = [str(p) for p in files.values() if not p.is_file()]
    if missing:
        pytest.skip(f"real test data absent: {', '.join(missing)}")
    return files


def _flow_args(files):
    return [a for k, v in files.items() for a in (f"--{k}", v)]


def test_dis_flow_end_point_error_on_real_sintel_pair_is_below_measured_bound(mona_vo_exe, sintel_pair):
    proc = cli(mona_vo_exe, "eval", "flow", *_flow_args(sintel_pair), "--flow", "dis")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert (r["width"], r["height"]) == (1024, 436)
    assert r["n_noc"] < r["n_all"] <= 1024 * 436          # occluded pixels left out of epe_noc
    assert r["epe_noc"] < DIS_EPE_NOC_MAX_PX
    assert r["epe_noc"] < r["epe_all"] < DIS_EPE_ALL_MAX_PX
    assert 2.5 < r["gt_mean_magnitude"] < 3.5             # the .flo was read as u, v pixels
    assert r["ms_per_pair"] > 0


def test_raft_flow_without_checkpoint_fails_with_one_line_naming_the_file(mona_vo_exe, sintel_pair):
    env = {k: v for k, v in os.environ.items() if k != "MONA_VO_WEIGHTS"}
    proc = cli(mona_vo_exe, "eval", "flow", *_flow_args(sintel_pair), "--flow", "raft", env=env)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mona-vo: error:")
    assert "raft_large_C_T_SKHT_V2-ff5fadd5.pth" in lines[0] and "MONA_VO_WEIGHTS" in lines[0]


def test_end_point_error_counts_only_valid_pixels():
    from eval.flow_eval import end_point_error

    gt = np.zeros((4, 5, 2), np.float32)
    est = gt.copy()
    est[0, 0] = (3.0, 4.0)                                 # one pixel 5 px off
    valid = np.ones((4, 5), bool)
    assert end_point_error(est, gt) == pytest.approx(5.0 / 20)
    valid[0, 0] = False
    assert end_point_error(est, gt, valid) == 0.0


def test_two_view_init_on_kitti_12_13_meets_the_vo_target(mona_vo_exe, shared_subdir):
    k = shared_subdir("kitti06")
    proc = cli(mona_vo_exe, "eval", "two-view", "--image0", k / "image_0/000012.png",
               "--image1", k / "image_0/000013.png", "--calib", k / "calib.txt",
               "--gt-poses", k / "poses.txt", "--gt-rows", "0,1")
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout)
    assert r["gt_translation_m"] == pytest.approx(1.19, abs=0.01)   # frame_ids.txt: rows 0, 1 = 12, 13
    assert r["rotation_error_deg"] < INIT_ROTATION_MAX_DEG
    assert r["translation_direction_error_deg"] < INIT_DIRECTION_MAX_DEG
    assert r["inliers"] >= 40                                       # the VO's init_min_inliers


def test_two_view_rejects_rows_outside_the_pose_file(mona_vo_exe, shared_subdir):
    k = shared_subdir("kitti06")
    proc = cli(mona_vo_exe, "eval", "two-view", "--image0", k / "image_0/000012.png",
               "--image1", k / "image_0/000013.png", "--calib", k / "calib.txt",
               "--gt-poses", k / "poses.txt", "--gt-rows", "0,99")
    assert proc.returncode == 1
    assert "row 99 out of range" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


def test_prompt_strip_of_two_small_frames_has_one_cell_per_frame_and_mode():
    from data_tools.synthetic import SceneConfig, SyntheticScene
    from eval import figures

    scene = SyntheticScene(SceneConfig(width=192, height=96, n_frames=2, preset="one-large", seed=0))
    frames = [(i, scene.render(i).image) for i in range(2)]
    cell_w, cell_h = 96, 48
    image = figures.prompt_strip(frames, cell_width=cell_w, title="two frames")
    top = figures.TITLE_HEIGHT_PX + figures.COLUMN_LABEL_HEIGHT_PX
    assert image.dtype == np.uint8
    assert image.shape == (top + 3 * (cell_h + figures.GAP_PX),
                           figures.LABEL_WIDTH_PX + 2 * (cell_w + figures.GAP_PX), 3)
    for r in range(3):                                    # every cell holds a drawn frame
        for c in range(2):
            y = top + r * (cell_h + figures.GAP_PX)
            x = figures.LABEL_WIDTH_PX + c * (cell_w + figures.GAP_PX)
            assert image[y:y + cell_h, x:x + cell_w].std() > 5
    assert image[:, :figures.LABEL_WIDTH_PX].min() < 128  # row labels were written


def test_picture_too_large_for_lossless_png_is_written_with_a_palette_under_the_limit(tmp_path):
    from PIL import Image

    from eval.figures import write_png

    noise = np.random.default_rng(0).integers(0, 256, (700, 700, 3), dtype=np.uint8)  # 1.5 MB raw
    path = write_png(tmp_path / "noise.png", noise, max_bytes=1_000_000, target_bytes=600_000)
    assert path.stat().st_size < 1_000_000
    with Image.open(path) as im:
        assert im.mode == "P" and im.size == (700, 700)


# Bonn crowd frames 0-224 (a slow pan of a static office with a little translation) without masks,
# `vo.grid_size=15`: with the fixed 0.3 deg ray angle the map starved (PnP inliers median 66,
# ATE 5.1 cm over the 0.69 m path); taking new landmarks at 0.1 deg while it is short of them,
# 186 inliers and 1.25 cm (measured on stop 48's host). The test runs the first 150 frames, where
# the start is slow, in two thirds of the time: 67 inliers and 4.03 cm against 166 and 0.58 cm
# (stop 50's host).
SLOW_START_FRAMES = 150
SLOW_START_MAX_ATE_M = 0.025


def _bonn_slow_start(exe, root, out, *extra):
    proc = cli(exe, "run", root / "rgb", "--calib", root / "calib.txt", "--masks", "none",
               "--max-frames", SLOW_START_FRAMES, "--out", out, "--set", "vo.grid_size=15",
               # The rule alone, as measured: the rolling shutter's pass (stop 57) feeds the
               # map too (the rule off: 163 inliers with it, 67 without).
               "--set", "vo.rolling_shutter=off", *extra)
    assert proc.returncode == 0, proc.stderr
    ev = cli(exe, "eval", "traj", "--gt", root / "groundtruth.txt", "--est", out / "trajectory.txt",
             "--max-diff", 0.02)
    assert ev.returncode == 0, ev.stderr
    report = json.loads((out / "report.json").read_text())
    return json.loads(ev.stdout)["ate"], report["pose_support"]["inliers_median"]


def test_a_slow_real_start_keeps_its_map_fed_with_landmarks(mona_vo_exe, shared_subdir, tmp_path):
    root = shared_subdir("bonn_crowd_long")
    ate, inliers = _bonn_slow_start(mona_vo_exe, root, tmp_path / "on")
    ate_off, inliers_off = _bonn_slow_start(mona_vo_exe, root, tmp_path / "off",
                                            "--set", "vo.triangulation_starved_angle_deg=0")
    assert ate < SLOW_START_MAX_ATE_M
    assert inliers > 1.5 * inliers_off and ate_off > 2 * ate     # the rule is what feeds it


def test_the_trajectory_picture_draws_each_curve_in_its_colour_and_takes_any_length(tmp_path):
    """trajectory.png (OpenCV since stop 52): the ground truth grey, the estimate blue, the start
    green, low-confidence frames red, in both views; one frame, a camera that never moved and a
    NaN pose still give a picture, written under its final name only."""
    import cv2

    from eval.plots import plot_trajectory

    t = np.linspace(0.0, 1.0, 40)
    gt = np.stack([np.sin(3 * t), 0.1 * t, t], axis=1)
    est = gt + 0.01 * np.random.default_rng(0).standard_normal(gt.shape)
    path = plot_trajectory(tmp_path / "t.png", est, gt, title="clip",
                           low_confidence=np.arange(40) % 10 == 5)
    image = cv2.imread(str(path))
    assert image is not None and image.shape == (495, 1100, 3)
    half = image.shape[1] // 2
    for colour in ((128, 128, 128), (180, 119, 31), (44, 160, 44), (40, 39, 214)):
        near = np.all(np.abs(image.astype(int) - colour) <= 12, axis=2)
        assert near[:, :half].sum() > 20 and near[:, half:].sum() > 20, colour
    def grey(im):
        return int(np.all(np.abs(im.astype(int) - (128, 128, 128)) <= 12, axis=2).sum())

    plain = cv2.imread(str(plot_trajectory(tmp_path / "p.png", est)))
    assert grey(plain) < 0.2 * grey(image)            # without GT, only the text's antialiasing
    for odd in (est[:1], np.zeros((5, 3)), np.vstack([est[:3], [[np.nan] * 3]])):
        assert cv2.imread(str(plot_trajectory(tmp_path / "odd.png", odd))) is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odd.png", "p.png", "t.png"]
