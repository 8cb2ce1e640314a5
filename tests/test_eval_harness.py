"""The dataset harness through the real commands: `eval sintel` on a generated Sintel-layout
root (with GT masks), resuming, one broken sequence not stopping the others, and `eval tum` on a
generated TUM-layout folder with exact GT and on the real Bonn crowd clip."""
import csv
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from data_tools.synthetic import SceneConfig, SyntheticScene, write_sintel
from data_tools.tum import read_tum_trajectory, write_tum_layout, write_tum_trajectory


def cli(exe, *args):
    return subprocess.run([exe, "-q", *map(str, args)], capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def sintel_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("sintel")
    for preset, seed in (("one-large", 0), ("several", 1)):
        scene = SyntheticScene(SceneConfig(width=384, height=164, n_frames=16, preset=preset, seed=seed))
        write_sintel(scene, root, seq=f"syn_{preset}")
    return root


def _rows(out):
    with open(out / "results.csv") as f:
        return list(csv.DictReader(f))


def test_eval_sintel_writes_tables_and_trajectories_and_resumes(mona_vo_exe, sintel_root, tmp_path):
    out = tmp_path / "eval"
    args = ["eval", "sintel", "--root", sintel_root, "--pass", "clean", "--seqs", "syn_one-large,syn_several",
            "--variants", "none,gt", "--masks-root", sintel_root / "training" / "moving_masks", "--out", out]
    proc = cli(mona_vo_exe, *args)
    assert proc.returncode == 0, proc.stderr
    rows = _rows(out)
    assert {(r["sequence"], r["variant"]) for r in rows} == {
        (s, v) for s in ("syn_one-large", "syn_several") for v in ("none", "gt")}
    assert all(r["status"] == "ok" and float(r["ate"]) >= 0 for r in rows)
    assert all(int(r["frames_with_pose"]) == int(r["frames"]) == 16 for r in rows)
    # Trajectories are TUM files stamped with the Sintel frame numbers (frame_0001 -> 1).
    ts, _ = read_tum_trajectory(out / "gt" / "syn_several" / "trajectory.txt")
    assert np.array_equal(ts, np.arange(1, 17))
    summary = json.loads((out / "results.json").read_text())["summary"]
    assert {s["variant"] for s in summary} == {"none", "gt"}
    md = (out / "results.md").read_text()
    assert "| Method | ATE (m) | RPE trans. (m) | RPE rot. (deg)" in md and "ground-truth masks" in md
    # The same command again skips every finished run.
    stamp = (out / "gt" / "syn_several" / "result.json").stat().st_mtime_ns
    assert cli(mona_vo_exe, *args).returncode == 0
    assert (out / "gt" / "syn_several" / "result.json").stat().st_mtime_ns == stamp


def test_one_broken_sequence_does_not_stop_the_others(mona_vo_exe, sintel_root, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(sintel_root, root)
    (root / "training" / "clean" / "syn_several" / "frame_0005.png").write_bytes(b"\x89PNG broken")
    out = tmp_path / "eval"
    args = ["eval", "sintel", "--root", root, "--pass", "clean", "--seqs", "syn_one-large,syn_several",
            "--variants", "none", "--out", out]
    proc = cli(mona_vo_exe, *args)
    assert proc.returncode == 1
    rows = {r["sequence"]: r for r in _rows(out)}
    assert rows["syn_one-large"]["status"] == "ok"
    assert rows["syn_several"]["status"].startswith("failed") and "frame_0005.png" in rows["syn_several"]["status"]
    # Rerun: the good run is kept, the failed one is retried (and fails again, reported).
    stamp = (out / "none" / "syn_one-large" / "result.json").stat().st_mtime_ns
    cli(mona_vo_exe, *args)
    assert (out / "none" / "syn_one-large" / "result.json").stat().st_mtime_ns == stamp
    assert "frame_0005.png" in _rows(out)[1]["status"]


def test_eval_sintel_rejects_a_root_without_camdata(mona_vo_exe, sintel_root, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(sintel_root, root)
    shutil.rmtree(root / "training" / "camdata_left")
    proc = cli(mona_vo_exe, "eval", "sintel", "--root", root, "--pass", "clean", "--seqs", "syn_several",
               "--variants", "none", "--out", tmp_path / "o")
    assert proc.returncode == 1 and "camdata_left" in proc.stderr and "Traceback" not in proc.stderr


def test_eval_tum_on_a_generated_tum_folder_with_exact_gt(mona_vo_exe, tmp_path):
    scene = SyntheticScene(SceneConfig(width=384, height=164, n_frames=16, preset="static", seed=2))
    stamps = 1311868164.0 + np.arange(len(scene)) / 30.0
    root = tmp_path / "tum_seq"
    write_tum_layout(root, stamps, (f.image for f in scene), scene.poses(), scene.intrinsics)
    out = tmp_path / "eval"
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out", out)
    assert proc.returncode == 0, proc.stderr
    row = _rows(out)[0]
    assert row["status"] == "ok" and int(row["n_matched"]) == 16
    ts, _ = read_tum_trajectory(out / "none" / "tum_seq" / "trajectory.txt")
    assert np.allclose(ts, stamps, atol=1e-6)   # stamped with rgb.txt's times
    assert float(row["ate_percent_of_path"]) < 5.0
    # Beside the metrics, the verdict batch would give the run and the numbers it reads.
    assert row["usable"] in ("True", "False") and float(row["support_p10"]) >= 12
    assert float(row["global_shift_pct"]) >= 0


def test_eval_tum_can_ignore_the_folders_calibration_and_estimate_the_camera(mona_vo_exe, tmp_path):
    # `--calib estimate` runs the sequence as an online video: calib.txt is not read, the camera
    # is estimated, and each row says which camera it ran with and the focal length used.
    scene = SyntheticScene(SceneConfig(width=384, height=164, n_frames=16, preset="static", seed=2))
    stamps = 1311868164.0 + np.arange(len(scene)) / 30.0
    root = tmp_path / "tum_seq"
    write_tum_layout(root, stamps, (f.image for f in scene), scene.poses(), scene.intrinsics)
    for calib, out in ((None, tmp_path / "given"), ("estimate", tmp_path / "est")):
        args = ["eval", "tum", "--root", root, "--variants", "none", "--out", out]
        proc = cli(mona_vo_exe, *(args + (["--calib", calib] if calib else [])))
        assert proc.returncode == 0, proc.stderr
    given, est = _rows(tmp_path / "given")[0], _rows(tmp_path / "est")[0]
    assert given["camera"] == "given" and est["camera"] == "estimated"
    assert float(given["focal_px"]) == pytest.approx(scene.intrinsics.fx)
    assert float(est["focal_px"]) != pytest.approx(scene.intrinsics.fx)


def test_eval_tum_associates_within_20_ms_and_warns_when_frames_go_unmatched(mona_vo_exe, tmp_path):
    # The GT clock runs 15 ms behind the camera's on frames 6-11 (Bonn's streams drift this way):
    # the TUM tolerance (20 ms) still matches every frame; evo's 10 ms drops those six, and the
    # row and results.md say so, since RPE pairs then span the gap.
    scene = SyntheticScene(SceneConfig(width=384, height=164, n_frames=16, preset="static", seed=2))
    stamps = 1311868164.0 + np.arange(len(scene)) / 30.0
    root = tmp_path / "tum_seq"
    write_tum_layout(root, stamps, (f.image for f in scene), scene.poses(), scene.intrinsics)
    gt_stamps = stamps.copy()
    gt_stamps[6:12] += 0.015
    write_tum_trajectory(root / "groundtruth.txt", gt_stamps, scene.poses())
    out = tmp_path / "eval"
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out", out)
    assert proc.returncode == 0, proc.stderr
    row = _rows(out)[0]
    assert int(row["n_matched"]) == 16 and not row.get("warning")
    out10 = tmp_path / "eval10"
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out", out10,
               "--max-diff", "0.01")
    assert proc.returncode == 0, proc.stderr
    row = _rows(out10)[0]
    assert int(row["n_matched"]) == 10
    assert "only 10 of 16 poses matched" in row["warning"] and "warning" in proc.stdout
    assert "only 10 of 16 poses matched" in (out10 / "results.md").read_text()
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out",
               tmp_path / "bad", "--max-diff", "-1")
    assert proc.returncode == 1 and "--max-diff" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "bad").exists()


def test_eval_tum_on_the_bonn_crowd_clip(mona_vo_exe, shared_subdir, tmp_path):
    root = shared_subdir("bonn_crowd")
    out = tmp_path / "eval"
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out", out)
    assert proc.returncode == 0, proc.stderr
    row = _rows(out)[0]
    assert row["status"] == "ok" and int(row["frames_with_pose"]) == 53
    assert int(row["n_matched"]) == 53
    assert 0 < float(row["ate"]) < 0.2   # metres, over a 0.17 m path: a sanity bound, not a target


def _small_tum_folder(tmp_path, preset: str, seed: int) -> Path:
    """A 14-frame 320 x 136 generated sequence in TUM RGB-D layout, at ``tmp_path/tum_seq``."""
    scene = SyntheticScene(SceneConfig(width=320, height=136, n_frames=14, preset=preset, seed=seed))
    stamps = 1311868164.0 + np.arange(len(scene)) / 30.0
    root = tmp_path / "tum_seq"
    write_tum_layout(root, stamps, (f.image for f in scene), scene.poses(), scene.intrinsics)
    return root


def test_eval_tum_draws_run_once_per_value_and_summarise_the_spread(mona_vo_exe, tmp_path):
    """`--draws KEY=V1,V2`: every variant runs once per value, each into draws/KEY=V/, and
    draws.json gives per sequence and variant the ATE of every draw with their mean, median and
    range (which must agree with the draws' own result files); a bad key or value is a one-line
    error naming it, before anything runs."""
    root = _small_tum_folder(tmp_path, "one-large", 0)
    out = tmp_path / "eval"
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out", out,
               "--draws", "vo.grid_size=12,16", "--draws", "vo.keyframe_max_gap=4")
    assert proc.returncode == 0, proc.stderr
    names = ["vo.grid_size=12", "vo.grid_size=16", "vo.keyframe_max_gap=4"]
    ates = [json.loads((out / "draws" / n / "results.json").read_text())["runs"][0]["ate"]
            for n in names]
    s, = json.loads((out / "draws.json").read_text())["summary"]
    assert s["sequence"] == "tum_seq" and s["variant"] == "none" and s["ok"] == s["draws"] == 3
    assert [s["ate"][n] for n in names] == pytest.approx(ates)
    assert s["ate_mean"] == pytest.approx(np.mean(ates))
    assert s["ate_median"] == pytest.approx(np.median(ates))
    assert s["ate_min"] == pytest.approx(min(ates)) and s["ate_max"] == pytest.approx(max(ates))
    assert len(set(round(a, 9) for a in ates)) > 1      # the draws are different runs
    assert "tum_seq" in (out / "draws.md").read_text()
    for bad, named in (("vo.grid_sise=3", "vo.grid_sise"), ("vo.grid_size=1", "vo.grid_size"),
                       ("vo.grid_size", "--draws")):
        proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none",
                   "--out", tmp_path / "bad", "--draws", bad)
        assert proc.returncode != 0 and named in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1
        assert not (tmp_path / "bad" / "draws").exists()


def test_a_masks_draw_runs_only_the_variants_that_use_mona_masks(tmp_path, monkeypatch):
    """A ``masks.*`` draw would only repeat a no-mask run (and weigh it twice in the means)."""
    import eval.harness as harness

    seen = []

    def spy(sequences, variants, out_dir, **kw):
        seen.append((Path(out_dir).name, list(variants)))
        return []

    monkeypatch.setattr(harness, "evaluate", spy)
    harness.evaluate_draws([], ["none", "mona", "mona-points"], tmp_path,
                           [{"vo.grid_size": "15"}, {"masks.dynamic_points.seed": "2"}])
    assert seen == [("vo.grid_size=15", ["none", "mona", "mona-points"]),
                    ("masks.dynamic_points.seed=2", ["mona", "mona-points"])]


def test_verdict_quality_counts_what_a_curator_keeps_and_throws_away():
    from eval.vo_bench import verdict_quality

    nan = float("nan")
    rows = [{"ate_pct": a, "usable": u} for a, u in
            [(0.2, True), (0.4, True), (3.0, True), (0.8, False), (6.0, False), (nan, False)]]
    q = verdict_quality(rows, 1.0)
    assert (q["scored"], q["good"], q["usable"], q["usable_and_good"]) == (5, 3, 3, 2)
    assert q["precision"] == pytest.approx(2 / 3) and q["recall"] == pytest.approx(2 / 3)
    assert q["base_rate"] == pytest.approx(3 / 5)
    assert q["worst_usable_pct"] == 3.0 and q["best_unusable_pct"] == 0.8
    q = verdict_quality(rows, 5.0)
    assert q["precision"] == 1.0 and q["recall"] == pytest.approx(3 / 4)
    assert np.isnan(verdict_quality([], 1.0)["precision"])


def test_parts_score_rows_of_a_trajectory_aligned_alone(tmp_path):
    """`--parts NAME=A:B`: each run's ATE on its rows A to B-1, each part aligned alone (as
    `eval traj --frames`): a drift confined to the second half shows in that part only."""
    from eval.datasets import EvalSequence
    from eval.harness import parse_parts, score_parts
    from eval.metrics import Trajectory
    from mona_vo.errors import ConfigError

    t = np.arange(20, dtype=float)
    gt = np.tile(np.eye(4), (20, 1, 1))
    gt[:, 0, 3] = 0.1 * t                          # a straight walk ...
    gt[:, 1, 3] = 0.02 * np.sin(t)                 # ... with some sway (a Sim(3) needs it)
    est = gt.copy()
    est[10:, 2, 3] += 0.05 * (t[10:] - 10) ** 2 / 100   # drift in the second half only
    write_tum_trajectory(tmp_path / "trajectory.txt", t, est)
    seq = EvalSequence("walk", lambda: iter(()), 20, None, Trajectory(t, gt), max_diff=0.01)
    parts = parse_parts(["first=0:10,second=10:20", "beyond=15:30"])
    assert parts == {"first": (0, 10), "second": (10, 20), "beyond": (15, 30)}
    ate = score_parts(seq, tmp_path / "trajectory.txt", parts)
    assert ate["first"] < 1e-9 < ate["second"]
    assert ate["beyond"] is None                   # the run has 20 rows
    for bad in ("first", "first=0-10", "=0:10", "first=5:6", "a=0:5,a=5:10"):
        with pytest.raises(ConfigError, match="--parts"):
            parse_parts([bad])


def test_compare_draws_pairs_the_draws_of_two_runs():
    from eval.harness import compare_draws

    def summary(ates, tune):
        return [{"sequence": "s", "variant": "mona", "ate": ates,
                 "parts": {"tune": {"ate": tune}}}]

    base = summary({"g=1": 0.04, "g=2": 0.06, "g=3": 0.05}, {"g=1": 0.02, "g=2": 0.02, "g=3": None})
    new = summary({"g=1": 0.03, "g=2": 0.05, "g=3": 0.07}, {"g=1": 0.01, "g=2": 0.03, "g=3": 0.01})
    rows = {r["part"]: r for r in compare_draws(base, new)}
    assert rows["all"]["draws"] == 3 and rows["all"]["lower"] == 2
    assert rows["all"]["diff_mean"] == pytest.approx(0.0)
    assert rows["all"]["diff_se"] == pytest.approx(np.std([-0.01, -0.01, 0.02], ddof=1) / np.sqrt(3))
    assert rows["tune"]["draws"] == 2              # a draw that failed in either run is left out
    assert rows["tune"]["diff_mean"] == pytest.approx(0.0) and rows["tune"]["lower"] == 1


def test_eval_tum_parts_over_draws_and_eval_compare(mona_vo_exe, tmp_path):
    """The product's commands give what `eval traj --frames` gives for each part, per draw in
    draws.md, and `eval compare` pairs two such runs; a folder without draws.json is a one-line
    error."""
    root = _small_tum_folder(tmp_path, "static", 1)
    out = tmp_path / "eval"
    proc = cli(mona_vo_exe, "eval", "tum", "--root", root, "--variants", "none", "--out", out,
               "--draws", "vo.grid_size=12,16", "--parts", "a=0:7", "--parts", "b=7:14")
    assert proc.returncode == 0, proc.stderr
    s, = json.loads((out / "draws.json").read_text())["summary"]
    for draw in ("vo.grid_size=12", "vo.grid_size=16"):
        est = out / "draws" / draw / "none" / "tum_seq" / "trajectory.txt"
        traj = cli(mona_vo_exe, "eval", "traj", "--gt", root / "groundtruth.txt", "--est", est,
                   "--max-diff", "0.02", "--frames", "7:14")
        assert traj.returncode == 0, traj.stderr
        assert s["parts"]["b"]["ate"][draw] == pytest.approx(json.loads(traj.stdout)["ate"])
        row, = json.loads((out / "draws" / draw / "results.json").read_text())["runs"]
        assert row["parts"]["b"] == pytest.approx(s["parts"]["b"]["ate"][draw])
    assert "| tum_seq | none | b | 2 / 2 |" in (out / "draws.md").read_text()
    proc = cli(mona_vo_exe, "eval", "compare", "--base", out, "--new", out)
    assert proc.returncode == 0, proc.stderr
    assert "| tum_seq | none | b | 2 |" in proc.stdout and "+0.0000 +- 0.0000 | 0 of 2 |" in proc.stdout
    proc = cli(mona_vo_exe, "eval", "compare", "--base", tmp_path / "nothing", "--new", out)
    assert proc.returncode != 0 and "draws.json" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_vo_bench_compare_pairs_two_runs_by_sequence(tmp_path):
    """`python -m eval.vo_bench --compare BASE NEW`: rows paired by preset, seed and variant;
    the per-preset ratio is the geometric mean of the paired ratios; a pair that one run could
    not score is listed and left out of the means; a missing file is a one-line error."""
    from eval.vo_bench import compare_runs, main

    def row(seed, ate, j=float("nan")):
        return {"preset": "mixed", "seed": seed, "variant": "mona", "ate_pct": ate, "mask_j": j}

    base = [row(0, 0.2, 0.5), row(1, 0.4), row(2, 1.0), row(3, float("nan"))]
    new = [row(0, 0.1, 0.6), row(1, 0.4), row(2, 2.0), row(3, 0.3), row(9, 0.1)]
    pairs, summary = compare_runs(base, new)
    assert [p["seed"] for p in pairs] == [0, 1, 2, 3]
    assert [p["moved"] for p in pairs] == [True, False, True, False]
    s, = summary
    assert s["n"] == 3 and s["lower"] == 1 and s["higher"] == 1
    assert s["ratio"] == pytest.approx(1.0) and s["gmean_new"] == pytest.approx(s["gmean_base"])
    assert s["gmean_base"] == pytest.approx((0.2 * 0.4 * 1.0) ** (1 / 3))
    (tmp_path / "a.json").write_text(json.dumps({"rows": base}))
    (tmp_path / "b.json").write_text(json.dumps({"rows": new}))
    assert main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 0
    assert main(["--compare", str(tmp_path / "a.json"), str(tmp_path / "none.json")]) == 1


def test_vo_bench_draws_read_a_variant_against_no_masks_over_each_sequences_draws(tmp_path, capsys):
    """`python -m eval.vo_bench --draws KEY=V1,V2`: per sequence, the variant's and the
    baseline's median ATE over the draws both scored, their ratio and the worst draw's ratio;
    per variant, the geometric mean of the median ratios and the sequences where the variant is
    clearly lower on the median (< 0.9) and never clearly higher in one draw (<= 1.1), the
    central claim test's two bounds. Pairs are matched by draw, not by order; a draw the
    baseline could not score is left out. A bad --draws is a one-line error."""
    from eval.vo_bench import compare_runs, draw_ratios, main

    def row(seed, variant, draw, ate):
        return {"preset": "one-large", "seed": seed, "variant": variant, "draw": draw,
                "repeat": 0, "ate_pct": ate}

    rows = [row(0, "none", "g=1", 0.2), row(0, "none", "g=2", 5.0), row(0, "none", "g=3", 0.1),
            row(0, "mona", "g=3", 0.1), row(0, "mona", "g=1", 0.1), row(0, "mona", "g=2", 0.15),
            row(1, "none", "g=1", 0.2), row(1, "none", "g=2", float("nan")),
            row(1, "mona", "g=1", 0.3), row(1, "mona", "g=2", 0.1)]
    per_seq, per_variant = draw_ratios(rows)
    a, b = per_seq
    assert a["draws"] == 3 and a["median_pct"] == pytest.approx(0.1)
    assert a["baseline_median_pct"] == pytest.approx(0.2) and a["median_ratio"] == pytest.approx(0.5)
    assert a["worst_ratio"] == pytest.approx(1.0)           # g=3: 0.1 against 0.1
    assert b["draws"] == 1 and b["median_ratio"] == pytest.approx(1.5)
    v, = per_variant
    assert v["sequences"] == 2 and v["lower"] == 1 and v["never_higher"] == 1 and v["both"] == 1
    assert v["gmean_median_ratio"] == pytest.approx(np.sqrt(0.5 * 1.5))
    # --compare pairs runs by draw too.
    pairs, _ = compare_runs(rows, [dict(r, ate_pct=2 * r["ate_pct"]) for r in rows])
    assert all(p["ate_pct_new"] == pytest.approx(2 * p["ate_pct_base"]) for p in pairs
               if np.isfinite(p["ate_pct_base"]))
    assert main(["--presets", "one-large", "--seeds", "0", "--draws", "vo.grid_size"]) == 1
    assert main(["--presets", "one-large", "--seeds", "0", "--draws", "vo.no_such_key=1,2"]) == 1
    assert main(["--presets", "one-large", "--seeds", "0", "--readout", "1.5"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all("--draws" in e or "no_such_key" in e for e in err[:2]), err
    assert "--readout" in err[2] and "1.5" in err[2], err


def test_vo_bench_draws_give_both_vos_from_the_same_runs(tmp_path, capsys):
    """With the global refinement (the default) every row carries its sliding window's ATE
    too, and --draws writes and prints the ratios of both; with vo.refine=none there is one VO
    and one table, and its ATE is the refined runs' ate_pct_streaming."""
    from eval.vo_bench import draw_ratios, main

    args = ["--presets", "one-large", "--seeds", "0", "--variants", "none,gt", "--frames", "10",
            "--size", "256x110", "--draws", "vo.grid_size=12,16"]
    assert main(args + ["--out", str(tmp_path / "both.json")]) == 0
    assert "before the global refinement" in capsys.readouterr().out
    both = json.loads((tmp_path / "both.json").read_text())
    rows = both["rows"]
    assert any(r["ate_pct_streaming"] != r["ate_pct"] for r in rows), rows
    (seq,) = both["draws_streaming"]["per_sequence"]
    assert seq["median_ratio"] == pytest.approx(draw_ratios(rows, key="ate_pct_streaming")[0][0]["median_ratio"])
    assert seq["median_ratio"] != pytest.approx(both["draws"]["per_sequence"][0]["median_ratio"])
    assert main(args + ["--set", "vo.refine=none", "--out", str(tmp_path / "none.json")]) == 0
    assert "before the global refinement" not in capsys.readouterr().out
    one = json.loads((tmp_path / "none.json").read_text())
    assert one["draws_streaming"]["per_sequence"] == []
    assert [r["ate_pct"] for r in one["rows"]] == [r["ate_pct_streaming"] for r in rows]


def test_vo_bench_runs_a_speed_preset_as_mona_vo_does_and_a_bad_set_is_one_line(monkeypatch, capsys):
    """`python -m eval.vo_bench --preset NAME`: the benchmark gets the configuration
    `mona-vo --preset NAME` builds (the preset, then --set), so a preset's figures need no copy
    of its keys; an unknown --set key is a one-line error and exit 1, not a traceback."""
    import eval.vo_bench as vb
    from mona_vo.config import apply_overrides
    from mona_vo.pipeline import PipelineConfig
    from mona_vo.presets import PRESETS

    class Seen(Exception):
        pass

    def fake_benchmark(*args, config, **kwargs):
        raise Seen(config)

    monkeypatch.setattr(vb, "benchmark", fake_benchmark)
    with pytest.raises(Seen) as got:
        vb.main(["--preset", "accurate", "--set", "vo.window_keyframes=9", "--presets", "static"])
    cfg = got.value.args[0]
    want = apply_overrides(apply_overrides(PipelineConfig(), PRESETS["accurate"]),
                           {"vo.window_keyframes": "9"})
    assert cfg == want and cfg.vo.grid_size == 24 and cfg.vo.start_grid == 16
    with pytest.raises(Seen) as got:
        vb.main(["--presets", "static"])
    assert got.value.args[0] == PipelineConfig()
    assert vb.main(["--presets", "static", "--set", "vo.grid_sise=3"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "vo.grid_sise" in err[0], err


def test_draws_md_lists_only_the_parts_a_sequence_scored(tmp_path):
    """A part beyond a short sequence (Bonn's 53-frame clip beside its 450-frame part) scores
    nothing there and is no row of draws.md's part table."""
    from eval.harness import write_draws

    def row(seq, ate, parts):
        return {"sequence": seq, "variant": "mona", "status": "ok", "ate": ate, "parts": parts}

    by_draw = {"g=1": [row("long", 0.05, {"tune": 0.02}), row("clip", 0.01, {"tune": None})],
               "g=2": [row("long", 0.06, {"tune": 0.03}), row("clip", 0.01, {"tune": None})]}
    write_draws(tmp_path, by_draw)
    md = (tmp_path / "draws.md").read_text()
    assert "| long | mona | tune | 2 / 2 | 0.0250 |" in md
    assert "| clip | mona | tune |" not in md
    s = {x["sequence"]: x for x in json.loads((tmp_path / "draws.json").read_text())["summary"]}
    assert s["clip"]["parts"]["tune"]["ok"] == 0 and s["long"]["parts"]["tune"]["ok"] == 2
