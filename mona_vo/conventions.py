"""The conventions of mona-vo, stated once. Every reader, writer and algorithm goes through here.

Poses
    ``T_world_cam``: 4x4 float64 camera-to-world matrix. A point in camera coordinates maps to the
    world by ``X_world = T[:3, :3] @ X_cam + T[:3, 3]``; ``T[:3, 3]`` is the camera centre in the
    world. World-to-camera matrices (Sintel ``.cam`` files, OpenCV ``rvec/tvec``) are named
    ``T_cam_world`` and converted with :func:`invert_pose` at the file boundary.

Camera frame
    OpenCV's: x right, y down, z forward (optical axis). Depth means z in this frame.

Quaternions
    ``quat_wxyz`` (scalar first) inside mona-vo, unit norm, sign chosen so that w >= 0.
    TUM files store ``qx qy qz qw`` (scalar last); only :func:`tum_row` and
    :func:`pose_from_tum_row` touch that order.

Intrinsics
    Pinhole ``fx, fy, cx, cy`` in pixels (:class:`Intrinsics`), one per frame allowed.

Working resolutions
    A stage that works on a reduced image is given its size as the reduced image's longer side
    (:func:`working_size`), so a portrait frame is reduced as the same frame turned landscape
    would be, not by its narrow width.

Pixels
    Pixel centres sit at integer coordinates: the centre of the top-left pixel is (0, 0), so an image
    of width w spans x in [-0.5, w - 0.5]. Pixel coordinates are ``(x, y)`` = (column, row) float
    arrays of shape (N, 2); images are indexed ``image[row, col]``. This is OpenCV's convention, so
    ``cv2.remap``, ``calcOpticalFlowPyrLK`` and ``solvePnP`` take these coordinates unchanged.
    Between an image and one ``s`` times its size, pixel edges map onto each other:
    ``x' + 0.5 = (x + 0.5) * s`` (:func:`scale_pixels`, :func:`scale_boxes`,
    :meth:`Intrinsics.scaled`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# scipy.spatial is imported by the two functions that use it: it costs 0.4 s, more than the rest of
# what the readers and writers import, and a command failing on a bad input should not pay it.


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 float64 pose from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (``T_a_b`` -> ``T_b_a``), exact for rotations."""
    R = T[:3, :3]
    t = T[:3, 3]
    Ti = np.eye(4)
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ t
    return Ti


def relative_pose(T_world_a: np.ndarray, T_world_b: np.ndarray) -> np.ndarray:
    """``T_a_b``: pose of camera b in camera a's frame."""
    return invert_pose(T_world_a) @ T_world_b


def is_rigid(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True when T is a finite 4x4 rigid transform (orthonormal, det +1, last row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1.0) < tol
            and np.allclose(T[3], [0, 0, 0, 1], atol=tol))


def quat_wxyz_from_rotation(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (4,) float64 w, x, y, z with w >= 0 from a 3x3 rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def rotation_from_quat_wxyz(q_wxyz: np.ndarray) -> np.ndarray:
    """3x3 rotation from a quaternion w, x, y, z (normalised first; any non-zero norm is accepted)."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64)
    return Rotation.from_quat([x, y, z, w]).as_matrix()


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees, in [0, 180]."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def tum_row(timestamp: float, T_world_cam: np.ndarray) -> tuple[float, ...]:
    """One TUM trajectory line as numbers: ``timestamp tx ty tz qx qy qz qw`` (scalar last)."""
    w, x, y, z = quat_wxyz_from_rotation(T_world_cam[:3, :3])
    tx, ty, tz = T_world_cam[:3, 3]
    return (float(timestamp), tx, ty, tz, x, y, z, w)


def pose_from_tum_row(row) -> tuple[float, np.ndarray]:
    """Inverse of :func:`tum_row`: (timestamp, T_world_cam) from 8 numbers."""
    row = np.asarray(row, dtype=np.float64)
    t, tx, ty, tz, qx, qy, qz, qw = row
    return float(t), make_pose(rotation_from_quat_wxyz([qw, qx, qy, qz]), [tx, ty, tz])


# Field of view guessed for uncalibrated video, degrees (typical of phone and action cameras),
# across the frame's longer side: a phone's portrait clip is its landscape camera turned, so its
# narrow side sees less. Runs take it from PipelineConfig's `assumed_hfov_deg`; this is the library
# fallback.
DEFAULT_HFOV_DEG = 60.0


def fov_span(width: int, height: int) -> int:
    """The side of a width x height frame that an uncalibrated camera's fields of view (the guess,
    the estimate's candidates) are measured across: the longer one."""
    return max(int(width), int(height))


def focal_for_fov(span: float, fov_deg: float) -> float:
    """Focal length (px) at which ``span`` pixels (:func:`fov_span`) see ``fov_deg`` degrees."""
    return 0.5 * span / float(np.tan(np.radians(fov_deg) / 2.0))


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; principal point in the integer-centre pixel convention."""

    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:
        """3x3 float64 calibration matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_K(cls, K: np.ndarray) -> "Intrinsics":
        K = np.asarray(K, dtype=np.float64)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    @classmethod
    def default_for(cls, width: int, height: int, fov_deg: float = DEFAULT_HFOV_DEG) -> "Intrinsics":
        """A focal guess for uncalibrated video: field of view ``fov_deg`` across the longer side
        (typical of phone and action cameras; :func:`focal_for_fov`), principal point at the image
        centre."""
        f = focal_for_fov(fov_span(width, height), fov_deg)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    def scaled(self, sx: float, sy: float | None = None) -> "Intrinsics":
        """Intrinsics of the image resized by (sx, sy), keeping pixel centres at integers."""
        sy = sx if sy is None else sy
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                          (self.cy + 0.5) * sy - 0.5)

    def check(self, width: int | None = None, height: int | None = None) -> list[str]:
        """Problems with these intrinsics (empty when they are usable)."""
        problems = []
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            problems.append("intrinsics are not finite numbers")
            return problems
        if self.fx <= 0 or self.fy <= 0:
            problems.append(f"focal length must be positive (fx={self.fx:g}, fy={self.fy:g})")
        if width is not None and not -0.5 <= self.cx <= width - 0.5:
            problems.append(f"principal point cx={self.cx:g} is outside the image width {width}")
        if height is not None and not -0.5 <= self.cy <= height - 0.5:
            problems.append(f"principal point cy={self.cy:g} is outside the image height {height}")
        return problems


def project(points_cam: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Pixels (N, 2) float64 x, y of camera-frame points (N, 3); z must be positive."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    return np.stack([intr.fx * p[:, 0] / z + intr.cx, intr.fy * p[:, 1] / z + intr.cy], axis=1)


def unproject(pixels: np.ndarray, depth: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame points (N, 3) of pixels (N, 2) x, y at z-depths (N,)."""
    px = np.asarray(pixels, dtype=np.float64)
    d = np.asarray(depth, dtype=np.float64)
    x = (px[:, 0] - intr.cx) / intr.fx * d
    y = (px[:, 1] - intr.cy) / intr.fy * d
    return np.stack([x, y, d], axis=1)


def reproject(T_world_cam: np.ndarray, points_world: np.ndarray, intr: Intrinsics,
              fx: float | None = None, fy: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) and camera-frame depths (N,) of world points (N, 3) seen from T_world_cam.
    Points at or behind the camera get non-finite or meaningless pixels; check ``depth > 0``.
    ``fx``/``fy`` override the intrinsics' focal lengths (shared-focal refinement)."""
    T_cam_world = invert_pose(T_world_cam)
    Xc = np.asarray(points_world, np.float64) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (intr.fx if fx is None else fx) * Xc[:, 0] / Xc[:, 2] + intr.cx
        v = (intr.fy if fy is None else fy) * Xc[:, 1] / Xc[:, 2] + intr.cy
    return np.stack([u, v], axis=1), Xc[:, 2]


def camera_depths(T_world_cam: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(M,) depth (camera-frame z) of each world point (M, 3) in its own camera (M, 4, 4
    camera-to-world poses): the third row of ``R^T (p - t)``, without inverting every pose."""
    T = np.asarray(T_world_cam, np.float64)
    P = np.asarray(points_world, np.float64)
    return np.einsum("mj,mj->m", T[:, :3, 2], P - T[:, :3, 3])


def pixels_in_mask(mask: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N,) bool: the nearest pixel centre of each (x, y) is True in the (H, W) bool mask;
    pixels outside the image take the nearest border pixel."""
    h, w = mask.shape
    x = np.clip(np.rint(pixels[:, 0]).astype(int), 0, w - 1)
    y = np.clip(np.rint(pixels[:, 1]).astype(int), 0, h - 1)
    return mask[y, x]


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return np.asarray(points) @ T[:3, :3].T + T[:3, 3]


def pixel_grid(width: int, height: int) -> np.ndarray:
    """(height, width, 2) float64 pixel-centre coordinates x, y."""
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([xs, ys], axis=-1)


def scale_pixels(xy: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """(..., 2) pixels x, y of an image -> pixels of one ``sx`` (``sy``) times its width (height):
    ``x' + 0.5 = (x + 0.5) * sx``. A float array keeps its dtype; any other becomes float64."""
    p = np.asarray(xy)
    if not np.issubdtype(p.dtype, np.floating):
        p = p.astype(np.float64)
    out = np.empty_like(p)
    out[..., 0] = (p[..., 0] + 0.5) * sx - 0.5
    out[..., 1] = (p[..., 1] + 0.5) * sy - 0.5
    return out


def scale_boxes(xyxy: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """(K, 4) boxes x0, y0, x1, y1 rescaled as :func:`scale_pixels` rescales their corners."""
    p = np.asarray(xyxy)
    return scale_pixels(p.reshape(-1, 2, 2), sx, sy).reshape(p.shape)


def working_size(width: int, height: int, long_side: int) -> tuple[int, int]:
    """(w, h) of a width x height image reduced so that its longer side is at most
    ``long_side`` (never enlarged), aspect kept, each side at least 1."""
    scale = min(1.0, long_side / max(width, height))
    if scale == 1.0:
        return int(width), int(height)
    return max(int(round(width * scale)), 1), max(int(round(height * scale)), 1)
