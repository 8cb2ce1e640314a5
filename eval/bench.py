"""``mona-vo bench``: speed and accuracy on generated 1024 x 436 sequences, side by side with
COLMAP's incremental SfM and its global SfM (GLOMAP) through pycolmap as the peers, in one run.

Per sequence: the generator writes a frame folder (images, GT masks, GT trajectory); mona-vo runs
on it from disk with no masks, with MONA masks and with the GT masks (its configuration as given:
``--refine global`` by default), given the true intrinsics and, with ``calibs`` holding
``estimated``, without them (the focal length then comes from :mod:`mona_vo.calibration`);
COLMAP's two mappers run on the same images after one shared feature extraction and matching,
without masks and, on dynamic presets, with the GT masks (no features on moving objects).
Reported: ATE (Sim(3), metres and % of the GT path), share of frames with a pose, wall time,
frames/s per stage, mean MONA mask IoU against GT, the focal length used, peak memory.
"""
from __future__ import annotations

import resource
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from data_tools.frames import open_frames
from data_tools.masks_io import write_mask_png
from data_tools.synthetic import SceneConfig, SyntheticScene, write_frames_folder
from eval.metrics import Trajectory, evaluate_trajectory
from mona_vo.errors import EvalError
from mona_vo.pipeline import PipelineConfig, estimate_trajectory


CALIBS = ("given", "estimated", "guess")


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


def run_ours(folder: Path, scene, variant: str, config: PipelineConfig, calib: str = "given") -> dict:
    """One mona-vo run. calib: ``given`` (the scene's true intrinsics), ``estimated`` (none given:
    the focal length is estimated) or ``guess`` (none given, the assumed field of view kept)."""
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
    if calib not in CALIBS:
        raise EvalError(f"bench: unknown calib {calib!r}; valid: {', '.join(CALIBS)}")
    if calib == "guess":
        config = replace(config, calibration=replace(config.calibration, mode="guess"))
    t0 = time.perf_counter()
    result = estimate_trajectory(source, intrinsics=scene.intrinsics if calib == "given" else None,
                                 masks=masks, config=config, on_frame=on_frame)
    wall = time.perf_counter() - t0
    n = result.n_frames
    gt = Trajectory(np.arange(len(scene), dtype=float), scene.poses())
    label = variant if calib == "given" else f"{variant}, {calib} focal"
    row = {"method": f"mona-vo ({label})", "frames_posed": n, "seconds": wall,
           "focal": float(result.vo.focal), "true_focal": float(scene.intrinsics.fx),
           **_score(gt, result.vo.timestamps, result.vo.poses),
           "stage_fps": {k: n / v for k, v in result.timings.items() if v > 0},
           "mask_iou": float(np.mean(ious)) if ious else None}
    return row


def run_peer(folder: Path, scene, with_masks: bool,
             mappers: tuple[str, ...] = ("incremental", "global")) -> list[dict]:
    """COLMAP's mappers on the frames (one shared extraction and matching): one row each."""
    from eval.colmap_peer import run_colmap

    mask_dir = None
    if with_masks:
        # COLMAP skips features where its mask is black: the inverse of a moving-object mask.
        mask_dir = Path(tempfile.mkdtemp(prefix="colmap-masks-"))
        for p in sorted((folder / "masks").glob("*.png")):
            from data_tools.masks_io import read_mask_png

            write_mask_png(mask_dir / f"{p.stem}.png.png", ~read_mask_png(p))
    try:
        outs = run_colmap(folder, scene.intrinsics, mask_dir=mask_dir, mappers=tuple(mappers))
    finally:
        if mask_dir is not None:
            shutil.rmtree(mask_dir, ignore_errors=True)
    if len(mappers) == 1:
        outs = {mappers[0]: outs}
    gt = Trajectory(np.arange(len(scene), dtype=float), scene.poses())
    rows = []
    for mapper, out in outs.items():
        names = sorted(out["poses"])
        ts = [int(Path(n).stem) for n in names]
        label = {"incremental": "COLMAP", "global": "GLOMAP"}[mapper]
        rows.append({"method": label + (" + GT masks" if with_masks else ""), "frames_posed": len(names),
                     "seconds": out["seconds"], **_score(gt, ts, [out["poses"][n] for n in names]),
                     "stage_fps": {"total": len(scene) / out["seconds"]}, "mask_iou": None,
                     "focal": float(scene.intrinsics.fx), "true_focal": float(scene.intrinsics.fx)})
    return rows


def bench(presets=("static", "one-large", "several"), seeds=(0,), *, n_frames: int = 50,
          width: int = 1024, height: int = 436, config: PipelineConfig | None = None,
          peer: bool = True, on_row=None, variants=("none", "mona", "gt"),
          calibs=("given",), mappers=("incremental", "global"), hfov_deg: float | None = None) -> list[dict]:
    """Rows of :func:`run_ours` (each variant x calib) and :func:`run_peer` per preset and seed.
    ``hfov_deg`` fixes the scenes' field of view (None: the generator draws it)."""
    config = config or PipelineConfig()
    rows = []
    for preset in presets:
        for seed in seeds:
            scene = SyntheticScene(SceneConfig(width=width, height=height, n_frames=n_frames,
                                               preset=preset, seed=seed, hfov_deg=hfov_deg))
            work = Path(tempfile.mkdtemp(prefix="mona-vo-bench-"))
            try:
                folder = write_frames_folder(scene, work / "frames")
                runs = [run_ours(folder, scene, v, config, c) for v in variants for c in calibs]
                if peer:
                    runs += run_peer(folder, scene, False, mappers)
                    if preset != "static":
                        runs += run_peer(folder, scene, True, mappers)
                for r in runs:
                    row = {"preset": preset, "seed": seed, "frames": n_frames,
                           "hfov_deg": float(np.degrees(2 * np.arctan(0.5 * width / scene.intrinsics.fx))), **r}
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
    focal = "" if r.get("focal") is None else f"  focal {r['focal']:.1f} (true {r['true_focal']:.1f})"
    return (f"{r['preset']:13s} {r['seed']:2d}  {r['method']:22s} ATE {ate}  posed "
            f"{r['frames_posed']:3d}/{r['frames']}  {r['seconds']:6.1f} s{iou}{focal}\n    frames/s: {stages}")


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
