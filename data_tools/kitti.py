"""KITTI odometry formats: pose files (12 numbers per line, the 3x4 camera-to-world matrix
row-major, one line per frame, no timestamps) and ``calib.txt`` projection matrices (``P0: ...``)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from data_tools.atomic import write_text_atomic
from data_tools.tum import numeric_rows
from mona_vo.conventions import Intrinsics
from mona_vo.errors import InputError

_ROW = "12 numbers: 3x4 [R|t] row-major"


def read_kitti_poses(path: str | os.PathLike) -> np.ndarray:
    """(N, 4, 4) float64 T_world_cam, one per line (frame i of the sequence is line i).

    Raises InputError naming file and line for a malformed line, and for a file without poses.
    """
    path = Path(path)
    poses = []
    for _, row in numeric_rows(path, 12, _ROW):
        T = np.eye(4)
        T[:3] = row.reshape(3, 4)
        poses.append(T)
    if not poses:
        raise InputError(f"{path}: no poses in this KITTI pose file")
    return np.stack(poses)


def write_kitti_poses(path: str | os.PathLike, poses) -> None:
    """Write (N, 4, 4) T_world_cam as a KITTI pose file, atomically, in shortest exact form."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.all(np.isfinite(poses)):
        raise ValueError(f"poses must be finite (N, 4, 4), got {poses.shape}")
    text = "".join(" ".join(repr(float(v)) for v in T[:3].reshape(-1)) + "\n" for T in poses)
    write_text_atomic(path, text)


def read_kitti_calib(path: str | os.PathLike, camera: str = "P0") -> Intrinsics:
    """Intrinsics of one camera (``camera`` = 'P0' .. 'P3') from a KITTI odometry ``calib.txt``.

    K is the left 3x3 block of the rectified 3x4 projection matrix; the fourth column (the stereo
    baseline times fx) is not needed for monocular VO.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None
    found = []
    for lineno, line in enumerate(lines, start=1):
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        found.append(key.strip())
        if key.strip() != camera:
            continue
        try:
            values = np.array([float(v) for v in rest.split()])
        except ValueError:
            raise InputError(f"{path}:{lineno}: not a number in the {camera} line") from None
        if values.size != 12 or not np.all(np.isfinite(values)):
            raise InputError(f"{path}:{lineno}: {camera} needs 12 finite numbers, got {values.size}")
        P = values.reshape(3, 4)
        if not np.allclose(P[2, :3], [0.0, 0.0, 1.0]) or P[0, 1] != 0.0 or P[1, 0] != 0.0:
            raise InputError(f"{path}:{lineno}: {camera} is not a rectified projection matrix "
                             "(expected [[fx 0 cx tx] [0 fy cy ty] [0 0 1 tz]])")
        intr = Intrinsics.from_K(P[:, :3])
        problems = intr.check()
        if problems:
            raise InputError(f"{path}:{lineno}: {problems[0]}")
        return intr
    have = ", ".join(found) if found else "no 'KEY: values' lines"
    raise InputError(f"{path}: no {camera} line (found: {have})")
