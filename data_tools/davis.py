"""DAVIS video object segmentation sequences (standard layout), for moving-object mask evaluation.

    <root>/JPEGImages/<resolution>/<seq>/00000.jpg   RGB frames
    <root>/Annotations/<resolution>/<seq>/00000.png  ground-truth masks, one per frame

DAVIS-2016 masks hold {0, 255}; DAVIS-2017 masks are palette PNGs of object ids. Either way a
pixel with a non-zero value is foreground, so a mask is the union of the annotated objects.
"""
from __future__ import annotations

import os
from pathlib import Path

from data_tools.frames import FrameSource, ImageFiles, natural_key
from data_tools.masks_io import MaskFolder, read_mask_folder
from mona_vo.errors import InputError


def list_sequences(root: str | os.PathLike, resolution: str = "480p") -> list[str]:
    """Sorted sequence names under ``<root>/JPEGImages/<resolution>``."""
    folder = Path(root) / "JPEGImages" / resolution
    if not folder.is_dir():
        raise InputError(f"{root}: no JPEGImages/{resolution} folder (expected the DAVIS layout)")
    return sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))


class DavisSequence:
    """One DAVIS sequence: its frames and (optional) per-frame ground-truth masks.

    ``names`` are the frame stems ('00000'); timestamps are their numbers (00012 -> 12.0).
    Missing frames raise InputError at opening; missing masks only when :meth:`masks` is called.
    """

    def __init__(self, root: str | os.PathLike, seq: str, resolution: str = "480p"):
        self.root, self.seq, self.resolution = Path(root), seq, resolution
        self.frame_dir = self.root / "JPEGImages" / resolution / seq
        self.mask_dir = self.root / "Annotations" / resolution / seq
        if not self.frame_dir.is_dir():
            have = list_sequences(self.root, resolution)
            raise InputError(f"{self.frame_dir}: no such sequence (JPEGImages/{resolution} has "
                             f"{', '.join(have[:5]) or 'none'}{', ...' if len(have) > 5 else ''})")
        self.frame_paths = sorted((p for p in self.frame_dir.glob("*.jpg") if not p.name.startswith(".")),
                                  key=lambda p: natural_key(p.name))
        if not self.frame_paths:
            raise InputError(f"{self.frame_dir}: no .jpg frames")
        self.names = [p.stem for p in self.frame_paths]

    def __len__(self) -> int:
        return len(self.frame_paths)

    def frames(self, *, stride: int = 1, max_frames: int | None = None) -> FrameSource:
        """Streamed frames; timestamp = the number in the name."""
        return ImageFiles(self.frame_paths, path=self.frame_dir, stride=stride, max_frames=max_frames)

    @property
    def mask_names(self) -> list[str]:
        """Stems of the annotation PNGs present, in natural order (may be fewer than the frames)."""
        if not self.mask_dir.is_dir():
            return []
        return [p.stem for p in sorted(self.mask_dir.glob("*.png"), key=lambda p: natural_key(p.name))
                if not p.name.startswith(".")]

    def masks(self, size: tuple[int, int] | None = None) -> MaskFolder:
        """Ground-truth masks, (H, W) bool each, one per frame in frame order, checked up front
        (a mask for every frame, no extra, optional size (width, height))."""
        return read_mask_folder(self.mask_dir, self.names, size)
