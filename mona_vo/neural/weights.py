"""Where the neural back ends find their checkpoints. Nothing is ever downloaded at run time.

Each back end takes ``checkpoint=`` (a file, or a folder holding the file under its documented
name). Without it, the file is looked up by its documented name in the folder named by the
environment variable ``MONA_VO_WEIGHTS``. A missing file raises :class:`BackendError` with one
line naming the file, its official download address and where to put it.

Documented file names (put them in ``$MONA_VO_WEIGHTS``):

==============  ========================================  ========================================
key             file                                      back end
==============  ========================================  ========================================
raft_large      raft_large_C_T_SKHT_V2-ff5fadd5.pth       ``raft`` flow (torchvision RAFT-large)
raft_small      raft_small_C_T_V2-01064c6d.pth            ``raft`` flow with ``model='small'``
yolo            yolo11n.pt                                ``yolo`` detector (ultralytics)
sam_vit_b       sam_vit_b_01ec64.pth                      ``sam`` segmenter, ``model_type='vit_b'``
sam_vit_l       sam_vit_l_0b3195.pth                      ``sam`` segmenter, ``model_type='vit_l'``
sam_vit_h       sam_vit_h_4b8939.pth                      ``sam`` segmenter, ``model_type='vit_h'``
cotracker       scaled_offline.pth                        CoTracker3 tracker (offline model)
==============  ========================================  ========================================

This module imports no torch: the missing-checkpoint error is raised before any network package
is imported.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mona_vo.errors import BackendError

WEIGHTS_ENV = "MONA_VO_WEIGHTS"


@dataclass(frozen=True)
class WeightFile:
    """One checkpoint: its file name in the weights folder and its official download address."""

    name: str       # file name in $MONA_VO_WEIGHTS
    url: str        # official download address (the publisher's own)
    what: str       # what it is, for messages


WEIGHT_FILES: dict[str, WeightFile] = {
    "raft_large": WeightFile(
        "raft_large_C_T_SKHT_V2-ff5fadd5.pth",
        "https://download.pytorch.org/models/raft_large_C_T_SKHT_V2-ff5fadd5.pth",
        "torchvision RAFT-large optical flow (C+T+S+K+H)"),
    "raft_small": WeightFile(
        "raft_small_C_T_V2-01064c6d.pth",
        "https://download.pytorch.org/models/raft_small_C_T_V2-01064c6d.pth",
        "torchvision RAFT-small optical flow (C+T)"),
    "yolo": WeightFile(
        "yolo11n.pt",
        "https://github.com/ultralytics/assets/releases/download/v8.3.0/yolo11n.pt",
        "Ultralytics YOLO11n COCO detector"),
    "sam_vit_b": WeightFile(
        "sam_vit_b_01ec64.pth",
        "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_b_01ec64.pth",
        "Segment Anything ViT-B"),
    "sam_vit_l": WeightFile(
        "sam_vit_l_0b3195.pth",
        "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_l_0b3195.pth",
        "Segment Anything ViT-L"),
    "sam_vit_h": WeightFile(
        "sam_vit_h_4b8939.pth",
        "https://dl.fbaipublicfiles.com/segment_anything/sam_vit_h_4b8939.pth",
        "Segment Anything ViT-H"),
    "cotracker": WeightFile(
        "scaled_offline.pth",
        "https://huggingface.co/facebook/cotracker3/resolve/main/scaled_offline.pth",
        "CoTracker3 offline point tracker"),
}


def _missing(weight: WeightFile, reason: str) -> BackendError:
    return BackendError(
        f"{weight.what} checkpoint {reason}: download {weight.name} from {weight.url} and put it "
        f"in the folder named by ${WEIGHTS_ENV} (or pass its path as checkpoint=)")


def resolve_checkpoint(key: str, checkpoint: str | os.PathLike | None = None) -> Path:
    """Path of an existing checkpoint file for ``key`` (a key of :data:`WEIGHT_FILES`).

    ``checkpoint``: a file, or a folder that holds the documented file name; None looks in
    ``$MONA_VO_WEIGHTS``. Raises :class:`BackendError` (one line: file, URL, where to put it)
    when the file is not there.
    """
    if key not in WEIGHT_FILES:
        raise KeyError(f"no documented checkpoint for '{key}'; known: {', '.join(WEIGHT_FILES)}")
    weight = WEIGHT_FILES[key]
    if checkpoint is not None and str(checkpoint) != "":
        path = Path(checkpoint).expanduser()
        if path.is_dir():
            path = path / weight.name
        if path.is_file():
            return path
        raise _missing(weight, f"not found at {path}")
    folder = os.environ.get(WEIGHTS_ENV, "")
    if not folder:
        raise _missing(weight, f"not given (no checkpoint= and ${WEIGHTS_ENV} is not set)")
    path = Path(folder).expanduser() / weight.name
    if path.is_file():
        return path
    raise _missing(weight, f"not found at {path}")
