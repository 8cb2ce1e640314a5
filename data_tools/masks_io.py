"""Moving-object masks as PNG files: one 8-bit image per frame, 0 = static, 255 = moving.

In memory a mask is (H, W) bool, True on moving objects. A mask folder holds ``<frame name>.png``
for every frame; :func:`read_mask_folder` checks that correspondence before any mask is used.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from data_tools.atomic import write_bytes_atomic
from data_tools.frames import decode_file, image_size
from mona_vo.errors import InputError

_SHOWN = 5  # file names listed in a message before '...'


def write_mask_png(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Write an (H, W) mask (bool, or numbers: non-zero = moving) as an 8-bit 0/255 PNG, atomically."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be (H, W), got shape {mask.shape}")
    ok, buf = cv2.imencode(".png", np.where(mask != 0, 255, 0).astype(np.uint8))
    if not ok:
        raise ValueError("OpenCV could not encode the mask as PNG")
    write_bytes_atomic(path, buf.tobytes())


def read_mask_png(path: str | os.PathLike) -> np.ndarray:
    """(H, W) bool mask: True where any colour channel is non-zero.

    Works for 0/255 and 0/1 binary PNGs and for DAVIS-2017 palette PNGs (object ids > 0 are
    foreground; their union is the moving mask). Raises InputError naming the file.
    """
    path = Path(path)
    image = decode_file(path, cv2.IMREAD_UNCHANGED, "mask image")
    if image.ndim == 3:
        image = image[:, :, :3]  # an alpha channel is not part of the mask
        return np.any(image != 0, axis=2)
    return image != 0


def _listing(names: Sequence[str]) -> str:
    shown = ", ".join(names[:_SHOWN])
    return shown + (f", ... ({len(names)} in all)" if len(names) > _SHOWN else "")


class MaskFolder:
    """Masks of a sequence, one per frame, read lazily: ``len()``, iteration in frame order and
    ``masks[i]`` each give (H, W) bool arrays. ``paths`` lists the files."""

    def __init__(self, folder: Path, paths: list[Path]):
        self.folder = folder
        self.paths = paths

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int) -> np.ndarray:
        return read_mask_png(self.paths[i])

    def __iter__(self) -> Iterator[np.ndarray]:
        for p in self.paths:
            yield read_mask_png(p)


def read_mask_folder(folder: str | os.PathLike, names: Sequence[str], size: tuple[int, int] | None = None,
                     *, allow_extra: bool = False) -> MaskFolder:
    """Masks ``<name>.png`` in ``folder`` for the frame names (stems, used as given: a name such
    as '1548339827.58438' is not an extension), checked up front.

    Checks that every frame has a mask, that no mask matches no frame (unless ``allow_extra``,
    e.g. for a strided run that uses every other frame), and, if ``size`` = (width, height) in
    pixels is given, that every mask has that size (read from the PNG header). Each problem raises
    InputError naming the folder and the file(s).
    """
    folder = Path(folder)
    try:
        found = folder.is_dir()
    except (OSError, ValueError):  # e.g. a name longer than the file system allows
        found = False
    if not found:
        raise InputError(f"{folder}: mask folder not found")
    paths = [folder / f"{name}.png" for name in names]
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        raise InputError(f"{folder}: no mask for {len(missing)} of {len(paths)} frames: {_listing(missing)}")
    if not allow_extra:
        expected = {p.name for p in paths}
        extra = sorted(p.name for p in folder.glob("*.png")
                       if p.name not in expected and not p.name.startswith("."))
        if extra:
            raise InputError(f"{folder}: {len(extra)} masks match no frame: {_listing(extra)}")
    if size is not None:
        w, h = size
        for p in paths:
            got = image_size(p)
            if got != (w, h):
                raise InputError(f"{folder}: mask {p.name} is {got[0]}x{got[1]}, the frames are {w}x{h}")
    return MaskFolder(folder, paths)
