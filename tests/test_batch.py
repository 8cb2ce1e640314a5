"""mona-vo batch on a real local Ray (2 CPUs, started once for the module): per-input rows and
statuses, run's outputs per input, a broken and a missing input failing alone, skip on rerun and
retry of failed inputs, a worker killed mid-video, the sockets a local batch opens, the page in a
real headless Chromium, and eval through the same engine. The verdict and the config checks need
no Ray."""
from __future__ import annotations

import csv
import ipaddress
import os
import re
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mona_vo.batch import (BatchConfig, RunOptions, VerdictConfig, batch_config_from_sets,
                           clip_verdict, config_hash, expand_inputs, input_names)
from mona_vo.errors import ConfigError, InputError

# The suite runs on two pytest-xdist workers (README); every test here shares one local Ray
# cluster (the module fixture below), so `--dist loadgroup` keeps them on one worker: one cluster
# per run, not one per worker competing for the same two cores.
pytestmark = pytest.mark.xdist_group("ray")


def test_the_ray_tests_share_one_worker(request):
    """The grouping above holds (on pytest 9.2 through tests/conftest.py's shim): split over the
    workers, two clusters and two first batches competed for the same two cores."""
    if not getattr(request.config.option, "loadgroup", False):
        pytest.skip("not run under pytest-xdist's --dist loadgroup")
    assert request.node.nodeid.endswith("@ray"), request.node.nodeid

CHROMIUM = Path("/usr/bin/chromium")
N_LONG = 24       # frames of the clip whose worker is killed
N_SHORT = 12      # frames of the other clips


# ----------------------------------------------------------------------------------------------
# Without Ray


def test_verdict_follows_its_thresholds():
    cfg = VerdictConfig(min_frames=10, min_posed_share=0.8, max_low_confidence_share=0.3,
                        max_reprojection_rmse_px=2.0)
    good = {"frames": 40, "frames_with_pose": 40, "low_confidence_share": 0.1, "reprojection_rmse_px": 0.7}
    assert clip_verdict(good, cfg).usable
    v = clip_verdict({**good, "frames_with_pose": 20, "reprojection_rmse_px": 3.5}, cfg)
    assert not v.usable and len(v.reasons) == 2
    assert "50 %" in v.reasons[0] and "3.50 px" in v.reasons[1]
    assert not clip_verdict({**good, "low_confidence_share": 0.5}, cfg).usable
    assert not clip_verdict({**good, "frames": 5, "frames_with_pose": 5}, cfg).usable
    # An unknown RMSE (no bundle adjustment ran) is not held against the clip.
    assert clip_verdict({**good, "reprojection_rmse_px": None}, cfg).usable
    assert clip_verdict({**good, "frames_with_pose": 20}, VerdictConfig(min_posed_share=0.5)).usable
    # A trajectory made of two maps (tracking lost: a cut) has a join nothing measured.
    v = clip_verdict({**good, "map_segments": 2}, cfg)
    assert not v.usable and "2 map segments" in v.reasons[0]
    assert clip_verdict({**good, "map_segments": 1}, cfg).usable
    assert clip_verdict({**good, "map_segments": 2}, VerdictConfig(max_map_segments=2)).usable
    assert clip_verdict({**good, "map_segments": None}, cfg).usable     # an older report


def test_verdict_refuses_a_map_the_global_refinement_had_to_move_or_poses_on_few_points():
    cfg = VerdictConfig(max_global_shift_pct=0.5, min_support_p10=40)
    good = {"frames": 40, "frames_with_pose": 40, "low_confidence_share": 0.0,
            "reprojection_rmse_px": 0.3, "global_shift_pct": 0.2, "support_p10": 120}
    assert clip_verdict(good, cfg).usable
    v = clip_verdict({**good, "global_shift_pct": 4.7}, cfg)
    assert not v.usable and "4.70 % of their path" in v.reasons[0]
    v = clip_verdict({**good, "support_p10": 23}, cfg)
    assert not v.usable and "fewer than 23 points" in v.reasons[0]
    assert len(clip_verdict({**good, "global_shift_pct": 4.7, "support_p10": 23}, cfg).reasons) == 2
    # Not measured (no global refinement, an older report, no posed frame): not held against it.
    for missing in ({"global_shift_pct": None}, {"global_shift_pct": float("nan")}, {"support_p10": None}):
        assert clip_verdict({**good, **missing, "support_p10": missing.get("support_p10", 120)}, cfg).usable
    assert clip_verdict({**good, "global_shift_pct": 4.7}, VerdictConfig(max_global_shift_pct=5)).usable


def test_the_verdicts_numbers_come_from_the_report_run_writes():
    from mona_vo.batch import summary_from_report

    report = {"frames": 40, "frames_with_pose": 40, "low_confidence_frames": [],
              "reprojection_rmse_px": 0.3, "map_segments": [{"first": "0", "last": "39"}],
              "global_refinement": {"keyframe_shift_pct": 0.12345678},
              "pose_support": {"frames": 40, "inliers_p10": 87.0, "inliers_median": 140.0}}
    s = summary_from_report(report)
    assert s["global_shift_pct"] == 0.1235 and s["support_p10"] == 87.0
    s = summary_from_report({**report, "global_refinement": None, "pose_support": {"inliers_p10": None}})
    assert s["global_shift_pct"] is None and s["support_p10"] is None


@pytest.mark.parametrize("key, value", [("verdict.min_posed_share", "1.5"), ("verdict.min_frames", "0"),
                                        ("verdict.max_reprojection_rmse_px", "0"),
                                        ("verdict.max_global_shift_pct", "0"),
                                        ("verdict.min_support_p10", "-1"),
                                        ("batch.cpus_per_video", "0"), ("batch.max_retries", "-1"),
                                        ("batch.nonsense", "1"), ("vo.grid_size", "3")])
def test_batch_config_refuses_bad_values_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=re.escape(key.split(".")[-1])):
        batch_config_from_sets({key: value})


def test_inputs_from_lists_and_names_that_do_not_collide(tmp_path):
    (tmp_path / "x").mkdir()
    lst = tmp_path / "x" / "list.txt"
    lst.write_text("# clips\nclip.mp4\n\n/abs/other/clip.mp4\n   frames_dir  \nclip.mp4\n")
    paths = expand_inputs([f"@{lst}", str(tmp_path / "solo.MOV")])
    assert paths == [str(tmp_path / "x" / "clip.mp4"), "/abs/other/clip.mp4",
                     str(tmp_path / "x" / "frames_dir"), str(tmp_path / "solo.MOV")]
    names = input_names(paths)
    assert names[2:] == ["frames_dir", "solo"]
    assert names[0] != names[1] and names[0].startswith("clip-") and names[1].startswith("clip-")
    assert input_names(list(reversed(paths)))[::-1] == names   # a name does not depend on order
    with pytest.raises(InputError, match="missing.txt"):
        expand_inputs([f"@{tmp_path / 'missing.txt'}"])


def test_config_hash_changes_with_what_changes_outputs():
    base = RunOptions()
    assert config_hash(base) == config_hash(RunOptions())
    assert config_hash(base) != config_hash(RunOptions(max_frames=5))
    assert config_hash(base) != config_hash(RunOptions(masks="none"))


# ----------------------------------------------------------------------------------------------
# Inputs and the local Ray


def _write_video(path: Path, images) -> Path:
    import cv2

    images = list(images)
    h, w = images[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h))
    for im in images:
        vw.write(cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    vw.release()
    return path


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """One generated 320x240 scene (a car ahead of the camera): its first frames as a video, the
    next ones as a frame folder, all of them as the long video; a truncated copy is the broken
    input, and a path that does not exist the missing one."""
    import cv2

    from data_tools.synthetic import SceneConfig, SyntheticScene

    root = tmp_path_factory.mktemp("clips")
    scene = SyntheticScene(SceneConfig(width=320, height=240, n_frames=N_LONG, preset="one-large", seed=5))
    images = [f.image for f in scene]
    short = _write_video(root / "short.mp4", images[:N_SHORT])
    folder = root / "folder"
    folder.mkdir()
    for i, im in enumerate(images[N_SHORT:2 * N_SHORT]):
        cv2.imwrite(str(folder / f"{i:05d}.png"), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    long = _write_video(root / "long.mp4", images)
    broken = root / "broken.mp4"
    broken.write_bytes(short.read_bytes()[:2000])
    return {"short": short, "folder": folder, "long": long, "broken": broken,
            "missing": root / "missing.mp4", "images": images, "intrinsics": scene.intrinsics,
            "poses": scene.poses()}


@pytest.fixture(scope="module")
def options():
    from mona_vo.config import load_config
    from mona_vo.pipeline import PipelineConfig
    from mona_vo.presets import PRESETS

    return RunOptions(config=load_config(PipelineConfig, None, dict(PRESETS["fast"])))


@pytest.fixture(scope="module")
def local_ray():
    pytest.importorskip("ray")
    from mona_vo.batch import start_local_ray

    stop = start_local_ray(num_cpus=2)
    yield
    stop()


@pytest.fixture(scope="module")
def first_batch(local_ray, clips, options, tmp_path_factory):
    from mona_vo.batch import run_batch

    out = tmp_path_factory.mktemp("batch") / "out"
    lst = out.parent / "inputs.txt"
    lst.write_text(f"{clips['short']}\n{clips['folder']}\n")
    result = run_batch([f"@{lst}", str(clips["broken"]), str(clips["missing"])], out,
                       options=options, progress=False)
    return out, result, (out / "batch.csv").read_text()


def _csv_rows(text: str) -> list[dict]:
    return list(csv.DictReader(text.splitlines()))


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def test_batch_rows_statuses_and_reasons(first_batch, clips):
    out, result, csv_text = first_batch
    rows = _csv_rows(csv_text)
    assert [r["input"] for r in rows] == [str(clips[k]) for k in ("short", "folder", "broken", "missing")]
    assert [r["name"] for r in rows] == ["short", "folder", "broken", "missing"]
    assert [r["status"] for r in rows] == ["ok", "ok", "failed", "failed"]
    assert len(result.failed) == 2
    for r in rows[:2]:
        assert int(r["frames"]) == int(r["frames_with_pose"]) == N_SHORT
        assert int(r["keyframes"]) >= 2 and float(r["seconds"]) > 0 and float(r["frames_per_second"]) > 0
        assert 0 <= float(r["low_confidence_share"]) <= 1 and 0 <= float(r["mask_coverage"]) < 1
        assert r["usable"] in ("true", "false") and r["node"]
    # The broken and the missing input fail alone, with one line naming the file.
    assert "broken.mp4" in rows[2]["reason"] and "cannot open" in rows[2]["reason"]
    assert "missing.mp4" in rows[3]["reason"] and "no such file" in rows[3]["reason"]
    assert all("\n" not in r["reason"] for r in rows)
    assert len({r["config_hash"] for r in rows}) == 1
    assert not (out / "broken").exists() or not (out / "broken" / "report.json").exists()


def test_each_input_gets_what_run_writes(first_batch, clips, options, tmp_path):
    from data_tools.tum import read_tum_trajectory
    from mona_vo.run import run

    out, _, _ = first_batch
    plain = tmp_path / "plain"
    run(str(clips["short"]), plain, config=options.config, progress=False)
    assert _files(out / "short") == _files(plain)
    assert len(list((out / "short" / "masks").glob("*.png"))) == N_SHORT
    ts_b, poses_b = read_tum_trajectory(out / "short" / "trajectory.txt")
    ts_p, poses_p = read_tum_trajectory(plain / "trajectory.txt")
    assert np.array_equal(ts_b, ts_p) and np.allclose(poses_b, poses_p, atol=1e-6)
    assert not [n for n in os.listdir(out) if n.startswith(".")]   # nothing half-written


def test_page_lists_every_input_and_its_pictures(first_batch):
    out, _, _ = first_batch
    page = (out / "index.html").read_text()
    for name in ("short", "folder", "broken", "missing"):
        assert f">{name}</a>" in page
    assert 'src="short/overlay_strip.jpg"' in page and 'src="folder/trajectory.png"' in page
    assert "cannot open video" in page and "no such file" in page
    assert 'src="broken/' not in page
    single = (out / "short" / "index.html").read_text()
    assert 'src="overlay_strip.jpg"' in single and 'src="trajectory.png"' in single


def _chromium_dom(url: str) -> str:
    proc = subprocess.run([str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu",
                           "--virtual-time-budget=5000", "--dump-dom", url],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-500:]
    return proc.stdout


@pytest.mark.skipif(not CHROMIUM.exists(), reason="/usr/bin/chromium is absent (Debian package chromium)")
def test_page_in_headless_chromium_loads_every_image_and_sorts(first_batch):
    out, _, csv_text = first_batch
    rows = _csv_rows(csv_text)
    ok = [r for r in rows if r["status"] == "ok"]
    dom = _chromium_dom((out / "index.html").as_uri())
    loaded = int(re.search(r'data-images-loaded="(\d+)"', dom).group(1))
    broken = int(re.search(r'data-images-broken="(\d+)"', dom).group(1))
    assert (loaded, broken) == (2 * len(ok), 0)
    # Sorted by seconds, longest first, through the address (the same code as a heading click).
    dom = _chromium_dom((out / "index.html").as_uri() + "#sort=-seconds")
    order = re.findall(r'<a href="([^"/]+)/">', dom)
    expected = [r["name"] for r in sorted(rows, key=lambda r: -float(r["seconds"]))]
    assert order == expected
    dom = _chromium_dom((out / "short" / "index.html").as_uri())
    assert 'data-images-loaded="2"' in dom and 'data-images-broken="0"' in dom


def _children_of(root_pid: int) -> set[int]:
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            parent[int(d)] = int(stat.rsplit(")", 1)[1].split()[1])
    tree, grew = {root_pid}, True
    while grew:
        new = {p for p, pp in parent.items() if pp in tree and p not in tree}
        tree |= new
        grew = bool(new)
    return tree


def _decode(hex_addr: str) -> ipaddress._BaseAddress:
    raw = bytes.fromhex(hex_addr)
    if len(raw) == 4:
        return ipaddress.IPv4Address(raw[::-1])
    return ipaddress.IPv6Address(b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))


def _listening_sockets(pids: set[int]) -> list[tuple[str, str, int, int]]:
    """(protocol, address, port, pid) of every listening TCP / bound UDP socket of ``pids``."""
    inode_pid = {}
    for pid in pids:
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                with_target = os.readlink(f"/proc/{pid}/fd/{fd}")
                if with_target.startswith("socket:["):
                    inode_pid[with_target[8:-1]] = pid
        except OSError:
            continue
    out = []
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        try:
            lines = Path(f"/proc/net/{proto}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            local, state, inode = f[1], f[3], f[9]
            if inode not in inode_pid or (proto.startswith("tcp") and state != "0A"):
                continue
            addr, port = local.split(":")
            out.append((proto, str(_decode(addr)), int(port, 16), inode_pid[inode]))
    return out


def _reachable_from_elsewhere(addr: str) -> bool:
    ip = ipaddress.ip_address(addr)
    mapped = getattr(ip, "ipv4_mapped", None)
    return not (ip.is_loopback or (mapped is not None and mapped.is_loopback))


def test_local_ray_listens_on_loopback_only_with_token_auth_and_no_dashboard(first_batch):
    import ray

    pids = _children_of(os.getpid())
    sockets = _listening_sockets(pids)
    # gcs_server, the raylet's servers, this driver's and each worker's core-worker server.
    assert len(sockets) >= 4, sockets
    exposed = [s for s in sockets if _reachable_from_elsewhere(s[1])]
    assert exposed == [], f"reachable from another host: {exposed}"
    cmdlines = []
    for pid in pids:
        with_args = Path(f"/proc/{pid}/cmdline")
        if with_args.exists():
            cmdlines.append(with_args.read_bytes().replace(b"\0", b" ").decode(errors="replace"))
    # Ray still starts its dashboard process, with no web front end and no job or state API
    # (only its usage-stats module, itself switched off); nothing listens on the dashboard port.
    heads = [c for c in cmdlines if "dashboard/dashboard.py" in c]
    assert all("--disable-frontend" in c and "--modules-to-load=UsageStatsHead" in c for c in heads), heads
    assert not [s for s in sockets if s[2] == 8265]
    assert any("gcs_server" in c for c in cmdlines)
    assert os.environ.get("RAY_AUTH_MODE") == "token"
    assert all(n["NodeManagerAddress"] == "127.0.0.1" for n in ray.nodes())


def test_rerun_skips_done_inputs_and_retries_failed_ones(first_batch, clips, options):
    from mona_vo.batch import run_batch

    out, _, _ = first_batch
    stamp = (out / "short" / "report.json").stat().st_mtime_ns
    shutil.copy(clips["short"], clips["broken"])          # the broken input is repaired
    try:
        result = run_batch([str(clips[k]) for k in ("short", "folder", "broken", "missing")], out,
                           options=options, progress=False)
    finally:
        clips["broken"].write_bytes(clips["short"].read_bytes()[:2000])
    rows = _csv_rows((out / "batch.csv").read_text())
    assert [r["status"] for r in rows] == ["skipped", "skipped", "ok", "failed"]
    assert [r["status"] for r in result.rows] == ["skipped", "skipped", "ok", "failed"]
    assert (out / "short" / "report.json").stat().st_mtime_ns == stamp   # not run again
    assert int(rows[0]["frames"]) == N_SHORT and int(rows[2]["frames"]) == N_SHORT


def _worker_running(task_name: str) -> int | None:
    for pid in _children_of(os.getpid()):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if cmd.startswith(f"ray::{task_name}".encode()):
            return pid
    return None


def test_killed_worker_the_video_completes_once_with_nothing_half_written(local_ray, clips, options, tmp_path):
    from data_tools.tum import read_tum_trajectory
    from mona_vo.batch import run_batch

    out = tmp_path / "out"
    box = {}
    thread = threading.Thread(target=lambda: box.update(result=run_batch(
        [str(clips["long"])], out, options=options, config=BatchConfig(max_retries=2), progress=False)))
    thread.start()
    killed = None
    deadline = time.monotonic() + 180
    while killed is None and thread.is_alive() and time.monotonic() < deadline:
        staged = list((out / "long").glob(".partial-*/masks/*.png")) if (out / "long").exists() else []
        pid = _worker_running("batch_video_task")
        if len(staged) >= 2 and pid is not None:     # mid-video: masks of the first frames staged
            os.kill(pid, signal.SIGKILL)
            killed = pid
        time.sleep(0.05)
    thread.join(timeout=300)
    assert killed is not None, "the video finished before its worker could be killed"
    row = box["result"].rows[0]
    assert row["status"] == "ok", row
    assert row["_pid"] != killed and row["_stale_removed"] >= 1   # a new worker, after the dead one
    rows = _csv_rows((out / "batch.csv").read_text())
    assert len(rows) == 1 and rows[0]["status"] == "ok" and int(rows[0]["frames"]) == N_LONG
    entries = sorted(os.listdir(out / "long"))
    assert entries == ["index.html", "masks", "overlay_strip.jpg", "report.json", "trajectory.png",
                       "trajectory.txt"]
    assert len(os.listdir(out / "long" / "masks")) == N_LONG
    ts, _ = read_tum_trajectory(out / "long" / "trajectory.txt")
    assert len(ts) == N_LONG and len(set(ts.tolist())) == N_LONG


def test_cli_batch_exit_status_and_verdict_thresholds(local_ray, clips, tmp_path, capsys):
    from mona_vo.cli import main

    out = tmp_path / "cli"
    rc = main(["-q", "batch", str(clips["short"]), str(clips["broken"]), "--out", str(out),
               "--preset", "fast", "--set", "verdict.min_frames=100"])
    printed = capsys.readouterr().out
    assert rc == 1 and "1 ok, 0 skipped, 1 failed; 0 usable" in printed and "failed broken" in printed
    rows = _csv_rows((out / "batch.csv").read_text())
    assert rows[0]["usable"] == "false" and f"{N_SHORT} frames (< 100)" in rows[0]["reason"]
    # The same outputs judged again with other thresholds: skipped, now usable, exit 0 without the broken one.
    rc = main(["-q", "batch", str(clips["short"]), "--out", str(out), "--preset", "fast"])
    assert rc == 0
    rows = _csv_rows((out / "batch.csv").read_text())
    assert rows[0]["status"] == "skipped"
    assert main(["-q", "batch", str(clips["short"]), "--out", str(out), "--set", "verdict.min_posed_share=2"]) == 1
    assert "verdict.min_posed_share" in capsys.readouterr().err


def test_eval_runs_its_sequences_on_the_same_engine(local_ray, clips, tmp_path):
    from data_tools.tum import write_tum_layout
    from eval.datasets import tum_sequences
    from eval.harness import evaluate

    root = tmp_path / "tum"
    write_tum_layout(root, np.arange(N_SHORT) * 0.1, clips["images"][:N_SHORT], clips["poses"][:N_SHORT],
                     clips["intrinsics"])
    rows = evaluate(tum_sequences([root]), ["none"], tmp_path / "eval", address="local", progress=False)
    assert len(rows) == 1 and rows[0]["status"] == "ok", rows
    assert rows[0]["frames_with_pose"] == N_SHORT and rows[0]["ate"] >= 0
    assert (tmp_path / "eval" / "none" / "tum" / "trajectory.txt").exists()
