"""MPI Sintel sequences in the standard training layout, and a writer for that layout.

    <root>/training/<pass>/<seq>/frame_0001.png       pass = 'clean' | 'final', 1024 x 436 RGB
    <root>/training/camdata_left/<seq>/frame_0001.cam  per-frame K and world-to-camera [R|t]
    <root>/training/depth/<seq>/frame_0001.dpt         optional z-depth
    <root>/training/moving_masks/<seq>/frame_0001.png  optional moving-object masks (mona-vo's
                                                       generator; not part of Sintel itself)

Timestamps are the frame numbers of the file names (frame_0001 -> 1), as in LEAP-VO's and
ParticleSfM's evaluation. Poses are T_world_cam; the world-to-camera inversion happens in
:func:`data_tools.sintel_formats.read_cam` / ``write_cam`` only.
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Sequence

import numpy as np

from data_tools.frames import FrameSource, ImageFiles, natural_key, write_image
from data_tools.masks_io import MaskFolder, read_mask_folder, write_mask_png
from data_tools.sintel_formats import read_cam, read_dpt, write_cam, write_dpt
from mona_vo.conventions import Intrinsics
from mona_vo.errors import InputError

PASSES = ("clean", "final")
MASKS_DIR = "moving_masks"  # under training/, beside camdata_left
_FRAME = re.compile(r"frame_(\d+)\.png")


def _pass_dir(root: Path, pass_: str) -> Path:
    if pass_ not in PASSES:
        raise ValueError(f"Sintel pass must be one of {PASSES}, got {pass_!r}")
    folder = root / "training" / pass_
    if not folder.is_dir():
        raise InputError(f"{root}: no training/{pass_} folder (expected the MPI Sintel layout "
                         f"<root>/training/{pass_}/<sequence>/frame_0001.png)")
    return folder


def list_sequences(root: str | os.PathLike, pass_: str = "final") -> list[str]:
    """Sorted names of the sequence folders under ``<root>/training/<pass_>``."""
    folder = _pass_dir(Path(root), pass_)
    return sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))


class SintelSequence:
    """One Sintel training sequence with its per-frame camera data.

    Opening checks the layout: the pass folder, the sequence, its frames and a ``.cam`` file for
    every frame; each problem raises InputError (one line naming the path). Attributes:
    ``names`` (stems, 'frame_0001'), ``numbers`` (ints), ``timestamps`` ((N,) float64 frame
    numbers), ``frame_paths``, ``cam_paths``.
    """

    def __init__(self, root: str | os.PathLike, seq: str, pass_: str = "final"):
        self.root, self.seq, self.pass_ = Path(root), seq, pass_
        pass_dir = _pass_dir(self.root, pass_)
        self.frame_dir = pass_dir / seq
        if not self.frame_dir.is_dir():
            have = list_sequences(self.root, pass_)
            raise InputError(f"{self.frame_dir}: no such sequence (training/{pass_} has "
                             f"{', '.join(have[:5]) or 'none'}{', ...' if len(have) > 5 else ''})")
        self.frame_paths = sorted((p for p in self.frame_dir.iterdir() if _FRAME.fullmatch(p.name)),
                                  key=lambda p: natural_key(p.name))
        if not self.frame_paths:
            raise InputError(f"{self.frame_dir}: no frame_XXXX.png files")
        self.names = [p.stem for p in self.frame_paths]
        self.numbers = [int(_FRAME.fullmatch(p.name).group(1)) for p in self.frame_paths]
        self.timestamps = np.array(self.numbers, dtype=np.float64)
        training = self.root / "training"
        cam_dir = training / "camdata_left" / seq
        if not cam_dir.is_dir():
            raise InputError(f"{cam_dir}: camera data missing for sequence {seq} (from "
                             "MPI-Sintel-depth-training: training/camdata_left)")
        self.cam_paths = [cam_dir / f"{n}.cam" for n in self.names]
        missing = [p for p in self.cam_paths if not p.is_file()]
        if missing:
            raise InputError(f"{missing[0]}: no camera file for frame {missing[0].stem} "
                             f"({len(missing)} of {len(self.cam_paths)} frames lack one)")
        self.depth_dir = training / "depth" / seq
        self.mask_dir = training / MASKS_DIR / seq
        self._cams: list[tuple[Intrinsics, np.ndarray]] | None = None

    def __len__(self) -> int:
        return len(self.frame_paths)

    def frames(self, *, stride: int = 1, max_frames: int | None = None) -> FrameSource:
        """Streamed frames; timestamp = frame number ('frame_0001' -> 1.0)."""
        return ImageFiles(self.frame_paths, path=self.frame_dir, timestamps=self.timestamps,
                          timestamp_kind="frame_number", stride=stride, max_frames=max_frames)

    def _cameras(self) -> list[tuple[Intrinsics, np.ndarray]]:
        if self._cams is None:  # ~200 bytes per file: all of them fit in memory
            self._cams = [read_cam(p) for p in self.cam_paths]
        return self._cams

    def intrinsics(self) -> list[Intrinsics]:
        """Per-frame intrinsics (pixels) from the ``.cam`` files, one per frame."""
        return [intr for intr, _ in self._cameras()]

    def groundtruth(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps (N,) float64 frame numbers, poses (N, 4, 4) float64 T_world_cam)."""
        return self.timestamps.copy(), np.stack([T for _, T in self._cameras()])

    def depth(self, i: int) -> np.ndarray:
        """(H, W) float32 z-depth of frame position ``i`` (0-based) from training/depth."""
        return read_dpt(self.depth_dir / f"{self.names[i]}.dpt")

    @property
    def has_masks(self) -> bool:
        return self.mask_dir.is_dir()

    def masks(self, size: tuple[int, int] | None = None) -> MaskFolder:
        """Moving-object masks (training/moving_masks/<seq>/frame_XXXX.png), one per frame,
        checked up front (see :func:`data_tools.masks_io.read_mask_folder`)."""
        return read_mask_folder(self.mask_dir, self.names, size)


def write_sintel_frame(root: str | os.PathLike, seq: str, number: int, image_rgb: np.ndarray,
                       intrinsics: Intrinsics, T_world_cam: np.ndarray, *,
                       passes: str | Sequence[str] = ("clean",), depth: np.ndarray | None = None,
                       mask: np.ndarray | None = None) -> None:
    """Write frame ``number`` of ``seq`` in the Sintel layout under ``root``, each file atomically.

    image_rgb (H, W, 3) uint8 RGB, written once per pass in ``passes`` (e.g. ('clean', 'final')
    for a synthetic sequence without motion blur); T_world_cam (4, 4) float64 camera-to-world
    (stored world-to-camera in the ``.cam``); depth (H, W) float32 z-depth, optional; mask (H, W)
    bool moving objects, optional, written to training/moving_masks/<seq>/.
    """
    root = Path(root)
    passes = (passes,) if isinstance(passes, str) else tuple(passes)
    bad = [p for p in passes if p not in PASSES]
    if bad or not passes:
        raise ValueError(f"passes must be taken from {PASSES}, got {passes!r}")
    if not isinstance(number, (int, np.integer)) or not 0 <= number <= 9999:
        raise ValueError(f"frame number must be an integer in 0..9999, got {number!r}")
    name = f"frame_{int(number):04d}"
    training = root / "training"
    # The image goes last: a reader listing frames never finds one whose .cam is not written yet.
    write_cam(training / "camdata_left" / seq / f"{name}.cam", intrinsics, T_world_cam)
    if depth is not None:
        write_dpt(training / "depth" / seq / f"{name}.dpt", depth)
    if mask is not None:
        write_mask_png(training / MASKS_DIR / seq / f"{name}.png", mask)
    for p in passes:
        write_image(training / p / seq / f"{name}.png", image_rgb)
