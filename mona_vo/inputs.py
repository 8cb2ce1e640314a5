"""What a run is given, opened and checked before any work starts: the frames, the camera, the
masks and the ground truth. This module imports only the readers (no GTSAM, no SciPy, no
pipeline), so that the commands open a run's inputs first and turn a bad one into its one-line
error in about half a second, not after loading the whole pipeline (1.5 s more)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np

if TYPE_CHECKING:
    from data_tools.frames import FrameSource
    from mona_vo.conventions import Intrinsics


@dataclass
class RunInputs:
    """A run's inputs, each checked. ``masks`` is what was asked for ('mona', 'none', None or a
    folder); ``mask_source`` is what the pipeline takes: None, 'mona' or an iterator over the
    folder's masks in frame order."""

    input_path: str | Path                          # as given (the report quotes it)
    source: FrameSource
    intrinsics: Intrinsics | None                   # from --calib (LensIntrinsics with distortion)
    masks: str | None
    mask_source: str | Iterator[np.ndarray] | None
    gt_poses: np.ndarray | None                     # (N, 4, 4) camera-to-world, or None


def open_inputs(input_path: str | Path, *, calib: str | None = None, masks: str | None = "mona",
                stride: int = 1, max_frames: int | None = None,
                gt_path: str | Path | None = None) -> RunInputs:
    """Open the frames of a video or folder (every ``stride``-th, at most ``max_frames``), parse
    ``calib`` against their size, open a masks folder against their names and size (``masks``
    'mona' or 'none'/None open nothing) and read the ground truth; the first defect raises
    InputError or ConfigError naming the file or option."""
    from data_tools.calibration import parse_calibration
    from data_tools.frames import open_frames

    source = open_frames(input_path, stride=stride, max_frames=max_frames)
    intr = parse_calibration(calib, source.width, source.height) if calib else None
    mask_source = None
    if masks == "mona":
        mask_source = "mona"
    elif masks not in (None, "none"):
        from data_tools.masks_io import read_mask_folder

        # A run over some of the input's frames (stride, max_frames) may find more masks.
        subset = stride != 1 or max_frames is not None
        folder = read_mask_folder(masks, source.names, (source.width, source.height),
                                  allow_extra=subset)
        mask_source = iter(folder)
    gt_poses = None
    if gt_path is not None:
        from data_tools.tum import read_tum_trajectory

        _, gt_poses = read_tum_trajectory(gt_path)
    return RunInputs(input_path, source, intr, masks, mask_source, gt_poses)
