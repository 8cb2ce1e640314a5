"""Copies of a frame folder with something done to its images (bars painted, overlays burned in,
frames held: ``data_tools.bars``, ``data_tools.overlays``, ``data_tools.repeats``): the same
names and formats, and a TUM-layout folder's text files (``rgb.txt``, ``groundtruth.txt``,
``calib.txt``) copied with it, so the copy runs through the same commands as the original."""
from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from data_tools.atomic import write_bytes_atomic
from data_tools.frames import IMAGE_EXTENSIONS
from mona_vo.errors import InputError

TUM_TEXT_FILES = ("rgb.txt", "groundtruth.txt", "calib.txt")


def image_folder_copy(src, dst) -> tuple[list[Path], Path]:
    """The sorted image files of ``src`` (or of its ``rgb/`` folder) and the folder of ``dst``
    their copies go to (made; a TUM folder's text files copied into ``dst``)."""
    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise InputError(f"{src}: not a folder")
    images = src / "rgb" if (src / "rgb").is_dir() else src
    files = sorted(p for p in images.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise InputError(f"{images}: no images")
    out = dst / images.relative_to(src)
    out.mkdir(parents=True, exist_ok=True)
    for name in TUM_TEXT_FILES:
        if images != src and (src / name).is_file():
            shutil.copy(src / name, dst / name)
    return files, out


def rewrite_image(src: Path, dst: Path, change: Callable[[np.ndarray], np.ndarray]) -> None:
    """Write ``change`` of the (H, W, 3) uint8 RGB image ``src`` to ``dst``, in ``dst``'s format."""
    im = cv2.imread(str(src), cv2.IMREAD_COLOR)
    if im is None:
        raise InputError(f"{src}: cannot be read as an image")
    rgb = change(cv2.cvtColor(im, cv2.COLOR_BGR2RGB))
    ok, buf = cv2.imencode(dst.suffix, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise InputError(f"{dst}: cannot be written as {dst.suffix}")
    write_bytes_atomic(dst, buf.tobytes())


def copy_tool_main(argv, prog: str, doc: str, write: Callable[[argparse.Namespace], str],
                   options: Callable[[argparse.ArgumentParser], None] | None = None) -> int:
    """The command line of a copy tool: ``SRC DST`` and ``options``; ``write(args)`` makes the
    copy and returns the line to print. Bad input (an InputError): one line on stderr naming
    the file, exit status 1."""
    ap = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    if options is not None:
        options(ap)
    args = ap.parse_args(argv)
    try:
        said = write(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(said)
    return 0
