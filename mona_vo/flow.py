"""Dense optical flow: one interface, back ends by name (``FLOWS``).

A :class:`Flow` maps two RGB frames to the per-pixel displacement from the first to the second.
MONA uses it twice: the mean flow magnitude ``m_t`` scales the per-frame threshold of the dynamic
points (paper, section Methods), and the motion detector compares the dense flow with the
camera-induced flow.

Default back end ``dis``: OpenCV's DIS optical flow (Kroeger et al., ECCV 2016) on grey images,
computed at a reduced resolution and upsampled (bilinear), the vectors multiplied by the
resize factors so they stay in full-resolution pixels. Measured on the real Sintel pair
alley_1 frame_0002 -> frame_0003 (clean, 1024 x 436, end-point error over the non-occluded
pixels, 2-core CPU, median of 5 runs including the resizes; the GT flow's mean magnitude is
3.0 px):

    ============  ======  ==============  =============
    DIS preset    scale   ms per pair     EPE (px)
    ============  ======  ==============  =============
    ultrafast     1.0       5.9           0.61
    ultrafast     0.5       1.3           0.97
    fast          0.5       2.4           0.83
    medium        1.0      44.5           0.29
    medium        0.5      10.7           0.47   <- default
    medium        0.25      3.2           0.78
    medium        0.125     1.4           1.48
    ============  ======  ==============  =============

The default (medium at half resolution) costs a quarter of full-resolution medium for an EPE
still under half a pixel; the 100 ms budget per 1024 x 436 frame of the whole mask pipeline
leaves room for it. ``scale=0.25`` is the choice for a faster run.

Neural back end ``raft`` (``mona_vo.neural.raft:RaftFlow``) is imported only when chosen.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import cv2
import numpy as np

from mona_vo.config import check_fields, setting
from mona_vo.errors import ConfigError
from mona_vo.registry import Registry
from mona_vo.tracking import to_gray

FLOWS = Registry("flow")

# OpenCV DIS presets by name (config values are names, checked by DISFlowConfig.validate).
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


class Flow(ABC):
    """Dense optical flow between two frames.

    Back ends are built by name from :data:`FLOWS`; classical ones take ``config=`` (their
    frozen config dataclass), neural ones ``device=``.
    """

    @abstractmethod
    def compute(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        """Flow from ``image0`` to ``image1``, both (H, W, 3) uint8 RGB of one size.

        Returns (H, W, 2) float32 displacement u, v in pixels: the pixel (x, y) of image0 is
        seen at (x + u, y + v) in image1.
        """

    def compute_resized(self, image0: np.ndarray, image1: np.ndarray, width: int,
                        height: int) -> tuple[np.ndarray, float]:
        """The flow of :meth:`compute` resampled to (height, width, 2) float32, vectors in pixels
        of that size (:func:`resize_flow`), and its ``m_t`` (:func:`mean_flow_magnitude`) in
        input pixels."""
        full = self.compute(image0, image1)
        return resize_flow(full, width, height), mean_flow_magnitude(full)


def mean_flow_magnitude(flow: np.ndarray) -> float:
    """The paper's ``m_t = (1/|Omega|) sum_x ||u_t(x)||``: mean Euclidean length, in pixels, of a
    (H, W, 2) flow field over all its pixels (non-finite vectors are left out)."""
    flow = np.asarray(flow, np.float32)
    mag = np.sqrt(flow[..., 0] ** 2 + flow[..., 1] ** 2)
    finite = np.isfinite(mag)
    if not finite.any():
        return 0.0
    return float(mag[finite].mean())


def vector_lengths(v: np.ndarray) -> np.ndarray:
    """Lengths of the 2-vectors along the last axis of ``v`` (..., 2): the values of
    ``np.linalg.norm(v, axis=-1)``, bit for bit, ten times faster (numpy reduces over a last
    axis of two slowly)."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1])


def resize_flow(flow: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width, 2) float32 flow resampled from (h, w, 2), the vectors multiplied by the
    resize factors so they stay in pixels of the new size (bilinear when upsampling, area
    averaging when downsampling)."""
    h, w = flow.shape[:2]
    if (w, h) == (width, height):
        return np.asarray(flow, np.float32)
    interp = cv2.INTER_AREA if width < w and height < h else cv2.INTER_LINEAR
    out = cv2.resize(np.asarray(flow, np.float32), (int(width), int(height)), interpolation=interp)
    out[..., 0] *= width / w
    out[..., 1] *= height / h
    return out


def _inside(x: np.ndarray, y: np.ndarray, w: int, h: int) -> np.ndarray:
    """Positions x, y (pixel centres at integers) that lie on a w x h image."""
    return (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)


def chain_flows(flows, *, max_change_px: float = np.inf, max_change_frac: float = np.inf,
                unsure=None) -> tuple[np.ndarray, np.ndarray]:
    """Flow from frame t to frame t + k composed from k consecutive (h, w, 2) float32 flows
    ``t -> t+1, ..., t+k-1 -> t+k`` (one size): ``c(x) = c_prev(x) + u_next(x + c_prev(x))``,
    each lookup bilinear.

    Returns the (h, w, 2) float32 composed flow and an (h, w) bool map of the pixels whose chain
    is trusted: it stayed inside the image at every step, and no step differs from the step
    before by more than ``max_change_px + max_change_frac * |previous step|`` pixels. A pixel
    that gets covered by another surface on the way takes that surface's flow from then on; the
    sudden change of step is how such a broken chain shows (a surface's own image velocity
    changes smoothly from frame to frame). ``unsure``: optional, per flow an (h, w) bool map (or
    None) of pixels whose vector is not to be trusted (:func:`forward_backward_mismatch`); a
    chain that starts or lands on one is not trusted.
    """
    flows = list(flows)
    if not flows:
        raise ValueError("chain_flows needs at least one flow")
    unsure = list(unsure) if unsure is not None else [None] * len(flows)
    out = np.array(flows[0], np.float32, copy=True)
    h, w = out.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))

    def inside(flow):
        return _inside(gx + flow[..., 0], gy + flow[..., 1], w, h)

    valid = inside(out)
    if unsure[0] is not None:
        valid &= ~np.asarray(unsure[0], bool)
    step_prev = out.copy()
    for f, bad in zip(flows[1:], unsure[1:]):
        step = cv2.remap(np.asarray(f, np.float32), gx + out[..., 0], gy + out[..., 1],
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        if bad is not None:
            xi = np.clip(np.rint(gx + out[..., 0]), 0, w - 1).astype(np.int64)
            yi = np.clip(np.rint(gy + out[..., 1]), 0, h - 1).astype(np.int64)
            valid &= ~np.asarray(bad, bool)[yi, xi]
        if np.isfinite(max_change_px) or np.isfinite(max_change_frac):
            change = vector_lengths(step - step_prev)
            valid &= change <= max_change_px + max_change_frac * vector_lengths(step_prev)
        out += step
        valid &= inside(out)
        step_prev = step
    return out, valid


FB_RELATIVE = 0.01   # share of the squared vector lengths a forward-backward mismatch may add
                     # (Sundaram, Brox and Keutzer, ECCV 2010: their occlusion test's 0.01)


def forward_backward_mismatch(forward: np.ndarray, backward: np.ndarray,
                              tolerance_px: float) -> np.ndarray:
    """(h, w) bool: pixels whose forward vector (``forward``, frame a -> b) and the backward
    vector (``backward``, b -> a) read where it lands do not cancel: ``|f + b|^2 > FB_RELATIVE
    (|f|^2 + |b|^2) + tolerance_px^2`` (pixels of the flows; bilinear read; a vector leaving
    the image counts as a mismatch). Occluded pixels fail (they have no partner), which is the
    test's first use, and so does flow fitted to noise where it wanders differently each way; a
    surface's own motion is found both ways. Flow that comes back as wrong as it went is not
    found: Bonn crowd's white wall, 1-2 px per frame off the camera's both ways (README, Masks,
    stop 49)."""
    f = np.asarray(forward, np.float32)
    h, w = f.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x, y = gx + f[..., 0], gy + f[..., 1]
    b = cv2.remap(np.asarray(backward, np.float32), x, y, cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE)
    err = np.sum((f + b) ** 2, axis=2)
    bound = FB_RELATIVE * (np.sum(f ** 2, axis=2) + np.sum(b ** 2, axis=2)) + tolerance_px ** 2
    return (err > bound) | ~_inside(x, y, w, h)


def forward_warp_values(values: np.ndarray, flow: np.ndarray, fill: float = 0.0) -> np.ndarray:
    """(h, w) float32 ``values`` of the previous frame moved into this frame along ``flow``
    ((h, w, 2) float32, previous -> this frame, pixels of the map): every pixel goes where its
    own vector takes it (rounded), the max kept where several land.

    Pixels nobody lands on are mostly background a mover uncovered: hidden in the previous
    frame, nothing can be carried there, so they get ``min(fill, values read at x - u(x))``
    (``fill``: no knowledge; the read keeps lower values, e.g. static evidence, where the flow
    only stretched). Reading at ``x - u(x)`` alone (the forward flow standing in for its
    inverse) reads the mover itself where the background moves behind it (a camera panning
    with a runner): the uncovered pixels' vectors point back onto it, and its evidence would
    trail behind it by the relative motion every frame. ``fill`` everywhere without a flow.
    """
    V = np.asarray(values, np.float32)
    if flow is None or flow.shape[:2] != V.shape:
        return np.full_like(V, fill)
    h, w = V.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x = np.rint(gx + flow[..., 0]).astype(np.int64).ravel()
    y = np.rint(gy + flow[..., 1]).astype(np.int64).ravel()
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    flat = np.full(h * w, -np.inf, np.float32)
    np.maximum.at(flat, y[ok] * w + x[ok], V.ravel()[ok])
    splat = flat.reshape(h, w)
    hole = ~np.isfinite(splat)
    if not hole.any():
        return splat
    back = cv2.remap(V, gx - flow[..., 0], gy - flow[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float(fill))
    filled = np.minimum(back, np.float32(fill))
    return np.where(hole, filled, splat).astype(np.float32)


def flow_edges(flow: np.ndarray, radius: int, min_change_px: float) -> np.ndarray:
    """(h, w) bool: pixels within ``radius`` of a flow discontinuity, where either component
    of the (h, w, 2) ``flow`` varies by more than ``min_change_px`` over the (2 radius + 1)^2
    window. There the flow mixes two motions (a mover's and its background's: a dense flow
    smooths across the boundary), so it cannot say where such a pixel went."""
    k = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    out = np.zeros(flow.shape[:2], bool)
    for c in range(2):
        f = np.ascontiguousarray(flow[..., c], np.float32)
        out |= (cv2.dilate(f, k) - cv2.erode(f, k)) > min_change_px
    return out


def forward_warp_mask(mask: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """(h, w) bool: the True pixels of an (h, w) bool ``mask`` moved along their own vectors of
    the (h, w, 2) float32 ``flow`` (same size, pixels; rounded to the nearest pixel), the pixels
    leaving the image dropped, and the one-pixel holes that splatting leaves where the flow
    stretches closed (3 x 3 closing)."""
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    out = np.zeros((h, w), np.uint8)
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return out > 0
    u = np.asarray(flow, np.float32)[ys, xs]
    x = np.rint(xs + u[:, 0]).astype(np.int64)
    y = np.rint(ys + u[:, 1]).astype(np.int64)
    ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    out[y[ok], x[ok]] = 1
    return cv2.morphologyEx(out, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0


@dataclass(frozen=True)
class DISFlowConfig:
    """Settings of the ``dis`` flow back end."""

    preset: str = setting("medium", choices=tuple(DIS_PRESETS))  # OpenCV DIS preset: ultrafast | fast | medium (see the table above)
    scale: float = setting(0.5, gt=0, le=1)  # flow computed at this fraction of the input size, in (0, 1]
    min_width: int = setting(64, ge=8)  # the reduced image is never narrower than this, pixels

    def validate(self) -> None:
        check_fields(self, 'masks.dis.')


@FLOWS.register("dis")
class DISFlow(Flow):
    """OpenCV DIS optical flow at a reduced resolution, upsampled to the input size."""

    def __init__(self, config: DISFlowConfig | None = None):
        self.config = config or DISFlowConfig()
        self.config.validate()
        self._dis = cv2.DISOpticalFlow_create(DIS_PRESETS[self.config.preset])

    def working_size(self, width: int, height: int) -> tuple[int, int]:
        """(w, h) in pixels at which the flow of a width x height input is computed."""
        s = max(self.config.scale, min(1.0, self.config.min_width / width))
        return max(int(round(width * s)), 1), max(int(round(height * s)), 1)

    def compute_reduced(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        """Flow at the working size (see :meth:`working_size`), (h, w, 2) float32, vectors in
        pixels of the *working* size (multiply by the resize factors for input pixels)."""
        g0, g1 = to_gray(image0), to_gray(image1)
        if g0.shape != g1.shape:
            raise ValueError(f"flow needs two images of one size, got {g0.shape} and {g1.shape}")
        height, width = g0.shape
        w, h = self.working_size(width, height)
        if (w, h) != (width, height):
            g0 = cv2.resize(g0, (w, h), interpolation=cv2.INTER_AREA)
            g1 = cv2.resize(g1, (w, h), interpolation=cv2.INTER_AREA)
        return self._dis.calc(g0, g1, None)

    def compute(self, image0: np.ndarray, image1: np.ndarray) -> np.ndarray:
        height, width = image0.shape[:2]
        return resize_flow(self.compute_reduced(image0, image1), width, height)

    def compute_resized(self, image0: np.ndarray, image1: np.ndarray, width: int,
                        height: int) -> tuple[np.ndarray, float]:
        # From the working-size flow, never upsampled: at 1024 x 436 the upsampling and m_t
        # over the upsampled field cost 4 ms, a third of the DIS itself.
        small = self.compute_reduced(image0, image1)
        H, W = image0.shape[:2]
        h, w = small.shape[:2]
        m_t = mean_flow_magnitude(small * np.float32([W / w, H / h]))
        return resize_flow(small, width, height), m_t


FLOWS.register("raft", "mona_vo.neural.raft:RaftFlow")
