"""Fuzz: random and damaged bytes as images, masks, videos, Sintel .cam/.flo/.dpt files,
calibration and trajectory files. Library readers may only raise a MonaVoError (InputError,
EvalError); the command may only end with exit 0 or 1, never with a traceback.

Every blob comes from a seeded generator, so a failure names a reproducible case.
"""
from __future__ import annotations

import os
import subprocess
import zlib
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
import pytest

from mona_vo.errors import MonaVoError

SEED = 20240613
TAG = np.float32(202021.25).tobytes()


def _png(rng, w=48, h=32) -> bytes:
    return cv2.imencode(".png", rng.integers(0, 255, (h, w, 3), np.uint8))[1].tobytes()


def _jpeg(rng, w=48, h=32) -> bytes:
    image = cv2.resize(rng.integers(0, 255, (h // 4, w // 4, 3), np.uint8), (w, h))
    return cv2.imencode(".jpg", image)[1].tobytes()


def _flip(rng, data: bytes, n: int) -> bytes:
    """``data`` with ``n`` random bytes replaced (bit rot), the first 8 (the magic) kept."""
    b = bytearray(data)
    for i in rng.integers(8, len(b), n):
        b[i] = int(rng.integers(0, 256))
    return bytes(b)


def image_blobs(rng) -> dict[str, tuple[str, bytes]]:
    """name -> (suffix, bytes) of things that claim to be images."""
    png, jpg = _png(rng), _jpeg(rng)
    ihdr = b"IHDR" + (60000).to_bytes(4, "big") * 2 + b"\x08\x02\x00\x00\x00"
    idat = b"IDAT" + rng.bytes(16)
    huge_png = (b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + ihdr + zlib.crc32(ihdr).to_bytes(4, "big")
                + (16).to_bytes(4, "big") + idat + zlib.crc32(idat).to_bytes(4, "big"))  # 60000 x 60000
    blobs = {
        "empty": (".png", b""),
        "one_byte": (".png", b"\x89"),
        "random_64": (".png", rng.bytes(64)),
        "random_4k": (".jpg", rng.bytes(4096)),
        "png_magic_then_garbage": (".png", b"\x89PNG\r\n\x1a\n" + rng.bytes(300)),
        "png_header_then_garbage": (".png", png[:33] + rng.bytes(200)),
        "png_absurd_size": (".png", huge_png),
        "jpeg_magic_then_garbage": (".jpg", b"\xff\xd8\xff\xe0" + rng.bytes(500)),
        "gif_magic_then_garbage": (".png", b"GIF89a" + rng.bytes(100)),
        "bmp_magic_then_garbage": (".bmp", b"BM" + rng.bytes(200)),
        "tiff_magic_then_garbage": (".tif", b"II*\x00" + rng.bytes(200)),
        "webp_magic_then_garbage": (".webp", b"RIFF" + (200).to_bytes(4, "little") + b"WEBPVP8 " + rng.bytes(200)),
        "png_bit_rot": (".png", _flip(rng, png, 6)),
        "jpeg_bit_rot": (".jpg", _flip(rng, jpg, 6)),
        "jpeg_truncated": (".jpg", jpg[: len(jpg) * 2 // 3]),
    }
    for cut in (9, 33, 60, len(png) // 2, len(png) - 1):
        blobs[f"png_truncated_at_{cut}"] = (".png", png[:cut])
    return blobs


def _check_frames(source) -> None:
    frames = list(source)
    for f in frames:
        assert f.image.dtype == np.uint8 and f.image.shape == (source.height, source.width, 3)


def test_random_bytes_as_image_files_raise_only_input_errors(tmp_path):
    from data_tools.frames import decode_image, image_size, open_frames
    from data_tools.masks_io import read_mask_folder, read_mask_png

    rng = np.random.default_rng(SEED)
    good = _png(rng)
    for name, (suffix, data) in image_blobs(rng).items():
        folder = tmp_path / name
        folder.mkdir()
        (folder / "00000.png").write_bytes(good)
        blob = folder / f"00001{suffix}"
        blob.write_bytes(data)
        for call in (lambda: decode_image(blob), lambda: image_size(blob), lambda: read_mask_png(blob),
                     lambda: _check_frames(open_frames(folder)),
                     lambda: list(read_mask_folder(folder, ["00000", "00001"], allow_extra=True))):
            try:
                call()
            except MonaVoError as exc:
                assert str(blob) in str(exc) or str(folder) in str(exc), (name, exc)
            except Exception as exc:  # noqa: BLE001 -- the point of the test
                pytest.fail(f"{name}: {type(exc).__name__} escaped: {exc}")


def video_blobs(rng, tmp_path) -> dict[str, tuple[str, bytes]]:
    frames = [cv2.resize(rng.integers(0, 255, (8, 12, 3), np.uint8), (96, 64)) for _ in range(12)]
    real = {}
    for suffix, fourcc in ((".avi", "MJPG"), (".mp4", "mp4v")):
        path = tmp_path / f"real{suffix}"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (96, 64))
        for f in frames:
            writer.write(f)
        writer.release()
        real[suffix] = path.read_bytes()
    blobs = {
        "empty": (".mp4", b""),
        "random_64": (".mp4", rng.bytes(64)),
        "random_64k": (".avi", rng.bytes(65536)),
        "mp4_ftyp_then_garbage": (".mp4", b"\x00\x00\x00\x18ftypisom\x00\x00\x02\x00isomiso2" + rng.bytes(4000)),
        "avi_riff_then_garbage": (".avi", b"RIFF" + (8000).to_bytes(4, "little") + b"AVI LIST" + rng.bytes(8000)),
        "mkv_ebml_then_garbage": (".mkv", b"\x1a\x45\xdf\xa3" + rng.bytes(3000)),
    }
    for suffix, data in real.items():
        for frac in (0.05, 0.3, 0.6, 0.95):
            blobs[f"{suffix[1:]}_truncated_{int(frac * 100)}pct"] = (suffix, data[: int(len(data) * frac)])
        for k in range(2):
            blobs[f"{suffix[1:]}_bit_rot_{k}"] = (suffix, _flip(rng, data, 40))
    return blobs


def test_random_bytes_as_video_files_raise_only_input_errors(tmp_path):
    from data_tools.frames import open_frames

    rng = np.random.default_rng(SEED + 1)
    for name, (suffix, data) in video_blobs(rng, tmp_path).items():
        path = tmp_path / f"{name}{suffix}"
        path.write_bytes(data)
        try:
            source = open_frames(path)
            _check_frames(source)
        except MonaVoError as exc:
            assert str(path) in str(exc), (name, exc)
        except Exception as exc:  # noqa: BLE001
            pytest.fail(f"{name}: {type(exc).__name__} escaped: {exc}")


def sintel_blobs(rng) -> dict[str, bytes]:
    wh = np.array([5, 4], "<i4").tobytes()
    blobs = {"empty": b"", "three_bytes": TAG[:3], "tag_only": TAG}
    for n in (8, 100, 172, 400):
        blobs[f"random_{n}"] = rng.bytes(n)
        blobs[f"tag_then_random_{n}"] = TAG + rng.bytes(n)
    blobs["tag_size_then_random_payload"] = TAG + wh + rng.bytes(5 * 4 * 8)
    blobs["tag_negative_size"] = TAG + np.array([-5, 4], "<i4").tobytes() + rng.bytes(200)
    blobs["tag_huge_size"] = TAG + np.array([99999, 99999], "<i4").tobytes() + rng.bytes(200)
    blobs["cam_random_doubles"] = TAG + rng.normal(0, 1e3, 21).tobytes()
    blobs["cam_huge_doubles"] = TAG + (rng.normal(0, 1, 21) * 1e300).tobytes()
    blobs["cam_nan"] = TAG + np.full(21, np.nan).tobytes()
    return blobs


def test_random_bytes_as_sintel_files_raise_only_input_errors(tmp_path):
    from data_tools.sintel_formats import read_cam, read_dpt, read_flo

    rng = np.random.default_rng(SEED + 2)
    for name, data in sintel_blobs(rng).items():
        for suffix, reader in ((".cam", read_cam), (".flo", read_flo), (".dpt", read_dpt)):
            path = tmp_path / f"{name}{suffix}"
            path.write_bytes(data)
            try:
                out = reader(path)
            except MonaVoError as exc:
                assert str(path) in str(exc) and "\n" not in str(exc), (name, exc)
                continue
            except Exception as exc:  # noqa: BLE001
                pytest.fail(f"{name}{suffix}: {type(exc).__name__} escaped: {exc}")
            if suffix == ".cam":  # accepted: then it is a usable camera
                intr, T = out
                assert not intr.check() and np.isfinite(T).all()


def test_random_bytes_and_strings_as_calibration_raise_only_input_errors(tmp_path):
    from data_tools.calibration import parse_calibration

    rng = np.random.default_rng(SEED + 3)
    files = {f"random_{n}": rng.bytes(n) for n in (0, 1, 50, 3000)}
    files["numbers_text"] = " ".join(f"{v:g}" for v in rng.normal(0, 500, 7)).encode()
    files["kitti_garbage"] = b"P0: " + rng.bytes(80)
    files["kitti_random_numbers"] = ("P0: " + " ".join(f"{v:g}" for v in rng.normal(0, 300, 12))).encode()
    files["utf16"] = "500 500 192 82".encode("utf-16")
    values = ["", " ", ",,,,", "1e999,1,1,1", "500;500;192;82", "0x10,1,1,1", "-0,-0,0,0", "5" * 400,
              "a/b/c.txt", "500,500,192,82,7"]
    values += ["".join(chr(int(c)) for c in rng.integers(32, 127, int(n))) for n in rng.integers(0, 80, 30)]
    values += [",".join(f"{v:.3g}" for v in rng.normal(100, 300, 4)) for _ in range(30)]
    cases = []
    for name, data in files.items():
        path = tmp_path / f"{name}.txt"
        path.write_bytes(data)
        cases.append((name, str(path)))
    cases += [(repr(v), v) for v in values]
    for name, value in cases:
        try:
            intr = parse_calibration(value, 384, 164)
        except MonaVoError as exc:
            assert "\n" not in str(exc), (name, exc)
            continue
        except Exception as exc:  # noqa: BLE001
            pytest.fail(f"calibration {name}: {type(exc).__name__} escaped: {exc}")
        assert intr.check(384, 164) == [], name


def trajectory_blobs(rng) -> dict[str, bytes]:
    blobs = {f"random_{n}": rng.bytes(n) for n in (0, 1, 64, 2048)}

    def table(rows):
        return "\n".join(" ".join(f"{v:.17g}" for v in r) for r in rows).encode()

    blobs["one_pose"] = table([[0, 0, 0, 0, 0, 0, 0, 1]])
    blobs["same_position"] = table([[t, 1, 2, 3, 0, 0, 0, 1] for t in range(6)])
    blobs["collinear"] = table([[t, t, 0, 0, 0, 0, 0, 1] for t in range(6)])
    blobs["duplicate_stamps"] = table([[1, *rng.normal(size=3), 0, 0, 0, 1] for _ in range(6)])
    blobs["random_quaternions"] = table([[t, *rng.normal(size=7)] for t in range(8)])
    blobs["tiny_quaternion"] = table([[t, *rng.normal(size=3), 1e-9, 0, 0, 0] for t in range(4)])
    blobs["seven_columns"] = table([[t, *rng.normal(size=6)] for t in range(4)])
    blobs["huge_values"] = table([[t, *(rng.normal(size=3) * 1e300), 0, 0, 0, 1] for t in range(5)])
    blobs["inf"] = b"0 inf 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n"
    return blobs


def test_random_trajectory_files_raise_only_mona_vo_errors(tmp_path):
    from data_tools.kitti import read_kitti_poses
    from data_tools.tum import read_tum_trajectory
    from eval.metrics import Trajectory, evaluate_trajectory

    rng = np.random.default_rng(SEED + 4)
    poses = np.stack([np.eye(4)] * 8)
    poses[:, 0, 3] = np.arange(8.0)
    poses[:, 1, 3] = np.arange(8.0) ** 2 / 8
    gt = Trajectory(np.arange(8.0), poses)
    for name, data in trajectory_blobs(rng).items():
        path = tmp_path / f"{name}.txt"
        path.write_bytes(data)
        for align in ("sim3", "se3", "none"):
            try:
                est = Trajectory(*read_tum_trajectory(path))
                with np.errstate(all="ignore"):  # 1e300 positions overflow to an ATE of inf
                    evaluate_trajectory(gt, est, align=align)
            except MonaVoError as exc:
                assert "\n" not in str(exc), (name, exc)
            except Exception as exc:  # noqa: BLE001
                pytest.fail(f"trajectory {name} ({align}): {type(exc).__name__} escaped: {exc}")
        try:
            read_kitti_poses(path)
        except MonaVoError:
            pass
        except Exception as exc:  # noqa: BLE001
            pytest.fail(f"KITTI poses {name}: {type(exc).__name__} escaped: {exc}")


# ------------------------------------------------------------------------- through the command

def _cli(exe, *args):
    return subprocess.run([exe, "-q", *map(str, args)], capture_output=True, text=True, timeout=120,
                          env={**os.environ})


def test_the_command_never_shows_a_traceback_on_random_bytes(mona_vo_exe, tmp_path):
    """A sample of every kind of blob through `mona-vo run`, `eval sintel` and `eval traj`."""
    from data_tools.synthetic import SceneConfig, SyntheticScene, write_sintel, write_frames_folder

    rng = np.random.default_rng(SEED + 5)
    scene = SyntheticScene(SceneConfig(width=96, height=40, n_frames=4, preset="static"))
    jobs = {}
    images = image_blobs(rng)
    for name in ("png_absurd_size", "png_bit_rot", "png_truncated_at_60", "jpeg_bit_rot", "random_64"):
        suffix, data = images[name]
        folder = tmp_path / "img" / name
        folder.mkdir(parents=True)
        (folder / "00000.png").write_bytes(_png(rng))
        (folder / f"00001{suffix}").write_bytes(data)
        (folder / f"00002{suffix}").write_bytes(data)
        jobs[f"run {name}"] = ["run", folder, "--masks", "none", "--out", tmp_path / "out" / name]
    videos = video_blobs(rng, tmp_path)
    for name in ("mp4_ftyp_then_garbage", "avi_truncated_60pct", "mp4_bit_rot_0", "avi_bit_rot_1"):
        suffix, data = videos[name]
        path = tmp_path / f"{name}{suffix}"
        path.write_bytes(data)
        jobs[f"run {name}"] = ["run", path, "--masks", "none", "--out", tmp_path / "out" / name]
    calib = tmp_path / "calib.bin"
    calib.write_bytes(rng.bytes(200))
    frames = write_frames_folder(scene, tmp_path / "frames")
    jobs["run calib garbage"] = ["run", frames, "--masks", "none", "--calib", calib, "--out", tmp_path / "out" / "c"]
    root = write_sintel(scene, tmp_path / "sintel", seq="alley_2", passes=("final",))
    blobs = list(sintel_blobs(rng).values())
    for k, cam in enumerate(sorted((root / "training" / "camdata_left" / "alley_2").glob("*.cam"))):
        cam.write_bytes(blobs[int(rng.integers(len(blobs)))] if k else TAG + rng.bytes(168))
    jobs["eval sintel garbage cams"] = ["eval", "sintel", "--root", root, "--seqs", "alley_2",
                                        "--variants", "none", "--out", tmp_path / "out" / "sintel"]
    trajs = trajectory_blobs(rng)
    for name in ("random_2048", "same_position", "random_quaternions", "duplicate_stamps"):
        path = tmp_path / f"traj_{name}.txt"
        path.write_bytes(trajs[name])
        jobs[f"eval traj {name}"] = ["eval", "traj", "--gt", frames / "groundtruth.txt", "--est", path]

    with ThreadPoolExecutor(max_workers=3) as pool:
        procs = dict(zip(jobs, pool.map(lambda argv: _cli(mona_vo_exe, *argv), jobs.values())))
    for name, proc in procs.items():
        assert proc.returncode in (0, 1), (name, proc.returncode, proc.stderr)
        assert "Traceback" not in proc.stderr + proc.stdout, (name, proc.stderr)
        if proc.returncode == 1 and not name.startswith("eval sintel"):
            assert len(proc.stderr.splitlines()) == 1, (name, proc.stderr)
    sintel = procs["eval sintel garbage cams"]
    assert sintel.returncode == 1 and ".cam" in sintel.stdout
