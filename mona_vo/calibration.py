"""Focal length of an uncalibrated video, from its first frames, before the VO starts.

Most videos come without intrinsics, and a wrong field-of-view guess bends the whole map. Here the
first ``frames`` frames are tracked (Lucas-Kanade), a few keyframes are picked by image motion,
and for every candidate field of view a small multi-view reconstruction is built (two-view
essential matrix, PnP, triangulation) and bundle-adjusted twice with :func:`ba.global_ba.refine_global`:
once with the candidate's focal length held (its reprojection RMSE is the evidence curve) and once
with one shared focal length freed (Cal3f). The freed solve with the lowest RMSE gives the
estimate. Principal point: the image centre.

Before that, a pure-rotation model is fitted to the same keyframes (:func:`rotation_focal`): views
of a camera that only turns map onto each other by K R K^-1, which pins down the focal length and
the principal point. Where its curve over the focal length is sharp and it fits about as well as the reconstruction
(``rotation_min_score``), as on a pan, it is used instead: there the reconstruction would invent
structure from noise, while footage that translates fits no focal length well under a rotation
model, so its curve stays flat.

For the reconstruction, the focal length is only observable with rotation and parallax together: a camera translating
without turning, or a scene too far away, fits every candidate equally well. The estimate is
therefore used only when the evidence curve has a clear minimum (the worst candidate's RMSE at
least ``min_contrast`` times the best one's) and the freed focal length stays inside the
candidates' range; otherwise the guess is kept and the report says why.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from ba.global_ba import KeyframeGraph, refine_global
from ba.sliding_window_ba import BAConfig
from mona_vo.conventions import (Intrinsics, focal_for_fov, fov_span, invert_pose, make_pose,
                                  rotation_angle_deg)
from mona_vo.config import setting
from mona_vo.errors import ConfigError
from mona_vo.tracking import LKTracker, to_gray
from mona_vo.two_view import bearings, kabsch_rotation, pixel_homography, relative_pose, triangulate

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FocalConfig:
    mode: str = setting("estimate", choices=("estimate", "guess"))  # without --calib: estimate
                                            # the focal length from the first frames, or keep the
                                            # guess of the assumed field of view
    frames: int = setting(40, ge=3)         # first frames looked at
    hfov_min_deg: float = setting(35.0, gt=5, lt=175)   # narrowest candidate field of view, deg
    hfov_max_deg: float = setting(110.0, gt=5, lt=175)  # widest one (both across the longer side)
    candidates: int = setting(5, ge=2)      # held-focal candidates, evenly spaced in log focal
    freed_from: int = setting(2, ge=1)      # freed-focal solves start from this many best candidates
    keyframe_motion_px: float = setting(15.0, gt=0)  # median track motion between keyframes, px
    max_keyframes: int = setting(8, ge=3)   # keyframes of the reconstruction
    points: int = setting(600, ge=20)       # points tracked (Shi-Tomasi corners)
    max_points: int = setting(300, ge=10)   # landmarks kept for the solves (the longest tracks)
    min_points: int = setting(30, ge=8)     # fewer reconstructed points: the guess is kept
    min_contrast: float = setting(1.05, ge=1.0)  # worst / best held-focal RMSE needed to use the
                                            # estimate (a flat curve: focal not observable)
    rotation_min_score: float = setting(8.0, gt=0)  # pure-rotation model taken when the sharpness
                                            # of its focal curve (worst / best RMSE over the
                                            # range) times reconstruction RMSE / its RMSE (at most
                                            # 1) reaches this. Tuning seeds: pans 16-70, footage
                                            # that translates 0.03-2.6
    second_pass_change: float = setting(0.05, gt=0)  # when the global refinement moves the
                                            # focal length by more than this share, the VO runs
                                            # again over the frames with the refined camera
                                            # (frames that can be read twice only)
    start_again: bool = setting(True)  # a run that built no map while its parallax says the
                                            # camera translated runs again with the start's
                                            # ray-angle test taken at hfov_max_deg (frames that
                                            # can be read twice only; pipeline._start_again)
    held_iterations: int = setting(5, ge=1)   # LM iterations of a held-focal solve (evidence)
    freed_iterations: int = setting(30, ge=1)  # LM iterations of a freed-focal solve

    def validate(self) -> None:
        if self.hfov_min_deg >= self.hfov_max_deg:
            raise ConfigError("config key 'calibration.hfov_min_deg': must be below "
                              "calibration.hfov_max_deg")

    def candidate_focals(self, span: int) -> np.ndarray:
        """(candidates,) focal lengths (px) from the widest to the narrowest field of view across
        ``span`` pixels (the longer side, :func:`mona_vo.conventions.fov_span`)."""
        lo = focal_for_fov(span, self.hfov_max_deg)
        hi = focal_for_fov(span, self.hfov_min_deg)
        return np.geomspace(lo, hi, self.candidates)


@dataclass
class FocalEstimate:
    """Outcome of :func:`estimate_focal`; ``as_dict()`` goes into report.json.

    focal:        focal length used (px): the estimate when ``used``, else the guess.
    guess:        the focal length of the assumed field of view (px).
    estimate:     the freed-focal solution's focal length (px) or None when nothing was solved.
    used:         the estimate replaced the guess.
    reason:       one line saying why (or why not).
    candidates:   per starting field of view: hfov_deg, focal_px, held_rmse_px, freed_focal_px,
                  freed_rmse_px.
    rotation_deg: rotation between the first and last keyframe (from the chosen solution).
    parallax_deg: median ray angle of the reconstructed points.
    keyframes, points: size of the reconstruction; frames: frames looked at; seconds: wall time.
    rotation_model: the pure-rotation fit (:func:`rotation_focal`): focal_px, cx, cy, rmse_px,
                  contrast, pairs, and the score it was judged by.
    cx, cy:       the principal point when the rotation model estimated it (``used`` from it),
                  else None: the image centre.
    freed_rmse_px: reprojection RMSE of the reconstruction's freed-focal solve (None: none).
    """

    focal: float
    guess: float
    span: int
    estimate: float | None = None
    used: bool = False
    reason: str = ""
    candidates: list = field(default_factory=list)
    rotation_deg: float = 0.0
    parallax_deg: float = 0.0
    keyframes: int = 0
    points: int = 0
    frames: int = 0
    seconds: float = 0.0
    rotation_model: dict = field(default_factory=dict)
    cx: float | None = None
    cy: float | None = None
    freed_rmse_px: float | None = None

    @property
    def hfov_deg(self) -> float:
        return float(np.degrees(2 * np.arctan(0.5 * self.span / self.focal)))

    def intrinsics_for(self, width: int, height: int) -> Intrinsics:
        """Pinhole intrinsics of a width x height frame: ``focal``, the estimated principal point
        or the centre."""
        cx = (width - 1) / 2.0 if self.cx is None else self.cx
        cy = (height - 1) / 2.0 if self.cy is None else self.cy
        return Intrinsics(self.focal, self.focal, cx, cy)

    def as_dict(self) -> dict:
        return {"focal_px": round(float(self.focal), 3), "hfov_deg": round(self.hfov_deg, 3),
                "guess_px": round(float(self.guess), 3),
                "estimate_px": None if self.estimate is None else round(float(self.estimate), 3),
                "used": bool(self.used), "reason": self.reason,
                "rotation_deg": round(float(self.rotation_deg), 3),
                "parallax_deg": round(float(self.parallax_deg), 4),
                "keyframes": int(self.keyframes), "points": int(self.points),
                "frames": int(self.frames), "seconds": round(float(self.seconds), 3),
                "principal_point": None if self.cx is None else [round(self.cx, 2), round(self.cy, 2)],
                "rotation_model": self.rotation_model, "candidates": self.candidates}


def _track(frames: list[np.ndarray], cfg: FocalConfig):
    """LK tracks over the frames: dict frame -> (ids, (N, 2) uv), new corners when tracks thin out."""
    tracker = LKTracker()
    out = {}
    for t, img in enumerate(frames):
        gray = to_gray(img)
        upd = tracker.step(gray)
        live = tracker.live()
        if len(live.ids) < 0.5 * cfg.points:
            h, w = gray.shape
            occupied = np.zeros_like(gray, np.uint8)
            for x, y in live.points.astype(int):
                cv2.circle(occupied, (int(x), int(y)), max(4, w // 60), 255, -1)
            corners = cv2.goodFeaturesToTrack(gray, cfg.points - len(live.ids), 0.01, max(4, w // 60),
                                              mask=255 - occupied)
            if corners is not None:
                tracker.add_points(corners.reshape(-1, 2))
            live = tracker.live()
        del upd
        out[t] = (live.ids.copy(), live.points.astype(np.float64))
    return out


def _pick_keyframes(tracks, cfg: FocalConfig) -> list[int]:
    keys = [0]
    for t in range(1, len(tracks)):
        ids0, uv0 = tracks[keys[-1]]
        ids1, uv1 = tracks[t]
        _, a, b = np.intersect1d(ids0, ids1, return_indices=True)
        if len(a) < 8:
            break
        if np.median(np.linalg.norm(uv1[b] - uv0[a], axis=1)) >= cfg.keyframe_motion_px:
            keys.append(t)
        if len(keys) >= cfg.max_keyframes:
            break
    last = len(tracks) - 1
    if keys[-1] != last and len(keys) < cfg.max_keyframes:
        keys.append(last)
    return keys


def _rotation_residuals(pairs, f: float, cx: float, cy: float) -> np.ndarray:
    """Pixel residuals (2M,) of matched pixels between view pairs each explained by a pure
    rotation (Kabsch on the rays of focal length f, principal point cx, cy)."""
    c = np.array([cx, cy])
    intr = Intrinsics(f, f, cx, cy)
    out = []
    for ua, ub in pairs:
        ra = bearings(ua, intr)
        q = ra @ kabsch_rotation(bearings(ub, intr), ra).T     # rays of a turned into b
        with np.errstate(divide="ignore", invalid="ignore"):
            out.append((f * q[:, :2] / q[:, 2:3] + c - ub).ravel())
    r = np.concatenate(out) if out else np.zeros(0)
    return np.where(np.isfinite(r), r, 1e3)


def _rmse(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r ** 2))) if len(r) else float("inf")


def rotation_focal(tracks, keys: list[int], span: int, guess: Intrinsics,
                   cfg: FocalConfig = FocalConfig()) -> dict:
    """Focal length and principal point under a pure-rotation model (a pan, or footage whose
    translation is too small for its depth): views of a turning camera map onto each other by
    K R K^-1, and only the right K makes that map a rotation. Every keyframe pair sharing >= 20
    tracks contributes its homography inliers (a focal-free fit, which leaves movers out). The
    focal length minimising their pooled rotation-reprojection RMSE over the candidate range
    (principal point at the guess's) starts a robust fit of focal length and principal point.
    ``contrast``: worst / best RMSE over the range; footage that translates fits no focal length
    well, so its curve is flat. Returns {} without a usable pair, else focal_px, cx, cy,
    rmse_px (of the final fit), contrast, pairs."""
    from scipy.optimize import least_squares

    pairs = []
    for i, ki in enumerate(keys):
        for kj in keys[i + 1:]:
            (ia, ua), (ib, ub) = tracks[ki], tracks[kj]
            _, a, b = np.intersect1d(ia, ib, return_indices=True)
            if len(a) < 20:
                continue
            H, inl = pixel_homography(ua[a], ub[b], 2.0)
            if H is None:
                continue
            pairs.append((ua[a][inl], ub[b][inl]))
    if not pairs:
        return {}
    lo, hi = cfg.candidate_focals(span)[[0, -1]]
    grid = np.geomspace(lo, hi, 60)
    cost = np.array([_rmse(_rotation_residuals(pairs, f, guess.cx, guess.cy)) for f in grid])
    k = int(np.argmin(cost))
    fit = least_squares(lambda x: _rotation_residuals(pairs, *x), [grid[k], guess.cx, guess.cy],
                        x_scale=[grid[k], 10.0, 10.0], loss="soft_l1", f_scale=1.0, max_nfev=200)
    f, cx, cy = (float(v) for v in fit.x)
    return {"focal_px": round(f, 3), "cx": round(cx, 3), "cy": round(cy, 3),
            "rmse_px": round(_rmse(_rotation_residuals(pairs, f, cx, cy)), 4),
            "contrast": round(float(cost.max() / max(cost[k], 1e-9)), 3), "pairs": len(pairs)}


def _reconstruct(tracks, keys, intr: Intrinsics, max_points: int):
    """Poses of the keyframes and points of the tracks at one focal length (world = keyframe 0).
    Returns a KeyframeGraph or None."""
    ids0, uv0 = tracks[keys[0]]
    # The farthest keyframe still sharing enough tracks with the first one gives the baseline.
    pair = None
    for j in reversed(keys[1:]):
        idsj, uvj = tracks[j]
        common, a, b = np.intersect1d(ids0, idsj, return_indices=True)
        if len(common) >= 30:
            rel = relative_pose(uv0[a], uvj[b], intr, intr)
            if rel is not None and rel.n_inliers >= 20:
                pair = (j, rel, common[rel.inliers], a[rel.inliers], b[rel.inliers])
                break
    if pair is None:
        return None
    j, rel, common, a, b = pair
    id_sets = [set(tracks[k][0].tolist()) for k in keys]
    poses = {keys[0]: np.eye(4), j: rel.T_a_b}
    X, err, ang = triangulate(poses[keys[0]], poses[j], uv0[a], tracks[j][1][b], intr, intr)
    good = (err < 4.0) & (ang > 0.05)
    landmarks = {int(i): p for i, p in zip(common[good], X[good])}
    for _ in range(2):
        for k in keys:
            if k in poses:
                continue
            ids, uv = tracks[k]
            have = np.array([int(i) in landmarks for i in ids], bool)
            if have.sum() < 12:
                continue
            P = np.array([landmarks[int(i)] for i in ids[have]])
            ok, rvec, tvec, inl = cv2.solvePnPRansac(P, uv[have], intr.K, None, iterationsCount=100,
                                                     reprojectionError=3.0, confidence=0.999,
                                                     flags=cv2.SOLVEPNP_EPNP)
            if ok and inl is not None and len(inl) >= 12:
                R, _ = cv2.Rodrigues(rvec)
                poses[k] = invert_pose(make_pose(R, tvec.ravel()))
        # Points of tracks seen by two posed keyframes: from the widest pair.
        posed = sorted(poses)
        for ka_i, ka in enumerate(posed):
            for kb in reversed(posed[ka_i + 1:]):
                idsa, uva = tracks[ka]
                idsb, uvb = tracks[kb]
                common, a, b = np.intersect1d(idsa, idsb, return_indices=True)
                new = np.array([int(i) not in landmarks for i in common], bool)
                if new.sum() == 0:
                    continue
                X, err, ang = triangulate(poses[ka], poses[kb], uva[a[new]], uvb[b[new]], intr, intr)
                good = (err < 4.0) & (ang > 0.05)
                for i, p in zip(common[new][good], X[good]):
                    landmarks[int(i)] = p
    if len(landmarks) > max_points:
        # The longest tracks constrain the focal length most; keep those.
        seen = {i: sum(int(i) in set_k for set_k in id_sets) for i in landmarks}
        keep = sorted(landmarks, key=lambda i: (-seen[i], i))[:max_points]
        landmarks = {i: landmarks[i] for i in keep}
    rows = sorted(poses)
    obs_kf, obs_lm, obs_uv = [], [], []
    for r, k in enumerate(rows):
        ids, uv = tracks[k]
        have = np.array([int(i) in landmarks for i in ids], bool)
        obs_kf.append(np.full(have.sum(), r))
        obs_lm.append(ids[have])
        obs_uv.append(uv[have])
    lm_ids = np.array(sorted(landmarks), np.int64)
    if len(rows) < 2 or len(lm_ids) < 8:
        return None
    intr_arr = np.tile([intr.fx, intr.fy, intr.cx, intr.cy], (len(rows), 1))
    obs_kf = np.concatenate(obs_kf).astype(np.int64)
    return KeyframeGraph(np.array(rows, np.int64), np.stack([poses[k] for k in rows]), intr_arr,
                         obs_kf, np.concatenate(obs_lm).astype(np.int64), np.concatenate(obs_uv),
                         np.zeros(len(obs_kf), bool), lm_ids,
                         np.stack([landmarks[int(i)] for i in lm_ids]))


def _median_parallax_deg(graph: KeyframeGraph, T: np.ndarray, P: np.ndarray, valid: np.ndarray) -> float:
    """Median over points of the widest angle between the rays of its first and last view."""
    row = np.searchsorted(graph.lm_ids, graph.obs_lm)
    angles = []
    for j in np.flatnonzero(valid)[:2000]:
        ks = graph.obs_kf[row == j]
        if len(ks) < 2:
            continue
        ra, rb = P[j] - T[ks.min(), :3, 3], P[j] - T[ks.max(), :3, 3]
        c = ra @ rb / max(np.linalg.norm(ra) * np.linalg.norm(rb), 1e-12)
        angles.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return float(np.median(angles)) if angles else 0.0


def estimate_focal(frames: list[np.ndarray], guess: Intrinsics,
                   cfg: FocalConfig = FocalConfig()) -> FocalEstimate:
    """Focal length of a video from its first frames (list of (H, W, 3) uint8 RGB or (H, W) grey).
    ``guess``: the assumed intrinsics (principal point kept). See the module docstring."""
    t0 = time.perf_counter()
    h, w = to_gray(frames[0]).shape
    frames = frames[:cfg.frames]
    tracks = _track(frames, cfg) if len(frames) >= 3 else {}
    est = focal_from_tracks(tracks, fov_span(w, h), guess, cfg)
    est.frames = len(frames)
    est.seconds = time.perf_counter() - t0
    return est


def focal_from_tracks(tracks: dict, span: int, guess: Intrinsics,
                      cfg: FocalConfig = FocalConfig()) -> FocalEstimate:
    """The estimate from point tracks: frame index (0, 1, ...) -> ((N,) int64 track ids,
    (N, 2) float64 pixels x, y); ``span``: the frame's longer side (px), which the candidates'
    fields of view are measured across. See :func:`estimate_focal`."""
    t0 = time.perf_counter()
    cfg.validate()
    span = int(span)
    out = FocalEstimate(focal=guess.fx, guess=guess.fx, span=span, frames=len(tracks))
    if len(tracks) < 3:
        out.reason = f"only {len(tracks)} frames: the guess is kept"
        out.seconds = time.perf_counter() - t0
        return out
    keys = _pick_keyframes(tracks, cfg)
    rot = rotation_focal(tracks, keys, span, guess, cfg) if len(keys) >= 2 else {}
    out.rotation_model = rot
    if len(keys) >= 3:
        _reconstruction_estimate(out, tracks, keys, span, guess, cfg)
    else:
        out.reason = (f"the first {len(tracks)} frames move less than {cfg.keyframe_motion_px:g} px "
                      f"twice: too little motion to see the focal length, the guess is kept")
        out.keyframes = len(keys)
    fmin, fmax = cfg.candidate_focals(span)[[0, -1]]
    # A principal point more than 5 % of the longer side off the centre is not a lens (they are within
    # 2-3 %), it is translation absorbed by the fit.
    centred = rot and max(abs(rot["cx"] - guess.cx), abs(rot["cy"] - guess.cy)) <= 0.05 * span
    if rot:
        # Sharpness of the rotation model's curve, discounted by how much worse it fits than the
        # reconstruction (which has 3 more numbers per point, so fits noise better).
        fit = 1.0 if out.freed_rmse_px is None else out.freed_rmse_px / max(rot["rmse_px"], 1e-9)
        rot["score"] = round(rot["contrast"] * min(fit, 1.0), 3)
    if centred and rot["score"] >= cfg.rotation_min_score and fmin <= rot["focal_px"] <= fmax:
        # Only rotations relate the views: the reconstruction invents structure from noise
        # there (measured 2-18 % off on pans), the rotation model is exact, and it also sees the
        # principal point.
        out.used, out.estimate, out.focal = True, rot["focal_px"], rot["focal_px"]
        out.cx, out.cy = rot["cx"], rot["cy"]
        out.reason = (f"the views fit a pure rotation (RMSE {rot['rmse_px']:.2f} px, worst/best "
                      f"{rot['contrast']:.1f} over {rot['pairs']} keyframe pairs): focal length and "
                      f"principal point from the rotations")
    out.seconds = time.perf_counter() - t0
    log.info("focal: %.1f px (%s)", out.focal, out.reason)
    return out


def _reconstruction_estimate(out: FocalEstimate, tracks, keys, span: int, guess: Intrinsics,
                             cfg: FocalConfig) -> None:
    """The multi-view reconstruction's estimate (module docstring), written into ``out``."""
    best = None
    solved = []
    held_cfg = BAConfig(global_max_iterations=cfg.held_iterations)
    # The freed solve's focal prior is only a guard (sigma 3 f): the candidates are guesses, and
    # the global BA's default prior (0.3 f) would pull a weakly constrained focal to its start.
    freed_cfg = BAConfig(global_max_iterations=cfg.freed_iterations, focal_prior_ratio=3.0)
    for f in cfg.candidate_focals(span):
        hfov = float(np.degrees(2 * np.arctan(0.5 * span / f)))
        intr = Intrinsics(f, f, guess.cx, guess.cy)
        graph = _reconstruct(tracks, keys, intr, cfg.max_points)
        row = {"hfov_deg": round(hfov, 2), "focal_px": round(float(f), 2), "held_rmse_px": None,
               "freed_focal_px": None, "freed_rmse_px": None}
        out.candidates.append(row)
        if graph is None:
            continue
        held = refine_global(graph, held_cfg)
        row.update(held_rmse_px=round(held.rmse_px, 4), observations=held.n_observations_used)
        if np.isfinite(held.rmse_px):
            solved.append((held.rmse_px, row, graph, held))
    # Freeing the focal length from the best-fitting candidates: a start near the truth converges
    # in a few iterations, one far from it may stop in a distorted local minimum.
    for _, row, graph, held in sorted(solved, key=lambda x: x[0])[:cfg.freed_from]:
        freed = refine_global(KeyframeGraph(graph.kf_frames, held.T_world_cam, graph.intrinsics,
                                            graph.obs_kf, graph.obs_lm, graph.obs_uv, graph.obs_masked,
                                            graph.lm_ids, held.lm_xyz), freed_cfg, refine_focal=True)
        row.update(freed_focal_px=round(float(freed.focal), 2), freed_rmse_px=round(freed.rmse_px, 4))
        if np.isfinite(freed.rmse_px) and (best is None or freed.rmse_px < best[1].rmse_px):
            best = (graph, freed)
    if best is None:
        out.reason = "no candidate focal length gave a two-view reconstruction: the guess is kept"
        out.keyframes = len(keys)
        return
    graph, freed = best
    out.estimate = float(freed.focal)
    out.freed_rmse_px = float(freed.rmse_px)
    out.keyframes = len(graph.kf_frames)
    out.points = int(freed.lm_valid.sum())
    T = freed.T_world_cam
    out.rotation_deg = rotation_angle_deg(T[0, :3, :3].T @ T[-1, :3, :3])
    out.parallax_deg = _median_parallax_deg(graph, T, freed.lm_xyz, freed.lm_valid)
    held = [c["held_rmse_px"] for c in out.candidates if c["held_rmse_px"] is not None]
    contrast = max(held) / max(min(held), 1e-9) if held else 1.0
    fmin, fmax = cfg.candidate_focals(span)[[0, -1]]
    if out.points < cfg.min_points:
        out.reason = f"only {out.points} points reconstructed: the guess is kept"
    elif contrast < cfg.min_contrast:
        out.reason = (f"every candidate fits about as well (held-focal RMSE worst/best {contrast:.2f} < "
                      f"{cfg.min_contrast:g}; rotation {out.rotation_deg:.1f} deg, parallax "
                      f"{out.parallax_deg:.2f} deg): the focal length is not observable here, the guess is kept")
    elif not fmin <= out.estimate <= fmax:
        out.reason = (f"the freed focal length {out.estimate:.1f} px left the candidates' range "
                      f"[{fmin:.0f}, {fmax:.0f}] px: the guess is kept")
    else:
        out.used = True
        out.focal = out.estimate
        out.reason = (f"held-focal RMSE worst/best {contrast:.2f}; rotation {out.rotation_deg:.1f} deg, "
                      f"parallax {out.parallax_deg:.2f} deg over {out.keyframes} keyframes")
