"""Benchmarks of the MONA masks (:mod:`mona_vo.masks`): quality on generated scenes with exact
ground truth, DAVIS-2016 J and F per prompt mode, and seconds per frame per stage.

Library functions return plain rows (lists of dicts); only ``python -m eval.mask_bench`` prints.

* :func:`synthetic_rows`: per preset and seed of :mod:`data_tools.synthetic`, the mean over frames
  of the mask IoU against the GT mask (DAVIS J, 1 when both masks are empty), boundary F, and the
  false-positive area (mask pixels outside the GT mask, fraction of the image); presets without
  movers ('static') are judged by the false-positive area. With ``mode`` 'gt-boxes' the
  segmenter alone, prompted with the true boxes; with 'gt-detector' the whole method with a
  perfect object detector (:class:`TrueBoxDetector`).
* :func:`davis_rows`: DAVIS J and F (all frames, :func:`eval.mask_metrics.evaluate_mask_sequence`)
  per sequence and prompt mode ('boxes', 'points', 'raw-boxes'), and 'gt-boxes': the segmenter
  alone, prompted with the boxes of the true mask's parts (:func:`gt_box_masks`), what the
  segmentation stage reaches when detection and filter are perfect; and 'gt-detector': the whole
  method (motion seeds, the paper's box filter, the objects the evidence follows) with a
  detector that finds every annotated object and nothing else, what an object detector back end
  (``yolo``) would at best give the method.
* :func:`speed_rows`: wall-clock seconds per frame of each stage (``MaskFrame.seconds``) on a
  1024 x 436 input (the real Sintel clip when present, else a generated scene; decoding and
  rendering are not timed).
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from data_tools.frames import Frame
from eval.mask_metrics import boundary_f, error_parts, evaluate_mask_sequence, region_similarity
from mona_vo.detection import Boxes, Detector, mask_to_boxes
from mona_vo.masks import STAGES, MaskConfig, compute_masks

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DYNAMIC_PRESETS = ("one-large", "several", "fast-rotation")


SYNTHETIC_MODES = ("boxes", "gt-boxes", "gt-detector")


def synthetic_rows(presets: Sequence[str] = ("static",) + DYNAMIC_PRESETS,
                   seeds: Sequence[int] = (0, 1, 2), n_frames: int = 30, width: int = 1024,
                   height: int = 436, config: MaskConfig | None = None,
                   use_intrinsics: bool = False, mode: str = "boxes", calib: str = "estimate",
                   pipeline=None, effects: bool = True) -> list[dict]:
    """One row per (preset, seed): J (mean IoU), F, false-positive area fraction, mask and GT area
    fractions, frames; where the pixels go (:func:`eval.mask_metrics.error_parts`: ``found``,
    ``spill``, ``apart`` as shares of the true masks' pixels, NaN without movers) and
    ``frames_found``, the share of the frames with a mover in view whose mask touches it (NaN
    without such frames): a low J from movers never found, from masks found late, or from masks
    too large or elsewhere. The masker's camera: ``use_intrinsics`` or ``calib`` 'given' passes
    the scene's true intrinsics; else ``calib`` 'estimate' (default) the focal length `mona-vo
    masks` and `run`
    estimate from the first frames, as the product's masks get it
    (:func:`mona_vo.pipeline.camera_ahead` with ``pipeline``'s calibration settings, a
    PipelineConfig, default its defaults), or 'guess' its ``assumed_hfov_deg`` guess (the
    bench's camera before stop 38). Rows of the method carry ``focal_error_pct``, the camera's
    focal length against the scene's, per cent. ``effects=False``: the ``mixed`` frames before
    their image effects (blur, noise, exposure, JPEG), the same scenes. ``mode``: 'boxes' the
    method; 'gt-boxes' the segmenter alone, prompted with the true masks' part boxes
    (:func:`gt_box_masks`); 'gt-detector' the method with :class:`TrueBoxDetector`."""
    if mode not in SYNTHETIC_MODES:
        raise ValueError(f"mode {mode!r}: one of {', '.join(SYNTHETIC_MODES)}")
    if calib not in ("guess", "estimate", "given"):
        raise ValueError(f"calib {calib!r}: one of guess, estimate, given")
    use_intrinsics = use_intrinsics or calib == "given"
    from data_tools.synthetic import SceneConfig, SyntheticScene
    from mona_vo.pipeline import PipelineConfig, camera_ahead

    config = config or MaskConfig()
    pipeline = pipeline or PipelineConfig()
    rows = []
    for preset in presets:
        for seed in seeds:
            scene = SyntheticScene(SceneConfig(width=width, height=height, n_frames=n_frames,
                                               preset=preset, seed=seed, effects=effects))
            gts: dict[int, np.ndarray] = {}

            def frames():
                for i in range(len(scene)):
                    f = scene.render(i)
                    gts[i] = f.mask
                    yield i, f.image

            intrinsics, extra = None, {}
            if mode != "gt-boxes":      # the true-box prompts need no camera
                if use_intrinsics:
                    intrinsics = scene.intrinsics
                elif calib == "estimate":
                    head = (Frame(i, float(i), f"{i:05d}", scene.render(i).image)
                            for i in range(min(len(scene), pipeline.calibration.frames)))
                    _, _, intrinsics = camera_ahead(head, pipeline, width, height)
                else:
                    intrinsics = pipeline.guessed_intrinsics(width, height)
                extra = {"focal_error_pct": 100.0 * (intrinsics.fx / scene.intrinsics.fx - 1)}
            if mode == "gt-boxes":
                images = [image for _, image in frames()]
                truth = [gts[i] for i in range(len(images))]
                found = zip(range(len(images)), gt_box_masks(images, truth, config))
            else:
                # The detector reads the truth of frames already rendered (``gts``) by index.
                backends = {"detector": TrueBoxDetector(gts)} if mode == "gt-detector" else {}
                found = ((out.index, out.mask) for out in
                         compute_masks(frames(), config, intrinsics, **backends))
            J, F, fp, area, gt_area, preds, truths = [], [], [], [], [], [], []
            for index, mask in found:
                gt = gts.pop(index)
                preds.append(mask)
                truths.append(gt)
                J.append(region_similarity(mask, gt))
                F.append(boundary_f(mask, gt))
                fp.append(float(np.mean(mask & ~gt)))
                area.append(float(mask.mean()))
                gt_area.append(float(gt.mean()))
            parts = error_parts(preds, truths)
            seen = [(p & g).any() for p, g in zip(preds, truths) if g.any()]
            rows.append({"preset": preset, "seed": seed, "frames": len(J),
                         "J": float(np.mean(J)), "F": float(np.mean(F)),
                         "fp_area": float(np.mean(fp)), "mask_area": float(np.mean(area)),
                         "gt_area": float(np.mean(gt_area)),
                         "found": parts["found"], "spill": parts["spill"],
                         "apart": parts["apart"],
                         "frames_found": float(np.mean(seen)) if seen else float("nan"),
                         **extra})
    return rows


def summarise(rows: list[dict], key: str = "preset") -> list[dict]:
    """Means of the numeric fields of ``rows`` grouped by ``key``."""
    out = []
    for value in dict.fromkeys(r[key] for r in rows):
        group = [r for r in rows if r[key] == value]
        row = {key: value, "runs": len(group)}
        for k, v in group[0].items():
            if isinstance(v, float):
                row[k] = float(np.mean([g[k] for g in group]))
        out.append(row)
    return out


DAVIS_TUNE = ("car-shadow", "dog", "libby", "parkour")            # the board's tuning part
DAVIS_VALIDATE = ("blackswan", "cows", "goat", "scooter-black")    # never tuned on
DAVIS_ROOTS = ("davis2016", "davis2016_more")                       # shared folders, same layout


def true_boxes(gt: np.ndarray, label: str = "object"):
    """:class:`~mona_vo.detection.Boxes` of the 8-connected parts of an (H, W) true mask, parts
    under 0.1 % of the image dropped, each labelled ``label``."""
    gt = np.asarray(gt, bool)
    xyxy, _ = mask_to_boxes(gt, max(1, int(0.001 * gt.size)))
    return Boxes.from_arrays(xyxy, label=np.full(len(xyxy), label))


class TrueBoxDetector(Detector):
    """A detector (:class:`mona_vo.detection.Detector`'s interface) that finds every annotated
    object and nothing else: the boxes of the true mask's parts of the frame
    (``FrameContext.frame_index``, looked up in ``truth``: a mapping frame index -> (H, W)
    bool mask), labelled as an object detector labels them. The masker treats its boxes as any
    object detector's (:mod:`mona_vo.masks`, evidence)."""

    def __init__(self, truth):
        self.truth = truth

    def detect(self, image, context=None):
        if context is None or context.frame_index not in self.truth:
            return Boxes.empty()
        return true_boxes(self.truth[context.frame_index])


def gt_box_masks(images: Iterable[np.ndarray], gts: Iterable[np.ndarray],
                 config: MaskConfig, device: str = "cpu") -> list[np.ndarray]:
    """Masks of ``config``'s segmenter prompted with one box per 8-connected part of each true
    mask (parts under 0.1 % of the image dropped), without the masker's motion context: the
    detector and the box filter replaced by the truth."""
    from mona_vo.masks import build_segmenter

    segmenter = build_segmenter(config, device)
    out = []
    for image, gt in zip(images, gts):
        boxes = true_boxes(gt)
        out.append(segmenter.segment(image, boxes) if len(boxes)
                   else np.zeros(np.shape(gt), bool))
    return out


def davis_root_of(sequence: str, data: str | Path | None = None) -> Path:
    """The shared DAVIS folder holding ``sequence`` (the first of :data:`DAVIS_ROOTS`)."""
    data = Path(data) if data is not None else SHARED_DATA
    for name in DAVIS_ROOTS:
        if (data / name / "JPEGImages" / "480p" / sequence).is_dir():
            return data / name
    return data / DAVIS_ROOTS[0]


def _noting_truth(frames, masks, truth: dict):
    """(index, image) of each frame, its true mask put in ``truth`` under its index first."""
    for frame, mask in zip(frames, masks):
        truth[frame.index] = mask
        yield frame.index, frame.image


def davis_rows(root: str | Path | None = None,
               sequences: Sequence[str] = DAVIS_TUNE + DAVIS_VALIDATE,
               modes: Sequence[str] = ("boxes",),
               config: MaskConfig | None = None, max_frames: int | None = None,
               calib: str = "estimate", pipeline=None) -> list[dict]:
    """One row per (sequence, prompt mode): J and F means over all frames, what the error is
    made of (:func:`eval.mask_metrics.error_parts`: ``found``, ``spill`` and ``apart`` as shares
    of the true masks' pixels), the sequence's split ('tune' or 'validate', by the board's DAVIS
    split) and the mean seconds per frame.
    ``root``: one DAVIS folder holding every sequence; None looks each one up in the shared
    data (:func:`davis_root_of`). ``calib``: ``estimate`` (default) gives the masker
    the focal length `mona-vo masks` and `mona-vo run` estimate from the first 40 frames
    (:func:`mona_vo.pipeline.camera_ahead`, with ``pipeline``'s calibration settings, a
    PipelineConfig, default its defaults), as the product's masks get it; the row then carries
    ``focal_px``. ``guess``: the 60-degree field-of-view guess."""
    from data_tools.davis import DavisSequence

    config = config or MaskConfig()
    rows = []
    for seq in sequences:
        ds = DavisSequence(Path(root) if root is not None else davis_root_of(seq), seq)
        intrinsics, extra = None, {}
        # The true-box prompts need no camera: the estimate is only for the masker's modes.
        if calib == "estimate" and any(mode != "gt-boxes" for mode in modes):
            from mona_vo.pipeline import PipelineConfig, camera_ahead

            pipeline = pipeline or PipelineConfig()
            head = ds.frames(max_frames=pipeline.calibration.frames)
            _, _, intrinsics = camera_ahead(head, pipeline, head.width, head.height)
            extra = {"focal_px": float(intrinsics.fx)}
        for mode in modes:
            t0 = time.perf_counter()
            if mode == "gt-boxes":
                images = [f.image for f in ds.frames(max_frames=max_frames)]
                gts = [m for m, _ in zip(ds.masks(), images)]
                preds = gt_box_masks(images, gts, config,
                                     pipeline.device if pipeline is not None else "cpu")
            else:
                truth = None
                if mode == "gt-detector":
                    # The truth is noted as each frame is read (the detector looks a frame up
                    # only after it was pushed), so frames and true masks are decoded once.
                    truth = {}
                    frames = _noting_truth(ds.frames(max_frames=max_frames), ds.masks(), truth)
                    backends, prompt = {"detector": TrueBoxDetector(truth)}, "boxes"
                else:
                    frames = ((f.index, f.image) for f in ds.frames(max_frames=max_frames))
                    backends, prompt = {}, mode
                preds = [out.mask for out in
                         compute_masks(frames, dataclasses.replace(config, prompt=prompt),
                                       intrinsics, **backends)]
                gts = (list(truth.values()) if truth is not None
                       else [m for m, _ in zip(ds.masks(), preds)])
            sec = (time.perf_counter() - t0) / max(len(preds), 1)
            metrics = evaluate_mask_sequence(preds, gts)
            parts = error_parts(preds, gts)
            split = "tune" if seq in DAVIS_TUNE else "validate" if seq in DAVIS_VALIDATE else "-"
            rows.append({"sequence": seq, "split": split, "prompt": mode,
                         "frames": metrics.n_frames, "J": metrics.J_mean, "F": metrics.F_mean,
                         "found": parts["found"], "spill": parts["spill"],
                         "apart": parts["apart"], "s_per_frame": sec, **extra})
    return rows


def speed_rows(n_frames: int = 25, config: MaskConfig | None = None,
               sintel_dir: str | Path | None = None) -> list[dict]:
    """Seconds per frame of each stage, and in total, at 1024 x 436: one row per stage with the
    mean and median over frames (frames decoded or rendered before timing). With
    ``segment_async`` the segmentation overlaps the next frame's analysis, so the wall clock per
    frame, the row the target is about, is below the sum of the stages."""
    config = config or MaskConfig()
    folder = Path(sintel_dir) if sintel_dir is not None else \
        SHARED_DATA / "sintel_clip_alley" / "training" / "clean" / "alley_1"
    if folder.is_dir():
        from data_tools.frames import open_frames

        images = [f.image for f in open_frames(folder, max_frames=n_frames)]
        source = f"sintel alley_1 ({len(images)} frames)"
    else:
        from data_tools.synthetic import SceneConfig, SyntheticScene

        scene = SyntheticScene(SceneConfig(width=1024, height=436, n_frames=n_frames,
                                           preset="one-large", seed=0))
        images = [scene.render(i).image for i in range(n_frames)]
        source = f"synthetic one-large ({n_frames} frames)"
    per_stage = {s: [] for s in STAGES}
    totals = []
    t0 = time.perf_counter()
    for out in compute_masks(enumerate(images), config):
        for s in STAGES:
            per_stage[s].append(out.seconds.get(s, 0.0))
        totals.append(sum(out.seconds.values()))
    wall = (time.perf_counter() - t0) / max(len(images), 1)
    h, w = images[0].shape[:2]
    rows = [{"stage": s, "mean_ms": 1000 * float(np.mean(v)),
             "median_ms": 1000 * float(np.median(v))} for s, v in per_stage.items()]
    rows.append({"stage": "total (sum of stages)", "mean_ms": 1000 * float(np.mean(totals)),
                 "median_ms": 1000 * float(np.median(totals))})
    rows.append({"stage": "wall clock per frame", "mean_ms": 1000 * wall,
                 "median_ms": float("nan")})
    for r in rows:
        r["input"] = f"{source}, {w} x {h}"
    return rows


def format_table(rows: list[dict]) -> str:
    """Plain-text table of rows (floats with 3 decimals)."""
    if not rows:
        return "(no rows)"
    keys = list(dict.fromkeys(k for r in rows for k in r))

    def cell(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)

    width = {k: max(len(k), *(len(cell(r.get(k, ""))) for r in rows)) for k in keys}
    lines = ["  ".join(k.ljust(width[k]) for k in keys)]
    lines += ["  ".join(cell(r.get(k, "")).ljust(width[k]) for k in keys) for r in rows]
    return "\n".join(lines)


def split_means(rows: list[dict]) -> list[dict]:
    """Per prompt mode: mean J and F over the tuning sequences, the validation ones and all,
    and the lowest J (the issue's "none below" bound)."""
    out = []
    for mode in dict.fromkeys(r["prompt"] for r in rows):
        sel = [r for r in rows if r["prompt"] == mode]
        for split in ("tune", "validate", "all"):
            part = [r for r in sel if split == "all" or r["split"] == split]
            if part:
                out.append({"prompt": mode, "split": split, "sequences": len(part),
                            "J": float(np.mean([r["J"] for r in part])),
                            "F": float(np.mean([r["F"] for r in part])),
                            "J_min": float(min(r["J"] for r in part))})
    return out


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m eval.mask_bench [--parts speed,davis,synthetic] [--presets ...] [--seeds 0,1,2]
    [--frames 30] [--size 1024x436] [--modes boxes]``: speed, DAVIS J/F, generated scenes."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m eval.mask_bench", description=__doc__)
    parser.add_argument("--parts", default="speed,davis,synthetic", help="which benchmarks to run")
    parser.add_argument("--presets", default=",".join(("static",) + DYNAMIC_PRESETS),
                        help="generator presets for the synthetic part, comma-separated")
    parser.add_argument("--seeds", default="0,1,2", help="synthetic scene seeds, e.g. 0,1,2 or 100-111")
    parser.add_argument("--frames", type=int, default=30, help="frames per synthetic scene")
    parser.add_argument("--size", default="1024x436", help="synthetic image size WxH")
    parser.add_argument("--modes", default="boxes",
                        help="DAVIS prompt modes: boxes,points,raw-boxes,gt-boxes,gt-detector (the "
                             "generated scenes: one of boxes, gt-boxes, gt-detector)")
    parser.add_argument("--calib", choices=("guess", "estimate", "given"), default="estimate",
                        help="the masker's camera, DAVIS and generated scenes: the focal length "
                             "`mona-vo masks` and `run` estimate (default) or the 60-degree "
                             "field-of-view guess; generated scenes also 'given', their true "
                             "intrinsics (whether a focal error is what a mask misses)")
    parser.add_argument("--effects", choices=("on", "off"), default="on",
                        help="generated scenes: off renders the `mixed` frames before their image "
                             "effects (blur, noise, exposure, JPEG), the same scenes (default on)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override one pipeline config value, e.g. --set "
                             "masks.evidence.decay=0.7 (repeatable; as `mona-vo masks --set`)")
    args = parser.parse_args(argv)
    from mona_vo.config import load_config, parse_set_options
    from mona_vo.pipeline import PipelineConfig

    pipeline = load_config(PipelineConfig, None, parse_set_options(args.set))
    config = pipeline.masks
    parts = set(args.parts.split(","))
    from eval.vo_bench import parse_seeds
    from mona_vo.errors import ConfigError

    try:
        seeds = parse_seeds(args.seeds)
    except ConfigError as exc:
        parser.error(str(exc))
    try:
        w, h = (int(v) for v in args.size.split("x"))
        if w < 16 or h < 16:
            raise ValueError
    except ValueError:
        parser.error(f"--size expects WIDTHxHEIGHT of at least 16x16 pixels, not '{args.size}'")
    if args.calib == "given" and "davis" in parts:
        parser.error("--calib given: DAVIS has no intrinsics; use it with --parts synthetic")
    if "speed" in parts:
        print("== speed (ms per frame per stage) ==")
        print(format_table(speed_rows(config=config)), flush=True)
    if "davis" in parts and (SHARED_DATA / "davis2016").is_dir():
        rows = davis_rows(modes=tuple(args.modes.split(",")), config=config, calib=args.calib,
                          pipeline=pipeline)
        print("\n== DAVIS-2016 (J, F) per sequence and prompt mode ==")
        print(format_table(rows))
        print("\n== DAVIS-2016 means: tuning part, validation part, all ==")
        print(format_table(split_means(rows)), flush=True)
    if "synthetic" in parts:
        # Of the prompt modes, the generated scenes take one: the method's boxes, gt-boxes (the
        # segmenter alone) or gt-detector (the method with a perfect object detector).
        if args.modes not in SYNTHETIC_MODES:
            parser.error(f"--modes {args.modes}: the generated scenes take one of "
                         f"{', '.join(SYNTHETIC_MODES)}")
        rows = synthetic_rows(presets=tuple(args.presets.split(",")), seeds=seeds,
                              n_frames=args.frames, width=w, height=h, config=config,
                              mode=args.modes, calib=args.calib, pipeline=pipeline,
                              effects=args.effects == "on")
        print("\n== synthetic scenes, per seed ==")
        print(format_table(rows))
        print("\n== synthetic scenes, per preset (J = mean IoU; static: fp_area) ==")
        print(format_table(summarise(rows)))


if __name__ == "__main__":
    main()
