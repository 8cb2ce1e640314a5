"""``mona-vo bench``: speed and accuracy on generated 1024 x 436 sequences, side by side with
COLMAP's incremental SfM (pycolmap) as the peer, in one run.

Per sequence: the generator writes a frame folder (images, GT masks, GT trajectory); mona-vo runs
on it from disk with no masks, with MONA masks and with the GT masks; COLMAP runs on the same
images without masks and with the GT masks (its features are not extracted on moving objects).
Reported: ATE (Sim(3), metres and % of the GT path), share of frames with a pose, wall time,
frames/s per stage, mean MONA mask IoU against GT, peak memory.
"""
from __future__ import annotations

import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from data_tools.frames import open_frames
from data_tools.masks_io import write_mask_png
from data_tools.synthetic import SceneConfig, SyntheticScene, write_frames_folder
from eval.metrics import Trajectory, evaluate_trajectory
from mona_vo.errors import EvalError
from mona_vo.pipeline import PipelineConfig, estimate_trajectory


def _iou(pred: np.ndarray, gt: np.ndarray) -> float | None:
    union = np.logical_or(pred, gt).sum()
    return None if union == 0 else float(np.logical_and(pred, gt).sum() / union)


def _score(gt: Trajectory, timestamps, poses) -> dict:
    if len(timestamps) < 3:
        return {"ate": None, "ate_pct": None}
    try:
        m = evaluate_trajectory(gt, Trajectory(np.asarray(timestamps, float), np.asarray(poses)))
    except EvalError:
        return {"ate": None, "ate_pct": None}
    return {"ate": m.ate, "ate_pct": m.ate_percent_of_path}


def run_ours(folder: Path, scene, variant: str, config: PipelineConfig) -> dict:
    from data_tools.masks_io import read_mask_folder

    source = open_frames(folder)
    masks = {"none": None, "mona": "mona",
             "gt": lambda: iter(read_mask_folder(folder / "masks", source.names))}[variant]
    masks = masks() if callable(masks) else masks
    gt_masks = read_mask_folder(folder / "masks", source.names)
    ious = []

    def on_frame(f):
        if variant == "mona":
            iou = _iou(f.mask, gt_masks[f.index])
            if iou is not None:
                ious.append(iou)
    t0 = time.perf_counter()
    result = estimate_trajectory(source, intrinsics=scene.intrinsics, masks=masks, config=config,
                                 on_frame=on_frame)
    wall = time.perf_counter() - t0
    n = result.n_frames
    gt = Trajectory(np.arange(len(scene), dtype=float), scene.poses())
    row = {"method": f"mona-vo ({variant})", "frames_posed": n, "seconds": wall,
           **_score(gt, result.vo.timestamps, result.vo.poses),
           "stage_fps": {k: n / v for k, v in result.timings.items() if v > 0},
           "mask_iou": float(np.mean(ious)) if ious else None}
    return row


def run_peer(folder: Path, scene, with_masks: bool) -> dict:
    from eval.colmap_peer import run_colmap

    mask_dir = None
    if with_masks:
        # COLMAP skips features where its mask is black: the inverse of a moving-object mask.
        mask_dir = Path(tempfile.mkdtemp(prefix="colmap-masks-"))
        for p in sorted((folder / "masks").glob("*.png")):
            from data_tools.masks_io import read_mask_png

            write_mask_png(mask_dir / f"{p.stem}.png.png", ~read_mask_png(p))
    try:
        out = run_colmap(folder, scene.intrinsics, mask_dir=mask_dir)
    finally:
        if mask_dir is not None:
            shutil.rmtree(mask_dir, ignore_errors=True)
    names = sorted(out["poses"])
    ts = [int(Path(n).stem) for n in names]
    gt = Trajectory(np.arange(len(scene), dtype=float), scene.poses())
    return {"method": "COLMAP" + (" + GT masks" if with_masks else ""), "frames_posed": len(names),
            "seconds": out["seconds"], **_score(gt, ts, [out["poses"][n] for n in names]),
            "stage_fps": {"total": len(scene) / out["seconds"]}, "mask_iou": None}


def bench(presets=("static", "one-large", "several"), seeds=(0,), *, n_frames: int = 50,
          width: int = 1024, height: int = 436, config: PipelineConfig | None = None,
          peer: bool = True, on_row=None) -> list[dict]:
    config = config or PipelineConfig()
    rows = []
    for preset in presets:
        for seed in seeds:
            scene = SyntheticScene(SceneConfig(width=width, height=height, n_frames=n_frames,
                                               preset=preset, seed=seed))
            work = Path(tempfile.mkdtemp(prefix="mona-vo-bench-"))
            try:
                folder = write_frames_folder(scene, work / "frames")
                runs = [run_ours(folder, scene, v, config) for v in ("none", "mona", "gt")]
                if peer:
                    runs += [run_peer(folder, scene, False)]
                    if preset != "static":
                        runs += [run_peer(folder, scene, True)]
                for r in runs:
                    row = {"preset": preset, "seed": seed, "frames": n_frames, **r}
                    rows.append(row)
                    if on_row is not None:
                        on_row(row)
            finally:
                shutil.rmtree(work, ignore_errors=True)
    return rows


def peak_memory_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def format_row(r: dict) -> str:
    ate = "   fail" if r["ate"] is None else f"{r['ate']:.4f} m {r['ate_pct']:7.3f}%"
    iou = "" if r["mask_iou"] is None else f"  mask IoU {r['mask_iou']:.3f}"
    stages = "  ".join(f"{k} {v:.1f}" for k, v in sorted(r["stage_fps"].items()))
    return (f"{r['preset']:13s} {r['seed']:2d}  {r['method']:22s} ATE {ate}  posed "
            f"{r['frames_posed']:3d}/{r['frames']}  {r['seconds']:6.1f} s{iou}\n    frames/s: {stages}")


def summary_table(rows: list[dict]) -> str:
    lines = ["| method | sequences | mean ATE % of path | max ATE % | frames posed | frames/s (total) | mask IoU |",
             "|---|---|---|---|---|---|---|"]
    for method in dict.fromkeys(r["method"] for r in rows):
        sel = [r for r in rows if r["method"] == method]
        ok = [r["ate_pct"] for r in sel if r["ate_pct"] is not None]
        posed = sum(r["frames_posed"] for r in sel) / max(1, sum(r["frames"] for r in sel))
        fps = np.mean([r["stage_fps"].get("total", np.nan) for r in sel])
        ious = [r["mask_iou"] for r in sel if r["mask_iou"] is not None]
        lines.append(f"| {method} | {len(sel)} ({len(sel) - len(ok)} failed) | "
                     f"{np.mean(ok) if ok else float('nan'):.3f} | {max(ok) if ok else float('nan'):.3f} | "
                     f"{100 * posed:.0f} % | {fps:.1f} | {np.mean(ious) if ious else float('nan'):.3f} |")
    return "\n".join(lines)
