"""Dataset readers behind the evaluation harness: each turns a dataset folder into
:class:`EvalSequence` objects. All file reading goes through data_tools. Light on imports (no
pipeline), so that `eval sintel` and `eval tum` check their folders before loading it."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

from data_tools.masks_io import read_mask_folder
from data_tools.sintel import SintelSequence, list_sequences as list_sintel
from data_tools.tum import TumSequence
from eval.metrics import Trajectory
from mona_vo.conventions import Intrinsics
from mona_vo.errors import InputError


@dataclass
class EvalSequence:
    """One sequence of a dataset, ready to run.

    frames:     callable returning a fresh frame iterator (objects with index, timestamp, name,
                image), so a sequence can be run once per variant.
    n_frames:   number of frames.
    intrinsics: one Intrinsics, a per-frame list, or None (the VO's guess).
    gt:         ground-truth trajectory (timestamps in the same clock as the frames').
    gt_masks:   callable returning an iterator of (H, W) bool masks aligned with the frames, or
                None when the dataset has none.
    max_diff:   timestamp association tolerance for the metrics, seconds (or frames).
    """

    name: str
    frames: Callable[[], Iterable]
    n_frames: int
    intrinsics: object
    gt: Trajectory
    gt_masks: Callable[[], Iterable] | None = None
    max_diff: float = 0.01
    error: str | None = None     # a damaged file found up front: every run of it fails with this


# The 14 sequences of the Sintel camera-trajectory protocol (LEAP-VO, ParticleSfM, MONA).
SINTEL_SEQUENCES = ("alley_2", "ambush_4", "ambush_5", "ambush_6", "cave_2", "cave_4", "market_2",
                    "market_5", "market_6", "shaman_3", "sleeping_1", "sleeping_2", "temple_2",
                    "temple_3")


def sintel_sequences(root: str | Path, *, pass_: str = "final", names: list[str] | None = None,
                     masks_root: str | Path | None = None) -> list[EvalSequence]:
    """The named sequences (default: the protocol's 14) of a Sintel-layout root. GT masks are
    read from ``masks_root/<seq>/frame_XXXX.png`` when given. Checks everything up front."""
    root = Path(root)
    if not (root / "training").is_dir():
        raise InputError(f"{root}: not a Sintel root (no training/ folder)")
    present = list_sintel(root, pass_)
    wanted = list(names) if names else list(SINTEL_SEQUENCES)
    missing = [n for n in wanted if n not in present]
    if missing:
        raise InputError(f"{root}: sequence(s) {', '.join(missing)} missing from training/{pass_}/"
                         f" (present: {', '.join(present) or 'none'})")
    out = []
    for name in wanted:
        seq = SintelSequence(root, name, pass_)   # missing folders: an error for the whole run
        try:
            # Damaged files inside one sequence fail that sequence only.
            intr = seq.intrinsics()
            ts, poses = seq.groundtruth()
            frames = seq.frames()
            gt_masks = None
            if masks_root is not None:
                folder = read_mask_folder(Path(masks_root) / name, seq.names, (frames.width, frames.height))
                gt_masks = (lambda f=folder: iter(f))
        except InputError as exc:
            out.append(EvalSequence(name=name, frames=seq.frames, n_frames=len(seq), intrinsics=None,
                                    gt=None, error=str(exc)))
            continue
        out.append(EvalSequence(name=name, frames=seq.frames, n_frames=len(seq), intrinsics=intr,
                                gt=Trajectory(ts, poses), gt_masks=gt_masks, max_diff=0.01))
    return out


# The TUM RGB-D benchmark's own association tolerance (its associate.py and evaluate_ate.py
# default). evo's default of 10 ms is too tight for 30 Hz streams whose clocks drift against
# each other: on bonn_crowd_long it matches 257 of 450 frames, in runs separated by two gaps of
# 71 and 75 frames, and the "1-frame" RPE pairs spanning them dominate the RPE (27 and 25 deg
# of the 2.5 deg RMSE). Half the 33 ms frame period matches every frame to its nearest GT pose.
TUM_MAX_DIFF = 0.02


def tum_sequences(roots: list[str | Path], *, calib: Intrinsics | None = None,
                  max_diff: float = TUM_MAX_DIFF, folder_calib: bool = True) -> list[EvalSequence]:
    """Folders in TUM RGB-D layout (rgb.txt, rgb/, groundtruth.txt, optional calib.txt). Poses
    are stamped with rgb.txt's timestamps and associated with the GT by evo's nearest-timestamp
    rule within ``max_diff`` seconds (default :data:`TUM_MAX_DIFF`). ``folder_calib=False``
    ignores calib.txt (the run estimates the camera, as for an online video)."""
    out = []
    for root in roots:
        seq = TumSequence(root)
        intr = calib or (seq.intrinsics() if folder_calib else None)
        ts, poses = seq.groundtruth()
        out.append(EvalSequence(name=Path(root).resolve().name, frames=seq.frames,
                                n_frames=len(seq.timestamps), intrinsics=intr,
                                gt=Trajectory(ts, poses), gt_masks=None, max_diff=max_diff))
    return out
