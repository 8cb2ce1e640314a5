"""VO accuracy and speed on generated scenes: presets x seeds x mask variants.

Variants: ``none`` (no masks), ``gt`` (the generator's exact moving-object masks), ``mona``
(masks computed by MONA on the fly; their rows also give the masks' mean IoU against the true
masks and false-positive area, as the mask bench measures them, so an ATE can be read beside the
masks that made it), ``gt-detector`` (MONA with a perfect object detector,
:class:`eval.mask_bench.TrueBoxDetector`: what an object detector back end would at best give
the VO). Each sequence is rendered once and shared by its variants.
ATE/RPE follow the Sintel protocol (:func:`eval.metrics.evaluate_trajectory`, Sim(3)); ATE is also
given as a percentage of the GT path length, the unit of the issue targets.

``python -m eval.vo_bench --presets static,one-large --seeds 0-5 --variants none,gt`` prints the
per-sequence rows and the per-preset means; ``mona-vo bench`` adds the COLMAP peer.
``python -m eval.vo_bench --compare BASE.json NEW.json`` pairs two ``--out`` files of one command,
before and after a change (:func:`compare_runs`).
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from data_tools.bars import KINDS as BAR_KINDS, add_bars
from data_tools.frames import Frame
from data_tools.overlays import KINDS as OVERLAY_KINDS, add_overlay
from data_tools.repeats import KINDS as REPEAT_KINDS, shown_images, shown_order
from data_tools.synthetic import SceneConfig, SyntheticScene
from eval.mask_metrics import region_similarity
from eval.harness import draw_name, parse_draws
from eval.metrics import RotationMetrics, Trajectory, score_trajectory
from mona_vo.batch import clip_verdict
from mona_vo.config import apply_overrides
from mona_vo.errors import EvalError, MonaVoError
from mona_vo.lens import Distortion, LensIntrinsics, Undistortion, camera as lens_camera
from mona_vo.pipeline import PipelineConfig, estimate_trajectory
from mona_vo.presets import PRESETS, preset_config
from mona_vo.run import clip_summary


def render_sequence(preset: str, seed: int, n_frames: int, width: int, height: int,
                    effects: bool = True, readout: float = 0.0):
    """(scene, frames, gt masks) of one generated sequence, rendered once, kept in memory.
    ``effects=False``: the frames before the image effects (``mixed``: blur, noise, exposure,
    JPEG), the same geometry, so what the effects cost can be read apart. ``readout``: rendered
    by a rolling shutter reading its rows over this share of the frame interval
    (``SceneConfig.readout``; 0 a global shutter)."""
    scene = SyntheticScene(SceneConfig(width=width, height=height, n_frames=n_frames,
                                       preset=preset, seed=seed, effects=effects,
                                       readout=readout))
    return (scene, *frames_of(scene))


def frames_of(rendered) -> tuple[list[Frame], list[np.ndarray]]:
    """The frames (named by their index) and true masks of rendered generated frames (an
    iterable of RenderedFrame)."""
    frames, masks = [], []
    for r in rendered:
        frames.append(Frame(r.index, float(r.index), f"{r.index:05d}", r.image))
        masks.append(r.mask)
    return frames, masks


def run_variant(scene, frames, gt_masks, variant: str, config: PipelineConfig,
                calib: str = "given", gt_poses: np.ndarray | None = None,
                camera=None, mona: "MonaReplay | None" = None) -> dict:
    """One run. ``calib``: ``given`` passes the scene's true intrinsics (``camera`` when the
    frames were seen through a lens: a LensIntrinsics); ``pinhole`` the true fx, fy, cx, cy
    without the lens (a run that ignores the distortion); ``estimate`` passes none, as `mona-vo
    run` without --calib (the focal length is estimated, or guessed).
    ``gt_poses``: the true pose of each frame when it is not the scene's (repeated frames).
    ``mona``: for the ``mona`` variant, a :class:`MonaReplay` that records the masks this run
    hands the VO, or, once filled, hands them again instead of computing them."""
    masks = {"none": None, "gt": list(gt_masks), "mona": "mona", "gt-detector": "mona"}[variant]
    replay = mona is not None and mona.filled
    if replay:
        masks = list(mona.vo_masks)
    detector = None
    if variant == "gt-detector":
        from eval.mask_bench import TrueBoxDetector

        detector = TrueBoxDetector(dict(enumerate(gt_masks)))
    quality = {"mask_j": [], "mask_fp": []}

    def judge(out):
        # The masks `run` computed for these frames (full-frame pixels), against the truth.
        if out.mona is not None and mona is not None:
            mona.vo_masks.append(out.vo_mask)
        if out.mona is not None:
            gt_mask = gt_masks[out.index]
            quality["mask_j"].append(region_similarity(out.mask, gt_mask))
            quality["mask_fp"].append(float(np.mean(out.mask & ~gt_mask)))

    t0 = time.perf_counter()
    intrinsics = {"given": camera or scene.intrinsics, "pinhole": scene.intrinsics}.get(calib)
    result = estimate_trajectory(frames, intrinsics=intrinsics,
                                 masks=masks, config=config, on_frame=judge, detector=detector)
    wall = time.perf_counter() - t0
    gt = Trajectory(np.arange(len(frames), dtype=float),
                    scene.poses() if gt_poses is None else gt_poses)
    nan = float("nan")
    errors = _errors(gt, Trajectory(result.vo.timestamps, result.vo.poses))
    # The sliding window's own trajectory (vo.refine=none, to the bit) from the same run.
    streaming = errors["ate_pct"]
    if result.vo.refine and result.vo.poses_streaming is not None:
        streaming = _errors(gt, Trajectory(result.vo.timestamps, result.vo.poses_streaming))["ate_pct"]
    n = len(frames)
    # The verdict `batch` would give this clip, from the report `run` would write.
    summary = clip_summary(result, name=f"generated/{variant}", masks=variant, config=config,
                           calib_given=intrinsics is not None)
    verdict = clip_verdict(summary)
    if mona is not None and not replay:
        mona.filled = True
        mona.quality = quality
        mona.seconds = {k: v for k, v in result.timings.items() if k.startswith("masks.")}
    if replay:   # the masks' quality and cost are those of the run that computed them
        quality = mona.quality
        result.timings.update(mona.seconds)
    vo_seconds = sum(v for k, v in result.timings.items() if k.startswith("vo."))
    mask_seconds = sum(v for k, v in result.timings.items() if k.startswith("masks."))
    true_fx = scene.intrinsics.fx
    return {
        "variant": variant, **errors, "ate_pct_streaming": streaming, "calib": calib,
        "focal_error_pct": 100.0 * (result.intrinsics.fx - true_fx) / true_fx,
        "final_focal_error_pct": 100.0 * (result.vo.focal - true_fx) / true_fx,
        "frames": n, "frames_with_pose": int(np.isfinite(result.vo.poses).all(axis=(1, 2)).sum()),
        "low_confidence": int(result.vo.low_confidence.sum()),
        "repeated_frames": int(np.sum(result.repeat_of >= 0)) if result.repeat_of is not None else 0,
        "keyframes": int(result.vo.is_keyframe.sum()),
        "vo_fps": n / vo_seconds if vo_seconds > 0 else float("nan"),
        # The stages' seconds summed: with masks.segment_async the segmentation runs beside
        # the other stages, so the masks' share of the wall clock (total_fps) is less.
        "mask_ms_per_frame": 1000 * mask_seconds / n,
        "total_fps": n / wall,
        "stage_seconds": {k: round(v, 3) for k, v in result.timings.items()},
        "dropped": dict(result.vo.drops),
        "mask_j": float(np.mean(quality["mask_j"])) if quality["mask_j"] else nan,
        "mask_fp_pct": 100 * float(np.mean(quality["mask_fp"])) if quality["mask_fp"] else nan,
        "global_shift_pct": _nan_if_none(summary["global_shift_pct"]),
        # The rolling shutter's readout the global refinement found (0: a global shutter,
        # as the generator renders; NaN: not estimated).
        "rolling_shutter_readout": float((result.vo.refine.get("rolling_shutter") or {})
                                         .get("readout", nan)),
        "support_p10": _nan_if_none(summary["support_p10"]),
        "usable": verdict.usable, "verdict": verdict.text(),
    }


def _errors(gt: Trajectory, est: Trajectory) -> dict:
    nan = float("nan")
    errors = {"ate": nan, "ate_pct": nan, "rpe_trans": nan, "rpe_rot_deg": nan, "path_m": 0.0,
              "heading_deg": nan, "rot_rmse_deg": nan, "est_translation_extent": nan,
              "status": "ok"}
    try:
        m = score_trajectory(gt, est)
        if isinstance(m, RotationMetrics):
            errors.update(rpe_rot_deg=m.rpe_rot_deg, rot_rmse_deg=m.rot_rmse_deg,
                          est_translation_extent=m.est_translation_extent)
        else:
            errors.update(ate=m.ate, ate_pct=m.ate_percent_of_path, rpe_trans=m.rpe_trans,
                          rpe_rot_deg=m.rpe_rot_deg, path_m=m.path_length,
                          heading_deg=m.heading_deg)
    except EvalError as exc:  # one sequence that cannot be scored must not end the benchmark
        errors["status"] = f"failed: {exc}"
    return errors


@dataclass
class MonaReplay:
    """MONA's masks of one sequence as its first run handed them to the VO (full-frame pixels;
    None on a frame whose mask was not reliable), with their quality and cost. They depend on
    the frames, the camera and the ``masks.*`` settings only, so draws that vary the VO's
    settings alone (``--draws vo.grid_size=...``) get the same masks: computed once, handed
    again as caller masks, the same trajectories at a fraction of the time
    (tests/test_mask_temporal.py checks that a replayed run equals a computed one)."""

    vo_masks: list = field(default_factory=list)
    filled: bool = False
    quality: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)


def masks_reusable(draws, *, lens=None) -> bool:
    """Whether MONA's masks can be computed once for all ``draws`` of a sequence: every draw
    changes ``vo.*`` settings only, and no lens lies between the run's picture and the full
    frame (its masks would come back through a resampling)."""
    return bool(draws) and lens is None and all(
        str(k).startswith("vo.") for d in draws for k in d)


def _nan_if_none(v) -> float:
    return float("nan") if v is None else float(v)


def benchmark(presets, seeds, variants, *, n_frames=50, width=1024, height=436,
              config: PipelineConfig | None = None, on_row=None, repeats: int = 1,
              calib: str = "given", bars: str | None = None,
              frame_repeats: str | None = None, overlay: str | None = None,
              draws: list[dict[str, str]] | None = None, effects: bool = True,
              lens=None, readout: float = 0.0) -> list[dict]:
    """One row per preset x seed x variant x draw x repeat. ``draws``: config overrides, one
    run of each per sequence and variant (:func:`eval.harness.parse_draws`; each row's ``draw``
    names its override, "" without draws): on a scene where one run is one draw of the VO's
    point grid, a variant's effect is read over the draws (:func:`draw_ratios`). ``repeats`` >
    1 runs each sequence again to
    measure the run-to-run spread of one input (0 when the pipeline is deterministic);
    ``calib`` as in :func:`run_variant`; ``bars``: paint bars of this kind over every frame
    (:func:`data_tools.bars.add_bars`; the true masks keep the movers under the bars, which no
    mask can find); ``frame_repeats``: show the frames with repeats of this kind
    (:mod:`data_tools.repeats`; each shown frame's true pose and mask are those of the frame
    shown, but for ``stutter``, whose held frame keeps its own time's); ``overlay``: burn in
    an overlay of this kind (:func:`data_tools.overlays.add_overlay`); ``effects=False``:
    the ``mixed`` frames before their image effects (:func:`render_sequence`); ``lens``: a
    :class:`mona_vo.lens.Distortion` the frames (and true masks) are seen through, the true
    camera then a LensIntrinsics (``calib="pinhole"`` leaves the lens out); ``readout``: the
    frames rendered by a rolling shutter (:func:`render_sequence`)."""
    config = config or PipelineConfig()
    if bars and "gt-detector" in variants:
        # The masker sees the picture inside the bars; the true boxes are the full frame's.
        raise EvalError("the gt-detector variant does not take bars")
    rows = []
    for preset in presets:
        for seed in seeds:
            scene, frames, masks = render_sequence(preset, seed, n_frames, width, height, effects,
                                                   readout)
            camera = None if lens is None else lens_camera(scene.intrinsics, lens)
            if isinstance(camera, LensIntrinsics):
                und = Undistortion(camera)
                frames = [Frame(f.index, f.timestamp, f.name, und.distort(f.image)) for f in frames]
                masks = [und.unmask(m) for m in masks]
            if bars:
                frames = [Frame(f.index, f.timestamp, f.name, add_bars(f.image, bars)) for f in frames]
            if overlay:
                frames = [Frame(f.index, f.timestamp, f.name, add_overlay(f.image, overlay))
                          for f in frames]
            gt_poses = None
            if frame_repeats:
                order = shown_order(len(frames), frame_repeats)
                frames = [Frame(k, float(k), f"{k:05d}", im) for k, im in
                          enumerate(shown_images([f.image for f in frames], frame_repeats))]
                gt_poses = scene.poses()[order if frame_repeats != "stutter" else slice(None)]
                masks = [masks[i] for i in (order if frame_repeats != "stutter" else range(len(order)))]
            coverage = float(np.mean([m.mean() for m in masks]))
            for variant in variants:
                replay = MonaReplay() if variant == "mona" and repeats == 1 and \
                    masks_reusable(draws, lens=lens) else None
                for draw in draws or [{}]:
                    cfg = apply_overrides(config, draw) if draw else config
                    for repeat in range(repeats):
                        row = {"preset": preset, "seed": seed, "repeat": repeat,
                               "draw": draw_name(draw), "coverage": coverage,
                               **run_variant(scene, frames, masks, variant, cfg, calib, gt_poses,
                                             camera, mona=replay)}
                        rows.append(row)
                        if on_row is not None:
                            on_row(row)
            del frames, masks
    return rows


def peak_memory_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _nanstat(fn, values: np.ndarray) -> float:
    """fn over the finite values; NaN when there are none (e.g. ATE of tripod pans)."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(fn(v)) if len(v) else float("nan")


def summarize(rows: list[dict], baseline: str = "none") -> list[dict]:
    """Per (preset, variant), over seeds: ATE % mean with its spread (standard deviation over
    seeds, min and max), the paired difference to the ``baseline`` variant on the same seeds
    (mean and standard deviation; a difference smaller than its spread is no difference), the
    run-to-run spread of one input (largest max - min ATE % over repeats, 0 without repeats),
    and mean VO frames/s."""
    out = []
    keys = sorted({(r["preset"], r["variant"]) for r in rows}, key=lambda k: (k[0], k[1]))
    first = [r for r in rows if r.get("repeat", 0) == 0]
    for preset, variant in keys:
        every = [r for r in rows if r["preset"] == preset and r["variant"] == variant]
        sel = [r for r in first if r["preset"] == preset and r["variant"] == variant]
        ate = np.array([r["ate_pct"] for r in sel])
        base = {r["seed"]: r["ate_pct"] for r in first
                if r["preset"] == preset and r["variant"] == baseline}
        diff = np.array([r["ate_pct"] - base[r["seed"]] for r in sel if r["seed"] in base])
        by_seed: dict[int, list[float]] = {}
        for r in every:
            by_seed.setdefault(r["seed"], []).append(r["ate_pct"])
        out.append({"preset": preset, "variant": variant, "n": len(sel),
                    "ate_pct_mean": _nanstat(np.nanmean, ate),
                    "ate_pct_std": _nanstat(lambda a: np.nanstd(a, ddof=1), ate) if len(ate) > 1 else 0.0,
                    "ate_pct_min": _nanstat(np.nanmin, ate),
                    "ate_pct_max": _nanstat(np.nanmax, ate),
                    "d_vs_baseline_mean": _nanstat(np.nanmean, diff),
                    "d_vs_baseline_std": _nanstat(lambda a: np.nanstd(a, ddof=1), diff) if len(diff) > 1 else float("nan"),
                    "repeat_spread_pct": _nanstat(np.nanmax, np.array([max(v) - min(v) for v in by_seed.values()])),
                    "ate_mean": _nanstat(np.nanmean, np.array([r["ate"] for r in sel])),
                    "rpe_trans_mean": _nanstat(np.nanmean, np.array([r["rpe_trans"] for r in sel])),
                    "rpe_rot_mean": _nanstat(np.nanmean, np.array([r["rpe_rot_deg"] for r in sel])),
                    "rot_rmse_mean": _nanstat(np.nanmean, np.array([r["rot_rmse_deg"] for r in sel])),
                    "scored": int(sum(r["status"] == "ok" for r in sel)),
                    "vo_fps_mean": float(np.mean([r["vo_fps"] for r in sel])),
                    "mask_ms_mean": float(np.mean([r["mask_ms_per_frame"] for r in sel])),
                    "all_frames_posed": all(r["frames_with_pose"] == r["frames"] for r in sel)})
    return out


def draw_ratios(rows: list[dict], baseline: str = "none",
                key: str = "ate_pct") -> tuple[list[dict], list[dict]]:
    """A variant against the ``baseline`` over the draws of each sequence (first repeats):
    per (preset, seed, variant), the median ATE % of path of either over the draws both scored,
    the ratio of the medians and the worst paired ratio (the largest variant / baseline of one
    draw); per variant, over the sequences, the geometric mean of the median ratios and how
    many sequences have the variant clearly lower (median ratio < 0.9) and never clearly higher
    (no draw above 1.1): the two bounds `tests/test_mask_temporal.py` asks of MONA on its one
    scene. ``key``: the row's error to compare (``ate_pct_streaming``: the same runs' sliding-
    window trajectories, before the global refinement). Returns (per sequence, per variant)."""
    by_run: dict[tuple, dict[str, float]] = {}     # (preset, seed, variant) -> draw -> ATE %
    for r in rows:
        if r.get("repeat", 0) == 0:
            by_run.setdefault((r["preset"], r["seed"], r["variant"]), {})[r.get("draw", "")] = \
                r[key]
    per_seq = []
    for (preset, seed, variant), ate in by_run.items():
        if variant == baseline:
            continue
        base = by_run.get((preset, seed, baseline), {})
        pairs = [(a, base.get(d, float("nan"))) for d, a in ate.items()]
        pairs = np.array([p for p in pairs if np.isfinite(p).all() and p[1] > 0]).reshape(-1, 2)
        if not len(pairs):
            continue
        med_v, med_b = float(np.median(pairs[:, 0])), float(np.median(pairs[:, 1]))
        per_seq.append({"preset": preset, "seed": seed, "variant": variant, "draws": len(pairs),
                        "median_pct": med_v, "baseline_median_pct": med_b,
                        "median_ratio": med_v / med_b,
                        "worst_ratio": float(np.max(pairs[:, 0] / pairs[:, 1]))})
    per_variant = []
    for variant in dict.fromkeys(s["variant"] for s in per_seq):
        sel = [s for s in per_seq if s["variant"] == variant]
        lower = [s["median_ratio"] < 0.9 for s in sel]
        never = [s["worst_ratio"] <= 1.1 for s in sel]
        per_variant.append({"variant": variant, "sequences": len(sel),
                            "gmean_median_ratio": float(np.exp(np.mean(np.log(
                                [s["median_ratio"] for s in sel])))),
                            "lower": int(sum(lower)), "never_higher": int(sum(never)),
                            "both": int(sum(a and b for a, b in zip(lower, never)))})
    return per_seq, per_variant


def format_draw_ratios(per_seq: list[dict], per_variant: list[dict], baseline: str = "none") -> str:
    lines = [f"{'preset':13s} {'seed':>4s} {'variant':11s} {'draws':>5s} {'median %':>9s} "
             f"{baseline + ' median %':>14s} {'ratio':>6s} {'worst':>6s}"]
    for s in per_seq:
        lines.append(f"{s['preset']:13s} {s['seed']:4d} {s['variant']:11s} {s['draws']:5d} "
                     f"{s['median_pct']:9.3f} {s['baseline_median_pct']:14.3f} "
                     f"{s['median_ratio']:6.2f} {s['worst_ratio']:6.2f}")
    for v in per_variant:
        lines.append(f"{v['variant']} against {baseline}, over {v['sequences']} sequences: geometric "
                     f"mean of the median ratios {v['gmean_median_ratio']:.2f}; median clearly lower "
                     f"(< 0.9) on {v['lower']}, no draw clearly higher (<= 1.1) on "
                     f"{v['never_higher']}, both on {v['both']}")
    return "\n".join(lines)


def verdict_quality(rows: list[dict], good_pct: float) -> dict:
    """How well ``batch``'s verdict picks the good trajectories among the rows that translate
    (scored by ATE): a clip is good when its ATE is at most ``good_pct`` % of its path.
    precision: share of the clips called usable that are good (what a curator keeps);
    recall: share of the good clips called usable (what the verdict throws away)."""
    scored = [r for r in rows if np.isfinite(r["ate_pct"])]
    usable = [r for r in scored if r["usable"]]
    good = [r for r in scored if r["ate_pct"] <= good_pct]
    hits = [r for r in usable if r["ate_pct"] <= good_pct]
    return {"good_pct": good_pct, "scored": len(scored), "good": len(good), "usable": len(usable),
            "usable_and_good": len(hits),
            "precision": len(hits) / len(usable) if usable else float("nan"),
            "recall": len(hits) / len(good) if good else float("nan"),
            "base_rate": len(good) / len(scored) if scored else float("nan"),
            "worst_usable_pct": max((r["ate_pct"] for r in usable), default=float("nan")),
            "best_unusable_pct": min((r["ate_pct"] for r in scored if not r["usable"]),
                                     default=float("nan"))}


def format_verdict_quality(q: dict) -> str:
    return (f"verdict (good: ATE <= {q['good_pct']:g} % of path), over {q['scored']} scored runs: "
            f"{q['usable']} usable, {q['usable_and_good']} of them good; precision "
            f"{q['precision']:.2f} (all scored runs: {q['base_rate']:.2f}), recall {q['recall']:.2f} "
            f"({q['good']} good); worst usable {q['worst_usable_pct']:.2f} %, best not usable "
            f"{q['best_unusable_pct']:.2f} %")


def format_row(r: dict) -> str:
    return (f"{r['preset']:13s} seed {r['seed']:2d} {r['variant']:11s} cov {100 * r['coverage']:5.1f}%  "
            f"ATE {r['ate']:.4f} m {r['ate_pct']:7.3f}% of {r['path_m']:5.2f} m  "
            f"RPE {r['rpe_trans']:.4f} m {r['rpe_rot_deg']:.3f} deg  "
            + (f"heading {r['heading_deg']:5.1f} deg  " if np.isfinite(r.get("heading_deg", float("nan"))) else "")
            + f"VO {r['vo_fps']:5.1f} fps  "
            f"masks {r['mask_ms_per_frame']:5.1f} ms/frame  low-conf {r['low_confidence']}"
            + (f"  focal {r['focal_error_pct']:+.1f}% -> {r['final_focal_error_pct']:+.1f}%"
               if r.get("calib") == "estimate" else "")
            + (f"  repeats {r['repeated_frames']}" if r.get("repeated_frames") else "")
            + (f"  mask J {r['mask_j']:.3f}, false positives {r['mask_fp_pct']:.2f} %"
               if np.isfinite(r.get("mask_j", float("nan"))) else "")
            + (f"  rot {r['rot_rmse_deg']:.3f} deg, est. translation {r['est_translation_extent']:.3g}"
               if np.isfinite(r["rot_rmse_deg"]) else "")
            + f"  shift {r['global_shift_pct']:.2f} %, support {r['support_p10']:.0f}, "
              + ("usable" if r["usable"] else "not usable")
            + ("" if r["status"] == "ok" else f"  {r['status']}"))


def format_summary(summary: list[dict], baseline: str = "none") -> str:
    """The summary as a table: ATE % mean +- standard deviation over seeds [min, max], the paired
    difference to the baseline variant +- its standard deviation, the run-to-run spread."""
    lines = [f"{'preset':13s} {'variant':11s} {'n':>2s} {'ATE% mean+-sd':>15s} {'[min, max]':>17s} "
             f"{'vs ' + baseline + ' +-sd':>17s} {'rerun':>6s} {'RPE m':>7s} {'RPE deg':>7s} "
             f"{'VO fps':>7s} {'mask ms':>7s} {'failed':>6s}"]
    for s in summary:
        d = ("-" if s["variant"] == baseline or s["d_vs_baseline_mean"] != s["d_vs_baseline_mean"]
             else f"{s['d_vs_baseline_mean']:+.3f}+-{s['d_vs_baseline_std']:.3f}")
        lines.append(f"{s['preset']:13s} {s['variant']:11s} {s['n']:2d} "
                     f"{s['ate_pct_mean']:7.3f}+-{s['ate_pct_std']:6.3f} "
                     f"[{s['ate_pct_min']:6.3f}, {s['ate_pct_max']:7.3f}] {d:>17s} "
                     f"{s['repeat_spread_pct']:6.3f} {s['rpe_trans_mean']:7.4f} {s['rpe_rot_mean']:7.3f} "
                     f"{s['vo_fps_mean']:7.1f} {s['mask_ms_mean']:7.1f} {s['n'] - s['scored']:6d}")
    lines.append("ATE% over seeds: mean +- standard deviation [min, max]; 'vs' is the paired difference "
                 "to the same seeds' baseline; 'rerun' the largest spread of one input over --repeats. "
                 "A difference within its +-sd is no difference. 'failed': sequences that could not be "
                 "scored (left out of the means; e.g. a rotation-only estimate of a camera that "
                 "translates, which no Sim(3) alignment can score).")
    return "\n".join(lines)


def compare_runs(base: list[dict], new: list[dict], flag: float = 0.05) -> tuple[list[dict], list[dict]]:
    """Two benches' rows (``--out`` files), paired by preset, seed, variant and draw: per pair the ATE
    % of path and mask J before and after, and whether the ATE moved by more than ``flag`` (a
    share, on the log scale); per preset and variant, over the pairs scored in both, the
    geometric means, the mean paired log ratio with its standard error (a ratio within about two
    standard errors of 1 is no change: the fast turns move by factors either way) and the count
    lower. Returns (pairs, summary)."""
    old = {(r["preset"], r["seed"], r["variant"], r.get("draw", "")): r for r in base}
    pairs = []
    for r in new:
        b = old.get((r["preset"], r["seed"], r["variant"], r.get("draw", "")))
        if b is None:
            continue
        x, y = float(b["ate_pct"]), float(r["ate_pct"])
        both = np.isfinite(x) and np.isfinite(y) and x > 0 and y > 0
        log_ratio = float(np.log(y / x)) if both else float("nan")
        pairs.append({"preset": r["preset"], "seed": r["seed"], "variant": r["variant"],
                      "ate_pct_base": x, "ate_pct_new": y, "log_ratio": log_ratio,
                      "mask_j_base": float(b.get("mask_j", float("nan"))),
                      "mask_j_new": float(r.get("mask_j", float("nan"))),
                      "moved": bool(both and abs(log_ratio) > np.log1p(flag))})
    summary = []
    for key in dict.fromkeys((p["preset"], p["variant"]) for p in pairs):
        sel = [p for p in pairs if (p["preset"], p["variant"]) == key and np.isfinite(p["log_ratio"])]
        if not sel:
            continue
        lr = np.array([p["log_ratio"] for p in sel])
        gm = lambda k: float(np.exp(np.mean(np.log([p[k] for p in sel]))))
        summary.append({"preset": key[0], "variant": key[1], "n": len(sel),
                        "gmean_base": gm("ate_pct_base"), "gmean_new": gm("ate_pct_new"),
                        "ratio": float(np.exp(lr.mean())),
                        "ratio_se": float(lr.std(ddof=1) / np.sqrt(len(lr))) if len(lr) > 1 else float("nan"),
                        "lower": int(np.sum(lr < 0)), "higher": int(np.sum(lr > 0))})
    return pairs, summary


def format_comparison(pairs: list[dict], summary: list[dict]) -> str:
    lines = []
    for p in pairs:
        j = (f"  mask J {p['mask_j_base']:.3f} -> {p['mask_j_new']:.3f}"
             if np.isfinite(p["mask_j_base"]) or np.isfinite(p["mask_j_new"]) else "")
        lines.append(f"{p['preset']:13s} seed {p['seed']:3d} {p['variant']:11s} ATE % "
                     f"{p['ate_pct_base']:7.3f} -> {p['ate_pct_new']:7.3f}{j}"
                     + ("  <<" if p["moved"] and p["log_ratio"] < 0 else
                        "  >>" if p["moved"] else ""))
    lines.append("")
    for s in summary:
        lines.append(f"{s['preset']:13s} {s['variant']:11s} n {s['n']:2d}  geometric mean ATE % "
                     f"{s['gmean_base']:.3f} -> {s['gmean_new']:.3f}  ratio {s['ratio']:.3f} "
                     f"(log se {s['ratio_se']:.3f})  lower {s['lower']}, higher {s['higher']}")
    lines.append("<< / >>: the ATE moved down / up by more than 5 %. Pairs a run could not score "
                 "(rotation-only) are listed, not counted.")
    return "\n".join(lines)


def _parse_lens(text: str) -> Distortion:
    """``"k1,k2[,p1,p2,k3]"`` -> Distortion; anything else raises ConfigError naming --lens."""
    from mona_vo.errors import ConfigError

    try:
        lens = Distortion.from_numbers([float(v) for v in text.split(",")])
        if lens.check():
            raise ValueError
    except ValueError:
        raise ConfigError(f"--lens expects up to five numbers k1,k2,p1,p2,k3, not '{text}'") from None
    return lens


def parse_seeds(text: str) -> list[int]:
    """``"0-2,5"`` -> ``[0, 1, 2, 5]``; anything else raises ConfigError naming --seeds."""
    from mona_vo.errors import ConfigError

    out = []
    try:
        for part in text.split(","):
            a, _, b = part.strip().partition("-")
            lo, hi = int(a), int(b) if b else int(a)
            if lo < 0 or hi < lo:
                raise ValueError
            out.extend(range(lo, hi + 1))
    except ValueError:
        raise ConfigError(f"--seeds expects non-negative seeds and ranges such as 0-2 or 0,3, "
                          f"not '{text}'") from None
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--compare", nargs=2, metavar=("BASE", "NEW"),
                    help="pair two --out files of one command (before and after a change) and "
                         "print per-sequence and per-preset changes; nothing is run")
    ap.add_argument("--presets", default="static,one-large,several,fast-rotation")
    ap.add_argument("--seeds", default="0-5")
    ap.add_argument("--variants", default="none,gt,mona")
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--size", default="1024x436")
    ap.add_argument("--preset", choices=sorted(PRESETS), default="default",
                    help="the speed/accuracy preset of `mona-vo --preset` (mona_vo/presets.py), "
                         "applied before --set; --presets names the generated scenes")
    ap.add_argument("--set", action="append", default=[], help="config override key=value")
    ap.add_argument("--out", metavar="FILE", help="also write the rows and the summary as JSON here")
    ap.add_argument("--calib", choices=("given", "estimate", "pinhole"), default="given",
                    help="given: the scenes' true intrinsics (with --lens, its distortion too); "
                         "estimate: none, as `mona-vo run` without --calib; pinhole: with "
                         "--lens, the true fx, fy, cx, cy without the distortion (default given)")
    ap.add_argument("--lens", metavar="K1,K2[,P1,P2,K3]",
                    help="see every frame through a lens with this distortion (OpenCV's order; "
                         "mona_vo.lens), the true masks too; write --lens=K1,... when k1 is "
                         "negative")
    ap.add_argument("--bars", choices=BAR_KINDS,
                    help="paint bars of this kind over every frame (data_tools.bars), as "
                         "online videos carry them")
    ap.add_argument("--overlay", choices=OVERLAY_KINDS,
                    help="burn in an overlay of this kind (data_tools.overlays), as online "
                         "videos carry them")
    ap.add_argument("--frame-repeats", choices=REPEAT_KINDS,
                    help="show the frames with repeats of this kind (data_tools.repeats), as "
                         "online videos carry them")
    ap.add_argument("--effects", choices=("on", "off"), default="on",
                    help="off: the `mixed` frames before their image effects (blur, noise, "
                         "exposure, JPEG), the same geometry (default on)")
    ap.add_argument("--readout", type=float, default=0.0, metavar="SHARE",
                    help="render the frames by a rolling shutter whose rows are read over this "
                         "share of the frame interval, top row first (0-1; default 0, a global "
                         "shutter, as the scenes' other presets)")
    ap.add_argument("--good-pct", type=float, default=1.0,
                    help="a trajectory within this ATE (%% of path) is good, for the verdict's "
                         "precision and recall (default 1)")
    ap.add_argument("--repeats", type=int, default=1,
                    help="runs of each sequence, to measure the run-to-run spread (default 1)")
    ap.add_argument("--draws", action="append", default=[], metavar="KEY=V1,V2,...",
                    help="run every sequence and variant once per value (repeatable, as `mona-vo "
                         "eval tum --draws`), and read each variant against 'none' over the "
                         "draws; when every key is a vo.* one, MONA's masks are computed in the "
                         "first draw and handed to the others (the same trajectories)")
    args = ap.parse_args(argv)
    if args.compare:
        try:
            rows = [_read_rows(f) for f in args.compare]
        except MonaVoError as exc:
            print(f"python -m eval.vo_bench: error: {exc}", file=sys.stderr)
            return 1
        print(format_comparison(*compare_runs(*rows)))
        return 0
    from mona_vo.config import parse_set_options

    w, h = (int(v) for v in args.size.split("x"))
    try:
        cfg = preset_config(args.preset, None, parse_set_options(args.set))
        draws = parse_draws(args.draws, cfg)
        lens = _parse_lens(args.lens) if args.lens else None
        if not 0.0 <= args.readout <= 1.0:
            raise EvalError(f"--readout: must be a share of the frame interval in [0, 1], "
                            f"got {args.readout:g}")
    except MonaVoError as exc:
        print(f"python -m eval.vo_bench: error: {exc}", file=sys.stderr)
        return 1
    rows = benchmark(args.presets.split(","), parse_seeds(args.seeds), args.variants.split(","),
                     n_frames=args.frames, width=w, height=h, config=cfg,
                     on_row=lambda r: print(format_row(r), flush=True), repeats=max(1, args.repeats),
                     calib=args.calib, bars=args.bars, frame_repeats=args.frame_repeats,
                     overlay=args.overlay, draws=draws, effects=args.effects == "on", lens=lens,
                     readout=args.readout)
    print()
    summary = summarize(rows)
    print(format_summary(summary))
    ratios = draw_ratios(rows) if draws else ([], [])
    # A second table only when some run was refined (its keyframes' shift is reported).
    refined = any(np.isfinite(r["global_shift_pct"]) for r in rows)
    streaming = draw_ratios(rows, key="ate_pct_streaming") if draws and refined else ([], [])
    if draws:
        print()
        print(format_draw_ratios(*ratios))
    if streaming[0]:
        print("\nthe same runs before the global refinement (the sliding window's trajectories):")
        print(format_draw_ratios(*streaming))
    verdicts = {v: verdict_quality([r for r in rows if r["variant"] == v], args.good_pct)
                for v in dict.fromkeys(r["variant"] for r in rows)}
    for v, q in verdicts.items():
        print(f"{v}: {format_verdict_quality(q)}")
    if args.out:
        import json

        from data_tools.atomic import write_text_atomic

        write_text_atomic(args.out, json.dumps({"rows": rows, "summary": summary, "verdict": verdicts,
                                                "draws": {"per_sequence": ratios[0],
                                                          "per_variant": ratios[1]},
                                                "draws_streaming": {"per_sequence": streaming[0],
                                                                    "per_variant": streaming[1]}},
                                               indent=1, default=float) + "\n")
    print(f"peak memory {peak_memory_mb():.0f} MB")
    return 0


def _read_rows(path: str) -> list[dict]:
    """The rows of a ``--out`` file; a missing or foreign file is a one-line InputError."""
    import json
    from pathlib import Path

    from mona_vo.errors import InputError

    try:
        return json.loads(Path(path).read_text())["rows"]
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: not a file written by eval.vo_bench --out ({exc})") from None


if __name__ == "__main__":
    raise SystemExit(main())
