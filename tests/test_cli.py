"""Every command through the real `mona-vo` entry point, on small generated inputs."""
import json
import subprocess

import cv2
import numpy as np
import pytest

from data_tools.tum import read_tum_trajectory
from eval.metrics import Trajectory, evaluate_trajectory
from mona_vo.batch import clip_verdict, summary_from_report


def cli(exe, *args, ok=True):
    proc = subprocess.run([exe, "-q", *map(str, args)], capture_output=True, text=True, timeout=600)
    if ok:
        assert proc.returncode == 0, proc.stderr
    return proc


def test_help_of_every_command_explains_options(mona_vo_exe):
    out = cli(mona_vo_exe, "--help").stdout
    for command in ("run", "masks", "demo", "eval"):
        assert command in out
    run_help = cli(mona_vo_exe, "run", "--help").stdout
    for option in ("--calib", "--masks", "--prompt", "--overlay", "--out", "--set", "--preset"):
        assert option in run_help
    for sub in ("traj", "masks"):
        assert "--gt" in cli(mona_vo_exe, "eval", sub, "--help").stdout


def test_run_with_given_masks_writes_trajectory_masks_report_and_plot(mona_vo_exe, small_scene, tmp_path):
    folder, scene = small_scene
    out = tmp_path / "run"
    proc = cli(mona_vo_exe, "run", folder, "--out", out, "--calib", folder / "calib.txt",
               "--masks", folder / "masks", "--gt", folder / "groundtruth.txt")
    ts, poses = read_tum_trajectory(out / "trajectory.txt")
    assert len(ts) == len(scene) and np.array_equal(ts, np.arange(len(scene)))
    # The estimate is a real trajectory: close to GT after Sim(3) alignment.
    m = evaluate_trajectory(Trajectory(np.arange(len(scene), dtype=float), scene.poses()),
                            Trajectory(ts, poses))
    assert m.ate_percent_of_path < 5.0
    masks = sorted(p.name for p in (out / "masks").iterdir())
    assert masks == [f"{i:05d}.png" for i in range(len(scene))]
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == report["frames_with_pose"] == len(scene)
    assert report["calibration"]["source"] == "given"
    assert abs(report["calibration"]["fx"] - scene.intrinsics.fx) < 1e-6
    assert report["frames_per_second"]["total"] > 0
    assert set(report["dropped"]) >= {"ba_masked_observations", "ba_masked_landmarks"}
    # The self-checks batch's verdict reads, and that verdict, printed.
    assert report["global_refinement"]["keyframe_shift_pct"] >= 0
    assert report["pose_support"]["frames"] == len(scene) and report["pose_support"]["inliers_p10"] >= 12
    verdict = clip_verdict(summary_from_report(report)).text()
    assert proc.stdout.strip().splitlines()[-1] == f"verdict: {verdict}"
    plot = cv2.imread(str(out / "trajectory.png"))
    assert plot is not None and plot.shape[0] > 100 and plot.std() > 5
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "temporary files left behind"


def test_run_without_masks_and_without_calibration_uses_the_assumed_field_of_view(mona_vo_exe, small_scene,
                                                                                   tmp_path):
    folder, scene = small_scene
    out = tmp_path / "run"
    cli(mona_vo_exe, "run", folder, "--out", out, "--masks", "none", "--set", "calibration.mode=guess",
        "--set", "assumed_hfov_deg=75")
    assert not (out / "masks").exists()
    report = json.loads((out / "report.json").read_text())
    assert report["calibration"]["source"] == "75-degree field-of-view guess"
    width = report["image_size"][0]
    assert report["calibration"]["fx"] == pytest.approx(0.5 * width / np.tan(np.radians(75 / 2)))
    assert len(read_tum_trajectory(out / "trajectory.txt")[0]) == len(scene)


def test_eval_traj_prints_the_metrics_of_the_library(mona_vo_exe, small_scene, tmp_path):
    folder, scene = small_scene
    out = tmp_path / "run"
    cli(mona_vo_exe, "run", folder, "--out", out, "--calib", folder / "calib.txt", "--masks", "none")
    for align in ("sim3", "se3"):
        got = json.loads(cli(mona_vo_exe, "eval", "traj", "--gt", folder / "groundtruth.txt",
                             "--est", out / "trajectory.txt", "--align", align).stdout)
        assert set(got) >= {"ate", "rpe_trans", "rpe_rot_deg", "n_matched", "scale"}
        want = evaluate_trajectory(Trajectory(*read_tum_trajectory(folder / "groundtruth.txt")),
                                   Trajectory(*read_tum_trajectory(out / "trajectory.txt")), align=align)
        assert got["ate"] == pytest.approx(want.ate, abs=1e-12)
        assert got["n_matched"] == len(scene)
    # --frames A:B scores one part of the run, aligned alone.
    got = json.loads(cli(mona_vo_exe, "eval", "traj", "--gt", folder / "groundtruth.txt",
                         "--est", out / "trajectory.txt", "--frames", "2:9").stdout)
    t, T = read_tum_trajectory(out / "trajectory.txt")
    want = evaluate_trajectory(Trajectory(*read_tum_trajectory(folder / "groundtruth.txt")),
                               Trajectory(t[2:9], T[2:9]))
    assert got["n_matched"] == 7 and got["ate"] == pytest.approx(want.ate, abs=1e-12)
    # --scale-window N adds the estimate's scale per N steps, as the library computes it.
    got = json.loads(cli(mona_vo_exe, "eval", "traj", "--gt", folder / "groundtruth.txt",
                         "--est", out / "trajectory.txt", "--scale-window", "4").stdout)
    want = evaluate_trajectory(Trajectory(*read_tum_trajectory(folder / "groundtruth.txt")),
                               Trajectory(t, T), scale_window=4)
    assert got["window_scales"] == [dict(r) for r in want.window_scales]
    assert len(got["window_scales"]) == -(-(len(scene) - 1) // 4)
    bad = cli(mona_vo_exe, "eval", "traj", "--gt", folder / "groundtruth.txt", "--est",
              out / "trajectory.txt", "--scale-window", "-2", ok=False)
    assert bad.returncode != 0 and "scale window" in bad.stderr and "Traceback" not in bad.stderr
    bad = cli(mona_vo_exe, "eval", "traj", "--gt", folder / "groundtruth.txt", "--est",
              out / "trajectory.txt", "--frames", "5:6", ok=False)
    assert bad.returncode != 0 and "--frames" in bad.stderr and "Traceback" not in bad.stderr


def test_eval_traj_kitti_format(mona_vo_exe, shared_subdir):
    d = shared_subdir("evo_trajectories")
    got = json.loads(cli(mona_vo_exe, "eval", "traj", "--gt", d / "KITTI_00_gt.txt",
                         "--est", d / "KITTI_00_ORB.txt", "--format", "kitti", "--align", "se3").stdout)
    # evo's own stored APE of this pair (res_files/orb_ape.zip) is 1.3034497145650266.
    assert got["ate"] == pytest.approx(1.3034497145650266, abs=1e-6)


def test_eval_masks_on_davis_gt(mona_vo_exe, shared_subdir):
    gt = shared_subdir("davis2016") / "Annotations" / "480p" / "dog"
    got = json.loads(cli(mona_vo_exe, "eval", "masks", "--pred", gt, "--gt", gt).stdout)
    assert got == {"J_mean": 1.0, "F_mean": 1.0, "n_frames": 40}


def test_errors_are_one_line_with_the_path_and_exit_1(mona_vo_exe, tmp_path):
    missing = tmp_path / "nope.mp4"
    proc = cli(mona_vo_exe, "run", missing, "--out", tmp_path / "o", ok=False)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(missing) in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "o" / "trajectory.txt").exists()
    proc = cli(mona_vo_exe, "run", tmp_path, "--out", tmp_path / "o", "--calib", "1,2,3", ok=False)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr


def test_masks_command_writes_one_mask_per_frame(mona_vo_exe, small_scene, tmp_path):
    folder, scene = small_scene
    out = tmp_path / "m"
    cli(mona_vo_exe, "masks", folder, "--out", out, "--max-frames", 12)
    masks = sorted(p.name for p in (out / "masks").iterdir())
    assert masks == [f"{i:05d}.png" for i in range(12)]
    # The generated mover is found: some frames have a non-empty mask overlapping the truth.
    from data_tools.masks_io import read_mask_png

    overlaps = [(read_mask_png(out / "masks" / n) & read_mask_png(folder / "masks" / n)).sum() for n in masks]
    assert sum(o > 0 for o in overlaps) >= 6


def test_masks_command_uses_the_camera_run_uses(mona_vo_exe, small_scene, tmp_path):
    """Without --calib, `masks` and `run` give MONA the same camera (the focal length estimated
    from the first frames, else the guess), so `masks` writes the masks `run` computes."""
    folder, _ = small_scene
    cli(mona_vo_exe, "masks", folder, "--out", tmp_path / "m", "--max-frames", 12)
    cli(mona_vo_exe, "run", folder, "--out", tmp_path / "r", "--max-frames", 12, "--masks", "none")
    masks = json.loads((tmp_path / "m" / "masks_report.json").read_text())["calibration"]
    run = json.loads((tmp_path / "r" / "report.json").read_text())["calibration"]
    assert masks["fx"] == pytest.approx(run["fx"]) and masks["source"] == run["source"]
    assert (masks["focal_estimate"] is None) == (run["focal_estimate"] is None)
    cli(mona_vo_exe, "masks", folder, "--out", tmp_path / "g", "--max-frames", 12,
        "--set", "calibration.mode=guess", "--set", "assumed_hfov_deg=75")
    guess = json.loads((tmp_path / "g" / "masks_report.json").read_text())["calibration"]
    assert guess["source"] == "75-degree field-of-view guess" and guess["focal_estimate"] is None
    assert guess["fx"] == pytest.approx(0.5 * 384 / np.tan(np.radians(75 / 2)))


def test_demo_prints_the_three_variants_and_where_its_outputs_are(mona_vo_exe, tmp_path):
    proc = cli(mona_vo_exe, "demo", "--size", "384x164", "--frames", 16, "--out", tmp_path / "d")
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("synthetic 'one-large' scene, seed 5, 16 frames 384x164")
    for label in ("no masks", "MONA masks", "GT masks"):
        row = next(line for line in lines if label in line)
        ate = float(row.split("ATE ")[1].split(" m")[0])
        assert 0 <= ate < 10
    assert (tmp_path / "d" / "mona" / "trajectory.txt").exists()
    assert lines[-2].startswith(f"outputs in {tmp_path / 'd'}: ")
    plot = lines[-1].split()[1]
    assert lines[-1].startswith("open ") and cv2.imread(plot) is not None


def test_bench_without_the_peer_reports_every_method(mona_vo_exe, tmp_path):
    out = tmp_path / "bench.json"
    proc = cli(mona_vo_exe, "bench", "--presets", "one-large", "--frames", 12, "--size", "320x136",
               "--no-peer", "--out", out)
    rows = json.loads(out.read_text())
    assert [r["method"] for r in rows] == ["mona-vo (none)", "mona-vo (mona)", "mona-vo (gt)"]
    assert all(r["frames_posed"] == 12 for r in rows)
    assert "| method |" in proc.stdout and "peak memory" in proc.stdout


# ---------------------------------------------------------------- bad arguments: one line, exit 1

def _src(tmp_path, small_scene):
    return small_scene[0]


BAD_ARGS = [
    # (argv, words the one line must hold)
    (["demo", "--preset", "bogus"], ["--preset", "bogus", "one-large"]),
    (["bench", "--presets", "bogus", "--no-peer"], ["--presets", "bogus"]),
    (["bench", "--seeds", "two"], ["--seeds", "two"]),
    (["demo", "--frames", "1"], ["--frames"]),
    (["run", "{src}", "--out", "{out}", "--set", "vo.keyframe_max_gap=0"], ["vo.keyframe_max_gap", ">= 1"]),
    (["run", "{src}", "--out", "{out}", "--set", "vo.ba.max_iterations=-1"], ["vo.ba.max_iterations", ">= 1"]),
    (["run", "{src}", "--out", "{out}", "--set", "masks.dynamic_points.window=1"],
     ["masks.dynamic_points.window", ">= 2"]),
    (["run", "{src}", "--out", "{out}", "--set", "vo.grid_sise=3"], ["vo.grid_sise", "vo.grid_size"]),
    (["run", "{src}", "--out", "{out}", "--config", "{missing}"], ["not found"]),
    (["run", "{src}", "--out", "{out}", "--preset", "bogus"], ["--preset", "bogus"]),
    (["run", "{src}", "--out", "{out}", "--stride", "x"], ["--stride", "x"]),
    (["run", "{src}", "--out", "{out}", "--stride", "0"], ["stride"]),
    (["run", "{src}", "--out", "{out}", "--refine", "maybe"], ["--refine", "maybe"]),
    (["run", "{src}", "--out", "{out}", "--device", "gpu"], ["'device'", "gpu"]),
    (["run", "{src}"], ["--out"]),
    (["run", "{src}", "--out", "{out}", "--bogus"], ["--bogus"]),
    (["masks", "{src}", "--out", "{out}", "-q", "--set", "masks.prompt=all"], ["masks.prompt", "all"]),
    (["--set", "vo.grid_size=3", "eval", "traj", "--gt", "a", "--est", "b"], ["--set", "eval traj"]),
    (["--preset", "fast", "demo"], ["--preset", "demo"]),
    (["eval", "sintel", "--root", "{src}", "--out", "{out}", "--workers", "0"], ["--workers"]),
    (["eval", "tum", "--root", "{src}", "--out", "{out}", "--variants", "gt"], ["gt"]),
    (["eval", "traj", "--gt", "{missing}", "--est", "{missing}"], ["{missing}"]),
    (["eval", "two-view", "--image0", "a", "--image1", "b", "--calib", "1,1,1,1", "--gt-poses", "p",
      "--gt-rows", "x"], ["--gt-rows"]),
    (["config", "--set", "assumed_hfov_deg=200"], ["assumed_hfov_deg", "[10, 170]"]),
    (["nonsense"], ["nonsense"]),
]


@pytest.mark.parametrize("argv, words", BAD_ARGS, ids=[" ".join(a[:4]) for a, _ in BAD_ARGS])
def test_bad_arguments_give_one_line_and_exit_1(mona_vo_exe, small_scene, tmp_path, argv, words):
    fill = {"src": str(small_scene[0]), "out": str(tmp_path / "o"), "missing": str(tmp_path / "missing.yaml")}
    argv = [a.format(**fill) for a in argv]
    proc = subprocess.run([mona_vo_exe, *argv], capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for word in words:
        assert word.format(**fill) in lines[0], lines[0]
    assert not (tmp_path / "o" / "trajectory.txt").exists()


def test_shared_options_go_before_or_after_the_command(mona_vo_exe, small_scene, tmp_path):
    folder, _ = small_scene
    a, b = tmp_path / "a", tmp_path / "b"
    # -q and the config options after the command, then before it: the same run.
    cli(mona_vo_exe, "run", folder, "--out", a, "--masks", "none", "--max-frames", 12, "--quiet",
        "--set", "vo.grid_size=12", "--preset", "fast")
    subprocess.run([mona_vo_exe, "--quiet", "--preset", "fast", "--set", "vo.grid_size=12", "run",
                    str(folder), "--out", str(b), "--masks", "none", "--max-frames", "12"],
                   check=True, capture_output=True, timeout=600)
    assert (a / "trajectory.txt").read_bytes() == (b / "trajectory.txt").read_bytes()
    ra, rb = (json.loads((d / "report.json").read_text())["config"] for d in (a, b))
    assert ra == rb and ra["vo"]["grid_size"] == 12 and ra["vo"]["window_keyframes"] == 6
    # --set before and after the command add up; the one after wins on the same key.
    proc = subprocess.run([mona_vo_exe, "--set", "vo.grid_size=10", "--set", "vo.refine=none", "config",
                           "--set", "vo.grid_size=14", "-q"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "  grid_size: 14" in proc.stdout and "  refine: none" in proc.stdout
    proc = subprocess.run([mona_vo_exe, "masks", str(folder), "--out", str(tmp_path / "m"), "-q",
                           "--max-frames", "10"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0 and not proc.stderr, proc.stderr    # -q: no progress bar on stderr


def test_printed_config_loads_back_and_reproduces_the_default_run(mona_vo_exe, small_scene, tmp_path):
    folder, _ = small_scene
    yaml_path = tmp_path / "default.yaml"
    text = cli(mona_vo_exe, "config").stdout
    assert "# point tracker of the masks and of the VO" in text and "tracker: lk" in text
    yaml_path.write_text(text)
    a, b = tmp_path / "a", tmp_path / "b"
    common = ["--masks", "none", "--calib", folder / "calib.txt", "--max-frames", 16]
    cli(mona_vo_exe, "run", folder, "--out", a, *common)
    cli(mona_vo_exe, "run", folder, "--out", b, "--config", yaml_path, *common)
    assert (a / "trajectory.txt").read_bytes() == (b / "trajectory.txt").read_bytes()
    ra, rb = (json.loads((d / "report.json").read_text())["config"] for d in (a, b))
    assert ra == rb


@pytest.mark.parametrize("command", [["run", "x", "--out", "o"], ["eval", "sintel", "--root", "r", "--out", "o"],
                                     ["eval", "tum", "--root", "r", "--out", "o"]])
def test_refine_option_is_the_config_key(command):
    from mona_vo.cli import _merge_shared, _pipeline_config, build_parser

    def config(*extra):
        args = build_parser().parse_args([*command, *extra])
        _merge_shared(args)
        return _pipeline_config(args)

    assert config().vo.refine == "global"
    assert config("--refine", "none") == config("--set", "vo.refine=none") != config()
    # An explicit option beats the YAML file; --set beats both.
    assert config("--refine", "none", "--set", "vo.refine=global").vo.refine == "global"
