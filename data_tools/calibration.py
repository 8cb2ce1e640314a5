"""Camera calibration from the command line: ``fx,fy,cx,cy`` or a file (``fx fy cx cy`` on one
line, TUM/Bonn/DPVO style, or a KITTI ``calib.txt`` with a ``P0:`` line), checked against the
image size. Up to five more numbers are the lens distortion (k1, k2, p1, p2, k3, OpenCV's order):
the camera is then a :class:`mona_vo.lens.LensIntrinsics`, whose frames a run undistorts."""
from __future__ import annotations

from pathlib import Path

from data_tools.kitti import read_kitti_calib
from data_tools.tum import read_calib_txt
from mona_vo.conventions import Intrinsics
from mona_vo.errors import InputError
from mona_vo.lens import COEFFICIENTS, Distortion, camera


def parse_calibration(value: str, width: int | None = None, height: int | None = None) -> Intrinsics:
    """Intrinsics from ``"fx,fy,cx,cy[,k1,k2,p1,p2,k3]"`` or from a calibration file path
    (LensIntrinsics with distortion); InputError otherwise."""
    text = value.strip()
    if not text:
        raise InputError("calibration is empty: give fx,fy,cx,cy in pixels or a calibration file")
    path = Path(text)
    try:
        exists, is_dir = path.exists(), path.is_dir()
    except (OSError, ValueError):  # not a usable path (too long, a NUL byte): a value, then
        exists = is_dir = False
    if is_dir:
        raise InputError(f"{path}: is a folder, expected a calibration file or fx,fy,cx,cy")
    if exists:
        try:
            with open(path, "rb") as f:
                head = f.read(4096).decode("utf-8", errors="replace")
        except OSError as exc:
            raise InputError(f"{path}: cannot read calibration ({exc.strerror or exc})") from None
        intr = read_kitti_calib(path) if "P0:" in head else read_calib_txt(path)
        where = str(path)
    else:
        parts = [p for p in text.replace(" ", ",").split(",") if p]
        try:
            numbers = [float(p) for p in parts]
        except ValueError:
            numbers = []
        if not 4 <= len(numbers) <= 4 + len(COEFFICIENTS):
            looks_like_file = any(c in text for c in "/\\") or text.endswith((".txt", ".yaml", ".json"))
            if looks_like_file:
                raise InputError(f"{text}: calibration file not found")
            raise InputError(f"calibration '{text}' is neither fx,fy,cx,cy[,k1,k2,p1,p2,k3] nor "
                             f"an existing file")
        intr = camera(Intrinsics(*numbers[:4]), Distortion.from_numbers(numbers[4:]))
        where = f"calibration '{text}'"
    problems = intr.check(width, height)
    if problems:
        raise InputError(f"{where}: {problems[0]}")
    return intr
