"""Rolling shutter: a frame's rows are read one after the other, so a turning camera sees each
row from a slightly different direction.

Most video cameras (phones, webcams, the Bonn RGB-D sequences' sensor) read their rows from top
to bottom over a good part of the frame interval. Under a hand-held camera turning 10 degrees a
second, a readout of 30 ms turns the bottom row 0.3 degrees from the top one, about 3 px at a
540 px focal length: a systematic error, the same in every frame that turns the same way, which
the pinhole model of the bundle adjustment cannot fit and no robust kernel removes.

The model here is rotation only (a hand-held camera turns far more within a readout than it
moves): the row at ``v`` is read ``s = readout * (v - c) / h`` frame intervals after the middle
row ``c`` (``readout``: the share of the frame interval the whole frame's readout takes, ``h``
rows), while the camera turns at ``w`` (a rotation vector per frame interval, in the camera's
frame). The frame's pose is the camera's at the middle row, and a pixel ``x`` of row ``v`` is
moved to where the middle row's camera would have seen the same ray: ``K exp(s w) K^-1 x``.

The turn rates come from the VO's own trajectory (:func:`turn_rates`), so the correction needs
no other sensor. Pure functions of arrays; the VO decides when (mona_vo.vo).
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def _central_pairs(segment: np.ndarray):
    """(frames, the frame before, the frame after, frames between) of each frame on a map that
    has a neighbour on it: its neighbours on the same map, itself on one side at a map's end."""
    seg = np.asarray(segment, np.int64)
    idx = np.flatnonzero(seg >= 0)
    same_prev = np.r_[False, seg[idx[1:]] == seg[idx[:-1]]]
    same_next = np.r_[seg[idx[:-1]] == seg[idx[1:]], False]
    prev = np.where(same_prev, np.r_[idx[0:1], idx[:-1]], idx)
    nxt = np.where(same_next, np.r_[idx[1:], idx[-1:]], idx)
    good = nxt > prev
    return idx[good], prev[good], nxt[good], (nxt - prev)[good].astype(np.float64)


def turn_rates(T_world_cam: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vector per frame interval of each frame's camera, in that camera's frame:
    the turn from the frame before to the frame after on the same map, over the frames between
    (a central difference; one-sided at a map's ends, zero for a frame alone on its map).

    T_world_cam: (N, 4, 4) camera-to-world poses; segment: (N,) int64 the map each frame was
    posed on, -1 for frames on none (their rate is zero: their world is not the map's)."""
    R = np.asarray(T_world_cam, np.float64)[:, :3, :3]
    out = np.zeros((len(R), 3))
    idx, prev, nxt, span = _central_pairs(segment)
    if len(idx):
        rel = np.einsum("nji,njk->nik", R[prev], R[nxt])             # R_prev^T R_next
        out[idx] = Rotation.from_matrix(rel).as_rotvec() / span[:, None]
    return out


def velocities(T_world_cam: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """(N, 3) camera centre's motion per frame interval of each frame, in that frame's camera
    frame (map units), by the central difference :func:`turn_rates` takes (zero where it
    takes none)."""
    T = np.asarray(T_world_cam, np.float64)
    out = np.zeros((len(T), 3))
    idx, prev, nxt, span = _central_pairs(segment)
    if len(idx):
        step = (T[nxt, :3, 3] - T[prev, :3, 3]) / span[:, None]
        out[idx] = np.einsum("nji,nj->ni", T[idx, :3, :3], step)
    return out


def corrected_pixels(uv: np.ndarray, rates: np.ndarray, readout: float, intrinsics: np.ndarray,
                     height: int, velocity: np.ndarray | None = None,
                     points_cam: np.ndarray | None = None) -> np.ndarray:
    """(M, 2) float64: where the camera of the middle row would have seen the rays seen at the
    (M, 2) pixels ``uv``, each in a frame turning at ``rates`` (M, 3) (:func:`turn_rates` of its
    frame), whose ``height`` rows are read over ``readout`` frame intervals, top row first.
    ``intrinsics`` (M, 4) or (4,): fx, fy, cx, cy. ``readout`` 0 returns ``uv`` unchanged.

    With ``velocity`` (M, 3) (:func:`velocities` of each frame) and ``points_cam`` (M, 3) (each
    observed point in its frame's middle-row camera, from a solution), the camera's own motion
    within the readout is taken out too: it moved each observation by the difference of the
    point's projections from the moved and the middle-row centre, which depends on the point's
    depth, so no image warp can undo it (a camera walking 10 cm a frame past points 5 m away,
    read over 0.8 of the interval: about as much as its turn of 0.6 deg a frame)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if readout == 0 or not len(uv):
        return uv.copy()
    K = np.broadcast_to(np.asarray(intrinsics, np.float64), (len(uv), 4))
    fx, fy, cx, cy = K[:, 0], K[:, 1], K[:, 2], K[:, 3]
    s = readout * (uv[:, 1] - (height - 1) / 2.0) / height
    rays = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(len(uv))], axis=1)
    turn = np.asarray(rates, np.float64).reshape(-1, 3) * s[:, None]
    turned = Rotation.from_rotvec(turn).apply(rays)
    z = turned[:, 2]
    out = np.stack([fx * turned[:, 0] / z + cx, fy * turned[:, 1] / z + cy], axis=1)
    if velocity is None or points_cam is None:
        return out
    P = np.asarray(points_cam, np.float64).reshape(-1, 3)
    moved = P - s[:, None] * np.asarray(velocity, np.float64).reshape(-1, 3)
    ok = (P[:, 2] > 1e-9) & (moved[:, 2] > 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.stack([fx * (moved[:, 0] / moved[:, 2] - P[:, 0] / P[:, 2]),
                          fy * (moved[:, 1] / moved[:, 2] - P[:, 1] / P[:, 2])], axis=1)
    return out - np.where(ok[:, None], shift, 0.0)


def unroll_maps(rate: np.ndarray, readout: float, intrinsics: np.ndarray, width: int,
                height: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (two (height, width) float32) that show a frame turning at ``rate`` (3,)
    as the camera of its middle row would have seen it: output pixel y takes the frame's pixel
    K exp(-s w) K^-1 y, with s taken at y's own row (the row a pixel moves to differs from its
    own by a fraction of a pixel per degree of turn within the readout). One homography per
    row, so a frame costs a few array operations (:func:`corrected_pixels` per pixel took 0.1
    s a frame at 640 x 480)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    v = np.arange(height, dtype=np.float64)
    s = readout * (v - (height - 1) / 2.0) / height
    turn = Rotation.from_rotvec(-s[:, None] * np.asarray(rate, np.float64)[None]).as_matrix()
    H = K @ turn @ np.linalg.inv(K)
    u = np.arange(width, dtype=np.float64)[None]
    rest = H[:, :, 1] * v[:, None] + H[:, :, 2]                       # (h, 3)
    den = H[:, 2, 0, None] * u + rest[:, 2, None]
    mx = (H[:, 0, 0, None] * u + rest[:, 0, None]) / den
    my = (H[:, 1, 0, None] * u + rest[:, 1, None]) / den
    return mx.astype(np.float32), my.astype(np.float32)


def best_readout(readouts: np.ndarray, costs: np.ndarray) -> float:
    """The readout (share of the frame interval) where the parabola through the lowest-cost
    (readout, cost) pair and its two neighbours is lowest, at most 1.0; the readouts increase
    from 0. 0 (a global shutter) when 0 costs least, and also when the cost still falls at the
    last readout tried beyond 1.0: a video's rows are all read within one frame interval, so a
    cost that keeps falling there is the readout absorbing something else (a mover's motion on
    a tiny generated clip: 1.5 was chosen, and the run lost)."""
    r = np.asarray(readouts, np.float64)
    c = np.asarray(costs, np.float64)
    k = int(np.argmin(c))
    if k == 0 or (k == len(r) - 1 and r[k] > 1.0):
        return 0.0
    if k == len(r) - 1:
        return float(r[k])
    return float(np.clip(_vertex(r, c, k), 0.0, 1.0))


def best_residual(readouts: np.ndarray, costs: np.ndarray) -> float:
    """The signed readout left over (share of the frame interval) where the parabola through the
    lowest-cost (readout, cost) pair and its two neighbours is lowest, within the readouts
    tried (increasing; they include 0); the lowest readout tried when it is at either end. For
    frames unrolled already at a first estimate, which may have been too short or too long."""
    r = np.asarray(readouts, np.float64)
    c = np.asarray(costs, np.float64)
    k = int(np.argmin(c))
    if k == 0 or k == len(r) - 1:
        return float(r[k])
    return float(np.clip(_vertex(r, c, k), r[k - 1], r[k + 1]))


def _vertex(r: np.ndarray, c: np.ndarray, k: int) -> float:
    """The lowest point of the parabola through (r, c) at k - 1, k and k + 1, where c[k] is
    below its neighbours (so the parabola opens upwards)."""
    a, b, _ = np.polyfit(r[k - 1:k + 2], c[k - 1:k + 2], 2)
    return -b / (2 * a)
