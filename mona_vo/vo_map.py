"""The visual odometry's long-lived state, as one object of arrays (:class:`VOMap`).

Three tables and a state:

- :class:`LandmarkTable`, indexed by track id (the trackers hand out increasing integer ids):
  world position (NaN until triangulated), flags (:class:`LandmarkFlag`: seen inside a mask,
  dynamic, rejected by the BA) and the dynamic test's strike count. A flagged landmark is never
  used again; its position is kept for the record.
- :class:`KeyframeTable`: one row per keyframe for the whole run (frame, pose, intrinsics, map
  segment) and every keyframe's observations (landmark id, pixel, inside-a-mask flag) in flat
  arrays, rows ``obs_start[k]:obs_start[k + 1]``: what the global refinement needs, compactly
  (about 30 bytes per observation).
- :class:`FrameTable`: one row per input frame: timestamp, status (written once, never patched),
  PnP support, and the pose, either relative to a keyframe (``ref_kf``, ``T_kf_frame``: it
  follows the keyframe when a bundle adjustment moves it) or absolute (``ref_kf == -1``).
- ``state`` (:class:`VOState`) and ``window``, the keyframe rows of the sliding window.

Arrays grow by doubling; nothing here knows about images, trackers or GTSAM.
"""
from __future__ import annotations

from enum import Enum, IntFlag, unique

import numpy as np

from mona_vo.conventions import Intrinsics


@unique
class VOState(Enum):
    INIT = "init"            # waiting for enough parallax to build a map
    TRACKING = "tracking"    # a map exists; frames get PnP poses


@unique
class FrameStatus(Enum):
    """Per-frame status, from most to least trustworthy (the last three are low-confidence)."""

    KEYFRAME = "keyframe"
    TRACKED = "tracked"
    BOOTSTRAP = "bootstrap"            # posed by PnP on a map built after the frame
    ROTATION_ONLY = "rotation-only"
    INTERPOLATED = "interpolated"
    EXTRAPOLATED = "extrapolated"


LOW_CONFIDENCE = frozenset({FrameStatus.ROTATION_ONLY, FrameStatus.INTERPOLATED,
                            FrameStatus.EXTRAPOLATED})
_STATUS_LIST = list(FrameStatus)


class LandmarkFlag(IntFlag):
    MASKED = 1       # observed inside a moving-object mask at some frame
    DYNAMIC = 2      # failed the front end's Cauchy test twice in a row
    REJECTED = 4     # the bundle adjustment could not explain it, or its track's patch stopped
                     # looking as at the last keyframe (VisualOdometry._drop_dissimilar); the
                     # report's `dropped` counters tell the two apart


def _grow(a: np.ndarray, n: int, fill) -> np.ndarray:
    """``a`` with at least n rows (capacity doubles), new rows set to ``fill``."""
    if len(a) >= n:
        return a
    cap = max(n, 2 * len(a), 64)
    out = np.empty((cap,) + a.shape[1:], a.dtype)
    out[:len(a)] = a
    out[len(a):] = fill
    return out


class LandmarkTable:
    """Landmarks by track id. xyz: (C, 3) float64 world (NaN: none); flags: (C,) uint8;
    strikes: (C,) uint8 consecutive dynamic-test failures; drift: (C,) float32 the drift test's
    running sum (:func:`mona_vo.vo_steps.drift_test`)."""

    def __init__(self):
        self.xyz = np.full((0, 3), np.nan)
        self.flags = np.zeros(0, np.uint8)
        self.strikes = np.zeros(0, np.uint8)
        self.drift = np.zeros(0, np.float32)

    def _ensure(self, ids: np.ndarray) -> None:
        if len(ids):
            n = int(np.max(ids)) + 1
            self.xyz = _grow(self.xyz, n, np.nan)
            self.flags = _grow(self.flags, n, 0)
            self.strikes = _grow(self.strikes, n, 0)
            self.drift = _grow(self.drift, n, 0.0)

    def has_position(self, ids: np.ndarray) -> np.ndarray:
        """(N,) bool: triangulated (whatever its flags)."""
        ids = np.asarray(ids, np.int64)
        out = np.zeros(len(ids), bool)
        inside = ids < len(self.flags)
        out[inside] = np.isfinite(self.xyz[ids[inside], 0])
        return out

    def usable(self, ids: np.ndarray) -> np.ndarray:
        """(N,) bool: triangulated and not flagged."""
        ids = np.asarray(ids, np.int64)
        out = self.has_position(ids)
        out[out] = self.flags[ids[out]] == 0
        return out

    def flagged(self, ids: np.ndarray) -> np.ndarray:
        ids = np.asarray(ids, np.int64)
        out = np.zeros(len(ids), bool)
        inside = ids < len(self.flags)
        out[inside] = self.flags[ids[inside]] != 0
        return out

    def set_positions(self, ids: np.ndarray, xyz: np.ndarray) -> None:
        ids = np.asarray(ids, np.int64)
        self._ensure(ids)
        self.xyz[ids] = xyz

    def flag(self, ids: np.ndarray, flag: LandmarkFlag) -> int:
        """Set ``flag`` on these ids; returns how many were not flagged before."""
        ids = np.unique(np.asarray(ids, np.int64))
        self._ensure(ids)
        new = int(np.count_nonzero(self.flags[ids] == 0))
        self.flags[ids] |= np.uint8(flag)
        return new

    def positions(self, ids: np.ndarray) -> np.ndarray:
        return self.xyz[np.asarray(ids, np.int64)]

    @property
    def n_usable(self) -> int:
        return int(np.count_nonzero(np.isfinite(self.xyz[:, 0]) & (self.flags == 0)))


class KeyframeTable:
    """Keyframes of the whole run and all their observations.

    frame: (K,) int64 frame index; T_world_cam: (K, 4, 4) float64; intr: (K, 4) float64 fx, fy,
    cx, cy px; segment: (K,) int64 map segment (a new one after each re-initialisation);
    obs_lm (M,) int64 landmark (track) id, obs_uv (M, 2) float32 pixels x, y, obs_masked (M,)
    bool inside the keyframe's moving-object mask; obs_start (K + 1,) int64 row offsets.
    """

    def __init__(self):
        self.n = 0
        self.frame = np.zeros(0, np.int64)
        self.T_world_cam = np.zeros((0, 4, 4))
        self.intr = np.zeros((0, 4))
        self.segment = np.zeros(0, np.int64)
        self.m = 0
        self.obs_lm = np.zeros(0, np.int64)
        self.obs_uv = np.zeros((0, 2), np.float32)
        self.obs_masked = np.zeros(0, bool)
        self.obs_start = np.zeros(1, np.int64)

    def add(self, frame: int, T_world_cam: np.ndarray, intr: Intrinsics, segment: int,
            ids: np.ndarray, uv: np.ndarray, masked: np.ndarray) -> int:
        k = self.n
        self.frame = _grow(self.frame, k + 1, -1)
        self.T_world_cam = _grow(self.T_world_cam, k + 1, 0.0)
        self.intr = _grow(self.intr, k + 1, 0.0)
        self.segment = _grow(self.segment, k + 1, -1)
        self.frame[k], self.T_world_cam[k], self.segment[k] = frame, T_world_cam, segment
        self.intr[k] = (intr.fx, intr.fy, intr.cx, intr.cy)
        m0, m1 = self.m, self.m + len(ids)
        self.obs_lm = _grow(self.obs_lm, m1, -1)
        self.obs_uv = _grow(self.obs_uv, m1, 0.0)
        self.obs_masked = _grow(self.obs_masked, m1, False)
        self.obs_lm[m0:m1], self.obs_uv[m0:m1], self.obs_masked[m0:m1] = ids, uv, masked
        self.obs_start = _grow(self.obs_start, k + 2, 0)
        self.obs_start[k + 1] = m1
        self.n, self.m = k + 1, m1
        return k

    def intrinsics(self, k: int) -> Intrinsics:
        return Intrinsics(*(float(v) for v in self.intr[k]))

    def observations(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ids, uv float64, masked) of keyframe row k (copies of the uv only)."""
        a, b = self.obs_start[k], self.obs_start[k + 1]
        return self.obs_lm[a:b], self.obs_uv[a:b].astype(np.float64), self.obs_masked[a:b]

    def observation_rows(self, rows) -> np.ndarray:
        """(M,) int64 keyframe row of each observation of ``rows`` (in that order)."""
        rows = np.asarray(rows, np.int64)
        counts = self.obs_start[rows + 1] - self.obs_start[rows]
        return np.repeat(rows, counts)

    def observation_index(self, rows) -> np.ndarray:
        """(M,) int64 indices into the obs_* arrays of the observations of ``rows``."""
        parts = [np.arange(self.obs_start[k], self.obs_start[k + 1]) for k in rows]
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)


class FrameTable:
    """One row per frame. status: (N,) int8 index into FrameStatus (-1: not written yet).

    Observations kept for the global refinement's re-posing (tracked and bootstrap frames, only
    when a refinement will run): flat arrays obs_frame (M,) int64 frame, obs_lm (M,) int64 landmark id, obs_uv (M, 2)
    float32 pixels, in the order they were added (about 20 bytes each)."""

    def __init__(self):
        self.n = 0
        self.timestamp = np.zeros(0)
        self.status = np.zeros(0, np.int8)
        self.inliers = np.zeros(0, np.int64)
        self.ref_kf = np.zeros(0, np.int64)
        self.T = np.zeros((0, 4, 4))      # T_kf_frame when ref_kf >= 0, else T_world_cam
        self.m = 0
        self.obs_frame = np.zeros(0, np.int64)
        self.obs_lm = np.zeros(0, np.int64)
        self.obs_uv = np.zeros((0, 2), np.float32)

    def add_observations(self, t: int, ids: np.ndarray, uv: np.ndarray) -> None:
        m0, m1 = self.m, self.m + len(ids)
        self.obs_frame = _grow(self.obs_frame, m1, -1)
        self.obs_lm = _grow(self.obs_lm, m1, -1)
        self.obs_uv = _grow(self.obs_uv, m1, 0.0)
        self.obs_frame[m0:m1], self.obs_lm[m0:m1], self.obs_uv[m0:m1] = t, ids, uv
        self.m = m1

    def observation_groups(self):
        """(frame, ids, uv float64) for each frame with kept observations, in frame order."""
        order = np.argsort(self.obs_frame[:self.m], kind="stable")
        frames, starts = np.unique(self.obs_frame[order], return_index=True)
        for t, rows in zip(frames, np.split(order, starts[1:])):
            yield int(t), self.obs_lm[rows], self.obs_uv[rows].astype(np.float64)

    def repose(self, t: int, T_kf_frame: np.ndarray) -> None:
        """A new pose for frame t, written relative to its keyframe; status stays as written."""
        if self.ref_kf[t] < 0:
            raise RuntimeError(f"frame {t}: only a frame tied to a keyframe can be re-posed")
        self.T[t] = T_kf_frame

    def append(self, timestamp: float) -> int:
        t = self.n
        self.timestamp = _grow(self.timestamp, t + 1, np.nan)
        self.status = _grow(self.status, t + 1, -1)
        self.inliers = _grow(self.inliers, t + 1, 0)
        self.ref_kf = _grow(self.ref_kf, t + 1, -1)
        self.T = _grow(self.T, t + 1, 0.0)
        self.timestamp[t] = timestamp
        self.T[t] = np.eye(4)
        self.n = t + 1
        return t

    def write(self, t: int, status: FrameStatus, inliers: int, *, ref_kf: int = -1,
              T: np.ndarray) -> None:
        """Record frame t once: ``T`` is T_kf_frame for ``ref_kf >= 0``, else T_world_cam."""
        if self.status[t] >= 0:
            raise RuntimeError(f"frame {t}: status already written")
        self.status[t] = _STATUS_LIST.index(status)
        self.inliers[t], self.ref_kf[t], self.T[t] = inliers, ref_kf, T

    def attach(self, t: int, ref_kf: int, T_world_kf: np.ndarray) -> None:
        """Tie frame t, written with an absolute pose, to keyframe row ``ref_kf`` (now at
        T_world_kf): its pose and status stay as written, but from now on it moves with that
        keyframe, as frames written relative to a keyframe do when a refinement moves it."""
        if self.status[t] < 0 or self.ref_kf[t] >= 0:
            raise RuntimeError(f"frame {t}: only a frame written with an absolute pose can be attached")
        self.T[t] = np.linalg.solve(T_world_kf, self.T[t])
        self.ref_kf[t] = ref_kf

    def backfill(self, t: int, T_world_cam: np.ndarray) -> None:
        """Frame t, written rotation-only before the first map, gets the translation the map's
        first velocity gives it (:func:`mona_vo.vo_steps.walk_back`): status extrapolated,
        pose absolute. The only rewrite of a status the table allows."""
        if self.status[t] != _STATUS_LIST.index(FrameStatus.ROTATION_ONLY):
            raise RuntimeError(f"frame {t}: only a rotation-only frame can be backfilled")
        self.status[t] = _STATUS_LIST.index(FrameStatus.EXTRAPOLATED)
        self.ref_kf[t], self.T[t] = -1, T_world_cam

    def written(self, t: int) -> bool:
        return bool(self.status[t] >= 0)

    def status_of(self, t: int) -> FrameStatus:
        return _STATUS_LIST[int(self.status[t])]


class VOMap:
    """Everything the VO remembers: landmarks, keyframes, frames, the window and the state."""

    def __init__(self):
        self.landmarks = LandmarkTable()
        self.keyframes = KeyframeTable()
        self.frames = FrameTable()
        self.window: list[int] = []      # keyframe rows, oldest first
        self.state = VOState.INIT
        self.segment = -1                # current map segment (-1: none yet)

    def pose_of(self, t: int) -> np.ndarray:
        """T_world_cam of a written frame."""
        ref = int(self.frames.ref_kf[t])
        if ref >= 0:
            return self.keyframes.T_world_cam[ref] @ self.frames.T[t]
        return self.frames.T[t].copy()

    def all_poses(self) -> np.ndarray:
        """(N, 4, 4) T_world_cam of every frame (identity where nothing is written)."""
        n = self.frames.n
        out = self.frames.T[:n].copy()
        ref = self.frames.ref_kf[:n]
        sel = np.flatnonzero(ref >= 0)
        if len(sel):
            out[sel] = np.einsum("nij,njk->nik", self.keyframes.T_world_cam[ref[sel]], out[sel])
        return out

    def frame_segments(self) -> np.ndarray:
        """(N,) int64 map segment of each written frame's keyframe (-1: posed alone, not on
        a map: rotation-only, extrapolated)."""
        ref = self.frames.ref_kf[:self.frames.n]
        out = np.full(len(ref), -1, np.int64)
        on = ref >= 0
        out[on] = self.keyframes.segment[ref[on]]
        return out

    def window_observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(obs_kf rows, obs_lm, obs_uv float64, obs_masked) of the window keyframes."""
        idx = self.keyframes.observation_index(self.window)
        rows = self.keyframes.observation_rows(self.window)
        k = self.keyframes
        return rows, k.obs_lm[idx], k.obs_uv[idx].astype(np.float64), k.obs_masked[idx]
