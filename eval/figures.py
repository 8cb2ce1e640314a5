"""Pictures of mona-vo on the real clips, for the README: ``python -m eval.figures --out docs``.

Two kinds, each written as a PNG under 1 MB:

``<clip>_prompts.png``
    The layout of the MONA paper's Fig. 3 on a real clip: a few frames (columns) x the three
    prompt modes (rows) -- points-only prompts, every detector box (raw boxes), the boxes kept
    by the adaptive filter (the method). Each cell is :func:`data_tools.overlay.draw_overlay` of
    that mode's :class:`mona_vo.masks.MaskFrame`: the mask tinted red, dynamic points red and
    static ones green, every detector box thin grey, the prompt boxes yellow. The masks are
    computed over the whole clip (the masker needs its look-ahead) with ``MaskConfig(prompt=...)``
    for each mode, the shown frames kept.

``bonn_trajectory.png``
    Camera centres of the Bonn clip, top and side views: the ground truth against the ``none``
    and ``mona`` runs of ``mona-vo eval tum --root .../bonn_crowd --variants none,mona --out
    runs/bonn``, each Sim(3)-aligned to the GT samples nearest its timestamps (for drawing; the
    numbers are the harness's). Run folders that hold no trajectory are reported, not drawn.

The clips are read from the shared real data (``--data``, default ``../shared/data`` beside the
project); nothing of them is written into the repository except these downscaled pictures.
"""
from __future__ import annotations

import argparse
import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np

from mona_vo.errors import InputError

log = logging.getLogger(__name__)

PROMPT_ROWS = (("points", "points-only prompts"),
               ("raw-boxes", "raw boxes"),
               ("boxes", "filtered boxes (MONA)"))
MAX_PNG_BYTES = 1_000_000      # each picture stays under this, bytes
TARGET_PNG_BYTES = 600_000     # above this a lossless PNG is redrawn with a 256-colour palette
LABEL_WIDTH_PX = 130           # strip: white margin left of the cells for the row labels
GAP_PX = 4                     # strip: white gap after each cell, right and below
TITLE_HEIGHT_PX = 44           # strip: title and legend lines above the cells
COLUMN_LABEL_HEIGHT_PX = 18    # strip: frame names above the cells
DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass(frozen=True)
class Clip:
    """A real clip for a prompt strip: its frame folder (relative to the data root)."""

    name: str        # output name: docs/<name>_prompts.png
    folder: str      # frame folder below the data root
    title: str       # figure title
    calib: str = ""  # calibration file below the data root ("" = the masker's guess)


CLIPS = (
    Clip("davis_car-shadow", "davis2016/JPEGImages/480p/car-shadow", "DAVIS-2016 car-shadow"),
    Clip("davis_dog", "davis2016/JPEGImages/480p/dog", "DAVIS-2016 dog"),
    Clip("sintel_alley_1", "sintel_clip_alley/training/clean/alley_1",
         "MPI Sintel alley_1 (clean), frames 1-25"),
    Clip("bonn_crowd", "bonn_crowd/rgb", "Bonn RGB-D Dynamic rgbd_bonn_crowd, 53 frames",
         "bonn_crowd/calib.txt"),
)


# ---------------------------------------------------------------------------------------- drawing
def _label(image: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45,
           color=(0, 0, 0), thickness: int = 1) -> None:
    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, thickness, cv2.LINE_AA)


def _wrap(text: str, width: int) -> list[str]:
    """Greedy word wrap to lines of at most ``width`` characters (longer words stay whole)."""
    lines: list[str] = []
    for word in text.split():
        if lines and len(lines[-1]) + 1 + len(word) <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return lines or [""]


def draw_strip(images: Sequence[np.ndarray], rows: Sequence[Sequence], row_labels: Sequence[str],
               col_labels: Sequence[str] | None = None, *, cell_width: int = 300,
               title: str = "") -> np.ndarray:
    """A grid picture: one column per image, one row per entry of ``rows``.

    images:     (H, W, 3) uint8 RGB frames, one size.
    rows:       per row, one :class:`mona_vo.masks.MaskFrame` (or None: the plain frame) per image.
    row_labels: text left of each row; col_labels: text above each column (default none).
    cell_width: width of each cell in pixels (frames are downscaled after drawing, INTER_AREA).
    Returns (H', W', 3) uint8 RGB, W' = LABEL_WIDTH_PX + columns x (cell_width + GAP_PX),
    H' = top + rows x (cell height + GAP_PX), top = TITLE_HEIGHT_PX with a title (GAP_PX
    without) + COLUMN_LABEL_HEIGHT_PX with column labels; cell height = cell_width x H / W.
    """
    from data_tools.overlay import draw_overlay

    if not images:
        raise ValueError("draw_strip needs at least one image")
    if any(len(r) != len(images) for r in rows) or len(row_labels) != len(rows):
        raise ValueError("every row needs one entry per image, and one label per row")
    h, w = images[0].shape[:2]
    cell_h = max(int(round(h * cell_width / w)), 1)
    left = LABEL_WIDTH_PX
    top = (TITLE_HEIGHT_PX if title else GAP_PX) + (COLUMN_LABEL_HEIGHT_PX if col_labels else 0)
    out = np.full((top + len(rows) * (cell_h + GAP_PX), left + len(images) * (cell_width + GAP_PX), 3),
                  255, np.uint8)
    if title:
        _label(out, title, (6, 18), 0.55, thickness=1)
        _label(out, "red tint: mask   red/green dots: dynamic/static points   grey: all boxes   "
                    "yellow: prompt boxes", (6, 36), 0.38, color=(70, 70, 70))
    for c, image in enumerate(images):
        x = left + c * (cell_width + GAP_PX)
        if col_labels:
            _label(out, col_labels[c], (x, top - 5), 0.4)
        for r, row in enumerate(rows):
            mf = row[c]
            drawn = draw_overlay(image, None if mf is None else mf.mask, mf)
            y = top + r * (cell_h + GAP_PX)
            out[y:y + cell_h, x:x + cell_width] = cv2.resize(drawn, (cell_width, cell_h),
                                                             interpolation=cv2.INTER_AREA)
    for r, text in enumerate(row_labels):
        y = top + r * (cell_h + GAP_PX) + cell_h // 2
        lines = _wrap(text, 14)
        for k, line in enumerate(lines):
            _label(out, line, (6, y + 16 * k - 8 * (len(lines) - 1)), 0.45)
    return out


def shown_positions(n_frames: int, n_shown: int = 4) -> list[int]:
    """Positions of ``n_shown`` frames spread over a clip of ``n_frames`` (ends left out, where
    the masker has least context)."""
    if n_frames <= n_shown:
        return list(range(n_frames))
    return sorted({int(round(v)) for v in np.linspace(0.08, 0.92, n_shown) * (n_frames - 1)})


def masks_by_mode(frames: Iterable, keep: Iterable[int], *, modes: Sequence[str] = ("points", "raw-boxes", "boxes"),
                  intrinsics=None, config=None) -> dict[str, dict[int, object]]:
    """MONA's output for every prompt mode: ``{mode: {frame index: MaskFrame}}`` for the frame
    indices in ``keep``. ``frames``: a re-iterable source of objects with ``index`` and ``image``
    (e.g. :func:`data_tools.frames.open_frames`) or a list of ``(index, image)`` pairs; each
    mode runs the masker over all of it. ``config``: a base :class:`mona_vo.masks.MaskConfig`."""
    from dataclasses import replace

    from mona_vo.masks import MaskConfig, compute_masks

    keep = set(keep)
    base = config or MaskConfig()
    out: dict[str, dict[int, object]] = {}
    for mode in modes:
        cfg = replace(base, prompt=mode)
        out[mode] = {mf.index: mf for mf in compute_masks(frames, cfg, intrinsics) if mf.index in keep}
    return out


def prompt_strip(frames: Sequence, *, n_shown: int = 4, cell_width: int = 300, title: str = "",
                 intrinsics=None, config=None) -> np.ndarray:
    """The Fig. 3 picture of a clip: ``n_shown`` frames x the three prompt modes.

    frames: a re-iterable frame source with ``len()`` (objects with ``index``, ``name``,
    ``image``; e.g. :func:`data_tools.frames.open_frames`) or a list of ``(index, image)`` pairs.
    Returns (H', W', 3) uint8 RGB (see :func:`draw_strip`)."""
    items = list(frames)            # decoded once; the clips here are tens of frames
    pairs = [(f.index, f.image) if not isinstance(f, tuple) else f for f in items]
    names = [getattr(f, "name", str(i)) for f, (i, _) in zip(items, pairs)]
    pos = shown_positions(len(pairs), n_shown)
    indices = [pairs[p][0] for p in pos]
    result = masks_by_mode(pairs, indices, modes=[m for m, _ in PROMPT_ROWS],
                           intrinsics=intrinsics, config=config)
    rows = [[result[mode].get(i) for i in indices] for mode, _ in PROMPT_ROWS]
    return draw_strip([pairs[p][1] for p in pos], rows, [label for _, label in PROMPT_ROWS],
                      [names[p] if names[p].startswith("frame") else f"frame {names[p]}" for p in pos],
                      cell_width=cell_width, title=title)


def write_png(path: str | Path, image_rgb: np.ndarray, max_bytes: int = MAX_PNG_BYTES,
              target_bytes: int = TARGET_PNG_BYTES) -> Path:
    """Write (H, W, 3) uint8 RGB as a PNG, atomically: lossless when it takes at most
    ``target_bytes``, else with a 256-colour palette (PIL's median cut, Floyd-Steinberg
    dithering); ValueError if even that exceeds ``max_bytes``."""
    from PIL import Image

    from data_tools.atomic import write_bytes_atomic

    path = Path(path)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_PNG_COMPRESSION, 9])
    data = buf.tobytes() if ok else b""
    if not ok or len(data) > target_bytes:
        pal = Image.fromarray(image_rgb).quantize(colors=256, method=Image.Quantize.MEDIANCUT,
                                                  dither=Image.Dither.FLOYDSTEINBERG)
        bio = io.BytesIO()
        pal.save(bio, format="PNG", optimize=True)
        data = bio.getvalue()
    if len(data) > max_bytes:
        raise ValueError(f"{path}: {len(data)} bytes even with a palette; draw it smaller")
    write_bytes_atomic(path, data)
    return path


# ----------------------------------------------------------------------------------- trajectories
def _nearest(gt_ts: np.ndarray, ts: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``ts``, the index of the nearest GT timestamp, and whether it is within
    ``max_diff`` seconds."""
    j = np.clip(np.searchsorted(gt_ts, ts), 1, len(gt_ts) - 1)
    j = np.where(np.abs(gt_ts[j - 1] - ts) <= np.abs(gt_ts[j] - ts), j - 1, j)
    return j, np.abs(gt_ts[j] - ts) <= max_diff


def plot_trajectories(path: str | Path, gt_ts: np.ndarray, gt_xyz: np.ndarray,
                      estimates: dict[str, tuple[np.ndarray, np.ndarray]], *, title: str = "",
                      max_diff: float = 0.01) -> Path:
    """Top (x-z) and side (z, -y) views of the GT camera centres and several estimates, each
    Sim(3)-aligned to the GT samples nearest its timestamps.

    gt_ts (N,) seconds, gt_xyz (N, 3) metres, world frame; estimates: label -> ((M,) seconds,
    (M, 3) camera centres, any scale). An estimate whose centres do not move (no translation
    was estimated) is drawn as one point at the GT mean.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from data_tools.atomic import atomic_path
    from eval.plots import align_sim3

    gt_ts, gt_xyz = np.asarray(gt_ts, float), np.asarray(gt_xyz, float)
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.2))
    colors = ("tab:orange", "tab:blue", "tab:green", "tab:purple")
    span = (gt_ts.min(), gt_ts.max())
    shown_gt = np.zeros(len(gt_ts), bool)
    drawn = []
    for (label, (ts, xyz)), color in zip(estimates.items(), colors):
        j, ok = _nearest(gt_ts, np.asarray(ts, float), max_diff)
        xyz = np.asarray(xyz, float)[ok]
        g = gt_xyz[j[ok]]
        shown_gt[j[ok]] = True
        if len(xyz) >= 3 and np.ptp(xyz, axis=0).max() > 1e-12:
            aligned = align_sim3(xyz, g)
        else:
            aligned = np.repeat(g.mean(0, keepdims=True), max(len(xyz), 1), axis=0)
        drawn.append((label, aligned, color))
    sel = shown_gt if shown_gt.any() else (gt_ts >= span[0])
    views = (("top view", 0, 2, "x (m)", "z (m)"), ("side view", 2, 1, "z (m)", "up, -y (m)"))
    for ax, (name, i, k, xl, yl) in zip(axes, views):
        sign = -1.0 if k == 1 else 1.0
        ax.plot(gt_xyz[sel, i], sign * gt_xyz[sel, k], "-", color="0.45", lw=2.2, label="ground truth")
        ax.plot(gt_xyz[sel][:1, i], sign * gt_xyz[sel][:1, k], "o", color="0.2", ms=5, label="start")
        for label, a, color in drawn:
            style = "-" if len(a) > 1 and np.ptp(a, axis=0).max() > 0 else "*"
            ax.plot(a[:, i], sign * a[:, k], style, color=color, lw=1.3, ms=10, label=label)
        ax.set_title(name)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path


def bonn_trajectory_figure(out_path: str | Path, runs_dir: str | Path, gt_path: str | Path, *,
                           sequence: str = "bonn_crowd", variants: Sequence[str] = ("none", "mona"),
                           title: str = "") -> Path:
    """``plot_trajectories`` of the runs ``runs_dir/<variant>/<sequence>/trajectory.txt`` written
    by ``mona-vo eval tum``, labelled with each run's ATE from its result.json."""
    from data_tools.tum import read_tum_trajectory

    runs_dir = Path(runs_dir)
    gt_ts, gt_poses = read_tum_trajectory(gt_path)
    estimates = {}
    for variant in variants:
        run = runs_dir / variant / sequence
        traj = run / "trajectory.txt"
        if not traj.is_file():
            raise InputError(f"{traj}: missing; run `mona-vo eval tum --root <bonn_crowd> "
                             f"--variants {','.join(variants)} --out {runs_dir}` first")
        ts, poses = read_tum_trajectory(traj)
        label = variant
        try:
            row = json.loads((run / "result.json").read_text())
        except (OSError, ValueError):
            row = {}
        if row.get("ate") is not None:
            label += f": ATE {1000 * row['ate']:.1f} mm"
        elif row.get("status", "ok") != "ok":
            label += ": no ATE (run failed, see result.json)"
        if row.get("low_confidence"):
            label += f"; {row['low_confidence']} of {row.get('frames', '?')} frames low-confidence"
        estimates[label] = (ts, poses[:, :3, 3])
    return plot_trajectories(out_path, gt_ts, gt_poses[:, :3, 3], estimates, title=title)


# ------------------------------------------------------------------------------------------ main
def make_figures(out_dir: str | Path, *, data: str | Path = DEFAULT_DATA,
                 runs: str | Path = "runs", clips: Sequence[str] | None = None,
                 cell_width: int = 300) -> list[Path]:
    """Every picture: the prompt strip of each clip in :data:`CLIPS` (or those named) and the
    Bonn trajectory of the ``mona-vo eval tum`` runs in ``runs/bonn``. Returns the files written."""
    from data_tools.calibration import parse_calibration
    from data_tools.frames import open_frames

    data, runs, out_dir = Path(data), Path(runs), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for clip in CLIPS:
        if clips is not None and clip.name not in clips:
            continue
        folder = data / clip.folder
        if not folder.is_dir():
            log.warning("%s: absent, no %s picture", folder, clip.name)
            continue
        source = open_frames(folder)
        intr = parse_calibration(str(data / clip.calib), source.width, source.height) if clip.calib else None
        image = prompt_strip(source, cell_width=cell_width, title=clip.title, intrinsics=intr)
        written.append(write_png(out_dir / f"{clip.name}_prompts.png", image))
        log.info("wrote %s", written[-1])
    gt = data / "bonn_crowd" / "groundtruth.txt"
    bonn_runs = runs / "bonn"
    if clips is None or "bonn_trajectory" in clips:
        if not gt.is_file():
            log.warning("%s: absent, no Bonn trajectory picture", gt)
        elif not bonn_runs.is_dir():
            log.warning("%s: absent, no Bonn trajectory picture; make it with `mona-vo eval tum "
                        "--root %s --variants none,mona --out %s`", bonn_runs, gt.parent, bonn_runs)
        else:
            written.append(bonn_trajectory_figure(
                out_dir / "bonn_trajectory.png", bonn_runs, gt,
                title="Bonn rgbd_bonn_crowd, 53 frames: mona-vo eval tum, Sim(3)-aligned"))
            log.info("wrote %s", written[-1])
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m eval.figures", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the PNGs (e.g. docs)")
    p.add_argument("--data", default=str(DEFAULT_DATA), help="shared real-data root (default ../shared/data)")
    p.add_argument("--runs", default="runs", help="folder holding the eval tum runs (bonn/)")
    p.add_argument("--only", help="comma-separated picture names: " + ", ".join(c.name for c in CLIPS)
                   + ", bonn_trajectory")
    p.add_argument("--cell-width", type=int, default=300, help="width of one strip cell, pixels")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from mona_vo.errors import MonaVoError

    try:
        files = make_figures(args.out, data=args.data, runs=args.runs,
                             clips=args.only.split(",") if args.only else None,
                             cell_width=args.cell_width)
    except MonaVoError as exc:
        import sys

        print(f"eval.figures: error: {exc}", file=sys.stderr)
        return 1
    for f in files:
        print(f"{f}  {f.stat().st_size // 1024} KB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
