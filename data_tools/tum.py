"""TUM RGB-D formats: trajectories (``timestamp tx ty tz qx qy qz qw``), ``rgb.txt`` frame lists,
and whole sequences in the TUM layout (``rgb/``, ``rgb.txt``, ``groundtruth.txt``, ``calib.txt``).

Trajectories are camera-to-world (``T_world_cam``), quaternions scalar-last in the file; the order
is handled only by :func:`mona_vo.conventions.tum_row` / :func:`~mona_vo.conventions.pose_from_tum_row`.
Timestamps are seconds (or frame numbers for datasets without times).
"""
from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from data_tools.atomic import write_text_atomic
from data_tools.frames import FrameSource, ImageFiles, write_image
from mona_vo.conventions import Intrinsics, pose_from_tum_row, tum_row
from mona_vo.errors import InputError
from mona_vo.lens import COEFFICIENTS, Distortion, camera

_SEPARATORS = re.compile(r"[,\s]+")


def _read_lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8", errors="replace").splitlines()
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, expected a text file") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None


def numeric_rows(path: str | os.PathLike, count: int, what: str) -> Iterator[tuple[int, np.ndarray]]:
    """(line number, (count,) float64 values) for each data line of a text table.

    Blank lines and '#' comments are skipped; numbers may be separated by spaces, tabs or commas.
    A line with the wrong number of values or a non-finite/non-numeric value raises InputError
    naming the file and the 1-based line number; ``what`` names the expected content.
    """
    path = Path(path)
    for lineno, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = _SEPARATORS.split(text)
        if len(fields) != count:
            raise InputError(f"{path}:{lineno}: expected {count} numbers ({what}), got {len(fields)}")
        try:
            values = np.array([float(f) for f in fields])
        except ValueError:
            raise InputError(f"{path}:{lineno}: not a number in {text[:60]!r} ({what})") from None
        if not np.all(np.isfinite(values)):
            raise InputError(f"{path}:{lineno}: non-finite value in {text[:60]!r}")
        yield lineno, values


def read_tum_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,) float64 seconds, poses (N, 4, 4) float64 T_world_cam) from a TUM file.

    Raises InputError naming file and line for a malformed line or a zero quaternion, and for a
    file without any pose.
    """
    path = Path(path)
    stamps, poses = [], []
    for lineno, row in numeric_rows(path, 8, "timestamp tx ty tz qx qy qz qw"):
        if np.linalg.norm(row[4:]) < 1e-6:
            raise InputError(f"{path}:{lineno}: zero quaternion")
        t, T = pose_from_tum_row(row)
        stamps.append(t)
        poses.append(T)
    if not poses:
        raise InputError(f"{path}: no poses in this TUM trajectory file")
    return np.array(stamps, dtype=np.float64), np.stack(poses)


def format_timestamp(t: float) -> str:
    """Timestamp text that reads back as the same float: microseconds ('%.6f', TUM's usual form)
    when that is exact, otherwise the shortest exact form (repr)."""
    t = float(t)
    text = f"{t:.6f}"
    return text if float(text) == t else repr(t)


def _check_trajectory(timestamps, poses) -> tuple[np.ndarray, np.ndarray]:
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(stamps):
        raise ValueError(f"need timestamps (N,) and poses (N, 4, 4), got {stamps.shape} and {poses.shape}")
    if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(poses))):
        raise ValueError("timestamps and poses must be finite")
    return stamps, poses


def write_tum_trajectory(path: str | os.PathLike, timestamps, poses) -> None:
    """Write timestamps (N,) seconds and poses (N, 4, 4) T_world_cam as a TUM file, atomically.

    Values are written in their shortest exact form, so reading back gives the same numbers
    (rotations up to float rounding of the quaternion conversion).
    """
    stamps, poses = _check_trajectory(timestamps, poses)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip(stamps, poses):
        row = tum_row(t, T)
        lines.append(" ".join([format_timestamp(row[0])] + [repr(float(v)) for v in row[1:]]))
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_rgb_list(path: str | os.PathLike) -> list[tuple[float, str]]:
    """[(timestamp seconds, image path relative to the list's folder)] from a TUM ``rgb.txt``."""
    path = Path(path)
    entries = []
    for lineno, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = text.split()
        if len(fields) != 2:
            raise InputError(f"{path}:{lineno}: expected 'timestamp filename', got {text[:60]!r}")
        try:
            t = float(fields[0])
        except ValueError:
            raise InputError(f"{path}:{lineno}: timestamp {fields[0]!r} is not a number") from None
        if not math.isfinite(t):
            raise InputError(f"{path}:{lineno}: timestamp {fields[0]!r} is not finite")
        entries.append((t, fields[1]))
    if not entries:
        raise InputError(f"{path}: lists no images")
    return entries


def read_calib_txt(path: str | os.PathLike) -> Intrinsics:
    """Intrinsics from a ``calib.txt`` whose first data line holds ``fx fy cx cy`` (pixels).

    A leading label ('K:', 'intrinsics') is ignored. Up to five numbers after the fourth are the
    lens distortion in OpenCV's order (DPVO's ``k1 k2 p1 p2``, TUM's ``d0 d1 d2 d3 d4``): with
    any of them non-zero the result is a :class:`mona_vo.lens.LensIntrinsics`, whose frames a run
    undistorts before reading them.
    """
    path = Path(path)
    for lineno, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = _SEPARATORS.split(text)
        if fields and not _is_number(fields[0]):
            fields = fields[1:]  # a label
        if len(fields) < 4 or not all(_is_number(f) for f in fields[:4]):
            raise InputError(f"{path}:{lineno}: expected 'fx fy cx cy', got {text[:60]!r}")
        rest = fields[4:]
        try:   # Distortion.from_numbers refuses more coefficients than the model has
            if not all(_is_number(f) for f in rest):
                raise ValueError
            lens = Distortion.from_numbers(rest)
        except ValueError:
            raise InputError(f"{path}:{lineno}: expected 'fx fy cx cy' and at most "
                             f"{len(COEFFICIENTS)} distortion coefficients "
                             f"({' '.join(COEFFICIENTS)}), got {text[:60]!r}") from None
        cam = camera(Intrinsics(*(float(f) for f in fields[:4])), lens)
        problems = cam.check()
        if problems:
            raise InputError(f"{path}:{lineno}: {problems[0]}")
        return cam
    raise InputError(f"{path}: no 'fx fy cx cy' line")


def _is_number(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


class TumSequence:
    """A sequence in the TUM RGB-D layout: ``rgb.txt`` listing ``rgb/<timestamp>.png``, optional
    ``groundtruth.txt`` (TUM trajectory, T_world_cam) and ``calib.txt`` (``fx fy cx cy``).

    Opening checks that ``rgb.txt`` and every image it lists exist; a missing file raises
    InputError naming it. ``frame_paths`` and ``timestamps`` ((N,) float64 seconds) follow rgb.txt.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        if not self.root.is_dir():
            raise InputError(f"{self.root}: not a folder (expected a TUM RGB-D sequence)")
        entries = read_rgb_list(self.root / "rgb.txt")
        self.frame_paths = [self.root / rel for _, rel in entries]
        self.timestamps = np.array([t for t, _ in entries], dtype=np.float64)
        missing = [p for p in self.frame_paths if not p.is_file()]
        if missing:
            raise InputError(f"{missing[0]}: listed in {self.root / 'rgb.txt'} but not found "
                             f"({len(missing)} of {len(self.frame_paths)} images missing)")

    def frames(self, *, stride: int = 1, max_frames: int | None = None) -> FrameSource:
        """Streamed frames in rgb.txt order, timestamps from rgb.txt (seconds)."""
        return ImageFiles(self.frame_paths, path=self.root, timestamps=self.timestamps,
                          timestamp_kind="seconds", stride=stride, max_frames=max_frames)

    def groundtruth(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps (M,) float64 seconds, poses (M, 4, 4) T_world_cam) from groundtruth.txt;
        the mocap rate differs from the frame rate, so associate by timestamp."""
        return read_tum_trajectory(self.root / "groundtruth.txt")

    def intrinsics(self) -> Intrinsics | None:
        """Intrinsics from calib.txt, or None when the sequence has none."""
        path = self.root / "calib.txt"
        return read_calib_txt(path) if path.exists() else None


def write_tum_layout(root: str | os.PathLike, timestamps, images: Iterable[np.ndarray], poses,
                     intrinsics: Intrinsics | None = None) -> None:
    """Write a sequence readable by :class:`TumSequence`: ``rgb/<timestamp>.png``, ``rgb.txt``,
    ``groundtruth.txt`` and (if intrinsics are given) ``calib.txt``.

    timestamps (N,) seconds; images an iterable of N (H, W, 3) uint8 RGB arrays, consumed one at a
    time; poses (N, 4, 4) float64 T_world_cam. Each file is written atomically and the lists are
    written last, so a reader never sees rgb.txt naming an image that is not there yet.
    """
    root = Path(root)
    stamps, poses = _check_trajectory(timestamps, poses)
    rel_paths = [f"rgb/{format_timestamp(t)}.png" for t in stamps]
    if len(set(rel_paths)) != len(rel_paths):
        raise ValueError("timestamps must be distinct (they name the image files)")
    n = 0
    for image in images:
        if n >= len(stamps):
            raise ValueError(f"more images than the {len(stamps)} timestamps")
        write_image(root / rel_paths[n], image)
        n += 1
    if n != len(stamps):
        raise ValueError(f"{n} images for {len(stamps)} timestamps")
    if intrinsics is not None:
        write_text_atomic(root / "calib.txt", "# fx fy cx cy\n" + " ".join(
            repr(float(v)) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)) + "\n")
    write_tum_trajectory(root / "groundtruth.txt", stamps, poses)
    write_text_atomic(root / "rgb.txt", "# timestamp filename\n" + "".join(
        f"{format_timestamp(t)} {rel}\n" for t, rel in zip(stamps, rel_paths)))
