"""What the commands do, as library calls: ``run`` (trajectory + masks + report of one video or
folder), ``masks_only`` and ``demo``. The CLI parses options and calls these; Python users can
call them directly. Outputs are written through :class:`data_tools.run_outputs.RunOutputs`
(temporary names, renamed into place at the end)."""
from __future__ import annotations

import dataclasses
import platform
import time
from pathlib import Path

import numpy as np

from mona_vo import __version__
from mona_vo.config import to_dict
from mona_vo.conventions import Intrinsics
from mona_vo.inputs import RunInputs, open_inputs
from mona_vo.pipeline import FrameOutput, PipelineConfig, estimate_trajectory


def _progress_bar(total: int | None, desc: str, enabled: bool):
    if not enabled:
        return None, lambda n, name=None: None
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="frame", leave=False)
    stage = [None]

    def update(n, name=None):
        # A later VO pass over the same frames (estimate_trajectory's progress) counts from 0
        # again under its own name.
        if name != stage[0]:
            stage[0] = name
            bar.reset(total=total)
            bar.set_description(f"{desc}: {name}" if name else desc)
        bar.update(n - bar.n)
    return bar, update


def run(input_path: str | Path, out_dir: str | Path, *, calib: str | None = None,
        masks: str | None = "mona", config: PipelineConfig | None = None, overlay: bool = False,
        stride: int = 1, max_frames: int | None = None, progress: bool = True,
        gt_path: str | Path | None = None, verdict=None, page_name: str | None = None) -> dict:
    """Trajectory, masks and report of a video file or a folder of images. Returns the report
    (also written to ``out_dir/report.json``). Also writes ``out_dir/index.html``, the page of
    :mod:`mona_vo.report_html` for this one video (``verdict``: a batch.VerdictConfig, None for
    the defaults; ``page_name``: the clip's name on it, default the input's name)."""
    # Everything the user gave is checked before the first frame is processed, so that a bad
    # option fails in a second, not after the run (which would lose the run's work).
    inputs = open_inputs(input_path, calib=calib, masks=masks, stride=stride,
                         max_frames=max_frames, gt_path=gt_path)
    return run_opened(inputs, out_dir, config=config, overlay=overlay, progress=progress,
                      verdict=verdict, page_name=page_name)


def run_opened(inputs: RunInputs, out_dir: str | Path, *, config: PipelineConfig | None = None,
               overlay: bool = False, progress: bool = True, verdict=None,
               page_name: str | None = None) -> dict:
    """:func:`run` on inputs already opened by :func:`mona_vo.inputs.open_inputs` (the CLI opens
    them before it loads the pipeline)."""
    from data_tools.run_outputs import RunOutputs
    from eval.plots import plot_trajectory
    from mona_vo.batch import run_page_files
    from mona_vo.report_html import ThumbnailStrip

    config = config or PipelineConfig()
    input_path, source, masks = inputs.input_path, inputs.source, inputs.masks
    intr, mask_src, gt_poses = inputs.intrinsics, inputs.mask_source, inputs.gt_poses
    overlay_writer = None
    with RunOutputs(out_dir, write_masks=masks not in (None, "none")) as outputs:
        if overlay:
            from data_tools.overlay import OverlayWriter

            overlay_writer = OverlayWriter(outputs.staging / "overlay.mp4",
                                           fps=source.fps or 10.0)

        strip = ThumbnailStrip(len(source))

        def on_frame(f: FrameOutput):
            outputs.add_mask(f.name, f.mask)
            strip.add(f)
            if overlay_writer is not None:
                overlay_writer.add(f)

        bar, update = _progress_bar(len(source), "mona-vo run", progress)
        try:
            result = estimate_trajectory(source, intrinsics=intr, masks=mask_src, config=config,
                                         on_frame=on_frame, progress=update)
        finally:
            if bar is not None:
                bar.close()
            if overlay_writer is not None:
                overlay_writer.close()
        vo = result.vo
        gt_xyz = None
        if gt_poses is not None and len(gt_poses) == len(vo.poses):
            gt_xyz = gt_poses[:, :3, 3]
        plot = plot_trajectory(outputs.staging / "trajectory.png", vo.poses[:, :3, 3], gt_xyz,
                               title=f"{Path(input_path).name}: {result.n_frames} frames",
                               low_confidence=vo.low_confidence)
        report = build_report(result, input_path=input_path, source=source, masks=masks,
                              config=config, calib_given=intr is not None)
        extra = {"trajectory.png": plot}
        extra.update(run_page_files(outputs.staging, report, strip, verdict=verdict,
                                    name=page_name or Path(input_path).name))
        if overlay_writer is not None:
            extra["overlay.mp4"] = overlay_writer.path
        outputs.commit(timestamps=vo.timestamps, poses=vo.poses, report=report, extra_files=extra)
    return report


def build_report(result, *, input_path, source, masks, config, calib_given: bool) -> dict:
    vo = result.vo
    t = result.timings
    per_stage = {k: round(v, 4) for k, v in sorted(t.items())}
    fps = {k: (result.n_frames / v if v > 0 else None) for k, v in t.items()}
    low = [result.names[i] for i in np.flatnonzero(vo.low_confidence)]
    intr = result.intrinsics
    return {
        "mona_vo_version": __version__,
        "input": str(input_path),
        "input_kind": getattr(source, "kind", None),
        "frames": result.n_frames,
        "frames_with_pose": int(np.isfinite(vo.poses).all(axis=(1, 2)).sum()),
        "keyframes": int(vo.is_keyframe.sum()),
        "reprojection_rmse_px": getattr(vo, "reprojection_rmse_px", None),
        "image_size": [result.width, result.height],
        # The picture inside flat letterbox / pillarbox bars, where the run looked (crop_bars);
        # pixel values under global_refinement are the picture's, all others the frame's.
        "picture_area": result.picture.as_dict() if result.picture is not None else None,
        # Burned-in logos and captions found standing still and painted over (hide_overlays).
        "overlay": _overlay_summary(getattr(result, "overlay", None)),
        "masks": masks or "none",
        "mean_mask_coverage": float(result.mask_coverage.mean()) if result.n_frames else 0.0,
        "calibration": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
                        "source": "given" if calib_given else
                                  _camera_source(_focal_estimated(result), config),
                        # fx above is the start; without --calib the global refinement
                        # frees the focal length over the whole clip, and this is the one used.
                        "focal_used": vo.focal,
                        "focal_refined": "focal_px" in (getattr(vo, "refine", None) or {}),
                        "focal_estimate": _focal_evidence(result),
                        # A distorted lens (--calib with k1 k2 p1 p2 k3): the frames were
                        # resampled to the pinhole camera with the same K (mona_vo.lens).
                        "lens": getattr(result, "lens", None)},
        "seconds": per_stage,
        "frames_per_second": {k: round(v, 2) for k, v in fps.items() if v is not None},
        "dropped": dict(vo.drops),
        # Landmarks whose tracks were lost (hidden by a passer-by) and that were found again.
        "landmarks_found_again": getattr(vo, "found_again", 0),
        # Translation evidence over the clip: rotation-free parallax vs the tracking noise floor.
        "parallax": getattr(vo, "parallax", None),
        "global_refinement": getattr(vo, "refine", None) or None,
        "pose_support": vo.pose_support(),
        "status_counts": {s: vo.status.count(s) for s in sorted(set(vo.status))},
        # One entry per map; a new one starts where tracking was lost (a blank stretch, a cut
        # between shots): each has its own scale, and the pose across a join is not measured.
        "map_segments": [{"first": result.names[a], "last": result.names[b], "frames": b - a + 1}
                         for a, b in getattr(vo, "map_segments", [])],
        "low_confidence_frames": low,
        # Frames that show the frame before them again (pulldown, a stalled stream): not
        # processed, they took that frame's pose and mask (mona_vo.repeats).
        "repeated_frames": _repeated_frames(result),
        "frame_status": dict(zip(result.names, vo.status)),
        "timestamps": "seconds from file names" if getattr(source, "timestamp_kind", "") == "seconds"
                      else "frame numbers",
        "config": to_dict(config),
        "machine": {"cpu_count": _cpu_count(), "platform": platform.platform()},
    }


def clip_summary(result, *, name: str, masks: str, config, calib_given: bool) -> dict:
    """The numbers ``batch``'s verdict judges a run by (:func:`mona_vo.batch.summary_from_report`
    of the report this run would write), for callers that keep no output folder (the benches,
    the evaluation harness), so that they judge exactly what ``batch`` judges."""
    from mona_vo.batch import summary_from_report

    return summary_from_report(build_report(result, input_path=name, source=None, masks=masks,
                                            config=config, calib_given=calib_given))


def _overlay_summary(overlay) -> dict | None:
    """The burned-in overlay painted over (mona_vo.overlays): its share of the frame and the
    box [x0, y0, x1, y1] (frame pixels, exclusive ends) of each of its parts; None: none found."""
    if overlay is None:
        return None
    import cv2

    n, _, stats, _ = cv2.connectedComponentsWithStats(overlay.astype(np.uint8), connectivity=8)
    boxes = [[int(x), int(y), int(x + w), int(y + h)] for x, y, w, h, _ in stats[1:]]
    return {"area": round(float(overlay.mean()), 5), "boxes": boxes}


def _repeated_frames(result) -> dict[str, str]:
    """{frame name: the name of the frame it repeats} (mona_vo.repeats)."""
    rep = getattr(result, "repeat_of", None)
    if rep is None:
        return {}
    return {result.names[k]: result.names[int(j)] for k, j in enumerate(rep) if j >= 0}


def _camera_source(estimated: bool, config: PipelineConfig) -> str:
    """How a run without --calib found its camera, as the reports say it."""
    return ("estimated from the first frames" if estimated
            else f"{config.assumed_hfov_deg:g}-degree field-of-view guess")


def _focal_estimated(result) -> bool:
    return bool(getattr(getattr(result, "calibration", None), "used", False))


def _focal_evidence(result) -> dict | None:
    """What the focal-length estimate tried and found (mona_vo.calibration), None with --calib."""
    est = getattr(result, "calibration", None)
    return est.as_dict() if est is not None else None


def _cpu_count() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def masks_only(input_path: str | Path, out_dir: str | Path, *, config: PipelineConfig | None = None,
               stride: int = 1, max_frames: int | None = None, progress: bool = True) -> dict:
    """MONA masks of a video or folder, written to ``out_dir/masks/<frame name>.png`` with
    ``out_dir/masks_report.json`` (staged like :func:`run`'s outputs, renamed into place at the end).
    The masks use the camera :func:`run` would use without ``--calib`` (the focal length estimated
    from the first frames, else the field-of-view guess), so they are the masks `run` computes."""
    inputs = open_inputs(input_path, masks=None, stride=stride, max_frames=max_frames)
    return masks_only_opened(inputs, out_dir, config=config, progress=progress)


def masks_only_opened(inputs: RunInputs, out_dir: str | Path, *,
                      config: PipelineConfig | None = None, progress: bool = True) -> dict:
    """:func:`masks_only` on frames already opened by :func:`mona_vo.inputs.open_inputs`."""
    from data_tools.run_outputs import RunOutputs
    from mona_vo.masks import compute_masks
    from mona_vo.picture_area import PictureArea
    from mona_vo.pipeline import camera_without_calib, open_stream

    config = config or PipelineConfig()
    input_path, source = inputs.input_path, inputs.source
    names = {}
    coverage = []
    repeated = {}

    def remember(src):
        for f in src:
            names[f.index] = f.name
            yield f

    with RunOutputs(out_dir, write_masks=True) as outputs:
        bar, update = _progress_bar(len(source), "mona-vo masks", progress)
        t0 = time.perf_counter()
        backends = config.masker_backends()       # before a frame is read (estimate_trajectory)
        try:
            stream = open_stream(source, None, config)
            area = stream.picture or PictureArea.whole(source.width, source.height)
            estimate = stream.calibration
            camera = camera_without_calib(estimate, config, *area.size)
            for n, mf in enumerate(compute_masks(remember(stream.frames), config.masks, camera,
                                                 repeat_max_diff=config.repeat_max_diff,
                                                 ignore=stream.overlay,
                                                 **backends), start=1):
                mask = stream.full_mask(mf.mask)
                outputs.add_mask(names[mf.index], mask)
                if mf.repeat_of >= 0:
                    repeated[names[mf.index]] = names[mf.repeat_of]
                coverage.append(float(mask.mean()))
                update(n)
            camera = area.to_frame(camera)
        finally:
            if bar is not None:
                bar.close()
        seconds = time.perf_counter() - t0
        report = {"input": str(input_path), "frames": len(coverage), "seconds": round(seconds, 3),
                  "frames_per_second": round(len(coverage) / seconds, 2) if seconds > 0 else None,
                  "mean_mask_coverage": float(np.mean(coverage)) if coverage else 0.0,
                  "picture_area": area.as_dict(),
                  "overlay": _overlay_summary(stream.full_mask(stream.overlay)),
                  "repeated_frames": repeated,
                  "calibration": {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                                  "source": _camera_source(getattr(estimate, "used", False),
                                                           config),
                                  "focal_estimate": estimate.as_dict() if estimate is not None
                                                    else None},
                  "config": to_dict(config)}
        outputs.commit_masks("masks_report.json", report)
    return report


def demo(out_dir: str | Path | None = None, *, preset: str = "one-large", seed: int = 5,
         n_frames: int = 40, width: int = 1024, height: int = 436, config: PipelineConfig | None = None,
         progress: bool = True) -> dict:
    """Generate a synthetic dynamic sequence, estimate its trajectory with no masks, with MONA
    masks and with the GT masks, and return the ATE of each (metres and % of the path)."""
    import tempfile

    from data_tools.synthetic import SceneConfig, SyntheticScene, write_frames_folder
    from data_tools.frames import open_frames
    from eval.metrics import Trajectory, evaluate_trajectory

    config = config or PipelineConfig()
    scene = SyntheticScene(SceneConfig(width=width, height=height, n_frames=n_frames, preset=preset,
                                       seed=seed))
    keep = out_dir is not None
    root = Path(out_dir) if keep else Path(tempfile.mkdtemp(prefix="mona-vo-demo-"))
    try:
        folder = write_frames_folder(scene, root / "input")
        gt = Trajectory(np.arange(n_frames, dtype=float), scene.poses())
        rows = {}
        for variant in ("none", "mona", "gt"):
            masks = {"none": "none", "mona": "mona", "gt": str(Path(folder) / "masks")}[variant]
            report = run(folder, root / variant, calib=_calib_string(scene.intrinsics),
                         masks=masks, config=config, progress=progress,
                         gt_path=Path(folder) / "groundtruth.txt")
            from data_tools.tum import read_tum_trajectory

            ts, poses = read_tum_trajectory(root / variant / "trajectory.txt")
            m = evaluate_trajectory(gt, Trajectory(ts, poses))
            rows[variant] = {"ate": m.ate, "ate_percent_of_path": m.ate_percent_of_path,
                             "rpe_trans": m.rpe_trans, "rpe_rot_deg": m.rpe_rot_deg,
                             "frames_per_second": report["frames_per_second"].get("total")}
        return {"preset": preset, "seed": seed, "frames": n_frames, "size": [width, height],
                "path_length": m.path_length, "results": rows,
                "out_dir": str(root) if keep else None}
    finally:
        if not keep:
            import shutil

            shutil.rmtree(root, ignore_errors=True)


def _calib_string(intr: Intrinsics) -> str:
    return f"{intr.fx!r},{intr.fy!r},{intr.cx!r},{intr.cy!r}"
