"""mona-vo: camera trajectories of videos in which people and cars move.

Commands parse options, call one library function (mona_vo.run, eval.*) and print. Imports are
lazy so that --help stays fast. Any MonaVoError, and any bad option, becomes one line on stderr
and exit code 1. -q/-v and the config options may come before or after the command.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from mona_vo import __version__
from mona_vo.errors import ConfigError, InputError, MonaVoError
from mona_vo.presets import PRESETS

# Options every command takes, and the config options of the commands that build a
# PipelineConfig. Both may be typed before the command too: there they land under "top_<dest>"
# and _merge_shared() folds them in (a value after the command wins; --set items add up).
_SHARED = ("quiet", "verbose")
_CONFIG = ("config", "set", "preset", "device", "weights")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors and exit code 1 (argparse's own usage errors included)."""

    def error(self, message: str):
        self.exit(1, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _add_shared_options(p: argparse.ArgumentParser, *, top: bool = False) -> None:
    pre = "top_" if top else ""
    verbosity = p.add_mutually_exclusive_group()
    verbosity.add_argument("-q", "--quiet", dest=pre + "quiet", action="store_true",
                           default=argparse.SUPPRESS, help="no progress bars, only results and errors")
    verbosity.add_argument("-v", "--verbose", dest=pre + "verbose", action="store_true",
                           default=argparse.SUPPRESS, help="log what each stage does")


def _add_config_options(p: argparse.ArgumentParser, *, top: bool = False, preset: bool = True) -> None:
    """--config, --set, --preset, --device, --weights: a run's PipelineConfig (see _pipeline_config)."""
    pre = "top_" if top else ""
    S = argparse.SUPPRESS
    p.add_argument("--config", dest=pre + "config", metavar="YAML", default=S,
                   help="YAML file of config values (keys as printed by `mona-vo config`)")
    p.add_argument("--set", dest=pre + "set", metavar="KEY=VALUE", action="append", default=S,
                   help="override one config value, e.g. --set vo.grid_size=20 (repeatable; applied after --config)")
    if preset:
        p.add_argument("--preset", dest=pre + "preset", choices=sorted(PRESETS), default=S,
                       help="speed/accuracy preset, applied first: fast (12 x 12 new points, a window of "
                            "6 keyframes), default, accurate (24 x 24 new points once a map exists; "
                            "about half the VO's speed)")
    p.add_argument("--device", dest=pre + "device", metavar="cpu|cuda[:N]", default=S,
                   help="device of the neural back ends, same as --set device=... (classical ones run on the CPU)")
    p.add_argument("--weights", dest=pre + "weights", metavar="DIR", default=S,
                   help="folder of neural checkpoints (RAFT, YOLO, SAM, CoTracker) under their documented names, "
                        "same as --set weights=...; default $MONA_VO_WEIGHTS")


def _add_refine_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--refine", choices=["global", "none"], default=None,
                   help="after the sliding window, one bundle adjustment over all keyframes (global, default) "
                        "or none (streaming); same as --set vo.refine=...")


def _add_draws_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--draws", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="run everything once per value (repeatable; each value of each key is one "
                        "draw, e.g. --draws vo.grid_size=14,15,16,17,18) and write draws.md with "
                        "each sequence's mean, median and range over the draws")
    p.add_argument("--parts", action="append", default=[], metavar="NAME=A:B",
                   help="also score each run on rows A to B-1 of its trajectory, aligned alone "
                        "(repeatable, e.g. --parts tune=0:225 --parts validate=225:450): a "
                        "tuning and a validation part of one sequence, in every table")


def _add_mask_options(p: argparse.ArgumentParser, *, allow_folder: bool = True) -> None:
    if allow_folder:
        p.add_argument("--masks", default="mona", metavar="mona|none|DIR",
                       help="moving-object masks: computed by MONA (default), none, or read from DIR/<frame name>.png")
    p.add_argument("--prompt", choices=["boxes", "points", "raw-boxes"], default=None,
                   help="MONA segmenter prompts: filtered boxes (the method, default), dynamic points only, "
                        "or all detector boxes (ablations); same as --set masks.prompt=...")


def _add_input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="a video file (mp4/avi/mov/mkv/webm) or a folder of images")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    p.add_argument("--stride", type=int, default=1, help="use every N-th frame (default 1)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")


def add_run_options(p: argparse.ArgumentParser) -> None:
    """Everything `run` takes about one input: input, --out, --stride, --max-frames, --calib,
    --masks, --prompt, the config options and --refine (reused by `batch`)."""
    _add_input_options(p)
    p.add_argument("--calib", metavar="fx,fy,cx,cy[,k1,k2,p1,p2,k3]|FILE",
                   help="intrinsics in pixels, with the lens distortion if the frames have it "
                        "(OpenCV's order; the frames are then undistorted), or a file (the same "
                        "numbers on one line, or KITTI calib.txt); default: estimated from the "
                        "first frames (calibration.mode)")
    _add_mask_options(p)
    _add_config_options(p)
    _add_refine_option(p)


def _sub(sub, name: str, *, config: bool = False, **kwargs) -> argparse.ArgumentParser:
    """A subcommand parser with the shared options (and the config options when it builds a config)."""
    p = sub.add_parser(name, **kwargs)
    _add_shared_options(p)
    if config:
        _add_config_options(p)
    p.set_defaults(takes_config=config)
    return p


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="mona-vo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"mona-vo {__version__}")
    _add_shared_options(p, top=True)
    _add_config_options(p, top=True)
    sub = p.add_subparsers(dest="command", metavar="COMMAND")

    r = _sub(sub, "run", help="camera trajectory, masks and report of a video or image folder",
             description="Writes DIR/trajectory.txt (TUM, camera-to-world), DIR/masks/, "
                         "DIR/report.json, DIR/trajectory.png and, with --overlay, DIR/overlay.mp4.")
    add_run_options(r)
    r.set_defaults(takes_config=True)
    r.add_argument("--overlay", action="store_true", help="also write DIR/overlay.mp4 with masks, points and boxes drawn")
    r.add_argument("--gt", metavar="TUM_FILE", help="ground-truth trajectory to draw in trajectory.png")
    r.set_defaults(func=_cmd_run)

    m = _sub(sub, "masks", config=True, help="MONA moving-object masks only, written to DIR/masks/")
    _add_input_options(m)
    _add_mask_options(m, allow_folder=False)
    m.set_defaults(func=_cmd_masks)

    bt = _sub(sub, "batch", help="many videos on Ray: run's outputs per input, batch.csv and index.html",
                        description="One Ray task per input; DIR/<input name>/ holds what `run` writes. "
                                    "DIR/batch.csv (one row per input: status ok|failed|skipped, the usable "
                                    "verdict, key numbers, node) and DIR/index.html are rewritten as tasks "
                                    "finish. A rerun skips inputs done with the same config and retries "
                                    "failed ones. Exit 1 when any input failed. Without --address a local "
                                    "Ray starts in this process (loopback only, no dashboard, token auth).")
    bt.add_argument("inputs", nargs="+", metavar="INPUT",
                    help="video files, frame folders, or @LIST (a text file, one path per line; relative "
                         "paths are relative to the list's folder)")
    bt.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    bt.add_argument("--address", metavar="auto|HOST:PORT", default=None,
                    help="join this Ray cluster (auto: the one `ray start` made on this machine); "
                         "default: an embedded local Ray on this machine's cores")
    bt.add_argument("--cpus-per-video", type=float, default=None, metavar="N",
                    help="Ray CPUs reserved per video (default 1; same as --set batch.cpus_per_video=N)")
    bt.add_argument("--stride", type=int, default=1, help="use every N-th frame (default 1)")
    bt.add_argument("--max-frames", type=int, default=None, help="stop each input after this many frames")
    bt.add_argument("--calib", metavar="fx,fy,cx,cy[,k1,k2,p1,p2,k3]|FILE",
                    help="intrinsics for every input (default: the field-of-view guess, per input)")
    bt.add_argument("--masks", default="mona", metavar="mona|none|DIR",
                    help="moving-object masks: MONA (default), none, or DIR/<input name>/<frame name>.png")
    _add_mask_options(bt, allow_folder=False)
    _add_config_options(bt)
    _add_refine_option(bt)
    bt.add_argument("--overlay", action="store_true", help="also write overlay.mp4 per input")
    bt.set_defaults(func=_cmd_batch, takes_config=True)

    d = _sub(sub, "demo", help="generate a synthetic dynamic scene and compare no masks, MONA and GT masks",
             description="Renders a synthetic scene and runs it three times (no masks, MONA masks, GT "
                         "masks); prints the ATE of each, the output folder and the plot to open.")
    d.add_argument("--out", metavar="DIR", help="output folder (default: a new temporary folder, kept)")
    d.add_argument("--preset", default="one-large",
                   help="synthetic scene preset (data_tools.synthetic.PRESETS, e.g. static, one-large, several)")
    d.add_argument("--seed", type=int, default=5, help="scene seed (default 5: a car keeps pace ahead of the camera)")
    d.add_argument("--frames", type=int, default=40, help="number of frames")
    d.add_argument("--size", default="1024x436", help="image size WxH (default Sintel's 1024x436)")
    _add_config_options(d, preset=False)
    d.set_defaults(func=_cmd_demo, takes_config=True)

    b = _sub(sub, "bench", config=True,
             help="speed and accuracy on generated 1024x436 scenes, beside COLMAP (pycolmap)",
             description="Generates sequences, runs mona-vo (no masks, MONA, GT masks) and COLMAP's "
                         "incremental SfM (without and with GT masks) on the same frames, and prints "
                         "ATE, frames posed, frames/s per stage, mask IoU and peak memory.")
    b.add_argument("--presets", default="static,one-large,several", help="comma-separated generator presets")
    b.add_argument("--seeds", default="0", help="seeds, e.g. 0-2 or 0,3")
    b.add_argument("--frames", type=int, default=50, help="frames per sequence")
    b.add_argument("--size", default="1024x436", help="image size WxH")
    b.add_argument("--no-peer", action="store_true", help="skip COLMAP (it runs at about 1 frame/s)")
    b.add_argument("--out", metavar="FILE", help="also write the rows as JSON here")
    b.set_defaults(func=_cmd_bench)

    c = _sub(sub, "config", config=True, help="print the configuration as YAML, a comment per key",
             description="Prints the default configuration (after --preset, --config and --set, if "
                         "given) as YAML with each key's meaning and allowed values. The output loads "
                         "back with --config and gives the same run.")
    c.add_argument("--out", metavar="FILE", help="write the YAML here instead of printing it")
    c.set_defaults(func=_cmd_config)

    e = _sub(sub, "eval", help="evaluate trajectories, masks, or whole datasets")
    esub = e.add_subparsers(dest="eval_command", metavar="WHAT")
    et = _sub(esub, "traj", help="ATE/RPE of an estimate against GT (evo's numbers), printed as JSON")
    et.add_argument("--gt", required=True, help="ground-truth trajectory file")
    et.add_argument("--est", required=True, help="estimated trajectory file")
    et.add_argument("--format", choices=["tum", "kitti"], default="tum",
                    help="file format: tum (timestamped, associated by time) or kitti (matched by line)")
    et.add_argument("--align", choices=["sim3", "se3", "none"], default="sim3",
                    help="alignment before the errors: sim3 for monocular (default), se3 for metric estimates")
    et.add_argument("--max-diff", type=float, default=0.01, help="timestamp association tolerance, seconds (tum)")
    et.add_argument("--frames", metavar="A:B",
                    help="score only the estimate's poses A to B-1 (rows of the file, from 0), "
                         "aligned alone: e.g. a tuning and a validation part of one run")
    et.add_argument("--scale-window", type=int, default=0, metavar="N",
                    help="add window_scales: per N steps of the aligned estimate, its path "
                         "length over the GT's (1 = the run's scale; near 0 = it stopped "
                         "translating, a scale collapse)")
    et.set_defaults(func=_cmd_eval_traj)
    ec = _sub(esub, "compare", help="two --draws runs of one command, before and after a change: "
                                   "paired differences per sequence, variant and part")
    ec.add_argument("--base", required=True, metavar="DIR", help="the first run's output folder (its draws.json)")
    ec.add_argument("--new", required=True, metavar="DIR", help="the second run's output folder")
    ec.set_defaults(func=_cmd_eval_compare)
    em = _sub(esub, "masks", help="DAVIS region J and boundary F of predicted masks, printed as JSON")
    em.add_argument("--pred", required=True, help="folder of predicted mask PNGs")
    em.add_argument("--gt", required=True, help="folder of ground-truth mask PNGs (same file names)")
    em.set_defaults(func=_cmd_eval_masks)

    es = _sub(esub, "sintel", config=True, help="MPI Sintel camera-trajectory benchmark and the paper's ablations",
              description="Runs every sequence x variant, writes DIR/results.csv, results.json, "
                          "results.md and DIR/<variant>/<seq>/trajectory.txt. Rerunning skips "
                          "runs already done with the same config and retries failed ones.")
    es.add_argument("--root", required=True, help="Sintel root (the folder holding training/)")
    es.add_argument("--pass", dest="pass_", choices=["final", "clean"], default="final", help="render pass (default final)")
    es.add_argument("--seqs", help="comma-separated sequences (default: the 14 of the protocol)")
    es.add_argument("--variants", default="none,mona",
                    help="comma-separated: none, mona, mona-points, mona-raw-boxes, gt (default none,mona)")
    es.add_argument("--masks-root", help="folder of GT masks <seq>/frame_XXXX.png, for the gt variant")
    es.add_argument("--out", required=True, metavar="DIR", help="output folder")
    es.add_argument("--workers", type=int, default=1, help="runs in parallel (processes)")
    es.add_argument("--address", metavar="local|auto|HOST:PORT", default=None,
                    help="run on Ray as `batch` does, one task per run: local (an embedded local Ray on "
                         "this machine's cores), auto or HOST:PORT (a cluster); replaces --workers")
    _add_refine_option(es)
    _add_draws_option(es)
    es.set_defaults(func=_cmd_eval_sintel)

    eu = _sub(esub, "tum", config=True, help="folders in TUM RGB-D layout (TUM, Bonn, ETH3D): ATE/RPE per variant")
    eu.add_argument("--root", required=True, action="append",
                    help="a folder with rgb.txt, rgb/ and groundtruth.txt (repeatable)")
    eu.add_argument("--variants", default="none,mona", help="comma-separated: none, mona, mona-points, mona-raw-boxes")
    eu.add_argument("--calib", metavar="fx,fy,cx,cy[,k1,k2,p1,p2,k3]|FILE|estimate",
                    help="intrinsics (default: the folder's calib.txt, else estimated as `run` "
                         "does); estimate: ignore calib.txt and estimate, as for an online video")
    eu.add_argument("--out", required=True, metavar="DIR", help="output folder")
    eu.add_argument("--workers", type=int, default=1, help="runs in parallel (processes)")
    eu.add_argument("--max-diff", type=float, default=None, metavar="SECONDS",
                    help="GT association tolerance (default 0.02, the TUM benchmark's own; evo's "
                         "default is 0.01)")
    eu.add_argument("--address", metavar="local|auto|HOST:PORT", default=None,
                    help="run on Ray as `batch` does, one task per run: local (an embedded local Ray on "
                         "this machine's cores), auto or HOST:PORT (a cluster); replaces --workers")
    _add_refine_option(eu)
    _add_draws_option(eu)
    eu.set_defaults(func=_cmd_eval_tum)

    ef = _sub(esub, "flow", help="end-point error and speed of a flow back end on one pair with GT flow, as JSON",
              description="EPE over valid non-occluded pixels (epe_noc) and over all valid pixels "
                          "(epe_all), and ms per pair (median of 5 calls after a warm-up).")
    ef.add_argument("--image0", required=True, help="first image")
    ef.add_argument("--image1", required=True, help="second image")
    ef.add_argument("--gt", required=True, metavar="FLO", help="ground-truth flow image0 -> image1 (.flo)")
    ef.add_argument("--occlusions", metavar="PNG", help="occlusion mask (non-zero = occluded; Sintel occlusions/)")
    ef.add_argument("--invalid", metavar="PNG", help="invalid-pixel mask (non-zero = left out; Sintel invalid/)")
    ef.add_argument("--flow", default="dis", help="flow back end: dis (default) or raft (needs a checkpoint)")
    ef.add_argument("--weights", metavar="DIR", help="checkpoint file or folder of a neural back end; default $MONA_VO_WEIGHTS")
    ef.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="device of a neural back end")
    ef.set_defaults(func=_cmd_eval_flow)

    ev = _sub(esub, "two-view", help="two-view initialisation (LK tracks + five-point pose) against GT, as JSON",
              description="Tracks the VO's grid points from image0 to image1 with its tracker, estimates "
                          "the relative pose and prints its rotation and translation-direction errors "
                          "against rows i, j of a KITTI pose file (GT: inv(T_i) T_j).")
    ev.add_argument("--image0", required=True, help="first image")
    ev.add_argument("--image1", required=True, help="second image")
    ev.add_argument("--calib", required=True, metavar="fx,fy,cx,cy|FILE", help="intrinsics (a KITTI calib.txt gives P0)")
    ev.add_argument("--gt-poses", required=True, metavar="FILE", help="KITTI pose file (12 numbers per line)")
    ev.add_argument("--gt-rows", required=True, metavar="i,j", help="0-based lines of image0 and image1 in the pose file")
    ev.set_defaults(func=_cmd_eval_two_view)
    return p


def _merge_shared(args) -> None:
    """Fold the options typed before the command into those after it (see _SHARED, _CONFIG)."""
    for name in _SHARED + _CONFIG:
        top = getattr(args, "top_" + name, None)
        if hasattr(args, "top_" + name):
            delattr(args, "top_" + name)
        if top is None:
            continue
        if name in _CONFIG and not getattr(args, "takes_config", False):
            cmd = " ".join(c for c in (args.command, getattr(args, "eval_command", None)) if c)
            raise ConfigError(f"--{name}: '{cmd or 'mona-vo'}' takes no config options")
        if name == "preset" and args.command == "demo":
            raise ConfigError("--preset before 'demo' is the speed preset, which demo does not take; "
                              "its scene preset goes after it: mona-vo demo --preset NAME")
        if name == "set":
            args.set = top + getattr(args, "set", [])
        elif not hasattr(args, name):
            setattr(args, name, top)
    args.quiet = getattr(args, "quiet", False)
    args.verbose = getattr(args, "verbose", False)
    if args.quiet and args.verbose:
        raise ConfigError("-q/--quiet and -v/--verbose exclude each other")


def _pipeline_config(args, *, speed_preset: bool = True):
    """The run's PipelineConfig: defaults, then --preset, then --config, then the options that
    name one key (--prompt, --device, --weights, --refine), then --set. Checked once, at the end.
    ``speed_preset`` False: the command's --preset is something else (demo's scene)."""
    from mona_vo.config import parse_set_options
    from mona_vo.presets import preset_config

    preset = (getattr(args, "preset", None) if speed_preset else None) or "default"
    overrides = {}
    for option, key in (("prompt", "masks.prompt"), ("device", "device"), ("weights", "weights"),
                        ("refine", "vo.refine")):
        if getattr(args, option, None) is not None:
            overrides[key] = getattr(args, option)
    overrides.update(parse_set_options(getattr(args, "set", None)))
    return preset_config(preset, getattr(args, "config", None), overrides)


def _cmd_run(args) -> int:
    from mona_vo.inputs import open_inputs

    # The inputs first, before the pipeline is imported: a bad one fails in about half a second.
    inputs = open_inputs(args.input, calib=args.calib, masks=args.masks, stride=args.stride,
                         max_frames=args.max_frames, gt_path=args.gt)
    from mona_vo.batch import clip_verdict, summary_from_report
    from mona_vo.run import run_opened

    report = run_opened(inputs, args.out, config=_pipeline_config(args), overlay=args.overlay,
                        progress=not args.quiet)
    fps = report["frames_per_second"].get("total")
    print(f"{report['frames']} frames, {report['keyframes']} keyframes, {fps:.1f} frames/s; "
          f"low-confidence frames: {len(report['low_confidence_frames'])}; wrote {args.out}/trajectory.txt")
    # The verdict batch would give (its default thresholds), so that one clip is judged alike.
    print(f"verdict: {clip_verdict(summary_from_report(report)).text()}")
    return 0


def _cmd_masks(args) -> int:
    from mona_vo.inputs import open_inputs

    inputs = open_inputs(args.input, masks=None, stride=args.stride, max_frames=args.max_frames)
    from mona_vo.run import masks_only_opened

    report = masks_only_opened(inputs, args.out, config=_pipeline_config(args),
                               progress=not args.quiet)
    print(f"{report['frames']} masks, {report['frames_per_second']} frames/s, mean coverage "
          f"{100 * report['mean_mask_coverage']:.1f} %; wrote {args.out}/masks/")
    return 0


def _check_scene(preset: str, seed: int, frames: int, width: int, height: int, option: str) -> None:
    """The generator's own check of the scene options, as a one-line error naming the option."""
    from data_tools.synthetic import SceneConfig

    options = {"preset": option, "seed": "--seed", "n_frames": "--frames", "width": "--size",
               "height": "--size"}
    try:
        SceneConfig(width=width, height=height, n_frames=frames, preset=preset, seed=seed)
    except ValueError as exc:
        text = str(exc)
        key = text.split(":")[0].replace("SceneConfig.", "")
        raise ConfigError(f"{options.get(key, key)}: {text.partition(': ')[2] or text}") from None


def _cmd_batch(args) -> int:
    from mona_vo.batch import RunOptions, batch_config_from_sets, run_batch, split_batch_sets

    # --set batch.* / verdict.* go to the batch's config, the rest to the pipeline's.
    pipeline_sets, batch_sets = split_batch_sets(getattr(args, "set", None) or [])
    args.set = pipeline_sets
    if args.cpus_per_video is not None:
        batch_sets["batch.cpus_per_video"] = str(args.cpus_per_video)
    options = RunOptions(config=_pipeline_config(args), calib=args.calib, masks=args.masks,
                         stride=args.stride, max_frames=args.max_frames, overlay=args.overlay)
    result = run_batch(args.inputs, args.out, options=options, config=batch_config_from_sets(batch_sets),
                       address=args.address, progress=not args.quiet)
    rows = result.rows
    count = {s: sum(r.get("status") == s for r in rows) for s in ("ok", "skipped", "failed")}
    usable = sum(bool(r.get("usable")) for r in rows)
    print(f"{len(rows)} inputs: {count['ok']} ok, {count['skipped']} skipped, {count['failed']} failed; "
          f"{usable} usable; {result.seconds:.1f} s (Ray start {result.ray_start_seconds:.1f} s); "
          f"wrote {result.out_dir}/batch.csv and index.html")
    for r in result.failed:
        print(f"  failed {r['name']}: {r.get('reason')}")
    return 1 if result.failed else 0


def _cmd_demo(args) -> int:
    import tempfile

    from mona_vo.run import demo

    w, h = _parse_size(args.size)
    _check_scene(args.preset, args.seed, args.frames, w, h, "--preset")
    config = _pipeline_config(args, speed_preset=False)
    out_dir = args.out or tempfile.mkdtemp(prefix="mona-vo-demo-")
    out = demo(out_dir, preset=args.preset, seed=args.seed, n_frames=args.frames, width=w,
               height=h, config=config, progress=not args.quiet)
    print(f"synthetic '{out['preset']}' scene, seed {out['seed']}, {out['frames']} frames "
          f"{out['size'][0]}x{out['size'][1]}, camera path {out['path_length']:.2f} m")
    for variant, label in (("none", "no masks"), ("mona", "MONA masks"), ("gt", "GT masks")):
        r = out["results"][variant]
        print(f"  {label:11s} ATE {r['ate']:.4f} m = {r['ate_percent_of_path']:.3f} % of path   "
              f"RPE {r['rpe_trans']:.4f} m / {r['rpe_rot_deg']:.3f} deg   {r['frames_per_second']:.1f} frames/s")
    print(f"outputs in {out['out_dir']}: input/ (frames, GT masks and poses), none/, mona/, gt/ (one run each)")
    print(f"open {out['out_dir']}/mona/trajectory.png (the MONA-masked trajectory against GT)")
    return 0


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size expects WIDTHxHEIGHT, e.g. 1024x436, not '{text}'") from None
    if w < 64 or h < 32:
        raise ConfigError(f"--size {text} is too small (at least 64x32)")
    return w, h


def _cmd_bench(args) -> int:
    from eval.bench import bench, format_row, peak_memory_mb, summary_table
    from eval.vo_bench import parse_seeds

    w, h = _parse_size(args.size)
    presets = [s.strip() for s in args.presets.split(",") if s.strip()]
    seeds = parse_seeds(args.seeds)
    for preset in presets or [""]:
        _check_scene(preset, seeds[0], args.frames, w, h, "--presets")
    rows = bench(presets, seeds, n_frames=args.frames, width=w,
                 height=h, config=_pipeline_config(args), peer=not args.no_peer,
                 on_row=lambda r: print(format_row(r), flush=True))
    print()
    print(summary_table(rows))
    print(f"peak memory {peak_memory_mb():.0f} MB; machine: {_machine()}")
    if args.out:
        from data_tools.atomic import write_text_atomic

        write_text_atomic(args.out, json.dumps(rows, indent=2, default=float) + "\n")
    return 0


def _machine() -> str:
    import os
    import platform

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{cores} cores, {platform.machine()}, {platform.python_implementation()} {platform.python_version()}"


def _frame_range(text: str | None, n: int) -> slice:
    """``--frames A:B`` -> slice(A, B) within n rows; an empty or malformed range is a
    ConfigError naming the option."""
    if text is None:
        return slice(0, n)
    a, sep, b = text.partition(":")
    try:
        lo = int(a) if a.strip() else 0
        hi = int(b) if b.strip() else n
    except ValueError:
        lo = hi = -1
    if not sep or lo < 0 or hi > n or hi - lo < 3:
        raise ConfigError(f"--frames expects A:B with 0 <= A, B <= {n} (the estimate's rows) and "
                          f"at least 3 poses, got '{text}'")
    return slice(lo, hi)


def _cmd_eval_traj(args) -> int:
    from eval.metrics import Trajectory, evaluate_trajectory

    if args.format == "tum":
        from data_tools.tum import read_tum_trajectory

        gt = Trajectory(*read_tum_trajectory(args.gt))
        t, T = read_tum_trajectory(args.est)
        part = _frame_range(args.frames, len(t))
        est = Trajectory(t[part], T[part])
        m = evaluate_trajectory(gt, est, align=args.align, max_diff=args.max_diff,
                                scale_window=args.scale_window)
    else:
        from data_tools.kitti import read_kitti_poses

        gt_poses, est_poses = read_kitti_poses(args.gt), read_kitti_poses(args.est)
        part = _frame_range(args.frames, len(est_poses))
        if args.frames is not None and len(gt_poses) != len(est_poses):
            raise ConfigError("--frames with --format kitti needs files of equal length (poses are "
                              "matched by line)")
        gt = Trajectory.from_poses(gt_poses[part])
        est = Trajectory.from_poses(est_poses[part])
        m = evaluate_trajectory(gt, est, align=args.align, associate=False,
                                scale_window=args.scale_window)
    d = m.to_dict()
    keys = ("ate", "rpe_trans", "rpe_rot_deg", "n_matched", "scale", "path_length",
            "ate_percent_of_path", "alignment", "heading_deg", "window_scales")
    print(json.dumps({k: d[k] for k in keys if k in d}))
    return 0


def _read_draws(folder: str) -> list[dict]:
    path = Path(folder) / "draws.json"
    try:
        summary = json.loads(path.read_text())["summary"]
    except FileNotFoundError:
        raise InputError(f"{path}: not found (run the command with --draws first)") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: not a draws.json written by mona-vo ({exc})") from None
    return summary


def _cmd_eval_compare(args) -> int:
    from eval.harness import compare_draws

    rows = compare_draws(_read_draws(args.base), _read_draws(args.new))
    if not rows:
        raise InputError(f"{args.base} and {args.new} share no sequence, variant and draw")
    print("| sequence | variant | part | draws | base mean | new mean | base median | new median | "
          "new - base (mean +- se) | new lower |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        se = "-" if r["diff_se"] is None else f"{r['diff_se']:.4f}"
        print(f"| {r['sequence']} | {r['variant']} | {r['part']} | {r['draws']} | {r['base_mean']:.4f} | "
              f"{r['new_mean']:.4f} | {r['base_median']:.4f} | {r['new_median']:.4f} | "
              f"{r['diff_mean']:+.4f} +- {se} | {r['lower']} of {r['draws']} |")
    return 0


def _cmd_eval_masks(args) -> int:
    from eval.mask_metrics import evaluate_mask_folders

    m = evaluate_mask_folders(args.pred, args.gt)
    print(json.dumps({"J_mean": m.J_mean, "F_mean": m.F_mean, "n_frames": m.n_frames}))
    return 0


def _print_summary(rows) -> None:
    from eval.harness import summarize

    for s in summarize(rows):
        ate = "-" if s["ate"] is None else f"{s['ate']:.4f}"
        rpe = "-" if s["rpe_trans"] is None else f"{s['rpe_trans']:.4f} m / {s['rpe_rot_deg']:.3f} deg"
        parts = "".join(f"  {p} {'-' if v is None else f'{v:.4f}'}"
                        for p, v in (s.get("parts") or {}).items())
        print(f"{s['variant']:15s} ATE {ate}  RPE {rpe}  ok {s['ok']}/{s['sequences']}{parts}")
    for r in rows:
        if r.get("status") != "ok":
            print(f"  {r['sequence']} [{r['variant']}]: {r.get('status')}")
        elif r.get("warning"):
            print(f"  {r['sequence']} [{r['variant']}]: warning: {r['warning']}")


def _check_workers(workers: int) -> None:
    if workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")


def _cmd_config(args) -> int:
    from mona_vo.config import to_yaml

    cfg = _pipeline_config(args)
    text = (f"# mona-vo {__version__} configuration: every key, its meaning and [its allowed values].\n"
            f"# Load it with --config FILE (then --set KEY=VALUE overrides single keys).\n"
            + to_yaml(cfg))
    if args.out:
        from data_tools.atomic import write_text_atomic

        write_text_atomic(args.out, text)
        print(f"wrote {args.out}")
    else:
        sys.stdout.write(text)
    return 0


def _cmd_eval_sintel(args) -> int:
    from eval.datasets import sintel_sequences
    from eval.variants import parse_variants

    _check_workers(args.workers)
    variants = parse_variants(args.variants)
    if "gt" in variants and not args.masks_root:
        raise ConfigError("variant 'gt' needs --masks-root (folder of <seq>/frame_XXXX.png masks)")
    # The dataset before the pipeline is imported (as run opens its inputs first).
    seqs = sintel_sequences(args.root, pass_=args.pass_, masks_root=args.masks_root,
                            names=args.seqs.split(",") if args.seqs else None)
    config = _pipeline_config(args)
    return _evaluate(args, config, seqs, variants, {"dataset": "sintel", "pass": args.pass_})


def _cmd_eval_tum(args) -> int:
    from data_tools.calibration import parse_calibration
    from eval.datasets import TUM_MAX_DIFF, tum_sequences
    from eval.variants import parse_variants

    _check_workers(args.workers)
    variants = parse_variants(args.variants)
    if "gt" in variants:
        raise ConfigError("TUM-layout folders carry no moving-object masks: variant 'gt' is not available")
    estimate = args.calib == "estimate"
    calib = parse_calibration(args.calib) if args.calib and not estimate else None
    max_diff = TUM_MAX_DIFF if args.max_diff is None else args.max_diff
    if not (math.isfinite(max_diff) and max_diff > 0):
        raise ConfigError(f"--max-diff must be a positive number of seconds, got {args.max_diff!r}")
    # The folder before the pipeline is imported (as run opens its inputs first).
    seqs = tum_sequences(args.root, calib=calib, max_diff=max_diff, folder_calib=not estimate)
    config = _pipeline_config(args)
    # The tolerance and the camera change the results of finished runs, so they are part of
    # what a run is.
    return _evaluate(args, config, seqs, variants,
                     {"dataset": "tum", "max_diff": max_diff,
                      "calib": "estimate" if estimate else _camera_numbers(calib) if calib else ""})


def _camera_numbers(intr) -> list[float]:
    """fx, fy, cx, cy and, for a distorted lens, its coefficients: what a run's camera is."""
    numbers = [intr.fx, intr.fy, intr.cx, intr.cy]
    lens = getattr(intr, "distortion", None)
    return numbers + [float(v) for v in lens.coeffs] if lens is not None else numbers


def _evaluate(args, config, seqs, variants, extra_hash: dict) -> int:
    """The harness on these sequences, once or once per --draws value; prints the summary."""
    from eval.harness import evaluate, evaluate_draws, parse_draws, parse_parts

    kwargs = dict(config=config, workers=args.workers, address=args.address,
                  extra_hash=extra_hash, progress=not args.quiet, parts=parse_parts(args.parts))
    if args.draws:
        by_draw = evaluate_draws(seqs, variants, args.out, parse_draws(args.draws, config), **kwargs)
        rows = [r for rows in by_draw.values() for r in rows]
        _print_draws(by_draw)
        print(f"wrote {args.out}/draws.md")
    else:
        rows = evaluate(seqs, variants, args.out, **kwargs)
        _print_summary(rows)
        print(f"wrote {args.out}/results.md")
    return 0 if all(r.get("status") == "ok" for r in rows) else 1


def _print_draws(by_draw) -> None:
    from eval.harness import summarize_draws

    for s in summarize_draws(by_draw):
        ate = "-" if s["ate_mean"] is None else \
            f"mean {s['ate_mean']:.4f} median {s['ate_median']:.4f} [{s['ate_min']:.4f}, {s['ate_max']:.4f}]"
        print(f"{s['sequence']} [{s['variant']}] ATE {ate}  ok {s['ok']}/{s['draws']}")
        for part, p in (s.get("parts") or {}).items():
            if p["ate_mean"] is not None:
                print(f"  part {part}: ATE mean {p['ate_mean']:.4f} median {p['ate_median']:.4f}  "
                      f"ok {p['ok']}/{len(p['ate'])}")


def _cmd_eval_flow(args) -> int:
    from eval.flow_eval import evaluate_flow

    r = evaluate_flow(args.image0, args.image1, args.gt, occlusions=args.occlusions,
                      invalid=args.invalid, flow=args.flow, weights=args.weights, device=args.device)
    print(json.dumps(r.to_dict()))
    return 0


def _cmd_eval_two_view(args) -> int:
    from eval.two_view_eval import evaluate_two_view

    try:
        rows = tuple(int(v) for v in args.gt_rows.split(","))
    except ValueError:
        rows = ()
    if len(rows) != 2:
        raise ConfigError(f"--gt-rows must be two line numbers i,j, got '{args.gt_rows}'")
    r = evaluate_two_view(args.image0, args.image1, args.calib, args.gt_poses, rows)
    print(json.dumps(r.to_dict()))
    return 0


def main(argv: list[str] | None = None) -> int:
    import signal

    # Batch schedulers stop jobs with SIGTERM: take the Ctrl-C path so temporaries are removed.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None or (args.command == "eval" and args.eval_command is None):
        parser.print_help() if args.command is None else parser.parse_args([args.command, "--help"])
        return 1
    try:
        _merge_shared(args)
        logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                            format="%(levelname)s %(name)s: %(message)s")
        return args.func(args)
    except MonaVoError as exc:
        print(f"mona-vo: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mona-vo: interrupted; finished outputs are intact, partial ones were removed", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
