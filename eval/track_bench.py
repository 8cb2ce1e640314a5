"""The point tracker against the renderer's truth, on generated scenes.

A track seeded where the VO seeds one (the same texture score and grid,
:mod:`mona_vo.point_selection`) on static surface is followed by the product's tracker back end;
at every later frame its true place is its start pixel moved with the renderer's depth and poses
(:func:`true_pixels`). The error is split along and across the point's true image motion of that
frame: motion blur smears a corner along the motion, and there a window tracker is pinned down
less well than across it. Rows give, per sequence, the median error after one frame and after
``max_age`` frames in each direction, the median image motion (px per frame) and the share of the
seeded tracks still followed at ``max_age``.

``python -m eval.track_bench --presets mixed --seeds 3,219 --frames 24 --size 640x272``; with
``--effects both`` each sequence is also tracked on its frames before the image effects (blur,
noise, exposure, JPEG), the same geometry, so the two rows tell what the effects cost.
"""
from __future__ import annotations

import argparse
import sys

import cv2
import numpy as np
from tqdm import tqdm

from data_tools.synthetic import SceneConfig, SyntheticScene
from eval.vo_bench import parse_seeds
from mona_vo.conventions import Intrinsics, pixels_in_mask, reproject, transform_points, unproject
from mona_vo.errors import MonaVoError
from mona_vo.point_selection import seed_points
from mona_vo.tracking import TRACKERS, Tracker, to_gray
from mona_vo.vo import VOConfig

VO = VOConfig()   # the VO's default point selection, so the bench tracks what the VO tracks
EDGE_REL = 0.05   # a start pixel whose 5 x 5 neighbourhood spans more depth than this share of its
                  # own is on a depth edge, where no single true place exists; it is not seeded


def true_pixels(depth0: np.ndarray, uv0: np.ndarray, T0: np.ndarray, T: np.ndarray,
                intr: Intrinsics) -> np.ndarray:
    """(N, 2) true pixels in the view T (camera-to-world) of start pixels uv0 (N, 2) seen at
    T0, whose depths are read from depth0 (H, W) at the nearest pixel centre."""
    h, w = depth0.shape
    x = np.clip(np.rint(uv0[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.rint(uv0[:, 1]).astype(int), 0, h - 1)
    world = transform_points(T0, unproject(uv0, depth0[y, x], intr))
    return reproject(T, world, intr)[0]


def seedable(depth: np.ndarray, object_id: np.ndarray, uv: np.ndarray, margin: int = 5) -> np.ndarray:
    """(N,) bool: start pixels on static surface, ``margin`` px clear of any mover and off depth
    edges (:data:`EDGE_REL`)."""
    k = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    near_mover = cv2.dilate((object_id > 0).astype(np.uint8), k) > 0
    kernel = np.ones((5, 5), np.uint8)
    spread = cv2.dilate(depth, kernel) - cv2.erode(depth, kernel)
    edge = spread > EDGE_REL * depth
    return ~pixels_in_mask(near_mover | edge, uv)


def measure_sequence(rendered: list, poses: np.ndarray, intr: Intrinsics, make_tracker,
                     starts: list[int], max_age: int) -> dict:
    """Errors of one sequence (see the module docstring). ``rendered``: the scene's
    RenderedFrame list; ``make_tracker``: a callable returning a fresh :class:`Tracker`."""
    along = {1: [], max_age: []}
    across = {1: [], max_age: []}
    signed = []   # along-motion error with its sign, after max_age frames: a common slide shows
    flow, seeded, alive = [], 0, 0
    for k0 in starts:
        if k0 + max_age >= len(rendered):
            continue
        r0 = rendered[k0]
        uv = seed_points(to_gray(r0.image), VO.grid_size, VO.point_score, VO.point_min_score,
                         VO.point_quality)
        uv = uv[seedable(r0.depth, r0.object_id, uv)].astype(np.float64)
        if not len(uv):
            continue
        tracker: Tracker = make_tracker()
        tracker.step(r0.image)
        ids = tracker.add_points(uv)
        seeded += len(uv)
        prev_true = uv
        for a in range(1, max_age + 1):
            k = k0 + a
            upd = tracker.step(rendered[k].image)
            truth = true_pixels(r0.depth, uv, poses[k0], poses[k], intr)
            motion = truth - prev_true
            prev_true = truth
            flow.append(np.median(np.linalg.norm(motion, axis=1)))
            live = upd.ids[upd.visible]
            i = np.searchsorted(ids, live)
            if a in along and len(live):
                e = np.asarray(upd.points, np.float64)[upd.visible] - truth[i]
                n = motion[i] / np.maximum(np.linalg.norm(motion[i], axis=1, keepdims=True), 1e-9)
                e_along = np.sum(e * n, axis=1)
                along[a].extend(np.abs(e_along))
                if a == max_age:
                    signed.extend(e_along)
                across[a].extend(np.abs(e[:, 0] * n[:, 1] - e[:, 1] * n[:, 0]))
            if a == max_age:
                alive += len(live)

    def med(v):
        return float(np.median(v)) if len(v) else float("nan")

    return {"tracks": seeded, "flow_px": med(flow), "followed": alive / seeded if seeded else float("nan"),
            "along_1": med(along[1]), "across_1": med(across[1]),
            "along_end": med(along[max_age]), "across_end": med(across[max_age]),
            "along_signed_end": med(signed),
            "max_age": max_age}


def benchmark(presets, seeds, *, n_frames=24, width=640, height=272, effects=("on",),
              tracker: str = "lk", starts=(0, 8), max_age=8, quiet=False) -> list[dict]:
    """One row per preset, seed and effects setting (``on``: the frames as rendered, ``off``:
    before the image effects)."""
    def make():
        return TRACKERS.create(tracker)

    rows = []
    jobs = [(p, s, e) for p in presets for s in seeds for e in effects]
    for preset, seed, eff in tqdm(jobs, desc="track bench", unit="seq", disable=quiet):
        scene = SyntheticScene(SceneConfig(width=width, height=height, n_frames=n_frames,
                                           preset=preset, seed=seed, effects=eff == "on"))
        rendered = list(scene)
        row = measure_sequence(rendered, scene.poses(), scene.intrinsics, make, list(starts), max_age)
        rows.append({"preset": preset, "seed": seed, "effects": eff, "tracker": tracker, **row})
    return rows


def format_rows(rows: list[dict]) -> str:
    head = ("preset        seed effects  flow px/frame  tracks  along / across px: after 1 frame"
            "   after N                  signed along  followed")
    lines = [head]
    for r in rows:
        ratio = r["along_1"] / r["across_1"] if r["across_1"] > 0 else float("nan")
        lines.append(f"{r['preset']:<12} {r['seed']:>5} {r['effects']:<7} {r['flow_px']:>10.1f}  "
                     f"{r['tracks']:>6}  {r['along_1']:6.2f} / {r['across_1']:4.2f} ({ratio:4.1f}x)"
                     f"   {r['along_end']:5.2f} / {r['across_end']:4.2f} (N={r['max_age']})"
                     f"   {r['along_signed_end']:+6.2f}   {r['followed']:5.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", default="mixed")
    ap.add_argument("--seeds", default="0-5")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--size", default="640x272")
    ap.add_argument("--effects", choices=("on", "off", "both"), default="on",
                    help="track the frames as rendered (on), before the image effects (off), or both")
    ap.add_argument("--starts", default="0,8", help="frames where tracks are seeded (default 0,8)")
    ap.add_argument("--max-age", type=int, default=8, help="frames each track is followed (default 8)")
    ap.add_argument("--tracker", default="lk", choices=list(TRACKERS.names()),
                    help="the tracker back end (a neural one reads its checkpoint from "
                         "$MONA_VO_WEIGHTS)")
    ap.add_argument("--out", metavar="FILE", help="also write the rows as JSON here")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        starts = [int(v) for v in args.starts.split(",")]
    except ValueError:
        print(f"python -m eval.track_bench: error: --size and --starts take numbers "
              f"(640x272, 0,8), not {args.size!r} / {args.starts!r}", file=sys.stderr)
        return 1
    if args.max_age < 1 or min(starts) < 0 or args.frames <= max(starts) + args.max_age:
        print(f"python -m eval.track_bench: error: --frames ({args.frames}) must exceed the last "
              f"start ({max(starts)}) plus --max-age ({args.max_age}), starts >= 0, max age >= 1",
              file=sys.stderr)
        return 1
    effects = ("on", "off") if args.effects == "both" else (args.effects,)
    try:
        rows = benchmark(args.presets.split(","), parse_seeds(args.seeds), n_frames=args.frames,
                         width=w, height=h, effects=effects, tracker=args.tracker,
                         starts=starts, max_age=args.max_age, quiet=args.quiet)
    except (MonaVoError, ValueError) as exc:
        print(f"python -m eval.track_bench: error: {exc}", file=sys.stderr)
        return 1
    print(format_rows(rows))
    if args.out:
        import json

        from data_tools.atomic import write_text_atomic

        write_text_atomic(args.out, json.dumps({"rows": rows}, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
