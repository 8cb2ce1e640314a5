"""MPI Sintel's binary files: ``.cam`` (intrinsics + world-to-camera extrinsics), ``.dpt`` (depth)
and ``.flo`` (optical flow). All little-endian, each starting with the float32 tag 202021.25.

Readers validate tag and length and raise :class:`InputError` naming the file; writers are atomic.
Poses cross this boundary once: ``.cam`` stores world-to-camera [R|t], mona-vo uses
``T_world_cam`` (see :mod:`mona_vo.conventions`).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from data_tools.atomic import write_bytes_atomic
from mona_vo.conventions import Intrinsics, invert_pose, is_rigid
from mona_vo.errors import InputError

TAG_FLOAT = np.float32(202021.25)
_F32 = np.dtype("<f4")
_F64 = np.dtype("<f8")
_I32 = np.dtype("<i4")


def _read(path: str | os.PathLike) -> bytes:
    path = Path(path)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror or exc})") from None


def _check_tag(path, data: bytes, kind: str) -> None:
    if len(data) < 4:
        raise InputError(f"{path}: too short for a Sintel {kind} file ({len(data)} bytes)")
    tag = np.frombuffer(data, _F32, 1)[0]
    if tag != TAG_FLOAT:
        raise InputError(f"{path}: wrong tag {tag!r} for a Sintel {kind} file (expected 202021.25)")


def read_cam(path: str | os.PathLike) -> tuple[Intrinsics, np.ndarray]:
    """(intrinsics, T_world_cam 4x4 float64) from a Sintel ``.cam`` file."""
    data = _read(path)
    _check_tag(path, data, ".cam")
    need = 4 + 9 * 8 + 12 * 8
    if len(data) < need:
        raise InputError(f"{path}: truncated .cam file ({len(data)} bytes, need {need})")
    K = np.frombuffer(data, _F64, 9, offset=4).reshape(3, 3).astype(np.float64)
    N = np.frombuffer(data, _F64, 12, offset=4 + 72).reshape(3, 4).astype(np.float64)
    T_cam_world = np.vstack([N, [0.0, 0.0, 0.0, 1.0]])
    intr = Intrinsics.from_K(K)
    with np.errstate(all="ignore"):  # garbage doubles overflow in the checks; they fail anyway
        problems = intr.check()
        if not problems and not (np.allclose(K[2], [0.0, 0.0, 1.0]) and K[1, 0] == 0.0
                                 and abs(K[0, 1]) <= 1e-9 * abs(K[0, 0])):
            problems = ["intrinsic matrix is not [[fx 0 cx] [0 fy cy] [0 0 1]]"]
        rigid = is_rigid(T_cam_world, tol=1e-4)
    if problems or not rigid:
        what = problems[0] if problems else "extrinsic matrix is not a rigid transform"
        raise InputError(f"{path}: bad .cam content: {what}")
    return intr, invert_pose(T_cam_world)


def write_cam(path: str | os.PathLike, intrinsics: Intrinsics, T_world_cam: np.ndarray) -> None:
    T_cam_world = invert_pose(np.asarray(T_world_cam, dtype=np.float64))
    payload = (TAG_FLOAT.astype(_F32).tobytes() + intrinsics.K.astype(_F64).tobytes()
               + T_cam_world[:3].astype(_F64).tobytes())
    write_bytes_atomic(path, payload)


def _read_wh(path, data: bytes, kind: str, channels: int) -> tuple[int, int]:
    _check_tag(path, data, kind)
    if len(data) < 12:
        raise InputError(f"{path}: truncated {kind} header ({len(data)} bytes)")
    w, h = (int(v) for v in np.frombuffer(data, _I32, 2, offset=4))
    if not (0 < w < 100000 and 0 < h < 100000):
        raise InputError(f"{path}: implausible {kind} size {w} x {h}")
    need = 12 + w * h * channels * 4
    if len(data) < need:
        raise InputError(f"{path}: truncated {kind} file ({len(data)} bytes, need {need} for {w} x {h})")
    return w, h


def read_dpt(path: str | os.PathLike) -> np.ndarray:
    """(H, W) float32 z-depth from a Sintel ``.dpt`` file."""
    data = _read(path)
    w, h = _read_wh(path, data, ".dpt", 1)
    return np.frombuffer(data, _F32, w * h, offset=12).reshape(h, w).astype(np.float32)


def write_dpt(path: str | os.PathLike, depth: np.ndarray) -> None:
    depth = np.asarray(depth, dtype=_F32)
    h, w = depth.shape
    header = TAG_FLOAT.astype(_F32).tobytes() + np.array([w, h], _I32).tobytes()
    write_bytes_atomic(path, header + np.ascontiguousarray(depth).tobytes())


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 2) float32 flow u, v in pixels from a ``.flo`` file (Middlebury/Sintel)."""
    data = _read(path)
    w, h = _read_wh(path, data, ".flo", 2)
    return np.frombuffer(data, _F32, w * h * 2, offset=12).reshape(h, w, 2).astype(np.float32)


def write_flo(path: str | os.PathLike, flow: np.ndarray) -> None:
    flow = np.asarray(flow, dtype=_F32)
    h, w, c = flow.shape
    if c != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    header = TAG_FLOAT.astype(_F32).tobytes() + np.array([w, h], _I32).tobytes()
    write_bytes_atomic(path, header + np.ascontiguousarray(flow).tobytes())
