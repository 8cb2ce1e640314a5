"""The central claims of the masks on a generated dynamic scene: MONA masks lower the VO's ATE
against no masks, and a mover's mask is stable from frame to frame. Also: unreliable masks
(too large, flickering) are not handed to the VO."""
from __future__ import annotations

import dataclasses

import numpy as np

from data_tools.frames import open_frames
from data_tools.masks_io import read_mask_png
from eval.metrics import Trajectory, evaluate_trajectory
from mona_vo.masks import MaskConfig, MonaMasker
from mona_vo.config import apply_overrides
from mona_vo.pipeline import PipelineConfig, estimate_trajectory


def _gt_masks(folder, names):
    return [read_mask_png(folder / "masks" / f"{n}.png") for n in names]


def test_mona_masks_lower_the_ate_against_no_masks(small_scene):
    # Measured (one-large seed 0, 384 x 164, 24 frames; a car covers 28 % of the view), ATE % of
    # path over five draws of the VO's point grid (vo.grid_size 14-18; `python -m eval.vo_bench
    # --presets one-large --seeds 0 --variants none,mona,gt --frames 24 --size 384x164 --draws
    # vo.grid_size=14,15,16,17,18`, which prints both VOs from the same runs), medians without
    # masks / with MONA / with the true masks:
    # - the sliding-window VO (vo.refine=none), what the masks are for: 0.478 / 0.182 / 0.163,
    #   MONA / none 0.28-0.43 in every draw; the bound asks for most of that gain: masks that
    #   miss the car, or mask static ground that the VO then loses, fail it;
    # - the default (global refinement after it): 0.137 / 0.143 / 0.142. The refinement over
    #   all keyframes outweighs the car's tracks by itself -- even the true masks do not lower
    #   its error (worst draw 1.47x none) -- so there the masks must not be clearly worse than
    #   the true masks (10 %; on the default draw 0.148 / 0.180), nor than none over draws and
    #   scenes (the test below). Until stop 54 the default showed a fifth of gain here: the
    #   no-mask VO's start pair went the wrong way in one draw (5.6 % of path), which the
    #   start's fit at its tracks' own noise (vo.init_fit_scales) mends since stop 55.
    folder, scene = small_scene
    t = np.arange(len(scene), dtype=float)
    gt = Trajectory(t, scene.poses())
    true_masks = _gt_masks(folder, [f.name for f in open_frames(folder)])
    # MONA's masks do not depend on the VO's settings: the first MONA run's masks, as it handed
    # them to the VO, are handed again to the later ones (the same trajectories, a fifth of the
    # time; eval.vo_bench.MonaReplay, checked in the test below).
    handed = []

    def ate(masks, **sets):
        """ATE % of path of the default VO and of its sliding window before the refinement
        (result.vo.poses_streaming, the trajectory vo.refine=none gives: one run, both VOs)."""
        cfg = apply_overrides(PipelineConfig(), sets)
        keep = None
        if masks == "mona" and handed:
            masks = list(handed)
        elif masks == "mona":
            def keep(out):
                handed.append(out.vo_mask)
        vo = estimate_trajectory(open_frames(folder), intrinsics=scene.intrinsics,
                                 masks=masks, config=cfg, on_frame=keep).vo
        return tuple(evaluate_trajectory(gt, Trajectory(t, p)).ate
                     for p in (vo.poses, vo.poses_streaming))

    grids = (14, 15, 16, 17, 18)
    runs = {(m, g): ate(m, **{"vo.grid_size": g}) for g in grids for m in ("mona", None)}
    streaming = np.array([(runs["mona", g][1], runs[None, g][1]) for g in grids])
    with_masks, without = streaming.T
    assert np.median(with_masks) < 0.6 * np.median(without), streaming
    assert np.all(with_masks <= 1.1 * without), streaming
    # The default against the true masks on its own draw (grid 16, the default); against none
    # over draws and scenes in the test below.
    mona, true = runs["mona", 16][0], ate(true_masks)[0]
    assert mona <= 1.1 * true, (mona, true)


def test_mona_masks_lower_the_ate_over_scenes_and_draws():
    """The same claim over five scenes of the kind (generated one-large seeds 0-4, a car over a
    fifth to a third of the view, 384 x 164, 24 frames, true intrinsics), three draws of the
    VO's point grid each (`python -m eval.vo_bench --presets one-large --seeds 0-4 --variants
    none,mona --frames 24 --size 384x164 --draws vo.grid_size=14,16,18`, both VOs from the same
    runs): one scene's median is one draw of scenes. Measured on the sliding-window VO,
    geometric mean over the scenes of MONA / no masks on the medians 0.78 (per scene 0.39 / 1.04
    / 1.07 / 0.70 / 0.96; on seeds 5-12, never chosen on, 0.80, worst scene 1.19). Masks that
    miss the cars, or mask static ground the VO then loses, give about 1. The default VO, with
    the global refinement: 0.97 (per scene 1.00 / 1.06 / 0.98 / 0.83 / 1.01; seeds 5-12 0.96,
    worst 1.24), held to no harm. Until stop 54 the default read 0.52: most of that was the
    no-mask VO's wrong-way starts (seeds 1 and 3), mended since stop 55 by the start's fit at
    its tracks' own noise (vo.init_fit_scales)."""
    from eval.vo_bench import benchmark, draw_ratios

    # Each run gives both VOs: its refined trajectory and, before the refinement, the one
    # vo.refine=none gives (row key ate_pct_streaming).
    rows = benchmark(("one-large",), range(5), ("none", "mona"), n_frames=24, width=384,
                     height=164, draws=[{"vo.grid_size": g} for g in ("14", "16", "18")])
    per_seq, (mona,) = draw_ratios(rows, key="ate_pct_streaming")
    assert mona["sequences"] == 5 and all(s["draws"] == 3 for s in per_seq), per_seq
    assert mona["gmean_median_ratio"] < 0.85, per_seq
    assert max(s["median_ratio"] for s in per_seq) < 1.2, per_seq
    per_seq, (mona,) = draw_ratios(rows)
    assert mona["sequences"] == 5 and mona["gmean_median_ratio"] < 1.05, per_seq
    assert max(s["median_ratio"] for s in per_seq) < 1.25, per_seq


def test_draws_of_the_vo_alone_get_the_masks_of_the_first_draw_and_the_same_trajectories():
    """`vo_bench --draws vo.*` computes MONA's masks once per sequence and hands them to the
    other draws: each draw's trajectory and counters must equal those of a run that computes
    its own masks, and the masks' quality and cost are reported from the run that did."""
    import eval.vo_bench as vb

    kw = dict(n_frames=16, width=384, height=164)
    draws = [{"vo.grid_size": g} for g in ("14", "16")]
    assert vb.masks_reusable(draws) and not vb.masks_reusable([{"masks.window": "7"}])
    assert not vb.masks_reusable(draws, lens=object()) and not vb.masks_reusable(None)
    reused = vb.benchmark(("one-large",), [0], ("mona",), draws=draws, **kw)
    own = vb.benchmark(("one-large",), [0], ("mona",), draws=draws[1:], **kw)
    assert [r["draw"] for r in reused] == ["vo.grid_size=14", "vo.grid_size=16"]
    replayed, computed = reused[1], own[0]
    for key in ("ate", "rpe_rot_deg", "heading_deg", "keyframes", "dropped", "mask_j", "mask_fp_pct"):
        assert replayed[key] == computed[key], key
    assert replayed["heading_deg"] < 10.0                 # the camera went the way it did
    assert replayed["mask_j"] > 0.3                       # a mask was found and scored
    assert replayed["mask_ms_per_frame"] == reused[0]["mask_ms_per_frame"] > 0


def test_a_movers_mask_is_stable_from_frame_to_frame(small_scene):
    folder, scene = small_scene
    frames = list(open_frames(folder))
    gts = _gt_masks(folder, [f.name for f in frames])
    masker = MonaMasker(MaskConfig(), scene.intrinsics)
    out = []
    for f in frames:
        out += masker.push(f.index, f.image)
    out += masker.flush()
    # IoU between consecutive masks, on frames where the mover is in view in both (the mover
    # moves a few pixels per frame: consecutive true masks overlap by more than this too).
    pairs = [(a.mask, b.mask, ga, gb) for a, b, ga, gb in zip(out, out[1:], gts, gts[1:])
             if ga.mean() > 0.01 and gb.mean() > 0.01]
    assert len(pairs) >= 10
    iou = [np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1) for a, b, _, _ in pairs]
    true_iou = [np.count_nonzero(ga & gb) / np.count_nonzero(ga | gb) for _, _, ga, gb in pairs]
    assert np.median(iou) > 0.8
    assert min(iou) > 0.5                       # no frame where the mover is lost or doubled
    assert np.mean(iou) > np.mean(true_iou) - 0.1
    # ... and it is the mover that is masked, not a stable blob elsewhere.
    J = [np.count_nonzero(o.mask & g) / max(np.count_nonzero(o.mask | g), 1)
         for o, g in zip(out, gts) if g.mean() > 0.01]
    assert np.mean(J) > 0.6
    assert all(o.reliable for o in out[2:])     # a stable mask of a car is handed to the VO


def test_too_large_or_flickering_masks_are_not_handed_to_the_vo():
    masker = MonaMasker(MaskConfig(vo_max_coverage=0.3, vo_min_stability=0.5))
    h, w = 40, 64
    masker._size = (w, h)
    big = np.zeros((h, w), bool)
    big[:, :40] = True                             # 62 % of the frame
    assert masker._reliability(big, big, None)[1] is False
    small = np.zeros((h, w), bool)
    small[5:15, 5:15] = True
    carried_same = small.copy()
    carried_elsewhere = np.zeros((h, w), bool)
    carried_elsewhere[25:35, 40:50] = True         # last frame's mask was somewhere else
    stab, ok = masker._reliability(small, small, carried_same)
    assert ok and stab == 1.0
    stab, ok = masker._reliability(small, small, carried_elsewhere)
    assert not ok and stab == 0.0
    stab, ok = masker._reliability(small, small, None)    # a first mask after none passes
    assert ok and np.isnan(stab)


def test_the_pipeline_gives_the_vo_only_reliable_masks(small_scene, monkeypatch):
    folder, scene = small_scene
    frames = list(open_frames(folder, max_frames=8))
    seen = []
    import mona_vo.pipeline as pipeline

    real = pipeline.VisualOdometry

    class Spy(real):
        def step(self, image, timestamp=None, mask=None, intrinsics=None):
            seen.append(mask)
            return super().step(image, timestamp=timestamp, mask=mask, intrinsics=intrinsics)

    monkeypatch.setattr(pipeline, "VisualOdometry", Spy)
    written = []
    # Every mask counts as too large: the VO sees none, the caller still gets every mask.
    cfg = pipeline.PipelineConfig(masks=dataclasses.replace(MaskConfig(), vo_max_coverage=1e-6))
    estimate_trajectory(frames, intrinsics=scene.intrinsics, masks="mona", config=cfg,
                        on_frame=lambda fo: written.append(fo.mask))
    assert len(seen) == len(frames) and all(m is None for m in seen)
    assert any(m is not None and m.any() for m in written)
